"""Per-epoch least-squares baselines as plug-ins: equal-weight (``wls``) and noise-weighted (``wls-weighted``)."""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from lfgnss.features import fill_from_nearest_epoch
from lfgnss.dop import dop
from lfgnss.frames import ecef_to_lla
from lfgnss.metrics import enu_rotations
from lfgnss.sequence import Sequence
from lfgnss.spp import SppConfig
from lfgnss.weighted_fix import weighted_least_squares

from .base import STATUS_NONE, STATUS_UPDATED, Solution, check_sequence, keep_slots, register, usable_sequence
from .noise import HeuristicNoise, NoiseModel, checked_noise, noise_output, resolve_noise, switched_on_warned


@dataclass
class LeastSquaresBaseline:
    """Least squares of each epoch on its own: ``create("wls")`` (equal weight) and ``create("wls-weighted")``.

    Per epoch, over position and one receiver clock per constellation (the inter-system biases):

        x = (H^T W H)^-1 H^T W rho,   W = I (wls) or diag(1 / R) (wls-weighted),  by

    Gauss-Newton from the coarse fix (the nearest epoch's where an epoch has none). Covariance [m^2]: wls scales
    ``(H^T H)^-1`` by the a-posteriori unit variance of the residuals; wls-weighted gives ``(H^T R^-1 H)^-1``
    unscaled. A noise model's R only weighs the satellites (R above ``estimators.noise.R_OFF_M2`` drops one); its
    innovation compensation v^c is not used here (that is the filters'), so a learned model does less in this
    baseline than in the EKF. An epoch with too few satellites for its unknowns, or whose fix the coarse fix would
    reject (:func:`plausible_fix`: underground or in orbit, GDOP beyond 50), has no position.
    """

    name: str
    noise: NoiseModel | None

    def solve(self, sequence: Sequence) -> Solution:
        """Least-squares fix of each epoch on its own (no filtering); positions [m], covariances [m^2]."""
        # NaN-free slots (the same object on valid input)
        sequence = usable_sequence(check_sequence(sequence, self.name), self.name, dopplers=False)
        if self.noise is None:
            r = np.ones(sequence.mask.shape)
        else:
            r, _ = checked_noise(self.name, sequence.name, sequence.mask,
                                 *noise_output(self.name, self.noise(sequence), self.noise), self.noise)
            # R > R_OFF_M2: satellite off
            sequence = keep_slots(sequence, switched_on_warned(self.name, sequence, sequence.mask, r))
        fix = weighted_least_squares(sequence.pr_m, sequence.sat_pos_ecef_m, sequence.system_index, sequence.mask,
                                     len(sequence.systems), fill_from_nearest_epoch(sequence.coarse_ecef_m), r,
                                     scale_by_residuals=self.noise is None)
        pos, cov, ok = fix.pos_ecef_m, fix.cov_ecef_m2, fix.ok
        ok &= plausible_fix(pos, sequence)
        # the reference system's clock; NaN in an epoch without its satellites (WeightedFix holds 0 there)
        seen = np.any(sequence.mask & (sequence.system_index == 0), axis=1)
        clock = np.where(seen, fix.clock_m[:, 0], np.nan)
        return Solution(self.name, sequence.time_gps_s.copy(), np.where(ok[:, None], pos, np.nan),
                        np.where(ok[:, None, None], cov, np.nan), np.where(ok, clock, np.nan),
                        np.where(ok, sequence.mask.sum(1), 0), np.where(ok, STATUS_UPDATED, STATUS_NONE))


def plausible_fix(pos_ecef_m: np.ndarray, sequence: Sequence, config: SppConfig = SppConfig()) -> np.ndarray:
    """(T,) bool: fixes [m] the coarse fix would keep: ellipsoidal height within ``config.height_range_m`` and GDOP of
    the used satellites in (0, ``config.max_gdop``]. An epoch without redundancy can land kilometres off (underground,
    in orbit); ``lfgnss.spp`` marks such fixes "implausible height" and "bad geometry", and so do the baselines."""
    pos = np.where(np.isfinite(pos_ecef_m), pos_ecef_m, 0.0)
    height = ecef_to_lla(pos)[:, 2]
    low, high = config.height_range_m
    gdop = fix_gdop(pos, sequence)
    return (height >= low) & (height <= high) & (gdop > 0) & (gdop <= config.max_gdop)


def fix_gdop(pos_ecef_m: np.ndarray, sequence: Sequence) -> np.ndarray:
    """(T,) GDOP (``lfgnss.dop``, as ``lfgnss.spp`` checks it) of the used satellites seen from positions (T, 3) [m].

    Elevations and azimuths come from the positions' own lines of sight, not the sequence's stored ones.
    """
    pos = np.where(np.isfinite(pos_ecef_m), pos_ecef_m, 0.0)
    los = np.nan_to_num(sequence.sat_pos_ecef_m) - pos[:, None, :]
    enu = np.einsum("tij,tnj->tni", enu_rotations(pos), los)
    el = np.arctan2(enu[..., 2], np.hypot(enu[..., 0], enu[..., 1]))
    az = np.arctan2(enu[..., 0], enu[..., 1])
    mask = sequence.mask
    return dop(el, az, np.where(mask, sequence.system_index, 0), mask, len(sequence.systems)).gdop


@register("wls")
def equal_weight_least_squares() -> LeastSquaresBaseline:
    """Equal-weight least squares per epoch (the coarse fix of LF-GNSS step 1); it takes no options."""
    return LeastSquaresBaseline("wls", None)


@register("wls-weighted")
def weighted_baseline(noise: NoiseModel | str | os.PathLike | None = None) -> LeastSquaresBaseline:
    """Least squares per epoch weighted by ``noise``'s R (a model, or a model file), default ``HeuristicNoise``."""
    noise = resolve_noise(noise, "wls-weighted")
    return LeastSquaresBaseline("wls-weighted", HeuristicNoise() if noise is None else noise)
