"""benchmarks/fgo_convergence.py: its rows are the batch graph's own figures; its page says which solves stopped."""
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import fgo_convergence  # noqa: E402


def test_rows_are_the_graphs_own_figures_and_the_page_marks_a_cut_off_solve():
    from estimators.fgo import LfgnssFgo
    from lfgnss import datasets
    from lfgnss.metrics import accuracy_table

    if datasets.get("hk-tst-static-2020").missing():
        pytest.skip(f"shared data missing ({datasets.get('hk-tst-static-2020').missing()[0]})")
    rows = fgo_convergence.run(["hk-tst-static-2020"], ["val"], iterations=(3, 50))
    assert [(r["model"], r["max_iterations"]) for r in rows] == [
        ("default", 3), ("default", 50), ("hk-tst-static-2020", 3), ("hk-tst-static-2020", 50)]
    assert [r["converged"] for r in rows] == [False, True, False, True]
    seq = datasets.load_split("hk-tst-static-2020", "val")[0]
    sol = LfgnssFgo(noise="hk-tst-static-2020").solve(seq)
    want = accuracy_table(sol.pos_ecef_m, seq.truth_ecef_m, sol.available)
    assert (rows[3]["rmse_3d_m"], rows[3]["iterations"], rows[3]["epochs"]) == (
        want["rmse_3d_m"], sol.info["iterations"], want["n_solved"])
    page = fgo_convergence.markdown(rows, "cmd")
    assert "| hk-tst-static-2020 | val | default | 6 | **no** |" in page      # 3 per stage, two stages
    pooled = np.sqrt(sum(r["rmse_3d_m"] ** 2 * r["epochs"] for r in rows[1::2]) / sum(r["epochs"] for r in rows[1::2]))
    assert f"{pooled:.2f} m at 50" in page
