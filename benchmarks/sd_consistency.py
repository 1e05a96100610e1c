"""Are the reported standard deviations calibrated? Each estimator's ENU covariance against its actual errors.

    python benchmarks/sd_consistency.py            # the bundled Berlin drive (all epochs), every estimator
    python benchmarks/sd_consistency.py --write    # ... and write docs/sd_consistency.md, with the splits below
    python benchmarks/sd_consistency.py --splits val test   # the EKF on shared/BENCHMARK.md's splits, by model

For each estimator (default settings, its default model): the median horizontal sd, the horizontal RMS error, the
share of east / north / up errors within 1 and 3 sd (68 % and 99.7 % if calibrated), and the mean and median NEES
e^T C^-1 e over the ENU covariance C (3 if calibrated); the EKF rows, and those of the factor graph's marginals, with
and without the covariance inflation (``estimators.consistency``). They say how far the sd columns of the outputs
(.pos sdn/sde/sdu, CSV sd_*_m) can be trusted. The inflation's form and time constant (and, in session 35, whether the
factor graph's covariances take it) were chosen on the validation splits' rows; the test rows only report.
"""
from __future__ import annotations

import argparse
import shlex
import sys
import warnings
from pathlib import Path

import numpy as np

DOC = Path(__file__).resolve().parents[1] / "docs" / "sd_consistency.md"
ESTIMATORS = {"ekf": {}, "ekf, formal covariance": {"inflate_cov": False}, "ekf, RTS-smoothed": {"smooth": True},
              "ekf, RTS-smoothed, formal": {"smooth": True, "inflate_cov": False}, "plain-ekf": {},
              "plain-ekf, formal": {"inflate_cov": False}, "fgo": {}, "fgo, marginals": {"covariances": True},
              "fgo, marginals, formal": {"covariances": True, "inflate_cov": False}, "wls": {}, "wls-weighted": {}}
SPLIT_ESTIMATORS = {"ekf": {}, "ekf, formal covariance": {"inflate_cov": False}, "fgo": {},
                    "fgo, marginals": {"covariances": True},
                    "fgo, marginals, formal": {"covariances": True, "inflate_cov": False}}
DATASETS = ("hk-tst-2019", "berlin-pp", "hk-tst-static-2020")


def consistency_row(label: str, sequences, solutions) -> dict:
    """Calibration figures of ``solutions`` against the truth of ``sequences`` (labelled epochs, finite covariance)."""
    from lfgnss.metrics import enu_errors

    err = np.concatenate([enu_errors(sol.pos_ecef_m, seq.truth_ecef_m) for seq, sol in zip(sequences, solutions)])
    cov = np.concatenate([sol.cov_enu_m2() for sol in solutions])
    available = np.concatenate([sol.available for sol in solutions])
    sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    ok = available & np.isfinite(err).all(1) & np.isfinite(cov).all((1, 2)) & (sd > 0).all(1)
    z = np.abs(err[ok]) / sd[ok]
    nees = np.einsum("ti,tij,tj->t", err[ok], np.linalg.inv(cov[ok]), err[ok])
    return {"estimator": label, "epochs": int(ok.sum()),
            "median 2D sd [m]": float(np.median(np.hypot(sd[ok, 0], sd[ok, 1]))),
            "2D RMS error [m]": float(np.sqrt(np.mean(err[ok, 0] ** 2 + err[ok, 1] ** 2))),
            "within 1 sd E/N/U [%]": "/".join(f"{v:.0f}" for v in 100 * (z < 1).mean(0)),
            "within 3 sd E/N/U [%]": "/".join(f"{v:.0f}" for v in 100 * (z < 3).mean(0)),
            "mean NEES": float(nees.mean()), "median NEES": float(np.median(nees))}


def rows_for(seq) -> list[dict]:
    """One row per estimator of ``ESTIMATORS`` on ``seq`` (its labelled epochs with a finite covariance)."""
    import estimators

    return [consistency_row(label, [seq], [estimators.create(label.split(",")[0], **options).solve(seq)])
            for label, options in ESTIMATORS.items()]


def split_rows(split: str) -> list[dict]:
    """The EKF and the factor graph (batch), with and without inflation, on ``split`` of each shared dataset present,
    with the shipped (joint) and the per-dataset model."""
    import estimators
    from learning.export import load_model
    from lfgnss.benchmark import DEFAULT_MODEL, MODEL_DIR
    from lfgnss.datasets import load_split, present

    rows = []
    for dataset_id in present(list(DATASETS), report=lambda text: print(text, file=sys.stderr)):
        parts = load_split(dataset_id, split)
        for model in (DEFAULT_MODEL, f"lfgnss-{dataset_id}.npz"):
            noise = load_model(MODEL_DIR / model)        # once, not per part and option
            for label, options in SPLIT_ESTIMATORS.items():
                backend = label.split(",")[0]
                solutions = [estimators.create(backend, noise=noise, **options).solve(p) for p in parts]
                rows.append({"dataset": dataset_id, "split": split, "model": model.removesuffix(".npz")}
                            | consistency_row(label, parts, solutions))
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python benchmarks/sd_consistency.py", description=__doc__.split("\n")[0])
    p.add_argument("--write", action="store_true", help=f"write {DOC.relative_to(DOC.parents[1])}")
    p.add_argument("--splits", nargs="*", default=None, choices=("train", "val", "test"),
                   help="also the EKF and the factor graph on these splits of the shared datasets (default with "
                        "--write: val test)")
    args = p.parse_args(argv)
    splits = args.splits if args.splits is not None else (["val", "test"] if args.write else [])
    import lfgnss
    from lfgnss.datasets import read_truth
    from lfgnss.metrics import markdown_table
    from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
        truth = read_truth(SAMPLE_TRUTH, meas.time_gps_s, "smartloc")
        seq = lfgnss.build_sequence(meas, lfgnss.spp(meas), truth_ecef_m=truth, name="bundled Berlin drive")
        table = markdown_table(rows_for(seq))
    command = shlex.join(["python", "benchmarks/sd_consistency.py", *(sys.argv[1:] if argv is None else argv)])
    text = (f"# Are the reported standard deviations calibrated?\n\nProduced by `{command}` on the bundled Berlin "
            f"drive (lfgnss/data/berlin-potsdamer-platz, all {len(seq)} epochs, {int(seq.labelled.sum())} with "
            "truth; the drive of shared/BENCHMARK.md's berlin-pp, every split). Calibrated 1-sigma sds would put 68 % of the errors within 1 sd, 99.7 % within "
            "3 sd, and give a mean NEES of 3. The EKF's rows without \"formal\" are inflated by its pseudorange "
            "residuals (`estimators.consistency`, the default: `inflate_cov=True`); its form and time constant were "
            "chosen on the validation rows below (docs/findings.md), and the test rows only report. The factor "
            "graph's marginals (`covariances=True`) take the same factor since session 35, decided on the validation "
            "rows too; its default stand-in covariance (\"fgo\") does not.\n\n" + table)
    print(table, end="")
    for split in splits:
        rows = split_rows(split)
        if not rows:
            continue
        split_table = markdown_table(rows)
        text += (f"\n## The EKF and the factor graph on the {split} splits (shared/BENCHMARK.md), shipped and "
                 f"per-dataset models\n\n" + split_table)
        print(split_table, end="")
    if args.write:
        DOC.write_text(text)
        print(f"wrote {DOC}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
