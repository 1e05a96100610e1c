"""--resume of learning.train: the run's own configuration, Ctrl-C, and checkpoints written whole (atomic)."""
import hashlib
import shutil
from pathlib import Path

import pytest
import torch

import learning.train as train_module
from learning.export import load_model
from learning.train import main

CONFIG = "learning/configs/default.toml"
TINY = ["data.datasets=['synthetic']", "data.synthetic.n_epochs=150", "data.window=20", "data.stride=10",
        "train.batch_size=4", "threads=1"]
RULE = ("a resumed run goes on with the configuration it was started with: only --set train.epochs=N (to extend the "
        "schedule), threads and device may change")


def _sets(settings: list[str]) -> list[str]:
    return [x for s in settings for x in ("--set", s)]


def _fails(argv: list[str], capsys, code: int = 2) -> str:
    """main(argv) exits ``code`` with one line on stderr and no traceback; that line."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == code
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err.strip()


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def one_epoch(tmp_path_factory):
    """A 1-epoch run started with --config (recorded in its checkpoint); tests copy it before resuming."""
    out = tmp_path_factory.mktemp("run") / "run"
    assert main(["--config", CONFIG, "--out", str(out), "--no-progress"] + _sets(TINY + ["train.epochs=1"])) == 0
    return out


@pytest.fixture
def run(one_epoch, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(one_epoch, out)
    return out


@pytest.mark.parametrize("setting, expected", [
    ("seed=5", "seed cannot change on --resume (0 -> 5)"),
    ("data.window=30", "data.window cannot change on --resume (20 -> 30)"),
    ("ekf.gate_sigma=5", "ekf.gate_sigma cannot change on --resume (3.0 -> 5)"),
    ("train.t_max=10", "train.t_max cannot change on --resume (50 -> 10)"),      # the saved scheduler keeps 50
    ("train.eta_min=0.0", "train.eta_min cannot change on --resume (0.0001 -> 0.0)"),
    ("train.lr=0.01", "train.lr cannot change on --resume (0.001 -> 0.01)"),
    ("train.select='last'", "train.select cannot change on --resume ('val' -> 'last')"),
])
def test_resume_refuses_a_setting_that_would_change_the_run(run, setting, expected, capsys):
    before = _digest(run / "last.pt")
    err = _fails(["--resume", "--out", str(run), "--no-progress", "--set", "train.epochs=2", "--set", setting], capsys)
    assert err.endswith(f"error: {run / 'last.pt'}: {expected}; {RULE} (start a new --out to train otherwise)"), err
    assert _digest(run / "last.pt") == before


def test_resume_names_every_changed_setting(run, capsys):
    err = _fails(["--resume", "--out", str(run), "--set", "seed=5", "--set", "data.window=30"], capsys)
    assert "seed cannot change on --resume (0 -> 5; nor can data.window)" in err, err


def test_resume_extends_the_schedule_and_keeps_the_runs_configuration(run, capsys):
    """train.epochs, threads and device may change; a --set equal to the run's own value (or to the filter's
    default for an unset [ekf] key) changes nothing and is accepted; the model file records the run's config."""
    started = torch.load(run / "last.pt", weights_only=False)["config"]
    argv = ["--resume", "--out", str(run), "--no-progress"]
    assert main(argv + _sets(["train.epochs=2", "threads=2", "seed=0", "data.window=20", "ekf.gate_sigma=3.0"])) == 0
    config = load_model(run / "model.npz").metadata["config"]
    assert config == {**started, "threads": 2, "train": {**started["train"], "epochs": 2}}
    assert config["ekf"] == {}                              # not recorded as if set
    err = _fails(argv + ["--set", "train.epochs=1"], capsys)           # a schedule does not shrink below its epochs
    assert f"{run / 'last.pt'}: holds epoch 2 already, train.epochs = 1 is fewer; --resume can only extend the " \
           "schedule (train.epochs >= 2)" in err, err


def test_resume_refuses_a_config_other_than_the_runs_own_file(run, tmp_path, capsys):
    """The file the run was started from, unchanged, is accepted (tests/test_train.py resumes so); another file,
    or an edited one, is refused rather than silently ignored."""
    last = run / "last.pt"
    other = tmp_path / "other.toml"
    other.write_text(Path(CONFIG).read_text())
    err = _fails(["--config", str(other), "--resume", "--out", str(run)], capsys)
    assert f"error: --config {other}: {last} was started from {Path(CONFIG).resolve()}; {RULE}; leave out --config " \
           f"(--resume --out {run})" in err, err

    mine = tmp_path / "mine.toml"                                     # a run started from a file later edited
    mine.write_text(f'base = "{Path(CONFIG).resolve()}"\n[train]\nlr = 1e-3\n')
    out = tmp_path / "mine"
    assert main(["--config", str(mine), "--out", str(out), "--no-progress"] + _sets(TINY + ["train.epochs=1"])) == 0
    mine.write_text(f'base = "{Path(CONFIG).resolve()}"\n[train]\nlr = 1e-2\n')
    err = _fails(["--config", str(mine), "--resume", "--out", str(out), "--set", "train.epochs=2"], capsys)
    assert f"error: {mine}: train.lr is 0.01 now, 0.001 when {out / 'last.pt'} was started; {RULE}" in err, err

    plain = tmp_path / "plain"                                        # started without --config
    assert main(["--out", str(plain), "--no-progress"] + _sets(TINY + ["train.epochs=1"])) == 0
    err = _fails(["--config", CONFIG, "--resume", "--out", str(plain)], capsys)
    assert f"--config {CONFIG}: {plain / 'last.pt'} was started without a --config it recorded" in err, err


def test_ctrl_c_is_one_line_naming_the_epoch_kept_and_resuming_gives_the_uninterrupted_run(tmp_path, monkeypatch,
                                                                                          capsys):
    argv = ["--no-progress"] + _sets(TINY + ["train.epochs=2"])
    assert main(argv + ["--out", str(tmp_path / "straight")]) == 0
    calls = []
    evaluate = train_module.evaluate

    def stopped_in_epoch_2(*args, **kwargs):               # epoch 0, epoch 1, then Ctrl-C in epoch 2
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return evaluate(*args, **kwargs)

    out = tmp_path / "run"
    with monkeypatch.context() as patch:
        patch.setattr(train_module, "evaluate", stopped_in_epoch_2)
        err = _fails(argv + ["--out", str(out)], capsys, code=130)
    assert err == f"python -m learning.train: interrupted; {out / 'last.pt'} holds epoch 1: continue with " \
                  f"--resume --out {out}"
    assert main(["--resume", "--out", str(out), "--no-progress"]) == 0
    resumed = torch.load(out / "last.pt", weights_only=False)
    straight = torch.load(tmp_path / "straight" / "last.pt", weights_only=False)
    assert resumed["epoch"] == 2 and [h["val_rmse_3d_m"] for h in resumed["history"]] == \
        [h["val_rmse_3d_m"] for h in straight["history"]]
    for key, value in straight["model"].items():
        assert torch.equal(resumed["model"][key], value), key

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "prepare", interrupted)
    err = _fails(argv + ["--out", str(tmp_path / "early")], capsys, code=130)
    assert err == "python -m learning.train: interrupted before the first checkpoint was written (nothing to resume)"


def test_a_kill_while_writing_a_checkpoint_keeps_the_previous_one_whole(run, monkeypatch, capsys):
    """Checkpoints go to a temporary file renamed onto last.pt: one stopped mid-write leaves last.pt as it was."""
    save = torch.save

    def half_written(obj, path, *args, **kwargs):          # a kill halfway through writing epoch 2's best.pt
        Path(path).write_bytes(b"PK\x03\x04 half a checkpoint")
        raise KeyboardInterrupt

    before = _digest(run / "last.pt")
    monkeypatch.setattr(torch, "save", half_written)
    err = _fails(["--resume", "--out", str(run), "--no-progress", "--set", "train.epochs=2"], capsys, code=130)
    assert f"{run / 'last.pt'} holds epoch 1" in err, err
    monkeypatch.setattr(torch, "save", save)
    assert _digest(run / "last.pt") == before
    assert sorted(p.name for p in run.iterdir()) == ["best.pt", "curves.png", "last.pt", "log.csv", "model.npz"]
    assert main(["--resume", "--out", str(run), "--no-progress", "--set", "train.epochs=2"]) == 0


@pytest.mark.parametrize("damage", ["truncated", "foreign", "wrong weights"])
def test_a_checkpoint_that_cannot_be_read_is_one_line(run, damage, capsys):
    last = run / "last.pt"
    if damage == "truncated":
        last.write_bytes(last.read_bytes()[: last.stat().st_size // 2])
        reason = "(RuntimeError: PytorchStreamReader failed"
    elif damage == "foreign":
        torch.save({"weights": [1, 2]}, last)
        reason = "(ValueError: no training configuration in it)"
    else:
        saved = torch.load(last, weights_only=False)
        saved["model"] = {"embed.weight": torch.zeros(2, 2)}
        torch.save(saved, last)
        reason = "(RuntimeError: Error(s) in loading state_dict for LfgnssNet"
    err = _fails(["--resume", "--out", str(run), "--no-progress", "--set", "train.epochs=2"], capsys)
    assert f"error: {last}: cannot read the checkpoint {reason}" in err, err
    assert err.endswith("; start a new --out"), err
