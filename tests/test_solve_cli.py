"""Command-line options of ``python -m lfgnss.solve`` that do not apply, or cannot work, say so in one line."""
from __future__ import annotations

import pytest

from lfgnss.errors import one_line
from lfgnss.measurements import load
from lfgnss.solve import DEFAULT_MODEL, SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH, main


@pytest.mark.parametrize("extra, message", [
    (["--nav", str(SAMPLE_NAV[0])], "--nav needs --obs"),
    (["--truth-format", "smartloc"], "--truth-format applies to a --truth file"),
    (["--truth-origin", "5"], "--truth-origin applies to a --truth file"),
    (["--obs", str(SAMPLE_OBS), "--nav", *map(str, SAMPLE_NAV), "--truth", str(SAMPLE_TRUTH), "--truth-origin", "5"],
     "--truth-origin applies to --truth-format smartloc only"),
    (["--backend", "plain-ekf", "--model", "m.npz"], "--model applies to --backend ekf and fgo, not plain-ekf"),
    (["--backend", "wls", "--no-model"], "--no-model applies to --backend ekf and fgo, not wls"),
    (["--model", "m.npz", "--no-model"], "--model and --no-model contradict each other"),
    (["--backend", "ekf", "--mode", "fixed-lag"], "--mode applies to --backend fgo, not ekf"),
    (["--smooth-lag", "5"], "--smooth-lag needs --smooth (--smooth --smooth-lag 5)"),
    # review: it advised --smooth, which fgo then refuses
    (["--backend", "fgo", "--smooth-lag", "2"],
     "--smooth-lag applies to --backend ekf and plain-ekf with --smooth, not fgo (its fixed-lag mode: --mode fixed-lag)"),
    (["--smooth", "--smooth-lag", "-1"], "--smooth-lag must be a lag >= 0 seconds, got -1"),
    (["--backend", "wls", "--formal-sd"],
     "--formal-sd applies to --backend ekf and plain-ekf and to fgo with --marginals, not wls (whose sds are not"),
    (["--backend", "fgo", "--formal-sd"], "not fgo's default stand-in (add --marginals)"),
    (["--backend", "ekf", "--marginals"], "--marginals applies to --backend fgo, not ekf"),
    (["--obs", "nope.obs"], "nope.obs: cannot read file (No such file or directory)"),   # not "no --nav"
    (["--model", "hk-tst"], "hk-tst: no such model file or bundled model (berlin-pp, default, hk-tst-2019,"),
    (["--truth-offset", "18"], "--truth-offset applies to a --truth file, and none was given"),
    (["--truth", "t.csv", "--truth-format", "static", "--truth-offset", "18"],
     "--truth-offset changes nothing for --truth-format static, whose one point labels every epoch"),
])
def test_misused_option_is_one_line_before_any_work(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    assert main(["--out", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert not any(out.glob("*.csv"))


@pytest.mark.parametrize("option", ["--out", "--obs", "--truth", "--model"])
def test_an_empty_path_option_is_refused(tmp_path, capsys, monkeypatch, option):
    """Review: --out "" (an unset shell variable) wrote the run's files into the current folder."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stopped:
        main([option, "", "--no-plots", "--quiet"])
    assert stopped.value.code == 2
    assert f"argument {option}: needs a path, got an empty string" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("make, message", [
    (lambda p: p.write_text(""), "--out is a file, not a folder"),
    (lambda p: (p.parent / "blocker").write_text("") or None, "cannot create the output folder"),
])
def test_unusable_output_folder_is_one_line_before_solving(tmp_path, capsys, make, message):
    out = tmp_path / "out"
    make(out)
    target = out if out.exists() else tmp_path / "blocker" / "out"      # a folder inside a file
    assert main(["--out", str(target), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1 and message in captured.err, captured.err
    assert str(target) in captured.err


@pytest.mark.parametrize("extra, message", [
    (["--systems", "GX"], "argument --systems: unknown constellation letter(s) 'X' in 'GX'; use letters of GCERJ"),
    (["--smooth", "--smooth-lag", "inf"], "argument --smooth-lag: needs a finite number, got 'inf'"),
    (["--obs", str(SAMPLE_OBS), "--nav", *map(str, SAMPLE_NAV), "--truth", str(SAMPLE_TRUTH),
      "--truth-format", "smartloc", "--truth-origin", "nan"], "argument --truth-origin: needs a finite number, got 'nan'"),
])
def test_non_finite_numbers_are_refused(tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["--out", str(tmp_path), *extra])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err and "Traceback" not in err


def test_a_nav_folder_is_named_as_such(tmp_path, capsys):
    assert main(["--obs", str(SAMPLE_OBS), "--nav", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == f"error: {tmp_path}: a folder, not a navigation file\n"


def test_ctrl_c_is_one_line_not_a_traceback(tmp_path, capsys, monkeypatch):
    import lfgnss.solve as solve

    def interrupted(_args):
        raise KeyboardInterrupt

    monkeypatch.setattr(solve, "run", interrupted)
    assert main(["--out", str(tmp_path)]) == 130
    assert capsys.readouterr().err == "interrupted\n"
    monkeypatch.setattr(solve, "build_parser", lambda: interrupted(None))     # while the estimators are imported
    assert main(["--out", str(tmp_path)]) == 130
    assert capsys.readouterr().err == "interrupted\n"


def test_an_output_that_cannot_be_written_costs_that_file_only(tmp_path, capsys):
    """A folder where the CSV should go: one line naming that file, every other output and the table kept, exit 2."""
    out = tmp_path / "out"
    (out / "Berlin_Potsdamer_Platz_ekf.csv").mkdir(parents=True)
    assert main(["--out", str(out), "--no-plots"]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines()[-1] == f"error: {out / 'Berlin_Potsdamer_Platz_ekf.csv'}: cannot write (Is a directory)"
    assert [line for line in captured.err.splitlines()[:-1]
            if "the accuracy table is in-sample on those epochs" not in line] == []
    assert any(line.startswith("ekf ") and "100.0" in line for line in captured.out.splitlines())   # the table
    for suffix in ("pos", "geojson", "kml"):
        assert (out / f"Berlin_Potsdamer_Platz_ekf.{suffix}").stat().st_size > 0
    assert "outputs: " in captured.out and ".csv" not in captured.out.split("outputs: ")[1].splitlines()[0]


def test_a_figure_that_cannot_be_written_costs_that_figure_only(tmp_path, capsys):
    """A folder where the track plot should go: the other figures and every file are written, exit 2."""
    out = tmp_path / "out"
    (out / "Berlin_Potsdamer_Platz_ekf_track.png" / "inside").mkdir(parents=True)
    assert main(["--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines()[-1] == (f"error: {out / 'Berlin_Potsdamer_Platz_ekf_track.png'}: cannot write "
                                             "(Is a directory)")
    for name in ("errors.png", "cdf.png", "pos", "csv"):
        stem = "Berlin_Potsdamer_Platz_ekf" + ("_" if name.endswith("png") else ".")
        assert (out / f"{stem}{name}").stat().st_size > 0
    assert not list(out.glob(".*partial*"))


def test_a_plotting_bug_costs_no_text_output(tmp_path, capsys, monkeypatch):
    """The figures are drawn after the .pos, CSV, GeoJSON and KML are written: a bug in the plotting is an internal
    error (exit 3) that leaves them."""
    import lfgnss.outputs

    def broken(*args, **kwargs):
        raise RuntimeError("plotting broke")

    monkeypatch.setattr(lfgnss.outputs, "solution_figures", broken)
    assert main(["--out", str(tmp_path), "--backend", "wls"]) == 3
    assert "internal error" in capsys.readouterr().err
    for suffix in ("pos", "csv", "geojson", "kml"):
        assert (tmp_path / f"Berlin_Potsdamer_Platz_wls.{suffix}").stat().st_size > 0


def test_truth_matching_no_epoch_warns_and_skips_the_table(tmp_path, capsys):
    args = ["--obs", str(SAMPLE_OBS), "--nav", *map(str, SAMPLE_NAV), "--truth", str(SAMPLE_TRUTH),
            "--truth-format", "smartloc", "--truth-origin", "0", "--out", str(tmp_path)]
    assert main(args) == 0
    captured = capsys.readouterr()
    assert "no truth epoch matches an epoch" in captured.err and "--truth-origin" in captured.err
    assert "RMSE" not in captured.out        # and no error plots: the track and the solution's own quality only
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["Berlin_Potsdamer_Platz_ekf_quality.png",
                                                              "Berlin_Potsdamer_Platz_ekf_track.png"]
    assert (tmp_path / "Berlin_Potsdamer_Platz_ekf.csv").exists()          # the solution is still written


def test_table_label_names_hand_set_noise_and_fixed_lag(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--no-plots", "--backend", "fgo", "--mode", "fixed-lag", "--no-model"]) == 0
    out = capsys.readouterr().out
    assert "fgo fixed-lag (hand-set noise) " in out                            # the table's row
    assert "backend fgo fixed-lag (hand-set C/N0 noise)\n" in out             # the header says it once
    assert (tmp_path / "Berlin_Potsdamer_Platz_fgo-fixed-lag-hand-set.pos").exists()


def test_a_model_of_ones_own_is_in_the_output_names_and_the_table(tmp_path, capsys):
    import shutil

    shutil.copy(DEFAULT_MODEL, tmp_path / "mine.npz")
    assert main(["--out", str(tmp_path / "o"), "--quiet", "--no-plots", "--model", str(tmp_path / "mine.npz")]) == 0
    assert (tmp_path / "o" / "Berlin_Potsdamer_Platz_ekf-mine.csv").exists()
    assert any(line.startswith("ekf (model mine) ") for line in capsys.readouterr().out.splitlines())
    assert main(["--out", str(tmp_path / "o"), "--quiet", "--no-plots", "--model", "default"]) == 0
    assert any(line.startswith("ekf  ") for line in capsys.readouterr().out.splitlines())    # the run without --model
    for run in ("a", "b"):                   # training runs all export model.npz: named by their run folder
        (tmp_path / run).mkdir()
        shutil.copy(DEFAULT_MODEL, tmp_path / run / "model.npz")
        assert main(["--out", str(tmp_path / "o"), "--quiet", "--no-plots", "--model",
                     str(tmp_path / run / "model.npz")]) == 0
    assert {p.name for p in (tmp_path / "o").glob("*ekf-[ab].csv")} == {"Berlin_Potsdamer_Platz_ekf-a.csv",
                                                                       "Berlin_Potsdamer_Platz_ekf-b.csv"}


def test_fgo_marginals_replace_the_stand_in_sds_and_are_named_in_the_outputs(tmp_path, capsys):
    """--marginals writes the graph's (inflated) marginal sds, not the least-squares stand-in; --formal-sd with it the
    marginals as they are; each run keeps its own files and the positions do not change."""
    import pandas as pd

    window = ["--start", "1900:126700", "--end", "1900:126760"]      # a minute of the drive: three graphs to solve
    for extra in ([], ["--marginals"], ["--marginals", "--formal-sd"]):
        assert main(["--out", str(tmp_path), "--no-plots", "--quiet", "--backend", "fgo", *window, *extra]) == 0
    stand_in, marginals, formal = (pd.read_csv(tmp_path / f"Berlin_Potsdamer_Platz_fgo{tag}-ts1900_126700-te1900_126760"
                                               ".csv") for tag in ("", "-marginals", "-marginals-formal-sd"))
    for a in (marginals, formal):
        assert (a[["x_m", "y_m", "z_m"]].to_numpy() == stand_in[["x_m", "y_m", "z_m"]].to_numpy()).all()
    sd = ["sd_e_m", "sd_n_m", "sd_u_m"]
    assert not (marginals[sd].to_numpy() == stand_in[sd].to_numpy()).all()
    assert (marginals[sd].to_numpy() >= formal[sd].to_numpy() - 1e-9).all()        # inflation never shrinks
    assert (marginals[sd].to_numpy() > formal[sd].to_numpy() + 1e-6).any()


def test_a_bundled_model_is_picked_by_name(tmp_path, capsys):
    from lfgnss.paths import bundled_models

    assert main(["--out", str(tmp_path), "--no-plots", "--model", "hk-tst-static-2020"]) == 0
    assert f"(model {bundled_models()['hk-tst-static-2020']})" in capsys.readouterr().out    # the file, not the name
    assert (tmp_path / "Berlin_Potsdamer_Platz_ekf-hk-tst-static-2020.csv").exists()
    assert main(["--out", str(tmp_path), "--no-plots", "--quiet", "--model", "default"]) == 0
    assert (tmp_path / "Berlin_Potsdamer_Platz_ekf.csv").exists()          # the default model: no tag
    assert not list(tmp_path.glob("*ekf-default*"))


def test_observation_files_that_differ_after_a_dot_keep_their_own_outputs(tmp_path, capsys):
    """drive.day1.obs and drive.day2.obs solved into one --out: each run's files are named after its own file (the
    name up to the first dot made them one, and the second run replaced the first's files)."""
    import shutil

    from lfgnss.solve import obs_stem

    assert [obs_stem(n) for n in ("Berlin_Potsdamer_Platz.obs.gz", "drive.day1.obs", "hksc155c.20o", "x.20d.Z",
                                  "ABMF00GLP_R_20231230000_01D_30S_MO.crx.gz", "data")] == [
        "Berlin_Potsdamer_Platz", "drive.day1", "hksc155c", "x", "ABMF00GLP_R_20231230000_01D_30S_MO", "data"]
    for day in ("day1", "day2"):
        shutil.copy(SAMPLE_OBS, tmp_path / f"drive.{day}.obs.gz")
        assert main(["--out", str(tmp_path / "o"), "--quiet", "--no-plots", "--backend", "wls",
                     "--obs", str(tmp_path / f"drive.{day}.obs.gz"), "--nav", *map(str, SAMPLE_NAV)]) == 0
    for day in ("day1", "day2"):
        pos = (tmp_path / "o" / f"drive.{day}_wls.pos").read_text()
        assert f"% inp file  : {tmp_path / f'drive.{day}.obs.gz'}" in pos


def test_back_ends_compared_in_one_folder_keep_their_own_outputs(tmp_path, capsys):
    """Each run's files carry its back end and variant, so a second run does not overwrite the first."""
    for extra in ([], ["--smooth", "--smooth-lag", "2"], ["--backend", "wls"]):
        assert main(["--out", str(tmp_path), "--quiet", *extra]) == 0
    stems = {"ekf", "ekf-rts-lag2s", "wls"}
    for tag in stems:
        for suffix in (".pos", ".csv", ".geojson", ".kml", "_track.png", "_errors.png", "_cdf.png", "_quality.png"):
            assert (tmp_path / f"Berlin_Potsdamer_Platz_{tag}{suffix}").exists(), (tag, suffix)
    assert len(list(tmp_path.iterdir())) == 8 * len(stems)
    capsys.readouterr()
    assert main(["--out", str(tmp_path), "--backend", "wls", "--smooth"]) == 2
    assert capsys.readouterr().err.rstrip().endswith("not wls")        # the factor graph's reason is fgo's alone


def test_systems_are_case_blind_and_absent_ones_are_reported():
    lower = load(SAMPLE_OBS, SAMPLE_NAV, systems="gr")
    assert lower.systems == load(SAMPLE_OBS, SAMPLE_NAV, systems="GR").systems == ("G", "R")
    with_e = load(SAMPLE_OBS, SAMPLE_NAV, systems="GE")
    assert with_e.systems == ("G",) and any("no E observations (requested)" in w for w in with_e.warnings)


def test_one_line_keeps_quotes_of_the_message():
    assert one_line(KeyError("unknown dataset 'x'")) == "unknown dataset 'x'"
    assert one_line(ValueError("unknown truth format 'foo'")) == "unknown truth format 'foo'"
    assert one_line(FileNotFoundError(2, "No such file or directory", "/a b")) == \
        "[Errno 2] No such file or directory: '/a b'"
    assert one_line(ValueError("two\nlines")) == "two lines"


def test_stdout_closed_early_keeps_the_outputs_and_exits_0(tmp_path):
    """``python -m lfgnss.solve | head -1``: the files are written first; no 'internal error' for the pipe."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "lfgnss.solve", "--no-model", "--no-plots", "--out", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().startswith(str(SAMPLE_OBS))
    proc.stdout.close()                                           # the reader goes away, as head does
    assert proc.wait(timeout=120) == 0
    assert proc.stderr.read() == ""
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".csv", ".geojson", ".kml", ".pos"]


@pytest.mark.parametrize("command", [["learning.export", "--show", "berlin-pp"], ["lfgnss"]])
def test_other_commands_whose_reader_went_away_exit_0(command):
    """Review: ``python -m learning.export --show berlin-pp | head`` sometimes ended 'error: [Errno 32] Broken pipe',
    exit 2 (``lfgnss.datasets`` would have called it an internal error)."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", *command], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()                                           # gone before the command prints
    assert proc.wait(timeout=120) == 0
    assert proc.stderr.read() == ""


def test_formal_sd_writes_the_filters_own_sds_and_the_same_positions(tmp_path):
    """Default: sds inflated by the pseudorange residuals (estimators.consistency), never below the formal ones."""
    import pandas as pd

    for extra in ([], ["--formal-sd"]):       # one folder: the formal run's files are named apart
        assert main(["--out", str(tmp_path), "--quiet", "--no-plots", *extra]) == 0
    inflated, formal = (pd.read_csv(tmp_path / f"Berlin_Potsdamer_Platz_{tag}.csv") for tag in ("ekf", "ekf-formal-sd"))
    pd.testing.assert_frame_equal(inflated[["x_m", "y_m", "z_m"]], formal[["x_m", "y_m", "z_m"]])
    sd = ["sd_e_m", "sd_n_m", "sd_u_m"]
    assert (inflated[sd].to_numpy() >= formal[sd].to_numpy() - 1e-4).all()
    assert (inflated[sd].to_numpy() > 2 * formal[sd].to_numpy()).any()


def test_points_writes_each_epoch_into_the_geojson_and_kml(tmp_path):
    """--points: the per-epoch points (time, status, satellites) were library-only."""
    import json

    assert main(["--out", str(tmp_path), "--no-plots", "--quiet", "--backend", "wls", "--points"]) == 0
    doc = json.loads((tmp_path / "Berlin_Potsdamer_Platz_wls.geojson").read_text())
    points = [f for f in doc["features"] if f["geometry"]["type"] == "Point"]
    assert len(points) == 1375 and points[0]["properties"]["time_utc"] == "2016-06-06T11:10:24.700Z"
    assert (tmp_path / "Berlin_Potsdamer_Platz_wls.kml").read_text().count("<TimeStamp>") == 1375
    assert main(["--out", str(tmp_path / "plain"), "--no-plots", "--quiet", "--backend", "wls"]) == 0
    doc = json.loads((tmp_path / "plain" / "Berlin_Potsdamer_Platz_wls.geojson").read_text())
    assert [f["geometry"]["type"] for f in doc["features"]] == ["LineString"]


def test_several_obs_files_are_joined_in_time_order(tmp_path, capsys):
    """--obs took one file; a drive logged in pieces (hourly files) had to be merged by hand. Given in any order, the
    pieces solve as the whole file does; overlapping pieces are refused in one line."""
    import gzip
    import re

    text = gzip.open(SAMPLE_OBS, "rt").read()
    end = text.index("\n", text.index("END OF HEADER")) + 1
    head, body = text[:end], text[end:]
    cut = re.search(r"^ 16  6  6 11 13 ", body, re.M).start()
    (tmp_path / "a.obs").write_text(head + body[:cut])
    (tmp_path / "b.obs").write_text(head + body[cut:])
    nav = ["--nav", *map(str, SAMPLE_NAV), "--no-plots", "--quiet", "--backend", "plain-ekf"]
    assert main(["--obs", str(tmp_path / "b.obs"), str(tmp_path / "a.obs"), "--out", str(tmp_path / "parts"), *nav]) == 0
    assert main(["--obs", str(SAMPLE_OBS), "--out", str(tmp_path / "whole"), *nav]) == 0
    parts = (tmp_path / "parts" / "b_plain-ekf.csv").read_text()        # named after the first file given
    assert parts == (tmp_path / "whole" / "Berlin_Potsdamer_Platz_plain-ekf.csv").read_text()
    header = [ln for ln in (tmp_path / "parts" / "b_plain-ekf.pos").read_text().splitlines() if ln.startswith("%")]
    assert [ln.split(":", 1)[1].strip() for ln in header if ln.startswith("% inp file")][:2] == [
        str(tmp_path / "b.obs"), str(tmp_path / "a.obs")]
    capsys.readouterr()
    assert main(["--obs", str(tmp_path / "a.obs"), str(SAMPLE_OBS), "--out", str(tmp_path / "o"), *nav]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "overlaps" in err and "must not overlap" in err, err
    assert main(["--obs", str(tmp_path / "a.obs"), str(tmp_path / "b.obs"), "--start", "1900:127000",
                 "--out", str(tmp_path / "o"), *nav]) == 2
    assert "(1900:127000); the files (a.obs + b.obs) span, with their gaps, 2016-06-06 11:10:41.7 to 11:15:25.1 " \
        in capsys.readouterr().err
