"""lfgnss.navigation: RINEX 2/3 navigation files -> Navigation records."""
from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest

from lfgnss.errors import RinexError
from lfgnss.navigation import Navigation, load_nav
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
    """No record is lost to georinex (blank BeiDou spare fields, RINEX 2 duplicate epochs)."""
    path = shared_data(rel)
    nav = load_nav(path)
    assert set(nav.kepler.system) | ({"R"} if len(nav.glonass) else set()) == systems
    assert len(nav.kepler) + len(nav.glonass) == _records_in(path)
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
