"""How far weighting alone can take the EKF: the same filter with R taken from the ground truth.

    python benchmarks/truth_weights.py                      # train, val and test splits, print the tables
    python benchmarks/truth_weights.py --write              # ... and write docs/truth_weights.md and its PNG

For each dataset: the plain EKF, the LF-GNSS EKF with the dataset's own model (``lfgnss-<dataset>.npz``, else the
joint one), and that model's filter with ``estimators.TruthNoise`` (R = squared true pseudorange error + a floor
of 0.3, 1 or 3 m squared, no v^c: shared/BENCHMARK.md's "weights taken from the truth", a reference and not a
method; with the filter's GLONASS sigma factor at 1, so R is the truth's as it is), each forward and
RTS-smoothed over the whole run. Nothing is chosen from these figures; they say whether a forward-filter miss
is the noise model's or the filter's.
"""
from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from page import command_line, parse, publish, save_figure, script_parser  # noqa: E402  (a sibling module)
from smoothing_lag import estimators_for  # noqa: E402  (a sibling script)

DOC = REPO / "docs" / "truth_weights.md"
FIGURE = REPO / "docs" / "figures" / "truth_weights.png"
SPLITS = ("train", "val", "test")
FLOORS_M = (0.3, 1.0, 3.0)     # sigma floor of the truth weights [m]: the conclusion must not hang on one value


def filters_for(dataset_id: str) -> dict:
    """Name -> factory(lag): plain EKF, LF-GNSS EKF, and its filter with ``TruthNoise`` at each of ``FLOORS_M``."""
    import estimators
    from estimators.ekf import config_of

    found = estimators_for(dataset_id)
    learned = [name for name in found if name.startswith("LF-GNSS")][0]
    # R from the truth as it is: a model filter's GLONASS sigma factor (the static model's 1.5) would weight it anew
    config = dataclasses.replace(config_of(found[learned](0.0).noise), glonass_sigma_factor=1.0)

    def truth(floor_m: float):
        return lambda lag: estimators.LfgnssEkf(noise=estimators.TruthNoise(floor_m=floor_m), config=config,
                                                name="truth-weights", smooth=lag > 0, smooth_lag_s=lag)

    return found | {f"EKF, weights from the truth, floor {f:g} m": truth(f) for f in FLOORS_M}


def run(dataset_ids, splits=SPLITS) -> list[dict]:
    """One row per dataset, split, filter and mode (forward, smoothed): 3D and 2D RMSE [m] over labelled epochs."""
    from lfgnss import datasets
    from lfgnss.metrics import accuracy_table

    rows = []
    for dataset_id in datasets.present(list(dataset_ids)):
        filters = filters_for(dataset_id)
        for split in splits:
            seqs = datasets.load_split(dataset_id, split)
            truth = np.concatenate([s.truth_ecef_m for s in seqs])
            for name, make in filters.items():
                for mode, lag in (("forward", 0.0), ("smoothed", math.inf)):
                    sols = [make(lag).solve(s) for s in seqs]
                    r = accuracy_table(np.concatenate([s.pos_ecef_m for s in sols]), truth,
                                       np.concatenate([s.available for s in sols]))
                    rows.append({"dataset": dataset_id, "split": split, "filter": name, "mode": mode,
                                 "rmse_3d_m": r["rmse_3d_m"], "rmse_2d_m": r["rmse_2d_m"],
                                 "availability": r["availability"]})
    return rows


def markdown(rows: list[dict], command: str) -> str:
    """One table per dataset: filters as rows, split x (forward, smoothed) as columns, 3D / 2D RMSE [m] in cells."""
    from lfgnss.benchmark import TARGETS

    out = ["# The EKF with weights taken from the truth", "",
           f"Produced by `{command}` (3D / 2D RMSE in metres over each split's labelled epochs, 100 % availability; "
           "forward = the filter, smoothed = RTS over the whole run). The last rows of each table are the second "
           "row's filter with R from the truth (`estimators.TruthNoise`: squared pseudorange error at the true "
           "position, per-constellation median removed, + the floor squared; no v^c; the filter's GLONASS sigma factor "
           "set to 1, so R is the truth's as it is). It needs the truth, so it is a "
           "reference and not a method; nothing is tuned on it.", ""]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        mine = [r for r in rows if r["dataset"] == dataset]
        cols = list(dict.fromkeys((r["split"], r["mode"]) for r in mine))
        target = TARGETS.get(dataset)
        out += [f"## {dataset}" + (f" (targets, test, forward: {target[0]:g} / {target[1]:g} m)" if target else ""),
                "", "| filter | " + " | ".join(f"{s} {m}" for s, m in cols) + " |", "| --- |" + " ---: |" * len(cols)]
        for name in dict.fromkeys(r["filter"] for r in mine):
            cells = {(r["split"], r["mode"]): f"{r['rmse_3d_m']:.2f} / {r['rmse_2d_m']:.2f}" for r in mine
                     if r["filter"] == name}
            out.append(f"| {name} | " + " | ".join(cells.get(c, "-") for c in cols) + " |")
        out.append("")
    out += [f"Figure: `figures/{FIGURE.name}`.", ""]
    return "\n".join(out)


def _short(name: str) -> str:
    """A filter's name cut to fit under a bar."""
    return ("truth\n" + name.rsplit("floor ", 1)[1]) if "truth" in name else name.split(" (")[0].replace(" EKF", "")


def plot(rows: list[dict], path: Path, split: str = "test") -> Path:
    """Forward 3D and 2D RMSE of the three filters on ``split``, one panel per dataset, targets dashed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from lfgnss.benchmark import TARGETS

    chosen = [r for r in rows if r["split"] == split and r["mode"] == "forward"]
    datasets_ = list(dict.fromkeys(r["dataset"] for r in chosen))
    fig, axes = plt.subplots(1, max(len(datasets_), 1), figsize=(4.2 * max(len(datasets_), 1), 3.8), squeeze=False)
    for ax, dataset in zip(axes[0], datasets_):
        mine = [r for r in chosen if r["dataset"] == dataset]
        x = np.arange(len(mine))
        ax.bar(x - 0.2, [r["rmse_3d_m"] for r in mine], 0.4, label="3D")
        ax.bar(x + 0.2, [r["rmse_2d_m"] for r in mine], 0.4, label="2D")
        for value, style in zip(TARGETS.get(dataset, ()), ("--", ":")):
            ax.axhline(value, color="k", linestyle=style, linewidth=1)
        ax.set_xticks(x, [_short(r["filter"]) for r in mine], fontsize=8)
        ax.set_title(f"{dataset} ({split}, forward)")
        ax.set_ylabel("RMSE [m] (targets: 3D --, 2D ..)")
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page and the figure."""
    p = script_parser(__doc__, f"write {DOC.relative_to(REPO)} and {FIGURE.name}", splits=SPLITS)
    args = parse(p, argv, "truth_weights.py")
    if args is None:
        return 2
    rows = run(args.datasets, args.splits)
    text = markdown(rows, command_line("truth_weights.py", argv))
    split = "test" if "test" in args.splits else args.splits[-1]
    return publish(text, DOC, args.write, FIGURE, lambda path: plot(rows, path, split))


if __name__ == "__main__":
    raise SystemExit(main())
