"""LF-GNSS noise network: per-satellite features -> pseudorange variance R and compensation v^c.

It maps normalised features ``(..., N, d)`` and a padding mask ``(..., N)`` to ``r_m2`` and ``vc_m`` of
shape ``(..., N)`` (LF-GNSS notes, step 3). With ``innovation=True`` it also reads the filter: one more
input column, each satellite's innovation against the filter's prior (``lfgnss.features.innovation_feature``),
so the network runs inside the filter, one epoch at a time (``learning.torch_ekf.batch_ekf``'s ``noise_step``):

    h0 = x W_e^T + b_e                               (embedding, d -> d_model)
    h1 = LayerNorm(h0 + MHA(h0, h0, h0; mask))       (self-attention over satellites, residual)
    h2 = MLP(h1)                                     (hidden 64-128-64, ReLU after each layer)
    [o_R, o_v] = h2 W_o^T + b_o
    r = r_scale_m2 * softplus(o_R) + r_floor_m2,     vc = o_v
    or, with a prior (``r_prior``):  r = r_prior(C/N0, el) * softplus(o_R) / ln 2 + r_floor_m2
where r_prior is the hand-set C/N0-elevation variance of ``estimators.noise.HeuristicNoise`` computed from
the network's own C/N0 and elevation inputs (un-normalised with stored constants): an untrained head
(o_R = 0) reproduces the plain EKF's noise, and training learns a per-satellite factor on it.

Padded slots are ignored as attention keys and their outputs are inert: ``r = PAD_R_M2``,
``vc = 0``. An epoch with no valid satellite yields inert outputs only (no NaN).
"""
from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

#: Variance written into padded slots [m^2] (finite and positive so no filter can divide by zero).
PAD_R_M2 = 1.0


class LfgnssNet(nn.Module):
    """Attention network over the satellites of one epoch.

    Parameters
    ----------
    n_features : int
        Feature dimension ``d``.
    d_model : int
        Embedding width (64 in the paper).
    n_heads : int
        Attention heads (4).
    hidden : tuple of int
        MLP widths after attention (64, 128, 64), each followed by ReLU.
    r_floor_m2 : float
        Floor added to the variance [m^2].
    r_scale_m2 : float
        Constant unit scale of the softplus output [m^2] (1.0 = the paper's ``softplus(o_R)``); not read with
        ``r_prior``.
    r_init_m2 : float or None
        If given, the R output bias is initialised so an all-zero input gives about this variance (without
        ``r_prior`` only: a ValueError with it, whose untrained network gives about the prior).
    compensation : bool
        Output the innovation compensation ``v^c`` (False: ``v^c = 0``, the network learns R only).
    innovation : bool
        Take the filter's prior innovation as input column ``d + 1`` (``forward``'s ``innovation``).
    r_prior : dict or None
        Prior variance model: ``cn0_index``, ``el_index`` (feature columns), ``cn0_mean``, ``cn0_std``,
        ``el_mean``, ``el_std`` (normaliser constants) and ``floor_m``, ``cn0_scale_m2``,
        ``elevation_power``, ``el_min_rad`` (HeuristicNoise parameters).
    """

    def __init__(self, n_features: int, *, d_model: int = 64, n_heads: int = 4,
                 hidden: tuple[int, ...] = (64, 128, 64), r_floor_m2: float = 0.01,
                 r_scale_m2: float = 1.0, r_init_m2: float | None = None, r_prior: dict | None = None,
                 compensation: bool = True, innovation: bool = False) -> None:
        super().__init__()
        if n_features < 1 or d_model % n_heads != 0:
            raise ValueError(f"need n_features >= 1 and d_model % n_heads == 0, got {n_features}, {d_model}, {n_heads}")
        if r_init_m2 is not None and r_prior is not None:
            raise ValueError("r_init_m2 has no meaning with r_prior: an untrained network gives about the prior")
        self.n_features = int(n_features)
        self.d_model = int(d_model)
        self.n_heads = int(n_heads)
        self.hidden = tuple(int(h) for h in hidden)
        self.r_floor_m2 = float(r_floor_m2)
        self.r_scale_m2 = float(r_scale_m2)
        self.compensation = bool(compensation)
        self.innovation = bool(innovation)
        self.r_prior = None if r_prior is None else {k: (int(v) if k.endswith("_index") else float(v))
                                                     for k, v in r_prior.items()}
        self.embed = nn.Linear(self.n_features + self.innovation, self.d_model)
        self.attention = nn.MultiheadAttention(self.d_model, self.n_heads, batch_first=True)
        self.norm = nn.LayerNorm(self.d_model)
        layers: list[nn.Module] = []
        width = self.d_model
        for h in self.hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        self.mlp = nn.Sequential(*layers)
        self.head = nn.Linear(width, 2)
        if r_init_m2 is not None:
            # softplus^-1((r_init - floor) / scale) = log(expm1(y))
            y = torch.tensor(max(float(r_init_m2) - self.r_floor_m2, 1e-3) / self.r_scale_m2, dtype=torch.float64)
            with torch.no_grad():
                self.head.bias[0] = float(y + torch.log(-torch.expm1(-y)))

    def hyperparameters(self) -> dict:
        """Constructor keyword arguments (for export / rebuild)."""
        return {"n_features": self.n_features, "d_model": self.d_model, "n_heads": self.n_heads,
                "hidden": list(self.hidden), "r_floor_m2": self.r_floor_m2, "r_scale_m2": self.r_scale_m2,
                "r_prior": self.r_prior, "compensation": self.compensation,
                "innovation": self.innovation}

    def forward(self, features: torch.Tensor, mask: torch.Tensor, innovation: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Noise for every slot.

        Parameters
        ----------
        features : (B, N, d) or (B, T, N, d) float tensor, normalised
        mask : (B, N) or (B, T, N) bool, True for valid satellites
        innovation : like ``mask``, float; required if and only if the network was built with ``innovation``

        Returns
        -------
        r_m2, vc_m : (B, N) or (B, T, N), dtype of ``features``; inert in padded slots.
        """
        if features.shape[:-1] != mask.shape or features.shape[-1] != self.n_features:
            raise ValueError(f"features {tuple(features.shape)} and mask {tuple(mask.shape)} do not match "
                             f"(..., N, {self.n_features}) / (..., N)")
        if (innovation is not None) != self.innovation or (innovation is not None and innovation.shape != mask.shape):
            raise ValueError(f"this network {'needs an' if self.innovation else 'takes no'} innovation input "
                             f"(shaped like the mask {tuple(mask.shape)})")
        lead = mask.shape[:-1]
        n = mask.shape[-1]
        if innovation is not None:
            features = torch.cat([features, innovation[..., None].to(features.dtype)], -1)
        x = features.reshape(-1, n, self.n_features + self.innovation)
        m = mask.reshape(-1, n).bool()
        # An epoch with no valid satellite would make every attention row -inf -> NaN; let such rows
        # attend to all (finite) slots; their outputs are overwritten below.
        empty = ~m.any(dim=-1, keepdim=True)
        key_padding = ~(m | empty)
        x = torch.where(m[..., None], x, torch.zeros((), dtype=x.dtype, device=x.device))
        prior = None if self.r_prior is None else prior_variance(x, self.r_prior)
        h0 = self.embed(x)
        attn, _ = self.attention(h0, h0, h0, key_padding_mask=key_padding, need_weights=False)
        h1 = self.norm(h0 + attn)
        out = self.head(self.mlp(h1))
        if prior is None:
            r = self.r_scale_m2 * F.softplus(out[..., 0]) + self.r_floor_m2
        else:
            r = prior * F.softplus(out[..., 0]) / math.log(2.0) + self.r_floor_m2
        vc = out[..., 1] if self.compensation else torch.zeros_like(r)
        r = torch.where(m, r, torch.full((), PAD_R_M2, dtype=r.dtype, device=r.device))
        vc = torch.where(m, vc, torch.zeros((), dtype=vc.dtype, device=vc.device))
        return r.reshape(*lead, n), vc.reshape(*lead, n)


#: How an ensemble's members can be combined (``combine_members``); the first is the default.
COMBINE_RULES = ("geometric", "mixture")


def check_combine(rule: str) -> str:
    """``rule`` if it is one of ``COMBINE_RULES``; a ValueError naming them otherwise."""
    if rule not in COMBINE_RULES:
        raise ValueError(f"ensemble combination {rule!r}: expected one of {', '.join(COMBINE_RULES)}")
    return rule


def combine_members(r_m2: list[torch.Tensor], vc_m: list[torch.Tensor], rule: str = "geometric"
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """One noise (r_m2 [m^2], vc_m [m]) from an ensemble's members; v^c is always the mean of theirs.

    ``"geometric"``: R is the geometric mean of theirs. R spans orders of magnitude: a member that distrusts a
    satellite 100-fold and one that trusts it meet at 10-fold, not at 50-fold.
    ``"mixture"``: the moment-matched equal-weight mixture of the members' N(v^c_m, R_m),
    ``R = mean_m R_m + mean_m (v^c_m - mean v^c)^2``: where the members' corrections disagree, R grows by their spread.
    Model files combine geometrically (``learning.export``, numpy, no torch at inference); the mixture is for
    ``learning.crossval --reuse ... --combine mixture`` (cross-validated worse on berlin-pp,
    docs/training/cv-berlin-mixture-ensemble.md).
    """
    check_combine(rule)
    r, vc = torch.stack(r_m2), torch.stack(vc_m)
    mean_vc = vc.mean(0)
    if rule == "geometric":
        return torch.exp(torch.log(r).mean(0)), mean_vc
    return r.mean(0) + ((vc - mean_vc) ** 2).mean(0), mean_vc


class NetworkEnsemble(nn.Module):
    """Networks of one recipe trained with different seeds, run as one noise model (``combine_members``).

    Every member reads the same (identically normalised) features; the training runs differ in their seed only,
    which moves a recipe trained on a few minutes of driving by metres (docs/training/cv-ensemble.md).
    """

    def __init__(self, members: list[LfgnssNet], combine: str = COMBINE_RULES[0]) -> None:
        super().__init__()
        if not members:
            raise ValueError("an ensemble needs at least one network")
        check_combine(combine)
        if len({m.innovation for m in members}) > 1:
            raise ValueError("an ensemble's networks must all read the filter's innovations, or none")
        self.members = nn.ModuleList(members)
        self.innovation = members[0].innovation
        self.combine = combine

    def forward(self, features: torch.Tensor, mask: torch.Tensor, innovation: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """``LfgnssNet.forward`` of each member, combined: (r_m2, vc_m), shaped like ``mask``."""
        outs = [m(features, mask, innovation) for m in self.members]
        return combine_members([o[0] for o in outs], [o[1] for o in outs], self.combine)


def prior_variance(x_norm: torch.Tensor, prior: dict) -> torch.Tensor:
    """Hand-set variance [m^2] from normalised features (..., N, d): HeuristicNoise's formula in torch."""
    cn0 = x_norm[..., prior["cn0_index"]] * prior["cn0_std"] + prior["cn0_mean"]
    el = x_norm[..., prior["el_index"]] * prior["el_std"] + prior["el_mean"]
    sin_el = torch.sin(torch.clamp(el, min=prior["el_min_rad"]))
    return (prior["floor_m"] ** 2 + prior["cn0_scale_m2"] * 10.0 ** (-cn0 / 5.0)) / sin_el ** prior["elevation_power"]


def heuristic_prior(feature_names, mean, std, noise=None) -> dict:
    """The ``r_prior`` dict for a feature layout and its normaliser (needs 'cn0' and 'elevation')."""
    from estimators.noise import HeuristicNoise

    noise = noise or HeuristicNoise()
    names = list(feature_names)
    if "cn0" not in names or "elevation" not in names:
        raise ValueError("a heuristic R prior needs the 'cn0' and 'elevation' features")
    i, j = names.index("cn0"), names.index("elevation")
    return {"cn0_index": i, "el_index": j, "cn0_mean": float(mean[i]), "cn0_std": float(std[i]),
            "el_mean": float(mean[j]), "el_std": float(std[j]), "floor_m": noise.floor_m,
            "cn0_scale_m2": noise.cn0_scale_m2, "elevation_power": noise.elevation_power,
            "el_min_rad": float(noise.el_min_rad)}
