"""Windows of consecutive epochs cut from Sequences and collated into ``WindowBatch`` tensors.

Sources of Sequences are pluggable (see ``learning.train.load_sequences``); this module only needs
a list of ``lfgnss.sequence.Sequence``. Features are chosen by NAME (``feature_names``), so an
ablation such as "w/o DPC" is the default list minus the four ``dpc_*`` names - configuration only.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence as Seq

import numpy as np
import torch

from estimators import models
from lfgnss.errors import did_you_mean
from lfgnss.features import AVAILABLE_FEATURES
from lfgnss.sequence import DEFAULT_FEATURES, Sequence

from .normalise import Normaliser, select_features
from .types import WindowBatch

#: The DOP-contribution features dropped by the "w/o DPC" ablation.
DPC_FEATURES = ("dpc_gdop", "dpc_pdop", "dpc_hdop", "dpc_vdop")


def resolve_feature_names(names: Iterable[str] | None = None, drop: Iterable[str] = ()) -> tuple[str, ...]:
    """Feature list from configuration: ``names`` (default ``DEFAULT_FEATURES``) minus ``drop``.

    ``drop`` may contain the word ``"dpc"`` as shorthand for the four ``dpc_*`` features; any other name in it must
    be a feature (of ``names`` or ``lfgnss.features.AVAILABLE_FEATURES``): ValueError otherwise, so that a typo does
    not silently train on every feature.
    """
    base = tuple(names) if names is not None else DEFAULT_FEATURES
    for n in base:                      # checked here too, so a fine-tuning run (whose features are the model's) says so
        if n not in AVAILABLE_FEATURES:
            raise ValueError(f"data.features: unknown feature {n!r}{did_you_mean(n, list(AVAILABLE_FEATURES))}; "
                             f"available: {', '.join(AVAILABLE_FEATURES)}")
    known = list(dict.fromkeys(("dpc", *base, *AVAILABLE_FEATURES)))
    for d in drop:
        if d not in known:
            raise ValueError(f"data.drop_features: unknown feature {d!r}{did_you_mean(d, known)}; it takes names "
                             f"of data.features ({', '.join(base)}) or 'dpc' (the four dpc_* features)")
    drop_set: set[str] = set()
    for d in drop:
        drop_set.update(DPC_FEATURES if d == "dpc" else (d,))
    out = tuple(n for n in base if n not in drop_set)
    if not out:
        raise ValueError(f"no features left after dropping {sorted(drop_set)} from {list(base)}")
    if len(set(out)) != len(out):
        raise ValueError(f"duplicate feature names in {list(out)}")
    return out


def signed_log_names(logged: Iterable[str], features: Iterable[str], r_prior: str | None = None) -> tuple[str, ...]:
    """``data.signed_log`` as feature names (``"dpc"``: the four ``dpc_*`` features that ``features`` has).

    Each name must be one of ``features``; with ``r_prior = "heuristic"`` neither 'cn0' nor 'elevation' (the prior
    reads them back from the normalised inputs, in their own units). ValueError otherwise.
    """
    features = tuple(features)
    out: list[str] = []
    for name in logged:
        for n in ([d for d in DPC_FEATURES if d in features] if name == "dpc" else [name]):
            if n not in features:
                raise ValueError(f"data.signed_log: {n!r} is not a feature of the model "
                                 f"({', '.join(features)}){did_you_mean(n, list(features))}")
            if r_prior == "heuristic" and n in ("cn0", "elevation"):
                raise ValueError(f"data.signed_log: {n!r} must stay in its own units with model.r_prior = "
                                 "'heuristic' (the prior reads it)")
            if n not in out:
                out.append(n)
    return tuple(out)


@dataclass(frozen=True)
class Window:
    """Epochs ``start:start + length`` of ``sequences[seq_index]``; the first ``burn_in`` are not scored.

    A window cut from the middle of a drive starts the filter cold, from the coarse fix, where the
    filter it trains runs on from earlier epochs: its first epochs are a start-up transient that a
    deployed filter only has at the start of a drive. ``burn_in`` epochs run the filter (and pass
    gradients to later epochs) without their labels; a window at a sequence's start keeps all its
    labels (``make_windows``), because there the cold start is real.
    """

    seq_index: int
    start: int
    length: int
    burn_in: int = 0


def make_windows(sequences: Seq[Sequence], length: int, stride: int, burn_in: int = 0) -> list[Window]:
    """All windows of ``length`` epochs every ``stride`` epochs that contain at least one scored label.

    Windows that do not start a sequence leave their first ``burn_in`` epochs unscored (see ``Window``).
    A sequence shorter than ``length`` gives no window. Raises ValueError if no window results.
    """
    if length < 1 or stride < 1:
        raise ValueError(f"window length and stride must be >= 1, got {length}, {stride}")
    if not 0 <= burn_in < length:
        raise ValueError(f"burn_in must be >= 0 and shorter than the {length}-epoch window, got {burn_in}")
    out = []
    for i, seq in enumerate(sequences):
        labelled = seq.labelled
        for start in range(0, len(seq) - length + 1, stride):
            skip = burn_in if start > 0 else 0
            if labelled[start + skip:start + length].any():
                out.append(Window(i, start, length, skip))
    if not out:
        longest = max((len(s) for s in sequences), default=0)
        raise ValueError(f"no labelled window of {length} epochs in {[s.name for s in sequences]} (the longest piece "
                         f"has {longest} epochs): lower data.window, or give longer (labelled) splits")
    return out


def collate(sequences: Seq[Sequence], windows: Seq[Window], normaliser: Normaliser, *,
            n_slots: int | None = None, n_systems: int | None = None) -> WindowBatch:
    """Stack ``windows`` (equal lengths) into one WindowBatch.

    Satellite slots are padded to ``n_slots`` (default: the largest among the windows' sequences)
    and the clock columns to ``n_systems`` (default: the most constellations); padding is masked
    (slots) or zero (clock columns). Features are selected by ``normaliser.feature_names`` and
    normalised. Geometry is float64, features float32. A window's burn-in epochs get NaN truth (unscored).
    """
    if not windows:
        raise ValueError("collate: no window given")
    lengths = {w.length for w in windows}
    if len(lengths) != 1:
        raise ValueError(f"collate: windows of different lengths {sorted(lengths)}")
    used = [sequences[w.seq_index] for w in windows]
    n = max(s.n_slots for s in used) if n_slots is None else n_slots
    c = max(len(s.systems) for s in used) if n_systems is None else n_systems
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("time_gps_s", "pr_m", "sat_pos_ecef_m", "system_index",
                                                          "mask", "features", "coarse_ecef_m", "coarse_clock_m",
                                                          "truth_ecef_m", "prr_m_s", "prr_mask",
                                                          "sat_vel_ecef_m_s", "cn0_dbhz", "glonass")}
    for w in windows:
        seq = sequences[w.seq_index].subset(slice(w.start, w.start + w.length)).pad_to(n)
        clock = np.zeros((len(seq), c))
        clock[:, :len(seq.systems)] = seq.coarse_clock_m
        parts["time_gps_s"].append(seq.time_gps_s)
        parts["pr_m"].append(seq.pr_m)
        parts["sat_pos_ecef_m"].append(seq.sat_pos_ecef_m)
        parts["system_index"].append(seq.system_index)
        parts["mask"].append(seq.mask)
        parts["features"].append(normaliser.apply(select_features(seq, normaliser.feature_names), seq.mask))
        parts["coarse_ecef_m"].append(seq.coarse_ecef_m)
        parts["coarse_clock_m"].append(clock)
        truth = seq.truth_ecef_m.copy()
        truth[:w.burn_in] = np.nan
        parts["truth_ecef_m"].append(truth)
        parts["prr_m_s"].append(seq.prr_m_s)
        parts["prr_mask"].append(seq.prr_mask)
        parts["sat_vel_ecef_m_s"].append(seq.sat_vel_ecef_m_s)
        parts["cn0_dbhz"].append(seq.cn0_dbhz)
        parts["glonass"].append(models.glonass_slots(seq.system_index, seq.systems))
    dtypes = {"system_index": torch.int64, "mask": torch.bool, "prr_mask": torch.bool, "features": torch.float32,
              "glonass": torch.bool}
    return WindowBatch(**{k: torch.as_tensor(np.stack(v), dtype=dtypes.get(k, torch.float64))
                          for k, v in parts.items()})


def sequence_batch(sequence: Sequence, normaliser: Normaliser, *, n_systems: int | None = None) -> WindowBatch:
    """The whole sequence as a batch of one window (B = 1, T = len(sequence))."""
    return collate([sequence], [Window(0, 0, len(sequence))], normaliser, n_systems=n_systems)


def batches(sequences: Seq[Sequence], windows: Seq[Window], normaliser: Normaliser, batch_size: int,
            order: np.ndarray | None = None, *, n_slots: int | None = None, n_systems: int | None = None):
    """Yield WindowBatch objects of up to ``batch_size`` windows, in ``order`` (indices into windows)."""
    order = np.arange(len(windows)) if order is None else np.asarray(order)
    for k in range(0, len(order), batch_size):
        chosen = [windows[i] for i in order[k:k + batch_size]]
        yield collate(sequences, chosen, normaliser, n_slots=n_slots, n_systems=n_systems)
