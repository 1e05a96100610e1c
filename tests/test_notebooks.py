"""The notebooks run top to bottom on the bundled data (nbclient), so they never rot."""
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path, monkeypatch):
    """Run from a folder of their own, as a user's copy would be: no notebook may lean on ``../``."""
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    # the kernel's tempfile.mkdtemp() folders (a user's are the system's to clean) go where pytest cleans up: each run
    # of the suite left ~3 MB of them in /tmp
    (tmp_path / "tmp").mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    notebook = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(notebook, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    outputs = [o for c in notebook.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert not [p.name for p in tmp_path.iterdir() if p.name not in ("cache", "tmp")]   # figures and files go to
    assert list((tmp_path / "tmp").iterdir())                                               # temporary folders
    # each walks through with at least one plot, shown in the notebook
    assert [o for o in outputs if "image/png" in o.get("data", {})]
    text = "".join(o.get("text", "") for o in outputs)
    if path.stem == "estimator_comparison":         # tables of the columns computed: no cell is "-" for lack of one
        tables = [line for line in text.splitlines() if line.startswith("| ")]
        assert tables and not [line for line in tables if "| - |" in line or line.endswith("| -")], tables
    if path.stem == "training_walkthrough":         # trains on simulated drives, never on a shared dataset
        assert "'datasets': ['synthetic']" in "".join(o.get("text", "") for o in outputs)
