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


#: RTKLIB's default Klobuchar coefficients (``ion_default``, 2004/1/1), used when a nav file has none.
KLOBUCHAR_DEFAULT = np.array([0.1118e-07, -0.7451e-08, -0.5961e-07, 0.1192e-06,
                              0.1167e+06, -0.2294e+06, -0.1311e+06, 0.1049e+07])


def saastamoinen_m(lat_rad: np.ndarray, h_m: np.ndarray, el_rad: np.ndarray, humidity: float = 0.7) -> np.ndarray:
    """Slant tropospheric delay [m], Saastamoinen with a standard atmosphere (RTKLIB ``tropmodel``).

    Zero for elevations <= 0 or heights outside -100 m .. 10 km; broadcastable inputs.
    """
    lat, h, el = np.broadcast_arrays(np.asarray(lat_rad, float), np.asarray(h_m, float), np.asarray(el_rad, float))
    hgt = np.clip(h, 0.0, 1e4)
    pres = 1013.25 * (1.0 - 2.2557e-5 * hgt) ** 5.2568
    temp = 15.0 - 6.5e-3 * hgt + 273.16
    e = 6.108 * humidity * np.exp((17.15 * temp - 4684.0) / (temp - 38.45))
    cos_z = np.cos(np.pi / 2.0 - el)
    safe = np.where(el > 0, cos_z, 1.0)
    trph = 0.0022768 * pres / (1.0 - 0.00266 * np.cos(2.0 * lat) - 0.00028 * hgt / 1e3) / safe
    trpw = 0.002277 * (1255.0 / temp + 0.05) * e / safe
    ok = (el > 0) & (h >= -100.0) & (h <= 1e4)
    return np.where(ok, trph + trpw, 0.0)


def klobuchar_m(tow_s: np.ndarray, lat_rad: np.ndarray, lon_rad: np.ndarray, az_rad: np.ndarray,
                el_rad: np.ndarray, coefficients: np.ndarray | None) -> np.ndarray:
    """GPS L1 ionospheric delay [m] from the broadcast Klobuchar model (IS-GPS-200, RTKLIB ``ionmodel``).

    ``coefficients`` are alpha0..3, beta0..3; all zeros or None selects ``KLOBUCHAR_DEFAULT``.
    Scale by (f_L1 / f)^2 for other frequencies.
    """
    ion = KLOBUCHAR_DEFAULT if coefficients is None or not np.any(coefficients) else np.asarray(coefficients, float)
    tow, lat, lon, az, el = np.broadcast_arrays(*(np.asarray(a, float) for a in (tow_s, lat_rad, lon_rad, az_rad, el_rad)))
    psi = 0.0137 / (el / np.pi + 0.11) - 0.022
    phi = np.clip(lat / np.pi + psi * np.cos(az), -0.416, 0.416)
    lam = lon / np.pi + psi * np.sin(az) / np.cos(phi * np.pi)
    phi = phi + 0.064 * np.cos((lam - 1.617) * np.pi)
    tt = np.mod(43200.0 * lam + tow, 86400.0)
    f = 1.0 + 16.0 * (0.53 - el / np.pi) ** 3
    amp = np.maximum(ion[0] + phi * (ion[1] + phi * (ion[2] + phi * ion[3])), 0.0)
    per = np.maximum(ion[4] + phi * (ion[5] + phi * (ion[6] + phi * ion[7])), 72000.0)
    x = 2.0 * np.pi * (tt - 50400.0) / per
    delay_s = f * np.where(np.abs(x) < 1.57, 5e-9 + amp * (1.0 + x * x * (-0.5 + x * x / 24.0)), 5e-9)
    return np.where(el > 0, SPEED_OF_LIGHT_M_S * delay_s, 0.0)
