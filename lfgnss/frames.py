"""Frames: ECEF <-> geodetic (WGS84), local ENU, azimuth and elevation."""
from __future__ import annotations

import numpy as np

from .constants import WGS84_A_M, WGS84_F

_E2 = WGS84_F * (2.0 - WGS84_F)


def lla_to_ecef(lat_rad: np.ndarray, lon_rad: np.ndarray, h_m: np.ndarray) -> np.ndarray:
    """ECEF [m], shape (..., 3), from geodetic latitude/longitude [rad] and ellipsoidal height [m]."""
    lat, lon, h = np.broadcast_arrays(np.asarray(lat_rad, float), np.asarray(lon_rad, float), np.asarray(h_m, float))
    n = WGS84_A_M / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack([(n + h) * np.cos(lat) * np.cos(lon),
                     (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - _E2) + h) * np.sin(lat)], axis=-1)


def ecef_to_lla(ecef_m: np.ndarray) -> np.ndarray:
    """Geodetic (lat [rad], lon [rad], h [m]), shape (..., 3), from ECEF [m] (4 fixed-point iterations on latitude)."""
    x, y, z = np.moveaxis(np.asarray(ecef_m, dtype=float), -1, 0)
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    lat = np.arctan2(z, p * (1.0 - _E2))

    def height(lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # p cos(lat) + z sin(lat) - a sqrt(1 - e2 sin^2 lat), not p / cos(lat) - N, which is -N on the axis
        s = np.sin(lat)
        n = WGS84_A_M / np.sqrt(1.0 - _E2 * s ** 2)
        return n, p * np.cos(lat) + z * s - WGS84_A_M * WGS84_A_M / n

    for _ in range(4):
        n, h = height(lat)
        nh = n + h
        lat = np.arctan2(z, p * (1.0 - _E2 * n / np.where(np.abs(nh) > 1.0, nh, 1.0)))
    return np.stack([lat, lon, height(lat)[1]], axis=-1)


def enu_rotation(lat_rad: float, lon_rad: float) -> np.ndarray:
    """Rotation matrix (3, 3) taking ECEF vectors to local east-north-up at (lat, lon) [rad]."""
    sl, cl = np.sin(lat_rad), np.cos(lat_rad)
    so, co = np.sin(lon_rad), np.cos(lon_rad)
    return np.array([[-so, co, 0.0],
                     [-sl * co, -sl * so, cl],
                     [cl * co, cl * so, sl]])


def ecef_to_enu(ecef_m: np.ndarray, ref_ecef_m: np.ndarray) -> np.ndarray:
    """ENU [m], shape (..., 3), of ECEF points relative to the reference ECEF point [m]."""
    lat, lon, _ = ecef_to_lla(np.asarray(ref_ecef_m, float))
    return (np.asarray(ecef_m, float) - ref_ecef_m) @ enu_rotation(lat, lon).T


def enu_to_ecef(enu_m: np.ndarray, ref_ecef_m: np.ndarray) -> np.ndarray:
    """ECEF [m] of ENU offsets [m] from the reference ECEF point."""
    lat, lon, _ = ecef_to_lla(np.asarray(ref_ecef_m, float))
    return np.asarray(enu_m, float) @ enu_rotation(lat, lon) + ref_ecef_m


def azimuth_elevation(rcv_ecef_m: np.ndarray, sat_ecef_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation [rad] of satellites (..., 3) seen from a receiver (3,) [m]."""
    lat, lon, _ = ecef_to_lla(np.asarray(rcv_ecef_m, float))
    los = np.asarray(sat_ecef_m, float) - rcv_ecef_m
    enu = los @ enu_rotation(lat, lon).T
    az = np.mod(np.arctan2(enu[..., 0], enu[..., 1]), 2.0 * np.pi)
    el = np.arctan2(enu[..., 2], np.hypot(enu[..., 0], enu[..., 1]))
    return az, el


#: Distance from the Earth's centre [m] a ground or airborne receiver's ECEF position lies within.
NEAR_SURFACE_RADIUS_M = (6.0e6, 6.6e6)
#: Distance from the Earth's centre [m] a navigation satellite lies within (MEO ~2.6e7 m, GEO / QZSS ~4.2e7 m).
ORBIT_RADIUS_M = (1.5e7, 5.0e7)


def _check_radius(owner: str, name: str, xyz: np.ndarray, bounds: tuple[float, float], hint: str) -> None:
    """ValueError naming ``owner`` and ``name`` unless every finite row of ``xyz`` (R, 3) [m] lies ``bounds`` [m]
    from the Earth's centre."""
    r = np.linalg.norm(xyz[np.isfinite(xyz).all(axis=1)], axis=1)
    low, high = bounds
    far = (r < low) | (r > high)
    if far.any():
        raise ValueError(f"{owner}: {name} has {int(far.sum())} row(s) {r[far][0]:.6g} m (first) from the Earth's "
                         f"centre, outside [{low:g}, {high:g}]: {hint}")


def check_near_surface(owner: str, name: str, ecef_m: np.ndarray) -> None:
    """ValueError unless every finite row of ``ecef_m`` (..., 3) [m] lies near the Earth's surface (ECEF metres).

    Catches positions given in other units, e.g. latitude/longitude/height or kilometres, or zeros for "no fix",
    before they give RMSEs of thousands of kilometres; NaN rows (no position) pass.
    """
    _check_radius(owner, name, np.asarray(ecef_m, dtype=float).reshape(-1, 3), NEAR_SURFACE_RADIUS_M,
                  "it must be ECEF metres (convert latitude/longitude/height (radians, metres) with "
                  "lfgnss.frames.lla_to_ecef), NaN where there is no position")


def check_in_orbit(owner: str, name: str, ecef_m: np.ndarray) -> None:
    """ValueError unless every finite row of ``ecef_m`` (..., 3) [m] lies at a navigation satellite's distance from
    the Earth's centre (``ORBIT_RADIUS_M``): satellite positions in kilometres (as SP3 files give them) or zeros."""
    _check_radius(owner, name, np.asarray(ecef_m, dtype=float).reshape(-1, 3), ORBIT_RADIUS_M,
                  "satellite positions must be ECEF metres (kilometres, as SP3 files give them, times 1000)")
