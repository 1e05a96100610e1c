"""Rauch-Tung-Striebel smoothing of a Kalman filter's run: every epoch estimated from all epochs of its segment.

Given the filter's posteriors ``x_k, P_k``, its priors ``x^-_{k+1}, P^-_{k+1}`` and transitions
``F_{k+1}`` (``x^-_{k+1} = F_{k+1} x_k + u_{k+1}``, ``P^-_{k+1} = F_{k+1} P_k F_{k+1}^T + Q_{k+1}``),
backwards from the segment's last epoch ``K`` (``x^s_K = x_K``)::

    C_k   = P_k F_{k+1}^T (P^-_{k+1})^-1
    x^s_k = x_k + C_k (x^s_{k+1} - x^-_{k+1})
    P^s_k = P_k + C_k (P^s_{k+1} - P^-_{k+1}) C_k^T

The stored prior, not ``F x_k``, enters the gain's difference, so a deterministic input ``u`` (the EKF's
receiver clock realignment, ``models.realign_clock``) is carried correctly; filterpy's
``KalmanFilter.rts_smoother`` recomputes the prior as ``F x_k`` and would smear a clock jump backwards.
Filter restarts (re-initialisations from the coarse fix) end a segment: nothing is smoothed across them.
For the EKF this is the extended RTS smoother with the filter's own linearisation points.
"""
from __future__ import annotations

import numpy as np


def rts_smooth(x_post: np.ndarray, p_post: np.ndarray, x_prior: np.ndarray, p_prior: np.ndarray,
               transition: np.ndarray, restart: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed states (T, n) and covariances (T, n, n) [state units] from a filter run.

    Parameters
    ----------
    x_post, p_post : (T, n), (T, n, n)
        Filtered (posterior) state and covariance per epoch; NaN rows (no state yet) stay NaN.
    x_prior, p_prior : (T, n), (T, n, n)
        Prior of epoch k, predicted from epoch k-1 (any value where ``restart[k]``).
    transition : (T, n, n)
        ``F_k``, the transition from epoch k-1 to k (any value where ``restart[k]``).
    restart : (T,) bool
        True where epoch k does not follow from epoch k-1 (first fix, re-initialisation).
    """
    xs = np.array(x_post, float, copy=True)
    ps = np.array(p_post, float, copy=True)
    valid = np.isfinite(xs).all(1)
    for k in range(xs.shape[0] - 2, -1, -1):
        if not (valid[k] and valid[k + 1]) or restart[k + 1]:
            continue
        f, pp = transition[k + 1], p_prior[k + 1]
        gain = np.linalg.solve(pp, f @ p_post[k]).T          # P_k F^T Pp^-1, Pp symmetric
        xs[k] = x_post[k] + gain @ (xs[k + 1] - x_prior[k + 1])
        ps[k] = p_post[k] + gain @ (ps[k + 1] - pp) @ gain.T
    return xs, ps


__all__ = ["rts_smooth"]
