"""Training losses on filtered positions: dynamic hard-example mining (HEM) and plain RMSE.

Samples are the labelled epochs of every window in the batch. Per sample (paper eqs. for L_dhem):

    L = ||e||_2                          e = x_pred - x_true (ENU; the norm is the same in ECEF)
    w = (1 - sqrt(L / max L)) ** (gamma * exp(-lambda * L))     max over the batch, detached
    l = alpha * w * L
    loss = sqrt(mean(l ** 2))

``rmse_loss`` (the "w/o HEM" ablation) is ``sqrt(mean(L ** 2))``. Epochs whose truth is NaN (no
label) or whose estimate is not finite are left out of both.
"""
from __future__ import annotations

import torch

_TINY = 1e-12


def error_norm_m(pos_m: torch.Tensor, truth_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Position error norms of the labelled samples.

    Parameters
    ----------
    pos_m, truth_m : (..., 3) estimated and true positions [m] (ECEF or ENU; truth NaN = unlabelled)

    Returns
    -------
    L : (K,) error norms [m] of the K valid samples (gradient-safe at zero error)
    valid : (...) bool, which samples were used
    """
    if pos_m.shape != truth_m.shape or pos_m.shape[-1] != 3:
        raise ValueError(f"positions {tuple(pos_m.shape)} and truth {tuple(truth_m.shape)} must both be (..., 3)")
    valid = torch.isfinite(truth_m).all(dim=-1) & torch.isfinite(pos_m).all(dim=-1)
    e = pos_m[valid] - truth_m[valid]
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


def hem_loss(pos_m: torch.Tensor, truth_m: torch.Tensor, *, alpha: float = 0.75, gamma: float = 1.5,
             lam: float = 1.0) -> torch.Tensor:
    """Dynamic hard-example-mining loss over all labelled samples.

    Parameters
    ----------
    pos_m, truth_m : (..., 3) estimated and true positions [m]; truth NaN where unlabelled.
    alpha, gamma, lam : loss scale, initial difficulty exponent, exponent decay rate [1/m].

    Returns
    -------
    scalar tensor; raises ValueError when no sample is labelled.
    """
    L, _ = error_norm_m(pos_m, truth_m)
    if L.numel() == 0:
        raise ValueError("hem_loss: no labelled sample with a finite estimate in the batch")
    sample = alpha * hem_weights(L, gamma=gamma, lam=lam) * L
    return torch.sqrt(torch.mean(sample ** 2))


def rmse_loss(pos_m: torch.Tensor, truth_m: torch.Tensor) -> torch.Tensor:
    """sqrt(mean(L ** 2)) over the labelled samples (the "w/o HEM" ablation); (..., 3) inputs."""
    L, _ = error_norm_m(pos_m, truth_m)
    if L.numel() == 0:
        raise ValueError("rmse_loss: no labelled sample with a finite estimate in the batch")
    return torch.sqrt(torch.mean(L ** 2))


def make_loss(kind: str, *, alpha: float = 0.75, gamma: float = 1.5, lam: float = 1.0):
    """The configured loss as ``fn(pos_m, truth_m) -> scalar``; ``kind`` is ``"hem"`` or ``"rmse"``."""
    if kind == "hem":
        return lambda pos, truth: hem_loss(pos, truth, alpha=alpha, gamma=gamma, lam=lam)
    if kind == "rmse":
        return rmse_loss
    raise ValueError(f"unknown loss kind {kind!r}; expected 'hem' or 'rmse'")
