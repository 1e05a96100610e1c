"""Coarse least squares and corrections: physics known values, synthetic truth recovery, real data."""
from types import SimpleNamespace

import numpy as np
import pytest

import lfgnss
from lfgnss import qc
from lfgnss.constants import GPS_L1_HZ, OMEGA_EARTH_RAD_S, SPEED_OF_LIGHT_M_S
from lfgnss.corrections import geometric_range_m, klobuchar_m, sagnac_m, saastamoinen_m
from lfgnss.frames import azimuth_elevation, ecef_to_lla, lla_to_ecef
from lfgnss.measurements import Measurements
from lfgnss.observations import Observations
from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS


def test_saastamoinen_known_values():
    # zenith hydrostatic + wet delay at sea level, standard atmosphere: ~2.3-2.5 m; ~1/sin(el) growth
    zenith = saastamoinen_m(np.radians(45.0), 0.0, np.pi / 2)
    assert 2.3 < zenith < 2.6
    assert saastamoinen_m(np.radians(45.0), 0.0, np.radians(10.0)) == pytest.approx(zenith / np.sin(np.radians(10)), rel=0.02)
    assert saastamoinen_m(0.3, 0.0, -0.1) == 0.0


def test_klobuchar_night_floor_and_day_peak():
    alpha_beta = np.array([1.1e-8, 0, -6e-8, 0, 9e4, 0, -2e5, 0])
    lat, lon = np.radians(40.0), 0.0
    night = klobuchar_m(2 * 3600.0, lat, lon, 0.0, np.pi / 2, alpha_beta)
    obliquity = 1.0 + 16.0 * (0.53 - 0.5) ** 3      # F at zenith
    assert night == pytest.approx(5e-9 * SPEED_OF_LIGHT_M_S * obliquity, rel=1e-9)  # 5 ns night-time floor
    day = klobuchar_m(14 * 3600.0, lat, lon, 0.0, np.pi / 2, alpha_beta)
    assert 2.0 < day < 15.0
    assert klobuchar_m(14 * 3600.0, lat, lon, 0.0, np.radians(10), alpha_beta) > 2.0 * day  # obliquity


def test_sagnac_formula_and_size():
    rcv = lla_to_ecef(np.radians(22.3), np.radians(114.2), 0.0)
    sat = np.array([-12e6, 20e6, 10e6])
    expected = OMEGA_EARTH_RAD_S / SPEED_OF_LIGHT_M_S * (sat[0] * rcv[1] - sat[1] * rcv[0])
    assert sagnac_m(sat, rcv) == pytest.approx(expected)
    assert 1.0 < abs(expected) < 40.0          # tens of metres at most for MEO satellites
    assert geometric_range_m(sat, rcv) == pytest.approx(np.linalg.norm(sat - rcv) + expected)


def _synthetic_measurements(n_epochs=5, seed=1):
    rng = np.random.default_rng(seed)
    truth = lla_to_ecef(np.radians(22.3), np.radians(114.18), 20.0)
    lat, lon, h = ecef_to_lla(truth)
    n_g, n_c = 7, 5
    az = rng.uniform(0, 2 * np.pi, n_g + n_c)
    el = np.radians(rng.uniform(15, 85, n_g + n_c))
    east_north_up = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], -1)
    from lfgnss.frames import enu_rotation
    sat = truth + 2.2e7 * east_north_up @ enu_rotation(lat, lon)
    sv = np.array([f"G{k + 1:02d}" for k in range(n_g)] + [f"C{k + 1:02d}" for k in range(n_c)])
    sysi = np.array([0] * n_g + [1] * n_c)
    carrier = np.where(sysi == 0, GPS_L1_HZ, 1561.098e6)
    t = 2.0e9 + np.arange(n_epochs, dtype=float)
    az_t, el_t = azimuth_elevation(truth, sat)
    tropo = saastamoinen_m(lat, h, el_t)
    iono = klobuchar_m(np.mod(t, 604800.0)[:, None], lat, lon, az_t, el_t, None) * (GPS_L1_HZ / carrier) ** 2
    clock, isb = 1234.5, -87.25
    pr = geometric_range_m(sat, truth) + clock + isb * (sysi == 1) + tropo + iono
    n_s = sv.size
    obs = Observations("synthetic.obs", 3.03, t, sv, pr, np.full((n_epochs, n_s), 45.0), np.zeros((n_epochs, n_s)),
                       {"G": "C1C", "C": "C2I"}, np.zeros(3))
    meas = Measurements(obs, SimpleNamespace(iono={}), ("G", "C"), sysi, np.broadcast_to(sat, (n_epochs, n_s, 3)).copy(),
                        np.zeros((n_epochs, n_s, 3)), np.zeros((n_epochs, n_s)), np.zeros((n_epochs, n_s)), carrier,
                        np.zeros((n_epochs, n_s), np.int8))
    return meas, truth, clock, isb


def test_spp_recovers_truth_from_earth_centre():
    meas, truth, clock, isb = _synthetic_measurements()
    fix = lfgnss.spp(meas)
    assert np.all(fix.ok)
    np.testing.assert_allclose(fix.pos_ecef_m, np.broadcast_to(truth, fix.pos_ecef_m.shape), atol=1e-3)
    np.testing.assert_allclose(fix.clock_m[:, 0], clock, atol=1e-3)
    np.testing.assert_allclose(fix.clock_m[:, 1], isb, atol=1e-3)
    assert np.nanmax(np.abs(fix.residual_m)) < 1e-3


def test_spp_too_few_satellites_and_gross_error_reasons():
    meas, truth, _, _ = _synthetic_measurements()
    reason = meas.reason.copy()
    reason[0, 3:] = qc.LOW_CN0                       # epoch 0: 3 satellites left -> no fix, with a reason
    pr = meas.obs.pr_m.copy()
    pr[1, 2] += 5000.0                               # epoch 1: one gross pseudorange -> excluded, fix kept
    obs = Observations(meas.obs.path, 3.03, meas.obs.time_gps_s, meas.obs.sv, pr, meas.obs.cn0_dbhz,
                       meas.obs.doppler_hz, meas.obs.codes, meas.obs.approx_ecef_m)
    from dataclasses import replace
    fix = lfgnss.spp(replace(meas, obs=obs, reason=reason))
    assert fix.status[0] == lfgnss.spp.__globals__["FIX_TOO_FEW_SATELLITES"]
    assert np.all(np.isnan(fix.pos_ecef_m[0]))
    assert fix.ok[1] and fix.reason[1, 2] == qc.GROSS_RESIDUAL
    assert np.linalg.norm(fix.pos_ecef_m[1] - truth) < 1e-3
    summary = fix.summary()
    assert summary["epoch_status"]["too few satellites"] == 1
    assert summary["observations"]["gross residual"] == 1


def test_bundled_sample_every_epoch_fixed():
    meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
    fix = lfgnss.spp(meas)
    assert fix.ok.mean() == 1.0
    assert meas.systems == ("G", "R")
    assert 4 <= np.median(fix.n_used) <= 20
    # urban residuals: metres to tens of metres, never absurd
    assert np.nanmedian(np.abs(fix.residual_m)) < 30.0
    counted = sum(fix.summary()["observations"].values())
    assert counted == int(np.isfinite(meas.pr_m).sum())
    frame = meas.to_frame()
    assert len(frame) == counted and set(frame["qc"]) <= set(qc.REASONS.values())


def test_implausible_height_is_rejected():
    meas, truth, _, _ = _synthetic_measurements()
    fix = lfgnss.spp(meas, lfgnss.SppConfig(height_range_m=(-1000.0, 10.0)))   # truth is at 20 m
    assert np.all(fix.status == lfgnss.spp.__globals__["FIX_IMPLAUSIBLE"])
    assert np.all(np.isnan(fix.pos_ecef_m))
    assert fix.summary()["epoch_status"] == {"implausible height": len(fix.status)}
