"""The estimator plug-in interface: ``Estimator.solve(sequence) -> Solution``, and a registry."""
from __future__ import annotations

import difflib
import importlib
import inspect
import os
import sys
import warnings
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Callable, Iterable, Protocol, runtime_checkable

import numpy as np

from lfgnss.errors import UnknownNameError, did_you_mean
from lfgnss.frames import check_near_surface, ecef_to_enu, ecef_to_lla
from lfgnss.metrics import enu_rotations
from lfgnss.sequence import Sequence, epochs_text, share_text, time_span_text

if TYPE_CHECKING:
    import pandas as pd

#: Per-epoch status codes of a Solution.
STATUS_NONE = 0        # no position (before the first fix)
STATUS_UPDATED = 1     # measurement update: satellites, Dopplers or (EKF) the zero-velocity update alone
STATUS_COASTED = 2     # prediction only (no usable satellite, or all gated)
STATUS_RESET = 3       # state re-initialised from the coarse fix (start or divergence)
STATUS_NAMES = {STATUS_NONE: "none", STATUS_UPDATED: "updated", STATUS_COASTED: "coasted", STATUS_RESET: "reset"}


@dataclass(frozen=True, eq=False, repr=False)
class Solution:
    """Per-epoch output of an estimator, shapes (T, ...).

    ``pos_ecef_m`` is NaN only where ``status == STATUS_NONE``. ``geodetic()``, ``enu_m()``, ``sd_enu_m()`` and
    ``to_frame()`` convert it (NaN where an epoch has no position); ``subset()`` selects epochs. ``repr`` is one
    line (backend, epochs, time span, statuses); ``==`` is identity, as the arrays have no single truth value.
    """

    backend: str
    time_gps_s: np.ndarray        # (T,) GPS seconds
    pos_ecef_m: np.ndarray        # (T, 3) [m]
    cov_ecef_m2: np.ndarray       # (T, 3, 3) position covariance [m^2]
    clock_m: np.ndarray           # (T,) receiver clock of the reference system [m]
    n_used: np.ndarray            # (T,) satellites used in the update
    status: np.ndarray            # (T,) STATUS_* codes
    vel_ecef_m_s: np.ndarray | None = None  # (T, 3) [m/s] where the estimator has velocity
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        """ValueError naming the back end and the field whose shape is not (T, ...) or whose status code is unknown;
        lists become arrays (an array stays the very object given)."""
        for name in ("time_gps_s", "pos_ecef_m", "cov_ecef_m2", "clock_m", "n_used", "status", "vel_ecef_m_s"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, np.ndarray):
                object.__setattr__(self, name, np.asarray(value))
        t = np.shape(self.time_gps_s)[:1]
        shapes = {"time_gps_s": (), "pos_ecef_m": (3,), "cov_ecef_m2": (3, 3), "clock_m": (), "n_used": (),
                  "status": ()} | ({} if self.vel_ecef_m_s is None else {"vel_ecef_m_s": (3,)})
        for name, tail in shapes.items():
            shape = np.shape(getattr(self, name))
            if len(t) != 1 or shape != t + tail:
                want = f"({t[0] if t else 'T'}{''.join(f', {d}' for d in tail)})"
                raise ValueError(f"Solution of {self.backend!r}: {name} has shape {shape}, expected {want}")
        unknown = sorted(set(np.unique(np.asarray(self.status)).tolist()) - set(STATUS_NAMES))
        if unknown:
            raise ValueError(f"Solution of {self.backend!r}: unknown status code(s) {unknown} (estimators.STATUS_NAMES: "
                             f"{STATUS_NAMES})")
        dtype = np.asarray(self.time_gps_s).dtype
        if dtype.kind == "f" and dtype.itemsize < 8:    # float32 steps 128 s at 1.2e9 s: every tag the same minute
            raise ValueError(f"Solution of {self.backend!r}: time_gps_s must be float64 GPS seconds, got {dtype} "
                             f"(.astype(float) before rounding, from the source)")
        n_used = np.asarray(self.n_used)
        if n_used.dtype.kind not in "iub":
            flat = n_used.ravel().astype(float) if n_used.dtype.kind == "f" else None
            odd = None if flat is None else flat[flat != np.round(flat)]      # NaN too
            if odd is None or odd.size:
                got = n_used.dtype if odd is None else f"{odd[0]} (of {odd.size} such values)"
                raise ValueError(f"Solution of {self.backend!r}: n_used must be whole numbers of satellites (0 where "
                                 f"none was used), got {got}")

    @property
    def available(self) -> np.ndarray:
        """(T,) bool, True where the estimator gave a position."""
        return self.status != STATUS_NONE

    def __len__(self) -> int:
        return int(np.shape(self.time_gps_s)[0])

    def __repr__(self) -> str:
        """One line: backend, epochs, time span, share with a position and the status counts (no arrays)."""
        status = np.asarray(self.status).ravel()
        counts = ", ".join(f"{name} {int(np.count_nonzero(status == code))}" for code, name in STATUS_NAMES.items()
                           if np.any(status == code))
        smoothed = ""
        if self.info.get("smooth"):
            lag = float(self.info.get("smooth_lag_s", np.inf))
            smoothed = ", smoothed (RTS" + (f", lag {lag:g} s)" if np.isfinite(lag) else ")")
        return (f"<Solution {self.backend!r}: {epochs_text(len(self))}, {time_span_text(self.time_gps_s)}, "
                f"{share_text(self.has_position(), 'with a position')}" + (f" ({counts})" if counts else "")
                + smoothed + ">")

    def has_position(self) -> np.ndarray:
        """(T,) bool: status is not none and the ECEF position is finite (the epochs the writers write)."""
        return (np.asarray(self.status) != STATUS_NONE) & np.isfinite(np.asarray(self.pos_ecef_m, float)).all(axis=-1)

    def _positions(self) -> np.ndarray:
        """(T, 3) ECEF [m], NaN where the epoch has no position (``has_position``)."""
        return np.where(self.has_position()[:, None], np.asarray(self.pos_ecef_m, float), np.nan)

    def cov_enu_m2(self) -> np.ndarray:
        """(T, 3, 3) position covariance in each estimate's local ENU frame [m^2]; 0 where unknown.

        ``C_enu = R C_ecef R^T`` (RTKLIB ``covenu``); rows with a non-finite covariance or position get 0.
        """
        pos = np.asarray(self.pos_ecef_m, dtype=float)
        cov = np.asarray(self.cov_ecef_m2, dtype=float)
        ok = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(pos).all(axis=1)
        out = np.zeros((len(pos), 3, 3))
        rot = enu_rotations(pos[ok]).reshape(-1, 3, 3)
        out[ok] = np.einsum("tij,tjk,tlk->til", rot, cov[ok], rot)
        return out

    def geodetic(self) -> np.ndarray:
        """(T, 3) WGS84 latitude [deg], longitude [deg], ellipsoidal height [m]; NaN where no position."""
        llh = ecef_to_lla(self._positions()).reshape(-1, 3)
        return np.column_stack([np.degrees(llh[:, 0]), np.degrees(llh[:, 1]), llh[:, 2]])

    def enu_m(self, ref_ecef_m: np.ndarray | None = None) -> np.ndarray:
        """(T, 3) east, north, up [m] from ``ref_ecef_m`` (3,) [m], default the first position; NaN where none."""
        pos = self._positions()
        if ref_ecef_m is None:
            found = np.flatnonzero(np.isfinite(pos).all(axis=-1))
            if not found.size:
                return np.full(pos.shape, np.nan)
            ref_ecef_m = pos[found[0]]
        ref = np.asarray(ref_ecef_m, float)
        if ref.shape != (3,) or not np.isfinite(ref).all():
            raise ValueError(f"Solution.enu_m: ref_ecef_m must be 3 finite ECEF coordinates [m], got {ref_ecef_m!r}")
        check_near_surface("Solution.enu_m", "ref_ecef_m", ref)
        return ecef_to_enu(pos, ref).reshape(-1, 3)

    def sd_enu_m(self) -> np.ndarray:
        """(T, 3) standard deviations east, north, up [m], the covariance in each epoch's local frame; NaN if none."""
        known = self.has_position() & np.isfinite(np.asarray(self.cov_ecef_m2, float)).all(axis=(1, 2))
        sd = np.sqrt(np.maximum(np.diagonal(self.cov_enu_m2(), axis1=1, axis2=2), 0.0))
        return np.where(known[:, None], sd, np.nan)

    def vel_enu_m_s(self) -> np.ndarray:
        """(T, 3) velocity east, north, up [m/s] in each epoch's local frame; NaN where no position or velocity."""
        out = np.full((len(self), 3), np.nan)
        if self.vel_ecef_m_s is None:
            return out
        pos = self._positions()
        vel = np.asarray(self.vel_ecef_m_s, float)
        ok = np.isfinite(pos).all(axis=1) & np.isfinite(vel).all(axis=1)
        out[ok] = np.einsum("tij,tj->ti", enu_rotations(pos[ok]).reshape(-1, 3, 3), vel[ok])
        return out

    def subset(self, index: slice | np.ndarray | int) -> "Solution":
        """Epochs selected by a slice, boolean mask, index array or one index, as a new Solution (and info's arrays).

        A mask of another length or an index out of range is an IndexError naming Solution.subset and the lengths.
        """
        t = len(self)
        index = np.array([index]) if isinstance(index, (int, np.integer)) and not isinstance(index, bool) else index
        check_epoch_index(index, t, "Solution.subset")
        per_epoch = {k: np.asarray(v)[index] for k, v in self.info.items()
                     if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == t}
        arrays = {k: getattr(self, k)[index] for k in ("time_gps_s", "pos_ecef_m", "cov_ecef_m2", "clock_m",
                                                       "n_used", "status")}
        vel = None if self.vel_ecef_m_s is None else self.vel_ecef_m_s[index]
        return replace(self, vel_ecef_m_s=vel, info=self.info | per_epoch, **arrays)

    def to_frame(self, truth_ecef_m: np.ndarray | None = None) -> "pd.DataFrame":
        """pandas DataFrame, one row per epoch, with the CSV writer's columns [m, deg] (``lfgnss.outputs.solution_frame``)."""
        from lfgnss.outputs import solution_frame

        return solution_frame(self, truth_ecef_m)


def check_epoch_index(index: object, n_epochs: int, owner: str) -> None:
    """IndexError naming ``owner`` when ``index`` (a mask or integer indices; a slice always fits) does not fit
    ``n_epochs`` epochs: a boolean mask of another length, or an index out of range."""
    if isinstance(index, slice):
        return
    arr = np.asarray(index)
    if arr.dtype == bool:
        if arr.shape != (n_epochs,):
            raise IndexError(f"{owner}: a boolean mask of shape {arr.shape} for {n_epochs} epochs; give one of "
                             f"length {n_epochs}")
    elif np.issubdtype(arr.dtype, np.integer):
        bad = arr[(arr >= n_epochs) | (arr < -n_epochs)]
        if bad.size:
            raise IndexError(f"{owner}: epoch index {int(bad.flat[0])} is out of range for {n_epochs} epochs")


@runtime_checkable
class Estimator(Protocol):
    """A positioning back end: takes a Sequence, returns a Solution with one row per epoch."""

    name: str

    def solve(self, sequence: Sequence) -> Solution:
        """Estimate positions for every epoch of ``sequence``."""
        ...


_REGISTRY: dict[str, Callable[..., Estimator]] = {}

_PACKAGE_DIR = os.path.normcase(os.path.dirname(os.path.abspath(__file__)))


def caller_stacklevel() -> int:
    """``stacklevel`` for ``warnings.warn`` in the calling function that names the first frame outside this package."""
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.normcase(os.path.dirname(os.path.abspath(frame.f_code.co_filename))) \
            == _PACKAGE_DIR:
        frame, level = frame.f_back, level + 1
    return level


def check_flag(value: object, key: str, owner: str) -> bool:
    """``value`` as a bool if it is True or False (numpy's too); TypeError naming ``owner`` and ``key`` otherwise."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{owner}: {key} must be True or False, got {value!r}")
    return bool(value)


def check_sequence(sequence: object, owner: str) -> Sequence:
    """``sequence`` if it is a Sequence with finite epoch times; TypeError or ValueError naming ``owner`` otherwise."""
    if not isinstance(sequence, Sequence):
        what = type(sequence).__name__
        if isinstance(sequence, (list, tuple)) and sequence and all(isinstance(s, Sequence) for s in sequence):
            raise TypeError(f"{owner}.solve: expected an lfgnss.Sequence, got a {what} of {len(sequence)} (the parts "
                            "lfgnss.datasets.load_split gives: a split may be cut in several); solve each part, e.g. "
                            "[est.solve(s) for s in parts]")
        hint = ("lfgnss.build_sequence(meas, lfgnss.spp(meas)), lfgnss.process(obs, nav) or lfgnss.load_sequence(path)"
                if what in ("Measurements", "CoarseFix", "str", "PosixPath", "WindowsPath", "Observations")
                else "lfgnss.build_sequence or lfgnss.process")
        raise TypeError(f"{owner}.solve: expected an lfgnss.Sequence, got {what}; make one with {hint}")
    bad = ~np.isfinite(np.asarray(sequence.time_gps_s, float))
    if bad.any():
        raise ValueError(f"{owner}: epoch time of {sequence.name!r} is not finite at epoch {int(np.argmax(bad))}")
    if len(sequence) and not np.isfinite(np.asarray(sequence.coarse_ecef_m, float)).all(axis=1).any():
        warnings.warn(f"{owner}: {sequence.name!r} has no coarse least-squares fix at any epoch (coarse_ecef_m is NaN "
                      "throughout), and the estimators start from one: no epoch gets a position (with "
                      "lfgnss.build_sequence(meas, lfgnss.spp(meas)) an epoch with 4 satellites or more gets a fix)",
                      stacklevel=3)
    return sequence


def usable_measurements(sequence: Sequence) -> np.ndarray:
    """(T, N) bool: masked-in slots with finite pseudorange and satellite position and a known system."""
    c = len(sequence.systems)
    return (sequence.mask & np.isfinite(sequence.pr_m) & np.isfinite(sequence.sat_pos_ecef_m).all(-1)
            & (sequence.system_index >= 0) & (sequence.system_index < c))


def usable_doppler(sequence: Sequence) -> np.ndarray:
    """(T, N) bool: usable slots whose Doppler is marked and finite, with a finite satellite velocity."""
    return (usable_measurements(sequence) & sequence.prr_mask & np.isfinite(sequence.prr_m_s)
            & np.isfinite(sequence.sat_vel_ecef_m_s).all(-1))


def _slots_text(flags: np.ndarray, what: str, sequence: Sequence) -> str:
    """``"12 <what> in 3 epochs of 'name' (first at epoch 10)"`` for the True slots of ``flags`` (T, N)."""
    epochs = flags.any(axis=1)
    return (f"{int(flags.sum())} {what} in {int(epochs.sum())} epochs of {sequence.name!r} "
            f"(first at epoch {int(np.argmax(epochs))})")


def warn_unusable(sequence: Sequence, usable: np.ndarray, owner: str, doppler: np.ndarray | None = None) -> None:
    """Warnings naming ``sequence`` and how many masked-in slots (and epochs) ``usable`` (T, N) leaves out.

    Masked-in slots with a non-finite pseudorange or satellite position, or no known system, are skipped; an epoch
    left with none is coasted (or has no position). With ``doppler`` (T, N, ``usable_doppler``), a second warning
    counts the marked Dopplers of usable slots it leaves out (non-finite Doppler or satellite velocity). Nothing
    when every masked-in slot is usable.
    """
    dropped = np.asarray(sequence.mask, bool) & ~usable
    if dropped.any():
        emptied = int(np.count_nonzero(dropped.any(axis=1) & ~usable.any(axis=1)))
        warnings.warn(f"{owner}: {_slots_text(dropped, 'masked-in slots', sequence)} have a non-finite pseudorange or "
                      f"satellite position (or no known system) and are skipped; {emptied} epochs are left without a "
                      f"usable satellite", UserWarning, stacklevel=caller_stacklevel())
    lost = None if doppler is None else usable & np.asarray(sequence.prr_mask, bool) & ~doppler
    if lost is not None and lost.any():
        warnings.warn(f"{owner}: {_slots_text(lost, 'marked Dopplers', sequence)} have a non-finite pseudorange rate "
                      f"or satellite velocity and are skipped (their pseudoranges are used)", UserWarning,
                      stacklevel=caller_stacklevel())


def usable_sequence(sequence: Sequence, owner: str = "estimators", dopplers: bool = True) -> Sequence:
    """``sequence`` with unusable masked-in slots (non-finite pseudorange, satellite state or Doppler) masked out.

    The same object when every masked-in slot is usable, as in every Sequence ``lfgnss.build_sequence`` makes;
    otherwise ``warn_unusable`` says, once, how many pseudorange slots ``owner`` skips, and, when it uses
    ``dopplers``, how many Dopplers.
    """
    usable, doppler = usable_measurements(sequence), usable_doppler(sequence)
    warn_unusable(sequence, usable, owner, doppler if dopplers else None)
    if np.array_equal(usable, sequence.mask) and np.array_equal(doppler, sequence.prr_mask):
        return sequence
    return replace(sequence, mask=usable, pr_m=np.where(usable, sequence.pr_m, 0.0),
                   sat_pos_ecef_m=np.where(usable[..., None], sequence.sat_pos_ecef_m, 0.0),
                   system_index=np.where(usable, sequence.system_index, -1), prr_mask=doppler,
                   prr_m_s=np.where(doppler, sequence.prr_m_s, 0.0),
                   sat_vel_ecef_m_s=np.where(doppler[..., None], sequence.sat_vel_ecef_m_s, 0.0))


def keep_slots(sequence: Sequence, keep: np.ndarray) -> Sequence:
    """``sequence`` with only the slots ``keep`` (T, N) masked in, pseudoranges and Dopplers alike (the same object
    when it keeps every masked-in slot)."""
    mask = sequence.mask & keep
    if np.array_equal(mask, sequence.mask):
        return sequence
    return replace(sequence, mask=mask, prr_mask=sequence.prr_mask & keep)


def register(name: str) -> Callable:
    """Class decorator ``@register("name")``: make an estimator available as ``create("name")`` (and as
    ``--backend name`` to ``lfgnss.solve.main([...])`` called from the same program); replacing a back end warns."""
    if not isinstance(name, str) or not name:
        what = f"the {name.__name__} itself" if callable(name) else repr(name)
        raise TypeError(f"estimators.register: give the back end's name, @register(\"name\"), not {what}")

    def wrap(factory: Callable[..., Estimator]) -> Callable[..., Estimator]:
        lazy_own = _LAZY.get(name) == getattr(factory, "__module__", None)    # fgo registering itself on first use
        if (name in _REGISTRY and _REGISTRY[name] is not factory) or (name in _LAZY and not lazy_own):
            warnings.warn(f"estimators.register: {name!r} now creates {getattr(factory, '__qualname__', factory)}, "
                          f"replacing the back end of that name", stacklevel=2)
        _REGISTRY[name] = factory
        return factory
    return wrap


#: Back ends whose module is imported on first use (gtsam adds ~0.2 s to every start-up otherwise).
_LAZY: dict[str, str] = {"fgo": "estimators.fgo"}


def epoch_range(start: int, stop: int, progress: bool, desc: str) -> Iterable[int]:
    """``range(start, stop)`` with a tqdm bar when ``progress`` and stderr is a terminal (long files take minutes)."""
    if not progress or not getattr(sys.stderr, "isatty", lambda: False)():   # tqdm's disable=None test, before
        return range(start, stop)                                            # importing it (20 ms)
    from tqdm.auto import tqdm

    return tqdm(range(start, stop), desc=desc, unit="epoch", disable=None, leave=False, mininterval=0.5)


def options_of(target: Callable) -> Callable:
    """Decorator: a factory ``f(**options)`` that passes its options on to ``target`` takes ``target``'s options.

    ``create`` checks a backend's options against its factory's signature; this gives the factory ``target``'s.
    """
    def wrap(factory: Callable[..., Estimator]) -> Callable[..., Estimator]:
        factory.__signature__ = inspect.signature(target)
        return factory
    return wrap


def backend_options(name: str) -> list[str] | None:
    """The keyword options backend ``name`` takes (None: its factory takes any keywords and checks them itself)."""
    if name not in _REGISTRY and name in _LAZY:
        importlib.import_module(_LAZY[name])
    if name not in _REGISTRY:
        raise UnknownNameError(f"unknown backend {name!r}{did_you_mean(name, available())}; available: "
                               f"{', '.join(available())}")
    params = inspect.signature(_REGISTRY[name]).parameters.values()
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return None
    return [p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]


def _check_options(name: str, options: dict) -> None:
    """TypeError naming the backend and each option it does not take (a typo, or one of another backend)."""
    accepted = backend_options(name)
    unknown = [o for o in options if accepted is not None and o not in accepted]
    if not unknown:
        return
    others: dict[str, list[str]] = {}
    for b in available():             # the error path only: a lazy back end is imported to list its options
        try:
            others[b] = (backend_options(b) or []) if b != name else []
        except ImportError:
            pass
    everything = sorted({o for opts in others.values() for o in opts})
    hints = []
    for o in unknown:
        owners = [b for b, opts in others.items() if o in opts]
        close = difflib.get_close_matches(o, accepted, n=1)
        if owners:
            hints.append(f" (an option of {', '.join(owners)})")
        elif close:
            hints.append(f" (did you mean {close[0]!r}?)")
        elif close := difflib.get_close_matches(o, everything, n=1):
            hints.append(f" (did you mean {close[0]!r}, an option of "
                         f"{', '.join(b for b, opts in others.items() if close[0] in opts)}?)")
        else:
            hints.append("")
    listed = ", ".join(f"{o!r}{h}" for o, h in zip(unknown, hints))
    takes = f"its options are {', '.join(accepted)}" if accepted else "it takes no options"
    plural = "s" if len(unknown) > 1 else ""
    raise TypeError(f"estimators.create({name!r}): backend {name!r} has no option{plural} {listed}; {takes}")


def create(name: str, /, **options: object) -> Estimator:
    """Instantiate the registered estimator ``name`` with keyword options; TypeError for an option it does not take."""
    if not isinstance(name, str):
        raise TypeError(f"estimators.create: the backend name must be a string, one of {', '.join(available())}; "
                        f"got {type(name).__name__}")
    _check_options(name, options)
    return _REGISTRY[name](**options)


def available() -> list[str]:
    """Names of the registered estimators."""
    return sorted(set(_REGISTRY) | set(_LAZY))


def factories() -> dict[str, object]:
    """Each back end's name -> what ``create`` calls for it, or the module that registers it on first use (a str)."""
    return {**_LAZY, **_REGISTRY}
