"""What learning.train and learning.crossval print: one line per epoch (epoch 0 included) with or without
--no-progress, no progress-bar debris where stderr is not a terminal, what to do with the model, a resume that has
nothing to train, an unknown data.drop_features name, and crossval's fold headers and train.init note."""
import math
import shutil

import pytest

from learning.crossval import _start_note, main as crossval_main
from learning.data import resolve_feature_names
from learning.train import main as train_main
from tiny_training import TINY, sets

CONFIG = "learning/configs/default.toml"



@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 1-epoch run with progress bars asked for (stderr is not a terminal here): (its --out, stdout, stderr)."""
    out = tmp_path_factory.mktemp("messages") / "run"
    capture = pytest.MonkeyPatch()
    import io
    import sys

    stdout, stderr = io.StringIO(), io.StringIO()
    capture.setattr(sys, "stdout", stdout)
    capture.setattr(sys, "stderr", stderr)
    try:
        assert train_main(["--config", CONFIG, "--out", str(out)] + sets(TINY)) == 0
    finally:
        capture.undo()
    return out, stdout.getvalue(), stderr.getvalue()


def test_epoch_lines_the_next_step_and_no_bar_debris_off_a_terminal(run):
    out, stdout, stderr = run
    lines = stdout.splitlines()
    assert lines[0].startswith("epoch 0 (untrained): val 3D RMSE ") and lines[0].endswith(" s)")
    assert lines[1].startswith("epoch 1: train loss ") and ", val 3D RMSE " in lines[1]
    assert lines[2].startswith(f"{out}: best validation 3D RMSE ")
    model = out / "model.npz"
    assert lines[3] == (f"use it: python -m lfgnss.solve --model {model} --obs OBS --nav NAV ... (without --obs: the "
                        f"bundled Berlin drive; python -m learning.export --show {model} describes the model)")
    assert "\r" not in stderr and "batch" not in stderr and "epoch 1/1" not in stderr, stderr   # no tqdm bar


def test_no_progress_keeps_the_epoch_lines_and_a_finished_resume_says_so(run, tmp_path, capsys):
    out, _, _ = run
    again = tmp_path / "run"
    shutil.copytree(out, again)
    assert train_main(["--resume", "--out", str(again), "--no-progress", "--set", "train.epochs=2"]) == 0
    shown = capsys.readouterr().out
    assert "epoch 2: train loss " in shown and "epoch 1:" not in shown and "already at" not in shown
    assert train_main(["--resume", "--out", str(again), "--no-progress"]) == 0
    shown = capsys.readouterr().out.splitlines()
    assert shown[0] == f"{again}: already at epoch 2 of 2; extend with --set train.epochs=M (M > 2)"
    assert not any(line.startswith("epoch ") for line in shown)


def test_epoch_0_of_a_fine_tuning_run_is_the_starting_model(run, tmp_path, capsys):
    out, _, _ = run
    argv = ["--config", CONFIG, "--out", str(tmp_path / "tuned"), "--no-progress"]
    assert train_main(argv + sets(TINY + [f"train.init={out / 'model.npz'}"])) == 0
    shown = capsys.readouterr().out.splitlines()
    assert shown[0].startswith("epoch 0 (start: train.init model): val 3D RMSE ")


@pytest.mark.parametrize("name, hint", [("dpc_gdp", " (did you mean 'dpc_gdop'?)"), ("azimut", " (did you mean "
                                        "'azimuth'?)"), ("x", "")])
def test_an_unknown_drop_feature_is_one_line_exit_2(name, hint, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train_main(["--out", str(tmp_path / "run")] + sets(TINY + [f"data.drop_features=['{name}']"]))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert f"error: data.drop_features: unknown feature {name!r}{hint}; it takes names of data.features (" in err
    assert not (tmp_path / "run").exists()                  # refused before anything is loaded or written


def test_drop_features_takes_features_and_dpc():
    assert resolve_feature_names(None, ["dpc"]) == ("cn0", "elevation", "azimuth", "residual")
    assert resolve_feature_names(["cn0", "elevation"], ["elevation"]) == ("cn0",)
    assert resolve_feature_names(["cn0"], ["track_age"]) == ("cn0",)      # a known feature not in the list: no-op
    with pytest.raises(ValueError, match="unknown feature 'cn00' \\(did you mean 'cn0'\\?\\)"):
        resolve_feature_names(None, ["cn00"])
    with pytest.raises(ValueError, match="^data.features: unknown feature 'bogus'; available: cn0, "):
        resolve_feature_names(["cn0", "bogus"])     # also with train.init, whose model's features replace the list


def test_an_unknown_feature_is_refused_when_fine_tuning_too(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        train_main(["--config", "finetune", "--out", str(tmp_path / "run"),
                    "--set", "data.features=['cn0', 'bogus']"])
    assert exit_info.value.code == 2
    assert "error: data.features: unknown feature 'bogus'" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_crossval_heads_each_fold_and_notes_the_starting_model(run, tmp_path, capsys):
    out, _, _ = run
    argv = ["--config", CONFIG, "--folds", "2", "--no-progress", "--out", str(tmp_path / "cv")]
    settings = ["data.datasets=['synthetic']", "data.synthetic.n_epochs=60", "data.window=20", "data.stride=10",
                "train.batch_size=4", "train.epochs=1", "threads=1", f"train.init={out / 'model.npz'}"]
    assert crossval_main(argv + sets(settings)) == 0
    shown = capsys.readouterr().out.splitlines()
    heads = [i for i, line in enumerate(shown) if line.startswith("fold ")]
    assert len(heads) == 2
    for j, i in enumerate(heads):
        assert shown[i].startswith(f"fold {j} ({j + 1}/2): training on ") and " piece(s), holding out " in shown[i]
        assert shown[i + 1].startswith("epoch 0 (start: train.init model): ")
        assert shown[i + 2].startswith("epoch 1: train loss ")
    held = sum(int(shown[i].split("holding out ")[1].split()[0]) for i in heads)
    assert held == 3 * 60                                   # two train seeds + one val seed, all held out once
    note = f"untrained_rmse_3d_m is the starting model (train.init = {out / 'model.npz'})"
    assert note in (tmp_path / "cv" / "crossval.md").read_text()


def test_no_starting_model_note_without_train_init_or_without_the_column():
    rows = [{"untrained_rmse_3d_m": 3.0}]
    assert _start_note(None, rows) == "" and _start_note("", rows) == ""
    assert _start_note("m.npz", [{"untrained_rmse_3d_m": math.nan}]) == ""          # --reuse: the column is empty
    assert "train.init = m.npz" in _start_note("m.npz", rows)


def test_the_library_call_prints_no_epoch_lines_unless_asked(tmp_path, capsys):
    """train(progress=False) stays quiet on stdout (a caller such as benchmarks/train_speed.py prints its own
    table there); epoch_lines=True prints them without a bar."""
    from learning.train import load_config, train

    config = load_config(CONFIG, TINY)
    train(config, tmp_path / "quiet", progress=False, export=False)
    assert capsys.readouterr().out == ""
    train(load_config(CONFIG, TINY), tmp_path / "lines", progress=False, export=False, epoch_lines=True)
    shown = capsys.readouterr().out.splitlines()
    assert shown[0].startswith("epoch 0 (untrained): ") and shown[1].startswith("epoch 1: train loss ")


def test_an_empty_split_of_a_registered_dataset_names_its_axis_bounds_and_file(sample_toml, tmp_path, capsys):
    path = sample_toml("my-off", splits=((0, 150), (1000, 1010), (180, 200)))      # the drive lasts 283 s
    argv = ["--config", CONFIG, "--out", str(tmp_path / "run"), "--no-progress",
            *sets(TINY[1:] + [f"data.register=['{path}']", "data.datasets=['my-off']"])]
    with pytest.raises(SystemExit) as stop:
        train_main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert (f"dataset 'my-off' split 'val' gave no sequence: [splits] axis = 'relative_s', val = [1000, 1010) in "
            f"{path}; check them against the drive (python -m lfgnss.datasets --register {path})") in err


@pytest.mark.parametrize("command", ["train", "crossval"])
def test_warnings_are_one_line_each(command, tmp_path, capsys, monkeypatch):
    """A warning during training (an unusable cache, a dropped constellation) is ``warning: ...`` on one line, not
    Python's two lines with the source line that raised it; the warning filters are as they were afterwards."""
    import warnings

    import learning.crossval as cv
    import learning.train as tr

    def warns(*args, **kwargs):
        warnings.warn("dataset x: constellation(s) J of its systems have no usable observation\nand are left out")
        raise KeyboardInterrupt

    monkeypatch.setattr(tr if command == "train" else cv, command, warns)
    before = warnings.showwarning
    with pytest.raises(SystemExit) as exit_info:
        (train_main if command == "train" else crossval_main)(["--out", str(tmp_path / "run")] + sets(TINY))
    assert exit_info.value.code == 130
    assert capsys.readouterr().err.splitlines()[0] == ("warning: dataset x: constellation(s) J of its systems have no "
                                                       "usable observation and are left out")
    assert warnings.showwarning is before


def test_a_smoothed_run_names_smooth_in_its_next_step(tmp_path, capsys):
    """train.smooth = true selects on RTS-smoothed positions: the 'use it' line runs the model with --smooth."""
    out = tmp_path / "smoothed"
    argv = ["--config", CONFIG, "--out", str(out), "--no-progress"] + sets(TINY + ["train.smooth=true"])
    assert train_main(argv) == 0
    model = out / "model.npz"
    assert f"use it: python -m lfgnss.solve --model {model} --smooth --obs OBS" in capsys.readouterr().out


def test_a_failed_filter_update_is_divergence_exit_3(tmp_path, capsys, monkeypatch):
    """A collapsed R makes the torch EKF's solve raise LinAlgError: a traceback before, now the exit-3 line."""
    import torch

    import learning.torch_ekf

    def singular(*args, **kwargs):
        raise torch.linalg.LinAlgError("linalg.solve: The solver failed because the input matrix is singular.")

    monkeypatch.setattr(learning.torch_ekf, "batch_ekf", singular)
    with pytest.raises(SystemExit) as info:
        train_main(["--config", CONFIG, "--out", str(tmp_path / "r"), "--no-progress"] + sets(TINY))
    err = capsys.readouterr().err
    assert info.value.code == 3 and "the filter's update failed (linalg.solve: The solver failed" in err, err
    assert "training stopped (exit status 3)" in err
