"""Which cues tell pseudoranges more than 10 m off apart: areas under the ROC curve against the truth.

    python benchmarks/bad_pseudoranges.py            # train and val splits, print the tables
    python benchmarks/bad_pseudoranges.py --write    # ... and write docs/bad_pseudoranges.md and its PNG

A diagnostic, not a method: every usable pseudorange of an epoch with truth is labelled by its error at the true
position (``estimators.noise.constellation_residual_m``) less a receiver clock per epoch and constellation, taken
two ways: the median of the constellation's errors (``estimators.TruthNoise``'s clock) or the median of its three
strongest signals' errors (constellations with 5 satellites or more in the epoch). A pseudorange is bad when that
error exceeds 10 m in size (a second table: 20 m), late when it is positive. Each cue (C/N0, elevation, the coarse
and the weighted fix's |residual|, the |residual| of a Cauchy-reweighted (IRLS) weighted fix, the weighted |residual|
averaged over each satellite's last 1 / 3 / 10 s, the R of the dataset's own model and of the joint model) is scored
by the area under the ROC curve for bad against good, oriented so that 0.5 is chance and 1 ranks every bad signal as
worse than every good one. Train and validation splits only (the test split is never read); nothing is chosen from
these figures.
"""
from __future__ import annotations

import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from lfgnss.sequence import Sequence
    from lfgnss.weighted_fix import WeightedFix

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from page import command_line, nothing, parse, publish, save_figure, script_parser  # noqa: E402  (a sibling module)

DOC = REPO / "docs" / "bad_pseudoranges.md"
FIGURE = REPO / "docs" / "figures" / "bad_pseudoranges.png"
DATASETS = ("berlin-pp", "hk-tst-2019")
SPLITS = ("train", "val")                 # never the test split
SPLIT_WORDS = {"train": "train", "val": "validation"}
BAD_M = 10.0
FAR_M = 20.0                              # the second threshold's table
STRONG_DBHZ = 38.0
LABELLINGS = {"median": "each constellation's epoch median", "strongest 3": "median of its 3 strongest signals"}
WINDOWS_S = (1.0, 3.0, 10.0)
CUES = ("C/N0", "elevation", "coarse |residual|", "weighted-fix |residual|", "robust-fix |residual|",
        *(f"weighted |residual| {w:g} s" for w in WINDOWS_S), "R own model", "R joint model")
#: Cauchy constant: 95 % asymptotic efficiency at the normal (the usual choice, not tuned on these figures).
CAUCHY_C = 2.3849
#: MAD to standard deviation at the normal.
MAD_TO_SIGMA = 1.4826
#: Floor of the robust scale of the normalised residuals: an epoch that fits better than the variance law says does
#: not shrink the cut below ``CAUCHY_C`` sigmas of that law.
SCALE_FLOOR = 1.0
ROBUST_ITERATIONS = 5
#: An epoch ``dt`` before is in the last ``T`` s when ``dt < T - WINDOW_SLACK_S``: a 1 Hz receiver's epochs 0.996 or
#: 1.004 s apart (hk-tst-2019) then give the same window, ``round(T / interval)`` epochs.
WINDOW_SLACK_S = 0.05


def roc_auc(score: np.ndarray, positive: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` (higher = more likely positive): P(a positive scores above a negative),
    ties counted half; NaN when either class is empty. ValueError on non-finite scores or mismatched shapes."""
    score, positive = np.asarray(score, float).ravel(), np.asarray(positive, bool).ravel()
    if score.shape != positive.shape:
        raise ValueError(f"roc_auc: {score.size} scores for {positive.size} labels")
    if not np.isfinite(score).all():
        raise ValueError("roc_auc: scores must be finite (leave the others out)")
    n_pos = int(positive.sum())
    n_neg = positive.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    _, inverse, counts = np.unique(score, return_inverse=True, return_counts=True)
    mid_rank = np.cumsum(counts) - (counts - 1) / 2.0      # 1-based rank of each distinct value, ties averaged
    rank_sum = mid_rank[inverse.ravel()][positive].sum()
    return float((rank_sum - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))   # Mann-Whitney U / (n_pos n_neg)


def roc_curve(score: np.ndarray, positive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(false, true positive rate) at each distinct threshold of ``score``, from (0, 0) to (1, 1); its trapezoid area
    is ``roc_auc``. Both classes must be present."""
    score, positive = np.asarray(score, float).ravel(), np.asarray(positive, bool).ravel()
    order = np.argsort(-score, kind="stable")
    s, p = score[order], positive[order]
    last = np.r_[np.flatnonzero(np.diff(s) != 0), s.size - 1]          # last index of each group of equal scores
    tp, fp = np.cumsum(p)[last], np.cumsum(~p)[last]
    return np.r_[0.0, fp / max(fp[-1], 1)], np.r_[0.0, tp / max(tp[-1], 1)]


def strongest_clock_m(error_m: np.ndarray, cn0_dbhz: np.ndarray, ok: np.ndarray, system_index: np.ndarray,
                      n_systems: int) -> np.ndarray:
    """(T, N) each slot's epoch median of ``error_m`` [m] over the three highest-C/N0 ``ok`` slots of its
    constellation (equal C/N0: the lower slot first); NaN where that constellation has under five ok slots. The clock
    ``loss.r_clock = "strongest"`` trains against (``learning.loss.strongest_clock``), so the two cannot part."""
    import torch

    from learning.loss import strongest_clock

    clock, kept = strongest_clock(torch.as_tensor(np.where(ok, error_m, 0.0), dtype=torch.float64),
                                  torch.as_tensor(cn0_dbhz, dtype=torch.float64), torch.as_tensor(ok, dtype=torch.bool),
                                  torch.as_tensor(system_index, dtype=torch.int64), n_systems)
    return np.where(kept.numpy(), clock.numpy(), np.nan)


def truth_errors_m(sequence: "Sequence") -> dict[str, np.ndarray]:
    """{labelling: (T, N) error [m] at the true position less that labelling's clock}; NaN where not labelled."""
    from estimators.noise import constellation_residual_m

    ok = sequence.mask & sequence.labelled[:, None]
    median = constellation_residual_m(sequence, sequence.truth_ecef_m, ok)
    # the median clock is one value per epoch and constellation, so removing it first leaves the strongest-3 error
    strongest = median - strongest_clock_m(median, sequence.cn0_dbhz, ok, sequence.system_index,
                                           len(sequence.systems))
    return {"median": median, "strongest 3": strongest}


def cauchy_weight(u: np.ndarray, c: float = CAUCHY_C) -> np.ndarray:
    """Cauchy IRLS weight [-] of scaled residuals ``u`` [-]: ``1 / (1 + (u / c)^2)``."""
    return 1.0 / (1.0 + (np.asarray(u, float) / c) ** 2)


def robust_scale(u: np.ndarray, mask: np.ndarray, floor: float = SCALE_FLOOR) -> np.ndarray:
    """(T,) each epoch's 1.4826 MAD of the normalised residuals ``u`` (T, N) [-] over its ``mask`` slots, floored;
    ``floor`` where the epoch has none."""
    x = np.where(mask, np.asarray(u, float), np.nan)
    with warnings.catch_warnings():                 # epochs without a usable slot: all-NaN rows
        warnings.simplefilter("ignore", RuntimeWarning)
        mad = np.nanmedian(np.abs(x - np.nanmedian(x, axis=1, keepdims=True)), axis=1)
    return np.maximum(np.nan_to_num(MAD_TO_SIGMA * mad, nan=floor), floor)


def robust_fix(sequence: "Sequence", iterations: int = ROBUST_ITERATIONS) -> tuple["WeightedFix", np.ndarray]:
    """The C/N0-elevation weighted fix reweighted ``iterations`` times with Cauchy weights of its residuals normalised
    by the variance law's sigma and each epoch's ``robust_scale``: (fix, (T, N) last Cauchy weights [-])."""
    from lfgnss.features import fill_from_nearest_epoch
    from lfgnss.weighted_fix import cn0_elevation_variance_m2, weighted_least_squares

    mask, n_sys = sequence.mask, len(sequence.systems)
    r_m2 = cn0_elevation_variance_m2(sequence.cn0_dbhz, sequence.el_rad)

    def solve(start: np.ndarray, weight: np.ndarray) -> "WeightedFix":
        return weighted_least_squares(sequence.pr_m, sequence.sat_pos_ecef_m, sequence.system_index, mask, n_sys,
                                      start, r_m2 / weight)

    weight = np.ones(mask.shape)
    fix = solve(fill_from_nearest_epoch(sequence.coarse_ecef_m), weight)
    for _ in range(iterations):
        u = fix.residual_m / np.sqrt(r_m2)
        weight = np.where(mask, cauchy_weight(u / robust_scale(u, mask)[:, None]), 1.0)
        fix = solve(np.where(fix.ok[:, None], fix.pos_ecef_m, np.nan), weight)
    return fix, weight


def windowed_mean(time_s: np.ndarray, values: np.ndarray, usable: np.ndarray, window_s: float) -> np.ndarray:
    """(T, N) each slot's mean of ``values`` over its ``usable`` epochs of the last ``window_s`` seconds, the current
    one included (causal); NaN where the slot is not usable now. ``time_s`` (T,) [s] must not decrease."""
    time_s = np.asarray(time_s, float)
    if np.any(np.diff(time_s) < 0):
        raise ValueError("windowed_mean: epoch times must not decrease")
    usable = np.asarray(usable, bool)
    total = np.concatenate([np.zeros((1, usable.shape[1])), np.cumsum(np.where(usable, values, 0.0), axis=0)])
    count = np.concatenate([np.zeros((1, usable.shape[1]), int), np.cumsum(usable, axis=0)])
    first = np.searchsorted(time_s, time_s - (window_s - WINDOW_SLACK_S), side="right")   # oldest epoch inside
    n = count[1:] - count[first]
    return np.where(usable & (n > 0), (total[1:] - total[first]) / np.maximum(n, 1), np.nan)


def _feature(sequence: "Sequence", name: str) -> np.ndarray:
    """(T, N) the raw feature ``name``; NaN everywhere when the sequence was built without it."""
    if name not in sequence.feature_names:
        return np.full(sequence.mask.shape, np.nan)
    return sequence.features[..., sequence.feature_names.index(name)]


def signals(sequence: "Sequence", models: dict[str, Callable]) -> dict[str, np.ndarray]:
    """Flat arrays over the usable slots of labelled epochs: each labelling's error [m], C/N0 [dB-Hz], each cue
    oriented so that higher is worse, and the own model's v^c [m]."""
    ok = sequence.mask & sequence.labelled[:, None]
    out = {f"error {name}": e[ok] for name, e in truth_errors_m(sequence).items()}
    out["cn0"] = sequence.cn0_dbhz[ok]
    if not np.all(sequence.sv == sequence.sv[:1]):       # build_sequence: one slot per satellite of the file
        raise ValueError(f"bad_pseudoranges: {sequence.name}'s slots change satellite; the time averages need "
                         "one satellite per slot")
    weighted = np.abs(_feature(sequence, "residual_weighted"))
    fix, _ = robust_fix(sequence)
    cues = {"C/N0": -sequence.cn0_dbhz, "elevation": -sequence.el_rad,
            "coarse |residual|": np.abs(_feature(sequence, "residual")), "weighted-fix |residual|": weighted,
            # epochs too thin for the robust fix keep the weighted fix's residual, as residual_weighted does
            "robust-fix |residual|": np.where(fix.ok[:, None], np.abs(fix.residual_m), weighted)}
    for window in WINDOWS_S:
        cues[f"weighted |residual| {window:g} s"] = windowed_mean(sequence.time_gps_s, weighted, sequence.mask, window)
    for name, model in models.items():
        r_m2, vc_m = model(sequence)
        cues[f"R {name}"] = np.asarray(r_m2, float)
        if name == "own model":
            out["vc own model"] = np.asarray(vc_m, float)[ok]
    out.update({f"cue {name}": value[ok] for name, value in cues.items()})
    return out


def _aucs(sig: dict[str, np.ndarray], bad: np.ndarray, on: np.ndarray) -> dict[str, float]:
    """{cue: area under the ROC curve} over the slots ``on`` (each cue's finite values)."""
    out = {}
    for cue in CUES:
        score = sig[f"cue {cue}"]
        keep = on & np.isfinite(score)
        out[cue] = roc_auc(score[keep], bad[keep]) if keep.any() else float("nan")
    return out


def summary(sig: dict[str, np.ndarray], labelling: str) -> dict:
    """One row: counts, bad and late shares, the error's 5th percentile [m], the cues' areas (all signals and those
    of ``STRONG_DBHZ`` and above), the correlation of the own model's v^c with minus the error, and the count and
    areas (all signals) of those more than ``FAR_M`` off."""
    error = sig[f"error {labelling}"]
    on = np.isfinite(error)
    bad = on & (np.abs(np.nan_to_num(error)) > BAD_M)
    far = on & (np.abs(np.nan_to_num(error)) > FAR_M)
    strong = on & (sig["cn0"] >= STRONG_DBHZ)
    n_bad = int(bad.sum())
    vc = sig["vc own model"][on]
    nan = float("nan")
    return {"labelled": int(on.sum()), "n_bad": n_bad, "bad": n_bad / on.sum() if on.any() else nan,
            "late": float((error[bad] > 0).mean()) if n_bad else nan,
            "p5_m": float(np.percentile(error[on], 5)) if on.any() else nan,
            "vc_corr": float(np.corrcoef(vc, -error[on])[0, 1]) if on.sum() > 1 and vc.std() > 0 else nan,
            "auc": _aucs(sig, bad, on),
            "strong": {"labelled": int(strong.sum()), "n_bad": int(bad[strong].sum()),
                       "bad": float(bad[strong].mean()) if strong.any() else nan,
                       "of_bad": float(bad[strong].sum() / n_bad) if n_bad else nan,
                       "auc": _aucs(sig, bad, strong)},
            "far": {"n_bad": int(far.sum()), "bad": float(far.sum() / on.sum()) if on.any() else nan,
                    "auc": _aucs(sig, far, on)}}


def model_files(dataset_id: str) -> dict[str, Path]:
    """{"own model": the dataset's bundled model (else the joint one), "joint model": the joint one}."""
    from lfgnss.benchmark import MODEL_DIR

    own = MODEL_DIR / f"lfgnss-{dataset_id}.npz"
    joint = MODEL_DIR / "lfgnss-default.npz"
    return {"own model": own if own.exists() else joint, "joint model": joint}


def _concat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def run(dataset_ids: list[str], splits: tuple[str, ...] = SPLITS) -> tuple[list[dict], dict]:
    """Rows (dataset, split, labelling, ``summary``), the splits pooled as a last row per dataset and labelling when
    there are several, and the flat ``signals`` {(dataset, split): ...} for the figure."""
    from learning.export import load_model
    from lfgnss import datasets
    from lfgnss.sequence import DEFAULT_FEATURES

    if "test" in splits:
        raise ValueError("bad_pseudoranges: the test split is not read by this diagnostic")
    rows, kept = [], {}
    for dataset_id in datasets.present(list(dataset_ids)):
        files = model_files(dataset_id)
        models = {name: load_model(path) for name, path in files.items()}
        names = list(DEFAULT_FEATURES) + ["residual_weighted"]
        names += [n for m in models.values() for n in getattr(m, "feature_names", ()) if n not in names]
        per_split = {}
        for split in splits:
            seqs = datasets.load_split(dataset_id, split, feature_names=tuple(dict.fromkeys(names)))
            if seqs:
                per_split[split] = _concat([signals(s, models) for s in seqs])
            else:
                print(f"{dataset_id}: no labelled epoch in its {split} split: left out", file=sys.stderr)
        if len(per_split) > 1:
            per_split["+".join(per_split)] = _concat(list(per_split.values()))
        for split, sig in per_split.items():
            kept[(dataset_id, split)] = sig
            for labelling in LABELLINGS:
                rows.append({"dataset": dataset_id, "split": split, "labelling": labelling,
                             "models": {k: v.name for k, v in files.items()}, **summary(sig, labelling)})
    return rows, kept


def _f(x: float, fmt: str = ".3f") -> str:
    return "-" if not np.isfinite(x) else format(x, fmt)


def _pct(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{100 * x:.0f} %"


def _count(n: int, share: float) -> str:
    """``"5147 (47 %)"``; under 1 % with a decimal, so a handful does not read as none."""
    return f"{n} ({100 * share:.1f} %)" if 0 < share < 0.01 else f"{n} ({_pct(share)})"


def tables(rows: list[dict], labelling: str) -> list[str]:
    """Markdown lines: the labelling's table over all signals, its table over those of ``STRONG_DBHZ`` and up, and
    its areas for ``FAR_M`` over all signals."""
    mine = [r for r in rows if r["labelling"] == labelling]
    head = " | ".join(c.replace("|", "\\|") for c in CUES)
    out = ["### All signals", "",
           f"| dataset / split | labelled | bad | late of bad | error p5 [m] | {head} | corr(v^c, -error) |",
           "| --- |" + " ---: |" * (len(CUES) + 5)]
    for r in mine:
        out.append(f"| {r['dataset']} {r['split']} | {r['labelled']} | {_count(r['n_bad'], r['bad'])} | "
                   f"{_pct(r['late'])} | {_f(r['p5_m'], '.1f')} | " + " | ".join(_f(r["auc"][c]) for c in CUES)
                   + f" | {_f(r['vc_corr'], '.2f')} |")
    out += ["", f"### Signals of {STRONG_DBHZ:g} dB-Hz and above", "",
            f"| dataset / split | signals | bad | share of all bad | {head} |", "| --- |" + " ---: |" * (len(CUES) + 3)]
    for r in mine:
        s = r["strong"]
        out.append(f"| {r['dataset']} {r['split']} | {s['labelled']} | {_count(s['n_bad'], s['bad'])} | "
                   f"{_pct(s['of_bad'])} | " + " | ".join(_f(s["auc"][c]) for c in CUES) + " |")
    out += ["", f"### More than {FAR_M:g} m off: all signals", "",
            f"| dataset / split | labelled | bad (> {FAR_M:g} m) | {head} |", "| --- |" + " ---: |" * (len(CUES) + 2)]
    for r in mine:
        f = r["far"]
        out.append(f"| {r['dataset']} {r['split']} | {r['labelled']} | {_count(f['n_bad'], f['bad'])} | "
                   + " | ".join(_f(f["auc"][c]) for c in CUES) + " |")
    return out + [""]


def markdown(rows: list[dict], command: str, shown: tuple[str, str] | None = None) -> str:
    """The page: a header paragraph (naming the figure's dataset and split ``shown``, where one is drawn) and, per
    labelling, the two tables of ``tables``."""
    from learning.loss import STRONGEST_MIN_SATS

    models = "; ".join(f"{d}: `{r['models']['own model']}`" for d, r in
                       {r["dataset"]: r for r in rows}.items())
    out = ["# Telling bad pseudoranges apart", "",
           f"Produced by `{command}` (area under the ROC curve for a pseudorange more than {BAD_M:g} m off, bad "
           "against good: rank statistic, ties counted half, 0.5 is chance, 1 ranks every bad signal as worse). It "
           "reads the truth: a diagnostic, nothing is chosen from it, and only the train and validation splits are "
           "read (train+val: the two pooled). Labelled: each usable pseudorange of an epoch with truth, its error "
           "at the true position less a receiver clock per epoch and constellation: *median*, the constellation's "
           "epoch median (`estimators.TruthNoise`'s clock); *strongest 3*, the median of its three highest-C/N0 "
           "signals' errors (C/N0 comes in whole dB-Hz: ties broken by slot order), only where the constellation "
           f"has {STRONGEST_MIN_SATS} satellites or more in the epoch "
           "(the others are left out). Late: error > 0 (longer than the clock says). Cues, higher = worse: minus "
           "C/N0, minus elevation, |residual| of the equal-weight (coarse) fix and of the C/N0-elevation weighted "
           "fix (features `residual`, `residual_weighted`); robust-fix: |residual| of that weighted fix reweighted "
           f"{ROBUST_ITERATIONS} times by Cauchy weights 1 / (1 + (u / (c s))^2), u the residual over the variance "
           f"law's sigma, c = {CAUCHY_C:g} (95 % efficiency at the normal, not tuned), s the epoch's "
           f"{MAD_TO_SIGMA:g} MAD of u floored at {SCALE_FLOOR:g} (epochs it cannot fix keep the weighted "
           "residual); weighted |residual| T s: each satellite's weighted-fix |residual| averaged over the epochs "
           "of its last T seconds in which it was usable, the current one included (an epoch dt before counts when "
           f"dt < T - {WINDOW_SLACK_S:g} s: berlin-pp's 5 Hz gives 5 / 15 / 50 epochs, hk-tst-2019's 1 Hz 1 / 3 / "
           "10, so its 1 s column is the weighted-fix one); and the learned R of the dataset's own bundled model "
           f"({models}) and of the joint one (`lfgnss-default.npz`); the models were trained on the train splits, so "
           "only the validation rows are out of sample for them. corr(v^c, -error): Pearson correlation of the own "
           "model's v^c with minus the error. A third table per labelling scores the cues against a pseudorange "
           f"more than {FAR_M:g} m off instead. Over a handful of bad signals (the counts) an area is noise."
           + (f" Figure: `figures/{FIGURE.name}` (ROC curves, {shown[0]}'s {SPLIT_WORDS[shown[1]]} split)."
              if shown else ""),
           ""]
    for labelling, words in LABELLINGS.items():
        out += [f"## Clock: {labelling} ({words})", ""] + tables(rows, labelling)
    return "\n".join(out)


def shown_split(kept: dict) -> tuple[str, str] | None:
    """The (dataset, split) of ``kept`` the figure draws: the first validation split, else the first split kept."""
    return next((key for key in kept if key[1] == "val"), next(iter(kept), None))


def plot(kept: dict, path: Path, dataset_id: str, split: str = "val") -> Path:
    """ROC curves of every cue for ``dataset_id``'s ``split``, one panel per labelling."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sig = kept[(dataset_id, split)]
    fig, axes = plt.subplots(1, len(LABELLINGS), figsize=(5 * len(LABELLINGS), 4.6), squeeze=False)
    for ax, labelling in zip(axes[0], LABELLINGS):
        error = sig[f"error {labelling}"]
        for cue in CUES:
            score = sig[f"cue {cue}"]
            keep = np.isfinite(error) & np.isfinite(score)
            bad = np.abs(error[keep]) > BAD_M
            if bad.any() and not bad.all():
                fpr, tpr = roc_curve(score[keep], bad)
                ax.plot(fpr, tpr, lw=1.2, label=f"{cue} ({roc_auc(score[keep], bad):.3f})")
        ax.plot([0, 1], [0, 1], color="k", lw=0.8, ls=":")
        ax.set_title(f"{dataset_id} {split}, clock: {labelling}")
        ax.set_xlabel("good signals flagged (false positive rate)")
        ax.set_ylabel(f"bad (> {BAD_M:g} m) signals flagged")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page and the figure."""
    p = script_parser(__doc__, f"write {DOC.relative_to(REPO)} and {FIGURE.name}", DATASETS, SPLITS)
    args = parse(p, argv, "bad_pseudoranges.py")
    if args is None:
        return 2
    rows, kept = run(args.datasets, tuple(args.splits))
    if not rows:
        return nothing("bad_pseudoranges.py", "no dataset with its files: nothing to score")
    shown = shown_split(kept)
    draw = (lambda path: plot(kept, path, *shown)) if shown else None
    return publish(markdown(rows, command_line("bad_pseudoranges.py", argv), shown), DOC, args.write, FIGURE, draw)


if __name__ == "__main__":
    raise SystemExit(main())
