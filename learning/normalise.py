"""Per-feature standardisation fitted on training Sequences (numpy only; torch is optional).

    x_norm = (x - mean) / std          valid slots;   x_norm = 0 in padded slots

Statistics come from the masked (valid) slots of the training split only and are stored in the
model file, so inference normalises exactly as training did.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from lfgnss.sequence import Sequence

#: A feature whose spread is below this is treated as constant (std := 1).
MIN_STD = 1e-6
#: Normalisers whose means and stds differ by at most this fraction of the std are the same (``same_as``): one
#: training split's features, computed on two machines, differ by ~1e-11 of it (berlin-pp's residual feature).
SAME_TOL = 1e-9


def select_features(sequence: Sequence, names: Iterable[str]) -> np.ndarray:
    """The named feature columns of ``sequence.features``, (T, N, len(names)), in ``names`` order.

    Raises ValueError naming the sequence and the missing features.
    """
    names = tuple(names)
    missing = [n for n in names if n not in sequence.feature_names]
    if missing:
        raise ValueError(f"sequence {sequence.name!r} lacks features {missing}; it has {list(sequence.feature_names)}")
    index = [sequence.feature_names.index(n) for n in names]
    return np.asarray(sequence.features, dtype=np.float64)[..., index]


@dataclass(frozen=True)
class Normaliser:
    """Feature names with their mean and std, each (d,)."""

    feature_names: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray

    def __post_init__(self) -> None:
        d = len(self.feature_names)
        if np.shape(self.mean) != (d,) or np.shape(self.std) != (d,):
            raise ValueError(f"normaliser: mean {np.shape(self.mean)} / std {np.shape(self.std)} must be ({d},)")
        if not (np.all(np.isfinite(self.mean)) and np.all(np.isfinite(self.std)) and np.all(self.std > 0)):
            raise ValueError("normaliser: mean/std must be finite and std > 0")

    @classmethod
    def fit(cls, sequences: Iterable[Sequence], feature_names: Iterable[str]) -> "Normaliser":
        """Mean and std of each named feature over the valid slots of ``sequences``.

        A non-finite feature in a valid slot is refused, naming it (the exported model refuses it at inference:
        ``learning.export.LfgnssModel.predict``; it used to drop the slot here and train on without a word).
        """
        names = tuple(feature_names)
        blocks = []
        for seq in sequences:
            full = select_features(seq, names)
            mask = np.asarray(seq.mask, bool)
            bad = mask[..., None] & ~np.isfinite(full)
            if bad.any():
                k, slot, j = (int(i[0]) for i in np.nonzero(bad))
                raise ValueError(f"normaliser: feature {names[j]!r} of sequence {getattr(seq, 'name', '?')!r} is not "
                                 f"finite at {int(bad[..., j].sum())} valid satellite slot(s) (first: epoch {k}, "
                                 f"slot {slot}): give numbers there or mask those slots out")
            blocks.append(full[mask])
        x = np.concatenate(blocks) if blocks else np.zeros((0, len(names)))
        if x.shape[0] == 0:
            raise ValueError("normaliser: no valid satellite slot in the training sequences")
        mean = x.mean(axis=0)
        std = x.std(axis=0)             # two passes: one, E[x^2] - mean^2, lost a small spread about a large mean
        std = np.where(std < MIN_STD, 1.0, std)
        return cls(names, mean, std)

    def same_as(self, other: "Normaliser") -> bool:
        """Whether ``other`` normalises as this one does: the same names, and means and stds within ``SAME_TOL``
        of this one's stds (the same training data's statistics, computed on another machine, differ in rounding)."""
        if tuple(self.feature_names) != tuple(other.feature_names) or self.mean.shape != other.mean.shape:
            return False
        tol = SAME_TOL * self.std
        return bool(np.all(np.abs(self.mean - other.mean) <= tol) and np.all(np.abs(self.std - other.std) <= tol))

    def apply(self, features: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Normalised copy of raw ``features`` (..., N, d) with padded slots (mask (..., N) False) zero."""
        x = (np.asarray(features, dtype=np.float64) - self.mean) / self.std
        valid = np.asarray(mask, bool)[..., None] & np.isfinite(x)
        return np.where(valid, x, 0.0)

    def apply_torch(self, features, mask):
        """As ``apply`` for torch tensors (dtype of ``features`` kept)."""
        import torch

        mean = torch.as_tensor(self.mean, dtype=features.dtype, device=features.device)
        std = torch.as_tensor(self.std, dtype=features.dtype, device=features.device)
        x = (features - mean) / std
        valid = mask.bool()[..., None] & torch.isfinite(x)
        return torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device))

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {"feature_names": list(self.feature_names), "mean": [float(v) for v in self.mean],
                "std": [float(v) for v in self.std]}

    @classmethod
    def from_dict(cls, data: dict) -> "Normaliser":
        """Inverse of ``to_dict``."""
        return cls(tuple(data["feature_names"]), np.asarray(data["mean"], float), np.asarray(data["std"], float))
