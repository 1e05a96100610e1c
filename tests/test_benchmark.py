"""Benchmark rows (methods) and the targets table (target_rows): which estimators run, against which bars."""
import shutil
from types import SimpleNamespace

from lfgnss.benchmark import MODEL_DIR, PLAIN, PLAIN_RTS, RTKLIB, _features_for, methods, target_rows
from lfgnss.metrics import markdown_table
from lfgnss.sequence import DEFAULT_FEATURES


def test_rows_follow_the_model_files(tmp_path):
    names = [m.name for m in methods(tmp_path, "berlin-pp")]
    assert names == ["least squares (equal weight)", "least squares (C/N0-weighted)", "plain EKF (C/N0 noise, gate)",
                     "plain EKF + RTS smoother"]

    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-default.npz")
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-no_hem.npz")
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-berlin-pp.npz")
    rows = {m.name: m for m in methods(tmp_path, "berlin-pp")}
    assert {"LF-GNSS EKF", "LF-GNSS FGO", "LF-GNSS EKF w/o HEM", "LF-GNSS EKF, per-dataset model",
            "LF-GNSS FGO, per-dataset model", "LF-GNSS EKF + RTS smoother",
            "LF-GNSS EKF + RTS smoother, per-dataset model"} <= set(rows)
    assert rows["LF-GNSS EKF + RTS smoother, per-dataset model"].create().smooth
    assert rows["plain EKF + RTS smoother"].create().smooth and not rows[PLAIN].create().smooth
    assert rows["LF-GNSS FGO, per-dataset model"].model == tmp_path / "lfgnss-berlin-pp.npz"
    assert rows["LF-GNSS FGO, per-dataset model"].backend == "fgo"
    # another dataset's own model is not used
    assert not any("per-dataset" in m.name for m in methods(tmp_path, "hk-tst-2019"))
    assert rows["LF-GNSS EKF, per-dataset model"].create().noise.metadata["feature_names"]


def test_one_test_sequence_carries_every_feature_the_models_read():
    plain = SimpleNamespace(noise=SimpleNamespace())                        # hand-set noise: no feature names
    extra = SimpleNamespace(noise=SimpleNamespace(feature_names=("cn0", "residual_weighted", "elevation")))
    names = _features_for([plain, extra, extra])
    assert names == DEFAULT_FEATURES + ("residual_weighted",)


def _row(dataset, method, d3, d2):
    return {"dataset": dataset, "method": method, "trained_on": "-", "rmse_3d_m": d3, "rmse_2d_m": d2}


def test_target_rows_compare_each_learned_row_with_its_bars():
    all_rows = [_row("hk-tst-2019", PLAIN, 13.0, 5.0), _row("hk-tst-2019", "LF-GNSS EKF", 9.0, 4.0),
                _row("hk-tst-2019", "LF-GNSS FGO", 12.5, 3.0), _row("hk-tst-2019", "LF-GNSS EKF w/o HEM", 9.5, 4.0),
                _row("hk-tst-2019", PLAIN_RTS, 8.0, 4.0), _row("hk-tst-2019", "LF-GNSS EKF + RTS smoother", 7.0, 3.0)]
    rtk_rows = [_row("hk-tst-2019", "LF-GNSS EKF", 8.0, 3.0), _row("hk-tst-2019", RTKLIB, 8.71, 3.88)]
    rows = {r["method"]: r for r in target_rows(all_rows, rtk_rows)}
    assert set(rows) == {"LF-GNSS EKF", "LF-GNSS FGO", "LF-GNSS EKF + RTS smoother"}   # not ablations, baselines
    ekf, fgo = rows["LF-GNSS EKF"], rows["LF-GNSS FGO"]
    assert ekf["3D vs target"] == "9.00 vs 10.00 (yes)" and ekf["2D vs target"] == "4.00 vs 3.50 (no)"
    assert ekf["3D vs plain EKF"] == "9.00 vs 13.00 (yes)"
    assert ekf["3D vs yardstick"] == "9.00 vs 14.00 (yes)"                  # the yardstick's EKF ...
    assert fgo["3D vs yardstick"] == "12.50 vs 12.20 (no)"                  # ... and its robust graph
    assert ekf["3D vs RTKLIB, its epochs"] == "8.00 vs 8.71 (yes)"
    assert fgo["3D vs RTKLIB, its epochs"] == "-"                           # no row on RTKLIB's epochs
    rts = rows["LF-GNSS EKF + RTS smoother"]                                # a smoother: against smoothers
    assert rts["3D vs plain EKF"] == "7.00 vs 8.00 (yes)" and rts["3D vs yardstick"] == "7.00 vs 12.20 (yes)"
    assert "| 3D vs target |" in markdown_table(list(rows.values()))
