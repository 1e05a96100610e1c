"""Inflating a filter's formal covariance by its pseudorange residuals, so its sds mean something in a city.

A Kalman filter's covariance is only as honest as its R. Where the pseudoranges disagree with the filtered position
by more than R says (street-canyon multipath, an R learned for accuracy rather than for variances), the residuals
show it. Their mean squared normalised value, the a-posteriori variance factor

    g_k = mean_i e_i^2 / r_i,   e_i = pr_i - |s_i - x_k| - median over i's constellation    (usable pseudoranges)

(each constellation's median standing in for its clock: ``noise.constellation_residual_m``, as ``TruthNoise``
uses it; the R the estimator weighs with, before any Huber scaling: the noise model's, in the EKF times
``EkfConfig.glonass_sigma_factor`` squared on GLONASS; no v^c) is about 1 when R is right and far above it when R
is too small.
``covariance_inflation`` averages it over the last ``tau_s`` seconds (the errors it flags last for seconds) and
never shrinks the covariance: residuals smaller than R do not prove the position right. The choice of this factor
and of ``INFLATION_TAU_S`` was made on the validation splits: docs/sd_consistency.md.
"""
from __future__ import annotations

import numpy as np

from lfgnss.dop import satellites_per_system
from lfgnss.sequence import Sequence

from .noise import constellation_residual_m

#: Time constant [s] of the running mean of the variance factor (chosen on validation: docs/sd_consistency.md).
INFLATION_TAU_S = 5.0


def residual_variance_factor(sequence: Sequence, pos_ecef_m: np.ndarray, r_m2: np.ndarray, usable: np.ndarray
                             ) -> np.ndarray:
    """(T,) ``g_k``, the mean of e^2 / r [-] over each epoch's usable pseudoranges at ``pos_ecef_m`` (T, 3) [m].

    ``r_m2`` (T, N) [m^2] is the R the estimator weighs with (module docstring); NaN where an epoch has no position,
    or no constellation with two usable pseudoranges (a position-blind epoch: nothing to compare).
    """
    pos = np.asarray(pos_ecef_m, float)
    ok = np.asarray(usable, bool) & np.isfinite(pos).all(-1)[:, None]
    # a constellation's lone satellite is its own median: a residual of 0 by construction, no evidence of a good R
    system = np.asarray(sequence.system_index)
    n_system = satellites_per_system(system, ok, len(sequence.systems))
    ok &= np.take_along_axis(n_system, np.where(ok, system, 0), axis=1) > 1
    e = constellation_residual_m(sequence, pos, ok)
    z2 = np.where(ok, np.nan_to_num(e) ** 2 / np.where(ok, r_m2, 1.0), 0.0)
    n = ok.sum(1)
    return np.where(n > 0, z2.sum(1) / np.maximum(n, 1), np.nan)


def covariance_inflation(time_gps_s: np.ndarray, residual_factor: np.ndarray, tau_s: float = INFLATION_TAU_S
                         ) -> np.ndarray:
    """(T,) factor >= 1 [-] for the covariance: ``max(1, f_k)``, f an exponential running mean of the factors.

    ``residual_factor`` (T,) is NaN where an epoch had none (it keeps the running mean; 1 before the first); the
    mean weighs the last factor, ``dt`` [s] older, by ``exp(-dt / tau_s)``; ``tau_s = 0``: each epoch's own.
    """
    time = np.asarray(time_gps_s, float)
    g = np.asarray(residual_factor, float)
    out = np.ones(g.shape)
    mean, t_last = np.nan, np.nan
    for k in range(g.size):     # a recursion over epochs; T is thousands, and the filter's own loop dominates
        if np.isfinite(g[k]):
            if not np.isfinite(mean) or tau_s <= 0:
                mean = g[k]
            else:
                w = np.exp(-(time[k] - t_last) / tau_s)
                mean = w * mean + (1.0 - w) * g[k]
            t_last = time[k]
        if np.isfinite(mean):
            out[k] = max(1.0, mean)
    return out


__all__ = ["INFLATION_TAU_S", "covariance_inflation", "residual_variance_factor"]
