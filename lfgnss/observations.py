"""Observation containers: per-epoch x per-satellite arrays read from one RINEX observation file."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


@dataclass(frozen=True)
class Observations:
    """Single-frequency code observations of one receiver, (T epochs, S satellites).

    Missing values are NaN here (inside the library only); nothing downstream writes them out.

    Attributes
    ----------
    path : str
        The observation file.
    version : float
        RINEX version of the file.
    time_gps_s : (T,) float
        Epoch time tags, GPS seconds since 1980-01-06, strictly increasing.
    sv : (S,) str
        Satellite ids, e.g. ``"G05"``, sorted.
    pr_m, cn0_dbhz, doppler_hz : (T, S) float
        Pseudorange [m], carrier-to-noise density [dB-Hz] and Doppler [Hz] of the chosen code.
    codes : dict
        Constellation letter -> chosen RINEX observation code (``{"G": "C1C", "C": "C2I"}``).
    approx_ecef_m : (3,) float
        Header APPROX POSITION XYZ [m] (zeros when absent).
    warnings : tuple of str
        One line per skipped record or epoch, ``PATH:LINE: reason``.
    """

    path: str
    version: float
    time_gps_s: np.ndarray
    sv: np.ndarray
    pr_m: np.ndarray
    cn0_dbhz: np.ndarray
    doppler_hz: np.ndarray
    codes: dict
    approx_ecef_m: np.ndarray
    warnings: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        t, s = np.shape(self.time_gps_s), np.shape(self.sv)
        shapes = {"pr_m": np.shape(self.pr_m), "cn0_dbhz": np.shape(self.cn0_dbhz),
                  "doppler_hz": np.shape(self.doppler_hz)}
        wrong = [f"{k} {v}" for k, v in shapes.items() if v != t + s]
        if len(t) != 1 or len(s) != 1 or wrong or np.shape(self.approx_ecef_m) != (3,):
            # a cache entry of another layout, or a caller's arrays: said here, not as an IndexError far away
            raise ValueError(f"Observations of {self.path}: time_gps_s {t} and sv {s} need (T, S) arrays and a (3,) "
                             f"approx_ecef_m; got {', '.join(wrong) or 'matching arrays'}, approx_ecef_m "
                             f"{np.shape(self.approx_ecef_m)}")

    def __len__(self) -> int:
        return int(self.time_gps_s.size)

    @property
    def systems(self) -> tuple[str, ...]:
        """Constellation letters present, in lfgnss order (GPS first)."""
        from .constants import SYSTEMS

        present = {s[0] for s in self.sv}
        return tuple(s for s in SYSTEMS if s in present)

    def select_systems(self, systems: tuple[str, ...] | list[str]) -> "Observations":
        """Only the satellites of the given constellations."""
        keep = np.isin(np.array([s[0] for s in self.sv]), list(systems))
        return replace(self, sv=self.sv[keep], pr_m=self.pr_m[:, keep], cn0_dbhz=self.cn0_dbhz[:, keep],
                       doppler_hz=self.doppler_hz[:, keep], codes={k: v for k, v in self.codes.items() if k in systems})

    def select_epochs(self, index: slice | np.ndarray) -> "Observations":
        """Only the epochs selected by a slice, boolean mask or index array."""
        return replace(self, time_gps_s=self.time_gps_s[index], pr_m=self.pr_m[index],
                       cn0_dbhz=self.cn0_dbhz[index], doppler_hz=self.doppler_hz[index])
