"""lfgnss: robust satellite positioning for cities (LF-GNSS learning-filtering fusion)."""
from .sequence import DEFAULT_FEATURES, Sequence

__version__ = "0.1.0"
__all__ = ["Sequence", "DEFAULT_FEATURES", "__version__"]
