"""Our filters against RTKLIB on the epochs RTKLIB solves, on every split (the benchmark does the test split only).

    python benchmarks/rtklib_epochs.py                  # train, val and test splits, print the tables
    python benchmarks/rtklib_epochs.py --write          # ... and write docs/rtklib_epochs.md

RTKLIB's ``rnx2rtkp`` runs as in the benchmark (its settings, ``lfgnss.benchmark._rtklib_on``), its solutions matched
to each split's epochs. On the epochs it solved, the plain EKF and the LF-GNSS EKF with the dataset's own model
(``lfgnss-<dataset>.npz``, else the joint one), run forward over the whole split, are scored beside it. It shows
whether a miss against RTKLIB on the test split's epochs is a property of those epochs or a bias of ours (height, for
one). The models were trained on the train split, so only the validation and test columns are out of sample. Nothing
is chosen from these figures.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from smoothing_lag import DATASETS, estimators_for  # noqa: E402  (a sibling script)

DOC = REPO / "docs" / "rtklib_epochs.md"
SPLITS = ("train", "val", "test")
RTKLIB = "RTKLIB rnx2rtkp"


def run(dataset_ids, splits=SPLITS) -> list[dict]:
    """One row per dataset, split and method: accuracy over the labelled epochs RTKLIB solved in that split."""
    from lfgnss import datasets
    from lfgnss.benchmark import _features_for, _rtklib_on
    from lfgnss.metrics import accuracy_table

    rows = []
    for dataset_id in datasets.present(list(dataset_ids)):
        spec = datasets.get(dataset_id)
        filters = {name: make(0.0) for name, make in estimators_for(dataset_id).items()}
        for split in splits:
            seqs = datasets.load_split(dataset_id, split, feature_names=_features_for(filters.values()))
            with tempfile.TemporaryDirectory() as tmp:
                rtk = [_rtklib_on(s, spec, Path(tmp))[0] for s in seqs]
            if any(pos is None for pos in rtk):
                print(f"{dataset_id}: no RTKLIB solution (rnx2rtkp missing, or see above): left out", file=sys.stderr)
                break
            truth = np.concatenate([s.truth_ecef_m for s in seqs])
            solved = {RTKLIB: np.concatenate(rtk)}
            solved |= {name: np.concatenate([f.solve(s).pos_ecef_m for s in seqs]) for name, f in filters.items()}
            ok = np.all(np.isfinite(solved[RTKLIB]), axis=1) & np.all(np.isfinite(truth), axis=1)
            n_labelled = int(np.all(np.isfinite(truth), axis=1).sum())
            for name, pos in solved.items():
                r = accuracy_table(pos[ok], truth[ok]) if ok.any() else {}
                rows.append({"dataset": dataset_id, "split": split, "method": name, "rtklib_epochs": int(ok.sum()),
                             "labelled": n_labelled} | {k: r.get(k, float("nan")) for k in
                                                        ("rmse_u_m", "rmse_2d_m", "rmse_3d_m")})
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
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--datasets", nargs="+", default=list(DATASETS))
    p.add_argument("--splits", nargs="+", default=list(SPLITS), choices=SPLITS)
    p.add_argument("--write", action="store_true", help="write the page, docs/rtklib_epochs.md")
    args = p.parse_args(argv)
    warnings.simplefilter("ignore", FutureWarning)
    sys.path.insert(0, str(REPO))
    rows = run(args.datasets, args.splits)
    if not rows:
        print("rtklib_epochs.py: no dataset with its files and RTKLIB's rnx2rtkp: nothing to compare", file=sys.stderr)
        return 2
    text = markdown(rows, " ".join(["python benchmarks/rtklib_epochs.py", *(sys.argv[1:] if argv is None else argv)]))
    print(text)
    if args.write:
        DOC.write_text(text)
        print(f"written: {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
