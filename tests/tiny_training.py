"""Test helper: the settings of a training run of a few seconds on the synthetic dataset, as ``--set`` arguments."""
from __future__ import annotations

#: One epoch on 150 synthetic epochs in 20-epoch windows: enough for every file and line a run writes.
TINY = ["data.datasets=['synthetic']", "data.synthetic.n_epochs=150", "data.window=20", "data.stride=10",
        "train.batch_size=4", "threads=1", "train.epochs=1"]


def sets(settings: list[str]) -> list[str]:
    """``["--set", s, ...]`` for each setting ``s``."""
    return [x for s in settings for x in ("--set", s)]
