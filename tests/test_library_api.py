"""The public Python API as a library user meets it: Solution conversions, slicing and joining, and misuse that
must fail in one clear line (never a deep numpy/gtsam traceback, never a silent NaN) on the bundled drive."""
from __future__ import annotations

import re
import warnings
from dataclasses import replace

import numpy as np
import pytest

import estimators
import lfgnss
from estimators import EkfConfig, FixedNoise, HeuristicNoise, TruthNoise
from lfgnss import outputs
from lfgnss.frames import ecef_to_lla

BACKENDS = ["ekf", "plain-ekf", "fgo", "wls", "wls-weighted"]


@pytest.fixture(scope="module")
def seq():
    """The first 120 epochs of the bundled Berlin drive, with Doppler (no truth)."""
    from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS

    return lfgnss.process(SAMPLE_OBS, SAMPLE_NAV).subset(slice(0, 120))


@pytest.fixture(scope="module")
def solution(seq):
    return estimators.create("plain-ekf").solve(seq)


def _broken(seq, field, value, rows=slice(10, 20)):
    """``seq`` with ``field`` set to ``value`` on the masked-in slots of ``rows``."""
    a = getattr(seq, field).copy()
    a[rows][seq.mask[rows]] = value
    return replace(seq, **{field: a})


# ------------------------------------------------------------------ Solution conversions
def test_geodetic_enu_and_sigmas_agree_with_the_frames(solution):
    llh = solution.geodetic()
    ref = ecef_to_lla(solution.pos_ecef_m)
    np.testing.assert_allclose(llh[:, :2], np.degrees(ref[:, :2]))
    np.testing.assert_allclose(llh[:, 2], ref[:, 2])
    assert 52 < llh[0, 0] < 53 and 13 < llh[0, 1] < 14                   # Berlin
    enu = solution.enu_m()
    np.testing.assert_allclose(enu[0], 0.0, atol=1e-6)                   # about the first position by default
    np.testing.assert_allclose(np.linalg.norm(enu, axis=1),
                               np.linalg.norm(solution.pos_ecef_m - solution.pos_ecef_m[0], axis=1), atol=1e-6)
    sd = solution.sd_enu_m()
    np.testing.assert_allclose((sd ** 2).sum(1), np.trace(solution.cov_ecef_m2, axis1=1, axis2=2), rtol=1e-9)
    with pytest.raises(ValueError, match="ref_ecef_m"):
        solution.enu_m(np.zeros(2))


def test_to_frame_matches_the_csv_writer(solution, seq, tmp_path):
    pd = pytest.importorskip("pandas")
    truth = solution.pos_ecef_m + [1.0, 0.0, 0.0]
    frame = solution.to_frame(truth)
    written = pd.read_csv(outputs.write_csv(tmp_path / "s.csv", solution, truth))
    assert list(frame.columns) == list(written.columns) and len(frame) == len(seq)
    for col in frame.columns:
        if written[col].dtype.kind == "f":
            np.testing.assert_allclose(frame[col], written[col], atol=1e-3, err_msg=col)
    assert (frame["status"] == written["status"]).all() and frame["err_3d_m"].max() == pytest.approx(1.0)


def test_epochs_without_a_position_are_nan_in_every_conversion(seq):
    coarse = seq.coarse_ecef_m.copy()
    coarse[:3] = np.nan                                # no fix before epoch 3: status none
    sol = estimators.create("plain-ekf").solve(replace(seq, coarse_ecef_m=coarse))
    assert (sol.status[:3] == estimators.STATUS_NONE).all()
    for values in (sol.geodetic(), sol.enu_m(), sol.sd_enu_m()):
        assert np.isnan(values[:3]).all() and np.isfinite(values[3:]).all()
    assert list(sol.to_frame()["status"][:4]) == ["none", "none", "none", "reset"]


def test_solution_subset_slices_every_per_epoch_array(solution):
    part = solution.subset(slice(10, 30))
    assert len(part) == 20 and part.info["n_gated"].shape == (20,)
    np.testing.assert_array_equal(part.pos_ecef_m, solution.pos_ecef_m[10:30])
    assert part.info["config"] is solution.info["config"]
    assert len(solution.subset(5)) == 1


# ------------------------------------------------------------------ Sequences: slices, joins, re-use
def test_an_estimator_reused_and_a_joined_sequence_give_the_same_run(seq):
    ekf = estimators.create("ekf")
    first = ekf.solve(seq)
    np.testing.assert_array_equal(ekf.solve(seq).pos_ecef_m, first.pos_ecef_m)
    joined = lfgnss.concat_sequences([seq.subset(slice(0, 50)), seq.subset(slice(50, None)).pad_to(seq.n_slots + 4)])
    assert len(joined) == len(seq) and joined.n_slots == seq.n_slots + 4
    np.testing.assert_allclose(ekf.solve(joined).pos_ecef_m, first.pos_ecef_m, atol=1e-6)
    assert len(seq.subset(7)) == 1
    with pytest.raises(ValueError, match="systems"):
        lfgnss.concat_sequences([seq, replace(seq, systems=("G", "E"))])
    with pytest.raises(TypeError, match="part 1"):
        lfgnss.concat_sequences([seq, "b.obs"])
    with pytest.raises(ValueError, match="not after .* ends .*; give the parts in time order$"):
        lfgnss.concat_sequences([seq.subset(slice(50, None)), seq.subset(slice(0, 50))])


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_and_single_epoch_sequences(seq, backend):
    assert len(estimators.create(backend).solve(seq.subset(slice(0, 0)))) == 0
    one = estimators.create(backend).solve(seq.subset(slice(5, 6)))
    assert one.available.all() and np.isfinite(one.pos_ecef_m).all()


# ------------------------------------------------------------------ misuse: one clear line
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("wrong", [None, "rover.obs", {}])
def test_solve_names_a_wrong_argument(seq, backend, wrong):
    with pytest.raises(TypeError, match="expected an lfgnss.Sequence"):
        estimators.create(backend).solve(wrong)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_non_finite_epoch_time_is_named(seq, backend):
    t = seq.time_gps_s.copy()
    t[50] = np.nan
    with pytest.raises(ValueError, match="not finite at epoch 50"):
        estimators.create(backend).solve(replace(seq, time_gps_s=t))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("field", ["pr_m", "sat_pos_ecef_m", "prr_m_s", "sat_vel_ecef_m_s"])
def test_nan_measurements_are_left_out_not_spread(seq, backend, field):
    """A NaN on a masked-in slot: the slot is dropped (one warning for a pseudorange or satellite position, one
    for a Doppler or satellite velocity); no epoch has status updated with a NaN position."""
    what = "masked-in slots" if field in ("pr_m", "sat_pos_ecef_m") else "marked Dopplers"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = estimators.create(backend).solve(_broken(seq, field, np.nan))
    said = [str(w.message) for w in caught if "are skipped" in str(w.message)]
    if what == "marked Dopplers" and backend.startswith("wls"):
        assert not said                                     # least squares uses no Doppler: nothing to say
    else:
        assert len(said) == 1 and re.search(rf"{what} in 10 epochs .* are skipped", said[0])
    assert np.isfinite(sol.pos_ecef_m[sol.available]).all()
    assert sol.available[20:].all()


def test_backend_name_and_options(seq):
    assert estimators.create("plain-ekf", name="mine").solve(seq.subset(slice(0, 3))).backend == "mine"
    with pytest.raises(TypeError, match="backend name must be a string"):
        estimators.create(estimators.LfgnssEkf)
    with pytest.raises(TypeError, match="config must be an estimators.EkfConfig"):
        estimators.create("ekf", config={"gate_sigma": 3.0})


@pytest.mark.parametrize("kwargs, message", [
    ({"gate_sigma": "3"}, "gate_sigma must be a number"),
    ({"p0_pos_m2": None}, "p0_pos_m2 must be a number"),
    ({"q_vel_m2_s3": float("inf")}, "q_vel_m2_s3 must be finite"),
    ({"min_sats_for_update": 1.5}, "min_sats_for_update must be a whole number"),
    ({"reset_gated_fraction": -1.0}, "reset_gated_fraction must be >= 0"),
])
def test_ekf_config_names_a_bad_setting(kwargs, message):
    with pytest.raises(ValueError, match=message):
        EkfConfig(**kwargs)


def test_ekf_config_stores_whole_number_counts_as_int():
    config = EkfConfig(reset_min_sats=5.0, min_sats_for_update=2.0)     # as a TOML file may give them
    assert (config.reset_min_sats, config.min_sats_for_update) == (5, 2)
    assert all(type(v) is int for v in (config.reset_min_sats, config.min_sats_for_update))


@pytest.mark.parametrize("kwargs, message", [
    ({"lag_s": "10"}, "lag_s must be a finite number"),
    ({"prior_pos_sigma_m": -1.0}, "prior_pos_sigma_m must be > 0"),
    ({"max_iterations": 0}, "max_iterations must be a whole number >= 1"),
])
def test_fgo_names_a_bad_option(kwargs, message):
    with pytest.raises(ValueError, match=message):
        estimators.create("fgo", **kwargs)


@pytest.mark.parametrize("backend", ["ekf", "fgo", "wls-weighted"])
@pytest.mark.parametrize("returned, got", [(None, "NoneType"), ((1, 2, 3), "3 values"), ("array", "shape")])
def test_a_noise_model_returning_the_wrong_thing_is_named(seq, backend, returned, got):
    out = np.ones(seq.mask.shape) if returned == "array" else returned
    with pytest.raises(TypeError, match=f"must return \\(r_m2, vc_m\\).*{got}"):
        estimators.create(backend, noise=lambda s: out).solve(seq)


def test_noise_models_check_their_settings_and_inputs(seq):
    for bad in ({"floor_m": "2"}, {"floor_m": -1.0}, {"el_min_rad": 0.0}, {"floor_m": 0.0, "cn0_scale_m2": 0.0}):
        with pytest.raises(ValueError, match="HeuristicNoise"):
            HeuristicNoise(**bad)
    with pytest.raises(ValueError, match="C/N0 or elevation is not finite .* epoch 10"):
        estimators.create("plain-ekf").solve(_broken(seq, "cn0_dbhz", np.nan))
    with pytest.warns(UserWarning, match="no ground truth"):
        TruthNoise()(seq)
    t, n = seq.mask.shape
    with pytest.raises(ValueError, match="do not fit"):
        estimators.LfgnssEkf(noise=FixedNoise(np.ones((t, n)), np.zeros((t, n)))).solve(seq.subset(slice(0, 10)))


@pytest.mark.parametrize("writer", ["write_pos", "write_csv", "write_geojson", "write_kml", "plot_solution"])
def test_writers_name_swapped_or_wrong_arguments(solution, seq, tmp_path, writer):
    write = getattr(outputs, writer)
    with pytest.raises(TypeError, match="arguments are swapped"):
        write(solution, tmp_path / "x")
    with pytest.raises(TypeError, match="must be an estimators.Solution.*got Sequence"):
        write(tmp_path / "x", seq)


# ------------------------------------------------------------------ the front end's entry points
def test_front_end_misuse_is_one_clear_error():
    from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS

    with pytest.raises(TypeError, match=r"^lfgnss.load: nav must be a RINEX navigation file .* got NoneType$"):
        lfgnss.load(SAMPLE_OBS, None)
    with pytest.raises(TypeError, match=r"^lfgnss.load: obs must be a RINEX observation file .* got int$"):
        lfgnss.load(123, SAMPLE_NAV)
    meas = lfgnss.load(SAMPLE_OBS, iter(SAMPLE_NAV))               # any iterable of paths
    fix = lfgnss.spp(meas)
    with pytest.raises(TypeError, match=r"^lfgnss.spp: expected the Measurements .* got Sequence$"):
        lfgnss.spp(lfgnss.build_sequence(meas, fix))
    with pytest.raises(TypeError, match=r"got CoarseFix and Measurements$"):
        lfgnss.build_sequence(fix, meas)
    gps_only = lfgnss.spp(lfgnss.load(SAMPLE_OBS, SAMPLE_NAV, systems="G"))
    with pytest.raises(ValueError, match=r"^lfgnss.build_sequence: the fix \(1375 epochs x 12 satellites, G\) is not "
                                         r"of these measurements \(1375 x 20, GR\); use lfgnss.spp\(meas\)$"):
        lfgnss.build_sequence(meas, gps_only)
    one = lfgnss.build_sequence(meas, fix, feature_names="cn0")      # one name, not its letters
    assert one.feature_names == ("cn0",) and one.features.shape[-1] == 1


def test_read_truth_is_align_truth_in_one_call(tmp_path):
    from lfgnss.datasets import DatasetSpec, align_truth, read_truth
    from lfgnss.errors import InputError
    from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH

    t = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV).time_gps_s
    truth = read_truth(SAMPLE_TRUTH, t, "smartloc")
    spec = DatasetSpec("s", (SAMPLE_OBS,), SAMPLE_NAV, SAMPLE_TRUTH, "smartloc", time_origin_gps_s=t[0])
    np.testing.assert_array_equal(truth, align_truth(t, spec)[0])
    assert truth.shape == (len(t), 3) and np.isfinite(truth).all(1).mean() > 0.9
    bad = tmp_path / "gt.txt"
    bad.write_text(SAMPLE_TRUTH.read_text().replace("point3", "garbage", 1))
    with pytest.warns(UserWarning, match=f"^{bad}:"):
        read_truth(bad, t, "smartloc")
    with pytest.raises(InputError, match="unknown truth format 'gpx'; use one of urbannav, smartloc"):
        read_truth(SAMPLE_TRUTH, t, "gpx")


def test_a_saved_sequence_reads_back_by_the_name_it_was_given_and_other_files_are_one_line(tmp_path):
    from lfgnss.errors import InputError
    from lfgnss.paths import default_model_path
    from lfgnss.simulate import simulate_sequence

    seq = simulate_sequence(20, seed=1)
    written = lfgnss.save_sequence(tmp_path / "mine", seq)          # numpy adds .npz: the caller is told
    assert written == tmp_path / "mine.npz" and written.exists()
    for path in (tmp_path / "mine", written):
        back = lfgnss.load_sequence(path)
        np.testing.assert_array_equal(back.pr_m, seq.pr_m)
        assert back.systems == seq.systems and back.name == seq.name
    (tmp_path / "a.toml").write_text('id = "x"\n')
    np.save(tmp_path / "arr.npy", np.zeros(3))
    for path, reason in ((tmp_path / "none", "no such Sequence file"),
                         (default_model_path(), "not a Sequence file written by lfgnss.save_sequence"),
                         (tmp_path / "a.toml", "not a Sequence file written by lfgnss.save_sequence"),
                         (tmp_path / "arr.npy", "not a Sequence file written by lfgnss.save_sequence (an .npy array)")):
        with pytest.raises(InputError, match=f"^{re.escape(str(path))}: {re.escape(reason)}"):
            lfgnss.load_sequence(path)


def test_latitude_longitude_for_an_ecef_truth_or_reference_is_refused_by_the_solution_too():
    from lfgnss.simulate import simulate_sequence

    seq = simulate_sequence(5, seed=2)
    sol = estimators.create("wls").solve(seq)
    lla = np.tile([52.5, 13.37, 70.0], (5, 1))
    with pytest.raises(ValueError, match="solution_frame: truth_ecef_m has 5 row.* it must be ECEF metres"):
        sol.to_frame(lla)
    with pytest.raises(ValueError, match="Solution.enu_m: ref_ecef_m has 1 row.* it must be ECEF metres"):
        sol.enu_m(lla[0])
    assert np.isfinite(sol.to_frame(seq.truth_ecef_m)["err_3d_m"]).all()


@pytest.mark.parametrize("field, value, message", [
    ("pos_ecef_m", np.zeros((10, 3)), r"pos_ecef_m has shape \(10, 3\), expected \(5, 3\)"),
    ("cov_ecef_m2", np.zeros((3, 3)), r"cov_ecef_m2 has shape \(3, 3\), expected \(5, 3, 3\)"),
    ("clock_m", np.zeros(4), r"clock_m has shape \(4,\), expected \(5\)"),
    ("vel_ecef_m_s", np.zeros((5, 2)), r"vel_ecef_m_s has shape \(5, 2\), expected \(5, 3\)"),
    ("status", np.full(5, 7), r"unknown status code\(s\) \[7\]"),
    # review: float32 times wrote every line of a .pos at one minute; a NaN n_used as -9223372036854775808 satellites
    ("time_gps_s", (1.2e9 + np.arange(5.0)).astype(np.float32), "time_gps_s must be float64 GPS seconds, got float32"),
    ("n_used", np.array([4.0, np.nan, 5.0, 6.0, 0.5]),
     r"n_used must be whole numbers .*, got nan \(of 2 such values\)"),
])
def test_a_solution_of_the_wrong_shape_is_refused_when_made(field, value, message):
    parts = dict(backend="mine", time_gps_s=np.arange(5.0), pos_ecef_m=np.zeros((5, 3)), cov_ecef_m2=np.zeros((5, 3, 3)),
                 clock_m=np.zeros(5), n_used=np.zeros(5, int), status=np.ones(5, int))
    estimators.Solution(**parts)
    estimators.Solution(**(parts | {"n_used": np.full(5, 4.0)}))        # whole numbers as floats stand
    with pytest.raises(ValueError, match=r"^Solution of 'mine': " + message):
        estimators.Solution(**(parts | {field: value}))


def test_parts_of_one_drive_are_told_apart_by_number_and_one_epoch_is_singular(tmp_path):
    from learning.data import make_windows
    from lfgnss.datasets import read_truth
    from lfgnss.simulate import simulate_sequence
    from lfgnss.solve import SAMPLE_TRUTH

    seq = simulate_sequence(20, seed=4)
    with pytest.raises(ValueError, match=r"part 2 \('synthetic'\) starts at .* not after part 1 \('synthetic'\) ends"):
        lfgnss.concat_sequences([seq.subset(slice(0, 5)), seq.subset(slice(10, 20)), seq.subset(slice(5, 10))])
    assert "1 epoch," in repr(seq.subset(3)) and "1 epoch," in repr(estimators.create("wls").solve(seq.subset(3)))
    assert "20 epochs," in repr(seq)
    time = np.array([1900 * 604800 + 126641.7])
    np.testing.assert_array_equal(read_truth(SAMPLE_TRUTH, time, "SmartLoc"), read_truth(SAMPLE_TRUTH, time, "smartloc"))
    with pytest.raises(ValueError, match=r"no labelled window of 40 epochs .* \(the longest piece has 20 epochs\): "
                                         r"lower data.window"):
        make_windows([seq], 40, 10)
