"""Receiver velocity from Doppler: per-epoch robust weighted least squares, vectorised over epochs.

Each Doppler pseudorange rate (``Sequence.prr_m_s``, satellite clock drift removed) is linear in the
receiver velocity ``v`` and clock drift ``d`` once the position ``p`` is known (the model of
``estimators.models.doppler_measurement``, Sagnac included)::

    prr_i = e_i . (vs_i - v) + d + omega_e / c (vs_x p_y + s_x v_y - vs_y p_x - s_y v_x)

``e_i`` changes by less than 1e-5 rad for a 100 m position error, so the coarse fix is good enough for
``p``. The fit is iteratively reweighted with Huber weights on the residuals in sigmas, which bounds the
pull of a Doppler multipath outlier (urban NLOS Dopplers are off by metres per second).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lfgnss.constants import OMEGA_EARTH_RAD_S, SPEED_OF_LIGHT_M_S
from lfgnss.corrections import line_of_sight

#: Unknowns of the fit: three velocity components and the clock drift.
N_UNKNOWNS = 4


@dataclass(frozen=True)
class DopplerVelocity:
    """Per-epoch velocity fix from Doppler. Shapes: ``T`` epochs.

    Attributes
    ----------
    vel_ecef_m_s : (T, 3) receiver velocity, ECEF [m/s]; NaN where ``ok`` is False
    drift_m_s : (T,) receiver clock drift times c [m/s]; NaN where ``ok`` is False
    cov_m2_s2 : (T, 3, 3) velocity covariance [(m/s)^2] of the weighted fit; NaN where not ``ok``
    n_used : (T,) Dopplers in the fit
    ok : (T,) True where at least ``min_dopplers`` Dopplers gave a well-conditioned fix
    """

    vel_ecef_m_s: np.ndarray
    drift_m_s: np.ndarray
    cov_m2_s2: np.ndarray
    n_used: np.ndarray
    ok: np.ndarray


def doppler_design(sat_pos_ecef_m: np.ndarray, sat_vel_ecef_m_s: np.ndarray, rcv_ecef_m: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Linear Doppler model ``prr = a + A [v; d]``: offsets ``a`` (..., N) [m/s] and rows ``A`` (..., N, 4).

    ``sat_*`` are (..., N, 3), ``rcv_ecef_m`` (..., 3) broadcast over satellites.
    """
    s = np.asarray(sat_pos_ecef_m, float)
    vs = np.asarray(sat_vel_ecef_m_s, float)
    p = np.asarray(rcv_ecef_m, float)[..., None, :]
    los = line_of_sight(s, p)
    w = OMEGA_EARTH_RAD_S / SPEED_OF_LIGHT_M_S
    a = np.einsum("...j,...j->...", los, vs) + w * (vs[..., 0] * p[..., 1] - vs[..., 1] * p[..., 0])
    A = np.empty(s.shape[:-1] + (N_UNKNOWNS,))
    A[..., :3] = -los
    A[..., 0] -= w * s[..., 1]
    A[..., 1] += w * s[..., 0]
    A[..., 3] = 1.0
    return a, A


def cn0_doppler_variance_m2_s2(cn0_dbhz, sigma_m_s: float, cn0_ref_dbhz: float):
    """Doppler variance ``sigma^2 (1 + 10^((ref - C/N0) / 5))`` [(m/s)^2] at C/N0 [dB-Hz] (numpy array or torch tensor).

    Near ``sigma_m_s`` [m/s] well above ``cn0_ref_dbhz``, growing tenfold in variance per 5 dB below it
    (benchmarks/doppler_noise.py fits it to Dopplers at the true velocity).
    """
    return sigma_m_s ** 2 * (1.0 + 10.0 ** ((cn0_ref_dbhz - cn0_dbhz) / 5.0))


def doppler_velocity(prr_m_s: np.ndarray, prr_mask: np.ndarray, sat_pos_ecef_m: np.ndarray,
                     sat_vel_ecef_m_s: np.ndarray, rcv_ecef_m: np.ndarray, *, sigma_m_s: float | np.ndarray = 0.5,
                     huber_k: float = 1.5, iterations: int = 5, min_dopplers: int = 5,
                     max_condition: float = 1e8) -> DopplerVelocity:
    """Robust per-epoch velocity and clock drift from Doppler (T epochs, N slots).

    Parameters
    ----------
    prr_m_s, prr_mask : (T, N) pseudorange rates [m/s] and where they are usable
    sat_pos_ecef_m, sat_vel_ecef_m_s : (T, N, 3) satellite positions [m] and velocities [m/s]
    rcv_ecef_m : (T, 3) receiver position [m], e.g. the coarse fix; epochs with NaN get no fix
    sigma_m_s : a priori Doppler standard deviation [m/s]: one for all, or (T, N) per Doppler (weights 1 / sigma^2)
    huber_k : Huber threshold [sigmas] of the reweighting
    iterations : reweighting passes after the 1 / sigma^2-weighted fit
    min_dopplers : fewest Dopplers for a fix (5: one more than the unknowns, so an outlier can show)
    max_condition : epochs whose normal matrix is worse conditioned get no fix
    """
    mask = np.asarray(prr_mask, bool) & np.all(np.isfinite(np.asarray(rcv_ecef_m, float)), axis=-1)[:, None]
    sigma = np.broadcast_to(np.asarray(sigma_m_s, float), mask.shape)
    if not np.all(np.isfinite(sigma[mask]) & (sigma[mask] > 0)):
        raise ValueError("lfgnss/velocity.py: doppler_velocity needs a positive, finite sigma_m_s on every "
                         "Doppler used")
    sigma = np.where(mask, sigma, 1.0)
    rcv = np.nan_to_num(np.asarray(rcv_ecef_m, float))
    # Empty slots hold zeros; a dummy satellite 1e7 m away keeps their line of sight finite (0/0 would be NaN,
    # and NaN times a zero weight is still NaN in the normal equations).
    a, A = doppler_design(np.where(mask[..., None], sat_pos_ecef_m, 1.0e7 + rcv[:, None, :]),
                          np.where(mask[..., None], sat_vel_ecef_m_s, 0.0), rcv)
    y = np.where(mask, np.asarray(prr_m_s, float) - a, 0.0)
    n_used = mask.sum(axis=1)
    enough = n_used >= min_dopplers
    eye = np.eye(N_UNKNOWNS)
    inv_var = np.where(mask, sigma ** -2.0, 0.0)
    weight = inv_var
    x = np.zeros((mask.shape[0], N_UNKNOWNS))
    for it in range(iterations + 1):
        normal = np.einsum("tn,tni,tnj->tij", weight, A, A)
        normal[~enough] = eye                     # keep the batch solvable; those epochs are discarded
        # Dopplers of satellites in one spot of the sky: singular, so no fix (np.linalg.solve would raise)
        enough &= np.isfinite(normal).all(axis=(1, 2)) & (np.linalg.cond(normal) < max_condition)
        normal[~enough] = eye
        x = np.linalg.solve(normal, np.einsum("tn,tni,tn->ti", weight, A, y)[..., None])[..., 0]
        if it == iterations:
            break
        u = np.abs(y - np.einsum("tni,ti->tn", A, x)) / sigma
        weight = inv_var * np.minimum(1.0, huber_k / np.maximum(u, 1e-12))
    ok = enough                                   # the last normal matrix's condition was checked in the loop
    cov = np.linalg.inv(normal)[:, :3, :3]
    nan3 = np.full(3, np.nan)
    return DopplerVelocity(vel_ecef_m_s=np.where(ok[:, None], x[:, :3], nan3),
                           drift_m_s=np.where(ok, x[:, 3], np.nan),
                           cov_m2_s2=np.where(ok[:, None, None], cov, np.nan),
                           n_used=n_used.astype(np.int32), ok=ok)


__all__ = ["DopplerVelocity", "cn0_doppler_variance_m2_s2", "doppler_design", "doppler_velocity"]
