"""lfgnss: robust satellite positioning for cities (LF-GNSS learning-filtering fusion).

Typical use::

    import lfgnss
    meas = lfgnss.load("rover.obs", ["brdc.nav"])      # observations + satellite states + QC
    fix = lfgnss.spp(meas)                              # equal-weight least squares, every epoch
    seq = lfgnss.build_sequence(meas, fix)              # features for the estimators
"""
from .errors import InputError, LfgnssError, RinexError
from .features import AVAILABLE_FEATURES, build_sequence
from .measurements import Measurements, load
from .navigation import Navigation, load_nav
from .observations import Observations
from .rinex import load_obs
from .sequence import DEFAULT_FEATURES, Sequence, load_sequence, save_sequence
from .spp import CoarseFix, SppConfig, spp

__version__ = "0.1.0"


def process(obs, nav, *, systems=None, feature_names=DEFAULT_FEATURES, truth_ecef_m=None, name: str = "") -> Sequence:
    """RINEX files to a feature Sequence in one call: ``load`` then ``spp`` then ``build_sequence``."""
    meas = load(obs, nav, systems=systems)
    return build_sequence(meas, spp(meas), feature_names=feature_names, truth_ecef_m=truth_ecef_m, name=name)


__all__ = ["AVAILABLE_FEATURES", "CoarseFix", "DEFAULT_FEATURES", "InputError", "LfgnssError", "Measurements",
           "Navigation", "Observations", "RinexError", "Sequence", "SppConfig", "build_sequence", "load",
           "load_nav", "load_obs", "load_sequence", "process", "save_sequence", "spp", "__version__"]
