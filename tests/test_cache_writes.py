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
