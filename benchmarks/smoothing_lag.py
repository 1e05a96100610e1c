"""Accuracy against latency of the EKF's fixed-lag RTS smoother (``estimators.smoother``), on one split.

    python benchmarks/smoothing_lag.py                      # validation splits, print the table
    python benchmarks/smoothing_lag.py --write              # ... and write docs/smoothing_lag.md and its PNG

For each dataset: the plain EKF and the LF-GNSS EKF with the dataset's own model (``lfgnss-<dataset>.npz``, else
the joint one), forward (lag 0), with fixed lags, and smoothed over the whole run. Validation by default, so
the choice of a lag is never made on the test split.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from page import command_line, parse, publish, save_figure, script_parser  # noqa: E402  (a sibling module)

DOC = REPO / "docs" / "smoothing_lag.md"
FIGURE = REPO / "docs" / "figures" / "smoothing_lag.png"
LAGS_S = (0.0, 1.0, 2.0, 5.0, 10.0, 30.0, math.inf)


def estimators_for(dataset_id: str) -> dict:
    """Name -> factory(lag) of the two filters compared: plain EKF, LF-GNSS EKF with the dataset's model."""
    import estimators
    from learning.export import load_model
    from lfgnss.benchmark import MODEL_DIR

    own = MODEL_DIR / f"lfgnss-{dataset_id}.npz"
    path = own if own.exists() else MODEL_DIR / "lfgnss-default.npz"
    noise = load_model(path)
    return {"plain EKF": lambda lag: estimators.create("plain-ekf", smooth=lag > 0, smooth_lag_s=lag),
            f"LF-GNSS EKF ({path.name})": lambda lag: estimators.create("ekf", noise=noise, smooth=lag > 0,
                                                                        smooth_lag_s=lag)}


def run(dataset_ids, split: str) -> list[dict]:
    """One row per dataset, filter and lag: 3D and 2D RMSE [m] over the split's labelled epochs."""
    from lfgnss import datasets
    from lfgnss.metrics import accuracy_table

    rows = []
    for dataset_id in datasets.present(list(dataset_ids)):
        seqs = datasets.load_split(dataset_id, split)
        truth = np.concatenate([s.truth_ecef_m for s in seqs])
        for name, make in estimators_for(dataset_id).items():
            for lag in LAGS_S:
                sols = [make(lag).solve(s) for s in seqs]
                r = accuracy_table(np.concatenate([s.pos_ecef_m for s in sols]), truth,
                                   np.concatenate([s.available for s in sols]))
                rows.append({"dataset": dataset_id, "filter": name, "lag_s": lag, "rmse_3d_m": r["rmse_3d_m"],
                             "rmse_2d_m": r["rmse_2d_m"], "availability": r["availability"]})
    return rows


def _lag_text(lag: float) -> str:
    return "forward" if lag == 0 else "whole run" if math.isinf(lag) else f"{lag:g} s"


def markdown(rows: list[dict], split: str, command: str) -> str:
    """The results as a Markdown page: one table per dataset, lags as columns, 3D / 2D RMSE [m] in the cells."""
    out = ["# EKF with the fixed-lag RTS smoother: accuracy against latency", "",
           f"Produced by `{command}` (split: {split}; 3D / 2D RMSE in metres over the split's labelled epochs, "
           "100 % availability; lag = how long after an epoch its estimate is ready; forward = the filter).", ""]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        out += [f"## {dataset}", "", "| filter | " + " | ".join(_lag_text(lag) for lag in LAGS_S) + " |",
                "| --- |" + " ---: |" * len(LAGS_S)]
        for name in dict.fromkeys(r["filter"] for r in rows if r["dataset"] == dataset):
            cells = [f"{r['rmse_3d_m']:.2f} / {r['rmse_2d_m']:.2f}" for r in rows
                     if r["dataset"] == dataset and r["filter"] == name]
            out.append(f"| {name} | " + " | ".join(cells) + " |")
        out.append("")
    out += [f"Figure: `figures/{FIGURE.name}`.", ""]
    return "\n".join(out)


def plot(rows: list[dict], path: Path, split: str) -> Path:
    """3D RMSE against lag, one panel per dataset (the whole-run smoother drawn at the right edge)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    datasets_ = list(dict.fromkeys(r["dataset"] for r in rows))
    fig, axes = plt.subplots(1, len(datasets_), figsize=(4.2 * len(datasets_), 3.6), squeeze=False)
    ticks = np.arange(len(LAGS_S))
    for ax, dataset in zip(axes[0], datasets_):
        for name in dict.fromkeys(r["filter"] for r in rows if r["dataset"] == dataset):
            y = [r["rmse_3d_m"] for r in rows if r["dataset"] == dataset and r["filter"] == name]
            ax.plot(ticks, y, marker="o", label=name)
        ax.set_xticks(ticks, [_lag_text(lag) for lag in LAGS_S], rotation=45, ha="right")
        ax.set_title(f"{dataset} ({split})")
        ax.set_ylabel("3D RMSE [m]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page and the figure."""
    p = script_parser(__doc__, f"write {DOC.relative_to(REPO)} and {FIGURE.name}")
    p.add_argument("--split", default="val", choices=("train", "val", "test"))
    args = parse(p, argv, "smoothing_lag.py")
    if args is None:
        return 2
    rows = run(args.datasets, args.split)
    text = markdown(rows, args.split, command_line("smoothing_lag.py", argv))
    return publish(text, DOC, args.write, FIGURE, lambda path: plot(rows, path, args.split))


if __name__ == "__main__":
    raise SystemExit(main())
