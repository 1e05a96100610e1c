"""Coarse single-point positioning: equal-weight iterative least squares with inter-system biases.

All epochs are solved at once: each Gauss-Newton iteration forms the (T, S, n) design matrices and
solves the T normal equations in one batched call. State per epoch: x, y, z [m], receiver clock of
``systems[0]`` [m], one ISB per further constellation [m] (RTKLIB ``estpos``). In an epoch without
``systems[0]`` the first system present owns the clock (its ISB held at 0); see :func:`spp`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import qc
from .constants import GPS_L1_HZ
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
    clock_m: np.ndarray          # (T, C) clock of systems[0] then ISBs [m], NaN where no fix (rules: spp)
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


def _geometry(meas: Measurements, pos: np.ndarray, rows: np.ndarray | None = None):
    """Ranges [m], unit vectors, azimuth/elevation [rad] and atmosphere [m] for receiver positions (T, 3).

    ``rows`` (R,) picks the epochs ``pos`` (R, 3) belongs to; all epochs when None.
    """
    sat = meas.sat_pos_ecef_m if rows is None else meas.sat_pos_ecef_m[rows]
    time_gps_s = meas.time_gps_s if rows is None else meas.time_gps_s[rows]
    rng = geometric_range_m(sat, pos[:, None, :])
    d = sat - pos[:, None, :]
    los = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1.0)
    lla = ecef_to_lla(pos)
    enu = np.einsum("tij,tsj->tsi", _enu_basis(lla[:, 0], lla[:, 1]), los)
    az = np.mod(np.arctan2(enu[..., 0], enu[..., 1]), 2 * np.pi)
    el = np.arcsin(np.clip(enu[..., 2], -1.0, 1.0))
    near_surface = (lla[:, 2] > -1e3)[:, None]
    tropo = np.where(near_surface, saastamoinen_m(lla[:, :1], lla[:, 2:3], el), 0.0)
    tow = np.mod(time_gps_s, SECONDS_PER_WEEK)[:, None]
    # every constellation takes GPS's Klobuchar scaled to its frequency, as RTKLIB's SPP does; BeiDou's own broadcast
    # model (nav.iono["BDS"]) gives 1.4-1.5 m more on the hk data, mostly common to BeiDou (its ISB takes that)
    ion_l1 = klobuchar_m(tow, lla[:, :1], lla[:, 1:2], az, el, meas.nav.iono.get("GPS"))
    iono = np.where(near_surface, ion_l1 * (GPS_L1_HZ / meas.carrier_hz[None, :]) ** 2, 0.0)
    return rng, los, az, el, tropo, iono


def _clock_columns(sys_onehot: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clock/ISB design columns (T, S, C) [m/m], each epoch's clock system (T,) and systems present (T, C).

    Column 0, the receiver clock [m], is 1 for every satellite; column k > 0, the ISB of ``systems[k]`` [m],
    is 1 for that system's satellites. The clock belongs to the epoch's first system present among the used
    satellites: ``systems[0]`` when it has one, else the lowest-index system present, whose ISB column is
    then empty (held at 0), as in :mod:`lfgnss.dop`.
    """
    present = np.einsum("tsk,ts->tk", sys_onehot, usable.astype(float)) > 0
    clock_system = np.argmax(present, axis=1)               # 0 when nothing is present
    cols = sys_onehot * (np.arange(sys_onehot.shape[-1]) != clock_system[:, None])[:, None, :]
    cols[..., 0] = sys_onehot.sum(-1)                        # every satellite of a known system
    return cols, clock_system, present


def _rebase_clock(x: np.ndarray, clock_system: np.ndarray) -> np.ndarray:
    """State (T, 3 + C) with the clock moved to each epoch's clock system (its ISB 0); predictions unchanged [m]."""
    shift = np.where(clock_system > 0, np.take_along_axis(x[:, 3:], clock_system[:, None], axis=1)[:, 0], 0.0)
    if not np.any(shift):
        return x
    x = x.copy()
    x[:, 3] += shift
    x[:, 4:] -= shift[:, None]
    return x


def _linearise(meas: Measurements, rows: np.ndarray, x: np.ndarray, active: np.ndarray, sys_onehot: np.ndarray,
               mask_rad: float) -> tuple[np.ndarray, ...]:
    """Geometry, usable satellites and clock columns at states x (R, 3 + C) of epochs ``rows`` (R,).

    The elevation mask applies only where x holds a position (|x| > 1000 km): from the Earth's centre
    every satellite is used, as in RTKLIB. Returns x with its clock rebased (:func:`_clock_columns`),
    the clock term of each satellite's prediction [m] and whether the epoch has as many satellites as
    unknowns (position, the clock, one ISB per further system present).
    """
    rng, los, az, el, tropo, iono = _geometry(meas, x[:, :3], rows)
    have_pos = np.linalg.norm(x[:, :3], axis=1) > 1e6
    usable = active & ~(have_pos[:, None] & (el < mask_rad))
    cols, clock_system, present = _clock_columns(sys_onehot, usable)
    x = _rebase_clock(x, clock_system)
    clock = np.einsum("tsk,tk->ts", cols, x[:, 3:])
    enough = usable.sum(1) >= 3 + present.sum(1)
    return x, usable, cols, present, enough, rng, clock, los, az, el, tropo, iono


def _iterate(meas: Measurements, rows: np.ndarray, x0: np.ndarray, active: np.ndarray, pr_sat: np.ndarray,
             sys_onehot: np.ndarray, config: SppConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched Gauss-Newton from x0 (R, 3 + C) [m] for epochs ``rows``; returns state, convergence, iterations."""
    n = x0.shape[1]
    x = x0.copy()
    converged = np.zeros(rows.size, bool)
    iterations = np.zeros(rows.size, int)
    mask_rad = np.radians(config.elevation_mask_deg)
    live = np.arange(rows.size)          # epochs still iterating: unconverged and, so far, with enough satellites
    for it in range(config.max_iterations):
        xl, usable, cols, _, enough, rng, clock, los, _, _, tropo, iono = _linearise(
            meas, rows[live], x[live], active[live], sys_onehot[live], mask_rad)
        x[live] = xl
        res = np.where(usable, pr_sat[live] - tropo - iono - (rng + clock), 0.0)
        h = np.concatenate([-los, cols], axis=-1) * usable[..., None]
        normal = np.einsum("tsi,tsj->tij", h, h)
        observed = np.diagonal(normal, axis1=1, axis2=2) > 0
        normal = normal + np.eye(n)[None] * (~observed)[:, :, None]  # ISBs without satellites stay fixed
        if not np.any(enough):
            break
        try:
            dx = np.linalg.solve(normal[enough], np.einsum("tsi,ts->ti", h[enough], res[enough])[..., None])[..., 0]
        except np.linalg.LinAlgError:
            dx = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in
                           zip(normal[enough], np.einsum("tsi,ts->ti", h[enough], res[enough]))])
        live = live[enough]
        x[live] += dx
        iterations[live] = it + 1
        converged[live] = np.linalg.norm(dx, axis=1) < config.tolerance_m
        live = live[~converged[live]]
        if not live.size:
            break
    return x, converged, iterations


def _solve(meas: Measurements, active: np.ndarray, x0: np.ndarray, config: SppConfig):
    """Batched Gauss-Newton over epochs; returns state, convergence, final geometry and usage.

    Epochs seeded with a position (|x0| > 1000 km) that do not end in a converged fix at a plausible height
    with enough satellites are solved again from the Earth's centre (no elevation mask on the first
    iteration, as in RTKLIB), and take that fix where it is one: a wrong seed (a stale, foreign or
    antipodal header position) cannot put the satellites below the mask.
    """
    n_t, n_s = active.shape
    n_sys = len(meas.systems)
    sysi = np.broadcast_to(meas.system_index, (n_t, n_s))
    sys_onehot = (sysi[..., None] == np.arange(n_sys)).astype(float)
    pr_sat = np.nan_to_num(meas.satclock_corrected_pr_m())
    mask_rad = np.radians(config.elevation_mask_deg)
    low, high = config.height_range_m

    def final(r: np.ndarray, xr: np.ndarray, conv: np.ndarray) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """Linearisation at the end, and (R,) whether it is a fix: converged, enough satellites, plausible height."""
        lin = _linearise(meas, r, xr, active[r], sys_onehot[r], mask_rad)
        height = ecef_to_lla(xr[:, :3])[:, 2]
        return lin, conv & lin[4] & (height >= low) & (height <= high)

    rows = np.arange(n_t)
    x, converged, iterations = _iterate(meas, rows, x0, active, pr_sat, sys_onehot, config)
    lin, fixed = final(rows, x, converged)
    retry = np.flatnonzero(~fixed & (np.linalg.norm(x0[:, :3], axis=1) > 1e6))
    if retry.size:
        xr, cr, ir = _iterate(meas, retry, np.zeros_like(x0[retry]), active[retry], pr_sat[retry],
                              sys_onehot[retry], config)
        better = final(retry, xr, cr)[1]
        if np.any(better):
            take = retry[better]
            x[take], converged[take] = xr[better], True
            iterations[take] += ir[better]
            lin = final(rows, x, converged)[0]
    x, usable, _, present, enough, rng, clock, _, az, el, tropo, iono = lin
    pr_corr = pr_sat - tropo - iono
    res = pr_corr - rng - clock
    observed = present.copy()            # reported clock states: the clock, ISBs of systems present
    observed[:, 0] = np.any(present, axis=1)
    return x, converged & enough, enough, usable, pr_corr, res, az, el, tropo, iono, iterations, observed


def spp(meas: Measurements, config: SppConfig = SppConfig()) -> CoarseFix:
    """Equal-weight least-squares fix of every epoch, with per-epoch status and per-satellite reasons.

    Seed: every epoch starts from the header's ``APPROX POSITION XYZ`` when its height is within
    ``config.height_range_m``, else from the Earth's centre; a seeded epoch that ends without a fix is
    solved again from the Earth's centre (:func:`_solve`), so a wrong header cannot cost fixes. Epochs
    are independent: no epoch is seeded from another's fix (an exclusion round re-seeds an epoch from its
    own previous fix only).

    Clock: ``clock_m[:, 0]`` is the receiver clock of ``systems[0]`` and ``clock_m[:, k]`` the ISB of
    ``systems[k]`` relative to it [m]. An ISB whose system has no used satellite in the epoch is not
    estimated (NaN). In an epoch without a used satellite of ``systems[0]``, the lowest-index system
    present takes over the clock: ``clock_m[:, 0]`` is that system's receiver clock, its ISB is 0 and the
    other ISBs are relative to it (the convention of :mod:`lfgnss.dop`). An epoch needs as many used
    satellites as unknowns: 3 + the number of systems present.
    """
    if not isinstance(meas, Measurements):
        raise TypeError(f"lfgnss.spp: expected the Measurements that lfgnss.load returns, got {type(meas).__name__}")
    n_t, n_s = meas.reason.shape
    n_sys = len(meas.systems)
    active = meas.reason == qc.OK
    x0 = np.zeros((n_t, 3 + n_sys))
    header = np.asarray(meas.obs.approx_ecef_m, float)
    header_height = ecef_to_lla(header)[2]
    if config.height_range_m[0] <= header_height <= config.height_range_m[1]:
        x0[:, :3] = header
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
