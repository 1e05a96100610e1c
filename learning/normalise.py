"""Per-feature standardisation fitted on training Sequences (numpy only; torch is optional).

    x_norm = (g(x) - mean) / std       valid slots;   x_norm = 0 in padded slots
    g(x) = sign(x) ln(1 + |x|)         for the features named in ``signed_log``;  g(x) = x for the others

The signed logarithm is for heavy-tailed features (the DOP contributions: a leave-one-out that leaves the geometry
singular is capped at -95 where most values lie within 0.3 of 0), whose few extreme slots would otherwise set the
std, squeeze every other value towards 0 and arrive at inference as hundreds of stds (docs/findings.md).

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


def signed_log(x):
    """sign(x) ln(1 + |x|), elementwise, for numpy arrays and torch tensors alike (odd, monotonic, ~x near 0)."""
    if isinstance(x, np.ndarray):
        return np.sign(x) * np.log1p(np.abs(x))
    import torch

    return torch.sign(x) * torch.log1p(torch.abs(x))


@dataclass(frozen=True)
class Normaliser:
    """Feature names with their mean and std, each (d,), of the features after ``signed_log`` (names, may be ())."""

    feature_names: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    signed_log: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        d = len(self.feature_names)
        object.__setattr__(self, "signed_log", tuple(self.signed_log))
        unknown = [n for n in self.signed_log if n not in self.feature_names]
        if unknown:
            raise ValueError(f"normaliser: signed_log names {unknown}, which are not among the features "
                             f"{list(self.feature_names)}")
        if np.shape(self.mean) != (d,) or np.shape(self.std) != (d,):
            raise ValueError(f"normaliser: mean {np.shape(self.mean)} / std {np.shape(self.std)} must be ({d},)")
        if not (np.all(np.isfinite(self.mean)) and np.all(np.isfinite(self.std)) and np.all(self.std > 0)):
            raise ValueError("normaliser: mean/std must be finite and std > 0")

    @property
    def log_columns(self) -> np.ndarray:
        """(d,) bool: which feature columns take the signed logarithm."""
        return np.array([n in self.signed_log for n in self.feature_names], bool)

    def transform(self, features: np.ndarray) -> np.ndarray:
        """Raw features (..., d) with the ``signed_log`` columns replaced by their signed logarithm (a copy)."""
        x = np.array(features, dtype=np.float64)
        cols = self.log_columns
        if cols.any():
            x[..., cols] = signed_log(x[..., cols])
        return x

    @classmethod
    def fit(cls, sequences: Iterable[Sequence], feature_names: Iterable[str],
            signed_log: Iterable[str] = ()) -> "Normaliser":
        """Mean and std of each named feature (after ``signed_log``'s) over the valid slots of ``sequences``.

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
        unit = cls(names, np.zeros(len(names)), np.ones(len(names)), tuple(signed_log))   # checks the names
        x = unit.transform(x)
        mean = x.mean(axis=0)
        std = x.std(axis=0)             # two passes: one, E[x^2] - mean^2, lost a small spread about a large mean
        std = np.where(std < MIN_STD, 1.0, std)
        return cls(names, mean, std, unit.signed_log)

    def same_as(self, other: "Normaliser") -> bool:
        """Whether ``other`` normalises as this one does: the same names, and means and stds within ``SAME_TOL``
        of this one's stds (the same training data's statistics, computed on another machine, differ in rounding)."""
        if (tuple(self.feature_names) != tuple(other.feature_names) or self.mean.shape != other.mean.shape
                or set(self.signed_log) != set(other.signed_log)):
            return False
        tol = SAME_TOL * self.std
        return bool(np.all(np.abs(self.mean - other.mean) <= tol) and np.all(np.abs(self.std - other.std) <= tol))

    def apply(self, features: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Normalised copy of raw ``features`` (..., N, d) with padded slots (mask (..., N) False) zero."""
        x = (self.transform(features) - self.mean) / self.std
        valid = np.asarray(mask, bool)[..., None] & np.isfinite(x)
        return np.where(valid, x, 0.0)

    def apply_torch(self, features, mask):
        """As ``apply`` for torch tensors (dtype of ``features`` kept)."""
        import torch

        mean = torch.as_tensor(self.mean, dtype=features.dtype, device=features.device)
        std = torch.as_tensor(self.std, dtype=features.dtype, device=features.device)
        cols = self.log_columns
        if cols.any():
            keep = torch.as_tensor(cols, device=features.device)
            features = torch.where(keep, signed_log(features), features)
        x = (features - mean) / std
        valid = mask.bool()[..., None] & torch.isfinite(x)
        return torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device))

    def to_dict(self) -> dict:
        """JSON-ready form."""
        out = {"feature_names": list(self.feature_names), "mean": [float(v) for v in self.mean],
               "std": [float(v) for v in self.std]}
        if self.signed_log:          # absent in the files of models trained before the option (all plain)
            out["signed_log"] = list(self.signed_log)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "Normaliser":
        """Inverse of ``to_dict``."""
        return cls(tuple(data["feature_names"]), np.asarray(data["mean"], float), np.asarray(data["std"], float),
                   tuple(data.get("signed_log", ())))
