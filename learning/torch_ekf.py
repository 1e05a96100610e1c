"""Batched, differentiable EKF mirroring ``estimators.ekf.LfgnssEkf`` (same models, gate and resets).

Gradients flow from every output epoch back to the ``R`` and ``v^c`` of all earlier epochs of the
window (no truncation). Matrices come from ``estimators.models`` (``F = I + dt A``,
``Q = Q1 dt + Q2 dt^2 + Q3 dt^3``, P0), so this filter and the filterpy plug-in share one model.

Padded or unusable slots are neutralised rather than removed: their ``H`` rows and innovations are
exactly zero and their ``R`` is 1, so ``S`` is block diagonal and their Kalman-gain columns are exactly
zero: they cannot change the state, the covariance or any gradient.

Per epoch, both possible priors are gated and updated in one batched call of size 2B:

* the normal prior ``F x, F P F^T + Q``;
* the reset prior ``x0(coarse), P0``.

When more than ``reset_gated_fraction`` of the usable satellites fail the gate (not right after a reset) and their
median innovation is clock-jump sized (``clock_jump_min_m``), the prior's clock is realigned and gated again. The
reset result is taken at the first epoch with a coarse fix, at the first one after a gap > ``max_gap_s`` (no
position before it), when the realigned prior is still mostly gated, and when the normal update ends farther than
``reset_distance_m`` from a coarse fix of redundancy ``reset_min_redundancy`` or more; in the rows that reset,
satellites failing the post-fit check are dropped and the reset prior updated again. With
``EkfConfig.zupt_sigma_m_s``, epochs the Dopplers find standing still (``estimators.models.stationary_epochs``) add
a zero-velocity update. The gate
decision (a hard mask), the Huber variance factor (``EkfConfig.huber_k``), the standstill decision and the reset
choice carry no gradient; everything else does.

With ``noise_step`` the network runs inside the filter: at each epoch it is given every satellite's
innovation against the normal prior (``prior_innovation``; 0 where the epoch has no prior) and returns
that epoch's ``R`` and ``v^c``. The innovation input carries no gradient.

``rts_smooth`` runs the plug-in's RTS smoother (``estimators.smoother``) backwards over such a run, for
training with ``train.smooth``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from estimators import models
from estimators.base import STATUS_COASTED, STATUS_NONE, STATUS_RESET, STATUS_UPDATED
from estimators.models import EkfConfig
from estimators.noise import R_OFF_M2
from lfgnss.constants import OMEGA_EARTH_RAD_S, SPEED_OF_LIGHT_M_S

from .types import WindowBatch

#: Stand-in position for unusable satellite slots (far from any receiver; the rows are zeroed anyway).
_FAR_SAT_ECEF_M = (0.0, 0.0, 2.6e7)


@dataclass
class EkfOutput:
    """Filter output for B windows of T epochs, n = ``models.n_states(n_systems)``.

    Attributes
    ----------
    pos_ecef_m : (B, T, 3) float64
        Filtered position [m]; NaN where ``status == STATUS_NONE`` (no coarse fix yet).
    state : (B, T, n) float64
        Posterior state (zeros before the first fix).
    cov : (B, T, n, n) float64
        Posterior covariance (P0 before the first fix).
    n_used : (B, T) int64
        Satellites used in the update.
    status : (B, T) int64
        ``estimators.base.STATUS_*`` codes, as in the plug-in's Solution.
    n_gated : (B, T) int64
        Usable satellites rejected by the gate.
    n_doppler : (B, T) int64
        Dopplers used in the update.
    prior_state, prior_cov, transition : (B, T, n), (B, T, n, n), (B, T, n, n)
        The prior each epoch's normal update started from (after any clock realignment) and the transition
        ``F`` from the epoch before, for the RTS smoother (``rts_smooth``); unused where an epoch reset.
    """

    pos_ecef_m: torch.Tensor
    state: torch.Tensor
    cov: torch.Tensor
    n_used: torch.Tensor
    status: torch.Tensor
    n_gated: torch.Tensor
    n_doppler: torch.Tensor
    prior_state: torch.Tensor
    prior_cov: torch.Tensor
    transition: torch.Tensor


def geometric_range_m(sat_ecef_m: torch.Tensor, rcv_ecef_m: torch.Tensor) -> torch.Tensor:
    """Torch twin of ``lfgnss.corrections.geometric_range_m``: |s - r| + omega_e / c (x_s y_r - y_s x_r) [m].

    ``sat_ecef_m`` (..., 3), ``rcv_ecef_m`` broadcastable (..., 3); returns (...).
    """
    d = sat_ecef_m - rcv_ecef_m
    sagnac = OMEGA_EARTH_RAD_S / SPEED_OF_LIGHT_M_S * (sat_ecef_m[..., 0] * rcv_ecef_m[..., 1]
                                                       - sat_ecef_m[..., 1] * rcv_ecef_m[..., 0])
    return torch.linalg.norm(d, dim=-1) + sagnac


def _first_sight_clocks(x: torch.Tensor, known: torch.Tensor, sat: torch.Tensor, clock_rows: torch.Tensor,
                        pr: torch.Tensor, usable: torch.Tensor, system_index: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """(x, known) of ``estimators.models.first_sight_clocks`` for M rows: the clock terms of each constellation
    first seen (``known`` (M, C) False, satellites now) from its raw pseudoranges ``pr`` (M, N) [m], against the
    known constellations' lower median."""
    n_sys = known.shape[-1]
    system = system_index.clamp(min=0, max=n_sys - 1)
    seen = (torch.nn.functional.one_hot(system, n_sys).bool() & usable[..., None]).any(-2)     # (M, C)
    old = usable & torch.gather(known, 1, system)
    if not bool((usable & ~old).any()):                 # nothing new (nearly every epoch): the medians cost a third
        return x, known | seen                          # of the filter's time
    h, _ = _measurement(x, sat, clock_rows)
    v = pr - h
    ref = _lower_median(v, old)                         # 0 where no known satellite, as the plug-in's
    shift = torch.stack([torch.where(seen[:, j] & ~known[:, j], _lower_median(v, usable & (system_index == j)) - ref,
                                     torch.zeros_like(ref)) for j in range(n_sys)], -1)      # (M, C)
    delta = torch.zeros_like(x)
    delta[:, models.CLOCK] = shift[:, 0]
    delta[:, models.ISB0:] = shift[:, 1:] - shift[:, :1]
    return x + delta, known | seen


def _clock_rows(system_index: torch.Tensor, usable: torch.Tensor, n: int) -> torch.Tensor:
    """(..., N, n) float64: the clock/ISB part of H (1 at the clock column and at the ISB column)."""
    cols = torch.where(system_index >= 1, models.ISB0 + system_index - 1, torch.full_like(system_index, models.CLOCK))
    rows = torch.nn.functional.one_hot(torch.where(usable, cols, 0), n).to(torch.float64)
    rows[..., models.CLOCK] = 1.0
    return rows * usable[..., None]


def _measurement(x: torch.Tensor, sat: torch.Tensor, clock_rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """h (M, N) and H (M, N, n) at states ``x`` (M, n); mirrors ``estimators.models.measurement``."""
    p = x[:, None, :3]
    d = sat - p
    los = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    h = geometric_range_m(sat, p) + (clock_rows @ x[:, :, None])[..., 0]
    H = torch.cat([-los, clock_rows[..., 3:]], dim=-1)
    return h, H


def _doppler_measurement(x: torch.Tensor, sat: torch.Tensor, sat_vel: torch.Tensor, usable: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """g (M, N) and G (M, N, n) at states ``x`` (M, n); mirrors ``estimators.models.doppler_measurement``."""
    p, v = x[:, None, :3], x[:, None, 3:6]
    d = sat - p
    los = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    sagnac = OMEGA_EARTH_RAD_S / SPEED_OF_LIGHT_M_S * (sat_vel[..., 0] * p[..., 1] + sat[..., 0] * v[..., 1]
                                                       - sat_vel[..., 1] * p[..., 0] - sat[..., 1] * v[..., 0])
    g = (los * (sat_vel - v)).sum(-1) + x[:, None, models.DRIFT] + sagnac
    G = torch.zeros(*los.shape[:-1], x.shape[-1], dtype=x.dtype, device=x.device)
    G[..., 3:6] = -los
    G[..., models.DRIFT] = 1.0
    return g, G * usable[..., None]


def _gate_and_update(x: torch.Tensor, P: torch.Tensor, sat: torch.Tensor, clock_rows: torch.Tensor,
                     z: torch.Tensor, r: torch.Tensor, usable: torch.Tensor, allowed: torch.Tensor,
                     config: EkfConfig, doppler: tuple | None = None, still: torch.Tensor | None = None
                     ) -> tuple:
    """Gate then Joseph-update priors (x (M, n), P (M, n, n)) with the usable slots (M, N).

    ``doppler`` = (sat_vel (M, N, 3), prr (M, N), usable (M, N), variance (M, N)) adds the Doppler rows
    (``estimators.models.doppler_variance_m2_s2``); pseudoranges and Dopplers are gated alike, each block needs
    ``min_sats_for_update`` kept rows to be used. ``still`` (M,) adds the zero-velocity rows where True
    (``EkfConfig.zupt_sigma_m_s``, never gated). Returns (x, P, n_used (M,), n_rejected (M,),
    n_usable (M,), n_doppler (M,)), counts of pseudoranges except ``n_doppler``; rows with
    ``allowed == False`` are returned unchanged (their numbers are never selected by the caller).
    """
    h, H = _measurement(x, sat, clock_rows)
    v = z - h
    n_pr = v.shape[-1]
    if doppler is not None:
        sat_vel, prr, dop_usable, dop_var = doppler
        g, G = _doppler_measurement(x, sat, sat_vel, dop_usable)
        v = torch.cat([v, prr - g], -1)
        H = torch.cat([H, G], -2)
        r = torch.cat([r, dop_var], -1)
        usable = torch.cat([usable, dop_usable], -1)
    HP = H @ P
    with torch.no_grad():
        usable = usable & allowed[:, None]
        t = v.abs() / torch.sqrt((HP * H).sum(-1) + r)
        keep = usable & (t <= config.gate_sigma) if config.gate_sigma > 0 else usable
        # 1 off the kept rows (padded slots may have t = 0/0, and 0 * NaN would poison r's gradient) and on Dopplers
        scale = torch.where(keep, models.huber_scale(t, config.huber_k), torch.ones_like(t))
        scale[:, n_pr:] = 1.0
        n_keep_pr = keep[:, :n_pr].sum(-1)
        n_keep_dop = keep[:, n_pr:].sum(-1)
        enough = torch.cat([(n_keep_pr >= config.min_sats_for_update)[:, None].expand(-1, n_pr),
                            (n_keep_dop >= config.min_sats_for_update)[:, None].expand(-1, keep.shape[-1] - n_pr)], -1)
        used = keep & enough
        n_usable = usable[:, :n_pr].sum(-1)
    n_rows = used.shape[-1]
    if still is not None:
        H_still = torch.zeros(x.shape[0], 3, x.shape[-1], dtype=H.dtype, device=H.device)
        H_still[:, :, models.VEL] = torch.eye(3, dtype=H.dtype, device=H.device)
        H = torch.cat([H, H_still], -2)
        v = torch.cat([v, -x[:, models.VEL]], -1)
        r = torch.cat([r, torch.full_like(v[:, :3], config.zupt_sigma_m_s ** 2)], -1)
        scale = torch.cat([scale, torch.ones_like(v[:, :3])], -1)
        used = torch.cat([used, (still & allowed)[:, None].expand(-1, 3)], -1)
    usedf = used.to(torch.float64)
    Hm = H * usedf[..., None]
    vm = torch.where(used, v, torch.zeros_like(v))
    Rm = torch.where(used, r * scale, torch.ones_like(r))
    PHt = (Hm @ P).transpose(-1, -2)                       # (M, n, N) = P H^T (P symmetric)
    S = Hm @ PHt + torch.diag_embed(Rm)                     # S = H P H^T + R
    L = torch.linalg.cholesky(S)
    K = torch.cholesky_solve(PHt.transpose(-1, -2), L).transpose(-1, -2)   # K = P H^T S^-1
    x_new = x + (K @ vm[..., None])[..., 0]                 # x = x^- + K (v + v^c)
    eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
    IKH = eye - K @ Hm
    P_new = IKH @ P @ IKH.transpose(-1, -2) + (K * Rm[:, None, :]) @ K.transpose(-1, -2)   # Joseph
    return x_new, P_new, used[:, :n_pr].sum(-1), n_usable - n_keep_pr, n_usable, used[:, n_pr:n_rows].sum(-1)


def _lower_median(v: torch.Tensor, usable: torch.Tensor) -> torch.Tensor:
    """(M,) lower median of ``v`` (M, N) over the usable slots (``estimators.models.lower_median``); 0 if none."""
    v = torch.where(usable, v, torch.full((), float("nan"), dtype=v.dtype, device=v.device))
    return torch.nan_to_num(torch.nanmedian(v, dim=-1).values, nan=0.0)


def _clock_shift(x: torch.Tensor, sat: torch.Tensor, clock_rows: torch.Tensor, z: torch.Tensor,
                 usable: torch.Tensor) -> torch.Tensor:
    """(M,) lower median innovation [m] of the usable pseudoranges."""
    h, _ = _measurement(x, sat, clock_rows)
    return _lower_median(z - h, usable)


def innovation_feature(innovation_m: torch.Tensor) -> torch.Tensor:
    """Torch twin of ``lfgnss.features.innovation_feature``: ``sign(v) ln(1 + |v|)``."""
    return torch.sign(innovation_m) * torch.log1p(innovation_m.abs())


@torch.no_grad()
def prior_innovation(x: torch.Tensor, sat: torch.Tensor, clock_rows: torch.Tensor, pr: torch.Tensor,
                     usable: torch.Tensor, has_prior: torch.Tensor) -> torch.Tensor:
    """(M, N) ``pr - h(x)`` minus its lower median over the usable slots [m]; 0 elsewhere and where not ``has_prior``.

    Mirrors ``estimators.models.prior_innovation_m``.
    """
    h, _ = _measurement(x, sat, clock_rows)
    v = pr - h
    v = v - _lower_median(v, usable)[:, None]
    return torch.where(usable & has_prior[:, None], v, torch.zeros((), dtype=x.dtype, device=x.device))


def _check_noise(r_m2: torch.Tensor, vc_m: torch.Tensor, usable: torch.Tensor) -> None:
    """FloatingPointError where a usable slot has an R [m^2] that is not finite and > 0 or a non-finite v^c [m].

    The plug-in refuses such noise (``estimators.noise.checked_noise``); here a NaN R would fail every gate test and
    drop its satellite in silence, so a diverged network would still score finite positions.
    """
    with torch.no_grad():
        bad = usable & ~(torch.isfinite(r_m2) & (r_m2 > 0) & torch.isfinite(vc_m))
        if bool(bad.any()):
            raise FloatingPointError(f"learning/torch_ekf.py: the noise gave {int(bad.sum())} usable pseudorange(s) "
                                     f"an R that is not finite and > 0 or a non-finite v^c (a diverged network?)")


def _measurement_noise(pr: torch.Tensor, r_m2: torch.Tensor, vc_m: torch.Tensor, usable: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """(z, R) float64, shaped like ``pr``: ``z = pr + v^c`` (the one place v^c enters) and R; 0 and 1 where unusable."""
    f64 = torch.float64
    z = pr + torch.where(usable, vc_m.to(f64), torch.zeros((), dtype=f64, device=pr.device))
    return z, torch.where(usable, r_m2.to(f64), torch.ones((), dtype=f64, device=pr.device))


#: ``noise_step(k, innovation_feature)`` -> (r_m2, vc_m), each (B, N), for epoch ``k`` of the window.
NoiseStep = Callable[[int, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def _vertical_noise_increment(dt: torch.Tensor, pos: torch.Tensor, n: int, config) -> torch.Tensor:
    """(B, n, n) ``models.vertical_noise_increment`` for a batch: dt (B, 1, 1) [s], pos (B, 3) ECEF [m]."""
    norm = pos.norm(dim=-1, keepdim=True)
    u = torch.where(norm >= 1.0, pos / norm.clamp_min(1.0), torch.zeros((), dtype=pos.dtype, device=pos.device))
    uu = (config.q_vel_up_m2_s3 - config.q_vel_m2_s3) * u[:, :, None] * u[:, None, :]
    q = torch.zeros(pos.shape[0], n, n, dtype=pos.dtype, device=pos.device)
    q[:, :3, :3] = dt ** 3 / 3.0 * uu
    q[:, :3, 3:6] = q[:, 3:6, :3] = dt ** 2 / 2.0 * uu
    q[:, 3:6, 3:6] = dt * uu
    return q


def batch_ekf(batch: WindowBatch, r_m2: torch.Tensor | None, vc_m: torch.Tensor | None, *, n_systems: int,
              config: EkfConfig, noise_step: NoiseStep | None = None) -> EkfOutput:
    """Run the EKF over B windows of T epochs, differentiably in ``r_m2`` and ``vc_m``.

    Each window starts un-initialised at its epoch 0 and initialises from its first coarse fix, as
    ``estimators.ekf.LfgnssEkf.solve`` does at the start of a sequence.

    Parameters
    ----------
    batch : WindowBatch
        Geometry, pseudoranges, masks, times and coarse fixes (float64).
    r_m2 : (B, T, N)
        Pseudorange variances R [m^2], finite and > 0 on usable slots (any value elsewhere; else a
        FloatingPointError). Above ``R_OFF_M2`` a slot is switched off, pseudorange and Doppler, as in the plug-in
        (not with ``noise_step``: the network cannot reach it).
    vc_m : (B, T, N)
        Innovation compensations v^c [m], finite (a non-finite one on a usable slot is a FloatingPointError).
    n_systems : int
        Constellations C in the state (clock + C - 1 ISBs).
    config : EkfConfig
        The same settings the plug-in takes; a ``glonass_sigma_factor`` other than 1 scales R on the batch's
        ``glonass`` slots (``learning.data.collate`` flags them) and needs those flags.
    noise_step : NoiseStep or None
        If given, ``r_m2`` and ``vc_m`` must be None: each epoch's noise comes from
        ``noise_step(k, innovation_feature(prior_innovation))`` instead.
    """
    b_len, t_len, n_slots = batch.mask.shape
    if (noise_step is None) == (r_m2 is None or vc_m is None):
        raise ValueError("learning/torch_ekf.py: give either r_m2 and vc_m or noise_step")
    if noise_step is None and (r_m2.shape != (b_len, t_len, n_slots) or vc_m.shape != (b_len, t_len, n_slots)):
        raise ValueError(f"learning/torch_ekf.py: r_m2 {tuple(r_m2.shape)} and vc_m {tuple(vc_m.shape)} must be "
                         f"{(b_len, t_len, n_slots)}")
    if batch.coarse_clock_m.shape[-1] < n_systems:
        raise ValueError(f"learning/torch_ekf.py: coarse_clock_m has {batch.coarse_clock_m.shape[-1]} systems, "
                         f"n_systems is {n_systems}")
    dev = batch.pr_m.device
    f64 = torch.float64
    n = models.n_states(n_systems)

    time = batch.time_gps_s.to(f64)
    dt_all = torch.zeros_like(time)
    dt_all[:, 1:] = time[:, 1:] - time[:, :-1]
    if t_len > 1 and not bool((dt_all[:, 1:] > 0).all()):
        raise ValueError("learning/torch_ekf.py: epoch times must increase within every window")

    # Inputs made harmless where unusable (finite, no influence, no NaN gradients).
    sat_ok = torch.isfinite(batch.sat_pos_ecef_m).all(-1)
    usable_all = (batch.mask & torch.isfinite(batch.pr_m) & sat_ok & (batch.system_index >= 0)
                  & (batch.system_index < n_systems))
    if r_m2 is not None:                 # switched off as in the plug-in (estimators.noise.switched_on); NaN: refused
        usable_all = usable_all & ~(r_m2.detach() > R_OFF_M2)
    far = torch.tensor(_FAR_SAT_ECEF_M, dtype=f64, device=dev)
    sat_all = torch.where(usable_all[..., None], batch.sat_pos_ecef_m.to(f64), far)
    pr = torch.where(usable_all, batch.pr_m.to(f64), torch.zeros((), dtype=f64, device=dev))
    if config.glonass_sigma_factor != 1.0 and batch.glonass is None:
        raise ValueError("learning/torch_ekf.py: EkfConfig.glonass_sigma_factor needs the batch's glonass flags "
                         "(learning.data.collate sets them)")
    glonass = torch.zeros_like(usable_all) if batch.glonass is None else batch.glonass.to(dev).bool()
    r_factor_all = models.pseudorange_variance_factor(glonass & usable_all, config)
    if noise_step is None:
        _check_noise(r_m2, vc_m, usable_all)
        z_all, r_all = _measurement_noise(pr, r_m2, vc_m, usable_all)
        r_all = r_all * r_factor_all
    clock_rows_all = _clock_rows(batch.system_index.long(), usable_all, n)
    use_doppler = config.doppler_sigma_m_s > 0
    dop_all = usable_all & batch.prr_mask if use_doppler else torch.zeros_like(usable_all)
    zero = torch.zeros((), dtype=f64, device=dev)
    prr_all = torch.where(dop_all, batch.prr_m_s.to(f64), zero)
    satvel_all = torch.where(dop_all[..., None], batch.sat_vel_ecef_m_s.to(f64), zero)
    cn0_all = batch.cn0_dbhz.to(f64)
    if use_doppler and config.doppler_cn0_ref_dbhz is not None and not bool(torch.isfinite(cn0_all[dop_all]).all()):
        raise ValueError("learning/torch_ekf.py: a C/N0-dependent Doppler variance (EkfConfig.doppler_cn0_ref_dbhz) "
                         "needs the batch's cn0_dbhz, finite, on every Doppler used")
    dopvar_all = models.doppler_variance_m2_s2(torch.where(dop_all, cn0_all, torch.full_like(cn0_all, 45.0)), config)
    still_all = None
    if config.zupt_sigma_m_s is not None:                 # a decision, not differentiated: numpy, as the plug-in
        flat = lambda a: a.detach().cpu().numpy().reshape((b_len * t_len,) + tuple(a.shape[2:]))  # noqa: E731
        still_all = torch.as_tensor(models.stationary_epochs(
            flat(prr_all), flat(dop_all), flat(batch.sat_pos_ecef_m.to(f64)), flat(satvel_all),
            flat(batch.coarse_ecef_m.to(f64)), flat(dopvar_all), config).reshape(b_len, t_len), device=dev)

    coarse_ok_all = torch.isfinite(batch.coarse_ecef_m).all(-1) & torch.isfinite(batch.coarse_clock_m[..., 0])
    coarse_pos_all = torch.where(coarse_ok_all[..., None], batch.coarse_ecef_m.to(f64), zero)
    judges_all = coarse_ok_all & torch.as_tensor(    # a decision, not differentiated: numpy, as the plug-in
        models.fix_can_judge(usable_all.cpu().numpy(), batch.system_index.cpu().numpy(), n_systems, config),
        device=dev)
    clk = torch.nan_to_num(batch.coarse_clock_m[..., :n_systems].to(f64), nan=0.0)
    x0_all = torch.zeros(b_len, t_len, n, dtype=f64, device=dev)
    x0_all[..., :3] = coarse_pos_all
    x0_all[..., models.CLOCK] = torch.where(coarse_ok_all, clk[..., 0], zero)
    drift0, found0 = models.coarse_drift(   # from the data, as the plug-in's
        *(a.detach().cpu().numpy() for a in (prr_all, dop_all, batch.sat_pos_ecef_m.to(f64), satvel_all,
                                             coarse_pos_all)))
    x0_all[..., models.DRIFT] = torch.as_tensor(drift0, dtype=f64, device=dev)
    drift_found_all = torch.as_tensor(found0, device=dev)
    # a start without a Doppler drift: its second epoch takes it from the two coarse clocks (as the plug-in)
    clock0 = batch.coarse_clock_m[..., 0].to(f64).detach().cpu().numpy()
    clock_drift = np.full(clock0.shape, np.nan)
    clock_drift[:, 1:] = models.coarse_clock_drift_m_s(clock0[:, :-1], clock0[:, 1:], dt_all[:, 1:].cpu().numpy())
    clock_drift_all = torch.as_tensor(clock_drift, dtype=f64, device=dev)
    x0_all[..., models.ISB0:] = clk[..., 1:]
    isb_finite_all = torch.isfinite(batch.coarse_clock_m[..., 1:n_systems])     # ISBs the coarse fix knew
    system_all = batch.system_index.long()
    reference_seen_all = (usable_all & (system_all == 0)).any(-1)
    drift_column = torch.zeros(n, dtype=torch.bool, device=dev)
    drift_column[models.DRIFT] = True

    P0 = torch.as_tensor(models.initial_covariance(n_systems, config), dtype=f64, device=dev)
    A = torch.as_tensor(models.transition_generator(n_systems), dtype=f64, device=dev)
    q1, q2, q3 = (torch.as_tensor(q, dtype=f64, device=dev) for q in models.process_noise_coefficients(n_systems, config))
    eye = torch.eye(n, dtype=f64, device=dev)

    x = torch.zeros(b_len, n, dtype=f64, device=dev)
    P = P0.expand(b_len, n, n)
    started = torch.zeros(b_len, dtype=torch.bool, device=dev)
    clock_known = torch.zeros(b_len, n_systems, dtype=torch.bool, device=dev)
    drift_found = torch.zeros(b_len, dtype=torch.bool, device=dev)
    prev_status = torch.full((b_len,), STATUS_NONE, dtype=torch.int64, device=dev)
    xs, Ps, used_out, gated_out, status_out, dop_out, priors, prior_Ps, Fs = [], [], [], [], [], [], [], [], []
    for k in range(t_len):
        if k > 0:
            take = (started & (prev_status == STATUS_RESET) & ~drift_found & reference_seen_all[:, k - 1]
                    & reference_seen_all[:, k] & torch.isfinite(clock_drift_all[:, k])
                    & ~(dt_all[:, k] > config.max_gap_s))
            x = torch.where(take[:, None] & drift_column, torch.nan_to_num(clock_drift_all[:, k, None]), x)
        dt = dt_all[:, k, None, None]
        F = eye + dt * A
        x_pred = (F @ x[..., None])[..., 0]
        P_pred = F @ P @ F.transpose(-1, -2) + q1 * dt + q2 * dt ** 2 + q3 * dt ** 3
        if config.q_vel_up_m2_s3 is not None:
            P_pred = P_pred + _vertical_noise_increment(dt, x[:, :3].detach(), n, config)
        coarse_ok = coarse_ok_all[:, k]
        started = started & ~(dt_all[:, k] > config.max_gap_s)     # a long gap: restart at the next coarse fix
        reset_a = ~started & coarse_ok
        normal = started & ~reset_a
        # a constellation first seen since the (re)start: its clock term from its satellites (first_sight_clocks)
        x_pred, known_n = _first_sight_clocks(x_pred, clock_known, sat_all[:, k], clock_rows_all[:, k], pr[:, k],
                                              usable_all[:, k], system_all[:, k])
        known_0 = torch.cat([(usable_all[:, k] & (system_all[:, k] == 0)).any(-1, keepdim=True),
                             isb_finite_all[:, k]], -1)
        x0_k, known_r = _first_sight_clocks(x0_all[:, k], known_0, sat_all[:, k], clock_rows_all[:, k], pr[:, k],
                                            usable_all[:, k], system_all[:, k])
        if noise_step is None:
            z_k, r_k = z_all[:, k], r_all[:, k]
        else:
            innov = prior_innovation(x_pred, sat_all[:, k], clock_rows_all[:, k], pr[:, k], usable_all[:, k], normal)
            r_step, vc_step = noise_step(k, innovation_feature(innov))
            _check_noise(r_step, vc_step, usable_all[:, k])
            z_k, r_k = _measurement_noise(pr[:, k], r_step, vc_step, usable_all[:, k])
            r_k = r_k * r_factor_all[:, k]

        # Both branches in one batched call: rows [0, B) normal prior, [B, 2B) reset prior.
        two = lambda a: torch.cat([a, a], 0)  # noqa: E731
        dop_k = (satvel_all[:, k], prr_all[:, k], dop_all[:, k], dopvar_all[:, k]) if use_doppler else None
        still_k = None if still_all is None else still_all[:, k]
        xu, Pu, n_used2, n_rej2, n_usable2, n_dop2 = _gate_and_update(
            torch.cat([x_pred, x0_k], 0), torch.cat([P_pred, P0.expand(b_len, n, n)], 0),
            two(sat_all[:, k]), two(clock_rows_all[:, k]), two(z_k), two(r_k),
            two(usable_all[:, k]), torch.cat([normal, coarse_ok], 0), config,
            tuple(two(a) for a in dop_k) if use_doppler else None, None if still_k is None else two(still_k))
        x_n, x_r = xu[:b_len], xu[b_len:]
        P_n, P_r = Pu[:b_len], Pu[b_len:]
        with torch.no_grad():
            n_usable = n_usable2[:b_len]
            # the realignment needs no coarse fix, only the reset after a failed one (reset_g & coarse_ok below)
            reset_g = (normal & (prev_status != STATUS_RESET) & (n_usable >= config.reset_min_sats)
                       & (n_rej2[:b_len].to(f64) > config.reset_gated_fraction * n_usable.to(f64)))
            if not config.gate_sigma > 0:
                reset_g = torch.zeros_like(reset_g)
        n_used_n, n_rej_n, n_dop_n = n_used2[:b_len], n_rej2[:b_len], n_dop2[:b_len]
        x_prior = x_pred
        if bool(reset_g.any()):
            # Mostly gated: a receiver clock jump if the median innovation is one (as the plug-in does).
            shift = _clock_shift(x_pred, sat_all[:, k], clock_rows_all[:, k], z_k, usable_all[:, k])
            x_c = x_pred.clone()
            x_c[:, models.CLOCK] = x_c[:, models.CLOCK] + shift        # models.realign_clock
            with torch.no_grad():
                try_jump = reset_g & (shift.abs() >= config.clock_jump_min_m)
            xc, Pc, n_used_c, n_rej_c, _, n_dop_c = _gate_and_update(
                x_c, P_pred, sat_all[:, k], clock_rows_all[:, k], z_k, r_k, usable_all[:, k], try_jump,
                config, dop_k, still_k)
            with torch.no_grad():
                realigned = try_jump & ~(n_rej_c.to(f64) > config.reset_gated_fraction * n_usable.to(f64))
            x_n = torch.where(realigned[:, None], xc, x_n)
            x_prior = torch.where(realigned[:, None], x_c, x_pred)
            P_n = torch.where(realigned[:, None, None], Pc, P_n)
            n_used_n = torch.where(realigned, n_used_c, n_used_n)
            n_rej_n = torch.where(realigned, n_rej_c, n_rej_n)
            n_dop_n = torch.where(realigned, n_dop_c, n_dop_n)
            reset_g = try_jump & ~realigned & coarse_ok     # a smaller median: multipath, no reset
        with torch.no_grad():
            far_off = torch.linalg.norm(x_n[:, :3] - coarse_pos_all[:, k], dim=-1) > config.reset_distance_m
            reset_d = normal & ~reset_g & judges_all[:, k] & far_off
            reset = reset_a | reset_g | reset_d
            keep_n = normal & ~reset
            measured = n_used_n + n_dop_n > 0 if still_k is None else (n_used_n + n_dop_n > 0) | still_k
            updated = torch.where(measured, STATUS_UPDATED, STATUS_COASTED)
            status = torch.where(reset, STATUS_RESET, torch.where(keep_n, updated, STATUS_NONE))
        n_used_r, n_rej_r, n_dop_r = n_used2[b_len:], n_rej2[b_len:], n_dop2[b_len:]
        if config.gate_sigma > 0 and bool(reset.any()):
            # Post-fit check of the reset update (as the plug-in's reset): drop satellites beyond the gate.
            h_r, _ = _measurement(x_r, sat_all[:, k], clock_rows_all[:, k])
            with torch.no_grad():
                ok = usable_all[:, k] & ((z_k - h_r).abs() <= config.gate_sigma * torch.sqrt(r_k))
                n_ok, n_us = ok.sum(-1), usable_all[:, k].sum(-1)
                redo = reset & (n_ok > 0) & (n_ok < n_us)
            if bool(redo.any()):
                x2, P2, n_used_2, n_rej_2, _, n_dop_2 = _gate_and_update(
                    x0_k, P0.expand(b_len, n, n), sat_all[:, k], clock_rows_all[:, k], z_k,
                    r_k, ok, redo, config, dop_k, still_k)
                x_r = torch.where(redo[:, None], x2, x_r)
                P_r = torch.where(redo[:, None, None], P2, P_r)
                n_used_r = torch.where(redo, n_used_2, n_used_r)
                n_rej_r = torch.where(redo, n_rej_2 + n_us - n_ok, n_rej_r)
                n_dop_r = torch.where(redo, n_dop_2, n_dop_r)
        x = torch.where(reset[:, None], x_r, torch.where(keep_n[:, None], x_n, x))
        P = torch.where(reset[:, None, None], P_r, torch.where(keep_n[:, None, None], P_n, P))
        started = started | reset
        clock_known = torch.where(reset[:, None], known_r, torch.where(keep_n[:, None], known_n, clock_known))
        drift_found = torch.where(reset, drift_found_all[:, k], drift_found)
        prev_status = status
        xs.append(x)
        Ps.append(P)
        priors.append(x_prior)
        prior_Ps.append(P_pred)
        Fs.append(F.expand(b_len, n, n))
        status_out.append(status)
        used_out.append(torch.where(reset, n_used_r, torch.where(keep_n, n_used_n, 0)))
        gated_out.append(torch.where(reset, n_rej_r, torch.where(keep_n, n_rej_n, 0)))
        dop_out.append(torch.where(reset, n_dop_r, torch.where(keep_n, n_dop_n, 0)))

    state = torch.stack(xs, 1)
    status = torch.stack(status_out, 1)
    pos = torch.where((status == STATUS_NONE)[..., None], torch.full((), float("nan"), dtype=f64, device=dev),
                      state[..., :3])
    return EkfOutput(pos_ecef_m=pos, state=state, cov=torch.stack(Ps, 1), n_used=torch.stack(used_out, 1),
                     status=status, n_gated=torch.stack(gated_out, 1), n_doppler=torch.stack(dop_out, 1),
                     prior_state=torch.stack(priors, 1), prior_cov=torch.stack(prior_Ps, 1),
                     transition=torch.stack(Fs, 1))


def rts_smooth(out: EkfOutput) -> torch.Tensor:
    """Smoothed positions (B, T, 3) [m] of a filter run: ``estimators.smoother.rts_smooth`` over each window.

    Batched and differentiable; a reset ends a segment and epochs before the first fix stay NaN, as there.
    """
    status = out.status
    started = status != STATUS_NONE
    link = started[:, :-1] & started[:, 1:] & (status[:, 1:] != STATUS_RESET)    # epoch k+1 follows from k
    t_len = status.shape[1]
    smoothed = [out.state[:, -1]]
    for k in range(t_len - 2, -1, -1):
        f, pp = out.transition[:, k + 1], out.prior_cov[:, k + 1]
        gain = torch.linalg.solve(pp, f @ out.cov[:, k]).transpose(-1, -2)        # P F^T Pp^-1, Pp symmetric
        x = out.state[:, k] + (gain @ (smoothed[-1] - out.prior_state[:, k + 1])[..., None])[..., 0]
        smoothed.append(torch.where(link[:, k, None], x, out.state[:, k]))
    state = torch.stack(smoothed[::-1], 1)
    return torch.where((status == STATUS_NONE)[..., None], torch.full((), float("nan"), dtype=state.dtype,
                                                                      device=state.device), state[..., :3])


__all__ = ["EkfOutput", "batch_ekf", "rts_smooth", "geometric_range_m"]
