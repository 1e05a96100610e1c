"""How much of each filter's error is its cold start: started as shipped against started at the true position.

    python benchmarks/cold_start.py                    # train, val and test splits, print the tables
    python benchmarks/cold_start.py --write            # ... and write docs/cold_start.md and its PNG

For each dataset, the plain EKF and the LF-GNSS EKF with the dataset's own model (``lfgnss-<dataset>.npz``, else the
joint one) run forward over each split twice: cold, as the benchmark runs them (from the first epoch's
least-squares fix with the filter's P0), and started at the true position with a 1 m sd per axis (only the
position is given; velocity and clock start as in the cold run). The second run is not a method (it reads the
truth): it shows what a perfect first fix would win, and so the most a robust first fix or a graph as initialiser
could. Each split is scored over all its labelled epochs, its first ``--head`` seconds and the rest. The figure
shows the test split's horizontal error over time. The models were trained on the train split, so only the
validation and test columns are out of sample. Nothing is chosen from these figures.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from estimators.ekf import LfgnssEkf
    from estimators.models import EkfConfig
    from lfgnss.sequence import Sequence

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from page import command_line, nothing, parse, publish, save_figure, script_parser  # noqa: E402  (a sibling module)
from smoothing_lag import estimators_for  # noqa: E402  (a sibling script)

DOC = REPO / "docs" / "cold_start.md"
FIGURE = REPO / "docs" / "figures" / "cold_start.png"
SPLITS = ("train", "val", "test")
STARTS = ("cold", "at the truth")
TRUE_START_SD_M = 1.0
HEAD_S = 35.0


def started_at_truth(sequence: "Sequence") -> "Sequence":
    """``sequence`` whose first epoch's coarse fix is its true position (the filter's start); unchanged without one."""
    truth = sequence.truth_ecef_m[0]
    if not np.isfinite(truth).all():
        return sequence
    coarse = sequence.coarse_ecef_m.copy()
    coarse[0] = truth
    return dataclasses.replace(sequence, coarse_ecef_m=coarse)


def truth_start_config(estimator: "LfgnssEkf") -> "EkfConfig":
    """The EkfConfig of ``estimator`` with a P0 position sd of ``TRUE_START_SD_M`` [m] per axis."""
    return dataclasses.replace(estimator.config, p0_pos_m2=TRUE_START_SD_M ** 2)


def _runs(dataset_id: str) -> list[tuple[str, str, object, bool]]:
    """(filter name, start, estimator, started at the truth) for the dataset's two filters and both starts."""
    out = []
    for name, make in estimators_for(dataset_id).items():
        cold = make(0.0)
        from_truth = type(cold)(noise=cold.noise, config=truth_start_config(cold))
        out += [(name, STARTS[0], cold, False), (name, STARTS[1], from_truth, True)]
    return out


def _score(pos: np.ndarray, available: np.ndarray, truth: np.ndarray, on: np.ndarray) -> tuple[float, float]:
    """(3D, 2D) RMSE [m] over the epochs ``on``; NaN where there are none."""
    from lfgnss.metrics import accuracy_table

    if not on.any():
        return float("nan"), float("nan")
    r = accuracy_table(pos[on], truth[on], available[on])
    return r["rmse_3d_m"], r["rmse_2d_m"]


def run(dataset_ids: list[str], splits: tuple[str, ...] = SPLITS, head_s: float = HEAD_S) -> tuple[list, dict]:
    """Rows (one per dataset, split, filter and start: 3D / 2D RMSE [m] over all, head and rest epochs, resets) and
    the test split's horizontal errors over time, {dataset: {(filter, start): (t [s], 2D error [m])}}."""
    from estimators.base import STATUS_RESET
    from lfgnss import datasets
    from lfgnss.benchmark import _features_for
    from lfgnss.metrics import enu_errors

    rows, traces = [], {}
    for dataset_id in datasets.present(list(dataset_ids)):
        runs = _runs(dataset_id)
        for split in splits:
            seqs = datasets.load_split(dataset_id, split, feature_names=_features_for([r[2] for r in runs]))
            if not seqs:
                print(f"{dataset_id}: no labelled epoch in its {split} split: left out", file=sys.stderr)
                continue
            truth = np.concatenate([s.truth_ecef_m for s in seqs])
            since = np.concatenate([s.time_gps_s - s.time_gps_s[0] for s in seqs])
            head = since < head_s
            for name, start, estimator, at_truth in runs:
                sols = [estimator.solve(started_at_truth(s) if at_truth else s) for s in seqs]
                pos = np.concatenate([x.pos_ecef_m for x in sols])
                available = np.concatenate([x.available for x in sols])
                rows.append({"dataset": dataset_id, "split": split, "filter": name, "start": start,
                             "epochs": len(truth), "head_epochs": int(head.sum()),
                             "resets": int(sum((x.status == STATUS_RESET).sum() for x in sols)),
                             "all": _score(pos, available, truth, np.ones(len(truth), bool)),
                             "head": _score(pos, available, truth, head), "rest": _score(pos, available, truth, ~head)})
                if split == "test":
                    err = np.hypot(*enu_errors(pos, truth)[:, :2].T)
                    traces.setdefault(dataset_id, {})[(name, start)] = (since, err)
    return rows, traces


def _cell(pair: tuple[float, float]) -> str:
    return "-" if not np.isfinite(pair[0]) else f"{pair[0]:.2f} / {pair[1]:.2f}"


def markdown(rows: list[dict], command: str, head_s: float = HEAD_S, figure: bool = True) -> str:
    """One table per dataset: filter and start as rows, split x (all, head, rest) as columns, 3D / 2D RMSE [m]; the
    header names the figure where one is drawn (``figure``: the test split was run)."""
    out = ["# How much of the error is the cold start", "",
           f"Produced by `{command}` (3D / 2D RMSE in metres over each split's labelled epochs, all of them, the first "
           f"{head_s:g} s and the rest; 100 % availability). Cold: as the benchmark runs the filters. At the truth: "
           f"the same filter started at the true position with a {TRUE_START_SD_M:g} m sd per axis: what a "
           "perfect first fix would give, not a method (it reads the truth). The models were trained on the train "
           "split: its columns are in-sample. Resets counts the filter's (re-)initialisations, the start included."
           + (f" Figure: `figures/{FIGURE.name}` (test split)." if figure else ""), ""]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        mine = [r for r in rows if r["dataset"] == dataset]
        splits = list(dict.fromkeys(r["split"] for r in mine))
        counts = {r["split"]: r for r in mine}
        head = [f"{s} all ({counts[s]['epochs']})" if part == "all" else
                f"{s} first {head_s:g} s ({counts[s]['head_epochs']})" if part == "head" else f"{s} rest"
                for s in splits for part in ("all", "head", "rest")]
        out += [f"## {dataset}", "", "| filter | start | " + " | ".join(head) + " | resets |",
                "| --- | --- |" + " ---: |" * (len(head) + 1)]
        for r0 in [r for r in mine if r["split"] == splits[0]]:
            same = [r for r in mine if (r["filter"], r["start"]) == (r0["filter"], r0["start"])]
            cells = [_cell(r[part]) for r in same for part in ("all", "head", "rest")]
            out.append(f"| {r0['filter']} | {r0['start']} | " + " | ".join(cells) + " | "
                       + " / ".join(str(r["resets"]) for r in same) + " |")
        out.append("")
    return "\n".join(out)


def plot(traces: dict, path: Path, head_s: float = HEAD_S) -> Path:
    """Test split's horizontal error against time, one panel per dataset, cold and truth-started filters."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(traces), 1, figsize=(9, 2.8 * len(traces)), squeeze=False)
    for ax, (dataset, runs) in zip(axes[:, 0], traces.items()):
        for (name, start), (t, err) in runs.items():
            ax.plot(t, err, lw=1, ls="-" if start == STARTS[0] else "--", label=f"{name}, {start}")
        ax.axvline(head_s, color="k", lw=0.8, alpha=0.5)
        ax.set_title(f"{dataset} (test split)")
        ax.set_xlabel("time since the split's start [s]")
        ax.set_ylabel("2D error [m]")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page and the figure."""
    p = script_parser(__doc__, f"write {DOC.relative_to(REPO)} and {FIGURE.name}", splits=SPLITS)
    p.add_argument("--head", type=float, default=HEAD_S, help=f"seconds scored apart at each split's start "
                                                              f"(default {HEAD_S:g})")
    args = parse(p, argv, "cold_start.py")
    if args is None:
        return 2
    rows, traces = run(args.datasets, tuple(args.splits), args.head)
    if not rows:
        return nothing("cold_start.py", "no dataset with its files: nothing to compare")
    text = markdown(rows, command_line("cold_start.py", argv), args.head, figure=bool(traces))
    return publish(text, DOC, args.write, FIGURE, (lambda path: plot(traces, path, args.head)) if traces else None)


if __name__ == "__main__":
    raise SystemExit(main())
