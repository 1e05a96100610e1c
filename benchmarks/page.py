"""What the benchmark scripts share: their command line and how each publishes its Markdown page and figure.

A script parses with ``script_parser`` + ``parse``, computes its rows, and ends with ``publish`` (or ``nothing`` when
no dataset had its files):

    p = script_parser(__doc__, "write docs/x.md and x.png", splits=("train", "val"))
    args = parse(p, argv, "x.py")
    if args is None:
        return 2
    ...
    return publish(text, DOC, args.write, FIGURE, draw)
"""
from __future__ import annotations

import argparse
import shlex
import sys
import warnings
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
DATASETS = ("hk-tst-2019", "berlin-pp", "hk-tst-static-2020")


def script_parser(doc: str, write_help: str, datasets: tuple[str, ...] = DATASETS,
                  splits: tuple[str, ...] | None = None) -> argparse.ArgumentParser:
    """The benchmark scripts' command line: ``--datasets`` (default ``datasets``), ``--write`` and, given ``splits``,
    ``--splits`` (one or more of them, all by default)."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--datasets", nargs="+", default=list(datasets),
                   help=f"benchmark dataset ids (default: {' '.join(datasets)})")
    p.add_argument("--write", action="store_true", help=write_help)
    if splits is not None:
        p.add_argument("--splits", nargs="+", default=list(splits), choices=splits)
    return p


def parse(p: argparse.ArgumentParser, argv: list[str] | None, script: str) -> argparse.Namespace | None:
    """``p``'s arguments, with the repository importable and georinex's FutureWarnings quiet; None, after a one-line
    error, when a dataset named is not registered."""
    args = p.parse_args(argv)
    warnings.simplefilter("ignore", FutureWarning)
    sys.path.insert(0, str(REPO))
    return None if unknown_datasets(script, args.datasets) else args


def unknown_datasets(script: str, dataset_ids: list[str]) -> bool:
    """True, with a one-line error naming them, if any of ``dataset_ids`` is not a registered dataset."""
    from lfgnss import datasets

    unknown = [d for d in dataset_ids if d not in datasets.registered()]
    if unknown:
        print(f"{script}: unknown dataset {', '.join(unknown)}; known: {', '.join(datasets.registered())}",
              file=sys.stderr)
    return bool(unknown)


def nothing(script: str, why: str) -> int:
    """One line on stderr saying there is nothing to publish (``why``); exit status 2."""
    print(f"{script}: {why}", file=sys.stderr)
    return 2


def publish(text: str, doc: Path, write: bool, figure: Path | None = None,
            draw: Callable[[Path], Path] | None = None) -> int:
    """Print the page; with ``write`` also write it to ``doc`` and draw the ``figure`` (``draw(figure)``), or, when
    this run has no figure to draw, remove the one an earlier run left (the caller's page must then not name it). Exit
    status 0."""
    if draw is not None and figure is None:
        raise ValueError("publish: a figure to draw needs its path")
    print(text)
    if write:
        doc.write_text(text)
        said = f"written: {doc}"
        if figure is not None and draw is not None:
            said += f", {draw(figure)}"
        elif figure is not None and figure.exists():
            figure.unlink()
            said += f"; removed {figure} (this run draws none)"
        print(said)
    return 0


def command_line(script: str, argv: list[str] | None) -> str:
    """The command as typed, for the page's header."""
    return shlex.join(["python", f"benchmarks/{script}", *(sys.argv[1:] if argv is None else argv)])


def save_figure(fig, path: Path) -> Path:
    """Lay ``fig`` out, write it to ``path`` (making its folder) and close it; returns ``path``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
