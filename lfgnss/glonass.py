"""GLONASS broadcast orbit: RK4 integration of the PZ-90 equations of motion (GLONASS ICD A.3.1.2).

Vectorised over satellites: every row integrates from its own toe to its own time with 60 s steps
and a last partial step, exactly like RTKLIB ``geph2pos``/``glorbit``/``deq``. PZ-90 coordinates are
used as WGS84 (as RTKLIB does; PZ-90.11 and WGS84 (G1762) agree at the centimetre level).
"""
from __future__ import annotations

import numpy as np

from .constants import GM_GLO_M3_S2, OMEGA_EARTH_GLO_RAD_S

J2_GLO = 1.0826257e-3      #: second zonal harmonic of the geopotential (ICD)
RE_GLO_M = 6378136.0       #: equatorial radius of the earth, PZ-90 [m]
STEP_S = 60.0              #: integration step [s] (RTKLIB TSTEP)
#: Longest propagation [s]: a broadcast state is valid for +-15 min; beyond hours it is a damaged record, and
#: integrating it would take |dt| / 60 s steps (an unbounded loop for an absurd time).
MAX_PROPAGATION_S = 6 * 3600.0


def derivatives(state: np.ndarray, acc_m_s2: np.ndarray) -> np.ndarray:
    """Time derivative of the ECEF state (RTKLIB ``deq``).

    Parameters
    ----------
    state : (N, 6) array
        Position [m] and velocity [m/s] in the rotating PZ-90 frame.
    acc_m_s2 : (N, 3) array
        Luni-solar acceleration of the ephemeris [m/s^2], held constant.

    Returns
    -------
    (N, 6) array: velocity and acceleration,
        a = -mu/r^3 x - 3/2 J2 mu Re^2/r^5 x (1 - 5 z^2/r^2) + omega^2 (x, y) + 2 omega (vy, -vx) + acc
        (z: -3/2 J2 mu Re^2 / r^5 z (3 - 5 z^2/r^2)).
    """
    x, y, z = state[:, 0], state[:, 1], state[:, 2]
    vx, vy = state[:, 3], state[:, 4]
    r2 = x * x + y * y + z * z
    r3 = r2 * np.sqrt(r2)
    omg2 = OMEGA_EARTH_GLO_RAD_S**2
    a = 1.5 * J2_GLO * GM_GLO_M3_S2 * RE_GLO_M**2 / r2 / r3   # 3/2 J2 mu Re^2 / r^5
    b = 5.0 * z * z / r2                                      # 5 z^2 / r^2
    c = -GM_GLO_M3_S2 / r3 - a * (1.0 - b)                    # -mu/r^3 - a (1 - b)
    out = np.empty_like(state)
    out[:, 0:3] = state[:, 3:6]
    out[:, 3] = (c + omg2) * x + 2.0 * OMEGA_EARTH_GLO_RAD_S * vy + acc_m_s2[:, 0]
    out[:, 4] = (c + omg2) * y - 2.0 * OMEGA_EARTH_GLO_RAD_S * vx + acc_m_s2[:, 1]
    out[:, 5] = (c - 2.0 * a) * z + acc_m_s2[:, 2]
    return out


def rk4_step(state: np.ndarray, acc_m_s2: np.ndarray, h_s: np.ndarray) -> np.ndarray:
    """One classical Runge-Kutta step of per-row length ``h_s`` (N,) [s] (RTKLIB ``glorbit``)."""
    h = h_s[:, None]
    k1 = derivatives(state, acc_m_s2)
    k2 = derivatives(state + k1 * h / 2.0, acc_m_s2)
    k3 = derivatives(state + k2 * h / 2.0, acc_m_s2)
    k4 = derivatives(state + k3 * h, acc_m_s2)
    return state + (k1 + 2.0 * k2 + 2.0 * k3 + k4) * h / 6.0


def propagate(pos_ecef_m: np.ndarray, vel_ecef_m_s: np.ndarray, acc_m_s2: np.ndarray,
              dt_s: np.ndarray, step_s: float = STEP_S) -> tuple[np.ndarray, np.ndarray]:
    """Integrate GLONASS broadcast states over ``dt_s`` = t - toe (RTKLIB ``geph2pos``).

    Parameters
    ----------
    pos_ecef_m, vel_ecef_m_s, acc_m_s2 : (N, 3) arrays
        Ephemeris state at toe and its luni-solar acceleration.
    dt_s : (N,) array
        Time from toe to the wanted epoch [s], either sign (|dt| up to ~1800 s in practice).

    Returns
    -------
    pos_ecef_m, vel_ecef_m_s : (N, 3) arrays at toe + dt in the ECEF frame of that time; NaN where ``dt_s`` is
        not finite or beyond ``MAX_PROPAGATION_S``.
    """
    state = np.concatenate([np.asarray(pos_ecef_m, float), np.asarray(vel_ecef_m_s, float)], axis=1)
    acc = np.asarray(acc_m_s2, float)
    remaining = np.asarray(dt_s, float).copy()
    unusable = ~(np.abs(remaining) <= MAX_PROPAGATION_S)
    remaining[unusable] = 0.0
    state[unusable] = np.nan
    n_steps = int(np.ceil(np.max(np.abs(remaining), initial=0.0) / step_s - 1e-12)) if remaining.size else 0
    for _ in range(n_steps):
        h = np.where(np.abs(remaining) > 1e-9, np.sign(remaining) * np.minimum(np.abs(remaining), step_s), 0.0)
        active = h != 0.0
        if not active.any():
            break
        state[active] = rk4_step(state[active], acc[active], h[active])
        remaining = remaining - h
    return state[:, 0:3], state[:, 3:6]
