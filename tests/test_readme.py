"""The README's library example runs as documented, and the main job runs on the bundled data."""
import re
from pathlib import Path

import numpy as np

from lfgnss.solve import main

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_library_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], str(README), "exec"), namespace)
    out = capsys.readouterr().out
    assert "3D RMSE [m]" in out and "ekf" in out
    solution, seq = namespace["solution"], namespace["seq"]
    assert solution.available.all() and np.all(np.isfinite(solution.pos_ecef_m))
    assert len(solution.time_gps_s) == len(seq)
    # create("ekf") is the LF-GNSS EKF with the bundled model, as on the command line, not the plain EKF
    from estimators import LfgnssEkf
    from learning.export import load_model
    from lfgnss.solve import DEFAULT_MODEL

    assert namespace["ekf"].noise.path == load_model(DEFAULT_MODEL).path
    np.testing.assert_array_equal(solution.pos_ecef_m, LfgnssEkf(load_model(DEFAULT_MODEL)).solve(seq).pos_ecef_m)
    assert "weights from the truth" in out and np.all(np.isfinite(namespace["reference"].pos_ecef_m))


def test_default_solve_runs_on_bundled_data(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "least squares (coarse)" in out and "ekf" in out
    csv = (tmp_path / "Berlin_Potsdamer_Platz_ekf.csv").read_text()
    assert "nan" not in csv.lower() and "inf" not in csv.lower()
    assert len(csv.splitlines()) == 1376
