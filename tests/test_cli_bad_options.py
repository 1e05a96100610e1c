"""Bad options and environments on the other command lines (``lfgnss.benchmark``, ``learning.crossval``,
``python -m lfgnss``): one line naming the file or option, the documented exit status, no traceback, and nothing
already computed lost (docs/bad_input.md, "Command lines")."""
import csv
import importlib
import math
import os
import re
import shlex
import subprocess
import sys

import pytest
import torch

import learning.crossval as cv
import lfgnss.benchmark as bench
from lfgnss.__main__ import main as lfgnss_main

CV_PROG = "python -m learning.crossval"
SYNTHETIC = ["--config", "learning/configs/default.toml", "--no-progress"]
for _s in ("data.datasets=['synthetic']", "data.synthetic.n_epochs=60", "data.window=20", "data.stride=10",
           "train.batch_size=4", "train.epochs=1"):
    SYNTHETIC += ["--set", _s]


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and err.endswith("\n") and "Traceback" not in err, err
    return err.rstrip("\n")


# ----------------------------------------------------------------------------------------------- lfgnss.benchmark


@pytest.fixture
def drive(sample_toml, tmp_path):
    """Benchmark arguments for the bundled Berlin drive registered as ``my-drive`` (no shared data needed)."""
    return ["my-drive", "--register", str(sample_toml("my-drive"))]


@pytest.mark.parametrize("make, message", [
    (lambda p: p.write_text("x"), "{out}: --out is a file, not a folder"),
    (lambda p: (p.parent / "file").write_text("x"), "{out}: cannot create the output folder (Not a directory)"),
    (lambda p: (p / "results.md").mkdir(parents=True), "{out}/results.md: cannot write (a folder of that name is in "
                                                       "the way)"),
    (lambda p: (p.mkdir(), (p / "figures").write_text("x")), "{out}/figures: cannot write the figures (a file of that "
                                                             "name is in the way; --no-plots skips them)"),
])
def test_benchmark_out_that_cannot_hold_the_results_is_refused_before_the_run(drive, tmp_path, capsys, monkeypatch,
                                                                              make, message):
    out = tmp_path / "out"
    make(out)
    if "Not a directory" in message:
        out = tmp_path / "file" / "out"
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("ran before checking --out"))
    assert bench.main([*drive, "--out", str(out)]) == 2
    assert _one_line(capsys.readouterr().err) == "error: " + message.format(out=out)


@pytest.mark.parametrize("option", ["--out", "--models"])
def test_benchmark_empty_path_option_is_an_option_error(drive, capsys, option):
    with pytest.raises(SystemExit) as exit_info:
        bench.main([*drive, option, ""])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (f"python -m lfgnss.benchmark: error: argument {option}: needs "
                                                        "a path, got an empty string")


def test_benchmark_unusable_cache_is_a_warning_and_too_long_a_name_one_line(drive, tmp_path, capsys, monkeypatch):
    (tmp_path / "a-file").write_text("x")
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "a-file"))
    assert bench.main([*drive, "--out", str(tmp_path / "out"), "--no-plots"]) == 0    # run without the cache
    err = capsys.readouterr().err
    assert err.count("cannot use the cache") == 1
    assert _one_line(err) == (f"warning: {tmp_path / 'a-file'}: cannot use the cache (File exists); going on without "
                              "it, so files are parsed again on every run (set $LFGNSS_CACHE to a writable folder)")
    assert (tmp_path / "out" / "results.md").is_file()
    monkeypatch.delenv("LFGNSS_CACHE")
    assert bench.main([*drive, "--models", "x" * 5000, "--no-plots"]) == 2
    assert _one_line(capsys.readouterr().err) == f"error: {'x' * 5000}: File name too long"


def test_benchmark_missing_shared_data_names_the_file_and_the_variable(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path / "no-data"))
    assert bench.main(["hk-tst-static-2020", "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith(f"error: {tmp_path / 'out' / 'results.md'}: not written: no dataset has all its files "
                           f"(first missing: {tmp_path / 'no-data'}/")
    assert line.endswith(") (the benchmark datasets are read from $LFGNSS_SHARED_DATA, else ../shared/data beside "
                         "the checkout)")


def test_datasets_and_training_missing_shared_data_name_the_variable(tmp_path, capsys, monkeypatch):
    """Review: python -m lfgnss.datasets hk-tst-2019 and learning.train said 'missing PATH' and not where the
    benchmark data are looked for."""
    from lfgnss import datasets
    from lfgnss.datasets import main as datasets_main

    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path / "no-data"))
    hint = "(the benchmark datasets are read from $LFGNSS_SHARED_DATA, else ../shared/data beside the checkout)"
    assert datasets.get("hk-tst-2019").missing_note().endswith(hint)
    with pytest.raises(FileNotFoundError, match=re.escape(hint)):
        datasets.build("hk-tst-2019")
    datasets_main(["hk-tst-2019"])
    assert hint in capsys.readouterr().out


@pytest.mark.parametrize("script, reason", [
    ("echo boom >&2\nexit 1\n", "rnx2rtkp exited with 1: "),
    ('while [ $# -gt 0 ]; do [ "$1" = -o ] && echo garbage > "$2"; shift; done\n', "read_pos "),
])
def test_benchmark_failing_rnx2rtkp_leaves_out_its_row_only(drive, tmp_path, capsys, monkeypatch, script, reason):
    fake = tmp_path / "rnx2rtkp"
    fake.write_text("#!/bin/sh\n" + script)
    fake.chmod(0o755)
    monkeypatch.setenv("LFGNSS_RNX2RTKP", str(fake))
    assert bench.main([*drive, "--out", str(tmp_path / "out"), "--no-plots"]) == 0
    line = _one_line(capsys.readouterr().err)
    assert line.startswith(f"warning: my-drive: RTKLIB row left out: {reason}") and len(line) < 400
    report = (tmp_path / "out" / "results.md").read_text()
    assert "RTKLIB rnx2rtkp" not in report and "| my-drive | LF-GNSS EKF |" in report


def test_benchmark_figure_that_cannot_be_written_costs_that_figure_only(drive, tmp_path, capsys):
    (tmp_path / "out" / "figures" / "my-drive-cdf.png").mkdir(parents=True)
    assert bench.main([*drive, "--out", str(tmp_path / "out")]) == 2
    captured = capsys.readouterr()
    assert _one_line(captured.err) == (f"error: {tmp_path / 'out' / 'figures' / 'my-drive-cdf.png'}: cannot write "
                                       "(Is a directory)")
    assert "LF-GNSS EKF" in captured.out and (tmp_path / "out" / "results.md").is_file()
    assert (tmp_path / "out" / "figures" / "my-drive-track.png").is_file()


def _fake_rows():
    from lfgnss.metrics import METRIC_COLUMNS

    row = {"dataset": "my-drive", "method": "LF-GNSS EKF", "trained_on": "-", "epochs_per_s": 1.0,
           **{k: 1.0 for k in METRIC_COLUMNS}}
    return [row], []


def test_benchmark_results_file_that_cannot_be_written_keeps_the_tables(drive, tmp_path, capsys, monkeypatch):
    def full_disk(path, *a):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(bench, "run", lambda *a, **k: _fake_rows())
    monkeypatch.setattr(bench, "write_report", full_disk)
    assert bench.main([*drive, "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    captured = capsys.readouterr()
    report = tmp_path / "out" / "results.md"
    assert _one_line(captured.err) == f"error: {report}: cannot write (No space left on device)"
    assert "LF-GNSS EKF" in captured.out and "written:" not in captured.out


@pytest.mark.parametrize("exc, code, line", [
    (KeyboardInterrupt(), 130, "interrupted"),
    (RuntimeError("boom\nsecond line"), 3, "error: internal error in the benchmark (RuntimeError: boom second line); "
                                           "please report it"),
])
def test_benchmark_ctrl_c_and_internal_errors(drive, tmp_path, capsys, monkeypatch, exc, code, line):
    def raise_it(*a, **k):
        raise exc

    monkeypatch.setattr(bench, "run", raise_it)
    assert bench.main([*drive, "--out", str(tmp_path / "out"), "--no-plots"]) == code
    assert _one_line(capsys.readouterr().err) == line


def test_benchmark_stdout_closed_early_still_writes_the_results(sample_toml, tmp_path):
    cmd = (f"{sys.executable} -m lfgnss.benchmark my-drive --register {sample_toml('my-drive')} "
           f"--out {tmp_path / 'out'} --no-plots | true")         # the reader is gone before the first line
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "LFGNSS_RNX2RTKP": "/nonexistent"})
    assert proc.returncode == 0 and "Traceback" not in proc.stderr and proc.stderr == ""
    assert (tmp_path / "out" / "results.md").is_file()


# ----------------------------------------------------------------------------------------------- learning.crossval


def _cv_exit(argv, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as exit_info:
        cv.main(argv)
    return exit_info.value.code, _one_line(capsys.readouterr().err)


@pytest.mark.parametrize("folds", ["0", "1", "-1"])
def test_crossval_too_few_folds_is_one_line_before_any_work(tmp_path, capsys, folds):
    code, line = _cv_exit([*SYNTHETIC, "--folds", folds, "--out", str(tmp_path / "cv")], capsys)
    assert code == 2 and line == f"{CV_PROG}: error: folds must be a whole number >= 2 (--folds), got {folds}"
    assert not (tmp_path / "cv").exists()


def test_crossval_huge_folds_is_refused_at_once_naming_the_dataset(tmp_path, capsys):
    code, line = _cv_exit([*SYNTHETIC, "--folds", str(10 ** 30), "--out", str(tmp_path / "cv")], capsys)
    assert code == 2 and line == (f"{CV_PROG}: error: synthetic: 180 epochs cannot make {10 ** 30} folds of at least 2 "
                                  f"epochs (--folds {10 ** 30})")


@pytest.mark.parametrize("where, message", [
    ("a-file", "{out}: --out is a file, not a folder"),
    ("a-file/sub", "{out}: cannot create the output folder (Not a directory)"),
    ("y" * 300, "{out}: cannot create the output folder (File name too long)"),
    ("has-md", "{out}: already holds a cross-validation; choose another --out"),
])
def test_crossval_unusable_out_is_one_line_before_any_work(tmp_path, capsys, where, message):
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "has-md").mkdir()
    (tmp_path / "has-md" / "crossval.md").write_text("an earlier run's table")
    out = tmp_path / where
    code, line = _cv_exit([*SYNTHETIC, "--folds", "2", "--out", str(out)], capsys)
    assert code == 2 and line == f"{CV_PROG}: error: " + message.format(out=out)


@pytest.mark.parametrize("option", ["--out", "--reuse"])
def test_crossval_empty_path_option_is_an_option_error(capsys, option):
    with pytest.raises(SystemExit) as exit_info:
        cv.main([*SYNTHETIC, option, ""])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == f"{CV_PROG}: error: argument {option}: needs a path, got an " \
                                                       "empty string"


@pytest.fixture(scope="module")
def fold0_run(tmp_path_factory):
    """A real one-fold cross-validation on simulated data: its --out (fold0/last.pt is a finished fold)."""
    out = tmp_path_factory.mktemp("cv") / "run"
    assert cv.main([*SYNTHETIC, "--folds", "2", "--fold", "0", "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize("damage, message", [
    (lambda s: s["model"].pop("embed.weight"), "not a usable learning.train checkpoint (RuntimeError: Error(s) in "
                                               "loading state_dict for LfgnssNet: Missing key(s) in state_dict: "
                                               '"embed.weight".)'),
    (lambda s: s["model"]["embed.weight"].fill_(math.nan), "not a usable learning.train checkpoint (non-finite "
                                                           "weights in embed.weight)"),
    (lambda s: s.update(normaliser={}), "not a usable learning.train checkpoint (KeyError: feature_names)"),
    (lambda s: s.update(epoch=0), "saved at epoch 0 of 1 (train.epochs): the fold was interrupted or diverged; "
                                  "cross-validate that fold again (--fold J) before rescoring it"),
])
def test_crossval_reuse_refuses_a_damaged_or_unfinished_checkpoint(fold0_run, tmp_path, capsys, damage, message):
    saved = torch.load(fold0_run / "fold0" / "last.pt", map_location="cpu", weights_only=False)
    damage(saved)
    (tmp_path / "old" / "fold0").mkdir(parents=True)
    torch.save(saved, tmp_path / "old" / "fold0" / "last.pt")
    code, line = _cv_exit([*SYNTHETIC, "--folds", "2", "--fold", "0", "--reuse", str(tmp_path / "old"),
                           "--out", str(tmp_path / "again")], capsys)
    assert code == 2 and line == f"{CV_PROG}: error: {tmp_path / 'old' / 'fold0' / 'last.pt'}: {message}"


def _fake_training(monkeypatch, last_fold):
    """Folds train in no time (``train`` faked); ``last_fold(out_fold)`` runs in place of the last fold's training."""
    def fake_train(config, fold_dir, **kwargs):
        if fold_dir.name == "fold1":
            last_fold(fold_dir)
        return [{"epoch": 0, "val_rmse_3d_m": 2.0}, {"epoch": 1, "val_rmse_3d_m": 1.0}]

    monkeypatch.setattr(cv, "train", fake_train)
    monkeypatch.setattr(cv, "_saved_rmse_m", lambda *a, **k: ({}, 1.0, 0.5))


def _raise(exc):
    def raise_it(*a):
        raise exc
    return raise_it


@pytest.mark.parametrize("exc, code, line", [
    (KeyboardInterrupt(), 130, "{prog}: interrupted; the rows of the finished fold(s) 0 are in {out}/crossval.csv"),
    (RuntimeError("boom"), 3, "{prog}: error: internal error (RuntimeError: boom); the rows of the finished fold(s) 0 "
                              "are in {out}/crossval.csv; please report it"),
])
def test_crossval_stopped_run_keeps_the_finished_folds_rows(monkeypatch, tmp_path, capsys, exc, code, line):
    _fake_training(monkeypatch, _raise(exc))
    out = tmp_path / "cv"
    code_seen, seen = _cv_exit([*SYNTHETIC, "--folds", "2", "--out", str(out)], capsys)
    finish = (f"; to finish, run the fold(s) left into a folder of their own ({CV_PROG} {shlex.join(SYNTHETIC)} "
              f"--folds 2 --fold 1 --out {out}-rest), then pool the two ({CV_PROG} --folds 2 --pool {out} --pool "
              f"{out}-rest --out {out}-all)") if code == 130 else ""
    assert code_seen == code and seen == line.format(prog=CV_PROG, out=out) + finish
    with open(out / "crossval.csv") as fh:
        assert [r["fold"] for r in csv.DictReader(fh)] == ["0"]


def test_crossval_results_that_cannot_be_written_are_printed(monkeypatch, tmp_path, capsys):
    _fake_training(monkeypatch, lambda fold_dir: (fold_dir.parent / "crossval.md").mkdir())   # in the way at the end
    out = tmp_path / "cv"
    with pytest.raises(SystemExit) as exit_info:
        cv.main([*SYNTHETIC, "--folds", "2", "--out", str(out)])
    captured = capsys.readouterr()
    assert exit_info.value.code == 2
    assert _one_line(captured.err) == f"{CV_PROG}: error: {out / 'crossval.md'}: cannot write (Is a directory)"
    assert "| pooled | 180 |" in captured.out and (out / "crossval.csv").is_file()


def test_an_os_error_in_the_cache_folder_is_named_as_such(monkeypatch, tmp_path):
    from lfgnss.errors import input_line

    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    assert input_line(FileExistsError(17, "File exists", str(tmp_path / "cache"))) == \
        f"{tmp_path / 'cache'} (the cache folder, $LFGNSS_CACHE): File exists"
    assert input_line(FileNotFoundError(2, "No such file or directory", "/x")) == "/x: No such file or directory"


# ----------------------------------------------------------------------------------------------- python -m lfgnss


def test_lfgnss_lists_the_commands_and_refuses_arguments(capsys):
    assert lfgnss_main([]) == 0 and lfgnss_main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "python -m lfgnss.benchmark" in out and "python -m learning.crossval" in out
    assert "python -m learning.export" in out
    from lfgnss.__main__ import COMMANDS
    for module in COMMANDS:                             # every listed command has a command line
        assert callable(importlib.import_module(module).main), module
    assert lfgnss_main(["nonsense"]) == 2
    assert _one_line(capsys.readouterr().err).startswith(
        "python -m lfgnss: error: unknown command 'nonsense'; the commands: python -m lfgnss.solve, ")
    from lfgnss import __version__

    assert lfgnss_main(["--version"]) == 0 and capsys.readouterr().out == f"lfgnss {__version__}\n"


def test_lfgnss_runs_a_command_by_its_short_name(tmp_path, capsys):
    """Review: python -m lfgnss solve ... refused ('run python -m lfgnss.solve') where it could run it."""
    assert lfgnss_main(["solve", "--obs", str(tmp_path / "x.obs")]) == 2
    assert "x.obs" in capsys.readouterr().err
    assert lfgnss_main(["solve", "--out", str(tmp_path), "--no-plots", "--quiet", "--backend", "wls"]) == 0
    assert (tmp_path / "Berlin_Potsdamer_Platz_wls.pos").exists()


@pytest.mark.parametrize("name, message", [
    ("a-file", "{out}: --out is a file, not a folder"),
    ("a-file/sub", "{out}: cannot create the output folder (Not a directory)"),
], ids=["a-file", "under-a-file"])
def test_train_refuses_an_unusable_out_before_any_data_are_built(tmp_path, capsys, name, message):
    """It used to build the datasets and then end in FileExistsError's traceback."""
    from learning.train import main as train_main

    (tmp_path / "a-file").write_text("x")
    out = tmp_path / name
    with pytest.raises(SystemExit) as exit_info:
        train_main(["--set", "train.epochs=1", "--out", str(out)])
    assert exit_info.value.code == 2
    assert _one_line(capsys.readouterr().err) == "python -m learning.train: error: " + message.format(out=out)


def _probe_fails(monkeypatch, code: int, reason: str) -> None:
    """check_output_folder's probe file fails with ``code`` (a read-only disk, no permission: root passes both)."""
    from pathlib import Path

    real_touch = Path.touch

    def touch(self, *args, **kwargs):
        if self.name.startswith(".lfgnss-write-test."):
            raise OSError(code, reason, str(self))
        return real_touch(self, *args, **kwargs)

    monkeypatch.setattr(Path, "touch", touch)


def test_a_read_only_out_is_said_before_the_solve(tmp_path, capsys, monkeypatch):
    """A folder that takes no file (a read-only disk) used to be found when the seven outputs were written."""
    import errno

    from lfgnss.solve import main as solve_main

    _probe_fails(monkeypatch, errno.EROFS, "Read-only file system")
    (tmp_path / "ro").mkdir()
    assert solve_main(["--out", str(tmp_path / "ro")]) == 2
    captured = capsys.readouterr()
    assert _one_line(captured.err) == f"error: {tmp_path / 'ro'}: cannot write into the output folder (Read-only file system)"
    assert captured.out == "" and not list((tmp_path / "ro").iterdir())
    assert solve_main(["--out", str(tmp_path / "ro" / "new")]) == 2          # a folder to be made in it
    assert _one_line(capsys.readouterr().err).endswith(f"cannot write into {tmp_path / 'ro'} (Read-only file system)")


def test_an_out_without_permission_for_new_files_still_rewrites_its_outputs(tmp_path, capsys, monkeypatch):
    """A folder one may not add files to, holding outputs one may rewrite: they are rewritten in place (it is only a
    folder to be made in such a place that is refused before the run)."""
    import errno

    from lfgnss.solve import main as solve_main

    out = tmp_path / "kept"
    assert solve_main(["--out", str(out), "--backend", "wls", "--no-plots", "--quiet"]) == 0
    _probe_fails(monkeypatch, errno.EACCES, "Permission denied")
    capsys.readouterr()
    assert solve_main(["--out", str(out), "--backend", "wls", "--no-plots", "--quiet"]) == 0
    assert solve_main(["--out", str(out / "sub"), "--backend", "wls", "--no-plots", "--quiet"]) == 2
    assert _one_line(capsys.readouterr().err) == (f"error: {out / 'sub'}: cannot create the output folder (no "
                                                  f"permission to write in {out})")


@pytest.mark.parametrize("module", ["lfgnss.solve", "lfgnss.datasets", "lfgnss.summary", "lfgnss.benchmark",
                                    "learning.train", "learning.crossval", "learning.export"])
def test_help_shows_no_rest_markup(module, capsys):
    """Review: the descriptions and option help come from docstrings, whose ``literal`` quotes --help printed as
    they are (lfgnss.solve's first line read ``python -m lfgnss.solve``: ...)."""
    with pytest.raises(SystemExit) as exit_info:
        importlib.import_module(module).main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert f"python -m {module}" in out and "``" not in out
