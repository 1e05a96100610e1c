"""Where lfgnss finds shared benchmark data, bundled data and its cache."""
from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable
from pathlib import Path

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
    (parallel tests, two solves of one file) each rename a whole file instead of writing into each other's.
    """
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{secrets.token_hex(4)}.partial{path.suffix}")
    try:
        write(tmp)
        with open(tmp, "r+b") as fh:            # on the disk before the rename, so a power cut leaves one or the other
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
