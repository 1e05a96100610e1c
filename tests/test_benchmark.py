"""Benchmark rows (lfgnss.benchmark.methods): which estimators run for a dataset, from which model files."""
import shutil

from lfgnss.benchmark import MODEL_DIR, methods


def test_rows_follow_the_model_files(tmp_path):
    names = [m.name for m in methods(tmp_path, "berlin-pp")]
    assert names == ["least squares (equal weight)", "least squares (C/N0-weighted)", "plain EKF (C/N0 noise, gate)"]

    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-default.npz")
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-no_hem.npz")
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-berlin-pp.npz")
    rows = {m.name: m for m in methods(tmp_path, "berlin-pp")}
    assert {"LF-GNSS EKF", "LF-GNSS FGO", "LF-GNSS EKF w/o HEM", "LF-GNSS EKF, per-dataset model",
            "LF-GNSS FGO, per-dataset model"} <= set(rows)
    assert rows["LF-GNSS FGO, per-dataset model"].model == tmp_path / "lfgnss-berlin-pp.npz"
    assert rows["LF-GNSS FGO, per-dataset model"].backend == "fgo"
    # another dataset's own model is not used
    assert not any("per-dataset" in m.name for m in methods(tmp_path, "hk-tst-2019"))
    assert rows["LF-GNSS EKF, per-dataset model"].create().noise.metadata["feature_names"]
