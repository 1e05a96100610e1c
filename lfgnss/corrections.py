"""Propagation corrections: Sagnac/geometric range, Saastamoinen troposphere, Klobuchar ionosphere."""
from __future__ import annotations

import numpy as np

from .constants import OMEGA_EARTH_RAD_S, SPEED_OF_LIGHT_M_S


def sagnac_m(sat_ecef_m: np.ndarray, rcv_ecef_m: np.ndarray) -> np.ndarray:
    """Sagnac (earth rotation during signal travel) range term [m] (RTKLIB ``geodist``).

    dR = omega_e / c * (x_s * y_r - y_s * x_r), satellites (..., 3), receiver broadcastable (..., 3).
    """
    s = np.asarray(sat_ecef_m, float)
    r = np.asarray(rcv_ecef_m, float)
    return OMEGA_EARTH_RAD_S / SPEED_OF_LIGHT_M_S * (s[..., 0] * r[..., 1] - s[..., 1] * r[..., 0])


def geometric_range_m(sat_ecef_m: np.ndarray, rcv_ecef_m: np.ndarray) -> np.ndarray:
    """Receiver-satellite range including the Sagnac term [m].

    ``sat_ecef_m`` is the satellite position at transmission time in the ECEF frame of that time,
    rho = |s - r| + omega_e / c (x_s y_r - y_s x_r). This is the one geometry model of lfgnss; gtsam's
    ``PseudorangeFactor`` uses the same convention.
    """
    s = np.asarray(sat_ecef_m, float)
    r = np.asarray(rcv_ecef_m, float)
    return np.linalg.norm(s - r, axis=-1) + sagnac_m(s, r)


def line_of_sight(sat_ecef_m: np.ndarray, rcv_ecef_m: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3) from receiver to satellites (the negated position rows of the design matrix)."""
    d = np.asarray(sat_ecef_m, float) - np.asarray(rcv_ecef_m, float)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
