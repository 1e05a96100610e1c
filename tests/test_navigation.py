"""lfgnss.navigation: RINEX 2/3 navigation files -> Navigation records."""
from __future__ import annotations

import gzip
import shutil
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from lfgnss.ephemeris import ephemeris_states
from lfgnss.errors import RinexError
from lfgnss.navigation import Navigation, load_nav
from lfgnss.paths import bundled_data_dir
from lfgnss.rinex import RinexWarning
from lfgnss.time import week_tow_to_gps_s

# One GPS and one GLONASS record of the IGS/CDDIS daily broadcast files brdc1580.16n / brdc1580.16g
# (2016-06-06), with their original headers. test_ephemeris.py checks them against RTKLIB.
GPS_RINEX2 = """\
     2              NAVIGATION DATA                         RINEX VERSION / TYPE
CCRINEXN V1.6.0 UX  CDDIS               07-JUN-16 17:31     PGM / RUN BY / DATE
IGS BROADCAST EPHEMERIS FILE                                COMMENT
    0.6519D-08  0.2235D-07 -0.5960D-07 -0.1192D-06          ION ALPHA
    0.8602D+05  0.9830D+05 -0.6554D+05 -0.5243D+06          ION BETA
    0.279396772385D-08 0.799360577730D-14   233472     1900 DELTA-UTC: A0,A1,T,W
    17                                                      LEAP SECONDS
                                                            END OF HEADER
 2 16  6  6 12  0  0.0 0.587235670537D-03-0.250111042988D-11 0.000000000000D+00
    0.320000000000D+02-0.206562500000D+02 0.442732727309D-08 0.274373320590D+01
   -0.103563070297D-05 0.157487246906D-01 0.120606273413D-04 0.515357678223D+04
    0.129600000000D+06 0.670552253723D-07-0.245475939600D+01-0.124797224999D-06
    0.943347811891D+00 0.133312500000D+03-0.211149389761D+01-0.761138847345D-08
    0.720387149874D-09 0.000000000000D+00 0.190000000000D+04 0.000000000000D+00
    0.200000000000D+01 0.000000000000D+00-0.200234353542D-07 0.320000000000D+02
    0.122400000000D+06 0.400000000000D+01 0.000000000000D+00 0.000000000000D+00
"""
GLONASS_RINEX2 = """\
     2.01           GLONASS NAV DATA                        RINEX VERSION / TYPE
CCRINEXG V1.4 UX    CDDIS               07-JUN-16 17:37     PGM / RUN BY / DATE
IGS BROADCAST EPHEMERIS FILE                                COMMENT
teqc  2013Mar15     GPS Operator        20160607  0:11:     COMMENT
  2016     6     6    0.232830643654D-08                    CORR TO SYSTEM TIME
    17                                                      LEAP SECONDS
                                                            END OF HEADER
 1 16  6  6 11 15  0.0-0.142797827721D-03 0.000000000000D+00 0.396000000000D+05
    0.973446533203D+04 0.109146881103D+01 0.000000000000D+00 0.000000000000D+00
   -0.198351259766D+05-0.136699771881D+01 0.279396772385D-08 0.100000000000D+01
    0.127667167969D+05-0.295661067963D+01-0.931322574616D-09 0.000000000000D+00
"""


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))


@pytest.fixture
def bundled(tmp_path) -> tuple[Path, Path]:
    n = tmp_path / "brdc1580.16n"
    g = tmp_path / "brdc1580.16g"
    n.write_text(GPS_RINEX2)
    g.write_text(GLONASS_RINEX2)
    return n, g


# ---------------------------------------------------------------- small bundled records (no shared data)
def test_rinex2_gps_record_fields(bundled):
    nav = load_nav(bundled[0])
    k = nav.kepler
    assert isinstance(nav, Navigation) and len(k) == 1 and len(nav.glonass) == 0
    assert k.sv[0] == "G02" and k.system[0] == "G"
    assert k.toe_gps_s[0] == week_tow_to_gps_s(1900, 129600.0)       # Monday 12:00 GPST
    assert k.toc_gps_s[0] == k.toe_gps_s[0]
    assert k.ttr_gps_s[0] == week_tow_to_gps_s(1900, 122400.0)
    assert k.sqrt_a_sqrt_m[0] == pytest.approx(5153.57678223)
    assert k.e[0] == pytest.approx(0.0157487246906)
    assert k.af0_s[0] == pytest.approx(0.587235670537e-3)
    assert k.tgd_s[0] == pytest.approx(-0.200234353542e-7)
    assert k.iode[0] == 32 and k.health[0] == 0
    np.testing.assert_allclose(nav.iono["GPS"], [0.6519e-8, 0.2235e-7, -0.5960e-7, -0.1192e-6,
                                                 0.8602e5, 0.9830e5, -0.6554e5, -0.5243e6])
    assert nav.sources == (str(bundled[0]),)


def test_rinex2_glonass_record_fields(bundled):
    g = load_nav(bundled[1]).glonass
    assert len(g) == 1 and g.sv[0] == "R01"
    assert g.toe_gps_s[0] == week_tow_to_gps_s(1900, 86400 + 11 * 3600 + 15 * 60 + 17)  # UTC + 17 s
    np.testing.assert_allclose(g.pos_ecef_m[0], [9734465.33203, -19835125.9766, 12766716.7969])
    np.testing.assert_allclose(g.vel_ecef_m_s[0], [1091.46881103, -1366.99771881, -2956.61067963])
    np.testing.assert_allclose(g.acc_ecef_m_s2[0], [0.0, 0.279396772385e-5, -0.931322574616e-6])
    assert g.tau_n_s[0] == pytest.approx(0.142797827721e-3)   # RINEX stores -tau_n
    assert g.gamma_n[0] == 0.0 and g.k[0] == 1 and g.health[0] == 0


def test_several_files_and_duplicates(bundled):
    n, g = bundled
    nav = load_nav([n, g, n])
    assert len(nav.kepler) == 1 and len(nav.glonass) == 1      # the repeated file adds nothing
    assert nav.sources == (str(n), str(g), str(n))


def test_gzip_copy_reads_the_same(bundled, tmp_path):
    gz = tmp_path / "brdc1580.16n.gz"
    with open(bundled[0], "rb") as src, gzip.open(gz, "wb") as dst:
        shutil.copyfileobj(src, dst)
    a, b = load_nav(bundled[0]).kepler, load_nav(gz).kepler
    for name in ("sv", "toe_gps_s", "sqrt_a_sqrt_m", "m0_rad", "af0_s", "tgd_s"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_rinex2_same_epoch_twice_keeps_both(tmp_path):
    """georinex drops a RINEX 2 satellite with two records at one epoch; load_nav keeps both."""
    head, rec = GPS_RINEX2.split("END OF HEADER\n")
    other = rec.replace("0.320000000000D+02-0.2065", "0.330000000000D+02-0.2065")   # IODE 32 -> 33
    path = tmp_path / "dup.16n"
    path.write_text(head + "END OF HEADER\n" + rec + other)
    k = load_nav(path).kepler
    assert sorted(k.iode.tolist()) == [32, 33]


def test_interior_blank_field_read_as_zero(tmp_path):
    """A blank field inside a record (RTKLIB reads 0) must not turn the record into NaN (georinex 1.16)."""
    head, rec = GPS_RINEX2.split("END OF HEADER\n")
    lines = rec.splitlines()
    lines[5] = lines[5][:22] + " " * 19 + lines[5][41:]          # "codes on L2" field blank
    path = tmp_path / "blank.16n"
    path.write_text(head + "END OF HEADER\n" + "\n".join(lines) + "\n")
    k = load_nav(path).kepler
    assert len(k) == 1 and k.sqrt_a_sqrt_m[0] == pytest.approx(5153.57678223)


def test_short_lines_are_padded(tmp_path):
    """Lines whose trailing blanks were stripped must not shift the following fields."""
    head, rec = GPS_RINEX2.split("END OF HEADER\n")
    lines = [ln.rstrip() for ln in rec.splitlines()]
    lines[6] = lines[6][:41]                                     # drop the last two fields of a line
    path = tmp_path / "short.16n"
    path.write_text(head + "END OF HEADER\n" + "\n".join(lines) + "\n")
    k = load_nav(path).kepler
    assert len(k) == 1 and k.ttr_gps_s[0] == week_tow_to_gps_s(1900, 122400.0)


# ---------------------------------------------------------------- errors
@pytest.mark.parametrize("content, words", [
    ("", "empty file"),
    ("hello world\nthis is not RINEX\n", "not"),
    ("     3.02           N: GNSS NAV DATA    G: GPS              RINEX VERSION / TYPE\n"
     "                                                            END OF HEADER\n", "no ephemeris"),
    ("     3.02           OBSERVATION DATA    M: Mixed            RINEX VERSION / TYPE\n"
     "                                                            END OF HEADER\n", "not a RINEX 2/3 navigation"),
], ids=["empty", "garbage", "header-only", "obs-file"])
def test_bad_file_raises_one_line_rinex_error(tmp_path, content, words):
    path = tmp_path / "bad.19n"
    path.write_text(content)
    with pytest.raises(RinexError) as info:
        load_nav(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "\n" not in msg and words in msg


def test_missing_file_raises(tmp_path, bundled):
    with pytest.raises(RinexError, match="file not found"):
        load_nav([bundled[0], tmp_path / "nope.16n"])


# ---------------------------------------------------------------- shared data
HK2019 = "urbannav-hk-tst-20190428"
BERLIN = "smartloc-berlin-potsdamer-platz-rinex"
STATIC = "hk-tst-static-20200603"


def _records_in(path: Path) -> int:
    """Records in a RINEX nav file (epoch lines), counted independently of load_nav."""
    lines = path.read_text().splitlines()
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln)
    if lines[0][5:6] == "3":
        return sum(1 for ln in lines[end + 1:] if ln[:1] in "GRECJ" and ln[1:3].strip().isdigit())
    return sum(1 for ln in lines[end + 1:] if ln[:2].strip().isdigit() and ln[3:5].strip().isdigit())


@pytest.mark.shared_data
@pytest.mark.parametrize("rel, systems", [
    (f"{HK2019}/hksc1180.19n", {"G"}),
    (f"{HK2019}/hksc1180.19b", {"C"}),
    (f"{BERLIN}/brdc1580.16n", {"G"}),
    (f"{BERLIN}/brdc1580.16g", {"R"}),
    (f"{STATIC}/hksc155c.20n", {"G"}),
    (f"{STATIC}/hksc155d.20g", {"R"}),
    (f"{STATIC}/hksc155c.20b", {"C"}),
], ids=lambda v: v if isinstance(v, str) else "")
def test_every_record_survives(shared_data, rel, systems):
    """No record is lost to georinex (blank BeiDou spare fields, RINEX 2 duplicate epochs); brdc1580.16g's six
    copies stamped 12:15:17 are its 12:15:00 records (GLONASS epochs on the 15 min grid, as RTKLIB takes them)."""
    path = shared_data(rel)
    nav = load_nav(path)
    assert set(nav.kepler.system) | ({"R"} if len(nav.glonass) else set()) == systems
    assert len(nav.kepler) + len(nav.glonass) == _records_in(path) - (6 if rel.endswith("brdc1580.16g") else 0)
    assert np.all(np.isfinite(nav.kepler.sqrt_a_sqrt_m)) and np.all(np.isfinite(nav.kepler.toe_gps_s))


@pytest.mark.shared_data
def test_bds_times_are_shifted_from_bdt(shared_data):
    """C01 2019 04 27 23 00 00 (BDT), toe 601200 s of BDT week 694 -> GPST + 14 s."""
    k = load_nav(shared_data(f"{HK2019}/hksc1180.19b")).kepler
    i = np.flatnonzero(k.sv == "C01")[0]
    toc_bdt = (np.datetime64("2019-04-27T23:00:00") - np.datetime64("1980-01-06T00:00:00")) / np.timedelta64(1, "s")
    assert k.toc_gps_s[i] == toc_bdt + 14.0
    assert k.toe_gps_s[i] == week_tow_to_gps_s(694 + 1356, 601200.0) + 14.0   # BDT week 0 = GPS week 1356
    assert k.tgd_s[i] == pytest.approx(1.420000028673e-8)                      # TGD1 (B1I)


@pytest.mark.shared_data
def test_galileo_inav_preferred(shared_data):
    """hksc155c.20l carries I/NAV (data source 517) and F/NAV (258) records; only I/NAV is kept,
    with BGD(E1, E5b) as its group delay."""
    path = shared_data(f"{STATIC}/hksc155c.20l")
    k = load_nav(path).kepler
    text = path.read_text().splitlines()

    def field(i, line, col):  # RINEX 3 field `col` (0-3) of continuation line `line` of the record at i
        return float(text[i + line][4 + 19 * col: 23 + 19 * col].replace("D", "E"))

    starts = [i for i, ln in enumerate(text) if ln[:1] == "E" and ln[1:3].isdigit()]
    inav = [i for i in starts if int(field(i, 5, 1)) & 0b101]
    assert {int(field(i, 5, 1)) for i in starts} == {258, 517}
    assert set(k.system) == {"E"} and len(k) == len({text[i][:23] for i in inav})
    i = next(i for i in inav if text[i].startswith("E02 2020 06 03 02 10 00"))
    j = np.flatnonzero((k.sv == "E02") & (k.toe_gps_s == week_tow_to_gps_s(2108, 267000.0)))
    assert len(j) == 1 and k.tgd_s[j[0]] == field(i, 6, 3)       # BGD E5b/E1 (E5a/E1 is field 2)
    assert k.af0_s[j[0]] == float(text[i][23:42].replace("D", "E"))


@pytest.mark.shared_data
def test_mixed_rinex3_and_iono(shared_data):
    mixed = load_nav(shared_data(f"{BERLIN}/BRDC00WRD_U_20161580000_01D_MN.rnx"))
    assert set(mixed.kepler.system) == {"G", "E", "C"} and len(mixed.glonass) > 0
    assert mixed.iono == {}
    hk = load_nav([shared_data(f"{HK2019}/hksc1180.19n"), shared_data(f"{HK2019}/hksc1180.19b")])
    np.testing.assert_allclose(hk.iono["GPS"][:4], [9.3132e-09, 1.4901e-08, -5.9605e-08, -1.1921e-07])
    np.testing.assert_allclose(hk.iono["BDS"][4:], [1.2493e05, -6.8813e05, 6.8813e06, -7.4056e06])


# ---------------------------------------------------------------- damaged records: skipped with a warning
SAMPLE = bundled_data_dir() / "berlin-potsdamer-platz"


def _record_starts(lines: list[bytes]) -> list[int]:
    """Indices of the epoch lines of a RINEX 2/3 nav file's records, found independently of load_nav."""
    end = next(i for i, ln in enumerate(lines) if b"END OF HEADER" in ln)
    if lines[0][5:6] == b"3":
        return [i for i in range(end + 1, len(lines)) if lines[i][:1] in b"GRECJ" and lines[i][1:3].strip().isdigit()]
    return [i for i in range(end + 1, len(lines)) if lines[i][:2].strip().isdigit() and lines[i][3:5].strip().isdigit()]


def _damaged_copy(src: Path, dst: Path, damage: list[tuple[int, int, int, bytes]]) -> list[tuple[int, str]]:
    """Write ``src`` (plain or gzip) to ``dst`` (gzip if it ends in .gz) with ``new`` bytes at column ``col``
    of line ``line`` of record ``record`` for each (record, line, col, new); returns (1-based line, sv)."""
    raw = src.read_bytes()
    lines = (gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw).split(b"\n")
    starts = _record_starts(lines)
    letter = "" if lines[0][5:6] == b"3" else {b"N": "G", b"G": "R"}[lines[0][20:21]]
    out = []
    for record, line, col, new in damage:
        head = lines[starts[record]]
        out.append((starts[record] + line + 1, f"{letter}{int(head[:2]):02d}" if letter else head[:3].decode()))
        i = starts[record] + line
        lines[i] = lines[i][:col] + new + lines[i][col + len(new):]
    data = b"\n".join(lines)
    dst.write_bytes(gzip.compress(data) if dst.suffix == ".gz" else data)
    return out


def _assert_one_record_less(clean: Navigation, damaged: Navigation, sv: str) -> None:
    """``damaged`` holds exactly the records of ``clean`` but one record of ``sv``, with identical values."""
    part = "glonass" if sv[0] == "R" else "kepler"
    for name in ("kepler", "glonass"):
        a, b = getattr(clean, name), getattr(damaged, name)
        cols = [f.name for f in fields(a)]
        if name != part:
            for c in cols:
                np.testing.assert_array_equal(getattr(a, c), getattr(b, c))
            continue
        assert len(b) == len(a) - 1

        def same(k: int) -> bool:
            return all(np.array_equal(getattr(a, c)[k], getattr(b, c)[k], equal_nan=getattr(a, c).dtype.kind == "f")
                       for c in cols)

        i = next((k for k in range(len(b)) if not same(k)), len(b))
        assert a.sv[i] == sv
        for c in cols:
            np.testing.assert_array_equal(np.delete(getattr(a, c), i, axis=0), getattr(b, c))


def _assert_states_unchanged(clean: Navigation, damaged: Navigation, sv_bad: str) -> None:
    """Satellite states of every other satellite are the same; the damaged one still has states."""
    svs = np.unique(np.concatenate([clean.kepler.sv, clean.glonass.sv]))
    toe = np.concatenate([clean.kepler.toe_gps_s, clean.glonass.toe_gps_s])
    times = np.arange(toe.min(), toe.max(), 600.0)
    sv, t = np.repeat(svs, times.size), np.tile(times, svs.size)
    a, b = ephemeris_states(clean, sv, t), ephemeris_states(damaged, sv, t)
    other = sv != sv_bad
    assert a.ok[other].sum() > 100
    for name in ("pos_ecef_m", "vel_ecef_m_s", "clock_s", "group_delay_s", "toe_gps_s", "ok"):
        np.testing.assert_array_equal(getattr(a, name)[other], getattr(b, name)[other])
    assert np.isfinite(b.pos_ecef_m[~other]).any()              # from its other records


@pytest.mark.parametrize("name, damage, reason, out", [
    ("brdc1580.16n.gz", (3, 2, 10, b"##garbage##"), "unreadable value", "gps.16n"),
    ("brdc1580.16n.gz", (40, 5, 30, b"\xff\xe9\xb0"), "non-ASCII bytes", "gps_bytes.16n"),
    ("brdc1580.16n.gz", (40, 5, 30, b"\xff\xe9\xb0"), "non-ASCII bytes", "gps_bytes.16n.gz"),
    ("brdc1580.16n.gz", (7, 3, 23, b"nan"), "unreadable value", "gps_nan.16n"),
    ("brdc1580.16n.gz", (9, 0, 6, b"13"), "unreadable satellite number or epoch", "gps_month.16n"),
    ("brdc1580.16g.gz", (10, 1, 8, b"x"), "unreadable value", "glo.16g"),
    ("brdc1580.16g.gz", (25, 3, 50, b"\xe9"), "non-ASCII bytes", "glo_bytes.16g.gz"),
], ids=["gps-text", "gps-non-ascii", "gps-non-ascii-gz", "gps-nan", "gps-bad-month", "glo-text", "glo-non-ascii-gz"])
def test_damaged_record_is_skipped_with_a_warning(tmp_path, name, damage, reason, out):
    """One damaged value costs that record only: a warning naming file and line, the rest identical."""
    src, path = SAMPLE / name, tmp_path / out
    [(line, sv)] = _damaged_copy(src, path, [damage])
    with pytest.warns(RinexWarning, match=rf"{path}: 1 problem.*first: {path}:{line}: {reason}"):
        nav = load_nav(path)
    assert len(nav.warnings) == 1 and nav.warnings[0].startswith(f"{path}:{line}: {reason}"), nav.warnings
    assert "\n" not in nav.warnings[0] and f"; {sv} record of line" in nav.warnings[0]
    clean = load_nav(src)
    _assert_one_record_less(clean, nav, sv)
    _assert_states_unchanged(clean, nav, sv)


def test_damaged_records_are_cached_and_warned_again_under_the_new_name(tmp_path):
    first, second = tmp_path / "first.16n", tmp_path / "second.16n"
    [(line, _), (line2, _)] = _damaged_copy(SAMPLE / "brdc1580.16n.gz", first,
                                            [(3, 2, 10, b"##garbage##"), (60, 7, 5, b"?")])
    shutil.copy(first, second)
    with pytest.warns(RinexWarning, match=r"first\.16n: 2 problem"):
        a = load_nav(first)
    with pytest.warns(RinexWarning, match=r"second\.16n: 2 problem"):
        b = load_nav(second)
    assert [w.split(": ", 1)[0] for w in a.warnings] == [f"{first}:{line}", f"{first}:{line2}"]
    assert [w.split(": ", 1)[0] for w in b.warnings] == [f"{second}:{line}", f"{second}:{line2}"]
    assert len(b.kepler) == len(a.kepler) == len(load_nav(SAMPLE / "brdc1580.16n.gz").kepler) - 2
    with pytest.warns(RinexWarning, match=r"second\.16n: 2 problem"):   # one note per file, also when repeated
        both = load_nav([second, SAMPLE / "brdc1580.16g.gz", second])
    assert len(both.warnings) == 2


def test_cut_records_are_skipped_not_read_as_zeros(tmp_path):
    """A file cut inside its last record: that record is skipped (georinex would fill the rest with 0)."""
    text = gzip.decompress((SAMPLE / "brdc1580.16n.gz").read_bytes()).decode()
    clean = load_nav(SAMPLE / "brdc1580.16n.gz")
    lines = text.splitlines()
    cut_lines = tmp_path / "cut_lines.16n"                      # cut after the 4th line of the last record
    cut_lines.write_text("\n".join(lines[:-4]) + "\n0.1676")
    with pytest.warns(RinexWarning, match="record cut short: 5 lines instead of 8"):
        nav = load_nav(cut_lines)
    assert nav.warnings[0].startswith(f"{cut_lines}:{len(lines) - 7}: ")
    _assert_one_record_less(clean, nav, f"G{int(lines[-8][:2]):02d}")
    cut_value = tmp_path / "cut_value.16n"                      # cut inside the last value, no newline
    cut_value.write_text(text.rstrip("\n")[:-51])               # last line: "    0.165600000000D+06 0.4000"
    with pytest.warns(RinexWarning, match=rf"{cut_value}:{len(lines)}: file ends inside value '0\.40*'"):
        nav = load_nav(cut_value)
    assert len(nav.kepler) == len(clean.kepler) - 1
    cut_epoch = tmp_path / "cut_epoch.16n"                      # cut inside the epoch line of a next record
    cut_epoch.write_text(text + "12 16  6")
    with pytest.warns(RinexWarning, match=rf"{cut_epoch}:{len(lines) + 1}: file ends inside this line"):
        nav = load_nav(cut_epoch)
    for c in ("sv", "toe_gps_s", "sqrt_a_sqrt_m", "af0_s"):
        np.testing.assert_array_equal(getattr(nav.kepler, c), getattr(clean.kepler, c))
    whole = tmp_path / "no_final_newline.16n"                   # a complete last record without a newline
    whole.write_text(text.rstrip("\n"))
    assert len(load_nav(whole).kepler) == len(clean.kepler) and not load_nav(whole).warnings


def test_gzip_cut_short_keeps_the_records_before_the_cut(tmp_path):
    """An interrupted download of a .gz nav file: what was decompressed is used, the cut record skipped."""
    data = (SAMPLE / "brdc1580.16g.gz").read_bytes()
    path = tmp_path / "cut.16g.gz"
    path.write_bytes(data[: len(data) // 2])
    with pytest.warns(RinexWarning, match=r"cut\.16g\.gz: 2 problem.*compressed data end early"):
        nav = load_nav(path)
    assert "record cut short" in nav.warnings[1] or "file ends inside value" in nav.warnings[1]
    clean = load_nav(SAMPLE / "brdc1580.16g.gz").glonass
    n = len(nav.glonass)
    assert 0 < n < len(clean)
    keys = set(zip(clean.sv.tolist(), clean.toe_gps_s.tolist(), clean.pos_ecef_m[:, 0].tolist()))
    assert set(zip(nav.glonass.sv.tolist(), nav.glonass.toe_gps_s.tolist(), nav.glonass.pos_ecef_m[:, 0].tolist())) <= keys


def test_record_merged_with_a_damaged_epoch_line_is_skipped(tmp_path):
    """An unrecognisable epoch line glues its record to the previous one: both are skipped, with a warning."""
    path = tmp_path / "epoch.16n"
    [(line, _)] = _damaged_copy(SAMPLE / "brdc1580.16n.gz", path, [(5, 0, 0, b"#")])
    with pytest.warns(RinexWarning, match=rf"{path}:{line - 8}: record too long .*16 lines instead of 8"):
        nav = load_nav(path)
    assert len(nav.kepler) == len(load_nav(SAMPLE / "brdc1580.16n.gz").kepler) - 2


def test_every_record_damaged_is_one_line_error(tmp_path):
    head, rec = GPS_RINEX2.split("END OF HEADER\n")
    one = tmp_path / "one.16n"
    one.write_text(head + "END OF HEADER\n" + rec.replace("0.320000000000D+02-0.2065", "0.3200#0000000D+02-0.2065"))
    with pytest.raises(RinexError) as info:
        load_nav(one)
    msg = str(info.value)
    assert msg.startswith(f"{one}:10: not a readable RINEX navigation file: all 1 ephemeris record(s) damaged")
    assert "\n" not in msg and "unreadable value" in msg
    src = SAMPLE / "brdc1580.16g.gz"
    n = len(_record_starts(gzip.decompress(src.read_bytes()).split(b"\n")))
    every = tmp_path / "every.16g"
    _damaged_copy(src, every, [(k, 2, 7 + k % 50, b"\xff") for k in range(n)])
    with pytest.raises(RinexError, match=rf"^{every}:\d+: not a readable RINEX navigation file: all {n} ephemeris"):
        load_nav(every)


@pytest.mark.shared_data
def test_damaged_rinex3_record_is_skipped_with_a_warning(shared_data, tmp_path):
    """RINEX 3 mixed file: georinex would drop a damaged record silently; now it is a warning."""
    src = shared_data(f"{BERLIN}/BRDC00WRD_U_20161580000_01D_MN.rnx")
    lines = src.read_bytes().split(b"\n")
    starts = _record_starts(lines)
    rec = next(k for k, i in enumerate(starts) if lines[i][:1] == b"E")
    glo = next(k for k, i in enumerate(starts) if lines[i][:1] == b"R")
    for k, line, system in ((rec, 4, "E"), (glo, 2, "R")):
        path = tmp_path / f"damaged_{system}.rnx"
        [(number, sv)] = _damaged_copy(src, path, [(k, line, 40, b"#x")])
        with pytest.warns(RinexWarning, match=rf"{path}:{number}: unreadable value .*{sv} record"):
            nav = load_nav(path)
        clean = load_nav(src)
        _assert_one_record_less(clean, nav, sv)
        _assert_states_unchanged(clean, nav, sv)


# ---------------------------------------------------------------- RINEX 3.05 GLONASS records (5 lines)
def _rinex3_lines(rinex2_record: str, sv: str) -> list[str]:
    """A RINEX 2 record (epoch line + continuation lines) in the RINEX 3 layout (same fields, same order)."""
    lines = rinex2_record.strip("\n").split("\n")
    yy, mo, d, h, mi, s = (int(float(v)) for v in lines[0][2:22].split())
    first = f"{sv} {2000 + yy:4d} {mo:02d} {d:02d} {h:02d} {mi:02d} {s:02d}" + lines[0][22:]
    return [first] + ["    " + ln[3:] for ln in lines[1:]]


GLO_REC_V3 = _rinex3_lines(GLONASS_RINEX2.split("END OF HEADER\n")[1], "R01")
GPS_REC_V3 = _rinex3_lines(GPS_RINEX2.split("END OF HEADER\n")[1], "G02")
GLO_STATUS_LINE = "     0.000000000000D+00 0.000000000000D+00 1.500000000000D+01 0.000000000000D+00"


def _nav3(path: Path, version: str, records: list[list[str]], kind: str = "M: MIXED") -> Path:
    head = [f"{version:>9s}           N: GNSS NAV DATA    {kind:<20s}RINEX VERSION / TYPE",
            "    17                                                      LEAP SECONDS",
            " " * 60 + "END OF HEADER"]
    path.write_text("\n".join(head + [ln for rec in records for ln in rec]) + "\n")
    return path


def _glonass_equal(a, b) -> None:
    for f in fields(a):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), err_msg=f.name)


def test_rinex305_glonass_records_have_five_lines(tmp_path, bundled):
    """RINEX 3.05 added a 4th BROADCAST ORBIT line to GLONASS records; all of them used to be rejected."""
    ref = load_nav(bundled[1]).glonass
    nav = load_nav(_nav3(tmp_path / "g305.rnx", "3.05", [GLO_REC_V3 + [GLO_STATUS_LINE]], "R: GLONASS"))
    assert not nav.warnings
    _glonass_equal(nav.glonass, ref)
    assert nav.glonass.toe_gps_s[0] == week_tow_to_gps_s(1900, 86400 + 11 * 3600 + 15 * 60 + 17)  # UTC + 17 s
    old = load_nav(_nav3(tmp_path / "g304.rnx", "3.04", [GLO_REC_V3], "R: GLONASS"))
    assert not old.warnings
    _glonass_equal(old.glonass, ref)


def test_rinex305_mixed_file_keeps_glonass(tmp_path, bundled):
    """A 3.05 mixed file silently lost all GLONASS (every record 'too long'); the GPS record after it too."""
    path = _nav3(tmp_path / "m305.rnx", "3.05", [GLO_REC_V3 + [GLO_STATUS_LINE], GPS_REC_V3])
    nav = load_nav(path)
    assert not nav.warnings
    assert len(nav.glonass) == 1 and len(nav.kepler) == 1
    _glonass_equal(nav.glonass, load_nav(bundled[1]).glonass)
    ref = load_nav(bundled[0]).kepler
    for name in ("sv", "toe_gps_s", "sqrt_a_sqrt_m", "m0_rad", "af0_s", "tgd_s"):
        np.testing.assert_array_equal(getattr(nav.kepler, name), getattr(ref, name))


def test_rinex305_file_whose_glonass_records_all_keep_four_lines(tmp_path, bundled):
    """Review: a file labelled 3.05 whose writer kept the 4-line GLONASS layout lost every GLONASS record ('cut
    short'); when all of them have 4 lines, that is the layout, read as such."""
    ref = load_nav(bundled[1]).glonass
    path = _nav3(tmp_path / "g.rnx", "3.05", [GPS_REC_V3, GLO_REC_V3, GLO_REC_V3])    # (a duplicate, dropped)
    nav = load_nav(path)
    assert not nav.warnings and len(nav.kepler) == 1
    _glonass_equal(nav.glonass, ref)


def test_rinex305_four_line_layout_needs_two_whole_records(tmp_path, bundled):
    """Review: a lone 4-line GLONASS record (one that lost a line) switched the layout and its status line was read as
    the z line; a file cut inside its last record kept the layout from switching. Two or more whole 4-line records
    and no 5-line one decide it; a record cut by the file's end does not count."""
    ref = load_nav(bundled[1]).glonass
    lone = _nav3(tmp_path / "lone.rnx", "3.05", [GPS_REC_V3, GLO_REC_V3])
    with pytest.warns(RinexWarning, match="damaged navigation records skipped"):
        nav = load_nav(lone)
    assert len(nav.glonass) == 0 and nav.warnings == (f"{lone}:12: record cut short: 4 lines instead of 5; R01 record "
                                                      "of line 12 skipped",)
    r02 = ["R02" + GLO_REC_V3[0][3:]] + GLO_REC_V3[1:]
    cut = tmp_path / "cut.rnx"
    cut.write_text(_nav3(tmp_path / "c.rnx", "3.05", [GLO_REC_V3, r02, GLO_REC_V3[:2]]).read_text().rstrip("\n")[:-20])
    with pytest.warns(RinexWarning, match="damaged navigation records skipped"):
        nav = load_nav(cut)
    assert len(nav.glonass) == 2 and nav.warnings == (f"{cut}:12: record cut short: 2 lines instead of 4; R01 record "
                                                      "of line 12 skipped",)
    assert sorted(nav.glonass.sv) == ["R01", "R02"]
    np.testing.assert_array_equal(nav.glonass.pos_ecef_m, np.repeat(ref.pos_ecef_m, 2, axis=0))


def test_a_status_line_read_as_an_orbit_line_is_impossible(tmp_path):
    """Two records that both lost their third orbit line (z, z velocity, z acceleration) in a 3.05 file read in the
    4-line layout: the status line's URAI 15 arrives as an acceleration of 15 km/s^2 and the records are skipped, not
    used with z = 0."""
    lost = [GLO_REC_V3[0], GLO_REC_V3[1], GLO_REC_V3[2], GLO_STATUS_LINE]
    r02 = ["R02" + lost[0][3:]] + lost[1:]
    path = _nav3(tmp_path / "g.rnx", "3.05", [GPS_REC_V3, lost, r02])
    with pytest.warns(RinexWarning):
        nav = load_nav(path)
    assert len(nav.glonass) == 0 and len(nav.kepler) == 1
    assert any("luni-solar acceleration [m/s^2] 15000 outside [0, 0.0001]" in w for w in nav.warnings), nav.warnings


@pytest.mark.parametrize("version, status_line, reason", [
    ("3.04", True, "record too long (damaged, or merged with the next record): 5 lines instead of 4"),
    ("3.05", False, "record cut short: 4 lines instead of 5"),
])
def test_glonass_record_line_count_by_version(tmp_path, version, status_line, reason):
    """The number of lines still protects against a lost or an extra line: 4 before 3.05, 5 from 3.05 on (a 4-line
    record among 5-line ones)."""
    bad = GLO_REC_V3 + ([GLO_STATUS_LINE] if status_line else [])
    good = GLO_REC_V3 + ([] if status_line else [GLO_STATUS_LINE])
    path = _nav3(tmp_path / "g.rnx", version, [bad, GPS_REC_V3] + ([] if status_line else [good]))
    with pytest.warns(RinexWarning, match="damaged navigation records skipped"):
        nav = load_nav(path)
    assert len(nav.glonass) == (0 if status_line else 1) and len(nav.kepler) == 1
    assert nav.warnings == (f"{path}:4: {reason}; R01 record of line 4 skipped",)


# ---------------------------------------------------------------- time scales
@pytest.mark.parametrize("stamp, leap", [
    ("2015-06-30T23:59:59", 16.0), ("2015-07-01T00:00:15", 16.0), ("2015-07-01T00:00:16", 16.0),
    ("2015-07-01T00:00:17", 17.0), ("2015-07-01T00:00:30", 17.0),
    ("2016-12-31T23:59:59", 17.0), ("2017-01-01T00:00:17", 17.0), ("2017-01-01T00:00:18", 18.0),
    ("2020-06-03T03:02:27", 18.0), ("1981-07-01T00:00:00", 0.0), ("1981-07-01T00:00:01", 1.0),
])
def test_leap_seconds_at_the_boundaries(stamp, leap):
    """GPST - UTC at a GPS time: the new value applies from the GPS second at which UTC reaches the date
    (2015-07-01 00:00:17 GPST = 00:00:00 UTC), as RTKLIB ``gpst2utc``; it used to lag 17-18 s behind."""
    from lfgnss.time import datetime64_to_gps_s, leap_seconds, utc_to_gps_s

    t = datetime64_to_gps_s(np.datetime64(stamp, "ns"))
    assert leap_seconds(t) == leap
    assert leap_seconds(np.array([t, t])).tolist() == [leap, leap]
    utc = t - leap                                        # and it inverts utc_to_gps_s away from the leap second
    if stamp not in ("2015-07-01T00:00:16", "2017-01-01T00:00:17", "1981-07-01T00:00:00"):   # 23:59:60 UTC
        assert utc_to_gps_s(utc) == t


# ---------------------------------------------------------------- no ionosphere coefficients: said so
def test_missing_ionosphere_coefficients_are_noted(tmp_path, capsys):
    """Without GPS Klobuchar coefficients lfgnss (like RTKLIB) uses default ones: now with a note, also in the CLI."""
    import lfgnss
    from lfgnss.solve import SAMPLE_OBS, main

    text = gzip.decompress((SAMPLE / "brdc1580.16n.gz").read_bytes()).decode()
    assert "ION ALPHA" in text
    no_iono = tmp_path / "noiono.16n"
    no_iono.write_text("\n".join(ln for ln in text.split("\n") if "ION ALPHA" not in ln and "ION BETA" not in ln))
    glo = SAMPLE / "brdc1580.16g.gz"
    assert load_nav(no_iono).iono == {}
    with pytest.warns(RinexWarning, match="no GPS ionosphere coefficients"):
        meas = lfgnss.load(SAMPLE_OBS, [no_iono, glo])
    note = [w for w in meas.warnings if "ionosphere" in w]
    assert note == [f"{no_iono}, {glo}: no GPS ionosphere coefficients (ION ALPHA/BETA or GPSA/GPSB header lines) "
                    f"in the navigation file(s); the Klobuchar ionosphere uses default coefficients (RTKLIB's, "
                    f"of 2004-01-01), which can be off by metres"]
    clean = lfgnss.load(SAMPLE_OBS, [SAMPLE / "brdc1580.16n.gz", glo])
    assert not [w for w in clean.warnings if "ionosphere" in w]
    code = main(["--backend", "wls", "--obs", str(SAMPLE_OBS), "--nav", str(no_iono), str(glo),
                 "--out", str(tmp_path / "o"), "--no-plots", "--quiet"])
    assert code == 0 and f"warning: {no_iono}, {glo}: no GPS ionosphere coefficients" in capsys.readouterr().err


# ---------------------------------------------------------------- impossible values: skipped with a warning
@pytest.mark.parametrize("name, damage, sv, reason", [
    ("brdc1580.16n.gz", (7, 2, 22, b" 0.150000000000D+01"), "G", r"eccentricity 1\.5 outside \[0, 0\.5\]"),
    ("brdc1580.16n.gz", (5, 2, 60, b" 0.515357678223D+14"), "G", r"sqrt\(A\) \[m\^0\.5\] 5\.15358e\+13 outside"),
    ("brdc1580.16n.gz", (8, 0, 22, b" 0.100000000000D+11"), "G", r"clock offset af0 \[s\] 1e\+10 outside"),
    ("brdc1580.16g.gz", (10, 0, 22, b"-0.100000000000D+11"), "R", r"clock offset tau_n \[s\] 1e\+10 outside"),
    ("brdc1580.16g.gz", (12, 1, 3, b" 0.973446533203D+08"), "R", r"orbit radius \[m\] .* outside \[2e\+07, 3\.5e\+07\]"),
], ids=["gps-eccentricity", "gps-sqrt-a-exponent", "gps-clock", "glonass-clock", "glonass-position"])
def test_impossible_record_is_skipped_with_a_warning(tmp_path, name, damage, sv, reason):
    """A readable but impossible value (a flipped exponent) costs that record only, with a note naming file and
    satellite; one such record would otherwise put a satellite light-years away (or, for GLONASS, integrate the
    orbit for 1e10 s: a hang) and wreck every epoch's coarse fix."""
    src, path = SAMPLE / name, tmp_path / ("bad" + Path(name).suffixes[0])
    [(_, bad_sv)] = _damaged_copy(src, path, [damage])
    assert bad_sv[0] == sv
    with pytest.warns(RinexWarning, match=rf"{path}: 1 problem.*first: {path}: 1 {bad_sv} record\(s\) skipped as "
                                          rf"impossible, first: {reason}"):
        nav = load_nav(path)
    clean = load_nav(src)
    _assert_one_record_less(clean, nav, bad_sv)
    _assert_states_unchanged(clean, nav, bad_sv)


def test_every_record_impossible_is_a_one_line_error(tmp_path):
    path = tmp_path / "bad.16n"
    path.write_text(GPS_RINEX2.replace("0.157487246906D-01", "0.157487246906D+01"))     # e = 1.57
    with pytest.raises(RinexError, match=rf"^{path}: no GPS.* records: every record impossible, e\.g\. 1 G02 "
                                         r"record\(s\) skipped as impossible, first: eccentricity 1\.57"):
        load_nav(path)


def test_lowercase_d_exponents_read_as_uppercase(bundled, tmp_path):
    """Fortran writes 1.5d-04 as well as 1.5D-04 (RTKLIB reads both), in the records and in the header."""
    import re

    lower = tmp_path / "lower.16n"
    lower.write_text(re.sub(r"(?<=\d)D(?=[+-]\d)", "d", GPS_RINEX2))
    assert "0.6519d-08" in lower.read_text()                          # ION ALPHA too
    a, b = load_nav(bundled[0]), load_nav(lower)
    assert not b.warnings
    for f in fields(a.kepler):
        np.testing.assert_array_equal(getattr(a.kepler, f.name), getattr(b.kepler, f.name))
    np.testing.assert_array_equal(a.iono["GPS"], b.iono["GPS"])


def test_an_impossible_record_flagged_unhealthy_is_kept_unhealthy(tmp_path):
    """A placeholder record the system marks unusable keeps that flag in force (not dropped, so that a healthy
    neighbour would be picked in its place), and needs no note."""
    path = tmp_path / "placeholder.16n"
    path.write_text(GPS_RINEX2.replace("0.157487246906D-01", "0.157487246906D+01")          # e = 1.57
                    .replace("0.200000000000D+01 0.000000000000D+00", "0.200000000000D+01 0.100000000000D+01"))
    nav = load_nav(path)
    assert len(nav.kepler) == 1 and nav.kepler.health[0] == 1 and not nav.warnings
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")                                    # no bare numpy warning from e >= 1
        states = ephemeris_states(nav, nav.kepler.sv[:1], nav.kepler.toe_gps_s[:1])
    assert not states.ok[0] and states.reason[0] == "unhealthy"


def test_glonass_propagation_is_bounded_and_a_non_finite_state_is_not_ok(bundled):
    """An absurd propagation time gives NaN at once (not |dt| / 60 s integration steps); ephemeris_states
    marks a non-finite state 'invalid ephemeris', never ok."""
    import dataclasses
    import time

    from lfgnss.glonass import MAX_PROPAGATION_S, propagate

    nav = load_nav(bundled[1])
    g = nav.glonass
    start = time.perf_counter()
    pos, vel = propagate(g.pos_ecef_m, g.vel_ecef_m_s, g.acc_ecef_m_s2, np.array([1e10]))
    assert time.perf_counter() - start < 1.0 and np.isnan(pos).all() and np.isnan(vel).all()
    pos, _ = propagate(g.pos_ecef_m, g.vel_ecef_m_s, g.acc_ecef_m_s2, np.array([MAX_PROPAGATION_S / 4]))
    assert np.isfinite(pos).all()
    broken = dataclasses.replace(nav, glonass=dataclasses.replace(g, pos_ecef_m=np.full_like(g.pos_ecef_m, np.nan)))
    states = ephemeris_states(broken, np.array(["R01"]), g.toe_gps_s[:1] + 60.0)
    assert not states.ok[0] and states.reason[0] == "invalid ephemeris"
    from lfgnss import qc

    assert qc.REASONS[int(qc.ephemeris_reason(states.reason)[0])] == "invalid ephemeris"     # counted as such
    assert ephemeris_states(nav, np.array(["R01"]), g.toe_gps_s[:1] + 60.0).ok[0]


# ---------------------------------------------------------------- session 55: a review against RTKLIB 2.4.3 b34
def test_glonass_epochs_are_on_the_15_minute_grid(tmp_path):
    """RTKLIB's decode_geph rounds a GLONASS epoch to 15 min of UTC: a copy stamped 17 s late (brdc1580.16g has six
    at 12:15:17) is the same record, not one that moves its satellite 60 km for a quarter of an hour."""
    head, rec = GLONASS_RINEX2.split("END OF HEADER\n")
    path = tmp_path / "late.16g"
    path.write_text(head + "END OF HEADER\n" + rec + rec.replace(" 11 15  0.0", " 11 15 17.0", 1))
    g = load_nav(path).glonass
    assert len(g) == 1 and g.toe_gps_s[0] == week_tow_to_gps_s(1900, 126900.0 + 17.0)    # 11:15:00 UTC


def test_blank_trailing_fields_and_header_numbers_are_read_as_zero(tmp_path):
    """RTKLIB reads a blank field as 0; georinex refused the file for a blank fit interval, a blank ionosphere
    coefficient or a blank DELTA-UTC number."""
    head, rec = GPS_RINEX2.split("END OF HEADER\n")
    lines = rec.splitlines()
    lines[-1] = lines[-1][:22]                                   # fit interval and spares left out
    head = head.replace("    0.8602D+05  0.9830D+05", "    0.8602D+05            ")      # ION BETA's second
    head = head.replace("0.799360577730D-14", " " * 18)                                 # DELTA-UTC's A1
    path = tmp_path / "blank.16n"
    path.write_text(head + "END OF HEADER\n" + "\n".join(lines) + "\n")
    nav = load_nav(path)
    assert len(nav.kepler) == 1 and nav.kepler.sqrt_a_sqrt_m[0] == pytest.approx(5153.57678223)
    assert nav.iono["GPS"][4:6].tolist() == [86020.0, 0.0]


def test_an_sbas_file_among_several_is_left_out_and_zero_ionosphere_hides_nothing(tmp_path):
    head, rec = GPS_RINEX2.split("END OF HEADER\n")
    sbas = tmp_path / "brdc1580.16h"
    sbas.write_text("     2.10           H: GEO NAV MSG DATA                     RINEX VERSION / TYPE\n"
                    + " " * 60 + "END OF HEADER\n")
    zero = tmp_path / "zero.16n"
    zero.write_text(head.replace("0.6519D-08  0.2235D-07 -0.5960D-07 -0.1192D-06",
                                 "0.0000D+00  0.0000D+00  0.0000D+00  0.0000D+00")
                    .replace("0.8602D+05  0.9830D+05 -0.6554D+05 -0.5243D+06",
                             "0.0000D+00  0.0000D+00  0.0000D+00  0.0000D+00") + "END OF HEADER\n" + rec)
    real = tmp_path / "real.16n"
    real.write_text(GPS_RINEX2)
    with pytest.warns(RinexWarning):
        nav = load_nav([zero, sbas, real])
    assert any("brdc1580.16h: no GPS/Galileo/QZSS/BeiDou/GLONASS ephemeris records" in w for w in nav.warnings)
    assert nav.iono["GPS"][0] == pytest.approx(0.6519e-8)        # the placeholder zeros of the first file hid it
    with pytest.raises(RinexError, match="no GPS/Galileo/QZSS/BeiDou/GLONASS ephemeris records"):
        load_nav(sbas)
    other = tmp_path / "brdc1590.16h"
    other.write_text(sbas.read_text())
    with pytest.raises(RinexError, match="ephemeris records in any of the 2 files given"):
        load_nav([sbas, other])


def test_a_rinex2_record_in_a_rinex3_file_costs_no_record_before_it(tmp_path):
    """A record in the RINEX 2 layout inside a 3.0x file is skipped on its own; it was glued onto the record before it,
    which was skipped (with a note blaming it) in its place."""
    v2_record = GPS_RINEX2.split("END OF HEADER\n")[1].strip("\n").split("\n")
    path = _nav3(tmp_path / "m.rnx", "3.04", [GPS_REC_V3, v2_record])
    with pytest.warns(RinexWarning, match=r"m.rnx:12: unreadable satellite number or epoch"):
        nav = load_nav(path)
    assert nav.kepler.sv.tolist() == ["G02"]
