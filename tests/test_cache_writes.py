"""Files that may be written by two processes at once (cache entries, model files) are renamed into place whole."""
import multiprocessing
import os
import warnings

import numpy as np
import pytest

from lfgnss.paths import replace_atomically
from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS


def test_a_write_that_fails_keeps_the_file_there_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "entry.npz"
    path.write_bytes(b"old")

    def fail(tmp):
        tmp.write_bytes(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        replace_atomically(path, fail)
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["entry.npz"]


def test_two_writers_of_one_file_each_write_a_whole_file_of_their_own(tmp_path):
    """A writer that starts while another is mid-write (two processes filling one cache entry) gets its own temporary
    file: with one fixed temporary name the second would truncate the first's half-written file, and the first's
    rename would put the second's half file in place."""
    path = tmp_path / "entry.npz"
    seen = []

    def inner(tmp):
        seen.append(tmp)
        np.savez(tmp, x=np.arange(3))

    def outer(tmp):
        seen.append(tmp)
        np.savez(tmp, x=np.arange(1000))
        replace_atomically(path, inner)            # the other process finishes first
        assert tmp.exists()                         # ours is untouched, still to be renamed

    replace_atomically(path, outer)
    assert seen[0] != seen[1] and all(t.parent == tmp_path and t.name.startswith(".entry.") for t in seen)
    with np.load(path) as z:
        np.testing.assert_array_equal(z["x"], np.arange(1000))
    assert [p.name for p in tmp_path.iterdir()] == ["entry.npz"]


def _load_both(cache: str) -> tuple:
    os.environ["LFGNSS_CACHE"] = cache
    from lfgnss.navigation import load_nav
    from lfgnss.rinex import load_obs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        obs = load_obs(SAMPLE_OBS)
        nav = load_nav(SAMPLE_NAV)
    return obs.pr_m.shape, int(np.isfinite(obs.pr_m).sum()), len(nav.kepler) + len(nav.glonass)


def test_processes_parsing_one_file_at_once_share_the_cache(tmp_path):
    """Four processes parse the bundled drive into one empty cache at the same time: each gets the whole parse, and
    the cache holds one whole entry per file (no temporary left behind)."""
    cache = tmp_path / "cache"
    with multiprocessing.get_context("spawn").Pool(4) as pool:
        results = pool.map(_load_both, [str(cache)] * 4)
    assert len(set(results)) == 1 and results[0][1] > 0
    entries = sorted(p.relative_to(cache).parts[0] for p in cache.rglob("*") if p.is_file())
    assert entries == ["nav", "obs"], entries
    assert _load_both(str(cache)) == results[0]     # and it reads back


def test_an_error_names_the_file_asked_for_not_the_temporary(tmp_path):
    (tmp_path / "out.csv").mkdir()                   # a folder where the file goes: the rename fails
    with pytest.raises(OSError) as info:
        replace_atomically(tmp_path / "out.csv", lambda tmp: tmp.write_text("x"))
    assert info.value.filename == str(tmp_path / "out.csv") and ".partial" not in str(info.value)
    with pytest.raises(OSError) as info:             # the temporary itself cannot be made: a folder that is not there
        replace_atomically(tmp_path / "no-folder" / "out.csv", lambda tmp: tmp.write_text("x"))
    assert info.value.filename == str(tmp_path / "no-folder" / "out.csv")
    assert str(info.value) == f"[Errno 2] No such file or directory: '{tmp_path / 'no-folder' / 'out.csv'}'"  # no "-> None"


def _parse_fresh(monkeypatch, cache) -> tuple:
    """The bundled drive's obs and nav, parsed with ``$LFGNSS_CACHE`` = ``cache``, and the warnings raised."""
    from lfgnss import paths
    from lfgnss.navigation import load_nav
    from lfgnss.rinex import load_obs

    monkeypatch.setenv("LFGNSS_CACHE", str(cache))
    monkeypatch.setattr(paths, "_CACHE_WARNED", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        obs, nav = load_obs(SAMPLE_OBS), load_nav(SAMPLE_NAV)
    return obs, nav, [str(w.message) for w in caught if issubclass(w.category, paths.CacheWarning)]


def test_an_unusable_cache_folder_is_one_warning_and_the_files_are_still_read(tmp_path, monkeypatch):
    (tmp_path / "a-file").write_text("x")
    obs, nav, warned = _parse_fresh(monkeypatch, tmp_path / "a-file")
    assert np.isfinite(obs.pr_m).sum() > 0 and len(nav.kepler) > 0
    assert warned == [f"{tmp_path / 'a-file'}: cannot use the cache (File exists); going on without it, so files are "
                      "parsed again on every run (set $LFGNSS_CACHE to a writable folder)"]


def test_a_folder_in_a_cache_entrys_place_is_passed_over_with_a_warning(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    first, _, warned = _parse_fresh(monkeypatch, cache)
    assert warned == []
    (entry,) = (cache / "obs").iterdir()
    entry.unlink()
    (entry / "inside").mkdir(parents=True)           # a folder (not empty) where the entry goes
    again, _, warned = _parse_fresh(monkeypatch, cache)
    np.testing.assert_array_equal(again.pr_m, first.pr_m)
    assert len(warned) == 1 and warned[0].startswith(f"{entry}: cannot use the cache (")


def test_a_damaged_entry_is_rebuilt_and_stale_temporaries_are_cleared(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    first, _, _ = _parse_fresh(monkeypatch, cache)
    (entry,) = (cache / "obs").iterdir()
    entry.write_bytes(b"not an npz")
    stale, fresh = cache / "obs" / ".x.1-ab.partial.npz", cache / "obs" / ".y.2-cd.partial.npz"
    stale.write_bytes(b"left by a killed run")
    fresh.write_bytes(b"another process still writing")
    os.utime(stale, (0, 0))
    again, _, warned = _parse_fresh(monkeypatch, cache)
    np.testing.assert_array_equal(again.pr_m, first.pr_m)
    assert warned == [] and sorted(p.name for p in (cache / "obs").iterdir()) == sorted([entry.name, fresh.name])
    with np.load(entry) as z:                        # rebuilt whole
        assert z["pr_m"].shape == first.pr_m.shape


def test_cache_false_makes_no_cache_folder(tmp_path, monkeypatch):
    from lfgnss.rinex import load_obs

    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        load_obs(SAMPLE_OBS, cache=False)
    assert not (tmp_path / "cache").exists()


def test_an_output_is_written_through_a_link_keeps_its_mode_and_may_have_a_long_name(tmp_path):
    from lfgnss.paths import write_output

    real = tmp_path / "real.pos"
    real.write_text("old")
    os.chmod(real, 0o600)
    (tmp_path / "link.pos").symlink_to(real)
    write_output(tmp_path / "link.pos", lambda p: p.write_text("new"))
    assert (tmp_path / "link.pos").is_symlink() and real.read_text() == "new"
    assert real.stat().st_mode & 0o777 == 0o600
    long_name = tmp_path / ("x" * 240 + ".csv")                     # 244 characters: the system allows 255
    write_output(long_name, lambda p: p.write_text("whole"))
    assert long_name.read_text() == "whole" and len(list(tmp_path.iterdir())) == 3


def test_an_output_that_is_a_fifo_is_written_in_place(tmp_path):
    """A FIFO (or /dev/stdout) is written, not replaced by a regular file."""
    import threading

    from lfgnss.paths import write_output

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    write_output(fifo, lambda p: p.write_text("through the pipe"))
    reader.join(timeout=10)
    assert got == ["through the pipe"] and fifo.is_fifo()


def test_an_error_names_the_output_as_given(tmp_path):
    from lfgnss.paths import write_output

    (tmp_path / "real").mkdir()
    (tmp_path / "real" / "out.csv").mkdir()                        # a folder where the file goes
    (tmp_path / "link").symlink_to(tmp_path / "real")
    with pytest.raises(OSError) as info:
        write_output(tmp_path / "link" / "out.csv", lambda p: p.write_text("x"))
    assert info.value.filename == str(tmp_path / "link" / "out.csv")


def test_a_cache_folder_removed_during_a_run_is_made_again(tmp_path, monkeypatch):
    import shutil

    cache = tmp_path / "cache"
    _parse_fresh(monkeypatch, cache)
    shutil.rmtree(cache / "obs")
    from lfgnss import paths

    monkeypatch.setattr(paths, "_CACHE_WARNED", set())
    target = paths.cache_file("obs", "x.npz")
    shutil.rmtree(cache / "obs")                                   # between the lookup and the store
    with warnings.catch_warnings():
        warnings.simplefilter("error", paths.CacheWarning)
        paths.store_cached(target, lambda p: np.savez(p, x=np.arange(2)))
    assert target.is_file()
