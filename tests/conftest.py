"""Generic fixtures: shared benchmark data and the RTKLIB binary, skipped with a reason when absent."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from lfgnss.paths import shared_data_dir


@pytest.fixture(scope="session")
def shared_data():
    """``shared_data(name)`` -> ``shared_data_dir() / name``, or skip when that path is missing.

    ``name`` may be a dataset folder or a file inside one ('urbannav-hk-tst-20190428/hksc1180.19n').
    """
    def get(name: str) -> Path:
        path = shared_data_dir() / name
        if not path.exists():
            pytest.skip(f"shared data not found at {path} (set LFGNSS_SHARED_DATA to the shared/data folder)")
        return path

    return get


@pytest.fixture(scope="session")
def rnx2rtkp() -> Path:
    """Path of RTKLIB's ``rnx2rtkp``; skip when it is not installed."""
    exe = shutil.which("rnx2rtkp")
    if exe is None:
        pytest.skip("RTKLIB rnx2rtkp not on PATH (Debian package 'rtklib')")
    return Path(exe)
