"""The estimator plug-in interface: ``Estimator.solve(sequence) -> Solution``, and a registry."""
from __future__ import annotations

import difflib
import importlib
import inspect
from dataclasses import dataclass, field
from typing import Callable, Iterable, Protocol, runtime_checkable

import numpy as np

from lfgnss.sequence import Sequence

#: Per-epoch status codes of a Solution.
STATUS_NONE = 0        # no position (before the first fix)
STATUS_UPDATED = 1     # measurement update with at least one satellite
STATUS_COASTED = 2     # prediction only (no usable satellite, or all gated)
STATUS_RESET = 3       # state re-initialised from the coarse fix (start or divergence)
STATUS_NAMES = {STATUS_NONE: "none", STATUS_UPDATED: "updated", STATUS_COASTED: "coasted", STATUS_RESET: "reset"}


@dataclass(frozen=True)
class Solution:
    """Per-epoch output of an estimator, shapes (T, ...).

    ``pos_ecef_m`` is NaN only where ``status == STATUS_NONE``.
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

    @property
    def available(self) -> np.ndarray:
        """(T,) bool, True where the estimator gave a position."""
        return self.status != STATUS_NONE


@runtime_checkable
class Estimator(Protocol):
    """A positioning back end: takes a Sequence, returns a Solution with one row per epoch."""

    name: str

    def solve(self, sequence: Sequence) -> Solution:
        """Estimate positions for every epoch of ``sequence``."""
        ...


_REGISTRY: dict[str, Callable[..., Estimator]] = {}


def register(name: str) -> Callable:
    """Class decorator: make an estimator available as ``--backend name``."""
    def wrap(factory: Callable[..., Estimator]) -> Callable[..., Estimator]:
        _REGISTRY[name] = factory
        return factory
    return wrap


#: Back ends whose module is imported on first use (gtsam adds ~0.2 s to every start-up otherwise).
_LAZY: dict[str, str] = {"fgo": "estimators.fgo"}


def epoch_range(start: int, stop: int, progress: bool, desc: str) -> Iterable[int]:
    """``range(start, stop)`` with a tqdm bar when ``progress`` and stderr is a terminal (long files take minutes)."""
    if not progress:
        return range(start, stop)
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
        raise KeyError(f"unknown backend {name!r}; available: {', '.join(available())}")
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


def create(name: str, **options) -> Estimator:
    """Instantiate the registered estimator ``name`` with keyword options; TypeError for an option it does not take."""
    _check_options(name, options)
    return _REGISTRY[name](**options)


def available() -> list[str]:
    """Names of the registered estimators."""
    return sorted(set(_REGISTRY) | set(_LAZY))
