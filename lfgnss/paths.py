"""Where lfgnss finds shared benchmark data, bundled data and its cache."""
from __future__ import annotations

import contextlib
import gzip
import hashlib
import os
import secrets
import shutil
import stat
import time
import warnings
import zlib
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeVar

from .errors import InputError

T = TypeVar("T")

PACKAGE_DIR = Path(__file__).resolve().parent
REPO_DIR = PACKAGE_DIR.parent
MODEL_PREFIX = "lfgnss-"          # a bundled model file is lfgnss-NAME.npz, and NAME is how users pick it


def names_something(path: str | os.PathLike) -> bool:
    """Whether ``path`` exists; a name too long or with a NUL names nothing (``Path.exists`` raises on those)."""
    try:
        return Path(path).exists()
    except (OSError, ValueError):
        return False


def shared_data_dir() -> Path:
    """Benchmark data folder: $LFGNSS_SHARED_DATA, else ``../shared/data`` beside the checkout."""
    env = os.environ.get("LFGNSS_SHARED_DATA")
    return Path(env) if env else REPO_DIR.parent / "shared" / "data"


def bundled_data_dir() -> Path:
    """Small redistributable sample shipped inside the package."""
    return PACKAGE_DIR / "data"


def default_model_path() -> Path:
    """The bundled LF-GNSS model file, which ``python -m lfgnss.solve`` and ``estimators.create("ekf")`` use."""
    return bundled_data_dir() / "model" / f"{MODEL_PREFIX}default.npz"


def bundled_models() -> dict[str, Path]:
    """The model files shipped with lfgnss by name: ``default``, ``hk-tst-2019``, ... (file ``lfgnss-NAME.npz``)."""
    folder = bundled_data_dir() / "model"
    return {p.stem.removeprefix(MODEL_PREFIX): p for p in sorted(folder.glob(f"{MODEL_PREFIX}*.npz"))}


def may_name_a_bundled_model(model: str | os.PathLike) -> bool:
    """Whether ``model`` has the form of a bundled model's name: no folder and no suffix (``"hk-tst-2019"``)."""
    path = Path(model)
    return not path.suffix and len(path.parts) == 1


def model_path(model: str | os.PathLike) -> Path:
    """A model file: ``model`` itself where that path exists or has a folder or suffix, else the bundled model of
    that name (``"hk-tst-2019"``: lfgnss-hk-tst-2019.npz), else ``model`` as it is."""
    path = Path(model)
    if names_something(path) or not may_name_a_bundled_model(path):
        return path
    return bundled_models().get(path.name, path)


def file_hashes(paths: Iterable[str | os.PathLike], *, content: bool = True) -> dict[str, str]:
    """``file_hash`` of each file, by file name."""
    return {Path(path).name: file_hash(path, content=content) for path in paths}


def file_hash(path: str | os.PathLike, *, content: bool = True) -> str:
    """SHA-256 (16 hex digits) of a file: of its content, a gzip file's decompressed, so that a file and its
    compressed copy are one (the bundled drive's ``.obs.gz`` is berlin-pp's ``.obs``); ``content=False``: of its
    bytes as they are (gzip data that do not decompress whole count so too)."""
    def digest(opener) -> str:
        h = hashlib.sha256()
        with opener(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        return h.hexdigest()[:16]

    packed = content and is_gzip(path)
    try:
        return digest(gzip.open if packed else open)
    except (OSError, EOFError, zlib.error):
        if not packed:
            raise
        return digest(open)


def is_gzip(path: str | os.PathLike) -> bool:
    """Whether the file starts with gzip's magic bytes (whatever its name)."""
    with open(path, "rb") as raw:
        return raw.read(2) == b"\x1f\x8b"


def file_digests(paths: Iterable[str | os.PathLike]) -> set[str]:
    """Every SHA-256 (16 hex digits) a record may hold of these files (``file_hashes``): of their content, and of a
    gzip file's bytes as they are too (records of before session 49 hashed those); a plain file is read once."""
    paths = list(paths)
    return {*file_hashes(paths).values(), *file_hashes([p for p in paths if is_gzip(p)], content=False).values()}


def cache_dir() -> Path:
    """Cache for parsed RINEX and built datasets: $LFGNSS_CACHE, else ~/.cache/lfgnss."""
    env = os.environ.get("LFGNSS_CACHE")
    path = Path(env) if env else Path.home() / ".cache" / "lfgnss"
    path.mkdir(parents=True, exist_ok=True)
    return path


def replace_atomically(path: Path, write: Callable[[Path], object]) -> None:
    """``write(tmp)`` to a temporary file beside ``path``, then renamed onto it (``os.replace``, atomic).

    A run killed mid-write keeps the previous file whole, and readers never see half a file. The temporary name is
    ``.STEM.PID-RANDOM.partial.SUFFIX``, its own for each write, so two processes filling one cache entry at once
    (parallel tests, two solves of one file) each rename a whole file instead of writing into each other's; its
    stem is cut to 100 characters, so a name near the system's limit still has room for it. A file replaced keeps
    its permissions. An OSError names ``path``, not the temporary file the user never asked for.
    """
    tmp = path.with_name(f".{path.stem[:100]}.{os.getpid()}-{secrets.token_hex(4)}.partial{path.suffix}")
    try:
        write(tmp)
        with open(tmp, "r+b") as fh:            # on the disk before the rename, so a power cut leaves one or the other
            os.fsync(fh.fileno())
        with contextlib.suppress(OSError):
            if path.is_file():
                shutil.copymode(path, tmp)
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(err, OSError) and err.filename in (str(tmp), tmp):
            raise type(err)(err.errno, err.strerror, str(path)) from None      # no "-> TARGET" of os.replace's
        raise


def write_output(path: str | os.PathLike, write: Callable[[Path], object]) -> Path:
    """``write`` an output file the user named, whole where it can be (:func:`replace_atomically`); the path written.

    A symbolic link is written through (the file it names is replaced, the link kept). Where the path is no regular
    file (``/dev/stdout``, a FIFO) or its folder takes no new file but the file itself may be written, ``write``
    writes it in place: a rename would replace the device or fail.
    """
    target = Path(os.path.realpath(path))
    try:
        try:
            mode = target.stat().st_mode
        except OSError:                         # not there yet (or not to be looked at): the rename says why
            mode = None
        if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
            write(target)
            return target
        try:
            replace_atomically(target, write)
        except PermissionError:
            if not (target.is_file() and os.access(target, os.W_OK)):
                raise
            write(target)                       # a folder that takes no new file, a file one may write
    except OSError as err:
        if err.filename == str(target):        # the name the user gave, not the one its links resolve to
            err.filename = str(path)
        raise
    return target


def check_output_folder(out: str | os.PathLike) -> None:
    """InputError naming ``--out`` unless it is, or can be made, a folder that takes files; it makes nothing.

    The first folder of ``out`` and its parents that exists is tried with a file of its own that is removed at once,
    so a read-only disk, or a folder to be made where one may not write, is said before any work rather than when
    the outputs are written. An existing ``out`` without write permission passes: the files in it one may write are
    rewritten in place (:func:`write_output`), and each other one is an error of its own after the run.
    """
    out = Path(out)
    try:
        if out.exists() and not out.is_dir():
            raise InputError(out, "--out is a file, not a folder")
        there = next(p for p in (out, *out.parents) if p.exists())
        if not there.is_dir():
            raise InputError(out, "cannot create the output folder (Not a directory)")
    except OSError as err:              # a name too long, a missing disk
        raise InputError(out, f"cannot create the output folder ({err.strerror or err})") from None
    probe = there / f".lfgnss-write-test.{os.getpid()}-{secrets.token_hex(4)}"
    try:
        probe.touch(exist_ok=False)
        probe.unlink()
    except PermissionError:
        if there != out:
            raise InputError(out, f"cannot create the output folder (no permission to write in {there})") from None
        # a folder that takes no new file may still hold outputs one may rewrite in place (write_output): go on
    except OSError as err:
        raise InputError(out, f"cannot write into {'the output folder' if there == out else there} "
                              f"({err.strerror or err})") from None


def make_output_folder(out: str | os.PathLike) -> Path:
    """``--out`` made (with its parents) before any work, once :func:`check_output_folder` finds it usable."""
    out = Path(out)
    check_output_folder(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(out, f"cannot create the output folder ({err.strerror or err})") from None
    return out


# ---------------------------------------------------------------- cache entries
class CacheWarning(UserWarning):
    """The cache cannot be used (a file in the folder's place, no space, no permission): lfgnss goes on without it."""


_CACHE_WARNED: set[str] = set()
_STALE_PARTIAL_S = 3600.0          # a temporary file this old was left by a killed process, not one still writing


def _cache_unusable(err: OSError | RuntimeError) -> None:
    """One CacheWarning per cache folder and process, naming the file and the reason."""
    root = os.environ.get("LFGNSS_CACHE") or "~/.cache/lfgnss"
    if root in _CACHE_WARNED:
        return
    _CACHE_WARNED.add(root)
    where = getattr(err, "filename", None) or root
    reason = getattr(err, "strerror", None) or err
    warnings.warn(f"{where}: cannot use the cache ({reason}); going on without it, so files are parsed "
                  "again on every run (set $LFGNSS_CACHE to a writable folder)", CacheWarning, stacklevel=3)


def cache_file(kind: str, name: str) -> Path | None:
    """The cache entry ``KIND/NAME`` in :func:`cache_dir`, its folder made; None (and a CacheWarning) when it cannot be."""
    try:
        folder = cache_dir() / kind
        folder.mkdir(parents=True, exist_ok=True)
    except (OSError, RuntimeError) as err:     # RuntimeError: Path.home() of a user without a home folder
        _cache_unusable(err)
        return None
    return folder / name


def load_cached(path: Path | None, read: Callable[[Path], T]) -> T | None:
    """``read(path)`` of a cache entry; None when there is none (or something not a file is in its place).

    An entry that cannot be read is removed and None returned: a damaged entry is rebuilt, never trusted.
    """
    try:
        if path is None or not path.is_file():
            return None
        return read(path)
    except Exception:
        with contextlib.suppress(OSError):
            path.unlink()
        return None


def store_cached(path: Path | None, write: Callable[[Path], object]) -> None:
    """``write`` a cache entry whole (:func:`replace_atomically`); when it cannot be, a CacheWarning and no entry.

    Temporary files that killed processes left in the entry's folder more than an hour ago are removed first.
    """
    if path is None:
        return
    cutoff = time.time() - _STALE_PARTIAL_S
    for stale in path.parent.glob(".*.partial*"):
        with contextlib.suppress(OSError):          # gone already: another process renamed or removed it
            if stale.stat().st_mtime < cutoff:
                stale.unlink()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)      # removed while this run was going (a cache cleaned)
        replace_atomically(path, write)
    except OSError as err:
        _cache_unusable(err)
