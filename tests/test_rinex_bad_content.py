"""RINEX observation files with bad content: a satellite repeated in an epoch, unreadable C/N0 or Doppler,
observation-type counts that disagree with the list, an unknown time system, a version label that does not
fit the header, consecutive damaged epoch lines. Each gives one ``PATH:LINE: reason`` note (a warning) or a
one-line :class:`RinexError`, never a traceback and never a silent loss.
"""
import gzip
import warnings

import numpy as np
import pytest

from lfgnss.errors import RinexError
from lfgnss.rinex import RinexWarning, load_obs
from lfgnss.solve import SAMPLE_OBS

# The bundled RINEX 2.11 sample: header lines 1-12 (types on line 9: C1 L1 S1 D1, TIME OF FIRST OBS on 10),
# first epoch line 13 (G12 R20 R02 ...), its satellite-id continuation line 14, its records from line 15.
TYPES_LINE, TIME_LINE, FIRST_EPOCH_LINE, FIRST_RECORD_LINE = 9, 10, 13, 15


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))


@pytest.fixture(scope="module")
def clean():
    return load_obs(SAMPLE_OBS, cache=False)


def _sample_lines() -> list[str]:
    return gzip.decompress(SAMPLE_OBS.read_bytes()).decode().split("\n")


def _write(path, lines):
    path.write_text("\n".join(lines))
    return path


def _load_warned(path, match=None):
    """load_obs with exactly one RinexWarning, which names the file; returns the observations."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        obs = load_obs(path, cache=False)
    assert [w.category for w in caught] == [RinexWarning], [str(w.message) for w in caught]
    message = str(caught[0].message)
    assert message.startswith(f"{path}: ") and "\n" not in message
    if match:
        assert match in message
    return obs


def _set_field(line: str, index: int, text: str) -> str:
    """A RINEX 2 record line with its field ``index`` (0-based, 16 columns each) replaced by ``text``."""
    line = line.ljust(16 * (index + 1))
    return line[:16 * index] + f"{text:>14s}" + line[16 * index + 14:]


def _rinex3(path, epochs: list[list[tuple[str, float, float]]], time_system: str = "GPS",
            g_types: str = "C1C L1C D1C S1C", declared: int | None = None):
    """A small RINEX 3.03 GPS file; each epoch a list of (satellite, pseudorange, C/N0) records."""
    n = len(g_types.split()) if declared is None else declared
    head = ["     3.03           OBSERVATION DATA    G: GPS              RINEX VERSION / TYPE",
            f"G  {n:3d} {g_types}".ljust(60) + "SYS / # / OBS TYPES",
            f"  2020     6     3     3     2    9.0000000     {time_system:<3s}".ljust(60) + "TIME OF FIRST OBS",
            " " * 60 + "END OF HEADER"]
    body = []
    for e, records in enumerate(epochs):
        body.append(f"> 2020 06 03 03 02{9.0 + e:11.7f}  0{len(records):3d}")
        for sv, pr, cn0 in records:
            body.append(f"{sv}{pr:14.3f}  {pr * 5.25:14.3f}  {-1000.0:14.3f}  {cn0:14.3f}")
    return _write(path, head + body + [""])


SATS = [("G01", 2.1e7, 41.0), ("G02", 2.2e7, 42.0), ("G03", 2.3e7, 43.0), ("G04", 2.4e7, 44.0)]


# ------------------------------------------------------------------ a satellite listed twice in one epoch
def test_repeat_with_the_same_pseudorange_keeps_the_first_record(tmp_path):
    """RINEX 3: G02 twice in epoch 2, same pseudorange, other C/N0: the first record's C/N0 is kept."""
    epochs = [SATS, SATS[:2] + [("G02", 2.2e7, 30.0)] + SATS[2:], SATS]
    path = _rinex3(tmp_path / "dup.rnx", epochs)
    obs = _load_warned(path, match="listed twice")
    repeat_line = 4 + 1 + len(SATS) + 1 + 3          # header, epoch 1, epoch line 2, G01 G02, the repeat
    assert obs.warnings == (f"{path}:{repeat_line}: satellite G02 listed twice in one epoch; the repeat is ignored",)
    g02 = list(obs.sv).index("G02")
    assert len(obs) == 3 and list(obs.sv) == ["G01", "G02", "G03", "G04"]
    assert obs.pr_m[1, g02] == 2.2e7
    assert obs.cn0_dbhz[1, g02] == 42.0                # the first record's, not the repeat's 30
    assert np.all(np.isfinite(obs.pr_m))


def test_repeat_with_another_pseudorange_skips_both_records(tmp_path):
    """RINEX 3: the repeat 5 km off (the fuzzing case that gave 1 km errors): neither record is trusted."""
    epochs = [SATS, SATS[:2] + [("G02", 2.2e7 + 5000.0, 42.0)] + SATS[2:], SATS]
    path = _rinex3(tmp_path / "dup.rnx", epochs)
    obs = _load_warned(path, match="listed twice")
    repeat_line, first_line = 4 + 1 + len(SATS) + 1 + 3, 4 + 1 + len(SATS) + 1 + 2
    assert obs.warnings == (f"{path}:{repeat_line}: satellite G02 listed twice in one epoch with different "
                            f"pseudoranges (22000000.000 m on line {first_line}, 22005000.000 m here): both "
                            f"records skipped",)
    g02 = list(obs.sv).index("G02")
    assert np.isnan(obs.pr_m[1, g02]) and np.isnan(obs.cn0_dbhz[1, g02])
    assert obs.pr_m[0, g02] == obs.pr_m[2, g02] == 2.2e7                 # the other epochs keep G02
    assert np.isfinite(obs.pr_m[1, [0, 2, 3]]).all()                     # and epoch 2 the other satellites


def test_many_repeats_give_one_note_with_a_count(tmp_path):
    epochs = [SATS + [SATS[0]]] * 5
    path = _rinex3(tmp_path / "dup.rnx", epochs)
    obs = _load_warned(path)
    assert obs.warnings == (f"{path}:{4 + 1 + len(SATS) + 1}: satellite G01 listed twice in one epoch; the repeat "
                            f"is ignored (5 such repeated records in the file, first here)",)
    assert len(obs) == 5 and np.all(obs.pr_m[:, 0] == 2.1e7)


def test_only_repeats_of_a_satellite_are_not_an_empty_column(tmp_path):
    """A satellite seen only in disagreeing repeats leaves no all-missing column behind."""
    epochs = [SATS, SATS + [("G05", 2.5e7, 45.0), ("G05", 2.6e7, 45.0)]]
    obs = _load_warned(_rinex3(tmp_path / "dup.rnx", epochs), match="both records skipped")
    assert list(obs.sv) == ["G01", "G02", "G03", "G04"]


def test_rinex2_satellite_id_repeated_in_the_epoch_line(tmp_path, clean):
    """RINEX 2: the first epoch line names G12 where R20 was: the records cannot both be G12's."""
    lines = _sample_lines()
    assert lines[FIRST_EPOCH_LINE - 1][32:38] == "G12R20"
    lines[FIRST_EPOCH_LINE - 1] = lines[FIRST_EPOCH_LINE - 1].replace("G12R20", "G12G12", 1)
    path = _write(tmp_path / "dup.obs", lines)
    obs = _load_warned(path, match="listed twice")
    assert obs.warnings[0].startswith(f"{path}:{FIRST_RECORD_LINE + 1}: satellite G12 listed twice in one epoch "
                                      f"with different pseudoranges")
    assert len(obs.warnings) == 1
    g12, r20 = list(obs.sv).index("G12"), list(obs.sv).index("R20")
    assert np.isnan(obs.pr_m[0, g12]) and np.isnan(obs.pr_m[0, r20])
    np.testing.assert_array_equal(obs.pr_m[1:], clean.pr_m[1:])
    finite = np.isfinite(obs.pr_m[0])
    np.testing.assert_array_equal(obs.pr_m[0, finite], clean.pr_m[0, finite])


# ------------------------------------------------------------------ unreadable C/N0 and Doppler
def test_garbage_cn0_and_doppler_are_counted_and_named(tmp_path, clean):
    lines = _sample_lines()
    records = [FIRST_RECORD_LINE, FIRST_RECORD_LINE + 1, FIRST_RECORD_LINE + 2]    # G12, R20, R02
    lines[records[0] - 1] = _set_field(lines[records[0] - 1], 2, "garbage!!")     # S1
    lines[records[1] - 1] = _set_field(lines[records[1] - 1], 3, "??junk??")      # D1
    lines[records[2] - 1] = _set_field(_set_field(lines[records[2] - 1], 2, "nan"), 3, "1.2.3")
    path = _write(tmp_path / "cn0.obs", lines)
    obs = _load_warned(path, match="unreadable C/N0 or Doppler")
    assert obs.warnings == (f"{path}:{FIRST_RECORD_LINE}: 4 unreadable C/N0 or Doppler values (D1/S1; first here) "
                            f"read as missing",)
    np.testing.assert_array_equal(obs.pr_m, clean.pr_m)                          # pseudoranges untouched
    g12, r20, r02 = (list(obs.sv).index(s) for s in ("G12", "R20", "R02"))
    assert np.isnan(obs.cn0_dbhz[0, g12]) and obs.doppler_hz[0, g12] == clean.doppler_hz[0, g12]
    assert np.isnan(obs.doppler_hz[0, r20]) and obs.cn0_dbhz[0, r20] == clean.cn0_dbhz[0, r20]
    assert np.isnan(obs.cn0_dbhz[0, r02]) and np.isnan(obs.doppler_hz[0, r02])


def test_nul_bytes_in_a_doppler_field(tmp_path):
    lines = _sample_lines()
    no = FIRST_RECORD_LINE + 5                          # the sixth record of the first epoch
    lines[no - 1] = _set_field(lines[no - 1], 3, "\0" * 14)
    path = _write(tmp_path / "nul.obs", lines)
    obs = _load_warned(path)
    assert obs.warnings == (f"{path}:{no}: 1 unreadable C/N0 or Doppler value (D1; first here) read as missing",)


def test_cached_result_repeats_the_note(tmp_path):
    lines = _sample_lines()
    lines[FIRST_RECORD_LINE - 1] = _set_field(lines[FIRST_RECORD_LINE - 1], 2, "xx")
    path = _write(tmp_path / "cn0.obs", lines)
    for _ in range(2):  # the second read comes from the cache
        with pytest.warns(RinexWarning, match=f"{path}:{FIRST_RECORD_LINE}: 1 unreadable C/N0"):
            load_obs(path)


# ------------------------------------------------------------------ header problems
def _error(path) -> str:
    with pytest.raises(RinexError) as info:
        load_obs(path, cache=False)
    message = str(info.value)
    assert "\n" not in message and "Error:" not in message and "Error(" not in message
    return message


def test_rinex2_type_count_disagrees_with_the_list(tmp_path):
    lines = _sample_lines()
    assert lines[TYPES_LINE - 1].startswith("     4    C1")
    lines[TYPES_LINE - 1] = "     9" + lines[TYPES_LINE - 1][6:]
    path = _write(tmp_path / "types.obs", lines)
    assert _error(path) == (f"{path}:{TYPES_LINE}: '# / TYPES OF OBSERV' header declares 9 observation types but "
                            f"lists 4 (C1 L1 S1 D1)")


def test_rinex2_type_list_with_continuation_line_is_read(tmp_path, clean):
    """The four types over two lines (the second with a blank count) agree with the count: read as before."""
    lines = _sample_lines()
    lines[TYPES_LINE - 1] = "     4    C1    L1".ljust(60) + "# / TYPES OF OBSERV"
    lines.insert(TYPES_LINE, "          S1    D1".ljust(60) + "# / TYPES OF OBSERV")
    obs = load_obs(_write(tmp_path / "types.obs", lines), cache=False)
    assert not obs.warnings
    np.testing.assert_array_equal(obs.pr_m, clean.pr_m)
    np.testing.assert_array_equal(obs.cn0_dbhz, clean.cn0_dbhz)


def test_rinex3_type_count_disagrees_with_the_list(tmp_path):
    path = _rinex3(tmp_path / "types.rnx", [SATS], declared=12)
    assert _error(path) == (f"{path}:2: 'SYS / # / OBS TYPES' header for G declares 12 observation types but "
                            f"lists 4 (C1C L1C D1C S1C)")


def test_rinex3_type_list_over_two_lines_is_read(tmp_path):
    """Fourteen types over two lines (RINEX 3: 13 a line) agree with the count: no error, no note."""
    path = _rinex3(tmp_path / "types.rnx", [SATS], declared=14)
    lines = path.read_text().split("\n")
    lines[1] = "G   14 C1C L1C D1C S1C C1W L1W D1W S1W C2W L2W D2W S2W C5Q".ljust(60) + "SYS / # / OBS TYPES"
    lines.insert(2, "       L5Q".ljust(60) + "SYS / # / OBS TYPES")
    _write(path, lines)
    obs = load_obs(path, cache=False)
    assert not obs.warnings and obs.pr_m[0, 0] == 2.1e7


def test_unknown_time_system_is_noted(tmp_path):
    path = _rinex3(tmp_path / "ts.rnx", [SATS, SATS], time_system="XYZ")
    gps = load_obs(_rinex3(tmp_path / "gps.rnx", [SATS, SATS]), cache=False)
    obs = _load_warned(path, match="unknown time system")
    assert obs.warnings == (f"{path}:3: unknown time system 'XYZ' in 'TIME OF FIRST OBS' (expected "
                            f"GPS/GLO/GAL/QZS/BDT/IRN): epoch times read as GPS time",)
    np.testing.assert_array_equal(obs.time_gps_s, gps.time_gps_s)


def test_rinex2_unknown_time_system_is_noted(tmp_path, clean):
    lines = _sample_lines()
    lines[TIME_LINE - 1] = lines[TIME_LINE - 1][:48] + "XYZ" + lines[TIME_LINE - 1][51:]
    path = _write(tmp_path / "ts.obs", lines)
    obs = _load_warned(path)
    assert obs.warnings[0].startswith(f"{path}:{TIME_LINE}: unknown time system 'XYZ'")
    np.testing.assert_array_equal(obs.time_gps_s, clean.time_gps_s)


def test_rinex2_body_under_a_rinex3_version_line(tmp_path):
    lines = _sample_lines()
    lines[0] = "     3.02" + lines[0][9:]
    path = _write(tmp_path / "ver.obs", lines)
    assert _error(path) == (f"{path}:{TYPES_LINE}: observation types given as '# / TYPES OF OBSERV' (RINEX 2), but "
                            f"line 1 says RINEX 3.02: version and header disagree")


# ------------------------------------------------------------------ consecutive damaged epoch lines
def _epoch_line_indices(lines):
    return [k for k, ln in enumerate(lines) if ln.startswith(" 16  6  6 ")]


def test_two_damaged_epoch_lines_in_a_row_each_get_a_note(tmp_path, clean):
    """Epoch 10 with month 13 and epoch 11 with seconds 75 run into the minutes: two notes, two epochs lost."""
    lines = _sample_lines()
    e10, e11 = _epoch_line_indices(lines)[9:11]
    lines[e10] = lines[e10][:3] + " 13" + lines[e10][6:]
    lines[e11] = lines[e11][:15] + "75.0000000" + lines[e11][25:]    # no blank between minutes and seconds
    path = _write(tmp_path / "dates.obs", lines)
    obs = _load_warned(path, match="unreadable epoch line")
    assert obs.warnings == (f"{path}:{e10 + 1}: unreadable epoch line, skipped up to the next epoch",
                            f"{path}:{e11 + 1}: unreadable epoch line, skipped up to the next epoch")
    assert len(obs) == len(clean) - 2
    np.testing.assert_array_equal(obs.time_gps_s, np.delete(clean.time_gps_s, [9, 10]))


def test_truncated_epoch_followed_by_a_damaged_epoch_line(tmp_path, clean):
    """An epoch missing its last record line, then a damaged epoch line: the damaged line is not read as
    a record; both are reported and only those two epochs are lost."""
    lines = _sample_lines()
    e5, e6 = _epoch_line_indices(lines)[4:6]
    lines[e6] = lines[e6][:15] + "75.0000000" + lines[e6][25:]
    del lines[e6 - 1]                                     # the last record line of epoch 5
    path = _write(tmp_path / "trunc.obs", lines)
    obs = _load_warned(path)
    assert obs.warnings[0].startswith(f"{path}:{e5 + 1}: epoch truncated")
    assert obs.warnings[1] == f"{path}:{e6}: unreadable epoch line, skipped up to the next epoch"
    assert len(obs.warnings) == 2
    np.testing.assert_array_equal(obs.time_gps_s, np.delete(clean.time_gps_s, [4, 5]))
    np.testing.assert_array_equal(obs.pr_m, np.delete(clean.pr_m, [4, 5], axis=0))


# ------------------------------------------------------------------ a file with no pseudorange at all
def test_all_blank_records_say_no_pseudorange_not_a_constellation_choice(tmp_path):
    """Satellite ids with blank fields: the error says there are no pseudoranges, not that none of the (never
    requested) constellations GCERJ were found."""
    from lfgnss.measurements import load
    from lfgnss.solve import SAMPLE_NAV

    path = _rinex3(tmp_path / "blank.rnx", [SATS, SATS])
    path.write_text("\n".join(line[:3] if line.startswith("G0") else line for line in path.read_text().split("\n")))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(RinexError, match=f"^{path}: no pseudorange observations of any constellation$"):
            load(path, SAMPLE_NAV, cache=False)
