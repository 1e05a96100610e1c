"""How noisy each receiver's Dopplers are against C/N0, measured with the ground truth, and the EKF's law fitted.

    python benchmarks/doppler_noise.py                      # train splits, print the table
    python benchmarks/doppler_noise.py --write              # ... and write docs/doppler_noise.md and its PNG

Each Doppler pseudorange rate's error is taken at the true velocity (differences of the truth, [m/s]) once the
epoch's median over satellites (the receiver clock drift) is removed. Per 2.5 dB-Hz of C/N0 the robust sigma
(1.4826 median absolute error) is listed, and ``EkfConfig``'s Doppler law, ``sigma^2 (1 + 10^((ref - C/N0) / 5))``,
is fitted to those bins (log sigma, least squares weighted by the bin counts): the ``doppler_sigma_m_s`` and
``doppler_cn0_ref_dbhz`` that describe the split. Train splits by default, so nothing is read off a test split.
"""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from page import command_line, parse, publish, save_figure, script_parser  # noqa: E402  (a sibling module)

DOC = REPO / "docs" / "doppler_noise.md"
FIGURE = REPO / "docs" / "figures" / "doppler_noise.png"
BIN_DB = 2.5
MIN_PER_BIN = 30


def doppler_errors(seq) -> tuple[np.ndarray, np.ndarray]:
    """(C/N0 [dB-Hz], Doppler error [m/s]) of every used Doppler at a labelled epoch, the epoch median removed.

    The prediction is the filters' Doppler model (``lfgnss.velocity.doppler_design``) at the true position and
    velocity, with a zero clock drift: the median takes the drift out.
    """
    from lfgnss.velocity import doppler_design

    velocity = np.gradient(seq.truth_ecef_m, seq.time_gps_s, axis=0)
    offset, rows = doppler_design(seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s, seq.truth_ecef_m)
    predicted = offset + np.einsum("tni,ti->tn", rows[..., :3], velocity)
    ok = seq.prr_mask & seq.mask & np.all(np.isfinite(velocity), axis=-1)[:, None]
    error = np.where(ok, seq.prr_m_s - predicted, np.nan)
    with warnings.catch_warnings():          # epochs without a Doppler: all-NaN rows
        warnings.simplefilter("ignore", RuntimeWarning)
        error = error - np.nanmedian(error, axis=1, keepdims=True)
    ok &= np.isfinite(error)
    return seq.cn0_dbhz[ok], error[ok]


def law_sigma_m_s(cn0_dbhz: np.ndarray, sigma_m_s: float, ref_dbhz: float) -> np.ndarray:
    """Doppler sigma [m/s] of ``estimators.models.doppler_variance_m2_s2``'s law."""
    from estimators.models import EkfConfig, doppler_variance_m2_s2

    return np.sqrt(doppler_variance_m2_s2(cn0_dbhz, EkfConfig(doppler_sigma_m_s=sigma_m_s,
                                                               doppler_cn0_ref_dbhz=ref_dbhz)))


def fit_law(bins: list[dict]) -> tuple[float, float]:
    """(doppler_sigma_m_s, doppler_cn0_ref_dbhz) fitted to the bins' robust sigmas in log, weighted by counts."""
    from scipy.optimize import least_squares

    centre = np.array([b["cn0_dbhz"] for b in bins])
    sigma = np.array([b["sigma_m_s"] for b in bins])
    weight = np.sqrt([b["n"] for b in bins])
    fit = least_squares(lambda p: weight * (np.log(law_sigma_m_s(centre, np.exp(p[0]), p[1])) - np.log(sigma)),
                        [np.log(np.min(sigma)), float(np.median(centre))])
    return float(np.exp(fit.x[0])), float(fit.x[1])


def run(dataset_ids, split: str = "train") -> list[dict]:
    """One row per dataset: its C/N0 bins (robust sigma, count) and the fitted law."""
    from lfgnss import datasets

    rows = []
    for dataset_id in datasets.present(list(dataset_ids)):
        parts = [doppler_errors(s) for s in datasets.load_split(dataset_id, split)]
        cn0, error = (np.concatenate(p) for p in zip(*parts))
        if error.size == 0:
            raise ValueError(f"benchmarks/doppler_noise.py: {dataset_id} {split} has no Doppler at a labelled epoch")
        bins = []
        for low in np.arange(np.floor(cn0.min() / BIN_DB) * BIN_DB, cn0.max() + BIN_DB, BIN_DB):
            inside = (cn0 >= low) & (cn0 < low + BIN_DB)
            if inside.sum() >= MIN_PER_BIN:
                bins.append({"cn0_dbhz": float(low + BIN_DB / 2), "n": int(inside.sum()),
                             "sigma_m_s": float(1.4826 * np.median(np.abs(error[inside])))})
        if len(bins) < 2:
            raise ValueError(f"benchmarks/doppler_noise.py: {dataset_id} {split} has fewer than two C/N0 bins of "
                             f"{MIN_PER_BIN} Dopplers: too few to fit the law")
        sigma, ref = fit_law(bins)
        rows.append({"dataset": dataset_id, "split": split, "n": int(error.size), "bins": bins,
                     "doppler_sigma_m_s": sigma, "doppler_cn0_ref_dbhz": ref})
    return rows


def markdown(rows: list[dict], command: str) -> str:
    """The fitted laws, then the bins of every dataset (robust sigma [m/s] and count per C/N0 bin)."""
    out = ["# Doppler noise against C/N0, and the EKF's law fitted to it", "",
           f"Produced by `{command}`. Error of each Doppler pseudorange rate at the true velocity, the epoch's "
           "median removed; robust sigma = 1.4826 x median absolute error [m/s]. The law is `EkfConfig`'s "
           "(`doppler_sigma_m_s^2 (1 + 10^((doppler_cn0_ref_dbhz - C/N0) / 5))`), fitted in log to the bins.", "",
           "| dataset | split | Dopplers | doppler_sigma_m_s | doppler_cn0_ref_dbhz |", "| --- | --- | ---: | ---: | ---: |"]
    out += [f"| {r['dataset']} | {r['split']} | {r['n']} | {r['doppler_sigma_m_s']:.3f} | {r['doppler_cn0_ref_dbhz']:.1f} |"
            for r in rows]
    for r in rows:
        out += ["", f"## {r['dataset']} ({r['split']})", "", "| C/N0 [dB-Hz] | Dopplers | robust sigma [m/s] | law [m/s] |",
                "| ---: | ---: | ---: | ---: |"]
        law = law_sigma_m_s(np.array([b["cn0_dbhz"] for b in r["bins"]]), r["doppler_sigma_m_s"],
                            r["doppler_cn0_ref_dbhz"])
        out += [f"| {b['cn0_dbhz']:.2f} | {b['n']} | {b['sigma_m_s']:.3f} | {s:.3f} |" for b, s in zip(r["bins"], law)]
    out += ["", f"Figure: `figures/{FIGURE.name}`.", ""]
    return "\n".join(out)


def plot(rows: list[dict], path: Path) -> Path:
    """Robust sigma per C/N0 bin (points) and the fitted law (line) of every dataset, log scale."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for r in rows:
        centre = np.array([b["cn0_dbhz"] for b in r["bins"]])
        line = ax.semilogy(centre, [b["sigma_m_s"] for b in r["bins"]], "o", label=f"{r['dataset']} ({r['split']})")
        grid = np.linspace(centre.min(), centre.max(), 100)
        ax.semilogy(grid, law_sigma_m_s(grid, r["doppler_sigma_m_s"], r["doppler_cn0_ref_dbhz"]), "-",
                    color=line[0].get_color(), label=f"law: {r['doppler_sigma_m_s']:.3f} m/s, "
                                                     f"{r['doppler_cn0_ref_dbhz']:.1f} dB-Hz")
    ax.set_xlabel("C/N0 [dB-Hz]")
    ax.set_ylabel("Doppler robust sigma [m/s]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page and the figure."""
    p = script_parser(__doc__, f"write {DOC.relative_to(REPO)} and {FIGURE.name}")
    p.add_argument("--split", default="train", choices=("train", "val", "test"))
    args = parse(p, argv, "doppler_noise.py")
    if args is None:
        return 2
    rows = run(args.datasets, args.split)
    text = markdown(rows, command_line("doppler_noise.py", argv))
    return publish(text, DOC, args.write, FIGURE, lambda path: plot(rows, path))


if __name__ == "__main__":
    raise SystemExit(main())
