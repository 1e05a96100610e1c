"""Rauch-Tung-Striebel smoothing of a Kalman filter's run: each epoch estimated from the epochs after it too.

Given the filter's posteriors ``x_k, P_k``, its priors ``x^-_{k+1}, P^-_{k+1}`` and transitions
``F_{k+1}`` (``x^-_{k+1} = F_{k+1} x_k + u_{k+1}``, ``P^-_{k+1} = F_{k+1} P_k F_{k+1}^T + Q_{k+1}``),
backwards from the last epoch ``K`` an estimate may use (``x^s_K = x_K``)::

    C_k   = P_k F_{k+1}^T (P^-_{k+1})^-1
    x^s_k = x_k + C_k (x^s_{k+1} - x^-_{k+1})
    P^s_k = P_k + C_k (P^s_{k+1} - P^-_{k+1}) C_k^T

``K`` is the end of the epoch's segment (the whole-run smoother), or an earlier horizon (a fixed-lag
smoother: epoch k's estimate is ready once epoch ``K(k)`` has been filtered). The stored prior, not ``F x_k``,
enters the difference, so a deterministic input ``u`` (the EKF's receiver clock realignment,
``models.realign_clock``) is carried correctly; filterpy's ``KalmanFilter.rts_smoother`` recomputes the prior as
``F x_k`` and would smear a clock jump backwards. Filter restarts (re-initialisations from the coarse fix) end
a segment: nothing is smoothed across them. For the EKF this is the extended RTS smoother with the filter's
own linearisation points.
"""
from __future__ import annotations

import numpy as np


def rts_smooth(x_post: np.ndarray, p_post: np.ndarray, x_prior: np.ndarray, p_prior: np.ndarray,
               transition: np.ndarray, restart: np.ndarray, horizon: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
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
    horizon : (T,) int, optional
        Last epoch each epoch's estimate may use (fixed-lag smoothing); default: the end of its segment.
    """
    t_len = x_post.shape[0]
    valid = np.isfinite(x_post).all(1)
    link = np.zeros(t_len, bool)                      # epoch k+1 follows from epoch k
    link[:-1] = valid[:-1] & valid[1:] & ~np.asarray(restart, bool)[1:]
    m = np.flatnonzero(link)
    gains = np.zeros_like(p_post)
    gains[m] = np.linalg.solve(p_prior[m + 1], transition[m + 1] @ p_post[m]).transpose(0, 2, 1)  # Pp symmetric

    def step(k: np.ndarray, at: np.ndarray, xs: np.ndarray, ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One backward step from epoch ``at + 1`` to epoch ``at`` of the estimates in rows ``k`` of xs, ps."""
        c = gains[at]
        x = x_post[at] + np.einsum("kij,kj->ki", c, xs[k] - x_prior[at + 1])
        p = p_post[at] + c @ (ps[k] - p_prior[at + 1]) @ c.transpose(0, 2, 1)
        return x, p

    if horizon is None:
        xs, ps = np.array(x_post, float), np.array(p_post, float)
        for k in m[::-1]:
            x, p = step(np.array([k + 1]), np.array([k]), xs, ps)
            xs[k], ps[k] = x[0], p[0]
        return xs, ps

    # Fixed lag: every epoch's backward pass at once, one step further back per iteration.
    idx = np.arange(t_len)
    seg_end = np.minimum.accumulate(np.where(link, t_len, idx)[::-1])[::-1]   # first epoch without a successor
    end = np.clip(np.minimum(seg_end, np.asarray(horizon)), idx, None)
    xs, ps = x_post[end].copy(), p_post[end].copy()
    span = end - idx
    for j in range(int(span.max(initial=0)) - 1, -1, -1):
        k = np.flatnonzero(span > j)
        xs[k], ps[k] = step(k, k + j, xs, ps)
    return xs, ps


def lag_horizon(time_s: np.ndarray, lag_s: float) -> np.ndarray:
    """(T,) int: the last epoch within ``lag_s`` seconds after each epoch (a fixed-lag smoother's horizon)."""
    time_s = np.asarray(time_s, float)
    return np.searchsorted(time_s, time_s + lag_s + 1e-6, side="right") - 1     # 1 us: float time tags


__all__ = ["rts_smooth", "lag_horizon"]
