"""estimators.TruthNoise (R from the ground truth, a reference) and benchmarks/truth_weights.py."""
import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from estimators import HeuristicNoise, LfgnssEkf, TruthNoise, create
from lfgnss.features import system_median_m
from lfgnss.metrics import accuracy_table
from lfgnss.simulate import simulate_sequence


def test_system_median_is_per_epoch_and_constellation_over_masked_slots_only():
    values = np.array([[1.0, 3.0, 100.0, 10.0, 20.0],
                       [5.0, 7.0, 9.0, -4.0, np.nan]])
    mask = np.array([[True, True, False, True, True],
                     [True, True, True, True, False]])
    system = np.array([[0, 0, 0, 1, 1], [0, 0, 0, 1, 1]])
    got = system_median_m(values, mask, system, 3)        # system 2 has no satellite: nothing breaks
    assert np.allclose(got, [[2.0, 2.0, 2.0, 15.0, 15.0], [7.0, 7.0, 7.0, -4.0, -4.0]])
    assert np.all(system_median_m(values, np.zeros_like(mask), system, 2) == 0.0)


def test_truth_noise_is_the_squared_error_about_the_clock_plus_the_floor():
    """Simulated pseudoranges are range + clock + ISB + error: R must be (error - its median per system)^2 + floor^2."""
    seq = simulate_sequence(30, seed=4)
    error = seq.features[..., seq.feature_names.index("residual")]       # the simulator's injected error [m]
    want = error - system_median_m(error, seq.mask, seq.system_index, len(seq.systems))
    r, vc = TruthNoise(floor_m=0.5)(seq)
    assert np.allclose(r[seq.mask], want[seq.mask] ** 2 + 0.25, atol=1e-6)
    assert np.all(vc == 0.0) and r.shape == vc.shape == seq.mask.shape


def test_truth_noise_falls_back_where_there_is_no_truth():
    seq = simulate_sequence(20, seed=5)
    seq.truth_ecef_m[3:6] = np.nan
    r, _ = TruthNoise()(seq)
    fallback, _ = HeuristicNoise()(seq)
    assert np.array_equal(r[3:6], fallback[3:6]) and np.all(np.isfinite(r)) and np.all(r[seq.mask] > 0)
    sol = LfgnssEkf(noise=TruthNoise()).solve(seq)
    assert np.all(np.isfinite(sol.pos_ecef_m))


@pytest.mark.parametrize("floor", [0.0, -1.0, float("nan"), float("inf"), True, "1"])
def test_truth_noise_refuses_a_floor_that_is_not_positive(floor):
    with pytest.raises(ValueError, match="floor_m must be a finite number > 0"):
        TruthNoise(floor_m=floor)


def test_truth_noise_takes_a_numpy_floor():
    assert TruthNoise(floor_m=np.float32(1.0)).floor_m == 1.0


def test_truth_weights_beat_the_hand_set_ones_on_simulated_reflections():
    seq = simulate_sequence(150, seed=6, nlos_fraction=0.3)
    rmse = {name: accuracy_table(est.solve(seq).pos_ecef_m, seq.truth_ecef_m)["rmse_3d_m"]
            for name, est in (("plain", create("plain-ekf")), ("truth", LfgnssEkf(noise=TruthNoise())))}
    assert rmse["truth"] < 0.7 * rmse["plain"], rmse


def test_truth_weights_script_on_a_validation_split(tmp_path):
    """``benchmarks/truth_weights.py``: its rows are the filters' own figures; its page and figure are written."""
    from lfgnss import datasets

    if datasets.get("hk-tst-static-2020").missing():
        pytest.skip(f"shared data missing ({datasets.get('hk-tst-static-2020').missing()[0]})")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import truth_weights

    rows = truth_weights.run(["hk-tst-static-2020"], ["val"])
    assert len(rows) == 2 * (2 + len(truth_weights.FLOORS_M)) and all(r["availability"] == 1.0 for r in rows)
    seq = datasets.load_split("hk-tst-static-2020", "val")[0]
    model = [r["filter"] for r in rows if r["filter"].startswith("LF-GNSS")][0]
    filters = truth_weights.filters_for("hk-tst-static-2020")
    config = filters["EKF, weights from the truth, floor 1 m"](0.0).config
    # the model's filter, but R from the truth as it is: its GLONASS sigma factor (1.5 since session 51) at 1
    assert filters[model](0.0).config.glonass_sigma_factor == 1.5
    assert config == dataclasses.replace(filters[model](0.0).config, glonass_sigma_factor=1.0)
    sol = LfgnssEkf(noise=TruthNoise(floor_m=1.0), config=config).solve(seq)
    want = accuracy_table(sol.pos_ecef_m, seq.truth_ecef_m, sol.available)["rmse_3d_m"]
    assert [r["rmse_3d_m"] for r in rows if r["filter"].endswith("floor 1 m") and r["mode"] == "forward"] == [want]
    page = truth_weights.markdown(rows, "cmd")
    assert "| val forward | val smoothed |" in page and page.count("| EKF, weights from the truth, floor") == 3
    assert truth_weights.plot(rows, tmp_path / "truth.png", "val").stat().st_size > 10_000
