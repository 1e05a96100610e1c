"""RINEX observation reading: bundled and shared real files, georinex cross-check, cache, bad input."""
import gzip
import shutil
import warnings

import numpy as np
import pytest

from lfgnss.errors import RinexError
from lfgnss.observations import Observations
from lfgnss.paths import shared_data_dir
from lfgnss.rinex import RinexWarning, load_obs
from lfgnss.solve import SAMPLE_OBS

SHARED_OBS = {
    "hk-tst-2019": "urbannav-hk-tst-20190428/COM3_190428_124409.obs",
    "hk-tst-static-2020": "hk-tst-static-20200603/2020_06_03_TST_03.obs",
    "berlin-pp": "smartloc-berlin-potsdamer-platz-rinex/Berlin_Potsdamer_Platz.obs",
}


def shared(rel: str):
    path = shared_data_dir() / rel
    if not path.exists():
        pytest.skip(f"shared data not found at {path}")
    return path


@pytest.fixture(autouse=True)
def _private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))


def test_bundled_rinex2_gzip():
    obs = load_obs(SAMPLE_OBS)
    assert obs.version == 2.11
    assert len(obs) == 1375
    assert set(obs.systems) == {"G", "R"}
    assert obs.codes == {"G": "C1", "R": "C1"}
    assert np.all(np.diff(obs.time_gps_s) > 0)
    # first epoch 2016-06-06 11:10:41.7 GPST = week 1900, TOW 126641.7
    assert obs.time_gps_s[0] == pytest.approx(1900 * 604800 + 126641.7, abs=1e-6)
    finite = np.isfinite(obs.pr_m)
    assert 19e6 < np.nanmedian(obs.pr_m) < 26e6
    assert np.all(np.isfinite(obs.cn0_dbhz[finite]))


def _first_epochs(path, tmp_path, n_epochs: int):
    """A copy of a RINEX 3 file cut after n_epochs epochs (keeps georinex's slow path short)."""
    lines = path.read_text().split("\n")
    starts = [i for i, ln in enumerate(lines) if ln.startswith(">")]
    cut = tmp_path / path.name
    cut.write_text("\n".join(lines[: starts[n_epochs]]) + "\n")
    return cut


@pytest.mark.parametrize("dataset", ["hk-tst-2019", "hk-tst-static-2020", "berlin-pp"], ids=str)
def test_matches_georinex(dataset, tmp_path):
    """Our vectorised record reader gives exactly georinex's numbers (georinex is 20-100x slower)."""
    path = shared(SHARED_OBS[dataset])
    if dataset != "berlin-pp":
        path = _first_epochs(path, tmp_path, 150)
    ours = load_obs(path, cache=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = load_obs(path, cache=False, engine="georinex")
    np.testing.assert_array_equal(ours.sv, ref.sv)
    np.testing.assert_allclose(ours.time_gps_s, ref.time_gps_s, rtol=0, atol=1.1e-3)  # georinex keeps ms for RINEX 2
    for name in ("pr_m", "cn0_dbhz", "doppler_hz"):
        np.testing.assert_array_equal(getattr(ours, name), getattr(ref, name), err_msg=name)


def test_rinex302_beidou_b1i_code():
    obs = load_obs(shared(SHARED_OBS["hk-tst-static-2020"]))
    assert obs.codes["C"] == "C1I"       # RINEX 3.02 names B1I 'C1I'
    assert obs.codes["G"] == "C1C"
    assert {"G", "R", "E", "J", "C"} <= set(obs.systems)


def test_rinex303_beidou_code():
    obs = load_obs(shared(SHARED_OBS["hk-tst-2019"]))
    assert obs.codes == {"G": "C1C", "C": "C2I"}


def test_cache_round_trip_and_key_by_content(tmp_path):
    src = tmp_path / "a.obs.gz"
    shutil.copy(SAMPLE_OBS, src)
    first = load_obs(src)
    second = load_obs(src)
    np.testing.assert_array_equal(first.pr_m, second.pr_m)
    assert list((tmp_path / "cache" / "obs").glob("*.npz"))
    text = gzip.decompress(src.read_bytes()).decode()
    changed = tmp_path / "b.obs"
    changed.write_text(text.replace("49.000", "48.000", 1))
    assert load_obs(changed).cn0_dbhz[0, np.argmax(first.sv == "G12")] == 48.0


def test_a_cache_entry_of_the_right_key_but_wrong_shapes_is_rebuilt(tmp_path):
    """Defect: an entry whose arrays did not fit together was trusted, failing far away as an IndexError."""
    src = tmp_path / "a.obs.gz"
    shutil.copy(SAMPLE_OBS, src)
    first = load_obs(src)
    (entry,) = (tmp_path / "cache" / "obs").glob("*.npz")
    with np.load(entry) as z:
        arrays = dict(z)
    arrays["pr_m"] = arrays["pr_m"][:, :-1]                    # one satellite short
    with open(entry, "wb") as fh:
        np.savez(fh, **arrays)
    again = load_obs(src)
    np.testing.assert_array_equal(again.pr_m, first.pr_m)
    with pytest.raises(ValueError, match=r"Observations of x.obs: .* pr_m \(2, 2\)"):
        Observations("x.obs", 3.0, np.zeros(2), np.array(["G01", "G02", "G03"]), np.zeros((2, 2)),
                     np.zeros((2, 3)), np.zeros((2, 3)), {}, np.zeros(3))


def _plain_sample(tmp_path):
    text = gzip.decompress(SAMPLE_OBS.read_bytes()).decode()
    return text, tmp_path / "s.obs"


def test_empty_file_error(tmp_path):
    path = tmp_path / "empty.obs"
    path.write_text("")
    with pytest.raises(RinexError, match="empty.obs: file is empty"):
        load_obs(path)


def test_nav_file_given_as_obs(tmp_path):
    path = tmp_path / "nav.obs"
    path.write_text(gzip.decompress((SAMPLE_OBS.parent / "brdc1580.16n.gz").read_bytes()).decode())
    with pytest.raises(RinexError, match="not an observation file"):
        load_obs(path)


def test_garbage_pseudorange_skips_record_with_line(tmp_path):
    text, path = _plain_sample(tmp_path)
    lines = text.split("\n")
    bad_line = 15  # first record of the first epoch (1-based line numbers)
    lines[bad_line - 1] = "  19834x89.652 8" + lines[bad_line - 1][16:]
    path.write_text("\n".join(lines))
    with pytest.warns(RinexWarning):
        obs = load_obs(path, cache=False)
    assert any(w.startswith(f"{path}:{bad_line}:") for w in obs.warnings)
    assert len(obs) == 1375
    assert np.isnan(obs.pr_m[0, np.argmax(obs.sv == "G12")])


def test_truncated_file_keeps_complete_epochs(tmp_path):
    text, path = _plain_sample(tmp_path)
    lines = text.split("\n")
    path.write_text("\n".join(lines[:100]))
    with pytest.warns(RinexWarning):
        obs = load_obs(path, cache=False)
    assert 1 <= len(obs) < 10
    assert any("truncated" in w for w in obs.warnings)


@pytest.mark.parametrize("keep", [5, 12, 29], ids=lambda k: f"{k}chars")
@pytest.mark.parametrize("where", ["end", "middle"])
def test_epoch_line_cut_short_costs_no_complete_epoch(tmp_path, keep, where):
    """A RINEX 2 epoch line cut short is not read as an extra record line of the epoch before it."""
    text, path = _plain_sample(tmp_path)
    lines = text.split("\n")
    full = load_obs(SAMPLE_OBS)
    epoch_lines = [k for k, ln in enumerate(lines) if ln.startswith(" 16  6  6 ")]
    cut = epoch_lines[20]                              # 0-based index of the 21st epoch line
    damaged = lines[:cut] + [lines[cut][:keep]] + (lines[cut + 1:] if where == "middle" else [])
    path.write_text("\n".join(damaged))
    with pytest.warns(RinexWarning):
        obs = load_obs(path, cache=False)
    assert obs.warnings[0].startswith(f"{path}:{cut + 1}: unreadable epoch line")
    np.testing.assert_array_equal(obs.time_gps_s[:20], full.time_gps_s[:20])   # the 20 epochs before it stay
    if where == "end":
        assert len(obs) == 20
    else:                                              # only the damaged epoch is lost
        np.testing.assert_array_equal(obs.time_gps_s[20:], full.time_gps_s[21:len(obs) + 1])


def test_crlf_line_endings(tmp_path):
    text, path = _plain_sample(tmp_path)
    path.write_bytes(text.replace("\n", "\r\n").encode())
    ref = load_obs(SAMPLE_OBS)
    np.testing.assert_array_equal(load_obs(path, cache=False).pr_m, ref.pr_m)


@pytest.mark.parametrize("kind", ["hatanaka", "hatanaka+gzip"], ids=str)
def test_hatanaka_compressed(kind, tmp_path):
    hatanaka = pytest.importorskip("hatanaka")
    crx = hatanaka.rnx2crx(gzip.decompress(SAMPLE_OBS.read_bytes()))
    assert crx.startswith(b"1.0") and b"COMPACT RINEX" in crx[:80]
    path = tmp_path / ("s.16d" if kind == "hatanaka" else "s.16d.gz")
    path.write_bytes(crx if kind == "hatanaka" else gzip.compress(crx))
    np.testing.assert_array_equal(load_obs(path, cache=False).pr_m, load_obs(SAMPLE_OBS).pr_m)


# ------------------------------------------------------------------ time systems of the epoch time tags
FIRST_EPOCH_GPS_S = 1900 * 604800 + 126641.7     # the sample's first epoch, 2016-06-06 11:10:41.7 GPST


def _sample_with_header(tmp_path, system_letter: str, time_system: str):
    """The bundled RINEX 2.11 sample with another satellite system letter and TIME OF FIRST OBS time system."""
    text, path = _plain_sample(tmp_path)
    lines = text.split("\n")
    lines[0] = lines[0][:40] + system_letter + lines[0][41:]
    k = next(i for i, ln in enumerate(lines) if "TIME OF FIRST OBS" in ln)
    lines[k] = lines[k][:48] + f"{time_system:<3s}" + lines[k][51:]
    path.write_text("\n".join(lines))
    return path


@pytest.mark.parametrize("letter, time_system, shift_s", [
    ("M", "GLO", 17.0),    # GLO time tags are UTC(SU): GPST = UTC + 17 s in 2016 (was 3 h early: -10800 + 17)
    ("R", "", 17.0),       # pure GLONASS file, time system left blank: GLO by default (RINEX 2.11/3.0x)
    ("C", "", 14.0),       # pure BeiDou file, blank: BDT (GPST = BDT + 14 s)
    ("M", "", 0.0),        # mixed or GPS file, blank: GPS time
    (" ", "", 0.0),
    ("M", "GPS", 0.0),
    ("M", "BDT", 14.0),
], ids=["GLO", "R-blank", "C-blank", "M-blank", "blank-blank", "GPS", "BDT"])
def test_epoch_time_system(tmp_path, letter, time_system, shift_s):
    path = _sample_with_header(tmp_path, letter, time_system)
    obs = load_obs(path, cache=False)
    assert obs.time_gps_s[0] == pytest.approx(FIRST_EPOCH_GPS_S + shift_s, abs=1e-6)
    np.testing.assert_array_equal(obs.pr_m, load_obs(SAMPLE_OBS).pr_m)


def test_glo_time_system_georinex_engine_agrees(tmp_path):
    """engine="georinex" applies the same time-system conversion (it used to ignore GLO and BDT)."""
    lines = gzip.decompress(SAMPLE_OBS.read_bytes()).decode().split("\n")
    k = next(i for i, ln in enumerate(lines) if "TIME OF FIRST OBS" in ln)
    lines[k] = lines[k][:48] + "GLO" + lines[k][51:]
    path = tmp_path / "glo.obs"
    cut = [i for i, ln in enumerate(lines) if ln.startswith(" 16  6  6 ")][10]
    path.write_text("\n".join(lines[:cut]) + "\n")                 # header and the first 10 epochs
    ours = load_obs(path, cache=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = load_obs(path, cache=False, engine="georinex")
    np.testing.assert_allclose(ref.time_gps_s, ours.time_gps_s, rtol=0, atol=1.1e-3)
    assert ours.time_gps_s[0] == pytest.approx(FIRST_EPOCH_GPS_S + 17.0, abs=1e-6)


# ------------------------------------------------------------------ RINEX 3 code choice (synthetic files)
def _rinex3(path, version: str, types: dict[str, str], time_system: str = "GPS", letter: str = "M",
            n_epochs: int = 3):
    """A small RINEX 3 file: per system the given types, satellites {system}01..03, all fields filled
    (pseudorange type k of satellite s: 2e7 + 1000 s + k, so the column read can be told)."""
    head = [f"{version:>9s}           OBSERVATION DATA    {letter:<20s}RINEX VERSION / TYPE"]
    for s, t in types.items():
        head.append(f"{s}  {len(t.split()):3d} {t}".ljust(60) + "SYS / # / OBS TYPES")
    head.append(f"  2020     6     3     3     2    9.0000000     {time_system:<3s}".ljust(60) + "TIME OF FIRST OBS")
    head.append(" " * 60 + "END OF HEADER")
    body = []
    for e in range(n_epochs):
        svs = [f"{s}{p:02d}" for s in types for p in (1, 2, 3)]
        body.append(f"> 2020 06 03 03 02{9.0 + e:11.7f}  0{len(svs):3d}")
        for sv in svs:
            names = types[sv[0]].split()
            vals = [(2e7 + 1000 * int(sv[1:]) + k) if n[0] == "C" else 45.0 if n[0] == "S" else 100.0
                    for k, n in enumerate(names)]
            body.append(sv + "".join(f"{v:14.3f}  " for v in vals).rstrip())
    path.write_text("\n".join(head + body) + "\n")
    return path


def test_rinex3_glo_time_system_is_utc(tmp_path):
    gps = load_obs(_rinex3(tmp_path / "gps.rnx", "3.04", {"G": "C1C S1C"}, "GPS"), cache=False)
    glo = load_obs(_rinex3(tmp_path / "glo.rnx", "3.04", {"G": "C1C S1C"}, "GLO"), cache=False)
    blank_r = load_obs(_rinex3(tmp_path / "r.rnx", "3.04", {"R": "C1C S1C"}, "", letter="R: GLONASS"), cache=False)
    assert glo.time_gps_s[0] - gps.time_gps_s[0] == pytest.approx(18.0)      # 2020: GPST - UTC = 18 s
    assert blank_r.time_gps_s[0] - gps.time_gps_s[0] == pytest.approx(18.0)


@pytest.mark.parametrize("version, types, code", [
    ("3.02", "C1I L1I D1I S1I", "C1I"),            # RINEX 3.02 label of B1I
    ("3.02", "C2I L2I D2I S2I", "C2I"),            # B1I labelled as in 3.01/3.03 in a 3.02 file (RTKLIB writes these)
    ("3.02", "C1X C2I", "C2I"),                    # band 2 present: C1X would be 3.03's B1C, not taken
    ("3.02", "C1X L1X", "C1X"),                    # genuine 3.02: C1X is B1I
    ("3.03", "C2I L2I D2I S2I", "C2I"),
    ("3.04", "C2X S2X", "C2X"),
    ("3.04", "C2Q S2Q", "C2Q"),
    ("3.04", "C1P C1X C2I S2I", "C2I"),            # B1C and B1I: B1I
    ("3.04", "C1I S1I", "C1I"),                    # 3.02 label in a later file: still B1I (B1C has no I code)
], ids=lambda v: v.replace(" ", "_") if isinstance(v, str) else v)
def test_beidou_b1i_codes(tmp_path, version, types, code):
    obs = load_obs(_rinex3(tmp_path / "c.rnx", version, {"G": "C1C S1C", "C": types}), cache=False)
    assert obs.codes == {"G": "C1C", "C": code}
    k = types.split().index(code)
    assert obs.pr_m[0, list(obs.sv).index("C02")] == 2e7 + 2000 + k
    assert not obs.warnings


@pytest.mark.parametrize("types", ["C1P L1P S1P", "C1D C1X S1X", "C1X S1X"])
def test_beidou_b1c_is_not_taken_for_b1i(tmp_path, types):
    """B1C (RINEX 3.03+ band 1) has other group delays than B1I (TGD1): not supported, said so, never used as B1I."""
    path = _rinex3(tmp_path / "c.rnx", "3.04", {"G": "C1C S1C", "C": types})
    with pytest.warns(RinexWarning, match="B1C, not supported"):
        obs = load_obs(path, cache=False)
    assert obs.codes == {"G": "C1C"} and set(obs.systems) == {"G"}
    assert obs.warnings[0].startswith(f"{path}: C has no supported pseudorange type")


# ------------------------------------------------------------------ RINEX 2 C1 / P1
def _sample_c1_p1(tmp_path, blank: list[int]):
    """The sample with P1 (a copy of C1) in place of L1, and C1 blanked on the given 1-based record lines."""
    text, path = _plain_sample(tmp_path)
    lines = text.split("\n")
    lines[8] = lines[8].replace("    L1", "    P1")
    for i in range(12, len(lines)):
        ln = lines[i]
        if ln[:1] == " " and ln[1:3] != "16" and ln.strip() and not ln.startswith(" " * 32):
            lines[i] = ln[:16] + ln[:16] + ln[32:]
    for no in blank:
        lines[no - 1] = " " * 16 + lines[no - 1][16:]
    path.write_text("\n".join(lines))
    return path


def test_rinex2_p1_stands_in_where_c1_is_blank(tmp_path):
    """RINEX 2 with C1 and P1: a record with C1 blank uses P1 (as RTKLIB), with a note; before, it was dropped."""
    ref = load_obs(SAMPLE_OBS)
    g12 = np.argmax(ref.sv == "G12")
    same = load_obs(_sample_c1_p1(tmp_path, []), cache=False)
    assert same.codes == {"G": "C1", "R": "C1"} and not same.warnings
    np.testing.assert_array_equal(same.pr_m, ref.pr_m)
    (tmp_path / "s.obs").unlink()
    path = _sample_c1_p1(tmp_path, [15, 36])          # G12 in the first two epochs
    with pytest.warns(RinexWarning, match=r"C1 blank \(or 0\), P1 used instead"):
        obs = load_obs(path, cache=False)
    np.testing.assert_array_equal(obs.pr_m, ref.pr_m)
    assert obs.pr_m[0, g12] == 19834589.652
    assert obs.warnings == (f"{path}:15: C1 blank (or 0), P1 used instead in 2 record(s) of 1 satellite(s) (G12); "
                            f"P1 differs from C1 by the satellite's P1-C1 code bias (typically decimetres), "
                            f"not corrected",)
    assert obs.codes == {"G": "C1", "R": "C1"}


def test_rinex2_c1_blank_without_p1_stays_missing(tmp_path):
    text, path = _plain_sample(tmp_path)
    lines = text.split("\n")
    lines[14] = " " * 16 + lines[14][16:]
    path.write_text("\n".join(lines))
    obs = load_obs(path, cache=False)
    assert np.isnan(obs.pr_m[0, np.argmax(obs.sv == "G12")]) and not obs.warnings
