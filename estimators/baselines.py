"""Per-epoch least-squares baselines as plug-ins: equal-weight (``wls``) and noise-weighted (``wls-weighted``)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgnss.corrections import geometric_range_m
from lfgnss.sequence import Sequence

from .base import STATUS_NONE, STATUS_UPDATED, Solution, register
from .noise import HeuristicNoise, NoiseModel


def _start_positions(seq: Sequence) -> np.ndarray:
    """(T, 3) coarse fix, else the nearest earlier (then later) coarse fix; NaN if the sequence has none."""
    pos = seq.coarse_ecef_m.copy()
    ok = np.flatnonzero(np.all(np.isfinite(pos), axis=1))
    if ok.size == 0:
        return pos
    idx = np.clip(np.searchsorted(ok, np.arange(len(seq)), side="right") - 1, 0, None)
    return pos[ok[idx]]


def weighted_least_squares(seq: Sequence, r_m2: np.ndarray, *, iterations: int = 10,
                           tolerance_m: float = 1e-4, scale_by_residuals: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Batched Gauss-Newton with weights 1/r over every epoch at once.

    Solves min sum_i (pr_i - |s_i - p| - sagnac - b_sys(i))^2 / r_i per epoch for p [m] and the clock
    of each constellation present [m]. Returns positions (T, 3), covariances (T, 3, 3) [m^2], clocks of
    systems[0] (T,) [m] and a (T,) bool of epochs with enough satellites (3 + constellations present).
    """
    n_t, n_s = seq.mask.shape
    n_c = len(seq.systems)
    x = np.concatenate([_start_positions(seq), np.zeros((n_t, n_c))], axis=1)
    onehot = np.zeros((n_t, n_s, n_c))
    t_i, s_i = np.nonzero(seq.mask)
    onehot[t_i, s_i, seq.system_index[t_i, s_i]] = 1.0
    observed = onehot.sum(1) > 0
    enough = np.all(np.isfinite(x[:, :3]), axis=1) & (seq.mask.sum(1) >= 3 + observed.sum(1))
    w = np.where(seq.mask, 1.0 / np.maximum(r_m2, 1e-6), 0.0)
    x = np.nan_to_num(x)
    cov = np.zeros((n_t, 3, 3))
    for _ in range(iterations):
        rng = geometric_range_m(seq.sat_pos_ecef_m, x[:, None, :3])
        d = seq.sat_pos_ecef_m - x[:, None, :3]
        los = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1.0)
        res = np.where(seq.mask, seq.pr_m - rng - np.einsum("tsc,tc->ts", onehot, x[:, 3:]), 0.0)
        h = np.concatenate([-los, onehot], axis=-1)
        normal = np.einsum("tsi,ts,tsj->tij", h, w, h) + np.eye(3 + n_c) * np.concatenate(
            [np.zeros((n_t, 3)), ~observed], axis=1)[:, :, None]
        normal[~enough] = np.eye(3 + n_c)
        dx = np.linalg.solve(normal, np.einsum("tsi,ts,ts->ti", h, w, res)[..., None])[..., 0]
        dx[~enough] = 0.0
        x += dx
        if np.all(np.linalg.norm(dx[:, :3], axis=1) < tolerance_m):
            break
    cov = np.linalg.inv(normal)[:, :3, :3]
    if scale_by_residuals:  # a-posteriori unit variance: sum(w v^2) / (n - m)
        dof = np.maximum(seq.mask.sum(1) - 3 - observed.sum(1), 1)
        cov = cov * (np.einsum("ts,ts->t", w, res ** 2) / dof)[:, None, None]
    return x[:, :3], cov, x[:, 3], enough


@dataclass
class _LeastSquares:
    name: str
    noise: NoiseModel | None

    def solve(self, sequence: Sequence) -> Solution:
        """Least-squares fix of each epoch on its own (no filtering)."""
        if self.noise is None:
            r = np.ones(sequence.mask.shape)
        else:
            r, _ = self.noise(sequence)
        pos, cov, clock, ok = weighted_least_squares(sequence, r, scale_by_residuals=self.noise is None)
        return Solution(self.name, sequence.time_gps_s.copy(), np.where(ok[:, None], pos, np.nan),
                        np.where(ok[:, None, None], cov, np.nan), np.where(ok, clock, np.nan),
                        np.where(ok, sequence.mask.sum(1), 0), np.where(ok, STATUS_UPDATED, STATUS_NONE))


@register("wls")
def equal_weight_least_squares(**_: object) -> _LeastSquares:
    """Equal-weight least squares per epoch (the coarse fix of LF-GNSS step 1)."""
    return _LeastSquares("wls", None)


@register("wls-weighted")
def weighted_baseline(noise: NoiseModel | None = None, **_: object) -> _LeastSquares:
    """Least squares per epoch weighted by the C/N0- and elevation-based noise model."""
    return _LeastSquares("wls-weighted", noise or HeuristicNoise())
