"""Frames against known WGS84 values: the axes, the poles, heights from below ground to beyond GEO."""
from __future__ import annotations

import numpy as np
import pytest

from lfgnss.frames import azimuth_elevation, ecef_to_enu, ecef_to_lla, lla_to_ecef

A_M = 6378137.0
B_M = 6356752.314245179          # WGS84 semi-minor axis a (1 - f), f = 1 / 298.257223563


@pytest.mark.parametrize("lat_deg, lon_deg, ecef", [
    (0.0, 0.0, (A_M, 0.0, 0.0)), (0.0, 90.0, (0.0, A_M, 0.0)), (0.0, 180.0, (-A_M, 0.0, 0.0)),
    (90.0, 0.0, (0.0, 0.0, B_M)), (-90.0, 0.0, (0.0, 0.0, -B_M)),
])
def test_the_ellipsoid_on_its_axes(lat_deg, lon_deg, ecef):
    np.testing.assert_allclose(lla_to_ecef(np.radians(lat_deg), np.radians(lon_deg), 0.0), ecef, rtol=0, atol=1e-6)
    lat, _, h = ecef_to_lla(np.array(ecef))
    assert lat == pytest.approx(np.radians(lat_deg), abs=1e-15) and h == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("h_m", [-100.0, 0.0, 100.0, 1000.0, 2.0e7])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_heights_at_the_poles(h_m, sign):
    """On the Earth's axis the height came out N too low (-6.4e6 m for a point 100 m above the pole): h was
    p / cos(lat) - N, with cos(lat) clamped at 1e-12 and p = 0."""
    lat, _, h = ecef_to_lla(np.array([0.0, 0.0, sign * (B_M + h_m)]))
    assert lat == sign * np.pi / 2 and h == pytest.approx(h_m, abs=1e-6)
    lat, _, h = ecef_to_lla(lla_to_ecef(sign * (np.pi / 2 - 1e-13), 0.3, h_m))     # next to the axis too
    assert h == pytest.approx(h_m, abs=1e-6)


def test_round_trip_everywhere():
    rng = np.random.default_rng(7)
    lat = rng.uniform(-np.pi / 2, np.pi / 2, 5000)
    lon = rng.uniform(-np.pi, np.pi, 5000)
    h = rng.uniform(-1000.0, 4.2e7, 5000)
    lla = ecef_to_lla(lla_to_ecef(lat, lon, h))
    np.testing.assert_allclose(lla[:, 0], lat, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.angle(np.exp(1j * (lla[:, 1] - lon))), 0.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(lla[:, 2], h, rtol=0, atol=1e-6)


def test_enu_and_azimuth_elevation_of_known_directions():
    """At (lat, lon) = (0, 0) east is +Y, north +Z, up +X; a satellite straight up is at 90 deg elevation."""
    ref = np.array([A_M, 0.0, 0.0])
    np.testing.assert_allclose(ecef_to_enu(ref + np.array([[0.0, 5.0, 0.0], [0.0, 0.0, 7.0], [3.0, 0.0, 0.0]]), ref),
                               [[5.0, 0.0, 0.0], [0.0, 7.0, 0.0], [0.0, 0.0, 3.0]], rtol=0, atol=1e-9)
    sats = ref + np.array([[2.0e7, 0.0, 0.0], [1.0, 1.0e7, 0.0], [1.0, 0.0, 1.0e7], [1.0e7, -1.0e7, 0.0]])
    az, el = azimuth_elevation(ref, sats)
    np.testing.assert_allclose(np.degrees(el), [90.0, 0.0, 0.0, 45.0], rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.degrees(az[1:]), [90.0, 0.0, 270.0], rtol=0, atol=1e-5)
