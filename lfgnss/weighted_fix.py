"""Weighted least-squares fix of every epoch at once, and the hand-set C/N0-elevation pseudorange variance.

Per epoch, with weights ``w_i = 1 / r_i``::

    min_x  sum_i w_i (pr_i - rho(s_i, p) - b_{sys(i)})^2,   x = [p (3), b_0 .. b_{C-1}]

solved by batched Gauss-Newton from a start position (the coarse fix). Used by the weighted
least-squares baseline (``estimators.baselines``) and, through its post-fit residuals, by the
``residual_weighted`` feature (``lfgnss.features``): in street canyons its residuals follow each
satellite's true error far more closely than the equal-weight fix's, because the weak (mostly
reflected) signals no longer drag the fix towards themselves.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .corrections import geometric_range_m

#: Hand-set variance parameters (chosen on the validation splits; see ``estimators.noise.HeuristicNoise``).
FLOOR_M = 2.0
CN0_SCALE_M2 = 1.0e9
ELEVATION_POWER = 1.0
EL_MIN_RAD = float(np.radians(5.0))


def cn0_elevation_variance_m2(cn0_dbhz: np.ndarray, el_rad: np.ndarray, *, floor_m: float = FLOOR_M,
                              cn0_scale_m2: float = CN0_SCALE_M2, elevation_power: float = ELEVATION_POWER,
                              el_min_rad: float = EL_MIN_RAD) -> np.ndarray:
    """Pseudorange variance [m^2]: ``(floor^2 + scale 10^(-C/N0 / 5)) / sin(max(el, el_min))^power``."""
    el = np.maximum(el_rad, el_min_rad)
    return (floor_m ** 2 + cn0_scale_m2 * 10.0 ** (-np.asarray(cn0_dbhz, float) / 5.0)) / np.sin(el) ** elevation_power


@dataclass(frozen=True)
class WeightedFix:
    """Per-epoch weighted least-squares solutions, (T epochs, N satellite slots, C constellations)."""

    pos_ecef_m: np.ndarray      # (T, 3) [m]; meaningless where not ok
    cov_ecef_m2: np.ndarray     # (T, 3, 3) position covariance [m^2]
    clock_m: np.ndarray         # (T, C) clock of each constellation [m] (0 where it has no satellite)
    residual_m: np.ndarray      # (T, N) post-fit residual pr - rho - b [m]; 0 in masked slots
    ok: np.ndarray              # (T,) bool: a start position and at least 3 + C_present satellites


#: Condition number of the normal matrix beyond which an epoch's geometry fixes nothing.
MAX_CONDITION = 1e12


def weighted_least_squares(pr_m: np.ndarray, sat_pos_ecef_m: np.ndarray, system_index: np.ndarray,
                           mask: np.ndarray, n_systems: int, start_ecef_m: np.ndarray, r_m2: np.ndarray, *,
                           iterations: int = 10, tolerance_m: float = 1e-4,
                           scale_by_residuals: bool = False) -> WeightedFix:
    """Batched Gauss-Newton over all epochs: pseudoranges (T, N) [m], satellites (T, N, 3) [m], variances (T, N) [m^2].

    ``start_ecef_m`` (T, 3) is where each epoch starts (NaN: the epoch is not solved). With
    ``scale_by_residuals`` the covariance is scaled by the a-posteriori unit variance ``sum(w v^2) / (n - m)``;
    an epoch with no redundancy (n = m) takes the median unit variance of the epochs that have some.
    """
    n_t, n_s = mask.shape
    onehot = np.zeros((n_t, n_s, n_systems))
    t_i, s_i = np.nonzero(mask)
    onehot[t_i, s_i, system_index[t_i, s_i]] = 1.0
    observed = onehot.sum(1) > 0
    start = np.asarray(start_ecef_m, float)
    ok = np.all(np.isfinite(start), axis=1) & (mask.sum(1) >= 3 + observed.sum(1))
    w = np.where(mask, 1.0 / np.maximum(r_m2, 1e-6), 0.0)
    x = np.nan_to_num(np.concatenate([start, np.zeros((n_t, n_systems))], axis=1))
    unobserved = np.concatenate([np.zeros((n_t, 3)), ~observed], axis=1)[:, :, None] * np.eye(3 + n_systems)

    def residuals(x: np.ndarray) -> np.ndarray:
        rng = geometric_range_m(sat_pos_ecef_m, x[:, None, :3])
        return np.where(mask, pr_m - rng - np.einsum("tsc,tc->ts", onehot, x[:, 3:]), 0.0)

    for _ in range(iterations):
        d = sat_pos_ecef_m - x[:, None, :3]
        los = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1.0)
        res = residuals(x)
        h = np.concatenate([-los, onehot], axis=-1)
        normal = np.einsum("tsi,ts,tsj->tij", h, w, h) + unobserved
        normal[~ok] = np.eye(3 + n_systems)
        # satellites in one spot of the sky: no fix (np.linalg.solve would raise on the singular matrix)
        ok &= np.isfinite(normal).all(axis=(1, 2)) & (np.linalg.cond(normal) < MAX_CONDITION)
        normal[~ok] = np.eye(3 + n_systems)
        dx = np.linalg.solve(normal, np.einsum("tsi,ts,ts->ti", h, w, res)[..., None])[..., 0]
        dx[~ok] = 0.0
        x += dx
        if np.all(np.linalg.norm(dx[:, :3], axis=1) < tolerance_m):
            break
    res = residuals(x)
    cov = np.linalg.inv(normal)[:, :3, :3]
    if scale_by_residuals:
        dof = mask.sum(1) - 3 - observed.sum(1)
        unit = np.einsum("ts,ts->t", w, res ** 2) / np.maximum(dof, 1)
        # no redundancy: the residuals are ~0 and say nothing; take the median of the epochs that have some
        redundant = ok & (dof > 0)
        unit = np.where(dof > 0, unit, np.median(unit[redundant]) if redundant.any() else 1.0)
        cov = cov * unit[:, None, None]
    return WeightedFix(x[:, :3], cov, x[:, 3:], res, ok)


__all__ = ["WeightedFix", "cn0_elevation_variance_m2", "weighted_least_squares"]
