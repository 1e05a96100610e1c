"""The estimator plug-in interface: ``Estimator.solve(sequence) -> Solution``, and a registry."""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable, Protocol, runtime_checkable

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


def create(name: str, **options) -> Estimator:
    """Instantiate the registered estimator ``name`` with keyword options."""
    if name not in _REGISTRY and name in _LAZY:
        importlib.import_module(_LAZY[name])
    if name not in _REGISTRY:
        raise KeyError(f"unknown backend {name!r}; available: {', '.join(available())}")
    return _REGISTRY[name](**options)


def available() -> list[str]:
    """Names of the registered estimators."""
    return sorted(set(_REGISTRY) | set(_LAZY))
