"""Does the batch factor graph's Levenberg-Marquardt solve converge, and would more iterations help?

    python benchmarks/fgo_convergence.py                    # train and validation splits, print the table
    python benchmarks/fgo_convergence.py --write            # ... and write docs/fgo_convergence.md

For each dataset and split: the batch ``LfgnssFgo`` with the shipped default model and the dataset's own model, at
the default ``max_iterations`` (50) and at 200: the iterations used (Huber start and Cauchy stage together), whether
the last stage converged (``info["converged"]``), and the 3D RMSE [m] over the labelled epochs. Train and validation
splits only: session 54 decided the default on this table (docs/findings.md), so the test split is not offered.
"""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from page import command_line, nothing, parse, publish, script_parser  # noqa: E402  (a sibling module)

DOC = REPO / "docs" / "fgo_convergence.md"
SPLITS = ("train", "val")
ITERATIONS = (50, 200)          # the default, and enough for every solve above to converge


def run(dataset_ids, splits=SPLITS, iterations=ITERATIONS) -> list[dict]:
    """One row per dataset, split, model and ``max_iterations``: iterations used, converged, 3D RMSE [m], epochs."""
    import estimators
    from estimators.fgo import LfgnssFgo
    from lfgnss import datasets
    from lfgnss.metrics import accuracy_table

    rows = []
    for dataset_id in datasets.present(list(dataset_ids)):
        for split in splits:
            seqs = datasets.load_split(dataset_id, split)
            for model in ("default", dataset_id):
                noise = estimators.create("fgo", noise=model).noise
                for n in iterations:
                    fgo = LfgnssFgo(noise=noise, max_iterations=n)
                    with warnings.catch_warnings():         # the table says which solves did not converge
                        warnings.simplefilter("ignore", UserWarning)
                        sols = [fgo.solve(s) for s in seqs]
                    r = accuracy_table(np.concatenate([s.pos_ecef_m for s in sols]),
                                       np.concatenate([s.truth_ecef_m for s in seqs]),
                                       np.concatenate([s.available for s in sols]))
                    rows.append({"dataset": dataset_id, "split": split, "model": model, "max_iterations": n,
                                 "iterations": sum(s.info["iterations"] for s in sols),
                                 "converged": all(s.info["converged"] for s in sols),
                                 "rmse_3d_m": r["rmse_3d_m"], "epochs": r["n_solved"]})
    return rows


def pooled_rmse_m(rows: list[dict], n: int) -> float:
    """3D RMSE [m] pooled over the rows at ``max_iterations`` n (by their labelled epochs)."""
    mine = [r for r in rows if r["max_iterations"] == n]
    return float(np.sqrt(sum(r["rmse_3d_m"] ** 2 * r["epochs"] for r in mine) / sum(r["epochs"] for r in mine)))


def markdown(rows: list[dict], command: str) -> str:
    """A table: one line per dataset, split and model; iterations, converged and 3D RMSE at each max_iterations."""
    its = sorted({r["max_iterations"] for r in rows})
    head = ["dataset", "split", "model"] + [f"{w} ({n})" for n in its for w in ("iterations", "converged", "3D [m]")]
    lines = ["| " + " | ".join(head) + " |", "| --- | --- | --- |" + " ---: |" * (3 * len(its))]
    keys = list(dict.fromkeys((r["dataset"], r["split"], r["model"]) for r in rows))
    for key in keys:
        cells = list(key)
        for n in its:
            r = next(r for r in rows if (r["dataset"], r["split"], r["model"], r["max_iterations"]) == (*key, n))
            cells += [str(r["iterations"]), "yes" if r["converged"] else "**no**", f"{r['rmse_3d_m']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    pooled = ", ".join(f"{pooled_rmse_m(rows, n):.2f} m at {n}" for n in its)
    return (f"# Does the batch factor graph converge?\n\nProduced by `{command}` (batch `LfgnssFgo`, the shipped "
            f"models; iterations over the Huber start and the Cauchy stage; converged: the last stage ended before "
            f"max_iterations, or there one more iteration lowered its error by less than the tolerances, and did not "
            f"give up; 3D RMSE in metres over the labelled epochs, 100 % availability; "
            f"train and validation splits only).\n\n" + "\n".join(lines)
            + f"\n\nPooled 3D RMSE: {pooled}. How the default was chosen from this table: docs/findings.md "
              f"(session 54).\n")


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page."""
    p = script_parser(__doc__, f"write {DOC.relative_to(REPO)}", splits=SPLITS)
    args = parse(p, argv, "fgo_convergence.py")
    if args is None:
        return 2
    rows = run(args.datasets, args.splits)
    if not rows:
        return nothing("fgo_convergence.py", "no dataset has its files (LFGNSS_SHARED_DATA)")
    return publish(markdown(rows, command_line("fgo_convergence.py", argv)), DOC, args.write)


if __name__ == "__main__":
    raise SystemExit(main())
