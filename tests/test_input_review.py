"""Session 50's own-data and library review of the front end: inputs that ran silently wrong or failed unclearly."""
from __future__ import annotations

import dataclasses
import gzip

import numpy as np
import pytest

from lfgnss import datasets
from lfgnss.errors import InputError, RinexError
from lfgnss.solve import SAMPLE_DIR

SAMPLE_NAV = [SAMPLE_DIR / "brdc1580.16n.gz", SAMPLE_DIR / "brdc1580.16g.gz"]
MET_HEADER = ("     3.02           METEOROLOGICAL DATA                     RINEX VERSION / TYPE\n"
              "                                                            END OF HEADER\n")


@pytest.fixture
def seq():
    """The first 20 epochs of the bundled drive as a Sequence."""
    import lfgnss

    return lfgnss.process(SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz", SAMPLE_NAV).subset(slice(0, 20))


@pytest.mark.parametrize("change, message", [
    (lambda s: {"coarse_ecef_m": np.where(np.arange(len(s))[:, None] < 5, 0.0, s.coarse_ecef_m)},
     "coarse_ecef_m has 5 row(s) 0 m (first) from the Earth's centre"),
    (lambda s: {"sat_pos_ecef_m": s.sat_pos_ecef_m / 1000.0}, "sat_pos_ecef_m (used slots) has"),
    (lambda s: {"pr_m": s.pr_m.astype(np.float32)}, "pr_m must be float64, got float32"),
    (lambda s: {"sat_pos_ecef_m": s.sat_pos_ecef_m.astype(np.float32)}, "sat_pos_ecef_m must be float64"),
], ids=["coarse-zeros", "satellites-in-km", "float32-pseudoranges", "float32-satellites"])
def test_a_sequence_refuses_positions_that_cannot_be_right(seq, change, message):
    """Defect: zeros for "no coarse fix" put the factor graph at the Earth's centre as 'updated'; satellites in km or
    float32 inputs ran and moved positions by metres, all without a word."""
    with pytest.raises(ValueError, match=f"^Sequence '.*': {message}".replace("(", r"\(").replace(")", r"\)")):
        dataclasses.replace(seq, **change(seq))


def test_nan_coarse_fixes_and_masked_zero_satellites_still_pass(seq):
    coarse = seq.coarse_ecef_m.copy()
    coarse[:3] = np.nan
    sats = np.where(seq.mask[..., None], seq.sat_pos_ecef_m, 0.0)
    assert len(dataclasses.replace(seq, coarse_ecef_m=coarse, sat_pos_ecef_m=sats)) == 20


TRUTH_ROWS = "2051,47000.0,22.30,114.17,6.5\n2051,47001.0,22.30,114.17,6.6\n"
EPOCHS = np.array([2051 * 604800 + 47000.0, 2051 * 604800 + 47001.0])


@pytest.mark.parametrize("text, labelled", [
    ("\ufeff" + TRUTH_ROWS, 2),                                            # Excel's "CSV UTF-8"
    ("% program : RTKLIB\n%  GPST lat lon h\n" + TRUTH_ROWS, 2),           # '%' lines: comments, no warning
], ids=["byte-order-mark", "percent-comments"])
def test_truth_rows_after_a_byte_order_mark_or_percent_comments_are_read(tmp_path, text, labelled, recwarn):
    path = tmp_path / "gt.csv"
    path.write_bytes(text.encode("utf-8"))
    truth = datasets.read_truth(path, EPOCHS)
    assert np.isfinite(truth).all(axis=1).sum() == labelled
    assert not [w for w in recwarn if "skipped" in str(w.message)]


@pytest.mark.parametrize("line, why", [
    ("2019/04/28 13:03:20.000 22.30 114.17 6.5", "a calendar date: truth times are numbers of GPS time"),
    ("2051;47000,0;22,30;114,17;6,5", "semicolon-separated: separate numbers by commas or spaces"),
], ids=["calendar", "semicolons"])
def test_a_truth_of_calendar_dates_or_semicolons_says_so(tmp_path, line, why):
    path = tmp_path / "gt.csv"
    path.write_text(line + "\n")
    with pytest.raises(InputError) as err:
        datasets.read_truth(path, EPOCHS)
    assert str(err.value).startswith(f"{path}:1: no readable ground-truth line; the first: unreadable truth line "
                                     f"({why}")


def test_an_rtklib_pos_file_is_a_truth_format(tmp_path, seq):
    """A reference trajectory from RTKLIB (or from python -m lfgnss.solve) is read as truth (format "pos"), in
    calendar or week/TOW time; its positions come back to the sub-millimetre."""
    import estimators
    from lfgnss.outputs import write_pos

    sol = estimators.create("wls").solve(seq)
    for time_format in ("calendar", "tow"):
        path = write_pos(tmp_path / f"ref-{time_format}.pos", sol, time_format=time_format)
        truth = datasets.read_truth(path, seq.time_gps_s, "POS")
        ok = np.isfinite(sol.pos_ecef_m).all(axis=1)
        assert ok.sum() > 10 and np.abs(truth[ok] - sol.pos_ecef_m[ok]).max() < 1e-3
    bad = tmp_path / "bad.pos"
    bad.write_text("%  GPST latitude(deg) longitude(deg) height(m)\n2016/06/06 11:10:41.7 52.5 13.3\n")
    with pytest.raises(InputError, match=r"bad\.pos:2: expected at least 13 fields \(time, position, Q, ns, six sds; age and ratio may follow\), got 4$"):
        datasets.read_truth(bad, seq.time_gps_s, "pos")


def test_a_truth_in_local_time_is_named_with_its_time_zone(sample_toml, tmp_path):
    """Defect: a truth stamped in local time (UTC+8) got "its GPS times miss them" and raw second counts."""
    import warnings

    epochs = EPOCHS[0] + np.arange(600.0)
    path = tmp_path / "gt_local.csv"
    tow = epochs - 2051 * 604800 + 8 * 3600 - 18           # local time, UTC+8, on GPS time's week count
    path.write_text("".join(f"2051,{t:.1f},22.30,114.17,6.5\n" for t in tow))
    spec = datasets.DatasetSpec("local", (), (), path, "urbannav")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert not np.isfinite(datasets.align_truth(epochs, spec)[0]).any()
    words = datasets.unmatched_time_words(spec, epochs)
    assert words.startswith("; its times (") and ("would fit the epochs as local time, about UTC+8 h: urbannav times "
                                                  "are GPST, so subtract 8 h and add GPST - UTC (18 s here): give "
                                                  "--truth-offset -28782;") in words
    # a first guess already given (UTC: 18 s) does not enter the offset named, which is the whole one
    guessed = dataclasses.replace(spec, time_offset_s=18.0)
    assert "give --truth-offset -28782;" in datasets.unmatched_time_words(guessed, epochs)


def test_an_unknown_split_is_one_line_with_a_suggestion_before_any_build(monkeypatch):
    monkeypatch.setattr(datasets, "build", lambda *a, **k: pytest.fail("built before the split was checked"))
    with pytest.raises(KeyError) as err:
        datasets.load_split("hk-tst-2019", "tst")
    assert str(err.value) == "dataset hk-tst-2019 has no split 'tst' (did you mean 'test'?); it has train, val, test"
    with pytest.raises(KeyError, match="no split 'vall' \\(did you mean 'val'\\?\\)"):
        datasets.load_split("hk-tst-2019", "train+vall")


def test_a_met_file_among_navigation_files_is_left_out_with_a_warning(tmp_path):
    """Defect: a glob over a station folder (brdc*.20n, .20g, .20m) failed on the meteorological file."""
    from lfgnss.navigation import RinexWarning, load_nav

    met = tmp_path / "brdc1580.16m"
    met.write_text(MET_HEADER)
    with pytest.warns(RinexWarning, match=f"^{met}: not a RINEX 2/3 navigation file .*METEOROLOGICAL DATA.*: left "
                                          "out of the navigation files$"):
        nav = load_nav([*SAMPLE_NAV, met], cache=False)
    assert nav.kepler is not None
    with pytest.raises(RinexError, match=f"^{met}:1: not a RINEX 2/3 navigation file"):
        load_nav([met], cache=False)
    other = tmp_path / "other.16m"
    with gzip.open(other, "wt") as fh:
        fh.write(MET_HEADER)
    with pytest.raises(RinexError, match="not a RINEX 2/3 navigation file, nor is any other of the 2 files given"):
        load_nav([met, other], cache=False)


def test_a_pos_truths_lines_off_the_earth_are_skipped_and_a_byte_order_mark_read_past(tmp_path, seq):
    """Review (session 50): a Q = 0 "no solution" line (0, 0, 0) was scored as truth (3D RMSE 155 km); a .pos file
    with a byte order mark was refused."""
    import estimators
    from lfgnss.outputs import write_pos

    sol = estimators.create("wls").solve(seq)
    good = write_pos(tmp_path / "ref.pos", sol).read_text()
    lines = good.splitlines(keepends=True)
    body = [i for i, line in enumerate(lines) if not line.startswith("%")]
    fields = lines[body[3]].split()
    fields[2:6] = ["0.000000000", "0.000000000", "0.0000", "0"]            # a Q = 0 "no solution" line
    lines[body[3]] = " ".join(fields) + "\n"
    (tmp_path / "q0.pos").write_text("".join(lines))
    with pytest.warns(UserWarning, match=r"q0\.pos: 1 solution line\(s\) with Q = 0 \(no solution\) or off the "
                                         r"Earth \(the first at GPS "):
        truth = datasets.read_truth(tmp_path / "q0.pos", seq.time_gps_s, "pos")
    ok = np.isfinite(sol.pos_ecef_m).all(axis=1)       # the skipped line's epoch: interpolated between its neighbours
    assert np.isfinite(truth[ok]).all() and np.linalg.norm(truth[ok] - sol.pos_ecef_m[ok], axis=1).max() < 50
    (tmp_path / "bom.pos").write_text("\ufeff" + good, encoding="utf-8")
    assert np.isfinite(datasets.read_truth(tmp_path / "bom.pos", seq.time_gps_s, "pos")).all(axis=1).sum() == len(body)
    (tmp_path / "none.pos").write_text("".join(lines[:body[0]]) + lines[body[3]])
    with pytest.raises(InputError, match="every solution line has Q = 0 \\(no solution\\) or lies off the Earth"):
        datasets.read_truth(tmp_path / "none.pos", seq.time_gps_s, "pos")


def test_the_local_time_zone_is_found_when_the_truth_covers_part_of_the_drive(tmp_path):
    """Review (session 50): from the middles of the two spans, a 484 s truth inside an hour's drive read as UTC+8.25."""
    epochs = EPOCHS[0] - 3000 + np.arange(4084.0)
    tow = EPOCHS[0] + np.arange(484.0) - 2051 * 604800 + 8 * 3600 - 18
    path = tmp_path / "gt_local.csv"
    path.write_text("".join(f"2051,{t:.1f},22.30,114.17,6.5\n" for t in tow))
    words = datasets.unmatched_time_words(datasets.DatasetSpec("local", (), (), path, "urbannav"), epochs)
    assert "about UTC+8 h" in words and "subtract 8 h" in words, words


def test_a_misspelt_truth_format_is_named_before_anything_about_its_keys(sample_toml):
    path = sample_toml("typo-format")
    path.write_text(path.read_text().replace('format = "smartloc"', 'format = "smartlock"'))
    with pytest.raises(InputError, match=r"unknown truth format 'smartlock' in \[truth\]; use one of .* \(did you mean "
                                         r"'smartloc'\?\)"):
        datasets.register_toml(path)


def test_the_unseen_constellation_note_offers_no_systems_option_that_would_leave_nothing():
    from types import SimpleNamespace

    from lfgnss.solve import unseen_systems_note

    g_only = SimpleNamespace(metadata={"data_spans": [{"systems": "G"}]})
    assert unseen_systems_note(g_only, ("E", "C")) == ("trained on G data only; this run's Galileo and BeiDou "
                                                       "satellites get R and v^c from a network that never saw those "
                                                       "constellations")
