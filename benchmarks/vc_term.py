"""How well each cross-validation fold model's v^c predicts the true pseudorange errors of its held-out block.

    python benchmarks/vc_term.py RUN_DIR [RUN_DIR ...]

RUN_DIR is the ``--out`` folder of ``python -m learning.crossval`` (3 folds unless ``--folds``); the data
settings are read from its fold checkpoints. Each fold's ``last.pt`` is scored on its held-out block of the train +
validation epochs (never test) with ``learning.loss.compensation_loss``: the mean Huber (5 m) of v^c + e, e being
each pseudorange's error at the true position, with the figure for v^c = 0 beside it. This is the loss term of
``loss.vc_weight`` (docs/training/cv-vc-supervision.md); nothing is trained or chosen from it.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch


def held_out_terms(run_dir: str | Path, folds: int = 3) -> tuple[float, float]:
    """(term of the fold models' v^c, term of v^c = 0) [m^2], pooled over the held-out satellites of every fold."""
    from learning.crossval import cv_sequences, fold_sequences
    from learning.data import sequence_batch
    from learning.loss import compensation_loss, labelled_errors_m
    from learning.train import checkpoint_network, read_checkpoint

    whole: dict = {}
    sums, count = [0.0, 0.0], 0
    for fold in range(folds):
        saved = read_checkpoint(Path(run_dir) / f"fold{fold}" / "last.pt")
        whole = whole or cv_sequences(saved["config"])
        model, normaliser = checkpoint_network(saved)
        model.eval()
        n_systems = int(saved["n_systems"])
        for sequences in whole.values():
            for piece in fold_sequences(sequences, folds, fold)[1]:
                batch = sequence_batch(piece, normaliser, n_systems=n_systems)
                with torch.no_grad():
                    _, vc = model(batch.features, batch.mask)
                usable, error = labelled_errors_m(batch, n_systems)
                n = int(usable.sum())
                if not n:
                    continue
                for k, v in enumerate((vc, torch.zeros_like(vc))):
                    sums[k] += float(compensation_loss(v, error, usable, batch.system_index, n_systems)) * n
                count += n
    if not count:
        raise ValueError(f"{run_dir}: no labelled satellite in the held-out blocks")
    return sums[0] / count, sums[1] / count


def main(argv: list[str] | None = None) -> int:
    """Print one line per run: its held-out term and the term with v^c = 0."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--folds", type=int, default=3)
    parser.add_argument("runs", nargs="+", help="learning.crossval --out folders")
    args = parser.parse_args(argv)
    for run in args.runs:
        term, zero = held_out_terms(run, args.folds)
        print(f"{run}: held-out v^c term {term:.2f} m^2 (v^c = 0: {zero:.2f} m^2)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
