"""Feature packer: DPC against brute force on real epochs, masking, one feature source for all consumers."""
import numpy as np
import pytest

import lfgnss
from lfgnss.dop import dop
from lfgnss.features import AVAILABLE_FEATURES, check_feature_names
from lfgnss.sequence import DEFAULT_FEATURES
from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS


@pytest.fixture(scope="module")
def sample():
    meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
    fix = lfgnss.spp(meas)
    return meas, fix, lfgnss.build_sequence(meas, fix)


def test_shapes_finite_and_masked(sample):
    _, _, seq = sample
    assert seq.features.shape == (len(seq), seq.n_slots, 8)
    assert seq.feature_names == DEFAULT_FEATURES
    assert np.all(np.isfinite(seq.features))
    assert np.all(seq.features[~seq.mask] == 0.0)
    assert np.all(seq.mask.sum(1) >= 4)
    cn0, el = seq.features[..., 0][seq.mask], seq.features[..., 1][seq.mask]
    assert np.all((cn0 >= 20) & (cn0 < 60)) and np.all(el >= np.radians(10) - 1e-9)


def test_dpc_matches_brute_force_leave_one_out(sample):
    _, _, seq = sample
    names = list(seq.feature_names)
    epochs = np.linspace(0, len(seq) - 1, 25).astype(int)
    n_sys = len(seq.systems)
    for t in epochs:
        m = seq.mask[t]
        el, az, si = seq.el_rad[t][None], seq.az_rad[t][None], seq.system_index[t][None]
        full = dop(el, az, si, m[None], n_sys)
        for s in np.flatnonzero(m):
            m2 = m.copy()
            m2[s] = False
            loo = dop(el, az, np.where(m2, si, -1), m2[None], n_sys)
            if not loo.valid[0]:
                continue  # singular leave-one-out: capped by design (see lfgnss.dop)
            for k, key in enumerate(("gdop", "pdop", "hdop", "vdop")):
                expected = getattr(full, key)[0] - getattr(loo, key)[0]
                assert seq.features[t, s, names.index(f"dpc_{key}")] == pytest.approx(expected, abs=1e-9)


def test_residual_feature_is_coarse_fix_residual(sample):
    _, fix, seq = sample
    used = fix.used
    np.testing.assert_allclose(seq.features[..., 3][used], fix.residual_m[used])


def test_feature_subset_is_configuration_only(sample):
    meas, fix, seq = sample
    no_dpc = ("cn0", "elevation", "azimuth", "residual")
    sub = lfgnss.build_sequence(meas, fix, feature_names=no_dpc)
    np.testing.assert_array_equal(sub.features, seq.features[..., :4])
    onehot = lfgnss.build_sequence(meas, fix, feature_names=DEFAULT_FEATURES + ("sys_G", "sys_R"))
    g = onehot.features[..., 8][seq.mask]
    r = onehot.features[..., 9][seq.mask]
    assert np.all(g + r == 1.0)
    with pytest.raises(ValueError, match="unknown feature"):
        check_feature_names(("cn0", "snr"))
    assert set(DEFAULT_FEATURES) <= set(AVAILABLE_FEATURES)


def test_padding_never_changes_a_result(sample):
    import estimators

    _, _, seq = sample
    short = seq.subset(slice(0, 150))
    padded = short.pad_to(short.n_slots + 7)
    # junk in the padded slots must not matter
    junk = padded.features.copy()
    junk[:, short.n_slots:] = 1e6
    from dataclasses import replace
    padded = replace(padded, features=junk, pr_m=np.where(padded.mask, padded.pr_m, 3e7))
    for backend in ("ekf", "fgo", "wls"):
        a = estimators.create(backend).solve(short)
        b = estimators.create(backend).solve(padded)
        np.testing.assert_allclose(a.pos_ecef_m, b.pos_ecef_m, atol=1e-6, err_msg=backend)


def test_same_features_for_every_entry_point(sample):
    meas, fix, seq = sample
    again = lfgnss.process(SAMPLE_OBS, SAMPLE_NAV)
    np.testing.assert_array_equal(again.features, seq.features)
    np.testing.assert_array_equal(again.mask, seq.mask)


def test_fill_from_nearest_epoch_is_forward_then_backward_fill():
    """The coarse ISB of an epoch without that system's satellites: the last earlier value, else the next one."""
    from lfgnss.features import fill_from_nearest_epoch

    nan = np.nan
    values = np.array([[nan, 1.0, nan], [2.0, nan, nan], [nan, nan, nan], [3.0, 4.0, nan]])
    expected = np.array([[2.0, 1.0, nan], [2.0, 1.0, nan], [2.0, 1.0, nan], [3.0, 4.0, nan]])
    np.testing.assert_array_equal(fill_from_nearest_epoch(values), expected)
    assert fill_from_nearest_epoch(np.zeros((0, 2))).shape == (0, 2)


def _moving_receiver(n_t: int = 6, n_s: int = 5, dt: float = 0.2):
    """Pseudoranges whose change matches their (linearly changing) rates exactly, plus a receiver clock."""
    t = 1.0e9 + dt * np.arange(n_t)
    rate0 = np.linspace(-600.0, 500.0, n_s)                    # m/s
    accel = np.linspace(-0.5, 0.4, n_s)                        # m/s^2
    clock = 3.0e3 + 40.0 * (t - t[0])                          # receiver clock [m] drifting 40 m/s
    pr = 2.2e7 + rate0 * (t - t[0])[:, None] + 0.5 * accel * (t - t[0])[:, None] ** 2 + clock[:, None]
    prr = rate0 + accel * (t - t[0])[:, None] + 40.0
    return t, pr, prr, np.ones((n_t, n_s), bool)


def test_code_doppler_is_zero_when_code_follows_doppler_and_clock_jumps_cancel():
    from lfgnss.features import CODE_DOPPLER_CAP_M, code_doppler_disagreement_m
    t, pr, prr, ok = _moving_receiver()
    pr[3:] += 299792.458                                       # a 1 ms receiver clock jump, common to all
    d = code_doppler_disagreement_m(t, pr, prr, ok)
    assert np.all(d[0] == CODE_DOPPLER_CAP_M)                  # nothing to compare the first epoch with
    np.testing.assert_allclose(d[1:], 0.0, atol=1e-6)          # trapezoid rule is exact for a linear rate


def test_code_doppler_shows_a_multipath_step_and_caps_what_it_cannot_compare():
    from lfgnss.features import CODE_DOPPLER_CAP_M, CODE_DOPPLER_MAX_GAP_S, code_doppler_disagreement_m
    t, pr, prr, ok = _moving_receiver()
    pr[2:, 1] += 25.0                                          # satellite 1's code jumps 25 m, its Doppler does not
    pr[4:, 3] += 500.0                                         # a step beyond the cap
    ok[2, 4] = False                                           # satellite 4 lost for one epoch
    d = code_doppler_disagreement_m(t, pr, prr, ok)
    np.testing.assert_allclose(d[2, 1], 25.0, atol=1e-6)
    np.testing.assert_allclose(d[[1, 3, 4, 5], 1], 0.0, atol=1e-6)   # only the epoch of the step
    assert d[4, 3] == CODE_DOPPLER_CAP_M
    assert d[2, 4] == CODE_DOPPLER_CAP_M and d[3, 4] == CODE_DOPPLER_CAP_M  # lost, and its first epoch back
    t_gap = t.copy()
    t_gap[5:] += CODE_DOPPLER_MAX_GAP_S                        # a gap in the recording
    assert np.all(code_doppler_disagreement_m(t_gap, pr, prr, ok)[5] == CODE_DOPPLER_CAP_M)


def test_code_doppler_feature_on_the_sample(sample):
    from lfgnss.features import CODE_DOPPLER_CAP_M
    meas, fix, seq = sample
    with_cd = lfgnss.build_sequence(meas, fix, feature_names=DEFAULT_FEATURES + ("code_doppler",))
    np.testing.assert_array_equal(with_cd.features[..., :8], seq.features)
    f = with_cd.features[..., 8]
    assert np.all(f[~with_cd.mask] == 0.0)
    assert np.all((f >= 0.0) & (f <= np.log10(1.0 + CODE_DOPPLER_CAP_M)))
    # an open-sky recording: code and Doppler agree within a few metres for most satellites
    assert np.median(10 ** f[with_cd.mask] - 1.0) < 3.0


def test_innovation_feature_is_a_signed_log():
    """sign(v) ln(1 + |v|): 0 at 0, odd, e - 1 m -> 1; hundreds of metres stay below 7."""
    from lfgnss.features import innovation_feature

    v = np.array([0.0, np.e - 1.0, -(np.e - 1.0), 500.0, -1e3])
    np.testing.assert_allclose(innovation_feature(v), [0.0, 1.0, -1.0, np.log(501.0), -np.log(1001.0)])


def test_heading_is_clockwise_from_north_and_held_while_slow():
    from lfgnss.features import heading_rad
    from lfgnss.frames import enu_rotation, lla_to_ecef

    lat, lon = np.radians(52.5), np.radians(13.37)
    ref = lla_to_ecef(lat, lon, 40.0)
    enu = np.array([[0.0, 0.2, 0.0],             # too slow, before any motion: gets the first heading
                    [0.0, 5.0, 0.3],             # north (a vertical component does not matter)
                    [5.0, 0.0, 0.0],             # east
                    [0.3, 0.3, 0.0],             # slow: keeps east
                    [np.nan, np.nan, np.nan],    # no velocity: keeps east
                    [-3.0, -3.0, 0.0]])          # south-west
    vel = enu @ enu_rotation(lat, lon)
    np.testing.assert_allclose(heading_rad(vel, ref), [0.0, 0.0, np.pi / 2, np.pi / 2, np.pi / 2, -3 * np.pi / 4],
                               atol=1e-12)
    assert np.all(np.isnan(heading_rad(vel[[0, 3]], ref)))   # never moved


def test_cross_street_is_zero_along_and_one_across_the_direction_of_travel():
    from lfgnss.features import CROSS_STREET_UNKNOWN, cross_street

    az = np.radians([[0.0, 90.0, 180.0, 270.0, 45.0]] * 2)
    got = cross_street(az, np.array([0.0, np.nan]))
    np.testing.assert_allclose(got[0], [0.0, 1.0, 0.0, 1.0, np.sqrt(0.5)], atol=1e-12)
    assert np.all(got[1] == CROSS_STREET_UNKNOWN)


def test_cross_street_feature_on_the_sample_follows_the_true_heading(sample):
    """The packed feature (Doppler heading) against the same feature from the bundled ground-truth track."""
    from dataclasses import replace

    from lfgnss.datasets import get, read_smartloc
    from lfgnss.features import cross_street, heading_rad
    from lfgnss.solve import SAMPLE_TRUTH

    meas, fix, seq = sample
    with_cs = lfgnss.build_sequence(meas, fix, feature_names=DEFAULT_FEATURES + ("cross_street",))
    np.testing.assert_array_equal(with_cs.features[..., :8], seq.features)
    f = with_cs.features[..., 8]
    assert np.all(f[~with_cs.mask] == 0.0) and np.all((f >= 0.0) & (f <= 1.0))
    t_truth, truth, _ = read_smartloc(SAMPLE_TRUTH, replace(get("berlin-pp"), time_origin_gps_s=seq.time_gps_s[0]))
    vel = np.gradient(truth, t_truth, axis=0)
    epochs = np.searchsorted(np.round(seq.time_gps_s, 1), np.round(t_truth, 1))
    moving = np.linalg.norm(vel, axis=1) > 3.0
    m = with_cs.mask[epochs] & moving[:, None]
    assert m.any(axis=1).sum() > 1000
    gap = np.abs(cross_street(with_cs.az_rad[epochs], heading_rad(vel, truth[0])) - f[epochs])[m]
    # urban Dopplers put the heading some degrees off (median 4 deg here): a coarse canyon cue, not a compass;
    # a heading off by a uniform random angle would give a median gap near 0.3
    assert np.median(gap) < 0.1 and np.percentile(gap, 75) < 0.2


def test_cross_street_without_dopplers_is_the_unknown_value(sample):
    """A file without Doppler gives no heading: the feature is the neutral constant, never NaN."""
    import dataclasses

    from lfgnss.features import CROSS_STREET_UNKNOWN

    meas, fix, _ = sample
    no_doppler = dataclasses.replace(meas, obs=dataclasses.replace(meas.obs,
                                                                    doppler_hz=np.zeros_like(meas.obs.doppler_hz)))
    seq = lfgnss.build_sequence(no_doppler, fix, feature_names=DEFAULT_FEATURES + ("cross_street",))
    assert not seq.prr_mask.any()
    np.testing.assert_allclose(seq.features[..., 8][seq.mask], CROSS_STREET_UNKNOWN)


def test_track_age_counts_seconds_of_continuous_pseudoranges_and_restarts_after_a_gap():
    from lfgnss.features import TRACK_AGE_CAP_S, track_age_s
    t = np.array([0.0, 1.0, 2.0, 3.0, 6.0, 7.0, 8.0])     # a 3 s hole in the epochs before t = 6
    tracked = np.array([[1, 0], [1, 1], [0, 1], [1, 1], [1, 1], [1, 0], [1, 1]], bool)
    age = track_age_s(t, tracked)
    # satellite 0: tracked from the first epoch (unknown age: the cap), lost, back at t = 3, restarted by the hole
    np.testing.assert_array_equal(age[:, 0], [TRACK_AGE_CAP_S, TRACK_AGE_CAP_S, 0, 0, 0, 1, 2])
    np.testing.assert_array_equal(age[:, 1], [0, 0, 1, 2, 0, 0, 0])
    long = track_age_s(np.arange(100.0), np.vstack([np.zeros((1, 1), bool), np.ones((99, 1), bool)]))
    assert long[1, 0] == 0 and long[-1, 0] == TRACK_AGE_CAP_S


def test_cn0_std_is_the_spread_over_the_last_seconds_of_the_current_track():
    from lfgnss.features import CN0_STD_WINDOW_S, cn0_std_dbhz
    t = np.arange(12.0)
    cn0 = np.array([40.0, 42.0, 40.0, 42.0, 40.0, 42.0, 30.0, 30.0, 30.0, 30.0, 30.0, 30.0])[:, None]
    tracked = np.ones((12, 1), bool)
    tracked[6] = False                                     # a lost epoch: the track restarts at t = 7
    std = cn0_std_dbhz(t, cn0, tracked)[:, 0]
    assert std[0] == 0.0 and std[1] == pytest.approx(1.0)
    assert std[5] == pytest.approx(np.std(cn0[6 - int(CN0_STD_WINDOW_S):6, 0]))   # the last 5 s only
    assert std[6] == 0.0 and np.all(std[7:] == 0.0)        # a steady new track: no spread from the old one


def test_cn0_std_leaves_a_missing_cn0_out():
    """A blank C/N0 inside a steady track is not read as 0 dB-Hz (which gave 18 dB-Hz of spread for 5 s)."""
    from lfgnss.features import cn0_std_dbhz
    t = np.arange(10.0)
    cn0 = np.full((10, 1), 45.0)
    cn0[4] = np.nan
    assert np.all(cn0_std_dbhz(t, cn0, np.ones((10, 1), bool)) == 0.0)
    cn0[5:] = 47.0                                          # the spread of the known values in the window
    assert cn0_std_dbhz(t, cn0, np.ones((10, 1), bool))[6, 0] == pytest.approx(np.std([45.0, 45.0, 47.0, 47.0]))


def test_epochs_without_a_fix_take_the_last_earlier_fix_never_a_later_one():
    """Features stay causal: an epoch without a coarse fix is built at the last fix before it (the nearest in time
    could be ahead); only epochs before the first fix, where no estimator starts, take the first."""
    from types import SimpleNamespace

    from lfgnss.features import _reference_positions
    ok = np.array([False, True, False, False, False, True, False])
    pos = np.column_stack([np.arange(7.0) * 1e3 + 6.4e6, np.zeros(7), np.zeros(7)])
    fix = SimpleNamespace(ok=ok, pos_ecef_m=pos, time_gps_s=np.arange(7.0))
    np.testing.assert_array_equal(_reference_positions(fix, np.zeros(3))[:, 0], pos[[1, 1, 1, 1, 1, 5, 5], 0])


@pytest.mark.shared_data
def test_features_of_a_drive_do_not_depend_on_epochs_after_them(shared_data):
    """hk-tst-2019 cut after epoch 400 (a stretch without coarse fixes ends at 412): every feature of the epochs
    before the cut is what the whole file gives them."""
    from dataclasses import replace

    root = shared_data("urbannav-hk-tst-20190428")
    meas = lfgnss.load(root / "COM3_190428_124409.obs", [root / "hksc1180.19n", root / "hksc1180.19b"])
    fix = lfgnss.spp(meas)
    whole = lfgnss.build_sequence(meas, fix)
    k = 400
    obs = meas.obs
    cut = replace(meas, obs=replace(obs, time_gps_s=obs.time_gps_s[:k], pr_m=obs.pr_m[:k], cn0_dbhz=obs.cn0_dbhz[:k],
                                    doppler_hz=obs.doppler_hz[:k]),
                  **{f: getattr(meas, f)[:k] for f in ("sat_pos_ecef_m", "sat_vel_ecef_m_s", "sat_clock_s",
                                                       "group_delay_s", "reason", "sat_clock_drift_s_s")})
    part = lfgnss.build_sequence(cut, lfgnss.spp(cut))
    assert not fix.ok[395:400].any() and fix.ok[412]        # the nearest fix of epochs 397-399 lies ahead
    np.testing.assert_array_equal(part.mask, whole.mask[:k])
    np.testing.assert_allclose(part.features, whole.features[:k], rtol=0, atol=1e-9)


def test_track_features_on_the_sample(sample):
    meas, fix, seq = sample
    names = DEFAULT_FEATURES + ("track_age", "cn0_std")
    more = lfgnss.build_sequence(meas, fix, feature_names=names)
    np.testing.assert_array_equal(more.features[..., :8], seq.features)
    age, spread = more.features[..., 8], more.features[..., 9]
    assert np.all(age[~more.mask] == 0.0) and np.all(spread[~more.mask] == 0.0)
    assert np.all((age >= 0) & (age <= np.log10(61.0))) and np.all((spread >= 0) & (spread < 30))
    assert np.any(age[more.mask] < 1.0)                      # some satellites are (re)acquired during the drive
