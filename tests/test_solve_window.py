"""``python -m lfgnss.solve --start/--end/--elevation-mask`` (rnx2rtkp's -ts/-te and elevation mask) on the bundled
Berlin sample: the window solves exactly its epochs, both time forms agree, the mask reaches the coarse fix and the
features alike, and misuse is one line."""
from __future__ import annotations

import csv
import gzip
import warnings
from dataclasses import replace

import numpy as np
import pytest

import lfgnss.features
from lfgnss.rinex import load_obs
from lfgnss.solve import DEFAULT_MODEL, SAMPLE_NAV, SAMPLE_OBS, WINDOW_TOLERANCE_S, main

FAST = ["--backend", "wls", "--no-plots", "--quiet"]          # least squares: the window and mask, not the filter


@pytest.fixture(scope="module")
def epochs() -> np.ndarray:
    """(T,) GPS seconds of every epoch of the bundled observation file."""
    return load_obs(SAMPLE_OBS).time_gps_s


def _times(path) -> np.ndarray:
    """The ``time_gps_s`` column of a solution CSV [s]."""
    with open(path, newline="") as fh:
        return np.array([float(row["time_gps_s"]) for row in csv.DictReader(fh)])


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.rstrip("\n")


@pytest.fixture
def sequences(monkeypatch) -> list:
    """The (meas, fix, Sequence) of every solve in the test, taken as ``build_sequence`` makes them."""
    made, build = [], lfgnss.features.build_sequence

    def spy(meas, fix, **kwargs):
        made.append((meas, fix, build(meas, fix, **kwargs)))
        return made[-1][2]

    monkeypatch.setattr(lfgnss.features, "build_sequence", spy)
    return made


def test_the_window_solves_exactly_its_epochs_with_ends_included(tmp_path, epochs, capsys):
    first, last = 100, 400
    start, end = (f"1900:{np.format_float_positional(round(t - 1900 * 604800, 1), trim='-')}"
                  for t in (epochs[first], epochs[last]))
    assert main([*FAST, "--out", str(tmp_path), "--start", start, "--end", end]) == 0
    stem = f"Berlin_Potsdamer_Platz_wls-ts{start.replace(':', '_')}-te{end.replace(':', '_')}"   # the window names them
    np.testing.assert_allclose(_times(tmp_path / f"{stem}.csv"), epochs[first:last + 1], rtol=0, atol=1e-3)
    header = (tmp_path / f"{stem}.pos").read_text().splitlines()[0]
    assert header.endswith(f"backend wls --start {start} --end {end}"), header
    assert "(--start/--end)" not in capsys.readouterr().out          # --quiet: the table only


def test_week_tow_and_calendar_times_give_the_same_run(tmp_path, capsys):
    runs = {"week-tow": ("1900:126700.5", "1900:126760"), "rnx2rtkp": ("2016/06/06 11:11:40.5", "2016/06/06 11:12:40"),
            "iso": ("2016-06-06T11:11:40.5", "2016-06-06T11:12:40.0")}
    for name, (start, end) in runs.items():
        assert main([*FAST, "--out", str(tmp_path / name), "--start", start, "--end", end]) == 0
    stem = "Berlin_Potsdamer_Platz_wls-ts1900_126700.5-te1900_126760"
    texts = {name: (tmp_path / name / f"{stem}.csv").read_text() for name in runs}
    assert texts["week-tow"] == texts["rnx2rtkp"] == texts["iso"]
    times = _times(tmp_path / "iso" / f"{stem}.csv")
    assert times[0] >= 1900 * 604800 + 126700.5 and times[-1] <= 1900 * 604800 + 126760 and times.size > 250


def test_an_open_window_and_truth_matched_as_on_the_whole_file(tmp_path, epochs, sequences):
    assert main([*FAST, "--out", str(tmp_path / "all")]) == 0
    assert main([*FAST, "--out", str(tmp_path / "late"), "--start", "2016/06/06 11:14:00"]) == 0
    whole, late = sequences[0][2], sequences[1][2]
    keep = epochs >= 1900 * 604800 + 126840.0 - WINDOW_TOLERANCE_S
    np.testing.assert_array_equal(late.time_gps_s, epochs[keep])
    # smartloc truth counts its t from the file's first epoch, not the window's: the same rows as the whole run's
    np.testing.assert_array_equal(late.truth_ecef_m, whole.truth_ecef_m[keep])
    assert np.isfinite(late.truth_ecef_m).all(axis=1).sum() > 300


def test_a_window_without_epochs_is_one_line_naming_file_window_and_span(tmp_path, capsys):
    assert main([*FAST, "--out", str(tmp_path), "--start", "1900:127000", "--end", "2016/06/06 11:20:00"]) == 2
    assert _one_line(capsys.readouterr().err) == (
        f"error: {SAMPLE_OBS}: no epoch in --start/--end 2016-06-06 11:16:40 GPST (1900:127000) to 2016-06-06 "
        f"11:20:00 GPST (1900:127200); the file spans 2016-06-06 11:10:41.7 to 11:15:25.1 GPST (283.4 s)")
    assert main(["--no-plots", "--out", str(tmp_path), "--end", "1900:126000", "--elevation-mask", "15"]) == 2
    err = _one_line(capsys.readouterr().err)                  # the model's mask warning waits for good input
    assert err.startswith(f"error: {SAMPLE_OBS}: no epoch in --start/--end up to 2016-06-06 11:00:00 GPST"), err
    assert not list(tmp_path.iterdir())


def test_an_end_before_the_start_is_one_line_before_any_work(tmp_path, capsys, sequences):
    assert main([*FAST, "--out", str(tmp_path / "out"), "--start", "1900:126800", "--end", "2016/06/06 11:12:00"]) == 2
    assert _one_line(capsys.readouterr().err) == ("error: --end 2016-06-06 11:12:00 GPST (1900:126720) is before "
                                                  "--start 2016-06-06 11:13:20 GPST (1900:126800)")
    assert not sequences and not (tmp_path / "out").exists()


def test_a_15_degree_mask_drops_low_satellites_everywhere_and_warns_of_the_model(tmp_path, capsys, sequences):
    window = ["--end", "1900:126700", "--no-plots", "--quiet"]      # G29 rises through 15 degrees at 126699.5 s
    assert main([*window, "--out", str(tmp_path)]) == 0
    assert "elevation mask" not in capsys.readouterr().err
    assert main([*window, "--out", str(tmp_path), "--elevation-mask", "15"]) == 0
    lines = capsys.readouterr().err.splitlines()        # and the bundled model's in-sample note (berlin-pp train)
    assert lines[0] == (
        f"warning: {DEFAULT_MODEL}: learned models are trained with a 10 degree elevation mask, this run uses "
        "--elevation-mask 15; its noise estimates may not carry over")
    assert len(lines) == 2 and lines[1].endswith("the accuracy table is in-sample on those epochs"), lines
    (_, fix10, seq10), (_, fix15, seq15) = sequences
    assert seq15.mask.sum() < seq10.mask.sum() and fix15.used.sum() < fix10.used.sum()
    assert np.all(seq15.el_rad[seq15.mask] >= np.radians(15)) and np.all(fix15.el_rad[fix15.used] >= np.radians(15))
    assert not (seq15.mask & ~seq10.mask).any()                  # only drops, and only below 15 degrees
    assert np.all(seq10.el_rad[seq10.mask & ~seq15.mask] < np.radians(15))
    header = (tmp_path / "Berlin_Potsdamer_Platz_ekf-te1900_126700-mask15.pos").read_text().splitlines()[0]
    assert header.endswith("backend ekf --end 1900:126700 --elevation-mask 15"), header
    assert (tmp_path / "Berlin_Potsdamer_Platz_ekf-te1900_126700.pos").exists()  # the 10-degree run keeps its files


def test_no_warning_without_a_learned_model(tmp_path, capsys):
    assert main([*FAST, "--out", str(tmp_path), "--elevation-mask", "5", "--end", "1900:126660"]) == 0
    assert capsys.readouterr().err == ""
    assert main(["--no-model", "--no-plots", "--quiet", "--out", str(tmp_path), "--elevation-mask", "5",
                 "--end", "1900:126660"]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("option, value, message", [
    ("--elevation-mask", "90", "needs an elevation in [0, 90) degrees, got '90'"),
    ("--elevation-mask", "-1", "needs an elevation in [0, 90) degrees, got '-1'"),
    ("--elevation-mask", "nan", "needs a finite number, got 'nan'"),
    ("--elevation-mask", "ten", "needs a finite number, got 'ten'"),
    ("--start", "1900:604800", "the time of week must be below 604800 s, got '1900:604800'"),
    ("--end", "2016/06/31 00:00:00", "not a calendar time (day is out of range for month), got '2016/06/31 00:00:00'"),
    ("--start", "2016/06/06", 'needs a GPS time, WEEK:TOW (1900:126700.5) or "YYYY/MM/DD HH:MM:SS" '
                              "(2016/06/06 11:11:40.5), got '2016/06/06'"),
])
def test_bad_values_are_option_errors(tmp_path, capsys, option, value, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["--out", str(tmp_path / "out"), option, value])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "Traceback" not in err
    assert err.splitlines()[-1] == f"python -m lfgnss.solve: error: argument {option}: {message}"
    assert not (tmp_path / "out").exists()


def test_an_epoch_tagged_a_few_ms_early_is_in_the_window(tmp_path, epochs, sequences):
    """Receivers tag epochs milliseconds off the second; the window takes them as rnx2rtkp does (DTTOL 25 ms)."""
    k = 200
    start = f"1900:{np.format_float_positional(round(epochs[k] - 1900 * 604800 + 0.02, 2), trim='-')}"
    end = f"1900:{np.format_float_positional(round(epochs[k + 5] - 1900 * 604800 - 0.02, 2), trim='-')}"
    assert main([*FAST, "--out", str(tmp_path), "--start", start, "--end", end]) == 0
    np.testing.assert_array_equal(sequences[0][2].time_gps_s, epochs[k:k + 6])


def test_a_window_without_one_constellation_gives_no_warning_about_it():
    """Epochs where GLONASS is not tracked (here: blanked) do not say "no C/N0 for R" or "no usable R observation"."""
    import lfgnss

    obs = load_obs(SAMPLE_OBS).select_epochs(slice(0, 50))
    glonass = np.array([s.startswith("R") for s in obs.sv])
    blank = replace(obs, pr_m=np.where(glonass, np.nan, obs.pr_m), cn0_dbhz=np.where(glonass, np.nan, obs.cn0_dbhz))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        meas = lfgnss.load(blank, SAMPLE_NAV)
    said = [str(w.message) for w in caught] + list(meas.warnings)
    assert glonass.any() and not [m for m in said if "for R" in m or "usable R" in m], said
    assert meas.systems == ("G",)


def test_input_notes_under_a_window_say_the_file_is_read_whole(tmp_path, epochs, capsys):
    """The whole file is read, so a damaged epoch after --end is noted, and the notes say whose they are."""
    lines = gzip.open(SAMPLE_OBS, "rt").read().splitlines(keepends=True)
    last = max(k for k, line in enumerate(lines) if line.startswith(" 16  6  6 "))     # RINEX 2 epoch lines
    lines[last] = " 16  6  6 xx" + lines[last][12:]
    obs = tmp_path / "damaged.obs"
    obs.write_text("".join(lines))
    end = f"1900:{np.format_float_positional(round(epochs[100] - 1900 * 604800, 1), trim='-')}"
    base = ["--backend", "wls", "--no-plots", "--obs", str(obs), "--nav", *map(str, SAMPLE_NAV)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")        # the reader's RinexWarning; the notes are what is tested
        assert main([*base, "--out", str(tmp_path / "window"), "--end", end]) == 0
        windowed = capsys.readouterr().out
        assert main([*base, "--out", str(tmp_path / "whole")]) == 0
        whole = capsys.readouterr().out
    note = f"warning: {obs}:{last + 1}: unreadable epoch line"
    assert "input notes (the file is read whole: some may be outside --start/--end): 1 (" in windowed, windowed
    assert note in windowed, windowed
    assert "input notes: 1 (" in whole and note in whole, whole
