"""Damaged inputs (tests/corpus/make_corpus.py): documented behaviour through the API and the CLI.

Every case is cut from the bundled real Berlin sample and damaged in one way. For each:

* API (``lfgnss.load`` / ``spp`` / ``build_sequence`` / estimators, ``learning.export.load_model``,
  ``lfgnss.datasets.align_truth``): an error is an ``LfgnssError`` whose one-line message names the file
  (and line); a warning leaves a ``PATH[:LINE]: reason`` note and the data are solved without the damage.
* CLI (``lfgnss.solve.main`` in-process): an error is exit code 2 and one ``error: FILE[:LINE]: reason``
  line on stderr, no traceback; otherwise exit 0, the warning printed, the qc summary counting what was
  skipped, no NaN or inf in any output file, and the EKF results of every epoch before the damage equal to
  those of the clean file.
"""
from __future__ import annotations

import atexit
import csv
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import warnings
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent / "corpus"))
import make_corpus  # noqa: E402

import estimators  # noqa: E402
import lfgnss  # noqa: E402
from lfgnss import datasets  # noqa: E402
from lfgnss.errors import LfgnssError  # noqa: E402
from lfgnss.solve import DEFAULT_MODEL, main  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CASE_NAMES = [fn.__name__ for fn in make_corpus._BUILDERS]
# outcomes at collection time, from a quick build without the model files (they need torch)
_SCRATCH = Path(tempfile.mkdtemp(prefix="lfgnss-corpus-"))
atexit.register(shutil.rmtree, _SCRATCH, ignore_errors=True)


def _scratch() -> Path:
    """The scratch folder, re-created if something removed it (it is shared by the whole run)."""
    _SCRATCH.mkdir(parents=True, exist_ok=True)
    return _SCRATCH


_OUTCOMES = {c.name: c.outcome for c in make_corpus.build(_scratch(), models=False).values()}
SOLVED_OBS_CASES = [n for n in CASE_NAMES if n.startswith("obs_") and _OUTCOMES.get(n) != "error"]
BAD_NUMBER = re.compile(r"\b(nan|inf|infinity)\b", re.IGNORECASE)


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """(folder, cases) with every corpus file written from the bundled sample."""
    folder = tmp_path_factory.mktemp("corpus")
    return folder, make_corpus.build(folder)


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))


def _files(folder: Path, case: make_corpus.Case) -> dict:
    return {"obs": folder / case.obs, "nav": [folder / n for n in case.nav],
            "truth": folder / case.truth if case.truth else None, "model": folder / case.model if case.model else None}


def _culprit_file(folder: Path, case: make_corpus.Case) -> list[Path]:
    f = _files(folder, case)
    return f["nav"] if case.culprit == "nav" else [f[case.culprit]]


# ----------------------------------------------------------------------------------------------- the corpus
def test_corpus_is_complete_and_small(corpus):
    folder, cases = corpus
    damaged = [c for c in cases.values() if not c.damage.startswith("(control)")]
    assert len(damaged) >= 20
    assert {c.outcome for c in cases.values()} == {"error", "warning", "ok"}
    size = sum(p.stat().st_size for p in folder.iterdir())
    assert size < 2_000_000, size
    doc = (REPO / "docs" / "bad_input.md").read_text()
    missing = [name for name in cases if f"`{name}`" not in doc]
    assert not missing, f"docs/bad_input.md lacks rows for {missing}"


def test_base_files_are_clean_real_data(corpus):
    folder, _ = corpus
    with warnings.catch_warnings():
        warnings.simplefilter("error")            # no warning at all on the undamaged files
        meas = lfgnss.load(folder / "base.obs", [folder / "base.16n", folder / "base.16g"], cache=False)
        meas3 = lfgnss.load(folder / "base3.rnx", meas.nav, cache=False)
    assert len(meas.time_gps_s) == make_corpus.BASE_EPOCHS and meas.systems == ("G", "R")
    np.testing.assert_array_equal(meas3.pr_m, meas.pr_m)   # the RINEX 3 conversion carries the same data
    assert lfgnss.spp(meas).ok.all()


# ----------------------------------------------------------------------------------------------- API
def _api(folder: Path, case: make_corpus.Case):
    """Run the library the way a user would; returns (notes, measurements, coarse fix, solution)."""
    f = _files(folder, case)
    notes: list[str] = []
    if f["model"] is not None:
        from learning.export import load_model

        noise = load_model(f["model"])
    else:
        noise = None
    meas = lfgnss.load(f["obs"], f["nav"], cache=False)
    notes += meas.warnings
    fix = lfgnss.spp(meas)
    truth = None
    if f["truth"] is not None:
        spec = datasets.DatasetSpec("corpus", (f["obs"],), tuple(f["nav"]), f["truth"], "smartloc",
                                    time_origin_gps_s=float(meas.time_gps_s[0]))
        truth, bad = datasets.align_truth(meas.time_gps_s, spec)
        notes += bad
    features = noise.feature_names if noise is not None else lfgnss.DEFAULT_FEATURES
    seq = lfgnss.build_sequence(meas, fix, feature_names=features, truth_ecef_m=truth)
    sol = estimators.create("ekf", **({"noise": noise} if noise is not None else {})).solve(seq)
    return notes, meas, fix, seq, sol


@pytest.mark.parametrize("name", CASE_NAMES)
def test_api(corpus, name):
    folder, cases = corpus
    case = cases[name]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if case.outcome == "error":
            with pytest.raises((LfgnssError, ValueError)) as info:
                _api(folder, case)
            message = str(info.value)
            assert "\n" not in message and case.message in message, message
            if case.extra.get("api_error") == "ValueError":   # documented API limitation (docs/bad_input.md)
                return
            assert isinstance(info.value, LfgnssError), f"{type(info.value).__name__}: {message}"
            if case.extra.get("api_no_file"):                   # documented API limitation (docs/bad_input.md)
                return
            assert any(str(p) in message for p in _culprit_file(folder, case)), message
            if case.line is not None:
                assert f":{case.line}:" in message, message
            return
        notes, meas, fix, seq, sol = _api(folder, case)
    for note in notes:
        assert "\n" not in note and note.startswith(str(folder)), note
    if case.outcome == "warning":
        hits = [n for n in notes if case.message in n]
        assert hits, notes
        if case.line is not None:
            assert any(f":{case.line}:" in n for n in hits), hits
        rinex_warnings = [str(w.message) for w in caught if issubclass(w.category, lfgnss.rinex.RinexWarning)]
        assert all(m.startswith(str(folder)) and "\n" not in m for m in rinex_warnings), rinex_warnings
    else:
        assert not [n for n in notes if "skipped" in n], notes
    if case.qc is not None:
        assert fix.summary()["observations"].get(case.qc, 0) > 0, fix.summary()
    has = sol.status != estimators.STATUS_NONE
    assert has.any() and np.isfinite(sol.pos_ecef_m[has]).all() and np.isfinite(sol.cov_ecef_m2[has]).all()
    for name_ in ("pr_m", "sat_pos_ecef_m", "cn0_dbhz", "el_rad", "az_rad", "features"):
        assert np.isfinite(getattr(seq, name_)).all(), name_


# ----------------------------------------------------------------------------------------------- CLI
def _cli(args: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = main(args)
    return code, out.getvalue(), err.getvalue()


def _cli_args(folder: Path, case: make_corpus.Case, out: Path, backend: str = "ekf",
              noise: str = "hand-set") -> list[str]:
    """CLI arguments; ``noise``: "hand-set" (``--no-model``) or "bundled" (the shipped model file)."""
    f = _files(folder, case)
    args = ["--obs", str(f["obs"]), "--nav", *map(str, f["nav"]), "--out", str(out), "--no-plots",
            "--backend", backend]
    if f["truth"] is not None:
        args += ["--truth", str(f["truth"]), "--truth-format", "smartloc"]
    if f["model"] is not None:
        args += ["--model", str(f["model"])]
    elif noise == "hand-set":
        args += ["--no-model"]
    return args


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _check_outputs(out: Path) -> list[dict]:
    """Every output file is free of NaN/inf; returns the CSV rows."""
    files = sorted(out.iterdir())
    assert {p.suffix for p in files} >= {".pos", ".csv", ".geojson", ".kml"}, files
    for p in files:
        text = p.read_text()
        assert not BAD_NUMBER.search(text), f"{p.name}: {BAD_NUMBER.search(text).group(0)}"
    json.loads(next(p for p in files if p.suffix == ".geojson").read_text())
    rows = _read_csv(next(p for p in files if p.suffix == ".csv"))
    for row in rows:
        for key in ("x_m", "y_m", "z_m", "lat_deg", "lon_deg", "h_m", "sd_e_m", "sd_n_m", "sd_u_m"):
            if row[key]:
                assert np.isfinite(float(row[key])), (key, row)
    return rows


@pytest.fixture(scope="module")
def clean_rows(corpus, tmp_path_factory):
    """CSV rows of the clean base files, per backend, for the 'earlier epochs keep their results' check."""
    folder, _ = corpus
    rows = {}
    for backend, noise in (("ekf", "hand-set"), ("fgo", "hand-set"), ("ekf", "bundled")):
        if noise == "bundled" and not DEFAULT_MODEL.exists():
            continue
        out = tmp_path_factory.mktemp(f"clean-{backend}")
        case = make_corpus.Case("clean", "", "ok", "", "")
        code, stdout, stderr = _cli(_cli_args(folder, case, out, backend, noise))
        assert code == 0, stderr
        rows[backend, noise] = _read_csv(next(out.glob("base_*.csv")))
    return rows


CLI_CASES = [(name, "hand-set") for name in CASE_NAMES]
if DEFAULT_MODEL.exists():  # the shipped model as well, except where the case brings its own model file
    CLI_CASES += [(name, "bundled") for name in CASE_NAMES if not name.startswith("model_")]


@pytest.mark.parametrize("name, noise", CLI_CASES)
def test_cli(corpus, clean_rows, name, noise, tmp_path):
    """Every case through ``main``, with the hand-set noise and with the shipped LF-GNSS model."""
    folder, cases = corpus
    case = cases[name]
    out = tmp_path / "out"
    code, stdout, stderr = _cli(_cli_args(folder, case, out, noise=noise))
    assert "Traceback" not in stdout + stderr
    if case.outcome == "error":
        assert code == 2, (code, stdout, stderr)
        lines = [ln for ln in stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: "), stderr
        assert case.message in lines[0], lines[0]
        assert any(str(p) in lines[0] for p in _culprit_file(folder, case)), lines[0]
        if case.line is not None:
            assert f":{case.line}:" in lines[0], lines[0]
        return
    assert code == 0, (code, stdout, stderr)
    printed = stdout + stderr
    if case.outcome == "warning":
        hits = [ln for ln in printed.splitlines() if ln.startswith("warning: ") and case.message in ln]
        assert hits, printed
        if case.line is not None:
            assert any(f":{case.line}:" in ln for ln in hits), hits
    if case.qc is not None:
        summary = next(ln for ln in stdout.splitlines() if ln.startswith("coarse fix:"))
        assert re.search(rf"'{re.escape(case.qc)}': [1-9]", summary), summary
    rows = _check_outputs(out)
    solved = [r for r in rows if r["status"] != "none"]
    assert solved, rows
    if case.fault_epoch is not None:
        _same_leading_epochs(clean_rows["ekf", noise], rows, case.fault_epoch)


def _same_leading_epochs(clean: list[dict], rows: list[dict], n: int, tol_m: float = 1e-3) -> None:
    """The first ``n`` epochs of the clean run appear with the same positions in ``rows``."""
    by_time = {r["time_gps_s"]: r for r in rows}
    for ref in clean[:n]:
        row = by_time.get(ref["time_gps_s"])
        assert row is not None, f"epoch {ref['time_gpst']} lost"
        assert row["status"] == ref["status"], (ref["time_gpst"], row["status"], ref["status"])
        for key in ("x_m", "y_m", "z_m"):
            assert abs(float(row[key]) - float(ref[key])) <= tol_m, (ref["time_gpst"], key, row[key], ref[key])


@pytest.mark.parametrize("name", SOLVED_OBS_CASES)
def test_cli_fgo(corpus, clean_rows, name, tmp_path):
    """The factor-graph back end on every solvable observation-file case: exit 0, no traceback, no NaN."""
    folder, cases = corpus
    case = cases[name]
    out = tmp_path / "out"
    code, stdout, stderr = _cli(_cli_args(folder, case, out, backend="fgo"))
    assert code == 0 and "Traceback" not in stdout + stderr, stderr
    rows = _check_outputs(out)
    assert any(r["status"] != "none" for r in rows)
    if case.fault_epoch is not None and case.fault_epoch >= make_corpus.BASE_EPOCHS:
        _same_leading_epochs(clean_rows["fgo", "hand-set"], rows, case.fault_epoch, tol_m=1e-2)  # batch: all alike


def test_gap_restarts_the_filter(corpus, tmp_path):
    folder, cases = corpus
    case = cases["obs_gap"]
    code, _, stderr = _cli(_cli_args(folder, case, tmp_path))
    assert code == 0, stderr
    rows = _read_csv(next(tmp_path.glob("obs_gap_*.csv")))
    assert len(rows) == make_corpus.BASE_EPOCHS
    t = np.array([float(r["time_gps_s"]) for r in rows])
    k = case.extra["reset_at"]
    assert t[k] - t[k - 1] > 180
    assert rows[k]["status"] == "reset" and all(r["status"] != "none" for r in rows)


@pytest.mark.parametrize("backend, mode", [("ekf", None), ("ekf", "smooth"), ("fgo", "batch"), ("fgo", "fixed-lag")])
def test_tunnel_is_coasted(corpus, backend, mode, tmp_path):
    """60 s of epochs without satellites: coasted, then updated again; never a traceback."""
    folder, cases = corpus
    case = cases["obs_empty_epochs"]
    out = tmp_path / "out"
    args = _cli_args(folder, case, out, backend) + (["--smooth"] if mode == "smooth" else
                                                     ["--mode", mode] if mode else [])
    code, stdout, stderr = _cli(args)
    assert "Traceback" not in stdout + stderr
    assert code == 0, stderr
    rows = _check_outputs(out)
    start, stop = case.extra["tunnel"]
    assert all(r["status"] == "coasted" for r in rows[start:stop])
    assert all(r["status"] in ("updated", "reset") for r in rows[stop + 2:])


@pytest.mark.parametrize("backend, extra, message", [
    ("fgo", ["--smooth"], "--smooth applies to --backend ekf and plain-ekf"),
    ("ekf", ["--smooth-lag", "5"], "--smooth-lag needs --smooth"),
    ("ekf", ["--smooth", "--smooth-lag", "-1"], "a lag >= 0 seconds, got -1")])
def test_smoothing_options_misused_is_one_line(corpus, tmp_path, backend, extra, message):
    folder, cases = corpus
    code, stdout, stderr = _cli(_cli_args(folder, cases["obs_gap"], tmp_path, backend=backend) + extra)
    assert code == 2 and stderr.count("\n") == 1 and message in stderr, stderr
    assert not list(tmp_path.glob("obs_gap*.csv"))


def test_fixed_lag_smoothing_from_the_command_line(corpus, tmp_path):
    folder, cases = corpus
    code, stdout, stderr = _cli(_cli_args(folder, cases["obs_gap"], tmp_path) + ["--smooth", "--smooth-lag", "5"])
    assert code == 0, stderr
    assert "ekf+rts (lag 5 s)" in stdout
    rows = _read_csv(next(tmp_path.glob("obs_gap_*.csv")))
    assert len(rows) == make_corpus.BASE_EPOCHS and rows[cases["obs_gap"].extra["reset_at"]]["status"] == "reset"


def test_truncated_gzip_keeps_what_could_be_decompressed(corpus):
    folder, cases = corpus
    with pytest.warns(lfgnss.rinex.RinexWarning, match="compressed data end early"):
        obs = lfgnss.load_obs(folder / cases["obs_truncated_gz"].obs, cache=False)
    clean = lfgnss.load_obs(folder / "base.obs", cache=False)
    n = len(obs)
    assert 10 <= n < len(clean)
    np.testing.assert_array_equal(obs.time_gps_s, clean.time_gps_s[:n])
    np.testing.assert_array_equal(obs.pr_m, clean.pr_m[:n][:, np.isin(clean.sv, obs.sv)])


def test_cache_hit_repeats_the_warning_and_names_this_file(corpus, tmp_path):
    """A file served from the parse cache warns again, naming itself (not the file first parsed)."""
    folder, cases = corpus
    src = folder / cases["obs_garbage_fields"].obs
    first, second = tmp_path / "first.obs", tmp_path / "second.obs"
    first.write_bytes(src.read_bytes())
    second.write_bytes(src.read_bytes())
    with pytest.warns(lfgnss.rinex.RinexWarning):
        lfgnss.load_obs(first)
    with pytest.warns(lfgnss.rinex.RinexWarning, match="second.obs"):
        obs = lfgnss.load_obs(second)
    assert obs.warnings and all(w.startswith(str(second)) for w in obs.warnings)


def test_subprocess_no_traceback(corpus, tmp_path):
    """``python -m lfgnss.solve`` on a damaged and on an unusable file: exit codes and clean stderr."""
    folder, cases = corpus
    env = {**os.environ, "LFGNSS_CACHE": str(tmp_path / "cache")}
    results = []
    for name in ("obs_truncated", "obs_unknown_version"):
        case = cases[name]
        args = _cli_args(folder, case, tmp_path / name)
        results.append(subprocess.run([sys.executable, "-m", "lfgnss.solve", *args], capture_output=True, text=True,
                                      env=env, cwd=REPO, timeout=120))
    ok, bad = results
    assert ok.returncode == 0 and "Traceback" not in ok.stderr, ok.stderr
    assert "epoch truncated" in ok.stdout + ok.stderr
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().splitlines() == [bad.stderr.strip()] and "obs_unknown_version.obs:1:" in bad.stderr
