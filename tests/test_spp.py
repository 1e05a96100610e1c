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


CARRIER_HZ = {"G": GPS_L1_HZ, "C": 1561.098e6, "E": GPS_L1_HZ}


def _synthetic(counts=(7, 5), letters=("G", "C"), isbs=(-87.25,), n_epochs=5, seed=1, approx_ecef_m=np.zeros(3)):
    """Error-free pseudoranges of satellites 15-85 deg up over Hong Kong; returns meas, truth, clock [m]."""
    rng = np.random.default_rng(seed)
    truth = lla_to_ecef(np.radians(22.3), np.radians(114.18), 20.0)
    lat, lon, h = ecef_to_lla(truth)
    n_s = sum(counts)
    az = rng.uniform(0, 2 * np.pi, n_s)
    el = np.radians(rng.uniform(15, 85, n_s))
    east_north_up = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], -1)
    from lfgnss.frames import enu_rotation
    sat = truth + 2.2e7 * east_north_up @ enu_rotation(lat, lon)
    sv = np.array([f"{s}{k + 1:02d}" for s, n in zip(letters, counts) for k in range(n)])
    sysi = np.repeat(np.arange(len(letters)), counts)
    carrier = np.array([CARRIER_HZ[s] for s in letters])[sysi]
    t = 2.0e9 + np.arange(n_epochs, dtype=float)
    az_t, el_t = azimuth_elevation(truth, sat)
    tropo = saastamoinen_m(lat, h, el_t)
    iono = klobuchar_m(np.mod(t, 604800.0)[:, None], lat, lon, az_t, el_t, None) * (GPS_L1_HZ / carrier) ** 2
    clock = 1234.5
    pr = geometric_range_m(sat, truth) + clock + np.concatenate([[0.0], isbs])[sysi] + tropo + iono
    obs = Observations("synthetic.obs", 3.03, t, sv, pr, np.full((n_epochs, n_s), 45.0), np.zeros((n_epochs, n_s)),
                       {"G": "C1C", "C": "C2I", "E": "C1C"}, np.asarray(approx_ecef_m, float))
    meas = Measurements(obs, SimpleNamespace(iono={}), tuple(letters), sysi,
                        np.broadcast_to(sat, (n_epochs, n_s, 3)).copy(), np.zeros((n_epochs, n_s, 3)),
                        np.zeros((n_epochs, n_s)), np.zeros((n_epochs, n_s)), carrier,
                        np.zeros((n_epochs, n_s), np.int8))
    return meas, truth, clock


def _synthetic_measurements(n_epochs=5, seed=1):
    meas, truth, clock = _synthetic(n_epochs=n_epochs, seed=seed)
    return meas, truth, clock, -87.25


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


BERLIN_ECEF_M = np.array([3783948.5893, 899154.6462, 5038184.0826])


@pytest.mark.parametrize("header", [BERLIN_ECEF_M, "antipode"], ids=["berlin", "antipode"])
def test_spp_wrong_header_position_still_fixes(header):
    # a wrong APPROX POSITION XYZ puts the satellites below the 10 deg mask at the seed; the epoch must be
    # solved again from the Earth's centre (RTKLIB never uses the header) and give the truth
    meas, truth, clock = _synthetic()
    seed = -truth if isinstance(header, str) else header
    wrong, *_ = _synthetic(approx_ecef_m=seed)
    good, *_ = _synthetic(approx_ecef_m=truth + [30.0, -20.0, 10.0])
    for m in (wrong, good):
        fix = lfgnss.spp(m)
        assert np.all(fix.ok), fix.summary()
        np.testing.assert_allclose(fix.pos_ecef_m, np.broadcast_to(truth, fix.pos_ecef_m.shape), atol=1e-3)
        np.testing.assert_allclose(fix.clock_m[:, 0], clock, atol=1e-3)
        assert not np.any(fix.reason == qc.LOW_ELEVATION)


def test_spp_bad_epoch_does_not_poison_the_others():
    # epochs are seeded from the header (or their own fix), never from a neighbour's: garbage in one epoch
    # (and a wrong header) leaves every other epoch's fix exactly as in the clean run
    meas, truth, _ = _synthetic(n_epochs=6, approx_ecef_m=-lla_to_ecef(np.radians(22.3), np.radians(114.18), 0.0))
    clean = lfgnss.spp(meas)
    pr = meas.obs.pr_m.copy()
    pr[2] += np.random.default_rng(7).uniform(-3e6, 3e6, pr.shape[1])
    from dataclasses import replace
    fix = lfgnss.spp(replace(meas, obs=replace(meas.obs, pr_m=pr)))
    others = np.arange(6) != 2
    assert np.all(clean.ok) and np.all(fix.ok[others]) and not fix.ok[2]
    np.testing.assert_array_equal(fix.pos_ecef_m[others], clean.pos_ecef_m[others])
    np.testing.assert_array_equal(fix.clock_m[others], clean.clock_m[others])


def _without(meas, epochs_sats):
    """meas with the given (epoch, satellite-slice) pairs failing QC."""
    from dataclasses import replace
    reason = meas.reason.copy()
    for t, s in epochs_sats:
        reason[t, s] = qc.LOW_CN0
    return replace(meas, reason=reason)


def test_spp_epoch_without_reference_system_uses_the_present_clock():
    # G+C run, 7 GPS then 5 BeiDou satellites; epochs 0-2 lose every GPS satellite
    meas, truth, clock = _synthetic(n_epochs=5)
    isb = -87.25
    g, c = slice(0, 7), slice(7, 12)
    meas = _without(meas, [(0, g), (0, slice(7, 8)),     # 4 BeiDou: 4 unknowns (x, y, z, BDS clock) -> fix
                           (1, g),                       # 5 BeiDou: fix, clock not split between two columns
                           (2, g), (2, slice(7, 9)),     # 3 BeiDou: too few
                           (3, slice(1, 7))])            # 1 GPS + 5 BeiDou = 6 for 5 unknowns -> fix
    fix = lfgnss.spp(meas)
    assert fix.ok.tolist() == [True, True, False, True, True]
    assert fix.status[2] == lfgnss.spp.__globals__["FIX_TOO_FEW_SATELLITES"]
    ok = fix.ok
    np.testing.assert_allclose(fix.pos_ecef_m[ok], np.broadcast_to(truth, (ok.sum(), 3)), atol=1e-3)
    # without GPS the clock is BeiDou's (its ISB held at 0); with GPS, GPS clock and BeiDou ISB
    np.testing.assert_allclose(fix.clock_m[:2], [[clock + isb, 0.0]] * 2, atol=1e-3)
    np.testing.assert_allclose(fix.clock_m[3:], [[clock, isb]] * 2, atol=1e-3)
    assert fix.n_used.tolist()[:2] == [4, 5]
    assert np.nanmax(np.abs(fix.residual_m[ok])) < 1e-3
    # the same satellites in a BeiDou-only run give the same fix and clock
    c_only = Measurements(meas.obs, meas.nav, ("C",), np.where(meas.system_index == 1, 0, -1), meas.sat_pos_ecef_m,
                          meas.sat_vel_ecef_m_s, meas.sat_clock_s, meas.group_delay_s, meas.carrier_hz,
                          np.where(meas.system_index[None] == 1, meas.reason, qc.LOW_CN0).astype(np.int8))
    fix_c = lfgnss.spp(c_only)
    np.testing.assert_allclose(fix_c.clock_m[:2, 0], fix.clock_m[:2, 0], atol=1e-6)
    np.testing.assert_allclose(fix_c.pos_ecef_m[:2], fix.pos_ecef_m[:2], atol=1e-6)


def test_spp_three_systems_without_reference_and_absent_isb():
    # G+C+E: epoch 0 has no GPS (BeiDou owns the clock, Galileo's ISB is relative to BeiDou), epoch 1 has
    # no BeiDou (its ISB not estimated: NaN, not counted as an unknown: 4 GPS + 1 Galileo = 5 unknowns)
    isb_c, isb_e = -87.25, 40.5
    meas, truth, clock = _synthetic(counts=(6, 5, 4), letters=("G", "C", "E"), isbs=(isb_c, isb_e), n_epochs=3)
    meas = _without(meas, [(0, slice(0, 6)), (0, slice(7, 9)),      # 3 BeiDou + 4 Galileo, 5 unknowns
                           (1, slice(4, 6)), (1, slice(6, 11)), (1, slice(12, 15))])  # 4 GPS + 1 Galileo
    fix = lfgnss.spp(meas)
    assert np.all(fix.ok), fix.summary()
    np.testing.assert_allclose(fix.pos_ecef_m, np.broadcast_to(truth, (3, 3)), atol=1e-3)
    np.testing.assert_allclose(fix.clock_m[0], [clock + isb_c, 0.0, isb_e - isb_c], atol=1e-3)
    np.testing.assert_allclose(fix.clock_m[1], [clock, np.nan, isb_e], atol=1e-3)
    np.testing.assert_allclose(fix.clock_m[2], [clock, isb_c, isb_e], atol=1e-3)


STATIC = "hk-tst-static-20200603"


def _static_obs(shared_data):
    """Observations of the HK static file and its nav files (shared data)."""
    from lfgnss.rinex import load_obs
    folder = shared_data(STATIC)
    navs = sorted(p for p in folder.glob("hksc155*.20?") if p.suffix[-1] in "nglb")
    return load_obs(folder / "2020_06_03_TST_03.obs"), navs


@pytest.mark.filterwarnings("ignore")
def test_static_wrong_header_gives_the_same_fixes(shared_data):
    # real data: a foreign (Berlin) or antipodal header position gave 0 fixes; now the fixes of the true header
    from dataclasses import replace
    obs, navs = _static_obs(shared_data)
    obs = replace(obs, time_gps_s=obs.time_gps_s[:120], pr_m=obs.pr_m[:120], cn0_dbhz=obs.cn0_dbhz[:120],
                  doppler_hz=obs.doppler_hz[:120])
    good = lfgnss.spp(lfgnss.load(obs, navs))
    assert np.all(good.ok)
    for header in (BERLIN_ECEF_M, -obs.approx_ecef_m):
        fix = lfgnss.spp(lfgnss.load(replace(obs, approx_ecef_m=header), navs))
        assert np.all(fix.ok), fix.summary()
        np.testing.assert_allclose(fix.pos_ecef_m, good.pos_ecef_m, atol=1e-3)
        np.testing.assert_array_equal(fix.used, good.used)


@pytest.mark.filterwarnings("ignore")
@pytest.mark.parametrize("n_bds", [4, 5])
def test_static_no_gps_epochs_match_beidou_only_run(shared_data, n_bds):
    # real data, G+C run with GPS removed from the first 300 epochs and n_bds BeiDou satellites kept: those
    # epochs are solved as by the BeiDou-only run (before: too few satellites, or a clock split in two)
    from dataclasses import replace
    obs, navs = _static_obs(shared_data)
    gps = np.char.startswith(obs.sv.astype(str), "G")
    keep = np.isin(obs.sv, ["C07", "C08", "C13", "C23", "C27"][:n_bds])
    pr = np.where(gps | keep, obs.pr_m, np.nan)
    pr[:300, gps] = np.nan
    fix = lfgnss.spp(lfgnss.load(replace(obs, pr_m=pr), navs, systems=("G", "C")))
    fix_c = lfgnss.spp(lfgnss.load(replace(obs, pr_m=np.where(keep, pr, np.nan)), navs, systems=("C",)))
    assert np.all(fix_c.ok[:300]) and np.all(fix.ok[:300])
    np.testing.assert_allclose(fix.pos_ecef_m[:300], fix_c.pos_ecef_m[:300], atol=1e-3)
    np.testing.assert_allclose(fix.clock_m[:300, 0], fix_c.clock_m[:300, 0], atol=1e-3)
    np.testing.assert_array_equal(fix.clock_m[:300, 1], 0.0)
    assert np.all(np.isfinite(fix.clock_m[300:][fix.ok[300:]]))       # with GPS back: clock and BeiDou ISB


def test_sequence_coarse_clock_fills_isbs_only_from_epochs_with_the_reference_system():
    """Epoch 0 without GPS: spp's clock there is BeiDou's (ISB 0); the sequence takes GPS epochs' ISB and
    brings the clock back to GPS, so the EKF starts from one consistent clock and ISB in every epoch."""
    meas, truth, clock = _synthetic(n_epochs=4)
    meas = _without(meas, [(0, slice(0, 7))])
    fix = lfgnss.spp(meas)
    np.testing.assert_allclose(fix.clock_m[0], [clock - 87.25, 0.0], atol=1e-3)
    seq = lfgnss.build_sequence(meas, fix)
    np.testing.assert_allclose(seq.coarse_clock_m, [[clock, -87.25]] * 4, atol=1e-3)
