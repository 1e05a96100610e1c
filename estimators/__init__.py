"""Estimator back ends behind one interface: EKF (filterpy), factor graph (gtsam) and baselines.

Importing this package registers the back ends: ``create("ekf")``, ``create("plain-ekf")``,
``create("fgo")``, ``create("wls")``, ``create("wls-weighted")``; ``fgo`` (gtsam) is imported on first use.
``create("ekf", smooth=True)`` (or ``plain-ekf``) adds the Rauch-Tung-Striebel smoother (``estimators.smoother``).
Their covariance is inflated by the pseudorange residuals unless ``inflate_cov=False`` (``estimators.consistency``).
An option a backend does not take is a TypeError naming both (``backend_options(name)`` lists its options);
``noise`` may be a model file path (``create("ekf", noise="my.npz")``), read as ``--model`` is. A learned model
runs in the filter it was trained in (``config_of(model)``); a noise model of your own that wraps one does not, unless
given ``config=config_of(model)`` (the EKF warns, as does the FGO where it takes a setting from the model).
"""
from .base import (STATUS_COASTED, STATUS_NAMES, STATUS_NONE, STATUS_RESET, STATUS_UPDATED, Estimator, Solution,
                   available, backend_options, create, register)
from .models import EkfConfig
from .noise import FixedNoise, HeuristicNoise, NoiseModel, NoiseWarning, TruthNoise
from .ekf import LfgnssEkf, PlainEkf, config_of
from .baselines import LeastSquaresBaseline  # registers "wls" and "wls-weighted"


def __getattr__(name: str):
    """``LfgnssFgo`` on first use: gtsam is imported only by those who need the factor graph."""
    if name == "LfgnssFgo":
        from .fgo import LfgnssFgo

        return LfgnssFgo
    raise AttributeError(f"module 'estimators' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The module's names and the lazy ``LfgnssFgo`` (tab completion, ``dir(estimators)``)."""
    return sorted(set(globals()) | {"LfgnssFgo"})

__all__ = ["Estimator", "Solution", "available", "backend_options", "create", "register", "STATUS_NONE",
           "STATUS_UPDATED", "STATUS_COASTED", "STATUS_RESET", "STATUS_NAMES", "EkfConfig", "NoiseModel",
           "HeuristicNoise", "FixedNoise", "TruthNoise", "NoiseWarning", "LfgnssEkf", "LfgnssFgo", "PlainEkf",
           "LeastSquaresBaseline", "config_of"]
