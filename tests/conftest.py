"""Generic fixtures: shared benchmark data and the RTKLIB binary, skipped with a reason when absent."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from lfgnss.paths import shared_data_dir

if "PYTEST_XDIST_WORKER_COUNT" in os.environ:      # pytest -n N: N workers share the cores, so torch's threads do too
    _workers = int(os.environ["PYTEST_XDIST_WORKER_COUNT"])
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // _workers)))


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


@pytest.fixture
def sample_toml(tmp_path):
    """``sample_toml(dataset_id, truth=..., splits=...)`` -> a dataset TOML in ``tmp_path`` for the bundled Berlin drive."""
    from lfgnss.solve import SAMPLE_DIR

    def write(dataset_id: str, truth: str | Path = SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt",
              splits: tuple = ((0, 150), (150, 180), (180, 200))) -> Path:
        train, val, test = (list(s) for s in splits)
        path = tmp_path / f"{dataset_id}.toml"
        path.write_text(f"""
id = "{dataset_id}"
obs = ["{SAMPLE_DIR / 'Berlin_Potsdamer_Platz.obs.gz'}"]
nav = ["{SAMPLE_DIR / 'brdc1580.16n.gz'}", "{SAMPLE_DIR / 'brdc1580.16g.gz'}"]
systems = ["G", "R"]
[truth]
file = "{truth}"
format = "smartloc"
time_origin_gps_s = {1900 * 604800 + 126641.7}
[splits]
axis = "relative_s"
train = {train}
val = {val}
test = {test}
""")
        return path

    return write


@pytest.fixture
def my_drive(monkeypatch, sample_toml):
    """The bundled drive registered alone as dataset ``my-drive`` (splits 0-150, 150-180, 180-200 s)."""
    from lfgnss import datasets

    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    datasets.register_toml(sample_toml("my-drive", splits=((0, 150), (150, 180), (180, 200))))
    return "my-drive"


@pytest.fixture(autouse=True)
def _own_dataset_registry(monkeypatch):
    """Each test registers its datasets in a copy of the registry: a dataset id registered by another test's TOML
    file would otherwise be refused (``lfgnss.datasets.register``: one file per id)."""
    from lfgnss import datasets

    monkeypatch.setattr(datasets, "_REGISTRY", dict(datasets._REGISTRY))
