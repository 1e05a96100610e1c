"""benchmarks/rtklib_epochs.py: our filters and RTKLIB scored on the epochs RTKLIB solved, split by split."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import estimators
from estimators.ekf import config_of
from learning.export import load_model
from lfgnss import datasets
from lfgnss.benchmark import MODEL_DIR
from lfgnss.metrics import accuracy_table
from lfgnss.outputs import align_to
from lfgnss.rtklib import spp_solution

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import rtklib_epochs  # noqa: E402

LEARNED = "LF-GNSS EKF (lfgnss-default.npz)"


def test_every_row_is_scored_on_rtklibs_own_epochs(tmp_path, monkeypatch, sample_toml, rnx2rtkp):
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    spec = datasets.register_toml(sample_toml("my-drive", splits=((0, 150), (150, 180), (180, 200))))
    rows = rtklib_epochs.run(["my-drive"], ("train", "val"))
    own = "plain EKF in the per-dataset model's filter"        # the joint model's filter (vertical noise) since session 23
    assert [(r["split"], r["method"]) for r in rows] == [
        (s, m) for s in ("train", "val") for m in (rtklib_epochs.RTKLIB, "plain EKF", LEARNED, own)]

    seq = datasets.load_split("my-drive", "train")[0]             # the bundled drive's first 150 s: one run
    sol, _ = spp_solution(spec.obs[0], list(spec.nav), tmp_path / "rtk.pos", systems=spec.systems)
    rtk = align_to(seq.time_gps_s, sol)
    ok = np.isfinite(rtk).all(axis=1) & np.isfinite(seq.truth_ecef_m).all(axis=1)
    assert 0 < ok.sum() < len(seq)                                 # RTKLIB rejects most of this street
    joint = load_model(MODEL_DIR / "lfgnss-default.npz")
    solved = {rtklib_epochs.RTKLIB: rtk, "plain EKF": estimators.create("plain-ekf").solve(seq).pos_ecef_m,
              LEARNED: estimators.create("ekf", noise=joint).solve(seq).pos_ecef_m,
              own: estimators.create("plain-ekf", config=config_of(joint)).solve(seq).pos_ecef_m}
    for r in rows[:4]:
        want = accuracy_table(solved[r["method"]][ok], seq.truth_ecef_m[ok])
        assert (r["rtklib_epochs"], r["labelled"], r["solved"]) == (ok.sum(), len(seq), ok.sum())
        assert (r["rmse_u_m"], r["rmse_3d_m"]) == pytest.approx((want["rmse_u_m"], want["rmse_3d_m"]))
    assert all(r["rtklib_epochs"] == 0 for r in rows[4:])          # 150-180 s: RTKLIB solves none

    page = rtklib_epochs.markdown(rows, "cmd")
    assert f"| train ({ok.sum()} of {len(seq)}) | val (0 of " in page and page.count("| plain EKF |") == 1
    assert "nan" not in page and page.rstrip().splitlines()[-1].endswith("| - |")   # no epochs: "-", not nan


def test_without_rtklib_nothing_is_compared_and_the_page_is_kept(tmp_path, monkeypatch, capsys):
    import lfgnss.rtklib

    monkeypatch.setattr(lfgnss.rtklib, "rtklib_available", lambda: False)
    monkeypatch.setattr(rtklib_epochs, "DOC", tmp_path / "page.md")
    if datasets.get("hk-tst-static-2020").missing():                # no data is the other way to have no row
        monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path / "no-data"))
    assert rtklib_epochs.run(["hk-tst-static-2020"]) == []
    assert rtklib_epochs.main(["--datasets", "hk-tst-static-2020", "--write"]) == 2
    assert "nothing to compare" in capsys.readouterr().err and not (tmp_path / "page.md").exists()
    assert rtklib_epochs.main(["--datasets", "nope"]) == 2
    assert "unknown dataset nope" in capsys.readouterr().err
