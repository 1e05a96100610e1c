"""Dataset TOML files (user review): typos, splits, constellation letters, missing files and unknown ids are one
line naming the TOML file (and the key), never silently ignored, never a traceback."""
from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from lfgnss import benchmark, datasets
from lfgnss.errors import InputError
from lfgnss.simulate import simulate_sequence
from lfgnss.solve import SAMPLE_DIR


@pytest.fixture
def clean_registry(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "_REGISTRY", {})


def _edited(sample_toml, name: str, old: str, new: str):
    """``sample_toml(name)`` with one line changed (``old`` must be in it)."""
    path = sample_toml(name)
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize("old, new, message", [
    ("systems =", "sytems =", "unknown key 'sytems' (did you mean 'systems'?); known keys: id, obs, nav, systems, "
                              "description, [truth], [splits]"),
    ("test =", "tset =", "unknown key 'tset' in [splits] (did you mean 'test'?); known keys in [splits]: "
                         "axis, train, val, test"),
    ("format =", "fromat =", "unknown key 'fromat' in [truth] (did you mean 'format'?); known keys in [truth]: "
                             "file, format, match_tolerance_s, time_origin_gps_s"),
    ("[truth]", "[truht]", "unknown table [truht] (did you mean [truth]?)"),
    ("axis =", "colour = 3\naxis =", "unknown key 'colour' in [splits]; known keys in [splits]: axis, train"),
], ids=["top", "splits", "truth", "table", "no-suggestion"])
def test_a_typo_at_any_level_is_refused_with_the_file_the_key_and_the_known_keys(
        sample_toml, clean_registry, capsys, old, new, message):
    """Defect: sytems, tset and fromat were ignored (all systems, no test split, the default truth format)."""
    path = _edited(sample_toml, "typo", old, new)
    with pytest.raises(InputError, match=re.escape(f"{path}: {message}")):
        datasets.register_toml(path)
    assert "typo" not in datasets.registered()
    assert datasets.main(["--register", str(path)]) == 2          # used to exit 0 for tset
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.startswith(f"error: {path}: {message}") and captured.err.count("\n") == 1


@pytest.mark.parametrize("case", ["no-table", "empty-table", "bad-bounds"])
def test_a_toml_without_usable_splits_is_refused_where_they_are_needed(tmp_path, sample_toml, clean_registry, capsys,
                                                                        case):
    """Defect: without [splits] the benchmark ended in '...has no split 'test'; it has))', not naming the TOML.

    A TOML without splits is valid where none is needed (``python -m lfgnss.summary``); the benchmark refuses it
    before the run, and malformed bounds are refused at registration.
    """
    path = sample_toml("no-splits")
    head, _ = path.read_text().split("[splits]")
    text, message = {
        "no-table": (head, "[splits] has no test, which this command uses; give test = [start, stop] on the tow "
                           "axis (it has none)"),
        "empty-table": (head + '[splits]\naxis = "relative_s"\n', "[splits] has no test, which this command uses; "
                                                                  "give test = [start, stop] on the relative_s axis"),
        "bad-bounds": (head + "[splits]\ntrain = [150, 0]\n",
                       "[splits] train must be [start, stop], two numbers (inf allowed) with start < stop (on the tow axis), got [150, 0]"),
    }[case]
    path.write_text(text)
    if case == "bad-bounds":
        with pytest.raises(InputError, match=re.escape(f"{path}: {message}")):
            datasets.register_toml(path)
    else:
        assert datasets.register_toml(path).splits == {}
    code = benchmark.main(["no-splits", "--register", str(path), "--out", str(tmp_path / "out"), "--no-plots"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"error: {path}: {message}") and err.count("\n") == 1


def test_an_open_ended_split_stays_valid(sample_toml, clean_registry):
    """``test = [180, inf]`` (to the end of the drive) was valid before the bounds were checked, and stays so."""
    path = _edited(sample_toml, "open", "test = [180, 200]", "test = [180, inf]")
    assert datasets.register_toml(path).splits["test"] == (180, float("inf"))


def test_splits_a_caller_needs_are_checked_at_registration_and_others_stay_optional(sample_toml, clean_registry):
    """A TOML with train and test only (no val) stays valid; a caller naming the splits it uses is refused early."""
    path = _edited(sample_toml, "no-val", "val = [150, 180]", "")
    spec = datasets.register_toml(path)
    assert sorted(spec.splits) == ["test", "train"] and spec.source == path
    assert datasets.register_toml(path, need_splits=("test",)).id == "no-val"
    with pytest.raises(InputError, match=re.escape(f"{path}: [splits] has no val, which this command uses; give "
                                                   f"val = [start, stop] on the relative_s axis (it has train, test)")):
        datasets.register_toml(path, need_splits=("train", "val"))


def test_a_missing_split_is_named_whole_and_with_its_toml(sample_toml, clean_registry):
    seq = simulate_sequence(5)
    spec = datasets.DatasetSpec("py", ("r.obs",), ("n.nav",), "t.csv", "urbannav")        # made in Python: no splits
    with pytest.raises(KeyError) as err:
        datasets.split_index(seq, spec, "test")
    assert err.value.args[0] == "dataset py has no split 'test'; it has none"
    path = _edited(sample_toml, "no-test", "test = [180, 200]", "")
    spec = datasets.register_toml(path)
    with pytest.raises(KeyError) as err:
        datasets.split_index(seq, spec, "test")
    assert err.value.args[0] == (f"dataset no-test has no split 'test'; it has train, val; give test = [start, stop] "
                                 f"under [splits] in {path}")


@pytest.mark.parametrize("systems, message", [
    ('["X"]', "unknown constellation letter(s) X in systems; use GCERJ"),
    ('["G", "Q", "X"]', "unknown constellation letter(s) QX in systems; use GCERJ"),
    ("[]", "systems must be a list of constellation letters of GCERJ"),
    ("[1]", "systems must be a list of constellation letters of GCERJ"),
])
def test_unknown_constellation_letters_name_the_toml(sample_toml, clean_registry, systems, message):
    """Defect: 'unknown constellation letter(s) X in the requested systems' came at build time without the TOML."""
    path = _edited(sample_toml, "letters", 'systems = ["G", "R"]', f"systems = {systems}")
    with pytest.raises(InputError, match=re.escape(f"{path}: {message}")):
        datasets.register_toml(path)


def test_lower_case_and_string_systems_are_still_letters(sample_toml, clean_registry):
    """Review: lower case was kept ("constellation(s) gr ... left out: the sequence has GR"); "G R" was refused."""
    assert datasets.register_toml(_edited(sample_toml, "lower", '["G", "R"]', '["g", "r"]')).systems == ("G", "R")
    assert datasets.register_toml(_edited(sample_toml, "string", '["G", "R"]', '"GR"')).systems == ("G", "R")
    assert datasets.register_toml(_edited(sample_toml, "spaced", '["G", "R"]', '"g, r"')).systems == ("G", "R")


def test_a_missing_obs_file_is_one_line_naming_the_toml_and_the_file(tmp_path, sample_toml, clean_registry, capsys):
    """Defect: 'my-drive: skipped, missing nope.obs' then 'error: dataset not built: ...', neither naming the TOML."""
    path = tmp_path / "bad.toml"
    path.write_text(re.sub(r'(?m)^obs = .*$', 'obs = ["nope.obs"]', sample_toml("my-drive").read_text()))
    assert datasets.main(["--register", str(path)]) == 2
    captured = capsys.readouterr()
    missing = f"missing {tmp_path / 'nope.obs'} (obs in {path})"
    assert captured.out == ""
    assert captured.err == f"error: dataset not built: my-drive: {missing}\n"
    spec = datasets.get("my-drive")
    assert spec.missing_note() == missing
    lines = []
    assert datasets.present(["my-drive"], lines.append) == [] and lines == [f"my-drive: skipped, {missing}"]
    with pytest.raises(FileNotFoundError, match=re.escape(f"dataset my-drive: {missing}")):
        datasets.build("my-drive")
    truth = tmp_path / "truth.txt"                                  # the truth file is named by its key too
    path.write_text(re.sub(r'(?m)^file = .*$', 'file = "truth.txt"', sample_toml("my-drive").read_text()))
    datasets.register_toml(path)
    assert datasets.get("my-drive").missing_note() == f"missing {truth} ([truth] file in {path})"


def test_built_in_datasets_without_shared_data_keep_their_skipped_line(tmp_path, monkeypatch, capsys):
    """The benchmark sets' absent shared data stay an informational line (quiet for the default run)."""
    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path))
    lines = []
    assert datasets.present(["berlin-pp"], lines.append) == []
    assert lines == [f"berlin-pp: skipped, missing {datasets.get('berlin-pp').missing()[0]} (the benchmark datasets "
                     f"are read from $LFGNSS_SHARED_DATA, else ../shared/data beside the checkout)"]
    assert datasets.main([]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and captured.out.count(": skipped, missing ") == 3
    assert datasets.main(["berlin-pp"]) == 2
    captured = capsys.readouterr()
    assert "berlin-pp: skipped, missing " in captured.out and captured.err.startswith("error: dataset not built: ")


def test_an_unknown_id_says_how_to_register_for_every_command(tmp_path, capsys, clean_registry):
    """Defect: learning.train said only 'unknown dataset ...; known: ...'; its way in is data.register."""
    from learning.train import main as train_main

    with pytest.raises(KeyError) as err:
        datasets.get("my-drive")
    message = err.value.args[0]
    assert message.startswith("unknown dataset 'my-drive'; known: berlin-pp, hk-tst-2019")   # and what else is registered
    assert '--register FILE.toml' in message and 'data.register = ["FILE.toml"]' in message
    assert "register_toml" in message
    for hint, end in (("--register FILE.toml", " (--register FILE.toml)"), ("", ")")):   # its own hint, or none
        with pytest.raises(KeyError) as err:
            datasets.get("my-drive", hint=hint)
        assert err.value.args[0].endswith(end) == bool(hint)
    with pytest.raises(SystemExit) as exit_info:
        train_main(["--set", 'data.datasets=["my-drive"]', "--out", str(tmp_path / "run")])
    err_text = capsys.readouterr().err
    assert exit_info.value.code == 2 and err_text.count("\n") == 1
    assert "unknown dataset 'my-drive'" in err_text and 'data.register = ["FILE.toml"]' in err_text


@pytest.mark.parametrize("old, new, message", [
    ("train = [0, 150]", "train = [0, 200]", "[splits] train [0, 200] and val [150, 180] overlap (on the relative_s"),
    ("val = [150, 180]", "val = [150, 190]", "[splits] val [150, 190] and test [180, 200] overlap"),
    ('id = "shadow"', 'id = "berlin-pp"', "id 'berlin-pp' is a benchmark dataset of shared/BENCHMARK.md; give yours "
                                          "another id"),
], ids=["train-test", "val-test", "builtin-id"])
def test_overlapping_splits_and_a_benchmark_id_are_refused(sample_toml, clean_registry, old, new, message):
    """Defects: train = [0, 200] with test = [180, ...] trained on test epochs; id = "berlin-pp" replaced the benchmark
    set (549 'test' epochs scored against its targets)."""
    path = _edited(sample_toml, "shadow", old, new)
    with pytest.raises(InputError, match=re.escape(f"{path}: {message}")):
        datasets.register_toml(path)
    assert datasets.get("berlin-pp").source is None


def test_a_listed_constellation_without_ephemerides_is_warned_of_when_built(sample_toml, monkeypatch, tmp_path):
    """The bundled Berlin drive has GPS and GLONASS navigation files only: a TOML that also lists Galileo gets a
    sequence without it and a warning naming it, each build (the cached one too), instead of a silent G+R model."""
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    path = sample_toml("my-gre")
    path.write_text(path.read_text().replace('systems = ["G", "R"]', 'systems = ["G", "R", "E"]'))
    datasets.register_toml(path)
    for _ in range(2):
        with pytest.warns(UserWarning, match=r"dataset my-gre: constellation\(s\) E of its systems have no usable "
                                             r"observation .* the sequence has GR"):
            seq = datasets.build("my-gre")
        assert seq.systems == ("G", "R")


def test_an_id_registered_by_another_toml_file_is_refused(tmp_path, sample_toml, clean_registry):
    """Review: two TOML files of one id, the last silently won."""
    first = datasets.register_toml(sample_toml("my-drive"))
    assert datasets.register_toml(sample_toml("my-drive")) == first                 # the same file again: fine
    text = sample_toml("my-drive").read_text()
    copy, other = tmp_path / "copy" / "my-drive.toml", tmp_path / "other" / "my-drive.toml"
    for path, content in ((copy, text), (other, text.replace('systems = ["G", "R"]', 'systems = ["G"]'))):
        path.parent.mkdir()
        path.write_text(content)
    assert datasets.register_toml(copy).source == copy  # the same dataset from another file (a notebook cell again)
    with pytest.raises(InputError, match=rf"{re.escape(str(other))}: id 'my-drive' is registered already, by "
                                         rf"{re.escape(str(copy))}, for another dataset; give each dataset its own id"):
        datasets.register_toml(other)
    assert datasets.get("my-drive").systems == ("G", "R")
    copy.write_text(text.replace('systems = ["G", "R"]', 'systems = ["G"]'))       # its own file edited: replaced
    assert datasets.register_toml(copy).systems == ("G",)


@pytest.mark.parametrize("value", ["-1", "0", "inf", "nan", '"0.5"', "true"])
def test_a_match_tolerance_that_is_no_positive_number_is_refused(sample_toml, clean_registry, value):
    path = _edited(sample_toml, "tol", 'format = "smartloc"', f'format = "smartloc"\nmatch_tolerance_s = {value}')
    with pytest.raises(InputError, match=r"match_tolerance_s in \[truth\] must be a number of seconds > 0"):
        datasets.register_toml(path)


def test_a_truth_starting_late_without_an_origin_gets_no_time_warning(tmp_path, sample_toml, clean_registry):
    """Review: the check took t = 0 at the first epoch with truth and a fix, not at the first epoch (as the truth was
    read), and warned of a wrong origin for a truth that starts 20 s into the drive."""
    from lfgnss.solve import SAMPLE_TRUTH

    rows = [line for line in SAMPLE_TRUTH.read_text().splitlines() if float(line.split()[1]) >= 20.0]
    (tmp_path / "late.txt").write_text("\n".join(rows) + "\n")
    path = sample_toml("late-truth", truth=tmp_path / "late.txt")
    path.write_text("\n".join(line for line in path.read_text().splitlines() if "time_origin_gps_s" not in line))
    datasets.register_toml(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq = datasets.build("late-truth")
    assert 1200 < seq.labelled.sum() < 1372


def test_the_same_dataset_spelled_otherwise_from_another_file_is_accepted(tmp_path, sample_toml, clean_registry):
    """Review: two TOMLs naming one truth file as ../data/gt.txt from sibling folders were refused as different."""
    from lfgnss.solve import SAMPLE_TRUTH

    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "gt.txt").write_text(SAMPLE_TRUTH.read_text())
    text = sample_toml("same").read_text().replace(str(SAMPLE_TRUTH), "../data/gt.txt")
    for folder, description in (("a", ""), ("b", 'description = "my notes"\n')):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "same.toml").write_text(description + text)
        assert datasets.register_toml(tmp_path / folder / "same.toml").source == tmp_path / folder / "same.toml"


def test_the_split_axis_is_read_in_any_case(sample_toml):
    spec = datasets.register_toml(_edited(sample_toml, "axis-case", 'axis = "relative_s"', 'axis = "Relative_S"'))
    assert spec.split_axis == "relative_s"


def test_a_truth_origin_that_would_change_nothing_is_refused(sample_toml, tmp_path):
    """Defect: time_origin_gps_s under an urbannav truth with tow splits was accepted and ignored, so a user who put
    the UTC shift there saw the same 'are its times UTC?' warning."""
    path = _edited(sample_toml, "origin-urbannav", 'format = "smartloc"', 'format = "urbannav"')
    path.write_text(path.read_text().replace('axis = "relative_s"', 'axis = "tow"'))
    with pytest.raises(InputError, match=r"time_origin_gps_s in \[truth\] is the t = 0 of a smartloc truth and of "
                                         r"relative_s splits, and this dataset has neither \(format = 'urbannav', "
                                         r"axis = 'tow'\): it would change nothing; remove it"):
        datasets.register_toml(path)
    path.write_text(path.read_text().replace('axis = "tow"', 'axis = "relative_s"'))
    assert datasets.register_toml(path).time_origin_gps_s is not None       # the 0 of relative_s splits


def test_home_folder_paths_in_a_toml_are_expanded(sample_toml, tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    path = _edited(sample_toml, "home", f'file = "{SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt"}"', 'file = "~/gt.txt"')
    assert datasets.register_toml(path).truth == tmp_path / "gt.txt"


def test_the_docstrings_example_registers(tmp_path):
    """The README points to lfgnss/datasets.py's docstring for the full format: its example must be accepted as it is
    (session 50 refused a time_origin_gps_s that changes nothing, which the example then held)."""
    import textwrap

    doc = datasets.__doc__
    block = doc[doc.index('    id = "my-drive"'):doc.index("\n\n", doc.index('    id = "my-drive"'))]
    path = tmp_path / "doc-drive.toml"
    path.write_text(textwrap.dedent(block))
    spec = datasets.register_toml(path)
    assert spec.id == "my-drive" and spec.split_axis == "tow" and spec.splits["test"] == (47001, 47186)


@pytest.mark.parametrize("line, message", [
    ('time_offset_s = "18"', r"time_offset_s in \[truth\] must be a number of seconds added to the truth's times"),
    ("time_offset_s = nan", r"time_offset_s in \[truth\] must be a number of seconds"),
])
def test_a_time_offset_that_is_not_a_number_of_seconds_is_refused(sample_toml, line, message):
    path = _edited(sample_toml, "offset", 'format = "smartloc"', f'format = "smartloc"\n{line}')
    with pytest.raises(InputError, match=message):
        datasets.register_toml(path)


def test_a_time_offset_moves_the_truth_and_is_refused_where_it_moves_nothing(sample_toml, tmp_path):
    """time_offset_s (session 50) is what the UTC and local-time notes tell a user to set: added to the truth's times."""
    import numpy as np

    truth = tmp_path / "gt.csv"
    truth.write_text("1300000000.0,3783000.0,900000.0,5030000.0\n1300000001.0,3783001.0,900000.0,5030000.0\n")
    read = datasets.read_truth(truth, np.array([1300000018.0, 1300000018.5]), "ecef-csv", time_offset_s=18.0)
    np.testing.assert_allclose(read[:, 0], [3783000.0, 3783000.5])
    with pytest.raises(ValueError, match="DatasetSpec api: time_offset_s must be a finite number of seconds, got nan"):
        datasets.DatasetSpec("api", (), (), truth, "ecef-csv", time_offset_s=float("nan"))
    with pytest.raises(ValueError, match=r"DatasetSpec truth: match_tolerance_s must be a number of seconds > 0 .*got -1"):
        datasets.read_truth(truth, np.array([1300000000.0]), "ecef-csv", match_tolerance_s=-1)
    path = _edited(sample_toml, "static-offset", 'format = "smartloc"', 'format = "static"\ntime_offset_s = 18')
    with pytest.raises(InputError, match=r"time_offset_s in \[truth\] would change nothing for a static truth"):
        datasets.register_toml(path)


# ------------------------------------------------------------------ session 55: a user's own data (helper review)
@pytest.mark.parametrize("old, new, message", [
    ('id = "mine"', 'id = "../../escaped"', "id '../../escaped' must be a name of letters, digits, '.', '_' or '-'"),
    ('id = "mine"', 'id = ""', "id '' must be a name of letters"),
    ('id = "mine"', 'id = 3', "id 3 must be a name of letters"),
    ("obs = [", "obs = 3\nold_obs = [", "obs must be a file name or a list of file names, got 3"),
], ids=["path", "empty", "number", "obs-number"])
def test_an_id_or_file_list_of_the_wrong_kind_is_one_line_naming_the_key(sample_toml, clean_registry, old, new,
                                                                         message):
    """An id became part of a cache path (``../../escaped`` wrote outside the cache folder); ``obs = 3`` said only
    "'int' object is not iterable"."""
    path = _edited(sample_toml, "mine", old, new)
    if "old_obs" in new:
        path.write_text(path.read_text().replace("old_obs = [", "# ["))
    with pytest.raises(InputError, match=re.escape(f"{path}: {message}")):
        datasets.register_toml(path)


def test_a_folder_given_as_a_file_is_named_as_such(sample_toml, clean_registry, tmp_path):
    path = _edited(sample_toml, "mine", f'"{SAMPLE_DIR / "brdc1580.16g.gz"}"', f'"{tmp_path}"')
    datasets.register_toml(path)
    assert datasets.get("mine").missing_note() == f"{tmp_path} is a folder, not a file (nav in {path})"


def _truth_rows(tmp_path, keep_every: int = 1, repeat_shift_m: float | None = None):
    """The bundled drive's smartLoc truth, every ``keep_every``-th row, each row twice with ``repeat_shift_m``."""
    rows = (SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text().splitlines()[::keep_every]
    if repeat_shift_m is not None:
        twice = []
        for row in rows:
            f = row.split()
            twice += [row, " ".join(f[:2] + [f"{float(f[2]) + repeat_shift_m:.7f}"] + f[3:])]
        rows = twice
    path = tmp_path / f"truth-{keep_every}-{repeat_shift_m}.txt"
    path.write_text("\n".join(rows) + "\n")
    return path


def test_a_truth_slower_than_the_receiver_keeps_each_split_one_piece(sample_toml, clean_registry, tmp_path):
    """A truth of every fifth row (1 Hz against 5 Hz): the epochs between stay in the split's piece, solved and not
    scored, where each labelled epoch used to be a piece of its own (and training found no window)."""
    datasets.register_toml(sample_toml("sparse", truth=_truth_rows(tmp_path, keep_every=5)))
    pieces = datasets.load_split("sparse", "train")
    assert len(pieces) == 1 and len(pieces[0]) > 600 and 100 < int(pieces[0].labelled.sum()) < 200
    from learning.data import make_windows
    assert make_windows(pieces, length=100, stride=50)


def test_repeated_truth_times_are_dropped_or_refused(sample_toml, clean_registry, tmp_path):
    """A row given twice labels as once (as it did); two positions at one time are refused (the later one won)."""
    datasets.register_toml(sample_toml("twice", truth=_truth_rows(tmp_path, repeat_shift_m=0.0)))
    once = datasets.build("twice")
    assert int(once.labelled.sum()) == 1372
    datasets.register_toml(sample_toml("apart", truth=_truth_rows(tmp_path, repeat_shift_m=111.0)))
    with pytest.raises(InputError, match="row\\(s\\) repeat another row's time with another position .* 111.0 m "
                                         "apart\\): which one is the truth"):
        datasets.build("apart")


def test_a_truth_in_radians_is_named_so():
    """Latitude and longitude written in radians lie thousands of km off; the note says what they look like."""
    from lfgnss.frames import lla_to_ecef
    fix = lla_to_ecef(np.radians([52.5] * 3), np.radians([13.4] * 3), np.full(3, 40.0)).reshape(3, 3)
    radians = lla_to_ecef(np.radians([0.916] * 3), np.radians([0.234] * 3), np.full(3, 40.0)).reshape(3, 3)
    spec = datasets.DatasetSpec("rad", ["a.obs"], ["a.nav"], "t.csv", "urbannav")
    notes = datasets.truth_fit_notes(spec, np.arange(3.0), radians, fix)
    assert len(notes) == 1 and "look like radians, not degrees" in notes[0]
    ecef = datasets.truth_fit_notes(datasets.DatasetSpec("x", ["a.obs"], ["a.nav"], "t.csv", "ecef-csv"),
                                    np.arange(3.0), radians, fix)
    assert len(ecef) == 1 and "radians" not in ecef[0]          # an ECEF truth has no degrees to mistake
