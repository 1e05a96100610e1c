"""Estimator back ends behind one interface: EKF (filterpy), factor graph (gtsam) and baselines.

Importing this package registers the back ends: ``create("ekf")``, ``create("plain-ekf")``,
``create("fgo")``, ``create("wls")``, ``create("wls-weighted")``.
"""
from .base import (STATUS_COASTED, STATUS_NAMES, STATUS_NONE, STATUS_RESET, STATUS_UPDATED, Estimator, Solution,
                   available, create, register)
from .models import EkfConfig
from .noise import FixedNoise, HeuristicNoise, NoiseModel
from .ekf import LfgnssEkf, PlainEkf
from .fgo import LfgnssFgo
from . import baselines  # noqa: F401  (registers "wls" and "wls-weighted")

__all__ = ["Estimator", "Solution", "available", "create", "register", "STATUS_NONE", "STATUS_UPDATED",
           "STATUS_COASTED", "STATUS_RESET", "STATUS_NAMES", "EkfConfig", "NoiseModel", "HeuristicNoise",
           "FixedNoise", "LfgnssEkf", "LfgnssFgo", "PlainEkf"]
