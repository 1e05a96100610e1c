"""lfgnss.ephemeris / lfgnss.glonass: satellite states from broadcast ephemerides, checked against RTKLIB."""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from lfgnss.constants import SPEED_OF_LIGHT_M_S
from lfgnss.ephemeris import MAX_AGE_S, SatelliteStates, ephemeris_states, satellite_states
from lfgnss.glonass import propagate
from lfgnss.navigation import Navigation, load_nav
from lfgnss.time import datetime64_to_gps_s, week_tow_to_gps_s

from rtklib import run_satposs
from test_navigation import GLONASS_RINEX2, GPS_RINEX2

HK2019 = "urbannav-hk-tst-20190428"
BERLIN = "smartloc-berlin-potsdamer-platz-rinex"
STATIC = "hk-tst-static-20200603"
SMARTLOC = "smartloc-berlin-potsdamer-platz"

# The rnx2rtkp trace gives positions to 1 mm and times to 1 us (4 mm of satellite motion at most),
# clocks to 1 ps. The brief asks for 0.1 m / 1 ns; we hold the implementation to the trace resolution.
POS_TOL_M = 0.01
CLOCK_TOL_S = 1e-11


def _t(stamp: str) -> float:
    return float(datetime64_to_gps_s(np.datetime64(stamp, "ns")))


@pytest.fixture
def bundled_nav(tmp_path) -> Navigation:
    n, g = tmp_path / "brdc1580.16n", tmp_path / "brdc1580.16g"
    n.write_text(GPS_RINEX2)
    g.write_text(GLONASS_RINEX2)
    return load_nav([n, g])


# ---------------------------------------------------------------- RTKLIB, no shared data needed
def test_bundled_records_match_rtklib(bundled_nav):
    """Two lines of an rnx2rtkp 2.4.3 b34 trace (berlin, epoch 2016/06/06 11:12:00, see
    test_rtklib_satposs for the command), for the two records bundled in test_navigation:

    4 2016/06/06 11:11:59.921241 sat= 2 rs= 14010799.828  22338045.766   5056901.819 dts=  587216.842 ...
    4 2016/06/06 11:11:59.924371 sat=33 rs=  9511950.577 -19561727.864  13343354.612 dts= -142797.828 ...
    """
    st = ephemeris_states(bundled_nav, np.array(["G02", "R01"]),
                          np.array([_t("2016-06-06T11:11:59.921241"), _t("2016-06-06T11:11:59.924371")]))
    assert st.ok.all()
    np.testing.assert_allclose(st.pos_ecef_m, [[14010799.828, 22338045.766, 5056901.819],
                                               [9511950.577, -19561727.864, 13343354.612]], rtol=0, atol=POS_TOL_M)
    np.testing.assert_allclose(st.clock_s, [587216.842e-9, -142797.828e-9], rtol=0, atol=CLOCK_TOL_S)
    assert st.group_delay_s[0] == pytest.approx(-0.200234353542e-7) and st.group_delay_s[1] == 0.0


# ---------------------------------------------------------------- RTKLIB on every shared dataset
DATASETS = {
    # id: (folder, obs, nav files, rnx2rtkp -sys, start, end, -ti, systems that must be compared)
    "hk2019-G-C": (HK2019, "COM3_190428_124409.obs", ["hksc1180.19n", "hksc1180.19b"], "G,C",
                   "2019/04/28 12:44:30", "2019/04/28 13:14:00", 30, {"G", "C"}),
    "berlin-rinex2-G-R": (BERLIN, "Berlin_Potsdamer_Platz.obs", ["brdc1580.16n", "brdc1580.16g"], "G,R",
                          "2016/06/06 11:10:40", "2016/06/06 11:15:30", 10, {"G", "R"}),
    "berlin-mixed-G-R": (BERLIN, "Berlin_Potsdamer_Platz.obs", ["BRDC00WRD_U_20161580000_01D_MN.rnx"], "G,R",
                         "2016/06/06 11:10:40", "2016/06/06 11:15:30", 10, {"G", "R"}),
    "static-G-R-E-J-C": (STATIC, "2020_06_03_TST_03.obs",
                         [f"hksc155{h}.20{x}" for h in "cd" for x in "nglb"], "G,R,E,J,C",
                         "2020/06/03 03:02:20", "2020/06/03 03:19:00", 30, {"G", "R", "E", "C"}),
}


@pytest.mark.shared_data
@pytest.mark.parametrize("case", list(DATASETS), ids=list(DATASETS))
def test_rtklib_satposs(case, shared_data, rnx2rtkp, tmp_path):
    """Positions and clocks equal RTKLIB's ``satposs`` at the same transmission times.

    Command (e.g. hk2019; see tests/rtklib.py ``run_satposs``):
        rnx2rtkp -p 0 -x 4 -sys G,C -ts 2019/04/28 12:44:30 -te 2019/04/28 13:14:00 -ti 30
                 -o OUT.pos COM3_190428_124409.obs hksc1180.19n hksc1180.19b
    and the ``satposs`` lines of OUT.pos.trace. Ephemerides are chosen at the epoch time stamp
    (``teph``) like RTKLIB. QZSS: the static set has J observations but no QZSS navigation file,
    so neither RTKLIB nor lfgnss has a J state (checked below; QZSS maths = GPS, see
    test_qzss_is_computed_like_gps).
    """
    folder, obs, navs, systems, start, end, ti, expect = DATASETS[case]
    root = shared_data(folder)
    nav_paths = [root / n for n in navs]
    trace, _cmd = run_satposs(root / obs, nav_paths, tmp_path, start, end, systems, ti)
    nav = load_nav(nav_paths)
    st = ephemeris_states(nav, trace.sv, trace.t_tx_gps_s, t_select_gps_s=trace.t_rx_gps_s)
    system = np.char.ljust(trace.sv, 1).astype("<U1")
    assert set(system) == expect
    assert np.all(np.isin(st.reason, ["", "unhealthy"]))
    np.testing.assert_array_equal(st.health != 0, trace.svh != 0)
    for s in expect:
        m = system == s
        assert m.sum() >= 20, f"too few {s} rows to compare"
        dpos = np.linalg.norm(st.pos_ecef_m[m] - trace.pos_ecef_m[m], axis=1)
        dclk = np.abs(st.clock_s[m] - trace.clock_s[m])
        assert dpos.max() < POS_TOL_M, f"{case} {s}: max position difference {dpos.max():.4f} m"
        assert dclk.max() < CLOCK_TOL_S, f"{case} {s}: max clock difference {dclk.max() * 1e9:.4f} ns"


def _berlin_obs_c1(root):
    """C1 pseudoranges of the berlin RINEX 2 obs (georinex), epochs as GPS seconds."""
    import georinex

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        obs = georinex.load(root / "Berlin_Potsdamer_Platz.obs", meas=["C1"])
    return datetime64_to_gps_s(obs.time.values), np.asarray(obs.sv.values).astype("<U3"), obs["C1"].values


@pytest.mark.shared_data
def test_satellite_states_transmission_time_matches_rtklib(shared_data, rnx2rtkp, tmp_path):
    """End to end (``satposs``): from (epoch, C1) to transmission time, position and clock.

        rnx2rtkp -p 0 -x 4 -sys G,R -ts 2016/06/06 11:10:40 -te 2016/06/06 11:15:30 -ti 10 -o OUT.pos
                 Berlin_Potsdamer_Platz.obs brdc1580.16n brdc1580.16g
    """
    root = shared_data(BERLIN)
    navs = [root / "brdc1580.16n", root / "brdc1580.16g"]
    trace, _ = run_satposs(root / "Berlin_Potsdamer_Platz.obs", navs, tmp_path,
                           "2016/06/06 11:10:40", "2016/06/06 11:15:30", "G,R", 10)
    t_obs, sv_obs, c1 = _berlin_obs_c1(root)
    ti = np.argmin(np.abs(t_obs[None, :] - trace.t_rx_gps_s[:, None]), axis=1)   # teph is printed to 1 ms
    assert np.abs(t_obs[ti] - trace.t_rx_gps_s).max() < 1e-3
    pr = c1[ti, np.searchsorted(sv_obs, trace.sv)]
    st = satellite_states(load_nav(navs), trace.sv, t_obs[ti], pr)
    assert st.ok.all()
    assert np.abs(st.t_tx_gps_s - trace.t_tx_gps_s).max() < 1e-6                # trace resolution 1 us
    assert np.linalg.norm(st.pos_ecef_m - trace.pos_ecef_m, axis=1).max() < POS_TOL_M
    assert np.abs(st.clock_s - trace.clock_s).max() < CLOCK_TOL_S


# ---------------------------------------------------------------- smartLoc preprocessed positions
@pytest.mark.shared_data
def test_smartloc_satellite_positions(shared_data):
    """smartLoc ``pseudorange3`` satellite positions vs ours (GPS brdc1580.16n, GLONASS .16g).

    What we found about their convention (all 20038 rows, 1372 epochs):
    - No Sagnac rotation: positions are in the ECEF frame of the transmission time, as ours. Rotating
      ours into the reception-time frame makes the median difference 100 m, evaluating at the
      reception time 200+ m; unrotated it is 1.7 m (GPS) / 2.0 m (GLONASS).
    - Their transmission time is ours (t_rx - C1/c - dts) plus 0 or 1 ms, common to all satellites of
      an epoch (43 % of epochs at +1 ms): the u-blox receiver clock's millisecond jumps, which they
      applied and RTKLIB's convention (receiver stamp minus pr/c) does not need.
    - The rest is a constant offset per satellite, 0.4-2.2 m for GPS and up to 4.5 m for GLONASS,
      mostly radial/along-track, stable to a few cm over the 5 minutes: a different orbit product
      (the upstream Readme lists SP3 precise orbits; broadcast minus precise is of that size).
    Hence: raw 3-D difference < 5 m (max 4.7 m GPS, 4.8 m GLONASS); after removing each epoch's common
    time offset (asserted to be 0 or 1 ms within 0.05 ms) and each satellite's mean offset, residuals
    < 0.1 m GPS (max 0.07) and < 0.25 m GLONASS (max 0.18: broadcast-minus-precise drift over 5 min).
    """
    text = (shared_data(SMARTLOC) / "Berlin_Potsdamer_Platz_Input.txt").read_text()
    rows = [ln.split() for ln in text.splitlines() if ln.startswith("pseudorange3")]
    a = np.array([[float(x) for x in r[1:10]] for r in rows])
    t_rel, ref_pos, sat_id, system_code = np.round(a[:, 0], 1), a[:, 3:6], a[:, 6].astype(int), a[:, 7].astype(int)
    assert set(system_code) == {1, 4}
    sv = np.array([f"G{i:02d}" if s == 1 else f"R{i - 300:02d}" for i, s in zip(sat_id, system_code)])

    root = shared_data(BERLIN)
    t_obs, sv_obs, c1 = _berlin_obs_c1(root)
    t_stamp = week_tow_to_gps_s(1900, 126641.7) + t_rel                # SOURCE.md time alignment
    ti = np.searchsorted(np.round(t_obs, 1), np.round(t_stamp, 1))
    assert np.all(np.round(t_obs[ti], 1) == np.round(t_stamp, 1))
    pr = c1[ti, np.searchsorted(sv_obs, sv)]
    st = satellite_states(load_nav([root / "brdc1580.16n", root / "brdc1580.16g"]), sv, t_obs[ti], pr)
    assert st.ok.all()

    d = ref_pos - st.pos_ecef_m
    is_gps = np.char.startswith(sv, "G")
    raw = np.linalg.norm(d, axis=1)
    assert raw[is_gps].max() < 5.0 and raw[~is_gps].max() < 5.0
    assert np.median(raw[is_gps]) < 2.5 and np.median(raw[~is_gps]) < 2.5

    v = st.vel_ecef_m_s
    dt = np.sum(d * v, axis=1) / np.sum(v * v, axis=1)                   # along-track offset as a time
    for s in np.unique(sv):
        dt[sv == s] -= np.median(dt[sv == s])
    epochs, idx = np.unique(t_rel, return_inverse=True)
    offset = np.array([np.median(dt[idx == i]) for i in range(len(epochs))])
    assert np.all(np.minimum(np.abs(offset), np.abs(offset - 1e-3)) < 5e-5)
    r = d - offset[idx][:, None] * v
    resid = np.zeros(len(sv))
    for s in np.unique(sv):
        m = sv == s
        resid[m] = np.linalg.norm(r[m] - r[m].mean(axis=0), axis=1)
    assert resid[is_gps].max() < 0.1
    assert resid[~is_gps].max() < 0.25


# ---------------------------------------------------------------- physics
@pytest.fixture(scope="module")
def hk_nav(shared_data):
    root = shared_data(HK2019)
    return load_nav([root / "hksc1180.19n", root / "hksc1180.19b"])


def _grid(nav, prefix, hours=20.0, step=300.0):
    """All satellites of one kind on a time grid over 2019-04-28, the day of the hk files (flat arrays)."""
    svs = np.unique(nav.kepler.sv[np.char.startswith(nav.kepler.sv, prefix)])
    t = _t("2019-04-28T00:00:00") + np.arange(0.0, hours * 3600, step)
    return np.repeat(svs, len(t)), np.tile(t, len(svs))


@pytest.mark.shared_data
def test_orbit_radii_speeds_and_relativity(hk_nav):
    sv, t = _grid(hk_nav, "G")
    st = ephemeris_states(hk_nav, sv, t)
    ok = st.ok
    assert ok.sum() > 1000
    k = hk_nav.kepler
    sel = np.array([np.flatnonzero((k.sv == s) & (k.toe_gps_s == toe))[-1] for s, toe in zip(sv[ok], st.toe_gps_s[ok])])
    a = k.sqrt_a_sqrt_m[sel] ** 2
    assert np.all(np.abs(a - 26_560e3) < 50e3)
    r = np.linalg.norm(st.pos_ecef_m[ok], axis=1)
    assert np.all(np.abs(r - a) <= a * k.e[sel] + 2e3)                 # r = a (1 - e cos E) + harmonics
    speed = np.linalg.norm(st.vel_ecef_m_s[ok], axis=1)
    assert np.all((speed > 2.5e3) & (speed < 4.0e3))                  # 3.9 km/s inertial, less in ECEF
    dt = t[ok] - k.toc_gps_s[sel]
    rel = st.clock_s[ok] - (k.af0_s[sel] + k.af1_s_s[sel] * dt + k.af2_s_s2[sel] * dt**2)
    bound = 2 * np.sqrt(3.986005e14 * k.sqrt_a_sqrt_m[sel] ** 2) * k.e[sel] / SPEED_OF_LIGHT_M_S**2
    assert np.all(np.abs(rel) <= bound * (1 + 1e-9)) and np.abs(rel).max() > 10e-9   # tens of ns

    sv, t = _grid(hk_nav, "C")
    st = ephemeris_states(hk_nav, sv, t)
    geo = np.isin(sv, ["C01", "C02", "C03", "C04", "C05"]) & st.ok
    r = np.linalg.norm(st.pos_ecef_m[geo], axis=1)
    assert geo.sum() > 100 and np.all(np.abs(r - 42_164e3) < 200e3)
    assert np.all(np.linalg.norm(st.vel_ecef_m_s[geo], axis=1) < 200.0)   # nearly fixed in ECEF


@pytest.mark.shared_data
def test_velocity_is_derivative_of_position(hk_nav):
    """Velocity (central difference, +-1 s) agrees with positions 60 s apart, GEO included, to the
    size of the third-order term r n^3 (30 s)^2 / 6 ~ 0.01 m/s (a naive Keplerian GEO velocity is off by
    4-10 m/s)."""
    sv, t = _grid(hk_nav, "C", hours=6.0, step=900.0)
    st = ephemeris_states(hk_nav, sv, t)
    plus = ephemeris_states(hk_nav, sv, t + 30.0, t_select_gps_s=t)
    minus = ephemeris_states(hk_nav, sv, t - 30.0, t_select_gps_s=t)
    ok = st.ok & plus.ok & minus.ok
    v_fd = (plus.pos_ecef_m - minus.pos_ecef_m)[ok] / 60.0
    assert np.abs(v_fd - st.vel_ecef_m_s[ok]).max() < 0.02
    drift_fd = (plus.clock_s - minus.clock_s)[ok] / 60.0
    assert np.abs(drift_fd - st.clock_drift_s_s[ok]).max() < 1e-14


# ---------------------------------------------------------------- selection
@pytest.mark.shared_data
def test_selection_refuses_other_days_and_expired(hk_nav):
    k = hk_nav.kepler
    toe = k.toe_gps_s[k.sv == "G05"]
    sv = np.array(["G05"] * 5 + ["G99", "S20", "G05"])
    t = np.array([toe.max() + 86400.0, toe.min() - 86400.0, toe.max() + MAX_AGE_S["G"],
                  toe.max() + MAX_AGE_S["G"] + 1.0, toe.max(), toe.max(), toe.max(), np.nan])
    st = ephemeris_states(hk_nav, sv, t)
    assert st.reason.tolist() == ["ephemeris expired", "no ephemeris", "", "ephemeris expired", "",
                                  "no ephemeris", "no ephemeris", "invalid time"]
    assert st.ok.tolist() == [r == "" for r in st.reason]
    assert np.isnan(st.pos_ecef_m[~st.ok]).all() and np.isfinite(st.pos_ecef_m[st.ok]).all()


@pytest.mark.shared_data
def test_unhealthy_is_computed_but_not_ok(hk_nav):
    k = hk_nav.kepler
    i = np.flatnonzero(k.health != 0)[0]
    st = ephemeris_states(hk_nav, k.sv[i:i + 1], k.toe_gps_s[i:i + 1])
    assert st.reason[0] == "unhealthy" and not st.ok[0] and np.isfinite(st.pos_ecef_m).all()


@pytest.mark.shared_data
def test_galileo_uses_past_toe_only(shared_data):
    root = shared_data(STATIC)
    nav = load_nav([root / "hksc155c.20l"])
    k = nav.kepler
    toe = np.sort(k.toe_gps_s[k.sv == "E02"])
    t = np.array([toe[0] - 1.0, toe[3] + 240.0, toe[3] + 360.0])
    st = ephemeris_states(nav, np.array(["E02"] * 3), t)
    assert st.reason[0] == "no ephemeris"                               # only a future toe
    assert st.toe_gps_s[1] == toe[3] and st.toe_gps_s[2] == toe[3]      # not the nearer toe[4]


@pytest.mark.shared_data
def test_broadcast_accuracies_are_read_and_exclude_nothing_in_the_data(shared_data):
    """URA (GPS, BeiDou ``SVacc``) and SISA (Galileo) come from the files; none of the benchmark data's records is
    excluded by them."""
    root = shared_data(STATIC)
    nav = load_nav([root / "hksc155c.20n", root / "hksc155c.20l", root / "hksc155c.20b"])
    k = nav.kepler
    assert set(k.accuracy_m[k.system == "G"]) <= {2.0, 2.8} and set(k.accuracy_m[k.system == "E"]) == {3.12}
    assert set(k.accuracy_m[k.system == "C"]) == {2.0}
    assert not ephemeris_states(nav, k.sv, k.toe_gps_s + 1.0).reason.tolist().count("inaccurate ephemeris")


def test_order_invariance_and_shapes(bundled_nav):
    sv = np.array(["G02", "R01", "G02", "E11", "R01"])
    t = _t("2016-06-06T11:12:00") + np.array([0.0, 1.0, 600.0, 5.0, -900.0])
    a = ephemeris_states(bundled_nav, sv, t)
    p = np.array([4, 2, 0, 3, 1])
    b = ephemeris_states(bundled_nav, sv[p], t[p])
    np.testing.assert_array_equal(a.pos_ecef_m[p], b.pos_ecef_m)
    np.testing.assert_array_equal(a.reason[p], b.reason)
    assert isinstance(a, SatelliteStates) and a.pos_ecef_m.shape == (5, 3) and len(a) == 5
    assert a.reason[3] == "no ephemeris"
    with pytest.raises(ValueError):
        ephemeris_states(bundled_nav, sv, t[:3])
    empty = satellite_states(bundled_nav, np.array([], "<U3"), np.array([]), np.array([]))
    assert len(empty) == 0 and empty.pos_ecef_m.shape == (0, 3)


def test_transmission_time_identity(bundled_nav):
    """t_rx - t_tx = pr/c + clock polynomial (no relativity), as RTKLIB ``satposs``."""
    sv = np.array(["G02", "R01"])
    t_rx = np.full(2, _t("2016-06-06T11:12:00"))
    pr = np.array([2.1e7, 2.3e7])
    st = satellite_states(bundled_nav, sv, t_rx, pr)
    k, g = bundled_nav.kepler, bundled_nav.glonass
    dt = st.t_tx_gps_s[0] - k.toc_gps_s[0]
    poly_g = k.af0_s[0] + k.af1_s_s[0] * dt + k.af2_s_s2[0] * dt**2
    poly_r = -g.tau_n_s[0] + g.gamma_n[0] * (st.t_tx_gps_s[1] - g.toe_gps_s[0])
    # GPS seconds since 1980 as float64 resolve 2.4e-7 s (0.9 mm of satellite motion): compare to 0.5 us
    np.testing.assert_allclose(t_rx - st.t_tx_gps_s - pr / SPEED_OF_LIGHT_M_S, [poly_g, poly_r], rtol=0, atol=5e-7)


def test_qzss_is_computed_like_gps(bundled_nav):
    """No dataset has QZSS navigation data: relabel the GPS record as J02 and expect GPS results."""
    k = bundled_nav.kepler
    qzss = dataclasses.replace(bundled_nav, kepler=dataclasses.replace(
        k, sv=np.array(["J02"]), system=np.array(["J"])))
    t = np.array([_t("2016-06-06T11:12:00")])
    a = ephemeris_states(bundled_nav, np.array(["G02"]), t)
    b = ephemeris_states(qzss, np.array(["J02"]), t)
    np.testing.assert_array_equal(a.pos_ecef_m, b.pos_ecef_m)
    assert b.ok[0] and b.clock_s[0] == a.clock_s[0]


def _relabelled(nav: Navigation, sv: str, **fields) -> Navigation:
    """The bundled GPS record as satellite ``sv`` with ``fields`` replaced (one value each)."""
    k = nav.kepler
    changes = {"sv": np.array([sv]), "system": np.array([sv[0]])} | {
        key: np.array([value]) for key, value in fields.items()}
    return dataclasses.replace(nav, kepler=dataclasses.replace(k, **changes))


def test_qzss_health_ignores_the_l6_bit(bundled_nav):
    """RTKLIB masks QZSS health bit 0 (L6/LEX, not L1 C/A: ``svh &= 0xFE``); any other bit still excludes."""
    t = np.array([_t("2016-06-06T11:12:00")])
    for health, reason in ((1, ""), (0x21, "unhealthy"), (0x20, "unhealthy")):
        nav = _relabelled(bundled_nav, "J02", health=health)
        assert ephemeris_states(nav, np.array(["J02"]), t).reason[0] == reason
    assert ephemeris_states(_relabelled(bundled_nav, "G02", health=1), np.array(["G02"]), t).reason[0] == "unhealthy"


@pytest.mark.parametrize("sv, accuracy_m, reason", [
    ("G02", 192.0, ""), ("G02", 193.0, "inaccurate ephemeris"), ("G02", 384.0, "inaccurate ephemeris"),
    ("C11", 6144.0, "inaccurate ephemeris"), ("J02", 2.0, ""), ("G02", 0.0, ""),      # 0: the field was absent
    ("E11", 3.12, ""), ("E11", 6.0, ""), ("E11", -1.0, "inaccurate ephemeris"), ("E11", 6.5, "inaccurate ephemeris"),
])
def test_broadcast_accuracy_excludes_as_rtklib_does(bundled_nav, sv, accuracy_m, reason):
    """RTKLIB excludes an ephemeris whose variance exceeds 300^2 m^2: a URA of 384 m or more in its table (above 192
    m), a Galileo SISA with no accuracy prediction (-1) or above 6 m (both 500 m)."""
    nav = _relabelled(bundled_nav, sv, accuracy_m=accuracy_m)
    st = ephemeris_states(nav, np.array([sv]), nav.kepler.toe_gps_s + 60.0)
    assert st.reason[0] == reason and st.ok[0] == (reason == "") and np.isfinite(st.pos_ecef_m).all()


def test_galileo_ephemerides_serve_four_hours(bundled_nav):
    """rnx2rtkp 2.4.3 b34 takes a Galileo record up to 4 h after its toe (MAXDTOE_GAL 14400 s; 2.4.2 had 3 h)."""
    nav = _relabelled(bundled_nav, "E11")
    toe = nav.kepler.toe_gps_s[0]
    st = ephemeris_states(nav, np.array(["E11"] * 3), toe + np.array([3.5 * 3600, MAX_AGE_S["E"], MAX_AGE_S["E"] + 1]))
    assert MAX_AGE_S["E"] == 14400.0 and st.reason.tolist() == ["", "", "ephemeris expired"]


def test_clock_polynomial_is_rtklibs_fixed_point(bundled_nav):
    """t = ts - dts(t), twice from ts (RTKLIB eph2clk, geph2clk); a large af1 shows a step from the wrong start."""
    from lfgnss.ephemeris import _clock_polynomial_s

    nav = _relabelled(bundled_nav, "G02", af0_s=1e-3, af1_s_s=1e-6, af2_s_s2=1e-12)
    nav = dataclasses.replace(nav, glonass=dataclasses.replace(nav.glonass, tau_n_s=np.full(len(nav.glonass.sv), 1e-3),
                                                               gamma_n=np.full(len(nav.glonass.sv), 1e-6)))
    k, g = nav.kepler, nav.glonass
    t_sv = np.array([k.toc_gps_s[0] + 1000.0, g.toe_gps_s[0] + 100.0])
    got = _clock_polynomial_s(nav, np.array(["G02", g.sv[0]]), t_sv, t_sv)
    ts = t_sv[0] - k.toc_gps_s[0]
    t = ts
    for _ in range(2):
        t = ts - (1e-3 + 1e-6 * t + 1e-12 * t * t)
    assert got[0] == pytest.approx(1e-3 + 1e-6 * t + 1e-12 * t * t, abs=1e-14)
    ts = t_sv[1] - g.toe_gps_s[0]
    t = ts
    for _ in range(2):
        t = ts - (-1e-3 + 1e-6 * t)
    assert got[1] == pytest.approx(-1e-3 + 1e-6 * t, abs=1e-14)


def test_a_glonass_channel_written_as_an_unsigned_byte_is_read_as_rtklib_does(tmp_path):
    """k = 1 in the bundled record; 255 is -1 (RTKLIB decode_geph: frq > 128 -> frq - 256)."""
    path = tmp_path / "k.16g"
    path.write_text(GLONASS_RINEX2.replace("0.279396772385D-08 0.100000000000D+01",
                                           "0.279396772385D-08 0.255000000000D+03"))
    assert load_nav([path]).glonass.k.tolist() == [-1]


# ---------------------------------------------------------------- GLONASS integrator
def test_glonass_rk4_step_size_and_reversibility(bundled_nav):
    g = bundled_nav.glonass
    dt = np.array([1800.0])
    p60, v60 = propagate(g.pos_ecef_m, g.vel_ecef_m_s, g.acc_ecef_m_s2, dt)
    p5, v5 = propagate(g.pos_ecef_m, g.vel_ecef_m_s, g.acc_ecef_m_s2, dt, step_s=5.0)
    assert np.linalg.norm(p60 - p5) < 0.01 and np.linalg.norm(v60 - v5) < 1e-5
    back, _ = propagate(p60, v60, g.acc_ecef_m_s2, -dt)
    assert np.linalg.norm(back - g.pos_ecef_m) < 1e-3
    r = np.linalg.norm(p60)
    assert 25.3e6 < r < 25.7e6                                            # GLONASS a = 25,510 km
    same, _ = propagate(g.pos_ecef_m, g.vel_ecef_m_s, g.acc_ecef_m_s2, np.array([0.0]))
    np.testing.assert_array_equal(same, g.pos_ecef_m)


# ---------------------------------------------------------------- BeiDou B1I labels and group delays
@pytest.mark.shared_data
def test_bds_b1i_labelled_c2i_in_rinex302_gets_tgd1(shared_data, tmp_path):
    """hk-tst-2019 (RINEX 3.03, B1I = C2I) relabelled 3.02: BeiDou was dropped ('no supported pseudorange type')
    while RTKLIB solves it. Now the same B1I pseudoranges, with the B1I group delay TGD1 of the ephemeris used."""
    import lfgnss

    src = shared_data(f"{HK2019}/COM3_190428_124409.obs")
    navs = [shared_data(f"{HK2019}/hksc1180.19n"), shared_data(f"{HK2019}/hksc1180.19b")]
    text = src.read_text()
    assert text.startswith("     3.03")
    relabelled = tmp_path / "v302.obs"
    relabelled.write_text("     3.02" + text[9:])
    ref = lfgnss.load(src, navs)
    meas = lfgnss.load(relabelled, navs)
    assert meas.obs.codes == ref.obs.codes == {"G": "C1C", "C": "C2I"}
    assert meas.systems == ("G", "C")
    for name in ("pr_m", "sat_clock_s", "group_delay_s", "reason"):
        np.testing.assert_array_equal(getattr(meas, name), getattr(ref, name), err_msg=name)
    is_c = np.array([s[0] == "C" for s in meas.sv])
    t, s = np.nonzero(np.isfinite(meas.pr_m) & is_c[None, :] & (meas.reason == 0))
    assert t.size > 1000
    states = satellite_states(meas.nav, meas.sv[s], meas.time_gps_s[t], meas.pr_m[t, s])
    kep = meas.nav.kepler
    tgd1: dict[tuple[str, float], set[float]] = {}
    for sv, toe, tgd in zip(kep.sv, kep.toe_gps_s, kep.tgd_s):   # BeiDou records: TGD1 (B1I), see navigation.py
        tgd1.setdefault((sv, toe), set()).add(tgd)
    got = meas.group_delay_s[t, s]
    assert all(g in tgd1[(sv, toe)] for g, sv, toe in zip(got, meas.sv[s], states.toe_gps_s))
    assert np.any(got != 0.0)


def test_a_damaged_qzss_record_flagged_in_its_l6_bit_alone_is_still_skipped(tmp_path):
    """A record flagged unhealthy escapes the plausibility check (a placeholder); QZSS's L6 bit does not count as
    unhealthy, so such a record with an impossible orbit must not escape it (it gave a satellite at 2.7e25 m)."""
    from lfgnss.errors import RinexError
    from test_navigation import GPS_REC_V3, _nav3

    rec = [ln.replace("G02", "J02").replace("0.515357678223D+04", "0.515357678223D+13")
           .replace(" 0.000000000000D+00-0.200234353542D-07", " 0.100000000000D+01-0.200234353542D-07")
           for ln in GPS_REC_V3]
    assert rec != GPS_REC_V3
    with pytest.raises(RinexError, match="every record impossible, e.g. 1 J02 record"):
        load_nav(_nav3(tmp_path / "j.rnx", "3.04", [rec], "J: QZSS"))
