"""Training losses on filtered positions: dynamic hard-example mining (HEM) and plain RMSE.

Samples are the labelled epochs of every window in the batch. Per sample (paper eqs. for L_dhem):

    L = ||e||_2                          e = x_pred - x_true (ENU; the norm is the same in ECEF)
                                         (``up_weight`` u != 1: L = sqrt(e_E^2 + e_N^2 + u^2 e_U^2))
    w = (1 - sqrt(L / max L)) ** (gamma * exp(-lambda * L))     max over the batch, detached
    l = alpha * w * L
    loss = sqrt(mean(l ** 2))

``rmse_loss`` (the "w/o HEM" ablation) is ``sqrt(mean(L ** 2))``. Epochs whose truth is NaN (no
label) or whose estimate is not finite are left out of both.

``compensation_loss`` is an optional second term (``loss.vc_weight``) that supervises v^c per satellite
with the pseudorange's error at the true position (``pseudorange_error_m``), where the position loss
reaches it only through the filter; ``variance_loss`` (``loss.r_weight``) does the same for R, by the Gaussian
negative log-likelihood of the error left after v^c.
"""
from __future__ import annotations

import math

import torch

from lfgnss.constants import WGS84_F

_TINY = 1e-12
_B_OVER_A_SQ = (1.0 - WGS84_F) ** 2


def up_unit(ecef_m: torch.Tensor) -> torch.Tensor:
    """Local up (ellipsoid normal) unit vectors (..., 3) at ECEF points ``ecef_m`` (..., 3) [m]."""
    n = ecef_m * ecef_m.new_tensor([1.0, 1.0, 1.0 / _B_OVER_A_SQ])
    return n / torch.linalg.vector_norm(n, dim=-1, keepdim=True)


def error_norm_m(pos_m: torch.Tensor, truth_m: torch.Tensor, *, up_weight: float = 1.0
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Position error norms of the labelled samples, the up component scaled by ``up_weight``.

    Parameters
    ----------
    pos_m, truth_m : (..., 3) estimated and true ECEF positions [m] (truth NaN = unlabelled); with the
        default ``up_weight`` 1 any frame will do (the norm is frame-free)
    up_weight : factor on the vertical error (0: horizontal error only)

    Returns
    -------
    L : (K,) error norms [m] of the K valid samples (gradient-safe at zero error)
    valid : (...) bool, which samples were used
    """
    if pos_m.shape != truth_m.shape or pos_m.shape[-1] != 3:
        raise ValueError(f"positions {tuple(pos_m.shape)} and truth {tuple(truth_m.shape)} must both be (..., 3)")
    valid = torch.isfinite(truth_m).all(dim=-1) & torch.isfinite(pos_m).all(dim=-1)
    e = pos_m[valid] - truth_m[valid]
    if up_weight != 1.0:
        u = up_unit(truth_m[valid])
        e = e + (up_weight - 1.0) * (e * u).sum(dim=-1, keepdim=True) * u
    return torch.sqrt(torch.clamp((e * e).sum(dim=-1), min=_TINY)), valid


def hem_weights(L: torch.Tensor, *, gamma: float, lam: float) -> torch.Tensor:
    """w = (1 - sqrt(L / max L)) ** (gamma * exp(-lambda L)), max detached; w = 0 at the maximum.

    Parameters
    ----------
    L : (K,) non-negative error norms [m]
    """
    base = 1.0 - torch.sqrt(L / L.detach().max().clamp(min=_TINY))
    power = gamma * torch.exp(-lam * L)
    positive = base > 0
    # where(base > 0) twice: the exact value 0 at the maximum without a 0 ** p NaN gradient.
    safe = torch.where(positive, base, torch.ones_like(base))
    return torch.where(positive, safe ** power, torch.zeros_like(base))


def root_mean_square(x: torch.Tensor) -> torch.Tensor:
    """sqrt(mean(x ** 2)) with a zero gradient where that is 0: sqrt'(0) is infinite, and times the zero
    errors it would make every gradient NaN (HEM weighs a batch's single or all-equal errors 0)."""
    m = torch.mean(x ** 2)
    positive = m > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, m, torch.ones_like(m))), torch.zeros_like(m))


def hem_loss(pos_m: torch.Tensor, truth_m: torch.Tensor, *, alpha: float = 0.75, gamma: float = 1.5,
             lam: float = 1.0, up_weight: float = 1.0) -> torch.Tensor:
    """Dynamic hard-example-mining loss over all labelled samples.

    Parameters
    ----------
    pos_m, truth_m : (..., 3) estimated and true positions [m]; truth NaN where unlabelled.
    alpha, gamma, lam : loss scale, initial difficulty exponent, exponent decay rate [1/m].
    up_weight : factor on the vertical error (``error_norm_m``).

    Returns
    -------
    scalar tensor; raises ValueError when no sample is labelled.
    """
    L, _ = error_norm_m(pos_m, truth_m, up_weight=up_weight)
    if L.numel() == 0:
        raise ValueError("hem_loss: no labelled sample with a finite estimate in the batch")
    sample = alpha * hem_weights(L, gamma=gamma, lam=lam) * L
    return root_mean_square(sample)


def rmse_loss(pos_m: torch.Tensor, truth_m: torch.Tensor, *, up_weight: float = 1.0) -> torch.Tensor:
    """sqrt(mean(L ** 2)) over the labelled samples (the "w/o HEM" ablation); (..., 3) inputs."""
    L, _ = error_norm_m(pos_m, truth_m, up_weight=up_weight)
    if L.numel() == 0:
        raise ValueError("rmse_loss: no labelled sample with a finite estimate in the batch")
    return root_mean_square(L)


def pseudorange_error_m(pr_m: torch.Tensor, sat_ecef_m: torch.Tensor, truth_m: torch.Tensor,
                        usable: torch.Tensor, system_index: torch.Tensor, n_systems: int) -> torch.Tensor:
    """(..., N) each usable pseudorange's error at the true position [m], its constellation's epoch median removed.

    The median stands for the receiver clock (and the ISB), which the truth does not give; 0 where not usable
    (``usable`` should be False where the truth is NaN). The torch twin of ``estimators.TruthNoise``'s error.
    """
    from .torch_ekf import geometric_range_m

    truth = torch.where(torch.isfinite(truth_m), truth_m, torch.zeros_like(truth_m))
    raw = torch.where(usable, pr_m - geometric_range_m(sat_ecef_m, truth[..., None, :]), torch.nan)
    out = torch.zeros_like(raw)
    for k in range(n_systems):
        in_sys = usable & (system_index == k)
        med = torch.nanquantile(torch.where(in_sys, raw, torch.nan), 0.5, dim=-1, keepdim=True)  # numpy's median
        out = torch.where(in_sys, raw - torch.nan_to_num(med), out)
    return out


def labelled_errors_m(batch, n_systems: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(usable, error) (B, T, N) of a WindowBatch: its masked-in slots of labelled epochs, and their
    ``pseudorange_error_m`` [m] (0 elsewhere)."""
    usable = batch.mask & torch.isfinite(batch.truth_ecef_m).all(dim=-1)[..., None]
    return usable, pseudorange_error_m(batch.pr_m, batch.sat_pos_ecef_m, batch.truth_ecef_m, usable,
                                       batch.system_index, n_systems)


def _centred(d: torch.Tensor, usable: torch.Tensor, system_index: torch.Tensor, n_systems: int) -> torch.Tensor:
    """``d`` on the usable slots less its constellation's epoch median (numpy's), 0 elsewhere."""
    centred = torch.zeros_like(d)
    for k in range(n_systems):
        in_sys = usable & (system_index == k)
        med = torch.nanquantile(torch.where(in_sys, d, torch.nan), 0.5, dim=-1, keepdim=True)
        centred = torch.where(in_sys, d - torch.nan_to_num(med), centred)
    return centred


def compensation_loss(vc_m: torch.Tensor, error_m: torch.Tensor, usable: torch.Tensor, system_index: torch.Tensor,
                      n_systems: int, *, delta_m: float = 5.0) -> torch.Tensor:
    """Mean Huber(delta) of v^c + e over the usable satellites [m^2], each constellation's epoch median removed.

    v^c = -e removes a pseudorange's error (the filter adds v^c to the innovation z - h(x)). A shift common to a
    constellation's satellites moves only the clock or ISB, so it costs nothing; the median, unlike a mean, does not
    let one large error move what the others are scored against. 0 when nothing is usable.
    """
    d = torch.where(usable, vc_m.to(error_m.dtype) + error_m, torch.zeros_like(error_m))
    if not usable.any():
        return d.sum() * 0.0
    centred = _centred(d, usable, system_index, n_systems)
    return torch.nn.functional.huber_loss(centred[usable], torch.zeros_like(centred[usable]), delta=delta_m)


#: ``variance_loss``'s "strongest" clock: the median of a constellation's this many highest-C/N0 signals, taken only
#: where it has at least ``STRONGEST_MIN_SATS`` usable satellites in the epoch (benchmarks/bad_pseudoranges.py).
STRONGEST_K, STRONGEST_MIN_SATS = 3, 5


def strongest_clock(d: torch.Tensor, cn0_dbhz: torch.Tensor, usable: torch.Tensor, system_index: torch.Tensor,
                    n_systems: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(clock, kept): each usable slot's median of ``d`` over its constellation's ``STRONGEST_K`` highest-C/N0 usable
    slots in the epoch (equal C/N0: the lower slot first; a C/N0 that is not finite counts as the weakest), and where
    that clock exists (``STRONGEST_MIN_SATS`` usable satellites or more); 0 / False elsewhere. The clock of
    benchmarks/bad_pseudoranges.py's "strongest 3" labelling too."""
    clock, kept = torch.zeros_like(d), torch.zeros_like(usable)
    cn0 = torch.nan_to_num(cn0_dbhz.to(d.dtype), nan=-1e9, posinf=-1e9, neginf=-1e9)
    for k in range(n_systems):
        in_sys = usable & (system_index == k)
        enough = in_sys.sum(dim=-1, keepdim=True) >= STRONGEST_MIN_SATS
        if not enough.any():
            continue
        score = torch.where(in_sys, cn0, torch.full_like(d, -torch.inf))
        top = torch.sort(score, dim=-1, descending=True, stable=True).indices[..., :STRONGEST_K]
        keep = in_sys & enough
        clock = torch.where(keep, torch.median(torch.gather(d, -1, top), dim=-1, keepdim=True).values, clock)
        kept = kept | keep
    return clock, kept


def strongest_centred(d: torch.Tensor, cn0_dbhz: torch.Tensor, usable: torch.Tensor, system_index: torch.Tensor,
                      n_systems: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(centred, kept): ``d`` less its ``strongest_clock`` where that exists; 0 / False elsewhere."""
    clock, kept = strongest_clock(d, cn0_dbhz, usable, system_index, n_systems)
    return torch.where(kept, d - clock, torch.zeros_like(d)), kept


def variance_loss(r_m2: torch.Tensor, vc_m: torch.Tensor, error_m: torch.Tensor, usable: torch.Tensor,
                  system_index: torch.Tensor, n_systems: int, cn0_dbhz: torch.Tensor | None = None) -> torch.Tensor:
    """Mean Gaussian negative log-likelihood 0.5 (ln R + c^2 / R) over the usable satellites [1].

    c = v^c + e less its constellation's epoch median [m]: the error a pseudorange keeps after its compensation, the
    clock and ISB aside (``compensation_loss``). Its minimum over R is R = c^2, the variance ``estimators.TruthNoise``
    gives without a floor; so the median satellite of a constellation with an odd count (and a lone one), whose c is
    0, is pulled to the network's ``r_floor_m2``. With ``cn0_dbhz`` [dB-Hz] the clock is instead the median of the
    constellation's three strongest signals (``strongest_centred``; epochs where it has under five satellites are left
    out): where half the signals are reflections, the plain median sits among them and makes clean signals look
    10-20 m early (docs/findings.md, session 50). No gradient flows through v^c (the shared layers still move). Scale
    free: errors and sds scaled alike (``loss.balance``) shift it by a constant. 0 when nothing is usable.
    """
    r = torch.where(usable, r_m2.to(error_m.dtype), torch.ones_like(error_m))
    d = torch.where(usable, vc_m.detach().to(error_m.dtype) + error_m, torch.zeros_like(error_m))
    if cn0_dbhz is None:
        centred, kept = _centred(d, usable, system_index, n_systems), usable
    else:
        centred, kept = strongest_centred(d, cn0_dbhz, usable, system_index, n_systems)
    if not kept.any():
        return r.sum() * 0.0
    c, r = centred[kept], r[kept]
    return 0.5 * torch.mean(torch.log(r) + c ** 2 / r)


def make_loss(kind: str, *, alpha: float = 0.75, gamma: float = 1.5, lam: float = 1.0, up_weight: float = 1.0):
    """The configured loss as ``fn(pos_m, truth_m) -> scalar``; ``kind`` is ``"hem"`` or ``"rmse"``."""
    if up_weight < 0 or not math.isfinite(up_weight):
        raise ValueError(f"loss up_weight must be a finite number >= 0, got {up_weight}")
    if kind == "hem":
        return lambda pos, truth: hem_loss(pos, truth, alpha=alpha, gamma=gamma, lam=lam, up_weight=up_weight)
    if kind == "rmse":
        return lambda pos, truth: rmse_loss(pos, truth, up_weight=up_weight)
    raise ValueError(f"unknown loss kind {kind!r}; expected 'hem' or 'rmse'")
