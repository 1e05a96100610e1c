"""Synthetic urban sequences with known truth, for tests and examples (no RINEX needed)."""
from __future__ import annotations

import numpy as np

from .constants import SPEED_OF_LIGHT_M_S
from .corrections import geometric_range_m
from .frames import enu_rotation, enu_to_ecef, lla_to_ecef
from .sequence import DEFAULT_FEATURES, Sequence

_ORBIT_RADIUS_M = 2.0e7


def simulate_sequence(n_epochs: int = 120, *, dt_s: float = 1.0, systems: tuple[str, ...] = ("G", "C"),
                      sats_per_system: int = 7, nlos_fraction: float = 0.2, seed: int = 0,
                      lat_deg: float = 22.30, lon_deg: float = 114.18, n_slots: int | None = None,
                      name: str = "synthetic", stops_s: tuple[tuple[float, ...], ...] = ()) -> Sequence:
    """A drive at ~8 m/s through an urban canyon: C/N0-dependent noise plus positive NLOS biases [m].

    ``stops_s``: (start, end) times [s after the first epoch] during which the car stands still, or (start, end,
    speed) during which it creeps at ``speed`` [m/s].
    """
    rng = np.random.default_rng(seed)
    ref = lla_to_ecef(np.radians(lat_deg), np.radians(lon_deg), 10.0)
    rot = enu_rotation(np.radians(lat_deg), np.radians(lon_deg))
    t = np.arange(n_epochs) * dt_s
    heading = 0.3 + 0.004 * t + 0.3 * np.sin(t / 40.0)
    speed = 8.0 + 2.0 * np.sin(t / 25.0)
    if any(len(stop) not in (2, 3) for stop in stops_s):
        raise ValueError(f"lfgnss/simulate.py: stops_s takes (start, end) or (start, end, speed), got {stops_s!r}")
    for start, end, *creep in stops_s:
        speed = np.where((t >= start) & (t <= end), creep[0] if creep else 0.0, speed)
    vel_enu = np.stack([speed * np.sin(heading), speed * np.cos(heading), np.zeros_like(t)], axis=-1)
    pos_enu = np.cumsum(vel_enu * dt_s, axis=0) - vel_enu[0] * dt_s
    truth = enu_to_ecef(pos_enu, ref)

    n_sat = sats_per_system * len(systems)
    sys_idx = np.repeat(np.arange(len(systems)), sats_per_system)
    sv = np.array([f"{systems[s]}{k + 1:02d}" for s, k in zip(sys_idx, np.tile(np.arange(sats_per_system), len(systems)))])
    az0 = rng.uniform(0, 2 * np.pi, n_sat)
    el0 = np.arcsin(rng.uniform(np.sin(np.radians(12)), 1.0, n_sat))
    az = az0[None, :] + 1e-4 * t[:, None]
    el = np.clip(el0[None, :] + 5e-5 * t[:, None] * rng.choice([-1, 1], n_sat), np.radians(8), np.radians(89))
    los_enu = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=-1)
    sat = ref + _ORBIT_RADIUS_M * los_enu @ rot

    cn0 = np.clip(28 + 20 * np.sin(el) + rng.normal(0, 3, (n_epochs, n_sat)), 15, 52)
    nlos = rng.random(n_sat) < nlos_fraction
    nlos_t = nlos[None, :] & (np.sin(t[:, None] / 15.0 + rng.uniform(0, 6, n_sat)) > -0.2)
    cn0 = np.where(nlos_t, cn0 - 8.0, cn0)
    sigma = 0.5 + 120.0 * 10 ** (-cn0 / 20.0)
    bias = np.where(nlos_t, rng.uniform(10, 60, n_sat)[None, :] * (1 + 0.3 * np.sin(t[:, None] / 9.0)), 0.0)
    clock = 3.0e4 + 50.0 * t + np.cumsum(rng.normal(0, 0.3, n_epochs))
    isb = np.concatenate([[0.0], rng.uniform(-50, 50, len(systems) - 1)])
    error = rng.normal(size=(n_epochs, n_sat)) * sigma + bias
    pr = geometric_range_m(sat, truth[:, None, :]) + clock[:, None] + isb[sys_idx][None, :] + error

    # Doppler: pseudorange rate = e . (v_sat - v) + clock drift + noise (heavier tails on NLOS)
    sat_vel = np.gradient(sat, t, axis=0) if n_epochs > 1 else np.zeros_like(sat)
    los = sat - truth[:, None, :]
    los /= np.linalg.norm(los, axis=-1, keepdims=True)
    vel = vel_enu @ rot
    drift = np.gradient(clock, t) if n_epochs > 1 else np.full(n_epochs, 50.0)
    rng_doppler = np.random.default_rng([seed, 1])     # its own stream: the other draws stay as they were
    prr_noise = rng_doppler.normal(size=(n_epochs, n_sat)) * np.where(nlos_t, 1.5, 0.1 + 2.0 * 10 ** (-cn0 / 20.0))
    prr = np.einsum("tni,tni->tn", los, sat_vel - vel[:, None, :]) + drift[:, None] + prr_noise

    mask = np.ones((n_epochs, n_sat), bool)
    mask[rng.random((n_epochs, n_sat)) < 0.05] = False
    n_slots = max(n_slots or n_sat, n_sat)
    coarse = truth + rng.normal(0, 8.0, (n_epochs, 3))
    coarse_clock = np.concatenate([clock[:, None], np.repeat(isb[None, 1:], n_epochs, 0)], axis=1)
    feats = np.zeros((n_epochs, n_sat, len(DEFAULT_FEATURES)))
    feats[..., 0], feats[..., 1], feats[..., 2], feats[..., 3] = cn0, el, np.mod(az, 2 * np.pi), error
    seq = Sequence(
        name=name, systems=tuple(systems), time_gps_s=1.2e9 + t, sv=np.broadcast_to(sv, (n_epochs, n_sat)).copy(),
        system_index=np.broadcast_to(sys_idx, (n_epochs, n_sat)).copy(), mask=mask,
        pr_m=np.where(mask, pr, 0.0), sat_pos_ecef_m=sat, cn0_dbhz=cn0, el_rad=el, az_rad=np.mod(az, 2 * np.pi),
        features=np.where(mask[..., None], feats, 0.0), feature_names=DEFAULT_FEATURES,
        coarse_ecef_m=coarse, coarse_clock_m=coarse_clock, truth_ecef_m=truth, prr_m_s=np.where(mask, prr, 0.0),
        prr_mask=mask.copy(), sat_vel_ecef_m_s=sat_vel)
    return seq.pad_to(n_slots)


__all__ = ["simulate_sequence", "SPEED_OF_LIGHT_M_S"]
