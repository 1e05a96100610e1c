"""Bad settings of learning.train: one line naming the file or key, exit 2, no traceback, nothing written."""
from pathlib import Path

import pytest

from learning.train import load_config, main

SYNTHETIC = ["data.datasets=['synthetic']"]
TINY = SYNTHETIC + ["data.synthetic.n_epochs=60", "data.window=20", "data.stride=10", "train.batch_size=4",
                    "train.epochs=1", "threads=1"]

BAD_SETTINGS = [
    ("loss.alpha=nan", "loss.alpha must be a finite number > 0, got nan"),
    ("loss.gamma=-1", "loss.gamma must be a finite number >= 0"),
    ("loss.lambda=inf", "loss.lambda must be a finite number >= 0"),
    ("loss.up_weight=-0.5", "loss.up_weight must be a finite number >= 0"),
    ("loss.kind='huber'", "loss.kind must be 'hem' or 'rmse'"),
    ("ekf=3", "ekf must be a table of settings, got 3"),
    ("data=1", "data must be a table of settings, got 1"),
    ("data.synthetic=5", "data.synthetic must be a table of settings"),
    ("train.batch_size=-2", "train.batch_size must be a whole number >= 1, got -2"),
    ("train.batch_size=0", "train.batch_size must be a whole number >= 1, got 0"),
    ("train.epochs=ten", "train.epochs must be a whole number >= 1, got 'ten'"),
    ("train.epochs=true", "train.epochs must be a whole number >= 1, got True"),
    ("train.epochs=2.5", "train.epochs must be a whole number >= 1"),
    ("data.window=0", "data.window must be a whole number >= 1, got 0"),
    ("data.stride=0", "data.stride must be a whole number >= 1"),
    ("train.t_max=0", "train.t_max must be a whole number >= 1"),
    ("model.d_model=0", "model.d_model must be a whole number >= 1, got 0"),
    ("model.n_heads=0", "model.n_heads must be a whole number >= 1"),
    ("model.d_model=6", "model.d_model must be a multiple of model.n_heads (4), got 6"),
    ("model.hidden=[64, 0]", "model.hidden must be a list of whole numbers >= 1"),
    ("train.lr=-1", "train.lr must be a finite number >= 0, got -1"),
    ("train.lr=nan", "train.lr must be a finite number >= 0, got nan"),
    ("train.eta_min=-1e-4", "train.eta_min must be a finite number >= 0"),
    ("train.weight_decay=inf", "train.weight_decay must be a finite number >= 0"),
    ("train.grad_clip=-1", "train.grad_clip must be a finite number >= 0"),
    ("threads=0", "threads must be a whole number >= 1"),
    ("seed=-1", "seed must be a whole number >= 0"),
    ("data.datasets=[]", "data.datasets must be a non-empty list of dataset ids"),
    ("data.datasets=[1]", "data.datasets must be a non-empty list of dataset ids"),
    ("ekf.gate_sigma='3'", "ekf.gate_sigma must be a number, got '3'"),
    ("ekf.gate_sigma=nan", "ekf.gate_sigma must be a number, got nan"),
    ("ekf.gate_sigma=-3", "ekf.gate_sigma must be >= 0, got -3"),
    ("ekf.q_vel_m2_s3=inf", "ekf.q_vel_m2_s3 must be finite, got inf"),
    ("train.epoch=5", "unknown configuration key 'train.epoch' (did you mean 'train.epochs'?)"),
    ("epochs=5", "unknown configuration key 'epochs' (did you mean 'train.epochs'?)"),
    ("data.synthetic.n_epoch=5", "unknown configuration key 'data.synthetic.n_epoch' (did you mean "
                                 "'data.synthetic.n_epochs'?)"),
    ("ekf.gate_sigm=5", "unknown [ekf] keys ['gate_sigm'] (did you mean 'ekf.gate_sigma'?); EkfConfig has"),
    ("data.train_split='train+'", "data.train_split must be a split name or names joined by '+' (e.g. "
                                  "\"train+val\"), each once and without spaces, got 'train+'"),
    ("data.train_split='train + val'", "data.train_split must be a split name or names joined by '+'"),
    ("data.val_split='val+val'", "data.val_split must be a split name or names joined by '+'"),
    ("data.train_split='train+test'", "data.train_split = 'train+test': the test split may not be used for training"),
    ("data.datasets=['synthetic', 'synthetic']",
     "data.datasets names 'synthetic' more than once (its data would count twice); name each dataset once, "
     "got ['synthetic', 'synthetic']"),
]


def _fails(argv: list[str], capsys) -> str:
    """main(argv) exits 2 with one line and no traceback; that line."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Warning" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    return err


@pytest.mark.parametrize("setting, expected", BAD_SETTINGS)
def test_a_bad_setting_is_named_in_one_line_before_anything_is_written(setting, expected, tmp_path, capsys):
    out = tmp_path / "run"
    argv = [x for s in SYNTHETIC + [setting] for x in ("--set", s)] + ["--out", str(out), "--no-progress"]
    err = _fails(argv, capsys)
    assert f"error: {expected}" in err, err
    assert not out.exists()                     # not even the folder: the settings are checked first


@pytest.mark.parametrize("text, expected", [
    ("ekf = 3\n", "ekf must be a table of settings ([ekf]), got 3"),
    ("data = 3\n", "data must be a table of settings ([data]), got 3"),
    ("base = 3\n", "base must be the path of a configuration file (a string), got 3"),
    ("[loss]\nalpha = nan\n", "loss.alpha must be a finite number > 0, got nan"),
    ("[data]\nwindow = 0\n", "data.window must be a whole number >= 1, got 0"),
    ("[data]\nsynthetic = 3\n", "data.synthetic must be a table of settings, got 3"),
    ("[trian]\nepochs = 3\n", "unknown configuration key 'trian' (did you mean 'train'?)"),
])
def test_a_bad_setting_of_a_file_names_the_file(text, expected, tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    out = tmp_path / "run"
    err = _fails(["--config", str(path), "--out", str(out)], capsys)
    assert f"error: {path}: {expected}" in err, err
    assert not out.exists()


def test_a_file_that_is_not_text_names_the_file(tmp_path, capsys):
    path = tmp_path / "noise.toml"
    path.write_bytes(bytes([0x8F, 0xFF, 0x00, 0xC3, 0x28, 0xA0, 0xA1]) * 20)
    err = _fails(["--config", str(path), "--out", str(tmp_path / "run")], capsys)
    assert f"error: {path}: cannot read configuration" in err, err
    assert not (tmp_path / "run").exists()


def test_a_setting_given_with_set_does_not_blame_the_file(tmp_path, capsys):
    """A file setting that an override puts right is fine; an override's own mistake names no file."""
    path = tmp_path / "mine.toml"
    path.write_text('base = "%s"\n[data]\nwindow = 0\n' % Path("learning/configs/synthetic.toml").resolve())
    assert load_config(path, ["data.window=20"])["data"]["window"] == 20
    err = _fails(["--config", "learning/configs/default.toml", "--set", "train.lr=-1"], capsys)
    assert "error: train.lr must be" in err and "default.toml" not in err


def test_single_names_are_one_item_lists():
    """data.datasets = "synthetic" (and features, drop_features, register) is one name, not its letters."""
    config = load_config(None, ["data.datasets=synthetic", "data.drop_features='dpc'"])
    assert config["data"]["datasets"] == ["synthetic"] and config["data"]["drop_features"] == ["dpc"]


@pytest.mark.parametrize("setting, expected", [
    ("model.r_init_m2=5.0", "model.r_init_m2 has no meaning with model.r_prior = 'heuristic'"),
    ("model.r_scale_m2=3.0", "model.r_scale_m2 = 3.0 is not read with model.r_prior = 'heuristic'")])
def test_settings_the_prior_makes_meaningless_are_refused(setting, expected):
    """With the prior, R = prior softplus(o_R) / ln 2 + floor: r_init_m2 set the bias as if R were r_scale_m2
    softplus(o_R) + floor (a review: 263 m^2 for r_init_m2 = 1), and r_scale_m2 was read nowhere."""
    assert load_config(None, [setting])["model"]                          # fine without the prior
    with pytest.raises(ValueError, match=expected):
        load_config(None, ["model.r_prior='heuristic'", setting])
    from learning.network import LfgnssNet

    with pytest.raises(ValueError, match="r_init_m2 has no meaning with r_prior"):
        LfgnssNet(8, r_init_m2=5.0, r_prior={"cn0_index": 0, "el_index": 1})


def test_every_shipped_config_passes_the_checks():
    for path in sorted(Path("learning/configs").glob("*.toml")):
        load_config(path)


def test_a_non_finite_gradient_of_a_finite_loss_stops_training(tmp_path, capsys, monkeypatch):
    """A finite loss with NaN gradients (sqrt at 0) must not reach Adam: exit 3 as a non-finite loss, not a run that
    goes on with NaN weights and logs a loss of 0."""
    import torch

    import learning.train

    monkeypatch.setattr(learning.train, "make_loss", lambda *a, **k: lambda pos, truth: torch.sqrt(
        (torch.nan_to_num(pos - truth) * 0.0).pow(2).sum()))
    out = tmp_path / "run"
    argv = [x for s in TINY for x in ("--set", s)] + ["--out", str(out), "--no-progress"]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 3
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "epoch 1: non-finite gradient of a finite training loss 0" in err
    assert (out / "last.pt").exists() and not (out / "model.npz").exists()


def test_a_non_finite_training_loss_is_one_line_and_keeps_the_checkpoints(tmp_path, capsys):
    """A finite but absurd loss.alpha overflows the loss: exit 3 (not bad input), one line, epoch-0 checkpoints kept."""
    out = tmp_path / "run"
    argv = [x for s in TINY + ["loss.alpha=1e308"] for x in ("--set", s)] + ["--out", str(out), "--no-progress"]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 3
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "epoch 1: non-finite training loss" in err and "training stopped" in err and str(out) in err
    assert (out / "last.pt").exists() and (out / "best.pt").exists()
    assert not (out / "model.npz").exists()


def test_a_key_with_nothing_close_gets_no_suggestion(capsys):
    err = _fails(["--set", "zzz=1"], capsys)
    assert err.strip().endswith("error: unknown configuration key 'zzz'"), err


def test_validating_on_the_training_split_is_warned_and_cross_validation_refuses_it(tmp_path, capsys):
    """data.val_split = data.train_split: learning.train runs (a dataset may have no validation split; with
    train.select = "last" the figure is only reported) but says in one line that its validation is optimistic;
    learning.crossval, which pools both splits into blocks, refuses it (each epoch would be there twice)."""
    from learning.crossval import main as crossval_main

    argv = [x for s in TINY + ["data.val_split='train'"] for x in ("--set", s)] + ["--no-progress"]
    assert main(argv + ["--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err
    assert "warning: data.val_split 'train' is trained on (data.train_split 'train'): the run's epoch is chosen on " \
           "its own training data, so best.pt and its validation RMSE are optimistic; use a held-out split, or " \
           "train.select = \"last\" with a schedule chosen by learning.crossval" in err, err
    assert err.count("warning") == 1
    with pytest.raises(SystemExit) as exit_info:
        crossval_main(argv + ["--out", str(tmp_path / "cv")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "error: data.val_split 'train' is trained on (data.train_split 'train'): cross-validation cuts the train " \
           "and validation epochs into blocks, so each epoch would be there twice, held out and trained on; give two " \
           "splits that share no epochs" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "cv").exists()


def test_training_on_train_plus_val_notes_that_its_validation_is_seen(tmp_path, capsys):
    """data.train_split = "train+val" (a refit on every non-test epoch, its schedule chosen by cross-validation):
    both splits' sequences are trained on, the run and its model file say its validation figure is on trained
    epochs, and cross-validation, which would hold out epochs it also trains on, refuses it in one line."""
    from learning.crossval import main as crossval_main
    from learning.export import describe_model, load_model
    from learning.train import load_sequences

    config = load_config(None, TINY)
    both = load_sequences("synthetic", "train+val", config)
    assert [s.name for s in both] == ([s.name for s in load_sequences("synthetic", "train", config)]
                                      + [s.name for s in load_sequences("synthetic", "val", config)])
    argv = [x for s in TINY + ["data.train_split='train+val'", "train.select='last'"] for x in ("--set", s)]
    assert main(argv + ["--no-progress", "--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err
    assert "note: data.val_split 'val' is trained on (data.train_split 'train+val'): its validation RMSE is " \
           "optimistic; train.select = \"last\" chooses nothing on it" in err and "warning" not in err, err
    model = load_model(tmp_path / "run" / "model.npz")
    assert {p["sequence"] for p in model.metadata["data_fingerprints"] if p["split"] == "train+val"} == \
        {s.name for s in both}
    shown = "\n".join(describe_model(model))
    assert "trained on: synthetic (train+val); epoch" in shown and " m (on trained epochs)" in shown, shown
    with pytest.raises(SystemExit) as exit_info:
        crossval_main(argv + ["--no-progress", "--out", str(tmp_path / "cv")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "error: data.val_split 'val' is trained on" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "cv").exists(), err


def test_a_shipped_configuration_is_picked_by_name(tmp_path, monkeypatch):
    """``--config finetune`` from any folder is learning/configs/finetune.toml; a file of that name here wins, and a
    name that is neither is left as given, so its reader names what is missing."""
    from learning.train import CONFIG_DIR, config_path, shipped_configs

    monkeypatch.chdir(tmp_path)
    assert {"default", "finetune", "berlin"} <= set(shipped_configs())
    (tmp_path / "finetune").mkdir()                            # a folder of that name hides nothing
    assert config_path("finetune") == str(CONFIG_DIR / "finetune.toml")
    assert load_config(config_path("finetune"))["train"]["init"] == load_config(CONFIG_DIR / "finetune.toml")["train"]["init"]
    (tmp_path / "finetune").rmdir()
    (tmp_path / "finetune").write_text("")                     # a file of one's own by that name comes first
    assert config_path("finetune") == "finetune"
    assert config_path("nope") == "nope" and config_path("sub/finetune") == "sub/finetune"
    with pytest.raises(SystemExit) as exit_info:
        main(["--config", "nope", "--out", str(tmp_path / "run")])
    assert exit_info.value.code == 2 and not (tmp_path / "run").exists()


def test_base_and_load_config_take_a_shipped_configurations_name(tmp_path, monkeypatch):
    """``base = "finetune"`` in a configuration of one's own and ``load_config("finetune")`` from Python read the
    shipped file (only ``--config finetune`` did); a base that is neither says where it looked."""
    from learning.train import CONFIG_DIR

    monkeypatch.chdir(tmp_path)
    shipped = load_config(CONFIG_DIR / "finetune.toml")
    assert load_config("finetune") == shipped
    (tmp_path / "mine.toml").write_text('base = "finetune"\n[train]\nepochs = 3\n')
    mine = load_config(tmp_path / "mine.toml")
    assert mine["train"]["epochs"] == 3 and mine["train"]["init"] == shipped["train"]["init"]
    (tmp_path / "bad.toml").write_text('base = "finetun"\n')
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'bad.toml'}: base = 'finetun': no such configuration file "
                                         r"beside it \(.*\), nor a shipped one of that name \(berlin, "):
        load_config(tmp_path / "bad.toml")


def test_a_copied_shipped_configuration_keeps_its_base(tmp_path, monkeypatch):
    """Review: a shipped file copied to edit (its base = "default.toml") was refused, 'no such configuration file
    beside it, nor a shipped one of that name (..., default, ...)'; --config finetune.toml from another folder too."""
    from learning.train import CONFIG_DIR, config_path

    monkeypatch.chdir(tmp_path)
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "my-ft.toml").write_text((CONFIG_DIR / "finetune.toml").read_text())
    assert load_config(tmp_path / "cfg" / "my-ft.toml") == load_config(CONFIG_DIR / "finetune.toml")
    assert config_path("finetune.toml") == str(CONFIG_DIR / "finetune.toml")


@pytest.mark.parametrize("given, said", [
    ("finetun", "no such file, nor a shipped configuration of that name (did you mean 'finetune'?)"),
    ("finetun.toml", "no such file, nor a shipped configuration of that name (did you mean 'finetune'?)"),
    ("qqqqqq", "no such file, nor a shipped configuration of that name (shipped: berlin, "),
    ("nothere/x.toml", "no such file"),
])
def test_a_config_that_is_no_file_says_which_shipped_one_was_meant(given, said):
    """Review: `--config finetun` was a raw "[Errno 2] No such file or directory: 'finetun'"."""
    with pytest.raises(ValueError) as err:
        load_config(given)
    assert str(err.value).startswith(f"{given}: cannot read configuration: {said}"), str(err.value)


def test_an_empty_run_folder_is_refused(capsys):
    """Review: --out "" (an unset shell variable) fell back to runs/<config name> without a word."""
    with pytest.raises(SystemExit) as stopped:
        main(["--out", ""])
    assert stopped.value.code == 2 and "argument --out: needs a path, got an empty string" in capsys.readouterr().err
