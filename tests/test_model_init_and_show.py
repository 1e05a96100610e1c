"""The fine-tuning configs name their bundled init model (so they run from any folder), --show says
what a model file does and does not record and prints its stored configuration (--config), and a model file that
holds no training can be told (learning.export.untrained_reason)."""
import hashlib
import json
import shutil
from pathlib import Path

import pytest

from learning.export import (ModelFileError, _write_model_file, bundled_name, config_text, describe_model, load_model,
                             untrained_reason)
from learning.export import main as export_main
from learning.train import adopt_init, init_model, load_config
from learning.train import main as train_main
from lfgnss.paths import bundled_models
from tiny_training import TINY as BASE, sets

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "learning" / "configs"
TINY = BASE + ["data.burn_in=0"]



def _rewritten(source: str, out: Path, **metadata) -> Path:
    """A copy of a bundled model file with some metadata changed (so no longer that file's bytes)."""
    model = load_model(source)
    return _write_model_file(out, model.params, model.normaliser, {**model.metadata, **metadata}, model.members[1:])


@pytest.mark.parametrize("config, name", [("finetune.toml", "default"), ("hk_finetune.toml", "transfer-base")])
def test_the_fine_tuning_configs_find_their_init_model_from_any_folder(config, name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)                                 # not the repository root
    loaded = load_config(CONFIGS / config)
    assert loaded["train"]["init"] == name
    start = init_model(loaded)
    assert Path(start.path) == bundled_models()[name]
    assert adopt_init(loaded)["model"] == start.metadata["config"]["model"]


def test_a_relative_init_path_is_still_read_beside_the_config_then_from_the_current_folder(tmp_path, monkeypatch):
    folder, work = tmp_path / "configs", tmp_path / "work"
    (work / "sub").mkdir(parents=True)
    folder.mkdir()
    shutil.copy(bundled_models()["transfer-base"], folder / "mine.npz")
    shutil.copy(bundled_models()["default"], work / "sub" / "mine.npz")
    base = f'base = "{CONFIGS / "default.toml"}"\n'
    (folder / "beside.toml").write_text(base + '[train]\ninit = "mine.npz"\n')
    (folder / "cwd.toml").write_text(base + '[train]\ninit = "sub/mine.npz"\n')
    monkeypatch.chdir(work)
    beside = load_config(folder / "beside.toml")
    assert beside["train"]["init"] == str(folder / "mine.npz")
    assert bundled_name(init_model(beside).path) == "transfer-base"
    here = load_config(folder / "cwd.toml")
    assert here["train"]["init"] == "sub/mine.npz"              # not beside the config: as given, from the cwd
    assert bundled_name(init_model(here).path) == "default"
    (work / "default").write_text("not a model")                # a file of the name wins over the bundled model
    with pytest.raises(ModelFileError, match="^default: not an lfgnss model file"):
        init_model(load_config(CONFIGS / "finetune.toml"))


def test_the_readme_fine_tuning_command_runs_from_another_folder(tmp_path, monkeypatch, capsys):
    """README, "Your own data": learning.train --config .../finetune.toml from a folder of one's own (1 tiny epoch);
    the model records the bundled file it started from, and --show says so."""
    monkeypatch.chdir(tmp_path)
    assert train_main(["--config", str(CONFIGS / "finetune.toml"), "--out", "run", "--no-progress", *sets(TINY)]) == 0
    tuned = load_model(tmp_path / "run" / "model.npz")
    assert tuned.metadata["config"]["train"]["init"] == "default"
    record, default = tuned.metadata["init_model"], bundled_models()["default"]
    assert Path(record["path"]) == default
    assert record["sha256_16"] == hashlib.sha256(default.read_bytes()).hexdigest()[:16]
    capsys.readouterr()
    assert export_main(["--show", "run/model.npz"]) == 0
    shown = capsys.readouterr().out
    assert "trained on: synthetic (train), fine-tuned from hk-tst-2019+berlin-pp+hk-tst-static-2020 (train)" in shown
    assert f"configuration file: {CONFIGS / 'finetune.toml'} (" in shown and f" in {tmp_path}, git" in shown


def test_show_of_a_bundled_model_names_its_readme_row_and_how_to_print_its_configuration(tmp_path, capsys):
    assert export_main(["--show", "lfgnss/data/model/lfgnss-default.npz"]) == 0
    shown = capsys.readouterr().out
    assert ("configuration file: its path was not recorded, but the configuration itself is stored in the model: "
            "python -m learning.export --show default --config prints it") in shown
    assert ("provenance: not recorded (trained before lfgnss recorded the command and git commit); the command that "
            "made it is in the lfgnss-default.npz row of lfgnss/data/model/README.md") in shown
    assert "the full configuration is in the file" not in shown and "holds no training" not in shown
    readme = (ROOT / "lfgnss" / "data" / "model" / "README.md").read_text()
    assert "| `lfgnss-default.npz` |" in readme
    copy = tmp_path / "copy.npz"                                # the same bytes elsewhere: still that model
    shutil.copy(bundled_models()["hk-tst-2019"], copy)
    assert bundled_name(copy) == "hk-tst-2019"
    assert "lfgnss-hk-tst-2019.npz row of lfgnss/data/model/README.md" in "\n".join(describe_model(load_model(copy)))


def test_show_of_another_file_without_provenance_does_not_point_at_the_bundled_readme(tmp_path, capsys):
    mine = _rewritten("hk-tst-static-2020", tmp_path / "mine.npz", created_utc="2026-01-01T00:00:00+00:00")
    assert bundled_name(mine) is None
    assert export_main(["--show", str(mine)]) == 0
    shown = capsys.readouterr().out
    assert "provenance: not recorded (this file was written before lfgnss recorded how a model was made" in shown
    assert "README" not in shown
    assert f"python -m learning.export --show {mine} --config prints it" in shown


@pytest.mark.parametrize("name", sorted(bundled_models()))
def test_show_config_prints_toml_that_learning_train_reads_back(name, tmp_path, capsys):
    """Every bundled model's stored configuration, as TOML: learning.train --config reads back exactly the stored
    settings (a null, TOML has none, is left out: the default), plus today's defaults for settings added since."""
    assert export_main(["--show", name, "--config"]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"# The training configuration stored in {bundled_models()[name]}\n")
    (tmp_path / "stored.toml").write_text(text)
    loaded = load_config(tmp_path / "stored.toml")
    stored = load_model(name).metadata["config"]

    def agree(a: dict, b: dict, path: str = "") -> None:
        for key, value in b.items():
            if isinstance(value, dict):
                agree(a[key], value, f"{path}{key}.")
            elif value is not None:
                assert a[key] == value and type(a[key]) is type(value), f"{path}{key}"

    agree(loaded, stored)


def test_show_config_falls_back_to_json_and_refuses_what_it_cannot_print(tmp_path, capsys):
    odd = load_model("default").metadata["config"] | {"note": [1, None]}      # TOML has no null in a list
    model = load_model(_rewritten("default", tmp_path / "odd.npz", config=odd))
    assert json.loads(config_text(model)) == odd
    none = _rewritten("default", tmp_path / "none.npz", config=None)
    with pytest.raises(SystemExit) as exit_info:
        export_main(["--show", str(none), "--config"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and len(err.strip().splitlines()) == 1
    assert f"{none}: no training configuration is recorded in this model file" in err
    with pytest.raises(SystemExit) as exit_info:
        export_main(["--config"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and err[-1].endswith("--config goes with --show MODEL: it prints the training "
                                                          "configuration stored in that model file")


def test_a_model_file_that_holds_no_training_is_told_apart(tmp_path, capsys):
    """A run whose training epochs never beat the untrained network (lr 0 here) exports epoch 0 and learning.train
    warns; untrained_reason says the same of the file, and --show repeats it. Epoch 0 of a fine-tuning run is its
    train.init model, which is trained: no reason then, nor for the bundled models."""
    argv = ["--config", str(CONFIGS / "default.toml"), "--out", str(tmp_path / "run"), "--no-progress",
            *sets(TINY + ["train.lr=0", "train.eta_min=0"])]
    assert train_main(argv) == 0
    assert "holds no training" in capsys.readouterr().err
    untrained = load_model(tmp_path / "run" / "model.npz")
    assert untrained.metadata["epoch"] == 0 and untrained.metadata["init_model"] is None
    reason = untrained_reason(untrained)
    assert reason is not None and reason.startswith("holds no training: it is epoch 0 of its run")
    assert f"warning: {reason}" in describe_model(untrained)
    tuned = load_model(_rewritten("default", tmp_path / "tuned.npz", epoch=0, init_model={"path": "x.npz"}))
    assert untrained_reason(tuned) is None
    assert all(untrained_reason(load_model(path)) is None for path in bundled_models().values())


def test_solve_warns_of_a_model_file_that_holds_no_training(tmp_path, capsys):
    from lfgnss.solve import main as solve_main

    path = _rewritten("default", tmp_path / "blank.npz", epoch=0, init_model=None)
    assert solve_main(["--out", str(tmp_path / "out"), "--no-plots", "--quiet", "--model", str(path)]) == 0
    err = capsys.readouterr().err
    assert f"warning: {path}: holds no training" in err and "--no-model runs the hand-set noise instead" in err
    assert solve_main(["--out", str(tmp_path / "out"), "--no-plots", "--quiet"]) == 0
    assert "holds no training" not in capsys.readouterr().err


def test_a_model_trained_on_smoothed_positions_is_said_to_want_the_smoother(tmp_path, capsys):
    """Review: train.smooth = true picks the model on RTS-smoothed positions, but --show printed the figure bare and
    solve ran it forward without a word (the forward filter was 20 % worse than the figure shown)."""
    from lfgnss.solve import main as solve_main

    meta = load_model("hk-tst-2019").metadata
    config = {**meta["config"], "train": {**meta["config"]["train"], "smooth": True}}
    path = _rewritten("hk-tst-2019", tmp_path / "smoothed.npz", config=config)
    model = load_model(path)
    assert "(RTS-smoothed positions: use it with --smooth)" in describe_model(model)[1]
    assert "RTS-smoothed" not in describe_model(load_model("hk-tst-2019"))[1]
    assert solve_main(["--out", str(tmp_path / "out"), "--no-plots", "--quiet", "--model", str(path)]) == 0
    assert (f"warning: {path}: trained and selected on RTS-smoothed positions (train.smooth = true); this run filters "
            "forward only: add --smooth to run it as it was trained") in capsys.readouterr().err
    for extra in (["--smooth"], ["--backend", "fgo"]):
        assert solve_main(["--out", str(tmp_path / "out"), "--no-plots", "--quiet", "--model", str(path), *extra]) == 0
        assert "RTS-smoothed" not in capsys.readouterr().err


def test_fine_tuning_says_when_its_start_saw_the_validation_epochs(my_drive):
    """Review: learning.crossval warned that a train.init model had seen the epochs it scores, learning.train did not
    (its epoch-0 line, 'the line to beat', was the start's own validation epochs)."""
    from types import SimpleNamespace

    from learning.train import init_saw_validation

    start = SimpleNamespace(path="start.npz", metadata={"config": {"train": {"select": "last"}}, "data_fingerprints": [
        {"dataset": "berlin-pp", "split": "train"}, {"dataset": "berlin-pp", "split": "val"}]})
    config = {"data": {"datasets": ["berlin-pp"], "val_split": "val"}}
    assert init_saw_validation(start, config) == ["validated on berlin-pp val"]
    # the bundled default model on one's own copy of its Berlin drive: by the drive's files
    config = load_config(None, [f"data.datasets=['{my_drive}']"])
    lines = init_saw_validation(init_model({"train": {"init": "default"}}), config)
    assert lines == ["validated on berlin-pp val (its split as registered now): 148 of my-drive's 148 validation "
                     "epochs"]
