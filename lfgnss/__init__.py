"""lfgnss: robust satellite positioning for cities (LF-GNSS learning-filtering fusion).

Typical use::

    import lfgnss
    meas = lfgnss.load("rover.obs", ["brdc.nav"])      # observations + satellite states + QC
    fix = lfgnss.spp(meas)                              # equal-weight least squares, every epoch
    seq = lfgnss.build_sequence(meas, fix)              # features for the estimators
"""
from __future__ import annotations

import os
from typing import Iterable

import numpy as np

from .errors import InputError, LfgnssError, RinexError
from .features import AVAILABLE_FEATURES, build_sequence
from .measurements import Measurements, load
from .navigation import Navigation, load_nav
from .observations import Observations
from .rinex import load_obs
from .sequence import DEFAULT_FEATURES, Sequence, concat_sequences, load_sequence, save_sequence
from .spp import CoarseFix, SppConfig, spp

__version__ = "0.1.0"


def process(obs: str | os.PathLike | Observations,
            nav: str | os.PathLike | Iterable[str | os.PathLike] | Navigation, *,
            systems: Iterable[str] | None = None, feature_names: tuple[str, ...] = DEFAULT_FEATURES,
            truth_ecef_m: np.ndarray | None = None, name: str = "") -> Sequence:
    """RINEX files to a feature Sequence in one call: ``load``, ``spp``, ``build_sequence`` (truth (T, 3) ECEF [m])."""
    meas = load(obs, nav, systems=systems)
    return build_sequence(meas, spp(meas), feature_names=feature_names, truth_ecef_m=truth_ecef_m, name=name)


__all__ = ["AVAILABLE_FEATURES", "CoarseFix", "DEFAULT_FEATURES", "InputError", "LfgnssError", "Measurements",
           "Navigation", "Observations", "RinexError", "Sequence", "SppConfig", "build_sequence", "concat_sequences", "load",
           "load_nav", "load_obs", "load_sequence", "process", "save_sequence", "spp", "__version__"]
