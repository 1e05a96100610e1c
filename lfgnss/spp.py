"""Coarse single-point positioning: equal-weight iterative least squares with inter-system biases.

All epochs are solved at once: each Gauss-Newton iteration forms the (T, S, n) design matrices and
solves the T normal equations in one batched call. State per epoch: x, y, z [m], receiver clock of
``systems[0]`` [m], one ISB per further constellation [m] (RTKLIB ``estpos``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import qc
from .constants import GPS_L1_HZ, SPEED_OF_LIGHT_M_S
from .corrections import geometric_range_m, klobuchar_m, saastamoinen_m
from .frames import ecef_to_lla
from .measurements import Measurements
from .time import SECONDS_PER_WEEK

FIX_OK = 0
FIX_TOO_FEW_SATELLITES = 1
FIX_NOT_CONVERGED = 2
FIX_GROSS_RESIDUALS = 3
FIX_BAD_GEOMETRY = 4
FIX_IMPLAUSIBLE = 5
FIX_STATUS = {FIX_OK: "ok", FIX_TOO_FEW_SATELLITES: "too few satellites", FIX_NOT_CONVERGED: "not converged",
              FIX_GROSS_RESIDUALS: "gross residuals", FIX_BAD_GEOMETRY: "bad geometry",
              FIX_IMPLAUSIBLE: "implausible height"}


@dataclass(frozen=True)
class SppConfig:
    """Settings of the coarse least-squares fix."""

    elevation_mask_deg: float = 10.0
    max_iterations: int = 20
    tolerance_m: float = 1e-4
    gross_residual_m: float = 1000.0
    max_exclusions: int = 3        # worst-residual satellites dropped per epoch before giving up
    max_gdop: float = 50.0
    height_range_m: tuple[float, float] = (-1000.0, 100_000.0)  # a fix without redundancy can land anywhere


@dataclass(frozen=True)
class CoarseFix:
    """Per-epoch least-squares fixes and per-satellite geometry, (T epochs, S satellites)."""

    systems: tuple[str, ...]
    time_gps_s: np.ndarray       # (T,)
    pos_ecef_m: np.ndarray       # (T, 3) NaN where status != FIX_OK
    clock_m: np.ndarray          # (T, C) clock of systems[0] then ISBs [m], NaN where no fix
    status: np.ndarray           # (T,) FIX_* code
    used: np.ndarray             # (T, S) bool, in the final solution
    reason: np.ndarray           # (T, S) qc code, including elevation mask and gross residuals
    pr_corrected_m: np.ndarray   # (T, S) pr + c(dts - tgd) - tropo - iono at the solution [m]
    residual_m: np.ndarray       # (T, S) pr_corrected - (range + clock) [m]
    el_rad: np.ndarray           # (T, S)
    az_rad: np.ndarray           # (T, S)
    tropo_m: np.ndarray          # (T, S)
    iono_m: np.ndarray           # (T, S)
    iterations: np.ndarray       # (T,)

    @property
    def ok(self) -> np.ndarray:
        """(T,) bool, epochs with a fix."""
        return self.status == FIX_OK

    @property
    def n_used(self) -> np.ndarray:
        """(T,) satellites in each fix."""
        return self.used.sum(axis=1)

    def summary(self) -> dict:
        """Counts of epoch statuses and observation qc reasons, for people."""
        values, counts = np.unique(self.status, return_counts=True)
        return {"epochs": int(self.status.size),
                "epoch_status": {FIX_STATUS[int(v)]: int(c) for v, c in zip(values, counts)},
                "observations": qc.count_reasons(self.reason)}


def _enu_basis(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """(T, 3, 3) rows east, north, up in ECEF."""
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    z = np.zeros_like(lat)
    return np.stack([np.stack([-so, co, z], -1), np.stack([-sl * co, -sl * so, cl], -1),
                     np.stack([cl * co, cl * so, sl], -1)], axis=-2)


def _geometry(meas: Measurements, pos: np.ndarray):
    """Ranges, unit vectors, azimuth/elevation and atmosphere for receiver positions (T, 3)."""
    sat = meas.sat_pos_ecef_m
    rng = geometric_range_m(sat, pos[:, None, :])
    d = sat - pos[:, None, :]
    los = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1.0)
    lla = ecef_to_lla(pos)
    enu = np.einsum("tij,tsj->tsi", _enu_basis(lla[:, 0], lla[:, 1]), los)
    az = np.mod(np.arctan2(enu[..., 0], enu[..., 1]), 2 * np.pi)
    el = np.arcsin(np.clip(enu[..., 2], -1.0, 1.0))
    near_surface = (lla[:, 2] > -1e3)[:, None]
    tropo = np.where(near_surface, saastamoinen_m(lla[:, :1], lla[:, 2:3], el), 0.0)
    tow = np.mod(meas.time_gps_s, SECONDS_PER_WEEK)[:, None]
    ion_l1 = klobuchar_m(tow, lla[:, :1], lla[:, 1:2], az, el, meas.nav.iono.get("GPS"))
    iono = np.where(near_surface, ion_l1 * (GPS_L1_HZ / meas.carrier_hz[None, :]) ** 2, 0.0)
    return rng, los, az, el, tropo, iono


def _solve(meas: Measurements, active: np.ndarray, x0: np.ndarray, config: SppConfig):
    """Batched Gauss-Newton over epochs; returns state, convergence, final geometry and usage."""
    n_t, n_s = active.shape
    n_sys = len(meas.systems)
    n = 3 + n_sys
    x = x0.copy()
    sysi = np.broadcast_to(meas.system_index, (n_t, n_s))
    onehot = np.zeros((n_t, n_s, n_sys))
    valid_sys = sysi >= 0
    onehot[np.nonzero(valid_sys) + (sysi[valid_sys],)] = 1.0
    onehot[..., 0] = np.where(valid_sys, 1.0, 0.0)   # receiver clock on every satellite, ISB on the others
    pr_sat = np.nan_to_num(meas.satclock_corrected_pr_m())
    mask_rad = np.radians(config.elevation_mask_deg)
    converged = np.zeros(n_t, bool)
    iterations = np.zeros(n_t, int)
    usable = active.copy()
    for it in range(config.max_iterations):
        rng, los, az, el, tropo, iono = _geometry(meas, x[:, :3])
        have_pos = np.linalg.norm(x[:, :3], axis=1) > 1e6
        usable = active & ~(have_pos[:, None] & (el < mask_rad))
        pred = rng + np.einsum("tsk,tk->ts", onehot, x[:, 3:])
        res = np.where(usable, pr_sat - tropo - iono - pred, 0.0)
        h = np.concatenate([-los, onehot], axis=-1) * usable[..., None]
        normal = np.einsum("tsi,tsj->tij", h, h)
        observed = np.diagonal(normal, axis1=1, axis2=2) > 0
        normal = normal + np.eye(n)[None] * (~observed)[:, :, None]  # unobserved ISBs stay fixed
        enough = usable.sum(1) >= observed[:, 3:].sum(1) + 3
        todo = enough & ~converged
        if not np.any(todo):
            break
        try:
            dx = np.linalg.solve(normal[todo], np.einsum("tsi,ts->ti", h[todo], res[todo])[..., None])[..., 0]
        except np.linalg.LinAlgError:
            dx = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in
                           zip(normal[todo], np.einsum("tsi,ts->ti", h[todo], res[todo]))])
        x[todo] += dx
        iterations[todo] = it + 1
        converged[todo] = np.linalg.norm(dx, axis=1) < config.tolerance_m
    rng, los, az, el, tropo, iono = _geometry(meas, x[:, :3])
    have_pos = np.linalg.norm(x[:, :3], axis=1) > 1e6
    usable = active & ~(have_pos[:, None] & (el < mask_rad))
    pr_corr = pr_sat - tropo - iono
    res = pr_corr - rng - np.einsum("tsk,tk->ts", onehot, x[:, 3:])
    observed = np.einsum("tsk,ts->tk", onehot, usable.astype(float)) > 0
    enough = usable.sum(1) >= observed[:, 1:].sum(1) + 4
    return x, converged & enough, enough, usable, pr_corr, res, az, el, tropo, iono, iterations, observed


def spp(meas: Measurements, config: SppConfig = SppConfig()) -> CoarseFix:
    """Equal-weight least-squares fix of every epoch, with per-epoch status and per-satellite reasons."""
    n_t, n_s = meas.reason.shape
    n_sys = len(meas.systems)
    active = meas.reason == qc.OK
    x0 = np.zeros((n_t, 3 + n_sys))
    if np.linalg.norm(meas.obs.approx_ecef_m) > 6e6:
        x0[:, :3] = meas.obs.approx_ecef_m
    excluded = np.zeros((n_t, n_s), bool)
    for _ in range(config.max_exclusions + 1):
        x, converged, enough, usable, pr_corr, res, az, el, tropo, iono, iters, observed = \
            _solve(meas, active & ~excluded, x0, config)
        gross = usable & (np.abs(res) > config.gross_residual_m) & converged[:, None]
        bad_epochs = np.any(gross, axis=1) | (~converged & enough)
        if not np.any(bad_epochs):
            break
        worst = np.argmax(np.where(usable, np.abs(res), -1.0), axis=1)
        drop = bad_epochs & np.any(gross, axis=1)
        excluded[np.flatnonzero(drop), worst[drop]] = True
        x0 = np.where(converged[:, None], x, x0)
        if not np.any(drop):
            break
    status = np.full(n_t, FIX_OK, dtype=np.int8)
    status[~converged] = FIX_NOT_CONVERGED
    status[~enough] = FIX_TOO_FEW_SATELLITES
    status[converged & np.any(usable & (np.abs(res) > config.gross_residual_m), axis=1)] = FIX_GROSS_RESIDUALS
    height = ecef_to_lla(x[:, :3])[:, 2]
    low, high = config.height_range_m
    status[(status == FIX_OK) & ~((height >= low) & (height <= high))] = FIX_IMPLAUSIBLE
    ok = status == FIX_OK
    if np.any(ok):
        from .dop import dop

        sysi = np.broadcast_to(meas.system_index, (n_t, n_s))
        gdop = dop(el, az, np.where(usable, sysi, -1), usable, n_sys).gdop
        status[ok & ~((gdop > 0) & (gdop <= config.max_gdop))] = FIX_BAD_GEOMETRY
        ok = status == FIX_OK
    reason = meas.reason.copy()
    reason[(reason == qc.OK) & excluded] = qc.GROSS_RESIDUAL
    reason[(reason == qc.OK) & ~usable] = qc.LOW_ELEVATION
    clock = np.where(observed, x[:, 3:], np.nan)
    return CoarseFix(meas.systems, meas.time_gps_s, np.where(ok[:, None], x[:, :3], np.nan),
                     np.where(ok[:, None], clock, np.nan), status, usable & ok[:, None], reason,
                     np.where(np.isfinite(meas.pr_m), pr_corr, np.nan), np.where(usable, res, np.nan),
                     el, az, tropo, iono, iters)
