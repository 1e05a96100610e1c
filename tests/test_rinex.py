"""RINEX observation reading: bundled and shared real files, georinex cross-check, cache, bad input."""
import gzip
import shutil
import warnings

import numpy as np
import pytest

from lfgnss.errors import RinexError
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
    np.testing.assert_allclose(ours.time_gps_s, ref.time_gps_s, atol=1.1e-3)  # georinex keeps ms for RINEX 2
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
