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
    assert caught[0].filename == __file__


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
