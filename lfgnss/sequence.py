"""The padded per-epoch sequence that every estimator and the trainer consume."""
from __future__ import annotations

import os
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Iterable

import numpy as np

from .errors import InputError
from .frames import check_in_orbit, check_near_surface
from .time import gpst_stamp

#: Default LF-GNSS feature set, in packing order (see lfgnss.features).
DEFAULT_FEATURES = ("cn0", "elevation", "azimuth", "residual", "dpc_gdop", "dpc_pdop", "dpc_hdop", "dpc_vdop")


def time_span_text(time_gps_s: np.ndarray) -> str:
    """The span of GPS times [s] in words: ``2016-06-06 11:10:41.7 to 11:15:25.1 GPST (283.4 s)``."""
    t = np.asarray(time_gps_s, float).ravel()
    t = t[np.isfinite(t)]
    if not t.size:
        return "no epoch times"
    first, last = (gpst_stamp(x, 1) for x in (t.min(), t.max()))
    end = last[11:] if last[:10] == first[:10] else last
    return f"{first} to {end} GPST ({t.max() - t.min():.1f} s)"


def epochs_text(n: int) -> str:
    """``"1 epoch"``, ``"5 epochs"``."""
    return f"{n} epoch{'' if n == 1 else 's'}"


def share_text(flags: np.ndarray, what: str) -> str:
    """``"85.2% labelled"``: the share of True in ``flags`` [%], or ``"none labelled"`` when there are none."""
    flags = np.asarray(flags, bool)
    if not flags.size or not flags.any():
        return f"none {what}"
    return f"{100.0 * flags.mean():.1f}% {what}"


@dataclass(frozen=True, eq=False, repr=False)
class Sequence:
    """Consecutive epochs of one receiver, padded to ``N`` satellite slots.

    ``repr`` is one line (name, epochs, slots, systems, time span, labelled share); ``==`` is identity, as the
    arrays have no single truth value (compare fields with ``np.array_equal`` for equal contents).

    Shapes: ``T`` epochs, ``N`` slots, ``C = len(systems)`` constellations, ``d`` features.
    Padded or unusable slots have ``mask == False``; their numbers are finite (zeros) and must not
    influence any result.

    Attributes
    ----------
    name : str
        Label, e.g. ``"hk-tst-2019/test"``.
    systems : tuple of str
        Constellation letters present; ``systems[0]`` owns the receiver clock, every further one an
        inter-system bias (ISB).
    time_gps_s : (T,) float
        Epoch time, GPS seconds since 1980-01-06.
    sv : (T, N) str
        Satellite ids such as ``"G05"``; ``""`` in padded slots.
    system_index : (T, N) int
        Index into ``systems``; -1 in padded slots.
    mask : (T, N) bool
        True where the measurement passed coarse quality control.
    pr_m : (T, N) float
        Pseudorange corrected for satellite clock (with relativity and group delay), troposphere and
        ionosphere [m]; the receiver clock and the Sagnac term are still in it.
    sat_pos_ecef_m : (T, N, 3) float
        Satellite position at signal transmission, ECEF frame of transmission time [m]; the range
        model is ``lfgnss.corrections.geometric_range_m`` (Sagnac term included there).
    cn0_dbhz, el_rad, az_rad : (T, N) float
        Carrier-to-noise density [dB-Hz], elevation and azimuth [rad] from the coarse fix.
    features : (T, N, d) float
        Raw (un-normalised) features named by ``feature_names``.
    coarse_ecef_m : (T, 3) float
        Equal-weight least-squares fix [m]; NaN where the epoch had none.
    coarse_clock_m : (T, C) float
        Receiver clock of ``systems[0]`` then ISBs of the others from the coarse fix [m]; NaN if none.
    truth_ecef_m : (T, 3) float
        Ground truth [m]; NaN where the epoch has no label.
    prr_m_s : (T, N) float, optional
        Pseudorange rate from Doppler, ``-lambda D``, corrected for the satellite clock drift [m/s];
        the receiver clock drift is still in it. Zeros where ``prr_mask`` is False.
    prr_mask : (T, N) bool, optional
        True where the slot's pseudorange is usable and it has a Doppler measurement.
    sat_vel_ecef_m_s : (T, N, 3) float, optional
        Satellite velocity at transmission, ECEF [m/s].

    The three Doppler arrays default to "no Doppler" (zeros, all False), so sequences built without
    Doppler stay valid; estimators then use pseudoranges only.
    """

    name: str
    systems: tuple[str, ...]
    time_gps_s: np.ndarray
    sv: np.ndarray
    system_index: np.ndarray
    mask: np.ndarray
    pr_m: np.ndarray
    sat_pos_ecef_m: np.ndarray
    cn0_dbhz: np.ndarray
    el_rad: np.ndarray
    az_rad: np.ndarray
    features: np.ndarray
    feature_names: tuple[str, ...]
    coarse_ecef_m: np.ndarray
    coarse_clock_m: np.ndarray
    truth_ecef_m: np.ndarray
    prr_m_s: np.ndarray | None = None
    prr_mask: np.ndarray | None = None
    sat_vel_ecef_m_s: np.ndarray | None = None

    def __post_init__(self) -> None:
        t, n = self.mask.shape
        for key, shape, dtype in (("prr_m_s", (t, n), float), ("prr_mask", (t, n), bool),
                                  ("sat_vel_ecef_m_s", (t, n, 3), float)):
            if getattr(self, key) is None:
                object.__setattr__(self, key, np.zeros(shape, dtype))
        expect = {"time_gps_s": (t,), "sv": (t, n), "system_index": (t, n), "pr_m": (t, n),
                  "sat_pos_ecef_m": (t, n, 3), "cn0_dbhz": (t, n), "el_rad": (t, n), "az_rad": (t, n),
                  "features": (t, n, len(self.feature_names)), "coarse_ecef_m": (t, 3),
                  "coarse_clock_m": (t, len(self.systems)), "truth_ecef_m": (t, 3), "prr_m_s": (t, n),
                  "prr_mask": (t, n), "sat_vel_ecef_m_s": (t, n, 3)}
        for key, shape in expect.items():
            got = np.shape(getattr(self, key))
            if got != shape:
                raise ValueError(f"Sequence {self.name!r}: {key} has shape {got}, expected {shape}")
        for key in ("mask", "prr_mask"):            # used as indices and in logical ops: 0/1 ints would not do
            dtype = np.asarray(getattr(self, key)).dtype
            if dtype != bool:
                raise ValueError(f"Sequence {self.name!r}: {key} must be a bool array, got dtype {dtype} "
                                 f"(.astype(bool) makes one)")
        if not np.issubdtype(np.asarray(self.system_index).dtype, np.integer):
            raise ValueError(f"Sequence {self.name!r}: system_index must be an integer array, got dtype "
                             f"{np.asarray(self.system_index).dtype}")
        owner = f"Sequence {self.name!r}"
        for key in ("time_gps_s", "pr_m", "sat_pos_ecef_m", "coarse_ecef_m", "coarse_clock_m", "truth_ecef_m"):
            dtype = np.asarray(getattr(self, key)).dtype
            if dtype.kind == "f" and dtype.itemsize < 8:     # float32 steps: 2 m at 2e7 m, 128 s at 1.2e9 s
                raise ValueError(f"{owner}: {key} must be float64, got {dtype} (which rounds satellite ranges to "
                                 f"metres and GPS times to minutes): .astype(float) before rounding, from the source")
        check_near_surface(owner, "truth_ecef_m", self.truth_ecef_m)
        check_near_surface(owner, "coarse_ecef_m", self.coarse_ecef_m)
        check_in_orbit(owner, "sat_pos_ecef_m (used slots)", np.asarray(self.sat_pos_ecef_m)[self.mask])

    def __len__(self) -> int:
        return int(self.mask.shape[0])

    def __repr__(self) -> str:
        """One line: name, epochs, slots, systems, time span and labelled share (no arrays)."""
        return (f"<Sequence {self.name!r}: {epochs_text(len(self))}, {self.n_slots} slots, systems {''.join(self.systems)}, "
                f"{time_span_text(self.time_gps_s)}, {share_text(self.labelled, 'labelled')}>")

    @property
    def labelled(self) -> np.ndarray:
        """(T,) bool: epochs with a ground-truth position."""
        return np.all(np.isfinite(self.truth_ecef_m), axis=-1)

    @property
    def n_slots(self) -> int:
        """Number of padded satellite slots N."""
        return int(self.mask.shape[1])

    def subset(self, index: slice | np.ndarray | int, name: str | None = None) -> "Sequence":
        """Epochs selected by a slice, boolean mask, index array or one index, as a new Sequence."""
        if isinstance(index, (int, np.integer)) and not isinstance(index, bool):
            index = np.array([index])
        per_epoch = {f.name: getattr(self, f.name)[index] for f in fields(self)
                     if isinstance(getattr(self, f.name), np.ndarray)}
        return replace(self, name=name or self.name, **per_epoch)

    def pad_to(self, n_slots: int) -> "Sequence":
        """The same sequence with ``n_slots`` satellite slots (>= current), new slots masked."""
        extra = n_slots - self.n_slots
        if extra < 0:
            raise ValueError(f"cannot pad {self.n_slots} slots down to {n_slots}")
        if extra == 0:
            return self

        def pad(a: np.ndarray, value) -> np.ndarray:
            width = [(0, 0)] * a.ndim
            width[1] = (0, extra)
            return np.pad(a, width, constant_values=value)

        return replace(self, sv=pad(self.sv, ""), system_index=pad(self.system_index, -1),
                       mask=pad(self.mask, False), pr_m=pad(self.pr_m, 0.0),
                       sat_pos_ecef_m=pad(self.sat_pos_ecef_m, 0.0), cn0_dbhz=pad(self.cn0_dbhz, 0.0),
                       el_rad=pad(self.el_rad, 0.0), az_rad=pad(self.az_rad, 0.0),
                       features=pad(self.features, 0.0), prr_m_s=pad(self.prr_m_s, 0.0),
                       prr_mask=pad(self.prr_mask, False), sat_vel_ecef_m_s=pad(self.sat_vel_ecef_m_s, 0.0))


def concat_sequences(parts: Iterable[Sequence], name: str | None = None) -> Sequence:
    """Sequences of one receiver, one after another, as one Sequence (slots padded to the widest; times in GPS s)."""
    parts = list(parts)
    if not parts:
        raise ValueError("concat_sequences: no sequences given")
    for k, part in enumerate(parts):
        if not isinstance(part, Sequence):
            raise TypeError(f"concat_sequences: part {k} is a {type(part).__name__}, not an lfgnss.Sequence")
    first = parts[0]
    for k, part in enumerate(parts[1:], 1):
        for key in ("systems", "feature_names"):
            if getattr(part, key) != getattr(first, key):
                raise ValueError(f"concat_sequences: part {k} ({part.name!r}) has {key} {getattr(part, key)}, part 0 "
                                 f"({first.name!r}) {getattr(first, key)}; build every part with the same systems and "
                                 f"feature_names")
    for k, (before, part) in enumerate(zip(parts, parts[1:]), 1):
        if len(before) and len(part) and not part.time_gps_s[0] > before.time_gps_s[-1]:
            raise ValueError(f"concat_sequences: part {k} ({part.name!r}) starts at {part.time_gps_s[0]:.3f} s, not "
                             f"after part {k - 1} ({before.name!r}) ends ({before.time_gps_s[-1]:.3f} s GPS); give "
                             f"the parts in time order")
    width = max(part.n_slots for part in parts)
    parts = [part.pad_to(width) for part in parts]
    arrays = {f.name: np.concatenate([getattr(part, f.name) for part in parts]) for f in fields(first)
              if isinstance(getattr(first, f.name), np.ndarray)}
    return replace(first, name=name or first.name, **arrays)


def save_sequence(path: str | os.PathLike, seq: Sequence) -> Path:
    """Write a Sequence to an ``.npz`` file; returns the file written (``.npz`` added to a name without it)."""
    arrays = {f.name: getattr(seq, f.name) for f in fields(seq) if isinstance(getattr(seq, f.name), np.ndarray)}
    out = Path(path) if str(path).endswith(".npz") else Path(f"{os.fspath(path)}.npz")   # as numpy names it
    np.savez_compressed(out, _name=np.array(seq.name), _systems=np.array(seq.systems),
                        _feature_names=np.array(seq.feature_names), **arrays)
    return out


def load_sequence(path: str | os.PathLike) -> Sequence:
    """Read a Sequence written by ``save_sequence`` (``path`` with or without its ``.npz``); InputError otherwise."""
    path = Path(path)
    if not path.exists() and Path(f"{path}.npz").exists():
        path = Path(f"{path}.npz")
    try:
        z = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(path, "no such Sequence file") from None
    except (OSError, ValueError) as exc:
        raise InputError(path, f"not a Sequence file written by lfgnss.save_sequence ({type(exc).__name__})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise InputError(path, "not a Sequence file written by lfgnss.save_sequence (an .npy array)")
    with z:
        if not {"_name", "_systems", "_feature_names"} <= set(z.files):
            raise InputError(path, "not a Sequence file written by lfgnss.save_sequence")
        arrays = {k: z[k] for k in z.files if not k.startswith("_")}
        return Sequence(name=str(z["_name"]), systems=tuple(str(s) for s in z["_systems"]),
                        feature_names=tuple(str(s) for s in z["_feature_names"]), **arrays)
