"""learning.crossval: blocked folds over train + validation epochs, and the command on simulated data."""
import csv
import math
from pathlib import Path

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


RECIPE = ["--config", "learning/configs/default.toml", "--folds", "2", "--no-progress"]
for _s in ("data.datasets=['synthetic']", "data.synthetic.n_epochs=60", "data.window=20", "data.stride=10",
           "train.batch_size=4", "train.epochs=2"):
    RECIPE += ["--set", _s]


def _rows(folder):
    with open(folder / "crossval.csv") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """One small cross-validation on simulated data: (its --out folder, its command-line arguments)."""
    out = tmp_path_factory.mktemp("cv")
    args = RECIPE + ["--out", str(out)]
    assert main(args) == 0
    return out, args


def test_command_writes_per_fold_and_pooled_rows(trained_run, capsys):
    tmp_path, args = trained_run
    rows = _rows(tmp_path)
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
    from learning.train import load_checkpoint

    for j in (0, 1):                                                    # each fold records its --config as train does
        record = load_checkpoint(tmp_path / f"fold{j}" / "last.pt")["config_file"]
        assert record["path"] == str(Path(RECIPE[1]).resolve()) and record["settings"]["data"]["window"] == 40
    pooled = math.sqrt(sum(float(r["plain_ekf_rmse_3d_m"]) ** 2 * k for r, k in zip(rows[:2], n)) / n[2])
    assert float(rows[2]["plain_ekf_rmse_3d_m"]) == pytest.approx(pooled)
    for j in (0, 1):
        assert (tmp_path / f"fold{j}" / "log.csv").exists() and not (tmp_path / f"fold{j}" / "model.npz").exists()
    with pytest.raises(SystemExit) as exit_info:        # never over an earlier run: one line, exit 2
        main(args)
    assert exit_info.value.code == 2 and "already holds a cross-validation" in capsys.readouterr().err


def test_reuse_scores_the_saved_fold_models_again_under_new_filter_settings(trained_run, tmp_path, capsys,
                                                                           monkeypatch):
    """``--reuse`` trains nothing: unchanged settings give the run's own figures back; an [ekf] change moves them;
    any other change, a missing run or a changed held-out block is one line and exit 2."""
    import torch

    run, _ = trained_run
    assert main(RECIPE + ["--out", str(tmp_path / "same"), "--reuse", str(run)]) == 0
    assert not (tmp_path / "same" / "fold0").exists()                       # nothing trained
    again, first = _rows(tmp_path / "same"), _rows(run)
    for a, b in zip(again, first):
        for key in ("held_out_epochs", "plain_ekf_rmse_3d_m", "last_rmse_3d_m", "plain_ekf_smoothed_rmse_3d_m",
                    "last_smoothed_rmse_3d_m", "plain_ekf_rmse_2d_m", "last_rmse_2d_m"):
            assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-9), key
        assert math.isnan(float(a["untrained_rmse_3d_m"])) and math.isnan(float(a["best_rmse_3d_m"]))
    printed = capsys.readouterr().out
    assert "| pooled | 180 | " in printed and "next:" not in printed              # a rescore trains nothing
    assert main(RECIPE + ["--out", str(tmp_path / "gate"), "--reuse", str(run), "--set", "ekf.gate_sigma=2.0"]) == 0
    gated = _rows(tmp_path / "gate")
    assert all(float(a["plain_ekf_rmse_3d_m"]) != float(b["plain_ekf_rmse_3d_m"]) for a, b in zip(gated, first))
    assert all(float(a["last_rmse_3d_m"]) != float(b["last_rmse_3d_m"]) for a, b in zip(gated, first))
    capsys.readouterr()
    for extra, message in ((["--set", "seed=3"], "fold0/last.pt: trained with seed = 0, this run has 3; a rescore "
                                                 "may change only ekf, threads, device settings"),
                           (["--set", "train.epochs=3"], "trained with train.epochs = 2, this run has 3")):
        with pytest.raises(SystemExit) as exit_info:
            main(RECIPE + extra + ["--out", str(tmp_path / "x"), "--reuse", str(run)])
        assert exit_info.value.code == 2 and message in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(RECIPE + ["--out", str(tmp_path / "y"), "--reuse", str(tmp_path / "none")])
    assert exit_info.value.code == 2 and "none/fold0/last.pt: no saved fold model" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:                            # a run of 2 folds rescored as 3
        main(RECIPE + ["--folds", "3", "--out", str(tmp_path / "v"), "--reuse", str(run)])
    assert exit_info.value.code == 2 and "fold2/last.pt: no saved fold model (--reuse takes the --out folder of an " \
        "earlier cross-validation of the same recipe and --folds; --folds 3 asks for fold 2)" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()
    tampered = tmp_path / "tampered" / "fold0"
    tampered.mkdir(parents=True)
    saved = torch.load(run / "fold0" / "last.pt", map_location="cpu", weights_only=False)
    saved["data_fingerprints"] = [dict(p, sha256_16="0" * 16) for p in saved["data_fingerprints"]]
    torch.save(saved, tampered / "last.pt")
    with pytest.raises(SystemExit) as exit_info:
        main(RECIPE + ["--fold", "0", "--out", str(tmp_path / "z"), "--reuse", str(tmp_path / "tampered")])
    assert exit_info.value.code == 2 and "its held-out block is not this run's" in capsys.readouterr().err
    saved["source_files"] = {"synthetic": {"drive.obs": "1234"}}     # the same files, another machine's features
    saved["provenance"] = dict(saved.get("provenance") or {}, git={"commit": "1" * 40, "dirty": False})
    torch.save(saved, tampered / "last.pt")

    def rescore(out: str, git: dict | None = None) -> int:
        """The tampered fold rescored, as if its input files were this run's (and the code at ``git``)."""
        with monkeypatch.context() as m:
            m.setattr("learning.train.source_file_hashes", lambda ds: {"drive.obs": "1234"})
            m.setattr("learning.provenance.git_state", lambda *a, **k: git or {"commit": "1" * 40, "dirty": False})
            return main(RECIPE + ["--fold", "0", "--out", str(tmp_path / out), "--reuse", str(tmp_path / "tampered")])

    assert rescore("z") == 0
    err = capsys.readouterr().err
    assert "warning: " + str(tampered / "last.pt") + ": its held-out block's features differ in the last digits from " \
        "those it was validated on when trained (the same input files, epochs and normalisation: another machine's " \
        "arithmetic); it is scored on this machine's features" in err and "trained at git" not in err
    assert float(_rows(tmp_path / "z")[0]["last_rmse_3d_m"]) == pytest.approx(float(first[0]["last_rmse_3d_m"]),
                                                                               rel=1e-9)     # scored as it was
    assert rescore("u", {"commit": "2" * 40, "dirty": True}) == 0
    assert "it was trained at git 111111111111 and this is git 222222222222 with uncommitted changes: if lfgnss's " \
        "front end differs between them" in capsys.readouterr().err
    toml = tmp_path / "drive.toml"
    toml.write_text('id = "drive"\n[truth]\nfile = "t.csv"\ntime_offset_s = 18\n')
    saved["provenance"]["dataset_tomls"] = {str(toml): toml.read_text().replace("18", "0")}
    torch.save(saved, tampered / "last.pt")
    with pytest.raises(SystemExit) as exit_info:                     # its dataset TOML says otherwise now: refused
        rescore("t")
    assert exit_info.value.code == 2 and f"its held-out block is not this run's ({toml}: truth.time_offset_s is 18 " \
        "now, unset when it was trained)" in capsys.readouterr().err
    saved["provenance"]["dataset_tomls"] = {str(toml): "(not readable: PermissionError)"}   # not read then: not judged
    torch.save(saved, tampered / "last.pt")
    assert rescore("q") == 0
    capsys.readouterr()
    saved["normaliser"] = dict(saved["normaliser"], mean=[m + 1.0 for m in saved["normaliser"]["mean"]])
    torch.save(saved, tampered / "last.pt")
    with pytest.raises(SystemExit) as exit_info:                     # its training blocks normalise otherwise
        rescore("s")
    assert exit_info.value.code == 2 and "its features are normalised otherwise than this run's beyond rounding" \
        in capsys.readouterr().err
    saved["source_files"] = {"synthetic": {"drive.obs": "5678"}}     # other input files: refused as before
    torch.save(saved, tampered / "last.pt")
    with pytest.raises(SystemExit) as exit_info:
        rescore("r")
    assert exit_info.value.code == 2 and "its held-out block is not this run's (its input files differ from this " \
        "run's" in capsys.readouterr().err
    (tampered / "last.pt").write_text("not a checkpoint")
    with pytest.raises(SystemExit) as exit_info:
        main(RECIPE + ["--fold", "0", "--out", str(tmp_path / "w"), "--reuse", str(tmp_path / "tampered")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "tampered/fold0/last.pt: not a learning.train checkpoint" in err
    assert "Traceback" not in err


def test_one_fold_alone_matches_that_fold_of_the_whole_run(monkeypatch, tmp_path, capsys):
    """``--fold J`` trains only fold J, on the same pieces as the whole run, and writes no pooled row; a fold out
    of range is one line and exit 2."""
    import learning.crossval as cv
    from learning.train import load_config

    config = load_config("learning/configs/default.toml", ["data.datasets=['synthetic']", "data.synthetic.n_epochs=60",
                                                           "data.window=20", "data.stride=10"])
    monkeypatch.setattr(cv, "train", lambda *a, **k: [{"epoch": 0, "val_rmse_3d_m": 1.0}])
    monkeypatch.setattr(cv, "_saved_rmse_m", lambda *a, **k: ({}, 1.0, 0.5))
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


def _spy_on_folds(monkeypatch, dataset_id: str) -> list:
    """Make crossval train nothing; the list it returns fills with each fold's (training pieces, held-out pieces) of
    ``dataset_id``, as ``prepare`` receives them."""
    import learning.crossval as cv

    seen = []
    real_prepare = cv.prepare

    def spy_prepare(cfg, source):
        seen.append((source(dataset_id, "train", cfg), source(dataset_id, "val", cfg)))
        return real_prepare(cfg, source)

    monkeypatch.setattr(cv, "prepare", spy_prepare)
    monkeypatch.setattr(cv, "train", lambda *a, **k: [{"epoch": 0, "val_rmse_3d_m": 1.0}])
    monkeypatch.setattr(cv, "_saved_rmse_m", lambda *a, **k: ({}, 1.0, 0.5))
    return seen


def test_each_fold_trains_on_the_other_blocks_and_scores_the_held_out_one(monkeypatch, tmp_path):
    """What ``prepare`` receives per fold: training pieces as the train split, the held-out block as validation."""
    import learning.crossval as cv
    from learning.train import load_config

    config = load_config("learning/configs/default.toml", ["data.datasets=['synthetic']", "data.synthetic.n_epochs=60",
                                                           "data.window=20", "data.stride=10"])
    seen = _spy_on_folds(monkeypatch, "synthetic")
    rows = cv.crossval(config, 3, tmp_path, progress=False)
    for j, (train, held) in enumerate(seen):
        assert all("/cv-train" in s.name for s in train) and all("/cv-held-out" in s.name for s in held)
        assert sum(len(s) for s in held) == rows[j]["held_out_epochs"] == 60       # 180 epochs in 3 blocks
        assert sum(len(s) for s in train) == 120


def test_scoring_runs_on_the_threads_setting_as_training_does(monkeypatch, tmp_path):
    """Folds run side by side with threads = 1 must not each score on every core (the plain EKF and the fold
    model's figures); the caller's thread count is given back, also when a fold fails."""
    import torch

    import learning.crossval as cv
    from learning.train import load_config

    config = load_config("learning/configs/default.toml", ["data.datasets=['synthetic']", "data.synthetic.n_epochs=60",
                                                           "data.window=20", "data.stride=10", "threads=1"])
    _spy_on_folds(monkeypatch, "synthetic")
    scored = []
    monkeypatch.setattr(cv, "_saved_rmse_m", lambda *a, **k: scored.append(torch.get_num_threads()) or ({}, 1.0, 0.5))
    monkeypatch.setattr(cv, "plain_ekf_rmse_m", lambda *a, **k: scored.append(torch.get_num_threads()) or (2.0, 1.0))
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        cv.crossval(config, 2, tmp_path / "a", progress=False)
        assert scored and set(scored) == {1} and torch.get_num_threads() == 2
        monkeypatch.setattr(cv, "plain_ekf_rmse_m", lambda *a, **k: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            cv.crossval(config, 2, tmp_path / "b", progress=False)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_diverging_fold_is_one_line_and_exit_3(tmp_path, capsys):
    """A non-finite training loss (here an overflowing loss weight) ends the run in one line, as learning.train."""
    with pytest.raises(SystemExit) as exit_info:
        main(RECIPE + ["--set", "loss.alpha=1e308", "--set", "train.epochs=1", "--fold", "0",
                       "--out", str(tmp_path / "cv")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 3 and err.count("\n") == 1 and "Traceback" not in err
    assert "non-finite training loss" in err and "cross-validation stopped" in err


def test_reuse_of_a_smoothed_recipe_reproduces_its_own_figure(tmp_path):
    """With train.smooth the run's last_rmse_3d_m is the smoothed RMSE; a rescore reports the same quantity."""
    smooth = RECIPE + ["--set", "train.smooth=true", "--fold", "0"]
    assert main(smooth + ["--out", str(tmp_path / "run")]) == 0
    assert main(smooth + ["--out", str(tmp_path / "again"), "--reuse", str(tmp_path / "run")]) == 0
    a, b = _rows(tmp_path / "again")[0], _rows(tmp_path / "run")[0]
    assert float(a["last_rmse_3d_m"]) == pytest.approx(float(b["last_rmse_3d_m"]), rel=1e-9)


def test_recipe_comparison_fills_defaults_and_resolves_paths(tmp_path, monkeypatch):
    """A key an older run did not record is its default; cfg/m.npz and /abs/cfg/m.npz are one file."""
    from learning.crossval import _recipe
    from learning.train import load_config

    monkeypatch.chdir(tmp_path)
    config = load_config(None, ["train.init=cfg/m.npz"])
    older = {k: (dict(v) if isinstance(v, dict) else v) for k, v in config.items()}
    del older["train"]["smooth"]
    older["train"]["init"] = str(tmp_path / "cfg" / "m.npz")
    assert _recipe(older) == _recipe(config)
    older["train"]["init"] = "other/m.npz"
    assert _recipe(older) != _recipe(config)


def test_several_datasets_get_a_row_each_per_fold_and_pooled(monkeypatch, tmp_path):
    """With two datasets each fold also gets one row per dataset (its model on that dataset's held-out pieces), and
    the pooled row of each dataset; the overall pooled row pools the fold rows only. Trained and rescored alike."""
    from dataclasses import replace

    import learning.crossval as cv
    import learning.train as train_module
    from learning.train import load_config, load_sequences

    hashes = train_module.source_file_hashes

    def two_sets(dataset_id, split, config):
        if dataset_id == "other":                   # a second dataset: the simulator's sequences under another name
            return [replace(s, name=s.name.replace("synthetic", "other"))
                    for s in load_sequences("synthetic", split, config)]
        return load_sequences(dataset_id, split, config)

    monkeypatch.setattr(cv, "load_sequences", two_sets)
    monkeypatch.setattr(train_module, "source_file_hashes", lambda ds: hashes("synthetic" if ds == "other" else ds))
    config = load_config("learning/configs/default.toml", [
        "data.datasets=['synthetic', 'other']", "data.synthetic.n_epochs=60", "data.window=20", "data.stride=10",
        "train.batch_size=4", "train.epochs=1", "threads=1"])
    rows = cv.crossval(config, 2, tmp_path / "cv", progress=False)
    folds = [r["fold"] for r in rows]
    assert folds == [0, "0:synthetic", "0:other", 1, "1:synthetic", "1:other", "pooled", "pooled:synthetic",
                     "pooled:other"]
    by = {r["fold"]: r for r in rows}
    for j in (0, 1):
        parts = [by[f"{j}:{ds}"] for ds in ("synthetic", "other")]
        assert sum(p["held_out_epochs"] for p in parts) == by[j]["held_out_epochs"]
        assert by[j]["last_rmse_3d_m"] == pytest.approx(cv.pooled_rmse([p["last_rmse_3d_m"] for p in parts],
                                                                       [p["held_out_epochs"] for p in parts]))
    assert by["pooled"]["held_out_epochs"] == by[0]["held_out_epochs"] + by[1]["held_out_epochs"]
    rescored = cv.crossval(config, 2, tmp_path / "again", progress=False, reuse=tmp_path / "cv")
    assert [r["fold"] for r in rescored] == folds
    for a, b in zip(rows, rescored):
        assert a["last_rmse_3d_m"] == pytest.approx(b["last_rmse_3d_m"]), a["fold"]


def test_folds_pool_by_their_labelled_epochs():
    """A fold's RMSE is over its labelled epochs: pooling by all held-out epochs gave a fold with truth gaps the
    weight of the epochs it never scored (a review's case: 35.5 m for 15.8 m)."""
    from learning.crossval import COLUMNS, pooled_rows

    def row(fold, held, scored, rmse):
        return {k: rmse for k in COLUMNS if k.endswith("_m")} | {"fold": fold, "held_out_epochs": held,
                                                                 "labelled_epochs": scored, "best_epoch": 1}

    pooled = pooled_rows([row(0, 100, 10, 50.0), row(1, 100, 90, 10.0)], [])[0]
    assert pooled["held_out_epochs"] == 200 and pooled["labelled_epochs"] == 100
    assert pooled["last_rmse_3d_m"] == pytest.approx(math.sqrt((10 * 50.0 ** 2 + 90 * 10.0 ** 2) / 100))


def test_pool_puts_parallel_fold_runs_in_one_table_with_the_pooled_rows(trained_run, tmp_path, capsys):
    """``--pool`` of one folder per fold (as ``--fold J`` runs leave them) gives the whole run's table back, pooled
    row included, training nothing; a fold missing or given twice, or folds of two recipes, is one line, exit 2."""
    import shlex
    import shutil

    import torch

    run, args = trained_run
    whole = _rows(run)
    command = f"python -m learning.crossval {shlex.join(args)}"
    assert (run / "crossval.md").read_text().startswith(f"Produced by `{command}` (")   # then the code's git commit
    for j in (0, 1):                                    # what `--fold j --out part<j>` leaves
        shutil.copytree(run / f"fold{j}", tmp_path / f"part{j}" / f"fold{j}")
        with open(tmp_path / f"part{j}" / "crossval.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(whole[0]))
            w.writeheader()
            w.writerow(whole[j])
    parts = ["--pool", str(tmp_path / "part0"), "--pool", str(tmp_path / "part1")]
    assert main(["--folds", "2", *parts, "--out", str(tmp_path / "all")]) == 0
    pooled = _rows(tmp_path / "all")
    assert [r["fold"] for r in pooled] == ["0", "1", "pooled"]
    for a, b in zip(pooled, whole):
        for key, value in b.items():
            assert value == a[key] if key in ("fold", "held_out_epochs", "labelled_epochs", "best_epoch") else \
                float(a[key]) == pytest.approx(float(value), rel=1e-12), key
    assert "| pooled | 180 | 180 | " in capsys.readouterr().out
    for j in (0, 1):                                    # a part written before labelled_epochs: all its epochs scored
        with open(tmp_path / f"part{j}" / "crossval.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=[k for k in whole[0] if k != "labelled_epochs"], extrasaction="ignore")
            w.writeheader()
            w.writerow(whole[j])
    assert main(["--folds", "2", *parts, "--out", str(tmp_path / "old")]) == 0
    assert [r["labelled_epochs"] for r in _rows(tmp_path / "old")] == [r["held_out_epochs"] for r in whole]
    capsys.readouterr()
    for argv, message in (
            (["--folds", "3", *parts], "fold(s) 2 of --folds 3 are in none of the --pool folders"),
            (["--folds", "2", *parts, "--pool", str(run)], "fold 0 is in"),
            (["--folds", "2", "--pool", str(tmp_path / "part0")], "fold(s) 1 of --folds 2 are in none"),
            (["--folds", "2", "--pool", str(tmp_path / "nowhere")], "nowhere/crossval.csv: cannot read it")):
        with pytest.raises(SystemExit) as exit_info:
            main(argv + ["--out", str(tmp_path / "x")])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    saved = torch.load(tmp_path / "part1" / "fold1" / "last.pt", map_location="cpu", weights_only=False)
    saved["config"]["seed"] = 7
    torch.save(saved, tmp_path / "part1" / "fold1" / "last.pt")
    with pytest.raises(SystemExit) as exit_info:
        main(["--folds", "2", *parts, "--out", str(tmp_path / "y")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "fold 1 was trained with seed = 7, fold 0 with 0; pool runs of one recipe" in err
    with pytest.raises(SystemExit) as exit_info:        # the recipe is the runs' own: --set is refused, not ignored
        main(["--folds", "2", *parts, "--set", "seed=1", "--out", str(tmp_path / "z")])
    assert exit_info.value.code == 2 and "--pool takes only --folds and an --out" in capsys.readouterr().err


def test_vc_term_script_scores_each_fold_model_on_its_held_out_block(trained_run, capsys):
    """benchmarks/vc_term.py: the v^c = 0 figure is compensation_loss of zeros over the same held-out satellites."""
    import sys
    from pathlib import Path

    import torch

    from learning.crossval import cv_sequences
    from learning.data import sequence_batch
    from learning.loss import compensation_loss, pseudorange_error_m
    from learning.normalise import Normaliser
    from learning.train import load_config

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import vc_term

    run, args = trained_run
    term, zero = vc_term.held_out_terms(run, folds=2)
    assert math.isfinite(term) and term > 0 and term != zero
    config = load_config("learning/configs/default.toml", [a for a in RECIPE if "=" in a])
    whole = cv_sequences(config)["synthetic"]
    sums, count = 0.0, 0
    for fold in range(2):
        normaliser = Normaliser.from_dict(torch.load(run / f"fold{fold}" / "last.pt", weights_only=False)["normaliser"])
        for piece in fold_sequences(whole, 2, fold)[1]:
            b = sequence_batch(piece, normaliser)
            usable = b.mask & torch.isfinite(b.truth_ecef_m).all(dim=-1)[..., None]
            n_sys = len(piece.systems)
            error = pseudorange_error_m(b.pr_m, b.sat_pos_ecef_m, b.truth_ecef_m, usable, b.system_index, n_sys)
            n = int(usable.sum())
            sums += float(compensation_loss(torch.zeros_like(error), error, usable, b.system_index, n_sys)) * n
            count += n
    assert zero == pytest.approx(sums / count, rel=1e-9)
    assert vc_term.main([str(run), "--folds", "2"]) == 0
    assert f"{run}: held-out v^c term {term:.2f} m^2 (v^c = 0: {zero:.2f} m^2)" in capsys.readouterr().out


def test_folds_are_not_cut_at_the_train_validation_boundary(monkeypatch, tmp_path, sample_toml):
    """Contiguous train and validation epochs are one piece to cut: a block across their boundary is held out whole,
    and the training pieces around it are whole too (before, each split was a separate sequence, so both broke)."""
    import learning.crossval as cv
    from learning.train import load_config
    from lfgnss import datasets

    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "_REGISTRY", {})
    toml = sample_toml("cv-berlin", splits=((0, 100), (100, 120), (120, 300)))
    config = load_config("learning/configs/default.toml", [f'data.register=["{toml}"]', "data.datasets=['cv-berlin']",
                                                           "data.window=20", "data.stride=10"])
    whole = cv.cv_sequences(config)["cv-berlin"]
    train, val = (datasets.load_split("cv-berlin", s) for s in ("train", "val"))
    assert len(whole) == 1 and len(whole[0]) == len(train[0]) + len(val[0])
    seen = _spy_on_folds(monkeypatch, "cv-berlin")
    cv.crossval(config, 3, tmp_path / "cv", progress=False)
    boundary = val[0].time_gps_s[0]
    assert [(len(t), len(h)) for t, h in seen] == [(1, 1), (2, 1), (1, 1)]
    last_held = seen[2][1][0].time_gps_s                # the last block runs from train into validation, unbroken
    assert last_held[0] < boundary <= last_held[-1] and np.all(np.diff(last_held) < 0.5)


def test_a_finished_run_says_how_to_train_its_recipe(monkeypatch, tmp_path, capsys):
    """After the table: the learning.train command of the same --config and --set's, pasteable."""
    import learning.crossval as cv

    def fake_crossval(config, folds, out, **_):
        Path(out).mkdir()
        (Path(out) / "crossval.md").write_text("| fold |\n")

    monkeypatch.setattr(cv, "crossval", fake_crossval)
    assert main(["--config", "learning/configs/default.toml", "--set", "data.datasets=['a b']", "--set", "seed=2",
                 "--out", str(tmp_path / "cv")]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        "next: train this recipe on data.train_split (python -m learning.train --config learning/configs/default.toml "
        "--set 'data.datasets=['\"'\"'a b'\"'\"']' --set seed=2 --out runs/NAME)")
    assert cv.next_step(None, []) == ("next: train this recipe on data.train_split (python -m learning.train "
                                      "--out runs/NAME)")


def test_reuse_of_several_runs_scores_their_fold_models_as_one_ensemble(trained_run, tmp_path, capsys):
    """``--reuse A --reuse B``: per fold the ensemble of A's and B's models. Two copies of one network (seeds told
    apart) give that network's figures back exactly; a run with another seed gives figures of its own; two runs of
    one seed, or of different recipes, are one line and exit 2."""
    import shutil

    import torch

    run, _ = trained_run
    twin = tmp_path / "twin"
    for j in (0, 1):
        (twin / f"fold{j}").mkdir(parents=True)
        saved = torch.load(run / f"fold{j}" / "last.pt", map_location="cpu", weights_only=False)
        saved["config"]["seed"] = 7
        torch.save(saved, twin / f"fold{j}" / "last.pt")
    assert main(RECIPE + ["--out", str(tmp_path / "same"), "--reuse", str(run), "--reuse", str(twin)]) == 0
    for a, b in zip(_rows(tmp_path / "same"), _rows(run)):
        for key in ("last_rmse_3d_m", "last_smoothed_rmse_3d_m", "last_rmse_2d_m"):
            assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-9), key
    other = tmp_path / "seed1"
    assert main(RECIPE + ["--set", "seed=1", "--out", str(other)]) == 0
    assert main(RECIPE + ["--out", str(tmp_path / "ens"), "--reuse", str(run), "--reuse", str(other)]) == 0
    ens, one, two = _rows(tmp_path / "ens"), _rows(run), _rows(other)
    assert all(float(e["last_rmse_3d_m"]) not in (float(a["last_rmse_3d_m"]), float(b["last_rmse_3d_m"]))
               for e, a, b in zip(ens, one, two))
    assert [e["plain_ekf_rmse_3d_m"] for e in ens] == [a["plain_ekf_rmse_3d_m"] for a in one]
    # --combine mixture: identical members have no spread, so the twin ensemble is the network again; two seeds differ
    assert main(RECIPE + ["--out", str(tmp_path / "mix-same"), "--reuse", str(run), "--reuse", str(twin),
                          "--combine", "mixture"]) == 0
    for a, b in zip(_rows(tmp_path / "mix-same"), one):
        assert float(a["last_rmse_3d_m"]) == pytest.approx(float(b["last_rmse_3d_m"]), rel=1e-9)
    assert main(RECIPE + ["--out", str(tmp_path / "mix"), "--reuse", str(run), "--reuse", str(other),
                          "--combine", "mixture"]) == 0
    assert "--combine mixture" in (tmp_path / "mix" / "crossval.md").read_text().splitlines()[0]
    assert all(float(m["last_rmse_3d_m"]) != float(e["last_rmse_3d_m"]) for m, e in zip(_rows(tmp_path / "mix"), ens))
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main(RECIPE + ["--out", str(tmp_path / "m1"), "--reuse", str(run), "--combine", "mixture"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "needs two or more --reuse folders" in err and "Traceback" not in err
    shutil.copytree(run, tmp_path / "copy", ignore=shutil.ignore_patterns("crossval.*"))
    for reuse, message in (([run, tmp_path / "copy"], "copy/fold0/last.pt: trained with seed 0, as another --reuse "
                                                      "folder's"),
                           ([run, other], "trained with train.epochs = 2, this run has 3")):
        extra = ["--set", "train.epochs=3"] if "epochs" in message else []
        with pytest.raises(SystemExit) as exit_info:
            main(RECIPE + extra + ["--out", str(tmp_path / "x"), *[a for r in reuse for a in ("--reuse", str(r))]])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and message in err and "Traceback" not in err


def test_an_interrupted_run_says_how_to_finish_its_folds(tmp_path):
    """Review: Ctrl-C after fold 0 kept its rows, but the same command again was refused (the --out holds a
    cross-validation) and nothing said that a --fold run of the rest and --pool finish it."""
    import argparse

    from learning.crossval import _go_on

    out = tmp_path / "cv"
    exc = KeyboardInterrupt()
    exc.crossval_stopped = (out, out / "crossval.csv", [0])
    args = argparse.Namespace(only=None, folds=3, pool=None, reuse=None)
    said = _go_on(exc, args, f"python -m learning.crossval --config berlin --fold 0 --out {out} --set seed=1")
    assert said == (f"; to finish, run the fold(s) left into a folder of their own (python -m learning.crossval "
                    f"--config berlin --set seed=1 --fold 1 --fold 2 --out {out}-rest), then pool the two (python -m "
                    f"learning.crossval --folds 3 --pool {out} --pool {out}-rest --out {out}-all)")
    exc.crossval_stopped = (out, None, [])                     # stopped in fold 0: nothing to pool
    assert _go_on(exc, args, "python -m learning.crossval") == ""
