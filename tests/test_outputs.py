"""Writers, .pos reader (our files and RTKLIB's) and plots."""
from __future__ import annotations

import csv
import json
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from estimators.base import STATUS_COASTED, STATUS_NONE, STATUS_RESET, STATUS_UPDATED, Solution
from lfgnss.frames import lla_to_ecef
from lfgnss.metrics import enu_errors
from lfgnss.outputs import (CSV_COLUMNS, CSV_TRUTH_COLUMNS, align_to, plot_solution, read_pos, write_csv,
                            write_geojson, write_kml, write_pos)
from lfgnss.paths import shared_data_dir
from lfgnss.time import utc_to_gps_s, week_tow_to_gps_s

# First lines of `rnx2rtkp -p 0 -t` (RTKLIB 2.4.3 b34) on the smartLoc Berlin Potsdamer Platz drive
# (TU Chemnitz, CC BY-SA 4.0), plus two lines with negative cross terms. Line ends as RTKLIB writes.
RTKLIB_SNIPPET = (
    "% program   : rnx2rtkp ver.2.4.3 b34\n"
    "% inp file  : Berlin_Potsdamer_Platz.obs\n"
    "% inp file  : brdc1580.16n\n"
    "% obs start : 2016/06/06 11:10:41.7 GPST (week1900 126641.7s)\n"
    "% obs end   : 2016/06/06 11:15:25.1 GPST (week1900 126925.1s)\n"
    "%\n"
    "% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)\r\n"
    "%  GPST                  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)"
    "  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio\r\n"
    "2016/06/06 11:10:45.200   52.504773959   13.375066262   240.6051   5   8   6.4497   3.9873  13.6992"
    "   3.1139   4.8902   5.0387   0.00    0.0\r\n"
    "2016/06/06 11:10:45.500   52.504800705   13.375125938   239.5618   5   8   6.4497   3.9873  13.6998"
    "   3.1138   4.8904   5.0391   0.00    0.0\r\n"
    "2016/06/06 11:11:17.300   52.505395952   13.373216587   198.2142   5   4  22.7836  14.0986  14.9724"
    "  17.1134  -1.9625  -6.8263   0.00    0.0\r\n"
    "2016/06/06 11:11:21.400   52.505933294   13.373573716   147.8625   5   4  21.3398  16.5709  31.6838"
    "  17.4577 -19.1100 -18.7662   0.00    0.0\r\n"
)


def _solution(t: int = 12, seed: int = 0) -> tuple[Solution, np.ndarray]:
    rng = np.random.default_rng(seed)
    time = week_tow_to_gps_s(1900, 126659.6 + 0.2 * np.arange(t))
    time[2] -= 0.0004  # 126659.9996 must print as 11:11:00.000, not 11:10:60.000
    truth = lla_to_ecef(np.radians(52.5048 + 1e-5 * np.arange(t)), np.radians(13.375 + 1e-5 * np.arange(t)),
                        np.full(t, 40.0))
    pos = truth + rng.normal(0, 5, (t, 3))
    a = rng.normal(0, 3, (t, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2) + 0.5 * np.eye(3)
    status = np.full(t, STATUS_UPDATED)
    status[0] = STATUS_NONE
    status[1] = STATUS_RESET
    status[5:7] = STATUS_COASTED
    status[9] = STATUS_NONE
    pos[status == STATUS_NONE] = np.nan
    cov[status == STATUS_NONE] = np.nan
    cov[8] = np.nan  # position but no covariance
    n_used = rng.integers(4, 12, t)
    n_used[status == STATUS_COASTED] = 0
    truth[10] = np.nan
    sol = Solution(backend="ekf", time_gps_s=time, pos_ecef_m=pos, cov_ecef_m2=cov, clock_m=np.zeros(t),
                   n_used=n_used, status=status)
    return sol, truth


def _no_nan_text(path: Path) -> str:
    text = Path(path).read_text()
    low = text.lower()
    assert "nan" not in low and "inf" not in low, path
    return text


# ---------------------------------------------------------------- .pos
@pytest.mark.parametrize("time_format", ["calendar", "tow"])
def test_pos_round_trip(tmp_path, time_format):
    sol, _ = _solution()
    path = write_pos(tmp_path / "a.pos", sol, time_format=time_format)
    _no_nan_text(path)
    back = read_pos(path)
    keep = sol.status != STATUS_NONE
    assert back.backend == "ekf"
    assert len(back.time_gps_s) == keep.sum()
    np.testing.assert_allclose(back.time_gps_s, np.round(sol.time_gps_s[keep], 3), rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.pos_ecef_m, sol.pos_ecef_m[keep], atol=2e-4)
    np.testing.assert_array_equal(back.n_used, sol.n_used[keep])
    np.testing.assert_array_equal(back.info["q"], np.where(sol.status[keep] == STATUS_COASTED, 7, 5))
    np.testing.assert_array_equal(back.status == STATUS_COASTED, sol.status[keep] == STATUS_COASTED)
    cov_ok = np.isfinite(sol.cov_ecef_m2[keep]).all(axis=(1, 2))
    np.testing.assert_allclose(back.cov_ecef_m2[cov_ok], sol.cov_ecef_m2[keep][cov_ok], rtol=1e-3, atol=1e-3)
    assert np.isnan(back.cov_ecef_m2[~cov_ok]).all()      # six sds of 0 (RTKLIB's unknown) read back as unknown
    assert np.isnan(back.sd_enu_m()[~cov_ok]).all() and np.isfinite(back.sd_enu_m()[cov_ok]).all()
    assert np.isnan(back.clock_m).all()


def test_pos_layout_matches_rtklib(tmp_path):
    """Our writer reproduces RTKLIB's column header and data lines byte for byte."""
    src = tmp_path / "rtk.pos"
    src.write_bytes(RTKLIB_SNIPPET.encode())
    sol = read_pos(src)
    assert sol.backend == "rtklib" and len(sol.time_gps_s) == 4
    np.testing.assert_allclose(sol.time_gps_s[0], week_tow_to_gps_s(1900, 126645.2), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(sol.n_used, [8, 8, 4, 4])
    assert np.all(sol.status == STATUS_UPDATED)
    out = write_pos(tmp_path / "ours.pos", sol)
    theirs = src.read_bytes().split(b"\n")
    ours = out.read_bytes().split(b"\n")
    assert ours[5:] == theirs[7:]
    assert ours[4] == theirs[6].replace(b"6:ppp,", b"6:ppp,7:dr,")      # the legend names the Q of a coasted epoch
    assert ours[0].startswith(b"% program   : lfgnss")
    assert ours[1] == b"% obs start : 2016/06/06 11:10:45.2 GPST (week1900 126645.2s)"
    named = write_pos(tmp_path / "named.pos", sol, inputs=["rover.obs", "brdc.nav"], systems="GRCE")
    header = named.read_bytes().split(b"\n")[1:4]
    assert header == [b"% inp file  : rover.obs", b"% inp file  : brdc.nav",      # as rnx2rtkp's own header lines
                      b"% navi sys  : gps glonass beidou galileo"]
    assert named.read_bytes().split(b"\n")[7:] == ours[4:] and len(read_pos(named).time_gps_s) == 4


def test_read_pos_ecef_and_week_tow(tmp_path):
    sol, _ = _solution()
    p = write_pos(tmp_path / "w.pos", sol, time_format="tow")
    text = p.read_text()
    assert "\n1900 126659.800 " in text.replace("\r", "")
    # An ECEF (rnx2rtkp -e) line without header: detected by magnitude.
    q = tmp_path / "e.pos"
    q.write_text("1900 126645.200   3785166.0232    900013.2237   5037378.8574   5   8   8.0715   4.6848  12.5726"
                 "   4.3097   6.2448   7.5152   0.00    0.0\r\n")
    e = read_pos(q)
    np.testing.assert_allclose(e.pos_ecef_m[0], [3785166.0232, 900013.2237, 5037378.8574])
    np.testing.assert_allclose(e.cov_ecef_m2[0, 0, 1], 4.3097 ** 2)
    short = tmp_path / "short.pos"        # without age and ratio (13 fields): read as 0
    short.write_text("1900 126645.200   3785166.0232    900013.2237   5037378.8574   5   8   8.0715   4.6848  12.5726"
                     "   4.3097   6.2448   7.5152\n")
    s = read_pos(short)
    np.testing.assert_allclose(s.pos_ecef_m, e.pos_ecef_m)
    assert s.info["age_s"][0] == 0.0 and s.info["ratio"][0] == 0.0
    bad = tmp_path / "bad.pos"
    bad.write_text("2016/06/06 11:10:45.200 52.5 13.3\n")
    with pytest.raises(ValueError, match="bad.pos:1"):
        read_pos(bad)


@pytest.mark.shared_data
@pytest.mark.skipif(shutil.which("rnx2rtkp") is None, reason="RTKLIB rnx2rtkp not installed")
@pytest.mark.parametrize("opts", [["-t"], [], ["-t", "-u"], ["-u"], ["-e"]],
                         ids=["gpst", "tow", "utc", "utc-tow", "ecef"])         # -u: UTC, weeks and TOW too
def test_read_pos_parses_real_rtklib_output(tmp_path, opts):
    d = shared_data_dir() / "smartloc-berlin-potsdamer-platz-rinex"
    obs, nav = d / "Berlin_Potsdamer_Platz.obs", d / "brdc1580.16n"
    if not (obs.exists() and nav.exists()):
        pytest.skip(f"shared data not found in {d}")
    out = tmp_path / "rtk.pos"
    subprocess.run(["rnx2rtkp", "-p", "0", *opts, "-o", str(out), str(obs), str(nav)], check=True,
                   capture_output=True, timeout=120)
    sol = read_pos(out)
    n_lines = sum(1 for line in out.read_text().splitlines() if line and not line.startswith("%"))
    assert len(sol.time_gps_s) == n_lines > 100
    assert np.isfinite(sol.pos_ecef_m).all() and np.isfinite(sol.cov_ecef_m2).all()
    np.testing.assert_allclose(sol.time_gps_s[0], week_tow_to_gps_s(1900, 126645.2), rtol=0, atol=1e-6)
    assert np.all(np.diff(sol.time_gps_s) > 0)
    assert np.linalg.norm(sol.pos_ecef_m - sol.pos_ecef_m[0], axis=1).max() < 5e3  # one city block drive
    if opts in (["-t"], []):
        ours = write_pos(tmp_path / "ours.pos", sol, time_format="calendar" if opts else "tow")
        mine, theirs = ours.read_bytes().split(b"\n"), out.read_bytes().split(b"\n")
        assert mine[5:] == theirs[7:] and mine[4] == theirs[6].replace(b"6:ppp,", b"6:ppp,7:dr,")


# ---------------------------------------------------------------- CSV / GeoJSON / KML
def test_csv(tmp_path):
    sol, truth = _solution()
    p = write_csv(tmp_path / "a.csv", sol, truth)
    _no_nan_text(p)
    with open(p, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == list(CSV_COLUMNS + CSV_TRUTH_COLUMNS)
    assert len(rows) == len(sol.time_gps_s)
    for k, r in enumerate(rows):
        if sol.status[k] == STATUS_NONE:
            assert r["status"] == "none" and r["x_m"] == "" and r["lat_deg"] == "" and r["err_3d_m"] == ""
        else:
            assert r["status"] in ("updated", "coasted", "reset")
            np.testing.assert_allclose([float(r[c]) for c in ("x_m", "y_m", "z_m")], sol.pos_ecef_m[k], atol=1e-4)
    assert rows[2]["time_gpst"] == "2016/06/06 11:11:00.000"
    assert rows[2]["tow_s"] == "126660.000" and rows[2]["week"] == "1900"
    assert rows[8]["sd_e_m"] == "" and rows[8]["x_m"] != ""
    assert rows[10]["err_e_m"] == ""  # unlabelled
    e = enu_errors(sol.pos_ecef_m, truth)
    np.testing.assert_allclose(float(rows[2]["err_u_m"]), e[2, 2], atol=1e-4)
    assert rows[5]["status"] == "coasted" and rows[1]["status"] == "reset"
    p2 = write_csv(tmp_path / "b.csv", sol)
    assert p2.read_text().splitlines()[0].split(",") == list(CSV_COLUMNS)


def test_geojson_and_kml(tmp_path):
    sol, _ = _solution()
    n_pos = int((sol.status != STATUS_NONE).sum())
    g = write_geojson(tmp_path / "a.geojson", sol, points=True)
    _no_nan_text(g)
    doc = json.loads(g.read_text())
    line = doc["features"][0]            # epoch 9 has no position: two pieces, not a line straight across it
    assert line["geometry"]["type"] == "MultiLineString" and line["properties"]["n_pieces"] == 2
    assert [len(piece) for piece in line["geometry"]["coordinates"]] == [8, 2] and n_pos == 10
    lon, lat, h = line["geometry"]["coordinates"][0][0]
    assert 13 < lon < 14 and 52 < lat < 53
    assert sum(f["geometry"]["type"] == "Point" for f in doc["features"]) == n_pos
    assert doc["features"][1]["properties"]["time_utc"] == "2016-06-06T11:10:42.800Z"     # as the KML's TimeStamp
    k = write_kml(tmp_path / "a.kml", sol, points=True)
    _no_nan_text(k)
    root = ET.parse(k).getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    pieces = root.findall(".//k:MultiGeometry/k:LineString/k:coordinates", ns)
    assert [len(c.text.split()) for c in pieces] == [8, 2]
    assert len(root.findall(".//k:Point", ns)) == n_pos
    when = [w.text for w in root.findall(".//k:Placemark/k:TimeStamp/k:when", ns)]     # UTC, for a time slider
    assert len(when) == n_pos and when[0] == "2016-06-06T11:10:42.800Z"                  # GPST 11:10:59.8 - 17 s
    from lfgnss.outputs import _utc_iso
    leap = week_tow_to_gps_s(1930, 18.0)          # 2017-01-01 00:00:00 UTC, the first second after 23:59:60
    assert _utc_iso(leap + np.array([-1.5, -0.5, 0.5])) == [        # the inserted second: no step back in time
        "2016-12-31T23:59:59.500Z", "2016-12-31T23:59:59.999Z", "2017-01-01T00:00:00.500Z"]


def test_writers_with_no_position(tmp_path):
    sol, truth = _solution(12)
    empty = Solution(backend="x", time_gps_s=sol.time_gps_s, pos_ecef_m=np.full((12, 3), np.nan),
                     cov_ecef_m2=np.full((12, 3, 3), np.nan), clock_m=np.full(12, np.nan),
                     n_used=np.zeros(12, int), status=np.full(12, STATUS_NONE))
    for writer in (write_pos, write_geojson, write_kml):
        _no_nan_text(writer(tmp_path / f"e.{writer.__name__}", empty))
    _no_nan_text(write_csv(tmp_path / "e.csv", empty, truth))
    assert len(read_pos(tmp_path / "e.write_pos").time_gps_s) == 0
    assert plot_solution(tmp_path / "p", empty, truth)[0].exists()


def test_map_files_of_a_single_fix(tmp_path):
    """One epoch with a position is a Point in the GeoJSON and the KML (a LineString needs two), not an empty map."""
    sol, _ = _solution()
    one = sol.subset(np.arange(len(sol.time_gps_s)) == 3)
    doc = json.loads(write_geojson(tmp_path / "one.geojson", one).read_text())
    assert [f["geometry"]["type"] for f in doc["features"]] == ["Point"]
    lon, lat, _h = doc["features"][0]["geometry"]["coordinates"]
    assert 13 < lon < 14 and 52 < lat < 53
    root = ET.parse(write_kml(tmp_path / "one.kml", one)).getroot()
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    assert root.find(".//k:LineString", ns) is None
    assert root.find(".//k:Point/k:coordinates", ns).text.split(",")[:2] == [f"{lon:.9f}", f"{lat:.9f}"]
    both = json.loads(write_geojson(tmp_path / "p.geojson", one, points=True).read_text())
    assert [f["geometry"]["type"] for f in both["features"]] == ["Point"]          # the epoch's point, once
    assert len(ET.parse(write_kml(tmp_path / "p.kml", one, points=True)).getroot().findall(".//k:Point", ns)) == 1


def test_a_track_with_gaps_and_a_lone_fix_is_drawn_in_pieces(tmp_path):
    """Epochs without a position (a wls run's unfixed epochs) cut the track: the pieces are lines, a lone fix between
    two gaps a point; one unbroken run stays one LineString (the EKF's usual track)."""
    sol, _ = _solution()
    status = sol.status.copy()
    status[[3, 5]] = STATUS_NONE                        # positions at 1-2, 4 (alone), 6-8, 10-11
    cut = Solution(backend="wls", time_gps_s=sol.time_gps_s, pos_ecef_m=sol.pos_ecef_m, cov_ecef_m2=sol.cov_ecef_m2,
                   clock_m=sol.clock_m, n_used=sol.n_used, status=status)
    doc = json.loads(write_geojson(tmp_path / "c.geojson", cut).read_text())
    assert [f["geometry"]["type"] for f in doc["features"]] == ["MultiLineString", "MultiPoint"]
    assert [len(p) for p in doc["features"][0]["geometry"]["coordinates"]] == [2, 3, 2]
    assert len(doc["features"][1]["geometry"]["coordinates"]) == 1 and doc["features"][1]["properties"] == {
        "backend": "wls", "lone_fixes": 1}
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    root = ET.parse(write_kml(tmp_path / "c.kml", cut)).getroot()
    assert [len(c.text.split()) for c in root.findall(".//k:MultiGeometry/k:LineString/k:coordinates", ns)] == [2, 3, 2]
    assert len(root.findall(".//k:MultiGeometry/k:Point", ns)) == 1
    status[[3, 5, 9]] = STATUS_UPDATED, STATUS_UPDATED, STATUS_NONE
    status[11] = STATUS_NONE                            # one line (1-8) and a lone fix (10), with points=True
    one = Solution(backend="wls", time_gps_s=sol.time_gps_s, pos_ecef_m=sol.pos_ecef_m, cov_ecef_m2=sol.cov_ecef_m2,
                   clock_m=sol.clock_m, n_used=sol.n_used, status=status)
    root = ET.parse(write_kml(tmp_path / "p.kml", one, points=True)).getroot()
    assert len(root.findall(".//k:LineString", ns)) == 1 and len(root.findall(".//k:Point", ns)) == 9
    doc = json.loads(write_geojson(tmp_path / "p.geojson", one, points=True).read_text())
    assert [len(p) for p in doc["features"][0]["geometry"]["coordinates"]] == [8]
    assert sum(f["geometry"]["type"] == "Point" for f in doc["features"]) == 9
    whole = Solution(backend="ekf", time_gps_s=sol.time_gps_s[1:9], pos_ecef_m=sol.pos_ecef_m[1:9],
                     cov_ecef_m2=sol.cov_ecef_m2[1:9], clock_m=sol.clock_m[1:9], n_used=sol.n_used[1:9],
                     status=sol.status[1:9])
    doc = json.loads(write_geojson(tmp_path / "w.geojson", whole).read_text())
    assert [f["geometry"]["type"] for f in doc["features"]] == ["LineString"]
    assert ET.parse(write_kml(tmp_path / "w.kml", whole)).getroot().find(".//k:MultiGeometry", ns) is None


def test_csv_week_and_tow_are_the_instant_time_gpst_shows(tmp_path):
    """Half a millisecond before a week's end prints as the next week's 00:00:00.000: week and TOW say so too."""
    time = week_tow_to_gps_s(2050, np.array([604799.9996, 604800.2]))
    pos = lla_to_ecef(np.radians([52.5, 52.5]), np.radians([13.4, 13.4]), np.full(2, 40.0)).reshape(2, 3)
    sol = Solution(backend="x", time_gps_s=time, pos_ecef_m=pos, cov_ecef_m2=np.tile(np.eye(3), (2, 1, 1)),
                   clock_m=np.zeros(2), n_used=np.full(2, 6), status=np.full(2, STATUS_UPDATED))
    rows = list(csv.DictReader(open(write_csv(tmp_path / "w.csv", sol), newline="")))
    assert [(r["time_gpst"][-12:], r["week"], r["tow_s"]) for r in rows] == [
        ("00:00:00.000", "2051", "0.000"), ("00:00:00.200", "2051", "0.200")]


def test_csv_time_utc_removes_the_leap_seconds(tmp_path):
    """time_utc is time_gpst less GPST - UTC (17 s in 2016, 18 s from 2017), the inserted second as 23:59:59.999."""
    time = utc_to_gps_s(np.array([(np.datetime64("2016-06-06T11:10:24.7") - np.datetime64("1980-01-06")) /
                                  np.timedelta64(1, "s"),
                                  (np.datetime64("2016-12-31T23:59:59.5") - np.datetime64("1980-01-06")) /
                                  np.timedelta64(1, "s")]))
    time = np.array([time[0], time[1], time[1] + 0.8, time[1] + 1.6])   # ... 23:59:60.3 and 2017-01-01 00:00:00.1
    pos = lla_to_ecef(np.radians(np.full(4, 52.5)), np.radians(np.full(4, 13.4)), np.full(4, 40.0)).reshape(4, 3)
    sol = Solution(backend="x", time_gps_s=time, pos_ecef_m=pos, cov_ecef_m2=np.tile(np.eye(3), (4, 1, 1)),
                   clock_m=np.zeros(4), n_used=np.full(4, 6), status=np.full(4, STATUS_UPDATED))
    rows = list(csv.DictReader(open(write_csv(tmp_path / "u.csv", sol), newline="")))
    assert [r["time_gpst"] for r in rows] == ["2016/06/06 11:10:41.700", "2017/01/01 00:00:16.500",
                                              "2017/01/01 00:00:17.300", "2017/01/01 00:00:18.100"]
    assert [r["time_utc"] for r in rows] == ["2016-06-06T11:10:24.700Z", "2016-12-31T23:59:59.500Z",
                                             "2016-12-31T23:59:59.999Z", "2017-01-01T00:00:00.100Z"]


def test_csv_velocity_in_the_local_frame_and_clock(tmp_path):
    """Robotics users asked for velocity: vel_e/n/u_m_s rotate vel_ecef_m_s into each epoch's ENU frame (empty for an
    estimator without velocity, and where no position); clock_m is the Solution's."""
    lat, lon = np.radians(52.5), np.radians(13.4)
    pos = np.tile(lla_to_ecef(lat, lon, 40.0), (3, 1))
    east = np.array([-np.sin(lon), np.cos(lon), 0.0])
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    north = np.cross(up, east)
    vel = np.array([10.0 * east + 1.0 * up, -3.0 * north, 10.0 * east])
    status = np.array([STATUS_UPDATED, STATUS_COASTED, STATUS_NONE])
    sol = Solution(backend="x", time_gps_s=1.0e9 + np.arange(3.0), pos_ecef_m=pos,
                   cov_ecef_m2=np.tile(np.eye(3), (3, 1, 1)),
                   clock_m=np.array([12.5, 13.0, 14.0]), n_used=np.array([6, 0, 0]), status=status, vel_ecef_m_s=vel)
    rows = list(csv.DictReader(open(write_csv(tmp_path / "v.csv", sol), newline="")))
    got = [(r["vel_e_m_s"], r["vel_n_m_s"], r["vel_u_m_s"], r["clock_m"]) for r in rows]
    assert got == [("10.0000", "0.0000", "1.0000", "12.5000"), ("0.0000", "-3.0000", "0.0000", "13.0000"),
                   ("", "", "", "")]
    without = Solution(backend="wls", time_gps_s=sol.time_gps_s, pos_ecef_m=pos, cov_ecef_m2=sol.cov_ecef_m2,
                       clock_m=sol.clock_m, n_used=sol.n_used, status=status)
    rows = list(csv.DictReader(open(write_csv(tmp_path / "w.csv", without), newline="")))
    assert [r["vel_e_m_s"] for r in rows] == ["", "", ""] and rows[0]["clock_m"] == "12.5000"


def test_read_pos_refuses_other_datums_and_geoid_heights(tmp_path):
    """rnx2rtkp's out-height=geodetic (above the geoid) or out-datum=tokyo would be read as WGS84 ellipsoidal."""
    for frame, words in (("WGS84/geodetic", "WGS84/geodetic"), ("Tokyo/ellipsoidal", "Tokyo/ellipsoidal")):
        path = tmp_path / "other.pos"
        path.write_text(RTKLIB_SNIPPET.replace("WGS84/ellipsoidal", frame))
        with pytest.raises(ValueError, match=f"other.pos:7: positions are {words}; only WGS84 with ellipsoidal"):
            read_pos(path)
    path.write_text(RTKLIB_SNIPPET)
    assert len(read_pos(path).time_gps_s) == 4


# ---------------------------------------------------------------- plots
def test_align_to_matches_on_tenth_of_second():
    sol, _ = _solution()
    sub = Solution(backend="rtk", time_gps_s=sol.time_gps_s[[2, 4, 7]] + 0.02, pos_ecef_m=sol.pos_ecef_m[[2, 4, 7]],
                   cov_ecef_m2=sol.cov_ecef_m2[[2, 4, 7]], clock_m=np.zeros(3), n_used=np.ones(3, int),
                   status=np.full(3, STATUS_UPDATED))
    al = align_to(sol.time_gps_s, sub)
    assert np.isfinite(al).all(axis=1).sum() == 3
    np.testing.assert_array_equal(al[[2, 4, 7]], sol.pos_ecef_m[[2, 4, 7]])


def test_align_to_a_receiver_faster_than_10_hz():
    """At 20 Hz each epoch gets the other solution's own epoch, not a neighbour's 0.05 s away, and an epoch the
    other lacks stays NaN."""
    t = 1.2e9 + 0.05 * np.arange(8)
    pos = np.column_stack([3785166.0 + np.arange(8), np.full(8, 900013.0), np.full(8, 5037378.0)])
    keep = np.array([0, 1, 2, 4, 5, 7])
    other = Solution(backend="rtk", time_gps_s=t[keep] + 0.001, pos_ecef_m=pos[keep],
                     cov_ecef_m2=np.tile(np.eye(3), (6, 1, 1)), clock_m=np.zeros(6), n_used=np.ones(6, int),
                     status=np.full(6, STATUS_UPDATED))
    al = align_to(t, other)
    np.testing.assert_array_equal(al[keep], pos[keep])
    assert np.isnan(al[[3, 6]]).all()
    # the tolerance is each epoch's own: two epochs 1 ms apart leave the others their 0.05 s, so RTKLIB's solutions
    # stamped 0.8 ms early (its receiver clock) still match them; a repeated epoch is one time, not a 0 s gap
    for offsets, sure in (([0.0, 1.0, 2.0, 2.001, 3.0], [0, 1, 4]), ([0.0, 1.0, 1.0, 2.0], [0, 3])):
        t, n = 1.2e9 + np.array(offsets), len(offsets)
        pos = np.column_stack([3785166.0 + np.arange(n), np.full(n, 900013.0), np.full(n, 5037378.0)])
        rtk = Solution(backend="rtk", time_gps_s=t - 0.0008, pos_ecef_m=pos, cov_ecef_m2=np.tile(np.eye(3), (n, 1, 1)),
                       clock_m=np.zeros(n), n_used=np.ones(n, int), status=np.full(n, STATUS_UPDATED))
        got = align_to(t, rtk)
        np.testing.assert_array_equal(got[sure], pos[sure])
    assert np.isfinite(got).all()                              # the repeated epoch is matched too (to one of its two)


def test_plot_solution(tmp_path):
    pytest.importorskip("matplotlib")
    sol, truth = _solution(40)
    rtk = read_pos(write_pos(tmp_path / "r.pos", sol))
    files = plot_solution(tmp_path / "figs", sol, truth, extra_solutions={"rtklib": rtk})
    assert [f.name for f in files] == ["track.png", "errors.png", "cdf.png", "quality.png"]
    for f in files:
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f.stat().st_size > 5000
    no_truth = plot_solution(tmp_path / "figs2", sol, prefix="ekf_")
    assert [f.name for f in no_truth] == ["ekf_track.png", "ekf_quality.png"]


def test_a_position_far_from_the_earth_is_written_without_one(tmp_path):
    """Review: a diverged estimate at the Earth's centre was written as latitude 180, height -6378137 m (in the .pos,
    the GeoJSON, against RFC 7946's [-90, 90], and the KML), and one at 1e12 m broke the .pos columns."""
    from dataclasses import replace

    from lfgnss.outputs import read_pos, write_csv, write_geojson, write_kml, write_pos

    sol, _ = _solution()
    pos = sol.pos_ecef_m.copy()
    pos[3], pos[7] = 0.0, 1e12
    far = replace(sol, pos_ecef_m=pos)
    for writer, name in ((write_pos, "a.pos"), (write_geojson, "a.geojson"), (write_kml, "a.kml")):
        with pytest.warns(UserWarning, match=rf"{writer.__name__} {tmp_path / name}: 2 epoch\(s\) of 'ekf' have a "
                                             r"position far from the Earth's surface \(first: epoch 3, 0 m from its "
                                             r"centre, .*written without one"):
            writer(tmp_path / name, far)
    keep = sol.has_position()
    keep[[3, 7]] = False
    np.testing.assert_allclose(read_pos(tmp_path / "a.pos").pos_ecef_m, sol.pos_ecef_m[keep], atol=1e-3)
    geometries = [f["geometry"] for f in json.loads((tmp_path / "a.geojson").read_text())["features"]]
    lats = [c[1] for g in geometries for c in (g["coordinates"] if g["type"] in ("LineString", "MultiPoint")
                                               else [c for line in g["coordinates"] for c in line])]
    assert len(lats) == keep.sum() and all(52 < lat < 53 for lat in lats)
    write_csv(tmp_path / "a.csv", far)                      # the estimate stays in ECEF; no geodetic coordinates
    rows = list(csv.DictReader((tmp_path / "a.csv").open()))
    assert rows[3]["x_m"] == "0.0000" and rows[3]["lat_deg"] == "" and rows[4]["lat_deg"] != ""
