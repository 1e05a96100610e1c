"""``python -m lfgnss.summary``: look at a dataset's features before training.

Prints per-dataset (and per-constellation) statistics of the packed features and writes two PNGs per
dataset: a sky plot coloured by the coarse pseudorange residual, and C/N0 against the residual.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from . import datasets
from .errors import path_option, print_stdout, run_command
from .help_text import PlainHelp
from .outputs import save_figure
from .paths import check_output_folder
from .sequence import Sequence


def feature_statistics(seq: Sequence) -> list[dict]:
    """One row per constellation and one for all: satellites per epoch, C/N0 and |residual| percentiles."""
    names = list(seq.feature_names)
    rows = []
    groups = [("all", seq.mask)] + [(s, seq.mask & (seq.system_index == k)) for k, s in enumerate(seq.systems)]
    for label, m in groups:
        cn0 = seq.cn0_dbhz[m]
        res = np.abs(seq.features[..., names.index("residual")][m]) if "residual" in names else np.zeros(0)
        row = {"dataset": seq.name, "system": label, "epochs": len(seq),
               "sats_per_epoch": float(m.sum(1).mean()) if len(seq) else 0.0,
               "cn0_p5_dbhz": np.percentile(cn0, 5) if cn0.size else np.nan,
               "cn0_p50_dbhz": np.percentile(cn0, 50) if cn0.size else np.nan,
               "abs_res_p50_m": np.percentile(res, 50) if res.size else np.nan,
               "abs_res_p95_m": np.percentile(res, 95) if res.size else np.nan}
        rows.append(row)
    return rows


#: Sky plot marker of each constellation (by letter).
SKY_MARKERS = {"G": "o", "R": "s", "E": "^", "C": "D", "J": "v"}


def plot_features(seq: Sequence, out_dir: Path, prefix: str) -> list[Path]:
    """Sky plot (a marker per constellation, each satellite named at its last position, colour |residual| up to its
    95th percentile) and C/N0-vs-residual scatter, as PNGs."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    out_dir.mkdir(parents=True, exist_ok=True)
    m = seq.mask
    residual = seq.features[..., list(seq.feature_names).index("residual")]
    res = residual[m]
    written = []

    fig = Figure(figsize=(7, 7))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="polar")
    ax.set_theta_zero_location("N")
    ax.set_theta_direction(-1)
    az, zenith = seq.az_rad, 90.0 - np.degrees(seq.el_rad)
    top = float(np.percentile(np.abs(res), 95)) if res.size else 1.0
    norm = Normalize(0.0, max(top, 1.0))                # the 95th percentile: a few outliers would wash out the rest
    sc = None
    for k, letter in enumerate(seq.systems):
        sel = m & (seq.system_index == k)
        if sel.any():
            sc = ax.scatter(az[sel], zenith[sel], c=np.abs(residual[sel]), s=4, cmap="viridis", norm=norm,
                            marker=SKY_MARKERS.get(letter, "o"), label=letter)
    for name in np.unique(seq.sv[m]):                   # each satellite named where it was last seen
        k, j = np.argwhere((seq.sv == name) & m)[-1]
        ax.annotate(str(name), (az[k, j], zenith[k, j]), fontsize=6, alpha=0.8)
    ax.set_rlim(0, 90)
    ax.set_yticks([0, 30, 60, 90], labels=["", "60°", "30°", ""])     # elevation; the rim (0°) holds the azimuths
    ax.set_rlabel_position(22.5)
    if sc is not None:
        fig.colorbar(sc, ax=ax, label=f"|coarse residual| [m] (to its 95th percentile, {top:.0f} m)", shrink=0.8,
                     pad=0.1)
        ax.legend(loc="lower left", bbox_to_anchor=(-0.12, -0.12), markerscale=3, title="constellation")
    ax.set_title(f"{seq.name}: sky plot (azimuth, elevation)")
    written.append(save_figure(out_dir / f"{prefix}skyplot.png", fig, dpi=110))

    fig = Figure(figsize=(6, 4))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    for k, s in enumerate(seq.systems):
        sel = seq.system_index[m] == k
        ax.scatter(seq.cn0_dbhz[m][sel], res[sel], s=2, alpha=0.4, label=s)
    ax.set_xlabel("C/N0 [dB-Hz]")
    ax.set_ylabel("coarse residual [m]")
    if res.size:                                         # the data's range, not a fixed one that dropped points
        ax.set_ylim(*np.percentile(res, [0.5, 99.5]) + np.array([-5.0, 5.0]))
    ax.grid(True, alpha=0.3)
    ax.legend(markerscale=5)
    ax.set_title(f"{seq.name}: C/N0 vs residual")
    written.append(save_figure(out_dir / f"{prefix}cn0_residual.png", fig, dpi=110))
    return written


def main(argv: list[str] | None = None) -> int:
    """Print feature statistics of datasets and write their plots.

    Exit status 0; 2 for bad input (one line ``error: ...``: an unknown id, a bad TOML, an --out that takes no file,
    a dataset asked for whose files are missing); 3 for an internal error; 130 for Ctrl-C.
    """
    p = argparse.ArgumentParser(prog="python -m lfgnss.summary", description=__doc__.split("\n\n")[0],
                                formatter_class=PlainHelp)
    p.add_argument("ids", nargs="*", help="dataset ids (default: the registered TOML datasets, else the "
                                          "three benchmark datasets)")
    p.add_argument("--register", action="append", default=[], metavar="TOML", help="user dataset config")
    p.add_argument("--out", type=path_option, default=Path("lfgnss-summary"), help="folder for the PNGs")
    args = p.parse_args(argv)
    return run_command(lambda: _summarise(args), "the summary")


def _summarise(args: argparse.Namespace) -> int:
    """:func:`main`'s work: the ids checked and built, the table printed, the plots written."""
    import pandas as pd

    registered = [datasets.register_toml(t).id for t in args.register]
    asked = list(dict.fromkeys([*args.ids, *registered]))       # a dataset named and registered too: once
    ids = asked or ["hk-tst-2019", "berlin-pp", "hk-tst-static-2020"]
    for dataset_id in ids:
        datasets.get(dataset_id)                                # an unknown id before any work
    missing = [f"{i}: {datasets.get(i).missing_note()}" for i in asked if datasets.get(i).missing()]
    if missing:
        raise FileNotFoundError(f"dataset not built: {'; '.join(missing)}")
    check_output_folder(args.out)                            # made by the first plot: none without a dataset
    rows, written = [], []
    for dataset_id in datasets.present(ids):
        seq = datasets.build(dataset_id)
        rows += feature_statistics(seq)
        written += plot_features(seq, args.out, f"{dataset_id}-")
    if rows:
        print_stdout(pd.DataFrame(rows).to_string(index=False, float_format=lambda v: f"{v:.1f}"))
    print_stdout(f"plots: {', '.join(str(w) for w in written)}" if written else "no dataset found (the benchmark data are "
          "read from $LFGNSS_SHARED_DATA, else ../shared/data; --register FILE.toml adds one of your own)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
