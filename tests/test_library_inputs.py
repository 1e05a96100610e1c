"""Library calls given inputs in the wrong form (a library user's review, session 26): one clear error or warning,
never a silently wrong figure."""
import tomllib
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import lfgnss
from learning.export import load_model
from lfgnss.datasets import read_truth
from lfgnss.metrics import accuracy_table
from lfgnss.rinex import RinexError
from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def meas():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)


def test_smartloc_truth_for_epochs_not_starting_at_its_origin_is_warned_of(meas):
    """smartloc truth counts t from the first epoch given unless told otherwise: a later start shifts it by hundreds
    of metres, so that is warned of (pointing at the caller); the same call with the origin is exact and quiet."""
    t = meas.time_gps_s
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        whole = read_truth(SAMPLE_TRUTH, t, "smartloc")                       # from the start: no warning
        exact = read_truth(SAMPLE_TRUTH, t[300:], "smartloc", time_origin_gps_s=t[0])
    np.testing.assert_array_equal(exact, whole[300:])
    with pytest.warns(UserWarning, match=r"only \d+ of \d+ epochs within the truth's time span match a truth time "
                                         r"when its t = 0 is taken as the first epoch given") as caught:
        read_truth(SAMPLE_TRUTH, t[300:], "smartloc")
    assert caught[0].filename == __file__ and "shifted" not in str(caught[0].message)
    with pytest.warns(UserWarning, match=r"taken as the first epoch given \(GPS \d+\.\d s\) and its times shifted by "
                                         r"\+0\.3 s \(time_offset_s, --truth-offset\); if these epochs"):
        read_truth(SAMPLE_TRUTH, t[300:], "smartloc", time_offset_s=0.3)       # the shift the user gave is named


def test_a_model_refuses_non_finite_features_on_used_slots():
    model = load_model(REPO / "lfgnss" / "data" / "model" / "lfgnss-default.npz")
    rng = np.random.default_rng(0)
    features = rng.normal(size=(3, 5, len(model.feature_names))) + 1.0
    mask = np.ones((3, 5), bool)
    mask[2, 4] = False
    features[2, 4, 0] = np.nan                                   # a padded slot may hold anything
    r, vc = model.predict(features, mask)
    assert np.isfinite(r).all() and np.isfinite(vc).all()
    features[1, 3, 0] = np.nan
    with pytest.raises(ValueError, match=r"feature 'cn0' is nan at epoch 1, satellite slot 3 \(1 satellite slot\(s\) "
                                         r"in all\); give finite features"):
        model.predict(features, mask)


def test_positions_in_other_units_than_ecef_metres_are_refused(meas):
    fix = lfgnss.spp(meas)
    truth = read_truth(SAMPLE_TRUTH, meas.time_gps_s, "smartloc")
    lla = np.tile([52.5, 13.37, 70.0], (len(meas.time_gps_s), 1))
    with pytest.raises(ValueError, match=r"Sequence '.*': truth_ecef_m has \d+ row\(s\) .* it must be ECEF metres"):
        lfgnss.build_sequence(meas, fix, truth_ecef_m=lla)
    seq = lfgnss.build_sequence(meas, fix, truth_ecef_m=truth)
    with pytest.raises(ValueError, match=r"Sequence 'mine': truth_ecef_m has \d+ row\(s\) .* it must be ECEF metres"):
        replace(seq, name="mine", truth_ecef_m=truth / 1000.0)             # a hand-built Sequence is checked too
    with pytest.raises(ValueError, match="accuracy_table: truth_ecef_m has"):
        accuracy_table(truth, truth / 1000.0)                                # kilometres
    with pytest.raises(ValueError, match=r"accuracy_table: est_ecef_m has \d+ row\(s\) within 1000 km of the "
                                         r"Earth's centre .*not Solution.geodetic\(\)"):
        accuracy_table(lla, truth)
    far = truth + [5.0e5, 0.0, 0.0]                                          # a diverged estimate is still scored
    assert accuracy_table(far, truth)["rmse_3d_m"] == pytest.approx(5.0e5)


def test_an_empty_selection_of_observations_says_so(meas):
    with pytest.raises(RinexError, match="no epoch: the Observations given hold none"):
        lfgnss.load(meas.obs.select_epochs(slice(0, 0)), SAMPLE_NAV)


def test_the_packages_ship_their_type_hints():
    """PEP 561: without py.typed in the installed package, type checkers ignore every hint."""
    package_data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for package in ("lfgnss", "estimators", "learning"):
        assert (REPO / package / "py.typed").is_file() and "py.typed" in package_data[package]


def test_solve_given_a_split_list_and_a_sequence_with_int_masks_say_so(meas):
    """``load_split`` gives a list (a split may be cut in several parts), and a mask of 0/1 ints failed deep in the
    solver (UFuncTypeError)."""
    import estimators

    seq = lfgnss.build_sequence(meas, lfgnss.spp(meas))
    with pytest.raises(TypeError, match=r"got a list of 2 \(the parts lfgnss.datasets.load_split gives"):
        estimators.create("ekf").solve([seq.subset(slice(0, 10)), seq.subset(slice(10, 20))])
    for key in ("mask", "prr_mask"):
        with pytest.raises(ValueError, match=f"{key} must be a bool array, got dtype int64"):
            replace(seq, **{key: getattr(seq, key).astype(int)})
    with pytest.raises(ValueError, match="system_index must be an integer array, got dtype float64"):
        replace(seq, system_index=seq.system_index.astype(float))


def test_accuracy_table_takes_a_solution(meas):
    import estimators

    seq = lfgnss.build_sequence(meas, lfgnss.spp(meas), truth_ecef_m=read_truth(SAMPLE_TRUTH, meas.time_gps_s,
                                                                                "smartloc"))
    sol = estimators.create("wls").solve(seq)
    assert accuracy_table(sol, seq.truth_ecef_m) == accuracy_table(sol.pos_ecef_m, seq.truth_ecef_m, sol.available)


def test_a_requested_constellation_the_file_lacks_is_warned_of():
    with pytest.warns(lfgnss.rinex.RinexWarning, match=r"no C observations \(requested\)"):
        meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV, systems="GC")
    assert meas.systems == ("G",)


# ------------------------------------------------------------------ estimators: options, noise models, solves
# (a library user's review of estimators/, session 51)
@pytest.fixture(scope="module")
def seq(meas):
    """The bundled drive's first 200 epochs, with truth."""
    truth = read_truth(SAMPLE_TRUTH, meas.time_gps_s, "smartloc")
    return lfgnss.build_sequence(meas, lfgnss.spp(meas), truth_ecef_m=truth, name="drive").subset(slice(0, 200))


def _fixed(seq, r_m2: float):
    import estimators

    return estimators.FixedNoise(np.full(seq.mask.shape, r_m2), np.zeros(seq.mask.shape))


@pytest.mark.parametrize("psd", [(1.0, 1.0, np.nan), (1.0, 1.0, np.inf), ("a", 1.0, 1.0), (1.0, 1.0), 0.5])
def test_fgo_refuses_a_non_finite_or_malformed_acceleration_density(psd):
    """NaN passed ``np.any(psd <= 0)`` and the graph returned its initial guess as 'updated'."""
    import estimators

    with pytest.raises(ValueError, match=r"^LfgnssFgo: accel_psd_enu_m2_s3 must be 3 finite positive numbers "
                                         r"\[m\^2/s\^3\] \(east, north, up\), got "):
        estimators.create("fgo", accel_psd_enu_m2_s3=psd)


def test_fgo_numeric_options_are_refused_as_the_ekf_config_refuses_them():
    import estimators

    same = "a number of dB-Hz or None, got '45'"
    with pytest.raises(ValueError, match=f"^LfgnssFgo: doppler_cn0_ref_dbhz must be finite: {same}$"):
        estimators.create("fgo", doppler_cn0_ref_dbhz="45")                       # was numpy's raw TypeError
    with pytest.raises(ValueError, match=f"EkfConfig.doppler_cn0_ref_dbhz must be {same}$"):
        estimators.EkfConfig(doppler_cn0_ref_dbhz="45")
    with pytest.raises(ValueError, match="LfgnssFgo: doppler_cn0_ref_dbhz must be finite: a number"):
        estimators.create("fgo", doppler_cn0_ref_dbhz=np.inf)
    for key in ("lag_s", "robust_k", "prior_pos_sigma_m", "prior_vel_sigma_m_s", "doppler_sigma_m_s"):
        for bad in (np.nan, np.inf, "1"):
            with pytest.raises(ValueError, match=f"^LfgnssFgo: {key} must be a finite number, got "):
                estimators.create("fgo", **{key: bad})
    for key in ("zupt_sigma_m_s", "zupt_max_speed_m_s"):
        with pytest.raises(ValueError, match=f"^LfgnssFgo: {key} must be a positive number of m/s"):
            estimators.create("fgo", **{key: np.nan})


@pytest.mark.parametrize("value", [float("inf"), float("nan"), -1.0, "0.1"])
def test_ekf_config_refuses_a_non_finite_vertical_density(value):
    """inf was accepted (the other densities must be finite) and gave NaN covariances."""
    import estimators

    with pytest.raises(ValueError, match=r"^estimators/models.py: EkfConfig.q_vel_up_m2_s3 must be a finite number "
                                         r">= 0 \[\(m/s\)\^2/s\] or None, got "):
        estimators.EkfConfig(q_vel_up_m2_s3=value)


@pytest.mark.parametrize("options, cause", [
    ({"noise": 1e11}, r"its largest R is 1e\+11 m\^2: R must be a pseudorange variance in m\^2"),
    ({"accel_psd_enu_m2_s3": (1e-9,) * 3}, r"accel_psd_enu_m2_s3 is \(1e-09, 1e-09, 1e-09\) m\^2/s\^3: near 0"),
])
def test_a_singular_fixed_lag_graph_names_the_epoch_and_the_input(seq, options, cause):
    """gtsam's multi-line RuntimeError ('Indeterminate linear system ... (Symbol: x24)') becomes one line naming the
    epoch of the variable gtsam names."""
    import estimators

    if "noise" in options:
        options = {"noise": _fixed(seq, options["noise"])}
    with pytest.raises(ValueError, match=r"^LfgnssFgo: the fixed-lag update at epoch (\d+) of 'drive' is numerically "
                                         r"singular \(gtsam: an indeterminate linear system near variable [xv]\1\); "
                                         + cause) as caught:
        estimators.create("fgo", mode="fixed-lag", **options).solve(seq)
    assert "\n" not in str(caught.value)


def test_a_fixed_lag_graph_given_a_tiny_r_solves_and_says_r_looks_wrong(seq):
    """R = 1e-12 m^2 (a sigma of a micrometre): solved since session 53's clock relinearisation (it used to be
    singular at epoch 193), with the warning that R looks given in another unit."""
    import estimators
    from estimators import NoiseWarning

    with pytest.warns(NoiseWarning, match="is a median 1.05e-14 times the hand-set C/N0-elevation variance"):
        sol = estimators.create("fgo", mode="fixed-lag", noise=_fixed(seq, 1e-12)).solve(seq)
    assert np.isfinite(sol.pos_ecef_m).all() and np.all(sol.status == estimators.STATUS_UPDATED)


def test_a_batch_graph_levenberg_marquardt_gives_up_on_is_named(seq):
    """R = 1e-12 m^2: Levenberg-Marquardt stopped at its largest damping and the graph returned 88 m errors silently."""
    import estimators

    with pytest.raises(ValueError, match=r"^LfgnssFgo: the batch solve of 'drive' failed: Levenberg-Marquardt could "
                                         r"not lower the error at its largest damping \(worst fit at epoch \d+\); "
                                         r"its smallest R is 1e-12 m\^2: R must be a pseudorange variance in m\^2, "
                                         r"not near 0$"):
        estimators.create("fgo", noise=_fixed(seq, 1e-12)).solve(seq)


def test_config_of_reads_a_bundled_model_name_or_a_model_file(tmp_path, monkeypatch):
    """config_of("hk-tst-2019") gave EkfConfig() silently; noise="~/m.npz" was not found."""
    import shutil

    import estimators
    from lfgnss.paths import bundled_models

    model = load_model("hk-tst-2019")
    want = estimators.config_of(model)
    assert want != estimators.EkfConfig() and want.zupt_sigma_m_s == 0.02
    assert estimators.config_of("hk-tst-2019") == want
    assert estimators.config_of(bundled_models()["hk-tst-2019"]) == want            # a Path
    assert estimators.config_of(None) == estimators.EkfConfig()                     # not a model: the defaults
    assert estimators.config_of(lambda s: model(s)) == estimators.EkfConfig()
    shutil.copy(bundled_models()["hk-tst-2019"], tmp_path / "m.npz")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert estimators.config_of("~/m.npz") == want
    assert estimators.create("ekf", noise="~/m.npz").config == want


def test_the_ekf_takes_a_missing_coarse_clock_from_the_pseudoranges(seq):
    """Only coarse_clock_m NaN (the position finite) gave no position at all, and no warning."""
    import estimators
    from estimators.models import pseudorange_clock_m

    k = 50
    clock = pseudorange_clock_m(seq.pr_m[k], seq.sat_pos_ecef_m[k], seq.system_index[k], seq.mask[k],
                                seq.coarse_ecef_m[k], len(seq.systems))
    assert abs(clock[0] - seq.coarse_clock_m[k, 0]) < 5.0 and abs(clock[1] - seq.coarse_clock_m[k, 1]) < 20.0
    gps_out = seq.mask[k] & (seq.system_index[k] != 0)                # systems[0] absent: the next one takes the clock
    alone = pseudorange_clock_m(seq.pr_m[k], seq.sat_pos_ecef_m[k], seq.system_index[k], gps_out,
                                seq.coarse_ecef_m[k], len(seq.systems))
    assert alone[1] == 0.0 and abs(alone[0] - clock[0] - clock[1]) < 1e-6
    part = seq.subset(slice(0, 40))
    blind = replace(part, coarse_clock_m=np.full_like(part.coarse_clock_m, np.nan))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = estimators.create("ekf").solve(blind)
    want = estimators.create("ekf").solve(part)
    assert got.has_position().all()
    assert np.nanmax(np.linalg.norm(got.pos_ecef_m - want.pos_ecef_m, axis=1)) < 0.1
    mask = blind.mask.copy()
    mask[:3] = False                                   # no pseudorange to take a clock from at epochs 0-2
    with pytest.warns(UserWarning, match=r"LfgnssEkf: coarse_clock_m of 'drive' is NaN at 3 epochs with a coarse "
                                         r"position and no usable pseudorange to take a clock from "
                                         r"\(first at epoch 0\)"):
        sol = estimators.create("ekf").solve(replace(blind, mask=mask, prr_mask=blind.prr_mask & mask))
    assert not sol.has_position()[:3].any() and sol.has_position()[3:].all()


def test_fgo_options_its_mode_or_kernel_would_drop_are_refused():
    """lag_s in batch mode and robust_k without a kernel were accepted and ignored (the EKF refuses smooth_lag_s
    without smooth)."""
    import estimators

    with pytest.raises(ValueError, match=r"^LfgnssFgo: lag_s=3 needs mode='fixed-lag' \(the batch mode uses every "
                                         r"epoch, with no window\)$"):
        estimators.create("fgo", lag_s=3)
    with pytest.raises(ValueError, match=r"^LfgnssFgo: robust_k=2 needs a robust kernel \(robust='auto', 'huber' or "
                                         r"'cauchy'\); robust=None uses none$"):
        estimators.create("fgo", robust=None, robust_k=2.0)
    assert estimators.create("fgo", mode="fixed-lag", lag_s=3).lag_s == 3.0         # what they are for
    assert estimators.create("fgo", robust="huber", robust_k=2.0).robust_k == 2.0
    estimators.create("fgo", lag_s=10.0)                                              # the defaults, said aloud
    estimators.create("fgo", robust=None, robust_k=None)


def test_a_noise_model_returning_the_wrong_thing_names_itself_and_what_it_must_return(seq):
    import estimators

    part = seq.subset(slice(0, 5))
    t, n = part.mask.shape
    must = r"must return \(r_m2, vc_m\), each a \(T, N\) float array \[m\^2, m\]"
    with pytest.raises(TypeError, match=r"^FixedNoise: r_m2 must be a \(T, N\) float array \[m\^2\], got an array of "
                                        r"dtype <U1$"):
        estimators.FixedNoise(np.full((t, n), "a"), np.zeros((t, n)))

    def as_dict(sequence):
        return {"r": np.ones((t, n)), "vc": np.zeros((t, n))}

    with pytest.raises(TypeError, match=rf"^LfgnssEkf: the noise model <function .*as_dict> {must}; got a dict "
                                        rf"\(keys 'r', 'vc'\): return the tuple$"):
        estimators.LfgnssEkf(noise=as_dict, config=estimators.EkfConfig()).solve(part)

    def as_strings(sequence):
        return np.full((t, n), "a"), np.zeros((t, n))

    with pytest.raises(TypeError, match=rf"^LfgnssFgo: the noise model <function .*as_strings> {must}; its r_m2 is an "
                                        rf"array of dtype <U1$"):
        estimators.LfgnssFgo(noise=as_strings).solve(part)
    with pytest.raises(TypeError, match=r"^TruthNoise: fallback must be a noise model \(sequence -> \(r_m2, vc_m\)\), "
                                        r"got int$"):
        estimators.TruthNoise(fallback=3)
    with pytest.raises(TypeError, match=rf"^TruthNoise.fallback: the noise model <function .*<lambda>> {must}; "
                                        r"got int$"):
        estimators.TruthNoise(fallback=lambda q: 1)(part)
    torch = pytest.importorskip("torch")

    def with_grad(sequence):
        return torch.ones((t, n), requires_grad=True), np.zeros((t, n))

    with pytest.raises(TypeError, match=rf"^LfgnssEkf: the noise model <function .*with_grad> {must}; its r_m2 is a "
                                        r"torch tensor that requires grad \(return "
                                        r"tensor.detach\(\).cpu\(\).numpy\(\)\)$"):
        estimators.LfgnssEkf(noise=with_grad, config=estimators.EkfConfig()).solve(part)


def test_solution_subset_of_another_length_says_so(seq):
    import estimators

    sol = estimators.create("wls").solve(seq.subset(slice(0, 20)))
    with pytest.raises(IndexError, match=r"^Solution.subset: a boolean mask of shape \(10,\) for 20 epochs; give one "
                                         r"of length 20$"):
        sol.subset(np.ones(10, bool))
    with pytest.raises(IndexError, match=r"^Solution.subset: epoch index 25 is out of range for 20 epochs$"):
        sol.subset(np.array([0, 25]))
    assert len(sol.subset(np.arange(20) < 5)) == 5 and len(sol.subset(-1)) == 1 and len(sol.subset(slice(2, 4))) == 2
