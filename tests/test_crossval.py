"""learning.crossval: blocked folds over train + validation epochs, and the command on simulated data."""
import csv
import math

import numpy as np
import pytest

from learning.crossval import fold_sequences, main
from lfgnss.simulate import simulate_sequence


@pytest.fixture(scope="module")
def sequences():
    return [simulate_sequence(50, seed=1, name="a"), simulate_sequence(31, seed=2, name="b")]


@pytest.mark.parametrize("folds", [2, 3, 4])
def test_folds_partition_the_epochs_without_overlap(sequences, folds):
    # an epoch's global position in the concatenated order: its time within a, or 50 + its index in b
    position = {("a", t): k for k, t in enumerate(sequences[0].time_gps_s)}
    position.update({("b", t): 50 + k for k, t in enumerate(sequences[1].time_gps_s)})

    def positions(pieces):
        return sorted(position[(s.name[0], t)] for s in pieces for t in s.time_gps_s)

    for j in range(folds):
        train, held = fold_sequences(sequences, folds, j, min_epochs=1)
        block = np.array_split(np.arange(81), folds)[j]
        assert positions(held) == list(block)                          # exactly block j, one contiguous range
        assert positions(train) == sorted(set(range(81)) - set(block))


def test_block_across_a_sequence_boundary_and_bad_arguments(sequences):
    train, held = fold_sequences(sequences, 2, 1)                     # 81 epochs: block 1 = 41..80, end of a + all b
    assert [len(s) for s in held] == [9, 31] and [len(s) for s in train] == [41]
    with pytest.raises(ValueError, match="fold"):
        fold_sequences(sequences, 2, 2)
    with pytest.raises(ValueError, match="cannot make"):
        fold_sequences(sequences[:1], 30, 0)


def test_command_writes_per_fold_and_pooled_rows(tmp_path, capsys):
    args = ["--config", "learning/configs/default.toml", "--folds", "2", "--out", str(tmp_path), "--no-progress"]
    for s in ("data.datasets=['synthetic']", "data.synthetic.n_epochs=60", "data.window=20", "data.stride=10",
              "train.batch_size=4", "train.epochs=2"):
        args += ["--set", s]
    assert main(args) == 0
    with open(tmp_path / "crossval.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["fold"] for r in rows] == ["0", "1", "pooled"]
    for r in rows:
        for key in ("plain_ekf_rmse_3d_m", "untrained_rmse_3d_m", "last_rmse_3d_m", "best_rmse_3d_m",
                    "plain_ekf_smoothed_rmse_3d_m", "last_smoothed_rmse_3d_m", "plain_ekf_rmse_2d_m", "last_rmse_2d_m"):
            assert math.isfinite(float(r[key])) and float(r[key]) > 0
        assert float(r["best_rmse_3d_m"]) <= float(r["last_rmse_3d_m"]) + 1e-12
        for what in ("plain_ekf", "last"):                              # horizontal part of the same positions
            assert float(r[f"{what}_rmse_2d_m"]) < float(r[f"{what}_rmse_3d_m"])
        assert float(r["last_smoothed_rmse_3d_m"]) != float(r["last_rmse_3d_m"])          # the RTS pass ran
    n = [int(r["held_out_epochs"]) for r in rows]
    assert n[2] == n[0] + n[1] == 3 * 60                                # two train seeds + one val seed, 60 epochs each
    pooled = math.sqrt(sum(float(r["plain_ekf_rmse_3d_m"]) ** 2 * k for r, k in zip(rows[:2], n)) / n[2])
    assert float(rows[2]["plain_ekf_rmse_3d_m"]) == pytest.approx(pooled)
    for j in (0, 1):
        assert (tmp_path / f"fold{j}" / "log.csv").exists() and not (tmp_path / f"fold{j}" / "model.npz").exists()
    assert "| pooled |" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:        # never over an earlier run: one line, exit 2
        main(args)
    assert exit_info.value.code == 2 and "already holds a cross-validation" in capsys.readouterr().err


def test_one_fold_alone_matches_that_fold_of_the_whole_run(monkeypatch, tmp_path, capsys):
    """``--fold J`` trains only fold J, on the same pieces as the whole run, and writes no pooled row; a fold out
    of range is one line and exit 2."""
    import learning.crossval as cv
    from learning.train import load_config

    config = load_config("learning/configs/default.toml", ["data.datasets=['synthetic']", "data.synthetic.n_epochs=60",
                                                           "data.window=20", "data.stride=10"])
    monkeypatch.setattr(cv, "train", lambda *a, **k: [{"epoch": 0, "val_rmse_3d_m": 1.0}])
    monkeypatch.setattr(cv, "_saved_rmse_m", lambda *a, **k: (1.0, 0.5))
    whole = cv.crossval(config, 3, tmp_path / "all", progress=False)
    alone = cv.crossval(config, 3, tmp_path / "one", progress=False, only=[2])
    assert [r["fold"] for r in whole] == [0, 1, 2, "pooled"] and [r["fold"] for r in alone] == [2]
    assert alone[0] == whole[2]
    with open(tmp_path / "one" / "crossval.csv") as fh:
        assert [r["fold"] for r in csv.DictReader(fh)] == ["2"]
    with pytest.raises(SystemExit) as exit_info:
        main(["--config", "learning/configs/default.toml", "--folds", "3", "--fold", "3", "--out", str(tmp_path / "x"),
              "--set", "data.datasets=['synthetic']"])
    assert exit_info.value.code == 2 and "folds to run must be among 0..2, got [3]" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_each_fold_trains_on_the_other_blocks_and_scores_the_held_out_one(monkeypatch, tmp_path):
    """What ``prepare`` receives per fold: training pieces as the train split, the held-out block as validation."""
    import learning.crossval as cv
    from learning.train import load_config

    config = load_config("learning/configs/default.toml", ["data.datasets=['synthetic']", "data.synthetic.n_epochs=60",
                                                           "data.window=20", "data.stride=10"])
    seen = []
    real_prepare = cv.prepare

    def spy_prepare(cfg, source):
        seen.append((source("synthetic", "train", cfg), source("synthetic", "val", cfg)))
        return real_prepare(cfg, source)

    monkeypatch.setattr(cv, "prepare", spy_prepare)
    monkeypatch.setattr(cv, "train", lambda *a, **k: [{"epoch": 0, "val_rmse_3d_m": 1.0}])
    monkeypatch.setattr(cv, "_saved_rmse_m", lambda *a, **k: (1.0, 0.5))
    rows = cv.crossval(config, 3, tmp_path, progress=False)
    for j, (train, held) in enumerate(seen):
        assert all("/cv-train" in s.name for s in train) and all("/cv-held-out" in s.name for s in held)
        assert sum(len(s) for s in held) == rows[j]["held_out_epochs"] == 60       # 180 epochs in 3 blocks
        assert sum(len(s) for s in train) == 120
