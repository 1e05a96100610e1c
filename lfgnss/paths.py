"""Where lfgnss finds shared benchmark data, bundled data and its cache."""
from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
REPO_DIR = PACKAGE_DIR.parent


def shared_data_dir() -> Path:
    """Benchmark data folder: $LFGNSS_SHARED_DATA, else ``../shared/data`` beside the checkout."""
    env = os.environ.get("LFGNSS_SHARED_DATA")
    return Path(env) if env else REPO_DIR.parent / "shared" / "data"


def bundled_data_dir() -> Path:
    """Small redistributable sample shipped inside the package."""
    return PACKAGE_DIR / "data"


def default_model_path() -> Path:
    """The bundled LF-GNSS model file, which ``python -m lfgnss.solve`` and ``estimators.create("ekf")`` use."""
    return bundled_data_dir() / "model" / "lfgnss-default.npz"


def cache_dir() -> Path:
    """Cache for parsed RINEX and built datasets: $LFGNSS_CACHE, else ~/.cache/lfgnss."""
    env = os.environ.get("LFGNSS_CACHE")
    path = Path(env) if env else Path.home() / ".cache" / "lfgnss"
    path.mkdir(parents=True, exist_ok=True)
    return path
