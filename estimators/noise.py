"""Per-satellite measurement noise: variance R [m^2] and innovation compensation v^c [m].

A noise model is any callable ``model(sequence) -> (r_m2, vc_m)`` returning two (T, N) arrays.
Padded/masked slots may hold any finite value; estimators ignore them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lfgnss.sequence import Sequence


class NoiseModel(Protocol):
    """Maps a Sequence to pseudorange variances R (T, N) [m^2] and compensations v^c (T, N) [m]."""

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        ...


@dataclass(frozen=True)
class HeuristicNoise:
    """Hand-set noise from C/N0 and elevation, no compensation (the "plain EKF" baseline).

    r = (floor_m^2 + cn0_scale_m2 * 10^(-C/N0 / 5)) / sin(max(el, el_min))^elevation_power

    Defaults chosen on the validation splits of hk-tst-2019, berlin-pp and hk-tst-static-2020 (grid over
    floor 2/5 m, scale 9e7/1e9/1e10, elevation power 1/2; EKF 3D RMSE 10.5 / 14.1 / 3.8 m there):
    sigma is 2.2 m at 45 dB-Hz, 3.8 m at 35, 10 m at 30 and 32 m at 25 dB-Hz at zenith.
    """

    floor_m: float = 2.0
    cn0_scale_m2: float = 1.0e9
    elevation_power: float = 1.0
    el_min_rad: float = np.radians(5.0)

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        cn0 = np.where(sequence.mask, sequence.cn0_dbhz, 45.0)
        el = np.maximum(np.where(sequence.mask, sequence.el_rad, np.pi / 2), self.el_min_rad)
        r = (self.floor_m ** 2 + self.cn0_scale_m2 * 10.0 ** (-cn0 / 5.0)) / np.sin(el) ** self.elevation_power
        return r, np.zeros_like(r)


@dataclass(frozen=True)
class FixedNoise:
    """Precomputed ``(r_m2, vc_m)`` arrays (T, N), e.g. from an offline network run or a test.

    Calling it checks that the arrays fit the sequence and returns them unchanged.
    """

    r_m2: np.ndarray
    vc_m: np.ndarray

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        shape = sequence.mask.shape
        if np.shape(self.r_m2) != shape or np.shape(self.vc_m) != shape:
            raise ValueError(f"estimators/noise.py: FixedNoise arrays {np.shape(self.r_m2)}, {np.shape(self.vc_m)} "
                             f"do not fit sequence {sequence.name!r} of shape {shape}")
        return np.asarray(self.r_m2, float), np.asarray(self.vc_m, float)
