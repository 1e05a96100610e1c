"""benchmarks/rtklib_epochs.py: our filters and RTKLIB scored on the epochs RTKLIB solved, split by split."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import estimators
from learning.export import load_model
from lfgnss import datasets
from lfgnss.benchmark import MODEL_DIR
from lfgnss.metrics import accuracy_table
from lfgnss.outputs import align_to
from lfgnss.rtklib import spp_solution

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import rtklib_epochs  # noqa: E402


def test_every_row_is_scored_on_rtklibs_own_epochs(tmp_path, monkeypatch, sample_toml, rnx2rtkp):
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    spec = datasets.register_toml(sample_toml("my-drive", splits=((0, 150), (150, 180), (180, 200))))
    rows = rtklib_epochs.run(["my-drive"], ("train", "val"))
    assert [(r["split"], r["method"]) for r in rows] == [
        (s, m) for s in ("train", "val") for m in (rtklib_epochs.RTKLIB, "plain EKF", "LF-GNSS EKF (lfgnss-default.npz)")]

    seq = datasets.load_split("my-drive", "train")[0]             # the bundled drive's first 150 s: one run
    sol, _ = spp_solution(spec.obs[0], list(spec.nav), tmp_path / "rtk.pos", systems=spec.systems)
    rtk = align_to(seq.time_gps_s, sol)
    ok = np.isfinite(rtk).all(axis=1) & np.isfinite(seq.truth_ecef_m).all(axis=1)
    assert 0 < ok.sum() < len(seq)                                 # RTKLIB rejects most of this street
    ekf = estimators.create("ekf", noise=load_model(MODEL_DIR / "lfgnss-default.npz")).solve(seq)
    want = {rtklib_epochs.RTKLIB: accuracy_table(rtk[ok], seq.truth_ecef_m[ok]),
            "LF-GNSS EKF (lfgnss-default.npz)": accuracy_table(ekf.pos_ecef_m[ok], seq.truth_ecef_m[ok])}
    for r in rows:
        if r["split"] == "train":
            assert r["rtklib_epochs"] == ok.sum() and r["labelled"] == len(seq)
            if r["method"] in want:
                assert r["rmse_3d_m"] == pytest.approx(want[r["method"]]["rmse_3d_m"])
                assert r["rmse_u_m"] == pytest.approx(want[r["method"]]["rmse_u_m"])

    page = rtklib_epochs.markdown(rows, "cmd")
    assert f"| train ({ok.sum()} of {len(seq)}) |" in page and page.count("| plain EKF |") == 1
    val = [r for r in rows if r["split"] == "val"]
    if val[0]["rtklib_epochs"] == 0:                               # a split RTKLIB never solved reads "-", not nan
        assert "nan" not in page and page.rstrip().splitlines()[-1].endswith("| - |")


def test_without_any_dataset_the_page_is_not_overwritten(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path / "no-data"))
    monkeypatch.setattr(rtklib_epochs, "DOC", tmp_path / "page.md")
    assert rtklib_epochs.main(["--datasets", "berlin-pp", "--write"]) == 2
    assert "nothing to compare" in capsys.readouterr().err and not (tmp_path / "page.md").exists()
