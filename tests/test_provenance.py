"""A model file says how it was made (learning.provenance), and ``python -m learning.export`` writes and shows one."""
import shlex
import shutil
import subprocess

import numpy as np
import pytest

from learning import provenance
from learning.export import load_model, main as export_main
from learning.train import load_config, main as train_main
from tiny_training import TINY, sets

CONFIG = "learning/configs/default.toml"



@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A 1-epoch training run from the command line: (its --out folder, its arguments)."""
    out = tmp_path_factory.mktemp("prov") / "run"
    argv = ["--config", CONFIG, "--out", str(out), "--no-progress"] + sets(TINY)
    assert train_main(argv) == 0
    return out, argv


def _head() -> str | None:
    try:
        return subprocess.run(["git", "-C", str(provenance.CODE_ROOT), "rev-parse", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def test_the_model_file_records_the_command_the_code_and_the_config_file(run):
    out, argv = run
    meta = load_model(out / "model.npz").metadata
    made = meta["provenance"]
    assert made["command"] == "python -m learning.train " + shlex.join(argv)
    assert made["git"] == (None if _head() is None else {"commit": _head(), "dirty": made["git"]["dirty"]})
    assert made["dataset_tomls"] == {} and made["started_utc"].endswith("+00:00")
    assert meta["config_file"]["path"].endswith("learning/configs/default.toml")
    assert meta["config_file"]["settings"]["train"]["epochs"] == 200         # the file's own, before --set


def test_a_resumed_run_keeps_its_start_and_adds_the_resumption(run, tmp_path):
    out, argv = run
    again = tmp_path / "run"
    shutil.copytree(out, again)
    resume = ["--resume", "--out", str(again), "--no-progress", "--set", "train.epochs=2"]
    assert train_main(resume) == 0
    made = load_model(again / "model.npz").metadata["provenance"]
    assert made["command"] == "python -m learning.train " + shlex.join(argv)
    assert [r["command"] for r in made["resumes"]] == ["python -m learning.train " + shlex.join(resume)]
    lines = provenance.describe(made)
    assert lines[0].startswith("trained ") and any(line.startswith("resumed ") for line in lines)


def test_registered_dataset_tomls_are_kept_whole(tmp_path):
    toml = tmp_path / "my-drive.toml"
    toml.write_text('id = "my-drive"\n')
    kept = provenance.registered_tomls({"data": {"register": [str(toml), str(tmp_path / "gone.toml")]}})
    assert kept[str(toml)] == 'id = "my-drive"\n'
    assert kept[str(tmp_path / "gone.toml")].startswith("(not readable: ")
    assert provenance.git_state(tmp_path) is None                            # not a checkout: no commit claimed
    assert "not recorded" in provenance.describe(None)[0]


def test_export_command_writes_the_runs_model_and_show_describes_it(run, tmp_path, capsys):
    out, argv = run
    written = tmp_path / "best.npz"
    assert export_main([str(out / "best.pt"), str(written)]) == 0
    mine, runs = load_model(written), load_model(out / "model.npz")          # select = "val": model.npz is best.pt
    assert mine.metadata["epoch"] == runs.metadata["epoch"]
    assert all(np.array_equal(mine.params[k], runs.params[k]) for k in runs.params)
    capsys.readouterr()
    assert export_main(["--show", str(written)]) == 0
    shown = capsys.readouterr().out
    assert "trained on: synthetic (train); epoch " in shown
    assert f"  command: python -m learning.train {shlex.join(argv)}" in shown
    assert "configuration file: " in shown and "default.toml" in shown
    assert f"python -m learning.export --show {written} --config prints it" in shown
    assert f"written {mine.metadata['created_utc']} by lfgnss" in shown and "(on trained epochs)" not in shown
    assert export_main(["--show", str(written), "--config"]) == 0           # the run's configuration, as TOML
    (tmp_path / "again.toml").write_text(capsys.readouterr().out)
    assert load_config(tmp_path / "again.toml") == mine.metadata["config"]


def test_show_of_a_bundled_model_says_what_is_not_recorded(capsys):
    assert export_main(["--show", "lfgnss/data/model/lfgnss-hk-tst-static-2020.npz"]) == 0
    shown = capsys.readouterr().out
    assert "trained on: hk-tst-static-2020 (train); epoch 27" in shown
    assert "zupt_sigma_m_s=0.02" in shown
    assert "provenance: not recorded" in shown
    assert "lfgnss-hk-tst-static-2020.npz row of lfgnss/data/model/README.md" in shown
    assert "its path was not recorded, but the configuration itself is stored in the model: " \
           "python -m learning.export --show hk-tst-static-2020 --config prints it" in shown


def test_show_of_the_bundled_ensemble_gives_each_networks_run(capsys):
    """The berlin-pp model is six training runs (seeds 0-5; 0-2 brought in by the three-network file it grew from):
    --show names each run's command and commit."""
    assert export_main(["--show", "berlin-pp"]) == 0
    shown = capsys.readouterr().out
    assert "trained on: berlin-pp (train), 6 seeds; epoch 120" in shown
    assert "huber_k=2.0" in shown and "q_vel_up_m2_s3=0.1" in shown
    assert "ensemble of 6 networks of one recipe (R: geometric mean" in shown
    for seed in range(6):
        via = ", via lfgnss/data/model/lfgnss-berlin-pp.npz)" if seed < 3 else ")"
        assert f"  {seed}: seed {seed}, epoch 120, validation 3D RMSE" in shown
        assert f"(runs/berlin-s{seed}/last.pt{via}" in shown
        assert f"network {seed}:" in shown
        assert (f"    command: python -m learning.train --config learning/configs/berlin.toml --set seed={seed} "
                f"--set threads=1 --out runs/berlin-s{seed}") in shown
    assert "provenance: not recorded" not in shown


def test_export_ekf_writes_the_same_network_in_another_filter(run, tmp_path, capsys):
    """--ekf from a checkpoint or from a model file: same weights and training config, the filter changed and
    recorded; --show says so; no staging file is left behind."""
    from estimators.ekf import config_of

    out, _ = run
    from_ckpt, from_file = tmp_path / "a.npz", tmp_path / "b.npz"
    assert export_main([str(out / "best.pt"), str(from_ckpt), "--ekf", "zupt_sigma_m_s=0.05",
                        "--ekf", "gate_sigma=4"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]
    assert export_main([str(from_ckpt), "--ekf", "zupt_sigma_m_s=none", str(from_file)]) == 0      # OUT after --ekf
    trained, a, b = load_model(out / "model.npz"), load_model(from_ckpt), load_model(from_file)
    assert all(np.array_equal(a.params[k], trained.params[k]) and np.array_equal(b.params[k], trained.params[k])
               for k in trained.params)
    assert a.metadata["config"] == trained.metadata["config"] == b.metadata["config"]
    with np.load(from_file) as raw:                                          # the format's float32 weights
        assert all(raw[f"param/{k}"].dtype == np.float32 for k in trained.params)
    assert config_of(a).zupt_sigma_m_s == 0.05 and config_of(a).gate_sigma == 4.0
    assert config_of(b).zupt_sigma_m_s is None and config_of(b).gate_sigma == 4.0
    assert config_of(trained).zupt_sigma_m_s is None and config_of(trained).gate_sigma == 3.0
    assert [r["changes"] for r in b.metadata["refilter"]] == [{"gate_sigma": [3.0, 4.0], "zupt_sigma_m_s": [None, 0.05]},
                                                              {"zupt_sigma_m_s": [0.05, None]}]
    capsys.readouterr()
    assert export_main(["--show", str(from_file)]) == 0
    shown = capsys.readouterr().out
    assert "filter changed after training: gate_sigma 3.0 -> 4.0, zupt_sigma_m_s None -> 0.05" in shown
    assert "filter changed after training: zupt_sigma_m_s 0.05 -> None" in shown and "--ekf zupt_sigma_m_s=none" in shown
    assert "validation 3D RMSE" in shown and " m (in the training filter)" in shown
    assert f"network exported {b.metadata['created_utc']} by lfgnss" in shown   # kept through refilters
    assert a.metadata["refilter"][0]["source"] == str(out / "best.pt")      # the checkpoint, not a staging file
    assert b.metadata["refilter"][-1]["source"] == str(from_ckpt) and "lfgnss" in b.metadata["refilter"][-1]["versions"]


def test_export_ekf_keeps_what_it_does_not_change(run, tmp_path):
    """A user's file next to the output is left alone; ekf_config keys this version does not know are kept; ".5"
    is a number."""
    out, _ = run
    precious = tmp_path / "m.unfiltered.npz"
    precious.write_bytes(b"mine")
    assert export_main([str(out / "best.pt"), str(tmp_path / "m.npz"), "--ekf", "gate_sigma=.5"]) == 0
    assert precious.read_bytes() == b"mine" and sorted(p.name for p in tmp_path.iterdir()) == ["m.npz",
                                                                                               "m.unfiltered.npz"]
    assert load_model(tmp_path / "m.npz").metadata["ekf_config"]["gate_sigma"] == 0.5
    from learning.export import _write_model_file
    src = load_model(tmp_path / "m.npz")
    meta = {**src.metadata, "ekf_config": {**src.metadata["ekf_config"], "future_knob": 7}}
    _write_model_file(tmp_path / "future.npz", src.params, src.normaliser, meta)
    assert export_main([str(tmp_path / "future.npz"), str(tmp_path / "f2.npz"), "--ekf", "gate_sigma=4"]) == 0
    assert load_model(tmp_path / "f2.npz").metadata["ekf_config"]["future_knob"] == 7


@pytest.mark.parametrize("where", ["d.npz", "file/m.npz"])
def test_export_to_an_unwritable_place_is_one_line_naming_it(where, tmp_path, capsys):
    """A folder, or a path under a file: one line naming the file asked for, never the temporary one."""
    (tmp_path / "d.npz").mkdir()
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as exit_info:
        export_main(["lfgnss/data/model/lfgnss-berlin-pp.npz", str(tmp_path / where), "--ekf", "gate_sigma=4"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and f"{tmp_path / where}: " in err and "partial" not in err, err
    assert len(err.splitlines()) == 1, err


@pytest.mark.parametrize("ekf, message", [
    (["--ekf", "bogus=1"], "--ekf: no EKF setting bogus (EkfConfig has"),
    (["--ekf", "zupt_sigma_m_s=-1"], "--ekf: EkfConfig.zupt_sigma_m_s must be a positive"),
    (["--ekf", "zupt_sigma_m_s"], "--ekf: expects KEY=VALUE, got 'zupt_sigma_m_s'"),
    (["--ekf", "gate_sigma=4", "--ekf", "gate_sigma=5"], "--ekf: gate_sigma given twice"),
    (["--ekf", "huber_k=2"], "--ekf: huber_k is already 2.0 in this model's filter"),
    (["--ekf", "gate_sigma=.5x"], "--ekf: EkfConfig.gate_sigma must be"),
    (["--ekf", "=4"], "--ekf: expects KEY=VALUE, got '=4'"),
    ([], "lfgnss-berlin-pp.npz: a model file, not a training checkpoint: give --ekf KEY=VALUE to write it"),
])
def test_export_ekf_bad_input_is_one_line(ekf, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        export_main(["lfgnss/data/model/lfgnss-berlin-pp.npz", str(tmp_path / "m.npz"), *ekf])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err, err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("argv", [[], ["a.pt"], ["a.pt", "b.npz", "--show", "c.npz"]])
def test_export_command_usage(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        export_main(argv)
    lines = capsys.readouterr().err.strip().splitlines()                     # argparse's usage (it wraps), the error
    usage, error = lines[0], lines[-1]
    assert exit_info.value.code == 2 and usage.startswith("usage: python -m learning.export")
    assert error.endswith("give CHECKPOINT OUT.npz to export, or --show MODEL.npz to describe a model file")


@pytest.mark.parametrize("argv, message", [
    (["a.pt", "model"], "model: give the model file a .npz name"),
    (["missing.pt", "m.npz"], "missing.pt: not a usable training checkpoint"),
    (["--show", "x.pt"], "x.pt: a training checkpoint, not a model file: export it first"),
    (["--show", "missing.npz"], "missing.npz: no such model file"),
])
def test_export_command_bad_input_is_one_line(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        export_main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not list(tmp_path.iterdir())


class _RunsCode:
    """Unpickling this (with pickle's full powers) creates a file: a stand-in for a checkpoint that runs code."""

    def __init__(self, mark):
        self.mark = str(mark)

    def __reduce__(self):
        return open, (self.mark, "w")


def test_a_checkpoint_that_would_run_code_is_refused_not_run(tmp_path):
    """Checkpoints are read with torch.load(weights_only=True): tensors, containers and numpy arrays only."""
    import torch

    import learning.crossval as cv
    from learning.export import ModelFileError, export_model
    from learning.train import load_checkpoint, read_checkpoint

    mark = tmp_path / "ran"
    bad = tmp_path / "fold0" / "last.pt"
    bad.parent.mkdir()
    torch.save({"config": {}, "epoch": 1, "model": {}, "payload": _RunsCode(mark)}, bad)
    with pytest.raises(ValueError, match="cannot read the checkpoint"):
        load_checkpoint(bad)
    with pytest.raises(ModelFileError, match="not a usable training checkpoint"):
        export_model(bad, tmp_path / "m.npz")
    with pytest.raises(ValueError, match="not a learning.train checkpoint"):
        cv.saved_fold(tmp_path, 0, {}, [])
    assert not mark.exists()
    good = tmp_path / "good.pt"                                     # what train saves: numpy RNG state included
    torch.save({"rng": {"numpy": np.random.get_state()}, "w": torch.ones(2)}, good)
    back = read_checkpoint(good)
    assert np.array_equal(back["rng"]["numpy"][1], np.random.get_state()[1]) and back["w"].sum() == 2


@pytest.mark.parametrize("content, reason", [
    (b"epoch,train_loss,val_rmse_3d_m\n0,1.5,20.0\n", "not a torch file (IndexError: "),
    (bytes(range(256)) * 3, "not a torch file (UnpicklingError: unknown pickle operand 0)"),
    (b"", "not a torch file (it ends before its first record: empty or cut short)"),
], ids=["log.csv", "binary", "empty"])
def test_exporting_a_text_or_foreign_file_is_one_line(content, reason, tmp_path, capsys):
    """``python -m learning.export runs/x/log.csv m.npz``: torch's old-format reader fails with IndexError there."""
    source = tmp_path / "log.csv"
    source.write_bytes(content)
    with pytest.raises(SystemExit) as exit_info:
        export_main([str(source), str(tmp_path / "m.npz")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert f"error: {source}: not a usable training checkpoint ({reason}" in err
    assert not (tmp_path / "m.npz").exists()


def test_exporting_a_file_that_is_not_a_checkpoint_dict_is_one_error(tmp_path):
    import torch

    from learning.export import ModelFileError, export_model

    for i, content in enumerate(([1, 2], {"model": [1], "model_hparams": {}, "normaliser": 3})):
        torch.save(content, tmp_path / f"odd{i}.pt")
        with pytest.raises(ModelFileError, match="not a usable training checkpoint"):
            export_model(tmp_path / f"odd{i}.pt", tmp_path / "m.npz")


def test_a_model_file_under_a_file_says_which_file_is_in_the_way(tmp_path, capsys):
    """Review: `learning.export M afile/x.npz` said only "(File exists)"."""
    (tmp_path / "afile").write_text("")
    with pytest.raises(SystemExit) as exit_info:
        export_main(["lfgnss/data/model/lfgnss-berlin-pp.npz", str(tmp_path / "afile" / "x.npz"), "--ekf",
                     "gate_sigma=4"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.rstrip().endswith(
        f"{tmp_path / 'afile' / 'x.npz'}: cannot write the model file ({tmp_path / 'afile'} is a file, not a folder)"), err
