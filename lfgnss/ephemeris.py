"""Satellite positions, velocities and clocks from broadcast ephemerides, vectorised over observations.

Inputs are flat arrays of M observations (all satellites of all epochs at once); the code loops over
constellations only. Results follow RTKLIB ``satposs``/``satpos``/``eph2pos``/``geph2pos``: position at
the signal transmission time in the ECEF frame *of that time* (no Sagnac rotation: the receiver side,
``lfgnss.corrections.geometric_range_m``, adds it), clock with the relativistic term and without TGD.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .constants import (GM_BDS_M3_S2, GM_GAL_M3_S2, GM_GPS_M3_S2, OMEGA_EARTH_BDS_RAD_S, OMEGA_EARTH_RAD_S,
                        SPEED_OF_LIGHT_M_S)
from .glonass import propagate
from .navigation import QZSS_HEALTH_MASK, KeplerEphemerides, Navigation, effective_health  # noqa: F401 (public)
from .time import BDT_MINUS_GPST_S, SECONDS_PER_WEEK

#: Largest |t - toe| [s] at which an ephemeris is used: RTKLIB 2.4.3's seleph / selgeph limits, MAXDTOE,
#: MAXDTOE_QZS and MAXDTOE_CMP plus its 1 s, MAXDTOE_GAL (4 h; 2.4.2 had 3 h) and MAXDTOE_GLO as they are.
MAX_AGE_S = {"G": 7201.0, "J": 7201.0, "E": 14400.0, "C": 21601.0, "R": 1800.0}
#: Largest broadcast accuracy [m] (URA of GPS, QZSS, BeiDou) at which an ephemeris is used: RTKLIB maps a URA to the
#: next value of its table (2.4, 3.4, ..., 192, 384, ...) and excludes variances above 300^2 m^2 (MAX_VAR_EPH), so
#: from 384 m on, a URA above 192 m.
MAX_URA_M = 192.0
#: Galileo SISA [m] beyond which RTKLIB takes "no accuracy prediction available" (500 m, excluded): -1 or above 6.
MAX_SISA_M = 6.0

_GM = {"G": GM_GPS_M3_S2, "J": GM_GPS_M3_S2, "E": GM_GAL_M3_S2, "C": GM_BDS_M3_S2}
_OMEGA_E = {"G": OMEGA_EARTH_RAD_S, "J": OMEGA_EARTH_RAD_S, "E": OMEGA_EARTH_RAD_S, "C": OMEGA_EARTH_BDS_RAD_S}
_SIN_M5, _COS_M5 = np.sin(np.deg2rad(-5.0)), np.cos(np.deg2rad(-5.0))
_VEL_STEP_S = 1.0           # central-difference half step for Kepler velocities
_KEPLER_TOL_RAD = 1e-13     # RTKLIB RTOL_KEPLER
_KEPLER_MAX_ITER = 30


@dataclass(frozen=True, eq=False)
class SatelliteStates:
    """Satellite states for M observations. Rows that are not ``ok`` for lack of an ephemeris are NaN;
    unhealthy rows carry their computed values with ``ok`` False and reason 'unhealthy'.

    The clock for a single-frequency code is ``clock_s - group_delay_s`` (GPS/QZSS L1 C/A: TGD,
    BeiDou B1I: TGD1, Galileo E1: BGD(E1, E5b); GLONASS: 0).
    """

    sv: np.ndarray               #: (M,) '<U3'
    t_tx_gps_s: np.ndarray       #: (M,) signal transmission time (GPS seconds) the states refer to
    pos_ecef_m: np.ndarray       #: (M, 3) ECEF position in the ECEF frame of ``t_tx_gps_s``
    vel_ecef_m_s: np.ndarray     #: (M, 3) ECEF velocity (time derivative of ``pos_ecef_m``)
    clock_s: np.ndarray          #: (M,) satellite clock offset incl. relativistic term, excl. TGD
    clock_drift_s_s: np.ndarray  #: (M,) its time derivative [s/s]
    group_delay_s: np.ndarray    #: (M,) TGD/BGD to subtract from ``clock_s`` for the single-frequency code
    toe_gps_s: np.ndarray        #: (M,) toe of the selected ephemeris (NaN if none)
    health: np.ndarray           #: (M,) int health word of the selected ephemeris (-1 if none)
    ok: np.ndarray               #: (M,) bool
    #: (M,) str: '' | 'no ephemeris' | 'ephemeris expired' | 'unhealthy' | 'inaccurate ephemeris' (its URA / SISA)
    #: | 'invalid time' | 'invalid ephemeris' (a non-finite state)
    reason: np.ndarray

    def __len__(self) -> int:
        return len(self.sv)


def ephemeris_states(nav: Navigation, sv: np.ndarray, t_gps_s: np.ndarray, *,
                     t_select_gps_s: np.ndarray | None = None) -> SatelliteStates:
    """Evaluate the broadcast ephemeris of each satellite at time t (RTKLIB ``satpos`` with EPHOPT_BRDC).

    Parameters
    ----------
    nav : Navigation
    sv : (M,) str array
        Satellite ids 'G05', 'R12', 'E30', 'J02', 'C01', ...
    t_gps_s : (M,) float array
        Time by GPS clock at which to evaluate, normally the signal transmission time [s].
    t_select_gps_s : (M,) float array, optional
        Time used to choose the ephemeris (RTKLIB ``teph``); default ``t_gps_s``.
        :func:`satellite_states` passes the reception time, so that all satellites of an epoch use
        the records valid at that epoch, as RTKLIB does.

    Returns
    -------
    SatelliteStates
        Selection policy (RTKLIB 2.4.3 ``seleph``/``selgeph``): the record of that satellite with the
        nearest toe (later toe, then latest transmission time, on ties) and |t - toe| <= ``MAX_AGE_S``;
        Galileo only considers toe < t, as rnx2rtkp 2.4.3 b34 does (seen in its traces; Galileo
        messages are transmitted minutes after their toe, so a nearer future toe was not yet received).
        Rows without a usable ephemeris are NaN.
        Kepler orbits (``eph2pos``) with each system's GM and earth rotation rate; BeiDou GEO
        (C01-C05, C59-C63) in the -5 deg inclined frame of the BDS ICD; GLONASS by RK4 (``geph2pos``).
        Kepler velocities are central differences of the full position function (so BeiDou GEO
        velocities are right in ECEF).
    """
    sv = np.asarray(sv).astype("<U3")
    t = np.asarray(t_gps_s, dtype=float)
    ts = t if t_select_gps_s is None else np.asarray(t_select_gps_s, dtype=float)
    if sv.shape != t.shape or sv.ndim != 1 or ts.shape != t.shape:
        raise ValueError(f"sv {sv.shape}, t_gps_s {t.shape} and t_select_gps_s {ts.shape} must be equal 1-D shapes")
    m = len(sv)
    pos = np.full((m, 3), np.nan)
    vel = np.full((m, 3), np.nan)
    clk = np.full(m, np.nan)
    drift = np.full(m, np.nan)
    tgd = np.full(m, np.nan)
    toe = np.full(m, np.nan)
    health = np.full(m, -1, dtype=int)
    accuracy = np.zeros(m)
    reason = np.full(m, "no ephemeris", dtype="<U20")
    finite = np.isfinite(t) & np.isfinite(ts)
    reason[~finite] = "invalid time"
    system = sv.astype("<U1")

    kep = nav.kepler
    for s in ("G", "E", "J", "C"):
        rows = np.flatnonzero((system == s) & finite)
        recs = np.flatnonzero(kep.system == s)
        if rows.size == 0:
            continue
        idx, why = _select(kep.sv[recs], kep.toe_gps_s[recs], sv[rows], ts[rows], MAX_AGE_S[s], past_only=s == "E")
        reason[rows] = why
        good = idx >= 0
        rows, sel = rows[good], recs[idx[good]]
        if rows.size == 0:
            continue
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):   # an unhealthy placeholder record (e >= 1)
            p, v, c, cd = _kepler_states(kep, sel, t[rows], s)                # gives NaN; it is never used
        pos[rows], vel[rows], clk[rows], drift[rows] = p, v, c, cd
        tgd[rows], toe[rows], health[rows] = kep.tgd_s[sel], kep.toe_gps_s[sel], kep.health[sel]
        accuracy[rows] = kep.accuracy_m[sel]

    glo = nav.glonass
    rows = np.flatnonzero((system == "R") & finite)
    if rows.size:
        idx, why = _select(glo.sv, glo.toe_gps_s, sv[rows], ts[rows], MAX_AGE_S["R"])
        reason[rows] = why
        good = idx >= 0
        rows, sel = rows[good], idx[good]
        if rows.size:
            dt = t[rows] - glo.toe_gps_s[sel]
            p, v = propagate(glo.pos_ecef_m[sel], glo.vel_ecef_m_s[sel], glo.acc_ecef_m_s2[sel], dt)
            pos[rows], vel[rows] = p, v
            clk[rows] = -glo.tau_n_s[sel] + glo.gamma_n[sel] * dt       # dts = -tau_n + gamma_n (t - toe)
            drift[rows] = glo.gamma_n[sel]
            tgd[rows], toe[rows], health[rows] = 0.0, glo.toe_gps_s[sel], glo.health[sel]

    unhealthy = (reason == "") & (effective_health(system, health) != 0)
    reason[unhealthy] = "unhealthy"
    reason[(reason == "") & inaccurate(system, accuracy)] = "inaccurate ephemeris"
    broken = (reason == "") & ~(np.isfinite(pos).all(axis=1) & np.isfinite(clk))
    reason[broken] = "invalid ephemeris"
    return SatelliteStates(sv=sv, t_tx_gps_s=t, pos_ecef_m=pos, vel_ecef_m_s=vel, clock_s=clk,
                           clock_drift_s_s=drift, group_delay_s=tgd, toe_gps_s=toe, health=health,
                           ok=reason == "", reason=reason)


def inaccurate(system: np.ndarray, accuracy_m: np.ndarray) -> np.ndarray:
    """Whether a broadcast accuracy [m] excludes its ephemeris, as RTKLIB's satexclude (var > 300^2 m^2): a URA above
    ``MAX_URA_M`` (GPS, QZSS, BeiDou), a Galileo SISA below 0 (no accuracy prediction) or above ``MAX_SISA_M``."""
    system = np.asarray(system)
    a = np.asarray(accuracy_m, dtype=float)
    return np.where(system == "E", (a < 0) | (a > MAX_SISA_M), np.isin(system, ("G", "J", "C")) & (a > MAX_URA_M))


def satellite_states(nav: Navigation, sv: np.ndarray, t_rx_gps_s: np.ndarray, pr_m: np.ndarray) -> SatelliteStates:
    """Satellite states at the signal transmission time of each pseudorange (RTKLIB ``satposs``).

    Parameters
    ----------
    nav : Navigation
    sv : (M,) str array
    t_rx_gps_s : (M,) float array
        Reception time stamps of the observations [GPS s] (receiver clock; RTKLIB uses them as is).
    pr_m : (M,) float array
        Pseudoranges [m].

    Returns
    -------
    SatelliteStates with ``t_tx_gps_s`` = t_rx - pr/c - dt_sv, where dt_sv is the broadcast clock
    polynomial (without relativistic term, as RTKLIB ``eph2clk``/``geph2clk``) evaluated at the
    satellite-clock time t_rx - pr/c with two fixed-point iterations. Ephemerides are selected at
    t_rx (RTKLIB ``teph``).
    """
    sv = np.asarray(sv).astype("<U3")
    t_rx = np.asarray(t_rx_gps_s, dtype=float)
    t = t_rx - np.asarray(pr_m, dtype=float) / SPEED_OF_LIGHT_M_S
    t_tx = t - _clock_polynomial_s(nav, sv, t, t_rx)
    return ephemeris_states(nav, sv, t_tx, t_select_gps_s=t_rx)


# --------------------------------------------------------------------------------------------------
def _select(rec_sv: np.ndarray, rec_toe: np.ndarray, sv: np.ndarray, t: np.ndarray,
            max_age_s: float, past_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Index into the records (sorted by sv, toe, tie-break) of the nearest-toe record of each query
    (only toe < t if ``past_only``).

    Returns (idx (N,) int, -1 when none; reason (N,) str, '' when found).
    """
    n = len(sv)
    idx = np.full(n, -1)
    reason = np.full(n, "no ephemeris", dtype="<U20")
    if len(rec_sv) == 0 or n == 0:
        return idx, reason
    names, rec_id = np.unique(rec_sv, return_inverse=True)
    q = np.clip(np.searchsorted(names, sv), 0, len(names) - 1)
    known = names[q] == sv
    # composite sort key sv_id * W + (toe - t0); records are already ordered by (sv, toe)
    t0 = rec_toe.min()
    width = 4e9
    keys = rec_id * width + (rec_toe - t0)
    qkey = q * width + np.clip(t - t0, -1e9, 1e9)
    k = np.searchsorted(keys, qkey, side="left")
    start = np.searchsorted(rec_id, q, side="left")
    stop = np.searchsorted(rec_id, q, side="right")
    has_prev = known & (k - 1 >= start)
    has_next = known & (k < stop) & (not past_only)
    prev = np.clip(k - 1, 0, len(keys) - 1)
    nxt = np.clip(k, 0, len(keys) - 1)
    d_prev = np.where(has_prev, np.abs(t - rec_toe[prev]), np.inf)
    d_next = np.where(has_next, np.abs(t - rec_toe[nxt]), np.inf)
    choice = np.where(d_next <= d_prev, nxt, prev)               # ties: later toe
    best = np.minimum(d_prev, d_next)
    # among records with the same (sv, toe) take the last one: latest transmission time
    choice = np.searchsorted(keys, keys[choice], side="right") - 1
    found = best <= max_age_s
    idx[found] = choice[found]
    reason[found] = ""
    reason[~found & has_prev] = "ephemeris expired"
    return idx, reason


def _kepler_position(kep: KeplerEphemerides, sel: np.ndarray, t: np.ndarray, s: str):
    """ECEF position (N, 3) and eccentric anomaly (N,) of Kepler records ``sel`` at ``t`` (``eph2pos``)."""
    mu, omge = _GM[s], _OMEGA_E[s]
    a = kep.sqrt_a_sqrt_m[sel] ** 2
    e = kep.e[sel]
    tk = t - kep.toe_gps_s[sel]
    mean = kep.m0_rad[sel] + (np.sqrt(mu / a**3) + kep.delta_n_rad_s[sel]) * tk
    ecc = mean.copy()
    for _ in range(_KEPLER_MAX_ITER):                           # Newton on E - e sin E = M
        step = (ecc - e * np.sin(ecc) - mean) / (1.0 - e * np.cos(ecc))
        ecc = ecc - step
        if np.max(np.abs(step), initial=0.0) <= _KEPLER_TOL_RAD:
            break
    sin_e, cos_e = np.sin(ecc), np.cos(ecc)
    u = np.arctan2(np.sqrt(1.0 - e * e) * sin_e, cos_e - e) + kep.omega_rad[sel]
    r = a * (1.0 - e * cos_e)
    inc = kep.i0_rad[sel] + kep.idot_rad_s[sel] * tk
    sin2u, cos2u = np.sin(2.0 * u), np.cos(2.0 * u)
    u = u + kep.cus_rad[sel] * sin2u + kep.cuc_rad[sel] * cos2u
    r = r + kep.crs_m[sel] * sin2u + kep.crc_m[sel] * cos2u
    inc = inc + kep.cis_rad[sel] * sin2u + kep.cic_rad[sel] * cos2u
    x, y = r * np.cos(u), r * np.sin(u)
    cos_i, sin_i = np.cos(inc), np.sin(inc)
    toe_sys = kep.toe_gps_s[sel] + (BDT_MINUS_GPST_S if s == "C" else 0.0)
    toes = np.mod(toe_sys, SECONDS_PER_WEEK)                     # toe in seconds of the system's week
    geo = np.zeros(len(sel), bool)
    if s == "C":
        digits = np.ascontiguousarray(kep.sv[sel], dtype="<U3").view("<U1").reshape(-1, 3)[:, 1:]
        prn = digits[:, 0].astype(int) * 10 + digits[:, 1].astype(int)
        geo = (prn <= 5) | (prn >= 59)
    # MEO/IGSO: Omega = Omega0 + (OmegaDot - omega_e) tk - omega_e toes
    big_omega = kep.omega0_rad[sel] + (kep.omega_dot_rad_s[sel] - np.where(geo, 0.0, omge)) * tk - omge * toes
    sin_o, cos_o = np.sin(big_omega), np.cos(big_omega)
    pos = np.column_stack([x * cos_o - y * cos_i * sin_o, x * sin_o + y * cos_i * cos_o, y * sin_i])
    if geo.any():
        # BDS GEO: position in the inertial-like frame rotated by -5 deg about X, then by omega_e tk about Z
        g = pos[geo]
        sino, coso = np.sin(omge * tk[geo]), np.cos(omge * tk[geo])
        pos[geo] = np.column_stack([
            g[:, 0] * coso + g[:, 1] * sino * _COS_M5 + g[:, 2] * sino * _SIN_M5,
            -g[:, 0] * sino + g[:, 1] * coso * _COS_M5 + g[:, 2] * coso * _SIN_M5,
            -g[:, 1] * _SIN_M5 + g[:, 2] * _COS_M5,
        ])
    return pos, ecc


def _kepler_states(kep: KeplerEphemerides, sel: np.ndarray, t: np.ndarray, s: str):
    """Position (N,3), velocity (N,3), clock (N,) and clock drift (N,) of Kepler records (``eph2pos``)."""
    pos, ecc = _kepler_position(kep, sel, t, s)
    p_plus, _ = _kepler_position(kep, sel, t + _VEL_STEP_S, s)
    p_minus, _ = _kepler_position(kep, sel, t - _VEL_STEP_S, s)
    vel = (p_plus - p_minus) / (2.0 * _VEL_STEP_S)
    mu = _GM[s]
    a = kep.sqrt_a_sqrt_m[sel] ** 2
    e = kep.e[sel]
    tc = t - kep.toc_gps_s[sel]
    # dts = af0 + af1 tc + af2 tc^2 - 2 sqrt(mu A) e sin(E) / c^2
    rel = -2.0 * np.sqrt(mu * a) * e / SPEED_OF_LIGHT_M_S**2
    clk = kep.af0_s[sel] + kep.af1_s_s[sel] * tc + kep.af2_s_s2[sel] * tc**2 + rel * np.sin(ecc)
    e_dot = (np.sqrt(mu / a**3) + kep.delta_n_rad_s[sel]) / (1.0 - e * np.cos(ecc))
    drift = kep.af1_s_s[sel] + 2.0 * kep.af2_s_s2[sel] * tc + rel * np.cos(ecc) * e_dot
    return pos, vel, clk, drift


def _clock_polynomial_s(nav: Navigation, sv: np.ndarray, t_sv: np.ndarray, t_select: np.ndarray) -> np.ndarray:
    """Broadcast clock polynomial without relativity at satellite-clock time ``t_sv`` (``eph2clk``,
    ``geph2clk``): t = t_sv - dts(t) by two fixed-point iterations; ephemeris chosen at ``t_select``.
    Satellites without ephemeris give 0."""
    out = np.zeros(len(sv))
    finite = np.isfinite(t_sv) & np.isfinite(t_select)
    system = sv.astype("<U1")
    kep, glo = nav.kepler, nav.glonass
    for s in ("G", "E", "J", "C", "R"):
        rows = np.flatnonzero((system == s) & finite)
        if rows.size == 0:
            continue
        if s == "R":
            idx, _ = _select(glo.sv, glo.toe_gps_s, sv[rows], t_select[rows], MAX_AGE_S[s])
            good = idx >= 0
            sel = idx[good]
            dt = ts0 = t_sv[rows[good]] - glo.toe_gps_s[sel]
            for _ in range(2):                                       # RTKLIB geph2clk: t = ts - dts(t)
                dt = ts0 - (-glo.tau_n_s[sel] + glo.gamma_n[sel] * dt)
            out[rows[good]] = -glo.tau_n_s[sel] + glo.gamma_n[sel] * dt
            continue
        recs = np.flatnonzero(kep.system == s)
        idx, _ = _select(kep.sv[recs], kep.toe_gps_s[recs], sv[rows], t_select[rows], MAX_AGE_S[s],
                         past_only=s == "E")
        good = idx >= 0
        sel = recs[idx[good]]
        dt = ts0 = t_sv[rows[good]] - kep.toc_gps_s[sel]
        f0, f1, f2 = kep.af0_s[sel], kep.af1_s_s[sel], kep.af2_s_s2[sel]
        for _ in range(2):                                           # RTKLIB eph2clk: t = ts - dts(t)
            dt = ts0 - (f0 + f1 * dt + f2 * dt * dt)
        out[rows[good]] = f0 + f1 * dt + f2 * dt * dt
    return out
