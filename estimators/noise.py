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
    """

    floor_m: float = 3.0
    cn0_scale_m2: float = 9.0e7
    elevation_power: float = 1.0
    el_min_rad: float = np.radians(5.0)

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        cn0 = np.where(sequence.mask, sequence.cn0_dbhz, 45.0)
        el = np.maximum(np.where(sequence.mask, sequence.el_rad, np.pi / 2), self.el_min_rad)
        r = (self.floor_m ** 2 + self.cn0_scale_m2 * 10.0 ** (-cn0 / 5.0)) / np.sin(el) ** self.elevation_power
        return r, np.zeros_like(r)
