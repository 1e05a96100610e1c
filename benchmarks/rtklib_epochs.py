"""Our filters against RTKLIB on the epochs RTKLIB solves, on every split (the benchmark does the test split only).

    python benchmarks/rtklib_epochs.py                  # train, val and test splits, print the tables
    python benchmarks/rtklib_epochs.py --write          # ... and write docs/rtklib_epochs.md

RTKLIB's ``rnx2rtkp`` runs once per dataset as in the benchmark (``lfgnss.benchmark.rtklib_solution``), its solutions
matched to each split's epochs. On the epochs it solved, the plain EKF, the LF-GNSS EKF with the dataset's own model
(``lfgnss-<dataset>.npz``, else the joint one) and, where that model's filter is not the default, the plain EKF in
that filter, each run forward over the whole split, are scored beside it. It shows
whether a miss against RTKLIB on the test split's epochs is a property of those epochs or a bias of ours (height, for
one). The models were trained on the train split, so only the validation and test columns are out of sample. Nothing
is chosen from these figures.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from page import command_line, nothing, parse, publish, script_parser  # noqa: E402  (a sibling module)
from smoothing_lag import estimators_for  # noqa: E402  (a sibling script)

DOC = REPO / "docs" / "rtklib_epochs.md"
SPLITS = ("train", "val", "test")
RTKLIB = "RTKLIB rnx2rtkp"


def filters_for(dataset_id: str) -> dict:
    """Name -> estimator: plain EKF, the LF-GNSS EKF with the dataset's model and, where that model's filter is not
    the default one, the plain EKF in it (as ``lfgnss.benchmark`` does)."""
    import estimators
    from lfgnss.benchmark import PLAIN_OWN_FILTER, own_filter

    found = {name: make(0.0) for name, make in estimators_for(dataset_id).items()}
    config = own_filter(next(f.noise for name, f in found.items() if name.startswith("LF-GNSS")))
    if config is not None:
        found[PLAIN_OWN_FILTER] = estimators.create("plain-ekf", config=config)
    return found


def _score(dataset_id: str, split: str, method: str, pos: np.ndarray, available: np.ndarray, truth: np.ndarray,
           on: np.ndarray) -> dict:
    """One row: U, 2D, 3D RMSE [m] of ``pos`` over the epochs ``on`` (NaN where there are none)."""
    from lfgnss.metrics import accuracy_table

    r = accuracy_table(pos[on], truth[on], available[on]) if on.any() else {}
    return {"dataset": dataset_id, "split": split, "method": method, "rtklib_epochs": int(on.sum()),
            "labelled": int(np.all(np.isfinite(truth), axis=1).sum()), "solved": r.get("n_solved", 0),
            **{k: r.get(k, float("nan")) for k in ("rmse_u_m", "rmse_2d_m", "rmse_3d_m")}}


def run(dataset_ids: list[str], splits: tuple[str, ...] = SPLITS) -> list[dict]:
    """One row per dataset, split and method: accuracy over the labelled epochs RTKLIB solved in that split."""
    from lfgnss import datasets
    from lfgnss.benchmark import _features_for, rtklib_solution
    from lfgnss.outputs import align_to

    rows = []
    for dataset_id in datasets.present(list(dataset_ids)):
        with tempfile.TemporaryDirectory() as tmp:
            rtk, _ = rtklib_solution(datasets.get(dataset_id), Path(tmp), tuple(datasets.build(dataset_id).systems))
        if rtk is None:
            print(f"{dataset_id}: no RTKLIB solution (rnx2rtkp missing, or see above): left out", file=sys.stderr)
            continue
        filters = filters_for(dataset_id)
        for split in splits:
            seqs = datasets.load_split(dataset_id, split, feature_names=_features_for(filters.values()))
            if not seqs:
                print(f"{dataset_id}: no labelled epoch in its {split} split: left out", file=sys.stderr)
                continue
            truth = np.concatenate([s.truth_ecef_m for s in seqs])
            rtk_pos = np.concatenate([align_to(s.time_gps_s, rtk) for s in seqs])
            on = np.all(np.isfinite(rtk_pos), axis=1) & np.all(np.isfinite(truth), axis=1)
            rows.append(_score(dataset_id, split, RTKLIB, rtk_pos, on, truth, on))
            for name, f in filters.items():
                sols = [f.solve(s) for s in seqs]
                rows.append(_score(dataset_id, split, name, np.concatenate([x.pos_ecef_m for x in sols]),
                                   np.concatenate([x.available for x in sols]), truth, on))
    return rows


def markdown(rows: list[dict], command: str) -> str:
    """One table per dataset: methods as rows, splits as columns, U / 2D / 3D RMSE [m] in cells."""
    out = ["# Our filters against RTKLIB on the epochs RTKLIB solves, per split", "",
           f"Produced by `{command}` (U / 2D / 3D RMSE in metres over the labelled epochs of each split that RTKLIB "
           "solved; the filters run forward over the whole split and are scored on those epochs only). The models "
           "were trained on the train split: its column is in-sample. docs/results.md has the test split's full "
           "table.", ""]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        mine = [r for r in rows if r["dataset"] == dataset]
        splits = list(dict.fromkeys(r["split"] for r in mine))
        counts = {r["split"]: f"{r['split']} ({r['rtklib_epochs']} of {r['labelled']})" for r in mine}
        out += [f"## {dataset}", "", "| method | " + " | ".join(counts[s] for s in splits) + " |",
                "| --- |" + " ---: |" * len(splits)]
        for name in dict.fromkeys(r["method"] for r in mine):
            cells = {r["split"]: f"{r['rmse_u_m']:.2f} / {r['rmse_2d_m']:.2f} / {r['rmse_3d_m']:.2f}"
                     for r in mine if r["method"] == name and r["rtklib_epochs"] > 0}
            out.append(f"| {name} | " + " | ".join(cells.get(s, "-") for s in splits) + " |")
        out.append("")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page."""
    p = script_parser(__doc__, "write the page, docs/rtklib_epochs.md", splits=SPLITS)
    args = parse(p, argv, "rtklib_epochs.py")
    if args is None:
        return 2
    rows = run(args.datasets, tuple(args.splits))
    if not rows:
        return nothing("rtklib_epochs.py", "no dataset with its files and RTKLIB's rnx2rtkp: nothing to compare")
    return publish(markdown(rows, command_line("rtklib_epochs.py", argv)), DOC, args.write)


if __name__ == "__main__":
    raise SystemExit(main())
