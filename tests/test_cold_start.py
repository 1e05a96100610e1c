"""benchmarks/cold_start.py: each filter run cold and started at the true position, scored at the start and after."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

import estimators
from lfgnss import datasets
from lfgnss.metrics import accuracy_table

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import cold_start  # noqa: E402


def test_the_truth_start_changes_only_the_first_fix_and_p0(my_drive):
    seq = datasets.load_split(my_drive, "test")[0]
    started = cold_start.started_at_truth(seq)
    assert np.array_equal(started.coarse_ecef_m[0], seq.truth_ecef_m[0])
    assert np.array_equal(started.coarse_ecef_m[1:], seq.coarse_ecef_m[1:], equal_nan=True)
    ekf = estimators.create("ekf")
    config = cold_start.truth_start_config(ekf)
    assert config.p0_pos_m2 == cold_start.TRUE_START_SD_M ** 2
    assert dataclasses.replace(config, p0_pos_m2=ekf.config.p0_pos_m2) == ekf.config


def test_a_sequence_without_a_first_truth_starts_cold(my_drive):
    seq = datasets.load_split(my_drive, "test")[0]
    unlabelled = dataclasses.replace(seq, truth_ecef_m=np.full_like(seq.truth_ecef_m, np.nan))
    assert cold_start.started_at_truth(unlabelled) is unlabelled


def test_rows_score_both_starts_at_the_head_and_after(my_drive, tmp_path):
    rows, traces = cold_start.run([my_drive], ("train", "val", "test"), head_s=10.0)
    names = [name for name, _, _, _ in cold_start._runs(my_drive)]
    assert [(r["split"], r["filter"], r["start"]) for r in rows] == [
        (s, n, start) for s in ("train", "val", "test") for n in dict.fromkeys(names) for start in cold_start.STARTS]
    assert all(r["resets"] == 1 for r in rows)                    # each contiguous split: the start, no reset after

    seq = datasets.load_split(my_drive, "train")[0]
    since = seq.time_gps_s - seq.time_gps_s[0]
    plain_cold = estimators.create("plain-ekf").solve(seq)
    head = since < 10.0
    want = accuracy_table(plain_cold.pos_ecef_m[head], seq.truth_ecef_m[head])
    row = rows[0]
    assert (row["filter"], row["start"], row["head_epochs"]) == ("plain EKF", "cold", head.sum())
    assert row["head"] == pytest.approx((want["rmse_3d_m"], want["rmse_2d_m"]))

    warm = estimators.create("plain-ekf", config=cold_start.truth_start_config(estimators.create("plain-ekf")))
    first = warm.solve(cold_start.started_at_truth(seq)).pos_ecef_m[0]
    assert np.linalg.norm(first - seq.truth_ecef_m[0]) < 3 * cold_start.TRUE_START_SD_M * np.sqrt(3)
    assert np.linalg.norm(plain_cold.pos_ecef_m[0] - seq.truth_ecef_m[0]) > 5.0   # this street's first fix is off
    assert rows[1]["head"][0] < row["head"][0]

    t, err = traces[my_drive][("plain EKF", "cold")]
    assert t.shape == err.shape and np.isfinite(err).all() and t[0] == 0.0

    page = cold_start.markdown(rows, "cmd", head_s=10.0)
    assert "nan" not in page and "| train first 10 s (" in page and "Figure: `figures/cold_start.png`" in page
    assert "Figure:" not in cold_start.markdown(rows, "cmd", figure=False)
    assert cold_start.plot(traces, tmp_path / "cold.png", head_s=10.0).stat().st_size > 0


def test_a_split_shorter_than_the_head_has_no_rest(my_drive):
    rows, _ = cold_start.run([my_drive], ("val",), head_s=35.0)
    assert all(r["head_epochs"] == r["epochs"] and np.isnan(r["rest"][0]) for r in rows)
    assert cold_start.markdown(rows, "cmd").count(" | - |") == len(rows)


def test_a_written_page_and_its_figure_agree(my_drive, tmp_path, monkeypatch):
    """--write without the test split draws no figure: the page names none and an earlier run's figure goes; with
    it, the page names the figure drawn."""
    monkeypatch.setattr(cold_start, "REPO", tmp_path)
    monkeypatch.setattr(cold_start, "DOC", tmp_path / "cold_start.md")
    monkeypatch.setattr(cold_start, "FIGURE", tmp_path / "cold_start.png")
    cold_start.FIGURE.write_bytes(b"an earlier run's")
    assert cold_start.main(["--datasets", my_drive, "--splits", "val", "--write"]) == 0
    assert not cold_start.FIGURE.exists() and "Figure:" not in cold_start.DOC.read_text()
    assert cold_start.main(["--datasets", my_drive, "--splits", "test", "--write"]) == 0
    assert cold_start.FIGURE.stat().st_size > 0 and "Figure: `figures/cold_start.png`" in cold_start.DOC.read_text()


def test_unknown_datasets_are_refused_in_one_line(capsys):
    assert cold_start.main(["--datasets", "nope"]) == 2
    assert capsys.readouterr().err.strip().startswith("cold_start.py: unknown dataset nope; known:")
