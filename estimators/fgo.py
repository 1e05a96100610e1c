"""Factor-graph back end (LF-GNSS step 5): gtsam batch smoothing or fixed-lag (causal) estimation.

Graph, after gtsam's ``SinglePointPositioningExample``:

* ``X(k)`` receiver position (Point3, ECEF [m]) and ``V(k)`` velocity (Point3, ECEF [m/s]) for
  every epoch from the first coarse fix on, also epochs without usable satellites (batch; see Modes for
  fixed-lag).
* ``B(k * C + j)`` receiver clock of constellation ``systems[j]`` at epoch ``k`` [s], created only
  where that constellation has a usable satellite at that epoch. Clocks are free per epoch and
  constellation: no clock-drift factor. This makes inter-system biases implicit, keeps the clock
  out of the motion model, and avoids clock-drift factors in seconds, whose weights of 1e16-1e18
  made Levenberg-Marquardt misbehave (LF-GNSS-notes.md). The price is one satellite per epoch and
  constellation spent on its clock; velocity still comes from the motion model over positions.
* Per usable satellite ``i`` the built-in ``gtsam.PseudorangeFactor(X(k), B(k*C+j), pr_i + vc_i,
  sat_pos_i, 0.0, model)`` with ``model = Diagonal.Sigmas([sqrt(r_i)])``, wrapped by a Huber or
  Cauchy M-estimator when ``robust`` is set. The factor's error is
  ``|s - x| + omega_e/c (x_s y_r - y_s x_r) + c * clock - (pr + vc)``, i.e. the range model of
  ``lfgnss.corrections.geometric_range_m`` (Sagnac applied inside, not in ``pr_m``).
* Constant-velocity motion between epochs, white-noise acceleration with spectral density
  ``q`` per local east/north/up axis (rotated to ECEF):
  ``[x1; v1] = F [x0; v0] + w``, ``F = [[I, dt I], [0, I]]``,
  ``Q = [[dt^3/3 Qa, dt^2/2 Qa], [dt^2/2 Qa, dt Qa]]``.
  gtsam has no built-in factor on Point3+Vector3 for this and the model is linear, so it is a
  ``GaussianConditional`` (whitened, 4 keys) inside a ``LinearContainerFactor`` linearised at zero,
  which is exact for a linear model and runs in C++ (no Python ``CustomFactor`` callbacks).
* Doppler: per epoch with at least 5 Dopplers, the robust least-squares velocity fix of
  ``lfgnss.velocity.doppler_velocity`` (at the coarse fix, covariance from ``doppler_sigma_m_s`` and, with
  ``doppler_cn0_ref_dbhz``, each Doppler's C/N0) as a
  Huber-robust ``PriorFactorPoint3`` on ``V(k)``: built in, and it needs no drift variable, which the
  free per-epoch clocks do not have. Velocities tie consecutive positions through the motion factors,
  so a multipath jump of one epoch's pseudoranges can no longer move that epoch alone.
* Zero velocity (``zupt_sigma_m_s``): at an epoch whose Doppler velocity fix says the receiver stands still
  (``estimators.models.still_fixes``: slower than ``zupt_max_speed_m_s`` and consistent with zero at 99 %), a
  Gaussian ``PriorFactorPoint3(V(k), 0, zupt_sigma I_3)``: the EKF's zero-velocity update as a factor.
* Weak priors on ``X``, ``V`` at the first epoch (coarse fix, ``prior_pos_sigma_m``,
  ``prior_vel_sigma_m_s``), and the same position prior, at the epoch's initial guess, on a later epoch with
  fewer than 3 satellites left once each constellation's clock took one (see ``_epoch``).

Modes: ``"batch"`` optimises the whole trajectory with Levenberg-Marquardt (smoothed estimate);
``"fixed-lag"`` runs ``gtsam.IncrementalFixedLagSmoother`` (iSAM2) epoch by epoch and outputs the
filtered (causal) estimate of each epoch right after its update. There, epochs whose pseudoranges say
nothing on position (no usable satellite, or one per constellation: ``position_blind_epochs``) stay out
of the graph and are coasted (CV prediction, clock from the residual); the next epoch is linked to the
last one in the graph by one CV factor over the whole interval, the exact marginal of the skipped chain,
so an outage is a time gap to the smoother. A long chain of short CV factors with nothing else on it made
gtsam's Cholesky give up (IndeterminantLinearSystem after ~100-200 epochs, ~30 s at 5 Hz). After a time step longer
than ``MAX_GAP_S`` the epochs get no position (STATUS_NONE) until one with a coarse fix, where a new graph starts,
as the EKF restarts (the batch graph needs no restart: it sees the fix after the gap). iSAM2 factorises by Cholesky;
where that finds weak epochs in a row indeterminate (e.g. two satellites of one constellation at the start) with inputs
in order, the run is solved again with QR factorisation (numerically stabler, ~1.5 times slower), with a warning.

Covariances: with ``covariances=True`` the position covariance is the gtsam marginal
(``Marginals`` in batch, ``marginalCovariance`` in fixed-lag, where coasted epochs propagate the joint
marginal of ``X``, ``V`` at the last epoch in the graph), times the EKF's inflation by the
pseudorange residuals (``estimators.consistency``; ``inflate_cov=False``: the bare marginal). Otherwise ``cov_ecef_m2``
holds a stand-in, mostly wider than the marginals: the weighted least-squares snapshot covariance of the epoch
(``(H^T R^-1 H)^-1`` at the estimate, position block, ignoring the motion model), and at epochs
whose snapshot is rank deficient the last full-rank one propagated by the motion model over the time T since it
(``P + T^3/3 Qa``), so it grows through an outage.
"""
from __future__ import annotations

import functools
import inspect
import numbers
import os
import re
import time
import warnings

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, V, X

from lfgnss.constants import SPEED_OF_LIGHT_M_S
from lfgnss.corrections import geometric_range_m, line_of_sight
from lfgnss.dop import satellites_per_system
from lfgnss.frames import ecef_to_lla, enu_rotation
from lfgnss.sequence import Sequence
from lfgnss.velocity import DopplerVelocity, doppler_velocity

from .base import (STATUS_COASTED, STATUS_NONE, STATUS_UPDATED, Solution, caller_stacklevel, check_flag, check_sequence,
                   epoch_range, keep_slots, options_of, register, usable_sequence)
from .consistency import covariance_inflation, residual_variance_factor
from .ekf import config_of
from .models import EkfConfig, still_fixes, used_doppler_variance_m2_s2
from .noise import (HeuristicNoise, NoiseModel, checked_noise, default_noise, describe_noise, noise_output,
                    resolve_noise, switched_on_warned, warn_no_filter_settings)

MODES = ("batch", "fixed-lag")
ROBUST_KERNELS = ("huber", "cauchy")
#: Robust kernel and threshold used by ``robust="auto"`` in each mode.
DEFAULT_KERNEL = {"batch": ("cauchy", 1.0), "fixed-lag": ("huber", 1.5)}
#: Huber threshold [sigmas] of the convex solve that starts a batch Cauchy solve.
CAUCHY_WARM_START_HUBER_K = 1.5
#: Huber threshold [sigmas] of the Doppler velocity priors.
DOPPLER_HUBER_K = 1.5
#: The standstill test's default speed bound [m/s], the EKF's.
DEFAULT_ZUPT_MAX_SPEED_M_S = EkfConfig().zupt_max_speed_m_s
#: Fixed-lag mode: a time step longer than this [s] whose epoch has no coarse fix leaves the epochs without a
#: position until the next coarse fix, where the graph restarts (the EKF's ``max_gap_s``; predicted across a day's
#: gap the graph's estimate stayed 4 km off, 1800 km after twelve days, without a word).
MAX_GAP_S = EkfConfig().max_gap_s
#: Default fixed-lag window [s] (``lag_s``).
DEFAULT_LAG_S = 10.0
#: iSAM2's relinearisation threshold [m] of the positions and velocities (m/s), and of the clocks as a range.
RELINEARIZE_M = 0.01
#: Bounds beyond which ``likely_cause`` blames an input for an ill-conditioned graph: a pseudorange sigma under 1 cm
#: or over 1 km [m^2], an acceleration density under 1e-6 m^2/s^3 (on the bundled drive R = 1e-12 or >= 1e8 m^2 and
#: a density of 1e-9 made the fixed-lag solve fail; 1e-8 to 1e6 m^2 and 1e-7 did not).
R_TINY_M2, R_HUGE_M2, PSD_TINY_M2_S3 = 1e-4, 1e6, 1e-6

_GTSAM_SYMBOL = re.compile(r"\(Symbol: ([a-zA-Z])(\d+)\)")


#: Sigma [m] of the batch graph's conditioning-only position prior at an epoch with fewer than 3 ranges left after
#: its clocks. It must weigh nothing beside the motion factors even summed over a long weak stretch, where it sits on
#: the coarse track interpolated (or held) across it: at prior_pos_sigma_m (100 m) 150 of them at 5 Hz pulled the graph
#: to that track, 175 m off where one satellite per constellation was left against 73 m with none. The fixed-lag
#: graph keeps prior_pos_sigma_m: its iSAM2 Cholesky found 1e4 m indeterminate, and its priors sit on the prediction.
LOOSE_PRIOR_SIGMA_M = 1.0e4


def symbol_epoch(message: str, n_systems: int) -> tuple[str, int] | None:
    """(symbol, epoch) of the variable a gtsam error names, ``(Symbol: x24)``: ("x24", 24) (``key_epoch``). None
    when the message names none."""
    found = _GTSAM_SYMBOL.search(message)
    if found is None:
        return None
    return found.group(1) + found.group(2), key_epoch(found.group(1), int(found.group(2)), n_systems)


def psd_text(accel_psd_enu_m2_s3: np.ndarray) -> str:
    """The acceleration density in a message: ``accel_psd_enu_m2_s3 is (1, 1, 0.1) m^2/s^3``."""
    return f"accel_psd_enu_m2_s3 is ({', '.join(f'{v:g}' for v in accel_psd_enu_m2_s3)}) m^2/s^3"


def likely_cause(r_m2: np.ndarray, accel_psd_enu_m2_s3: np.ndarray) -> str | None:
    """The input most likely behind an ill-conditioned graph, in words: R [m^2] (an epoch's, (n,)) near 0 or huge,
    or an acceleration density [m^2/s^3] near 0; None when neither is out of the ordinary."""
    r = np.asarray(r_m2, float)
    if r.size and r.min() < R_TINY_M2:
        return f"its smallest R is {r.min():.3g} m^2: R must be a pseudorange variance in m^2, not near 0"
    if r.size and r.max() > R_HUGE_M2:
        return (f"its largest R is {r.max():.3g} m^2: R must be a pseudorange variance in m^2 (a sigma of kilometres "
                f"says nothing; an R above estimators.noise.R_OFF_M2, 1e12 m^2, leaves a satellite out)")
    if min(accel_psd_enu_m2_s3) < PSD_TINY_M2_S3:
        return (f"{psd_text(accel_psd_enu_m2_s3)}: near 0 the motion factors outweigh every pseudorange; "
                f"a car's is about 0.1 to 10")
    return None


def checked_accel_psd(value: object) -> np.ndarray:
    """``accel_psd_enu_m2_s3`` as a (3,) float array [m^2/s^3]; ValueError naming LfgnssFgo unless it is 3 finite
    positive numbers (east, north, up)."""
    items = value.tolist() if isinstance(value, np.ndarray) else value
    if (not isinstance(items, (tuple, list)) or len(items) != 3
            or any(isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real) or not 0 < v < np.inf
                   for v in items)):
        raise ValueError(f"LfgnssFgo: accel_psd_enu_m2_s3 must be 3 finite positive numbers [m^2/s^3] (east, north, "
                         f"up), got {value!r}")
    return np.array(items, float)


def clock_key(k: int, j: int, n_systems: int) -> int:
    """gtsam key of the receiver clock [s] of constellation ``j`` at epoch ``k``."""
    return B(k * n_systems + j)


def key_epoch(letter: str, index: int, n_systems: int) -> int:
    """The epoch of a variable from its symbol's letter and index: ``index`` itself, a clock's (``clock_key``)
    ``index // n_systems``."""
    return index // n_systems if letter == "b" else index


def cv_process_covariance(dt_s: float, accel_psd_ecef: np.ndarray) -> np.ndarray:
    """Process noise Q (6, 6) of the constant-velocity model over ``dt_s`` [s].

    Q = [[dt^3/3 Qa, dt^2/2 Qa], [dt^2/2 Qa, dt Qa]], ``accel_psd_ecef`` = Qa (3, 3) [m^2/s^3].
    """
    qa = np.asarray(accel_psd_ecef, float)
    return np.block([[dt_s ** 3 / 3.0 * qa, dt_s ** 2 / 2.0 * qa],
                     [dt_s ** 2 / 2.0 * qa, dt_s * qa]])


def cv_motion_factor(k0: int, k1: int, dt_s: float, accel_psd_ecef: np.ndarray) -> gtsam.LinearContainerFactor:
    """Constant-velocity factor between ``X(k0), V(k0)`` and ``X(k1), V(k1)``.

    Whitened error ``W ([x1; v1] - F [x0; v0])`` with ``W`` upper triangular, ``W^T W = Q^-1``,
    ``F = [[I, dt I], [0, I]]``. Exact (the model is linear): a GaussianConditional on the four
    keys, linearised at zero, in a LinearContainerFactor.
    """
    return _cv_factor_from_blocks(k0, k1, _cv_whitened_blocks(dt_s, accel_psd_ecef))


def _cv_whitened_blocks(dt_s: float, accel_psd_ecef: np.ndarray) -> tuple[np.ndarray, ...]:
    """Blocks (W_x1, W_v1, S_x0, S_v0), each (6, 3), of the whitened CV residual (see cv_motion_factor)."""
    q = cv_process_covariance(dt_s, accel_psd_ecef)
    w = np.linalg.cholesky(np.linalg.inv(q)).T          # upper triangular, W^T W = Q^-1
    f = np.eye(6)
    f[:3, 3:] = dt_s * np.eye(3)
    s = -w @ f
    return w[:, :3].copy(), w[:, 3:].copy(), s[:, :3].copy(), s[:, 3:].copy()


_UNIT6 = gtsam.noiseModel.Unit.Create(6)


def _cv_factor_from_blocks(k0: int, k1: int, blocks: tuple[np.ndarray, ...]) -> gtsam.LinearContainerFactor:
    wx1, wv1, sx0, sv0 = blocks
    terms = [(X(k1), wx1), (V(k1), wv1), (X(k0), sx0), (V(k0), sv0)]
    conditional = gtsam.GaussianConditional(terms, 2, np.zeros(6), _UNIT6)
    zero = gtsam.Values()
    for key in (X(k0), V(k0), X(k1), V(k1)):
        zero.insertPoint3(key, np.zeros(3))
    return gtsam.LinearContainerFactor(gtsam.JacobianFactor(conditional), zero)


class _MotionModel:
    """CV factors with the whitening blocks cached per time step (dt rounded to 1 us)."""

    def __init__(self, accel_psd_ecef: np.ndarray) -> None:
        self.accel_psd_ecef = accel_psd_ecef
        self._cache: dict[float, tuple[np.ndarray, ...]] = {}

    def factor(self, k0: int, k1: int, dt_s: float) -> gtsam.LinearContainerFactor:
        key = round(dt_s, 6)
        blocks = self._cache.get(key)
        if blocks is None:
            blocks = self._cache[key] = _cv_whitened_blocks(dt_s, self.accel_psd_ecef)
        return _cv_factor_from_blocks(k0, k1, blocks)


def _interpolate_rows(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fill NaN rows of ``y`` (T, 3) by linear interpolation in ``t`` (constant outside)."""
    ok = np.all(np.isfinite(y), axis=1)
    out = np.empty_like(y)
    for a in range(y.shape[1]):
        out[:, a] = np.interp(t, t[ok], y[ok, a])
    return out


def _median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a small 1-D array, to the bit (the middle value, or the mean of the two middle
    ones as np.median takes it: their sum halved), without np.median's overhead (25 us a call, 7000 calls a solve)."""
    v = np.sort(values).tolist()
    n = len(v)
    return v[n // 2] if n % 2 else (v[n // 2 - 1] + v[n // 2]) / 2.0


@functools.cache
def _m_estimator(robust: str, k: float) -> gtsam.noiseModel.mEstimator.Base:
    """The Huber or Cauchy kernel with threshold ``k``, made once and shared by every factor that uses it."""
    return {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[robust].Create(k)


def position_ranges(seq: Sequence) -> np.ndarray:
    """(T,) int: usable pseudoranges left for position once each constellation's clock took one.

    With a free clock per epoch and constellation, each constellation's first satellite is spent on its clock.
    """
    present = satellites_per_system(seq.system_index, seq.mask, len(seq.systems)) > 0
    return seq.mask.sum(axis=1) - present.sum(axis=1)


def position_blind_epochs(seq: Sequence) -> np.ndarray:
    """(T,) bool: epochs whose usable pseudoranges say nothing on position (none, or one per constellation)."""
    return position_ranges(seq) <= 0


def _coasted_position_covariance(joint: gtsam.JointMarginal, x_key: int, v_key: int, dt_s: float,
                                 accel_psd_ecef: np.ndarray) -> np.ndarray:
    """Position block [m^2] of F P F^T + Q after ``dt_s`` [s] of CV prediction from the joint marginal P of x, v."""
    pxx, pxv, pvv = joint.at(x_key, x_key), joint.at(x_key, v_key), joint.at(v_key, v_key)
    out = pxx + dt_s * (pxv + pxv.T) + dt_s ** 2 * pvv + cv_process_covariance(dt_s, accel_psd_ecef)[:3, :3]
    return 0.5 * (out + out.T)


class LfgnssFgo:
    """gtsam factor-graph estimator with learned (or heuristic) per-satellite noise.

    Parameters
    ----------
    noise : NoiseModel, str or Path
        ``noise(sequence) -> (r_m2, vc_m)``, (T, N) each; sigma_i = sqrt(r_i), measurement pr + vc; or the path
        of a model file (read with ``learning.export.load_model``). None: ``HeuristicNoise``; ``create("fgo")``
        gives the bundled model. An R above ``estimators.noise.R_OFF_M2`` (1e12 m^2; 1e30 or inf, say) switches the
        satellite off: its pseudorange and Doppler are left out as if masked (``switched_on``). R is used as given:
        the graph does not apply a model filter's ``EkfConfig.glonass_sigma_factor`` (the static model's 1.5
        reaches its EKF, not this graph).
    mode : {"batch", "fixed-lag"}
        Whole-trajectory smoothing, or causal fixed-lag estimation (filtered estimate per epoch).
    lag_s : float
        Fixed-lag window [s]; only with ``mode="fixed-lag"`` (another value in batch mode is a ValueError).
    robust : {"auto", "huber", "cauchy"} or None
        M-estimator on each pseudorange factor; ``robust_k`` is its threshold in sigmas. "auto" takes
        ``DEFAULT_KERNEL[mode]``. Batch: Cauchy 1.0, started from a Huber 1.5 solve (``_solve_batch``),
        chosen with the shipped model and Doppler priors on the train and validation splits (3D RMSE
        train / val, hk; berlin; static: Cauchy 1.0 10.7 / 9.3; 15.9 / 7.5; 2.9 / 3.3 m. Cauchy 0.5
        22.9 / 9.4; 34.2 / 7.8; 3.2 / 3.4. Cauchy 2.0 11.4 / 8.9; 17.4 / 8.0; 2.7 / 3.1. Huber 1.5
        12.5 / 8.6; 20.1 / 11.0; 2.8 / 2.9). Fixed-lag: Huber 1.5, whose single iSAM2 step per epoch
        from a predicted start cannot escape the local minima of the non-convex Cauchy kernel (errors
        of 80 m after gaps).
    robust_k : float, optional
        Kernel threshold (whitened units); default from ``DEFAULT_KERNEL`` (1.5 for an explicit kernel). Given with
        ``robust=None`` it is a ValueError (no kernel to take it).
    accel_psd_enu_m2_s3 : (3,) float
        White-noise acceleration spectral density per east/north/up axis [m^2/s^3], finite and > 0. A graph gtsam
        cannot solve (an indeterminate linear system, or Levenberg-Marquardt giving up at its largest damping where
        an input is extreme: ``likely_cause``) is a one-line ValueError naming the epoch and that input.
    prior_pos_sigma_m, prior_vel_sigma_m_s : float
        Priors on the first epoch (from the coarse fix).
    covariances : bool
        True: gtsam marginal position covariances (on the bundled 1375-epoch drive no slower than the stand-in in
        either mode, session 35). False: snapshot/propagated stand-in, the default: its sds came closer to the
        errors on the validation splits (docs/sd_consistency.md).
    inflate_cov : bool
        With ``covariances``: multiply the marginals by ``estimators.consistency.covariance_inflation`` (>= 1: how
        far the pseudorange residuals at the estimated positions exceed the noise model's R over the last seconds),
        as the EKF does; ``info["cov_inflation"]`` holds the factor (1 without ``covariances``: the stand-in is not
        inflated). Chosen on the validation splits (docs/sd_consistency.md): the marginals' shares of errors within
        1 sd came 8.5 points closer to 68 % on average (berlin-pp's mean NEES 632-731 -> 20-30, hk unchanged); the
        stand-in, already wider, gained 1 point and grew too wide on berlin-pp (2D sd 15 m for 9.7 m errors).
    max_iterations : int
        Levenberg-Marquardt iterations (batch), per stage. A final stage that reaches them before its error settles
        (one more iteration, not used, would still lower it beyond the tolerances), or gives up at its largest
        damping with no extreme input to blame, keeps its last iterate with one warning and
        ``info["converged"] = False``. Of the train and validation solves with the shipped models only berlin-pp's
        train split with the default model stops at 50; run to convergence (200) its 3D RMSE went 13.52 -> 17.51 m
        (the Cauchy kernel is not convex), the other eleven did not move: 50 stays (docs/fgo_convergence.md).
    fixed_lag_iterations : int
        iSAM2 updates per epoch in fixed-lag mode (1 = one Gauss-Newton step per new epoch).
    doppler_sigma_m_s : float
        Doppler standard deviation [m/s] of the per-epoch velocity fixes (``lfgnss.velocity``) that
        become Huber-robust priors on ``V(k)``; 0 leaves Doppler out. With 0.5 (as the EKF) the train /
        val 3D RMSE went from 12.7 / 9.1; 23.0 / 18.1; 3.2 / 3.6 m (hk; berlin; static, Cauchy 1.0,
        no Doppler) to the figures above; 2.0 was in between.
    doppler_cn0_ref_dbhz : float or None
        With a value, each Doppler's variance follows C/N0 as in the EKF's ``EkfConfig.doppler_cn0_ref_dbhz``
        (``estimators.models.doppler_variance_m2_s2``); None: every Doppler has ``doppler_sigma_m_s``. Not taken
        from a model's filter settings: with the berlin-pp model's law (0.1 m/s, 45 dB-Hz) the graph's train / val
        3D RMSE went 10.87 / 9.67 -> 9.74 / 13.08 m against the constant 0.5 m/s.
    zupt_sigma_m_s : float, None or "model"
        Sigma per axis [m/s] of a zero-velocity prior on ``V(k)`` at every epoch whose Doppler fix finds the
        receiver standing still (needs ``doppler_sigma_m_s > 0``); None: none. "model": the setting of the filter
        the learned model runs in (``estimators.ekf.config_of(noise).zupt_sigma_m_s``; None for hand-set noise or
        with ``doppler_sigma_m_s=0``; a function wrapping a learned model has none: a warning says so, as the EKF's).
        Off by default: with the hk-tst-2019 model's 0.02 m/s the batch graph's train / val 3D RMSE went 11.37 / 6.25
        -> 12.31 / 6.12 m (fixed-lag 9.32 / 6.42 -> 9.41 / 5.69), while the static receiver's went 1.12 / 1.09 ->
        0.78 / 0.92 m (fixed-lag 1.31 / 4.12 -> 0.88 / 4.07).
    zupt_max_speed_m_s : float or None
        The standstill test's speed bound [m/s] (``estimators.models.still_fixes``); None: the model's filter's
        (``EkfConfig.zupt_max_speed_m_s``, 0.5 m/s by default).
    progress : bool
        Show a tqdm bar over the epochs on a terminal (``python -m lfgnss.solve`` does, unless ``--quiet``).
    name : str, optional
        Backend label written into the Solution; default ``fgo``, or ``fgo-fixed-lag`` in fixed-lag mode (as the
        command line names the run's files), with ``noise=None`` too, where the hand-set ``HeuristicNoise`` runs
        (``name="plain-fgo"`` says so).

    The Solution's ``info`` holds ``n_velocity_priors`` (epochs with a Doppler velocity prior), ``stationary`` ((T,)
    bool: epochs given the zero-velocity prior), ``residual_factor`` and ``cov_inflation`` (see ``inflate_cov``)
    and, in batch mode, ``iterations`` (all stages) and ``converged``, in fixed-lag mode ``coasted_outside_graph`` and
    ``factorization`` (``"CHOLESKY"``, or ``"QR"`` where Cholesky found the graph indeterminate).
    An epoch whose state gtsam returns non-finite is left STATUS_NONE with one warning. Unlike the EKFs,
    a position-blind epoch held only by the zero-velocity prior (batch) stays STATUS_COASTED: its satellites
    place no position.
    """

    #: The backend's name, the start of ``name``.
    default_name = "fgo"

    def __init__(self, *, noise: NoiseModel | str | os.PathLike | None = None, mode: str = "batch",
                 lag_s: float = DEFAULT_LAG_S,
                 robust: str | None = "auto", robust_k: float | None = None,
                 accel_psd_enu_m2_s3: tuple[float, float, float] = (1.0, 1.0, 0.1),
                 prior_pos_sigma_m: float = 100.0, prior_vel_sigma_m_s: float = 10.0,
                 covariances: bool = False, inflate_cov: bool = True, max_iterations: int = 50,
                 fixed_lag_iterations: int = 1,
                 doppler_sigma_m_s: float = 0.5, doppler_cn0_ref_dbhz: float | None = None,
                 zupt_sigma_m_s: float | str | None = None, zupt_max_speed_m_s: float | None = None,
                 progress: bool = False, name: str | None = None) -> None:
        owner = type(self).__name__
        covariances = check_flag(covariances, "covariances", owner)
        inflate_cov = check_flag(inflate_cov, "inflate_cov", owner)
        if name is not None and not isinstance(name, str):
            raise TypeError(f"{owner}: name must be a string, got {type(name).__name__}")
        progress = check_flag(progress, "progress", owner)
        if mode not in MODES:
            raise ValueError(f"{owner}: mode {mode!r} not in {MODES}")
        for key, value in (("lag_s", lag_s), ("robust_k", robust_k), ("prior_pos_sigma_m", prior_pos_sigma_m),
                           ("prior_vel_sigma_m_s", prior_vel_sigma_m_s), ("max_iterations", max_iterations),
                           ("fixed_lag_iterations", fixed_lag_iterations), ("doppler_sigma_m_s", doppler_sigma_m_s)):
            if value is None and key == "robust_k":
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value):
                raise ValueError(f"{owner}: {key} must be a finite number, got {value!r}")
        for key, value in (("prior_pos_sigma_m", prior_pos_sigma_m), ("prior_vel_sigma_m_s", prior_vel_sigma_m_s)):
            if not value > 0:
                raise ValueError(f"{owner}: {key} must be > 0, got {value}")
        for key, value in (("max_iterations", max_iterations), ("fixed_lag_iterations", fixed_lag_iterations)):
            if not (value >= 1 and float(value).is_integer()):
                raise ValueError(f"{owner}: {key} must be a whole number >= 1, got {value}")
        if doppler_cn0_ref_dbhz is not None and (isinstance(doppler_cn0_ref_dbhz, bool)
                                                 or not isinstance(doppler_cn0_ref_dbhz, numbers.Real)
                                                 or not np.isfinite(doppler_cn0_ref_dbhz)):
            raise ValueError(f"{owner}: doppler_cn0_ref_dbhz must be finite: a number of dB-Hz or None, "
                             f"got {doppler_cn0_ref_dbhz!r}")
        if not lag_s > 0:
            raise ValueError(f"{owner}: lag_s must be > 0, got {lag_s}")
        if mode == "batch" and lag_s != DEFAULT_LAG_S:
            raise ValueError(f"{owner}: lag_s={float(lag_s):g} needs mode='fixed-lag' (the batch mode uses every "
                             f"epoch, with no window)")
        if robust is None and robust_k is not None:
            raise ValueError(f"{owner}: robust_k={float(robust_k):g} needs a robust kernel (robust='auto', 'huber' "
                             f"or 'cauchy'); robust=None uses none")
        if robust == "auto":
            robust, default_k = DEFAULT_KERNEL[mode]
            robust_k = default_k if robust_k is None else robust_k
        robust_k = 1.5 if robust_k is None else robust_k
        if robust is not None and robust not in ROBUST_KERNELS:
            raise ValueError(f"{owner}: robust {robust!r} not in {('auto', *ROBUST_KERNELS)} or None")
        if not doppler_sigma_m_s >= 0:
            raise ValueError(f"{owner}: doppler_sigma_m_s must be >= 0, got {doppler_sigma_m_s}")
        if not robust_k > 0:
            raise ValueError(f"{owner}: robust_k must be > 0, got {robust_k}")
        psd = checked_accel_psd(accel_psd_enu_m2_s3)
        noise = resolve_noise(noise, owner)
        self.noise = noise if noise is not None else HeuristicNoise()
        self.zupt_sigma_m_s, self.zupt_max_speed_m_s = self._zupt_settings(zupt_sigma_m_s, zupt_max_speed_m_s,
                                                                           doppler_sigma_m_s > 0)
        if self.zupt_sigma_m_s is not None and not doppler_sigma_m_s > 0:
            raise ValueError(f"{owner}: zupt_sigma_m_s needs Dopplers to detect a standstill; "
                             "doppler_sigma_m_s is 0")
        self.mode = mode
        self.name = (self.default_name + ("-fixed-lag" if mode == "fixed-lag" else "")) if name is None else name
        self.lag_s = float(lag_s)
        self.robust = robust
        self.robust_k = float(robust_k)
        self.accel_psd_enu_m2_s3 = psd
        self.prior_pos_sigma_m = float(prior_pos_sigma_m)
        self.prior_vel_sigma_m_s = float(prior_vel_sigma_m_s)
        self.covariances = covariances
        self.inflate_cov = inflate_cov
        self.max_iterations = int(max_iterations)
        self.fixed_lag_iterations = int(fixed_lag_iterations)
        self.doppler_sigma_m_s = float(doppler_sigma_m_s)
        self.doppler_cn0_ref_dbhz = None if doppler_cn0_ref_dbhz is None else float(doppler_cn0_ref_dbhz)
        self.progress = progress

    def _zupt_settings(self, sigma: float | str | None, max_speed: float | None,
                       dopplers: bool) -> tuple[float | None, float]:
        """The zero-velocity prior's sigma [m/s] (None: off) and speed bound [m/s], "model"/None resolved.

        The model's filter is read only where it gives a value: a graph without the prior ignores its settings, and
        "model" without ``dopplers`` to find a standstill is off. Read for noise that carries no filter (a function
        wrapping a learned model), it is the default EkfConfig, which a warning says, as the EKF's does."""
        read: dict[str, float | None] = {}          # the settings taken from the model's filter, with their values
        owner = type(self).__name__
        if isinstance(sigma, str) and sigma == "model":
            sigma = None
            if dopplers:
                sigma = read["zupt_sigma_m_s"] = config_of(self.noise).zupt_sigma_m_s
        if max_speed is None:
            max_speed = DEFAULT_ZUPT_MAX_SPEED_M_S
            if sigma is not None:
                max_speed = read["zupt_max_speed_m_s"] = config_of(self.noise).zupt_max_speed_m_s
        if read:
            warn_no_filter_settings(
                self.noise, owner,
                "it gets the default EkfConfig's " + ", ".join(f"{key}={value!r}" for key, value in read.items()),
                ", ".join(f"{key}=estimators.config_of(model).{key}" for key in read))
        for key, value in (("zupt_sigma_m_s", sigma), ("zupt_max_speed_m_s", max_speed)):
            if value is None and key == "zupt_sigma_m_s":
                continue
            if (isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value)
                    or not value > 0):
                extra = ', None or "model"' if key == "zupt_sigma_m_s" else ""
                raise ValueError(f"{owner}: {key} must be a positive number of m/s{extra}, got {value!r}")
        return (None if sigma is None else float(sigma)), float(max_speed)

    def __repr__(self) -> str:
        """The settings: name, noise model, mode (and lag), robust kernel, and every option off its default."""
        parts = [f"name={self.name!r}", f"noise={describe_noise(self.noise)}", f"mode={self.mode!r}"]
        parts += [f"lag_s={self.lag_s:g}"] if self.mode == "fixed-lag" else []
        parts += [f"robust={self.robust!r}"] + ([f"robust_k={self.robust_k:g}"] if self.robust is not None else [])
        if self.zupt_sigma_m_s is not None:            # as resolved: "model" says nothing without the model
            parts.append(f"zupt_sigma_m_s={self.zupt_sigma_m_s!r}")
            parts += ([f"zupt_max_speed_m_s={self.zupt_max_speed_m_s!r}"]
                      if self.zupt_max_speed_m_s != DEFAULT_ZUPT_MAX_SPEED_M_S else [])
        shown = {"self", "name", "noise", "mode", "lag_s", "robust", "robust_k", "zupt_sigma_m_s", "zupt_max_speed_m_s"}
        for key, param in inspect.signature(LfgnssFgo.__init__).parameters.items():
            value = getattr(self, key, None)
            value = tuple(float(v) for v in value) if key == "accel_psd_enu_m2_s3" else value
            if key not in shown and value != param.default:
                parts.append(f"{key}={value!r}")
        return f"{type(self).__name__}({', '.join(parts)})"

    # ------------------------------------------------------------------ building blocks
    def _measurement_model(self, sigma_m: float, kernel: tuple[str | None, float] | None = None
                           ) -> gtsam.noiseModel.Base:
        """A pseudorange's noise model: sigma ``sigma_m`` [m] in the robust ``kernel`` (default: the graph's)."""
        robust, k = (self.robust, self.robust_k) if kernel is None else kernel
        base = gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma_m]))
        if robust is None:
            return base
        return gtsam.noiseModel.Robust.Create(_m_estimator(robust, k), base)

    def _epoch(self, k: int, seq: Sequence, z_m: np.ndarray, sigma_m: np.ndarray, pos_guess: np.ndarray,
               graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
               kernel: tuple[str | None, float] | None = None, loose_sigma_m: float | None = None) -> int:
        """Add epoch k's pseudorange factors, clock initial values (and with ``loose_sigma_m`` [m], for fewer than 3
        ``position_ranges``, a loose position prior of that sigma); return satellites used.

        Clock initial value per constellation: median(pr + vc - rho(x_guess)) / c [s].
        """
        used = np.flatnonzero(seq.mask[k])
        if used.size == 0:
            return 0
        n_sys = len(seq.systems)
        sat = seq.sat_pos_ecef_m[k, used]
        sysj = seq.system_index[k, used]
        resid = z_m[k, used] - geometric_range_m(sat, pos_guess)
        keys = [clock_key(k, j, n_sys) for j in sysj.tolist()]
        for j in np.unique(sysj).tolist():
            # keyword c= picks the double overload directly (positional: ~80 us of overload resolution)
            values.insert(clock_key(k, j, n_sys), c=_median(resid[sysj == j]) / SPEED_OF_LIGHT_M_S)
        xk = X(k)
        for key, z, s, sig in zip(keys, z_m[k, used].tolist(), sat, sigma_m[k, used].tolist()):
            graph.add(gtsam.PseudorangeFactor(xk, key, z, s, 0.0, self._measurement_model(sig, kernel)))
        if loose_sigma_m:
            # Fewer than 3 satellites left once each constellation's clock took one: with the clocks' Jacobians
            # (c, in seconds) beside the positions', gtsam's undamped Cholesky (iSAM2, marginals) declares the
            # system indeterminate although the motion factors fix it. A loose prior at the guess lets it through.
            loose = gtsam.noiseModel.Isotropic.Sigma(3, loose_sigma_m)
            graph.add(gtsam.PriorFactorPoint3(xk, pos_guess, loose))
        return int(used.size)

    def _doppler_velocity(self, seq: Sequence) -> DopplerVelocity | None:
        """Per-epoch Doppler velocity fixes at the coarse fix (``lfgnss.velocity``); None when not used."""
        if self.doppler_sigma_m_s <= 0 or not np.any(seq.prr_mask):
            return None
        used = seq.prr_mask & seq.mask
        law = EkfConfig(doppler_sigma_m_s=self.doppler_sigma_m_s, doppler_cn0_ref_dbhz=self.doppler_cn0_ref_dbhz)
        sigma = np.sqrt(used_doppler_variance_m2_s2(seq.cn0_dbhz, used, law, type(self).__name__, seq.name))
        return doppler_velocity(seq.prr_m_s, used, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s,
                                seq.coarse_ecef_m, sigma_m_s=sigma)

    def _still(self, dv: DopplerVelocity | None) -> np.ndarray | None:
        """(T,) bool: epochs that get a zero-velocity prior (``still_fixes`` of the Doppler fixes); None: off."""
        if self.zupt_sigma_m_s is None or dv is None:
            return None
        return still_fixes(dv, self.zupt_max_speed_m_s)

    def _velocity_prior(self, k: int, dv: DopplerVelocity | None, still: np.ndarray | None,
                        graph: gtsam.NonlinearFactorGraph) -> None:
        """Add epoch k's Doppler velocity fix, if it has one, as a Huber-robust prior on ``V(k)``, and a zero-velocity
        prior where ``still[k]``.

        A prior on each epoch's velocity, not a factor per Doppler: the fix has already spent one
        Doppler per epoch on the clock drift, which the graph does not carry (free clocks per epoch).
        """
        if dv is None or not dv.ok[k]:
            return
        base = gtsam.noiseModel.Gaussian.Covariance(dv.cov_m2_s2[k])
        model = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(DOPPLER_HUBER_K), base)
        graph.add(gtsam.PriorFactorPoint3(V(k), dv.vel_ecef_m_s[k], model))
        if still is not None and still[k]:
            graph.add(gtsam.PriorFactorPoint3(V(k), np.zeros(3),
                                              gtsam.noiseModel.Isotropic.Sigma(3, self.zupt_sigma_m_s)))

    def _accel_psd_ecef(self, ref_ecef_m: np.ndarray) -> np.ndarray:
        """The ENU acceleration density [m^2/s^3] as a 3x3 ECEF matrix at ``ref_ecef_m`` [m]."""
        lat, lon, _ = ecef_to_lla(ref_ecef_m)
        rot = enu_rotation(lat, lon)
        return rot.T @ np.diag(self.accel_psd_enu_m2_s3) @ rot

    @staticmethod
    def _first_velocity(k: int, dv: DopplerVelocity | None) -> np.ndarray:
        """Velocity [m/s] a graph starts from at epoch k, under its prior: the Doppler fix, else 0 (as the EKF starts).

        Not the coarse fixes' time derivative: at 5 Hz, fixes 10-30 m apart in noise differ by 50-150 m/s, which a
        prior of ``prior_vel_sigma_m_s`` (10 m/s) then held (a fixed-lag run 100 m/s off diverged by hundreds of m).
        """
        return dv.vel_ecef_m_s[k] if dv is not None and dv.ok[k] else np.zeros(3)

    def _priors(self, k0: int, pos: np.ndarray, vel: np.ndarray, graph: gtsam.NonlinearFactorGraph) -> None:
        """Priors on the first epoch's position ``pos`` [m] and velocity ``vel`` [m/s] (``prior_*_sigma``)."""
        graph.add(gtsam.PriorFactorPoint3(X(k0), pos, gtsam.noiseModel.Isotropic.Sigma(3, self.prior_pos_sigma_m)))
        graph.add(gtsam.PriorFactorPoint3(V(k0), vel, gtsam.noiseModel.Isotropic.Sigma(3, self.prior_vel_sigma_m_s)))

    # ------------------------------------------------------------------ solve
    def solve(self, sequence: Sequence) -> Solution:
        """Estimate every epoch of ``sequence`` (positions [m]); epochs before the first coarse fix get STATUS_NONE."""
        owner = type(self).__name__
        seq = usable_sequence(check_sequence(sequence, owner), owner,         # the same Sequence on valid input
                              dopplers=self.doppler_sigma_m_s > 0)
        t = np.asarray(seq.time_gps_s, float)
        n_t = len(seq)
        if n_t > 1 and np.any(np.diff(t) <= 0):
            k = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise ValueError(f"{owner}: {seq.name!r}: time not increasing at epoch {k + 1}")
        r_m2, vc_m = checked_noise(owner, seq.name, seq.mask, *noise_output(owner, self.noise(seq), self.noise),
                                   self.noise)
        seq = keep_slots(seq, switched_on_warned(owner, seq, seq.mask, r_m2))
        z_m = np.where(seq.mask, seq.pr_m + vc_m, 0.0)
        sigma_m = np.sqrt(np.where(seq.mask, r_m2, 1.0))

        pos = np.full((n_t, 3), np.nan)
        vel = np.full((n_t, 3), np.nan)
        clock = np.full(n_t, np.nan)
        cov = np.full((n_t, 3, 3), np.nan)
        status = np.full(n_t, STATUS_NONE, int)
        n_used = np.zeros(n_t, int)
        info: dict = {"mode": self.mode, "robust": self.robust}
        fixed = np.all(np.isfinite(seq.coarse_ecef_m), axis=1)
        if not np.any(fixed):
            info["reason"] = "no coarse fix in the sequence"
            return Solution(self.name, t.copy(), pos, cov, clock, n_used, status, vel, info)
        k0 = int(np.argmax(fixed))
        psd_ecef = self._accel_psd_ecef(seq.coarse_ecef_m[k0])
        ranges = position_ranges(seq)                # position information per epoch, after the clocks
        start = time.perf_counter()
        dv = self._doppler_velocity(seq)
        info["n_velocity_priors"] = 0 if dv is None else int(np.count_nonzero(dv.ok[k0:]))
        still = self._still(dv)
        inputs = (seq, k0, z_m, sigma_m, psd_ecef, dv, still, info, ranges)
        # fixed-lag: iSAM2's Cholesky, fast; where it finds weak epochs in a row (few satellites, each constellation's
        # clock in seconds beside positions in metres) indeterminate with inputs in order, QR again, the stabler one
        tries = ["CHOLESKY", "QR"] if self.mode == "fixed-lag" else [""]
        for factorization in tries:
            try:
                est = (self._solve_fixed_lag(*inputs, factorization) if factorization
                       else self._solve_batch(*inputs))
                break
            except RuntimeError as err:
                found = symbol_epoch(str(err), len(seq.systems))
                if found is None or "linear system" not in str(err):
                    raise
                where = (f"fixed-lag update at epoch {found[1]} of {seq.name!r}" if self.mode == "fixed-lag"
                         else f"batch graph of {seq.name!r} at epoch {found[1]}")
                what = (f"the {where} is numerically singular (gtsam: an indeterminate linear system near variable "
                        f"{found[0]})")
                failure = self._failure(seq, r_m2, found[1], what, always=factorization == tries[-1])
                cause = likely_cause(r_m2[seq.mask], self.accel_psd_enu_m2_s3)  # anywhere: not solved around (review)
                if failure is None and cause is not None:
                    failure = ValueError(f"{owner}: {what}; {cause}")
                if failure is not None:
                    raise failure from None
                warnings.warn(f"{owner}: gtsam's Cholesky factorisation found the fixed-lag graph of {seq.name!r} "
                              f"indeterminate at epoch {found[1]} ({int(ranges[found[1]])} pseudorange(s) on "
                              f"position after the clocks); solving it again with QR factorisation (numerically "
                              f"stabler, slower)", UserWarning, stacklevel=caller_stacklevel())
        if factorization:
            info["factorization"] = factorization
        info["solve_time_s"] = time.perf_counter() - start
        pos[k0:], vel[k0:], clock[k0:], n_used[k0:], cov_m = est
        gap = np.zeros(n_t, bool)                   # fixed-lag epochs left without a position after a long gap
        gap[k0:] = info.pop("after_gap", False)
        lost = ~np.isfinite(pos).all(axis=1) & (np.arange(n_t) >= k0) & ~gap
        if np.any(lost):
            first = int(np.argmax(lost))
            warnings.warn(f"{type(self).__name__}: gtsam returned a non-finite position at {np.count_nonzero(lost)} "
                          f"epoch(s) of {seq.name!r} (first: epoch {first}); they are left without a solution "
                          f"(STATUS_NONE)", UserWarning, stacklevel=caller_stacklevel())
            pos[lost], vel[lost], clock[lost] = np.nan, np.nan, np.nan
        # a position-blind epoch spends its satellites on clocks: its position is the motion model's (coasted)
        blind = ranges <= 0
        blind[k0] = False                           # the first epoch is placed by the coarse fix's prior
        n_used[blind] = 0
        # epochs given the zero-velocity prior: from the first fix on; fixed-lag coasts blind ones outside the graph
        given = (np.arange(n_t) >= k0) & (~blind if self.mode == "fixed-lag" else True)
        info["stationary"] = np.zeros(n_t, bool) if still is None else still & given
        status[k0:] = np.where(n_used[k0:] > 0, STATUS_UPDATED, STATUS_COASTED)
        status[lost | gap], n_used[lost | gap] = STATUS_NONE, 0
        info["residual_factor"] = residual_variance_factor(seq, pos, r_m2, seq.mask)
        inflation = np.ones(n_t)
        if cov_m is None:
            cov_m = self._stand_in_covariance(seq, k0, pos, sigma_m, psd_ecef)
        elif self.inflate_cov:
            inflation = covariance_inflation(t, info["residual_factor"])
        info["cov_inflation"] = inflation
        cov[k0:] = cov_m * inflation[k0:, None, None]
        cov[lost] = np.nan
        return Solution(self.name, t.copy(), pos, cov, clock, n_used, status, vel, info)

    def _failure(self, seq: Sequence, r_m2: np.ndarray, k: int, what: str, always: bool = False) -> ValueError | None:
        """ValueError saying ``what`` went wrong at epoch ``k`` of ``seq``, with the input most likely behind it
        (``likely_cause`` of the epoch's R [m^2] and the acceleration density); None, unless ``always``, when no input
        is out of the ordinary."""
        k = min(max(int(k), 0), len(seq) - 1)
        cause = likely_cause(r_m2[k][seq.mask[k]], self.accel_psd_enu_m2_s3)
        if cause is None and not always:
            return None
        r = r_m2[seq.mask]
        cause = cause or (f"R spans {r.min():.3g} to {r.max():.3g} m^2 and {psd_text(self.accel_psd_enu_m2_s3)}: "
                          f"R must be a pseudorange variance in m^2 and the density a car's, about 0.1 to 10 m^2/s^3"
                          if r.size else "no satellite is used")
        return ValueError(f"{type(self).__name__}: {what}; {cause}")

    @staticmethod
    def _worst_epoch(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, n_systems: int) -> int:
        """Epoch of the variable of the factor with the largest error at ``values`` (a clock ``B(k C + j)``: k)."""
        errors = [graph.at(i).error(values) if graph.exists(i) else -np.inf for i in range(graph.size())]
        symbol = gtsam.Symbol(graph.at(int(np.argmax(errors))).keys()[0])
        return key_epoch(chr(symbol.chr()), int(symbol.index()), n_systems)

    @staticmethod
    def _initial_trajectory(seq: Sequence, k0: int, dv: DopplerVelocity | None = None
                            ) -> tuple[np.ndarray, np.ndarray]:
        """Positions (coarse fix, interpolated where missing) and velocities (Doppler fixes where there
        are some, else the time derivative of the positions)."""
        t = seq.time_gps_s[k0:]
        p = _interpolate_rows(t, np.asarray(seq.coarse_ecef_m[k0:], float))
        v = np.gradient(p, t, axis=0) if len(t) > 1 else np.zeros_like(p)
        if dv is not None:
            v = np.where(dv.ok[k0:, None], dv.vel_ecef_m_s[k0:], v)
        return p, v

    def _solve_batch(self, seq, k0, z_m, sigma_m, psd_ecef, dv, still, info, ranges):
        """The whole graph from epoch ``k0`` on, solved by Levenberg-Marquardt: (positions [m], velocities [m/s],
        clocks [m], satellites used, marginal covariances [m^2] or None), one row per epoch from ``k0``."""
        n_t, n_sys = len(seq), len(seq.systems)
        t = seq.time_gps_s
        p0, v0 = self._initial_trajectory(seq, k0, dv)
        motion = _MotionModel(psd_ecef)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.max_iterations)
        params.setRelativeErrorTol(1e-5)
        params.setAbsoluteErrorTol(1e-5)
        # The Cauchy kernel is not convex: from a coarse start 30+ m off it keeps the satellites that agree
        # with the wrong position. A Huber (convex) solve first gives it a start near the right minimum.
        stages = [(self.robust, self.robust_k)]
        if self.robust == "cauchy":
            stages.insert(0, ("huber", CAUCHY_WARM_START_HUBER_K))
        values = None
        info["iterations"] = 0
        for kernel in stages:
            graph = gtsam.NonlinearFactorGraph()
            start = gtsam.Values()
            self._priors(k0, p0[0], self._first_velocity(k0, dv), graph)
            n_used = np.zeros(n_t - k0, int)
            for k in epoch_range(k0, n_t, self.progress, f"{self.name} ({kernel[0]} graph)"):
                guess = p0[k - k0] if values is None else values.atPoint3(X(k))
                start.insertPoint3(X(k), guess)
                start.insertPoint3(V(k), v0[k - k0] if values is None else values.atPoint3(V(k)))
                loose = LOOSE_PRIOR_SIGMA_M if k > k0 and ranges[k] < 3 else None
                n_used[k - k0] = self._epoch(k, seq, z_m, sigma_m, guess, graph, start, kernel, loose_sigma_m=loose)
                self._velocity_prior(k, dv, still, graph)
                if k > k0:
                    graph.add(motion.factor(k - 1, k, float(t[k] - t[k - 1])))
            if values is None:
                info["initial_error"] = float(graph.error(start))
            optimizer = gtsam.LevenbergMarquardtOptimizer(graph, start, params)
            values = gtsam.Values(optimizer.optimize())     # a copy: _settled's iterate() frees the optimizer's own
            iterations = int(optimizer.iterations())
            info["iterations"] += iterations
            gave_up = optimizer.lambda_() >= params.getlambdaUpperBound()
            # only the last stage is judged (earlier ones start it), so only it pays the probe's extra iteration
            settled = not gave_up and (iterations < self.max_iterations or kernel is not stages[-1]
                                       or self._settled(optimizer, params))
            if gave_up:
                # Levenberg-Marquardt gave up: no step lowered the error even at its largest damping
                worst = self._worst_epoch(graph, values, n_sys)
                stuck = (f"Levenberg-Marquardt could not lower the error at its largest damping (worst fit at epoch "
                         f"{worst})")
                failure = self._failure(seq, sigma_m ** 2, worst, f"the batch solve of {seq.name!r} failed: {stuck}")
                if failure is not None:
                    raise failure
        # the last stage's optimum; earlier stages only start it, so only its end is judged
        result = values
        info["converged"] = settled
        if gave_up:
            self._warn_not_converged(seq, f"{stuck}; the positions are its last iterate")
        elif not info["converged"]:
            self._warn_not_converged(seq, f"Levenberg-Marquardt stopped at max_iterations={self.max_iterations} "
                                          f"before its error settled; the positions are its last iterate (a larger "
                                          f"max_iterations goes on, to a minimum of the robust kernel that need not "
                                          f"be nearer the truth)")
        info["final_error"] = float(graph.error(result))
        pos = np.array([result.atPoint3(X(k)) for k in range(k0, n_t)])
        vel = np.array([result.atPoint3(V(k)) for k in range(k0, n_t)])
        clk = np.array([result.atDouble(clock_key(k, 0, n_sys)) * SPEED_OF_LIGHT_M_S
                        if result.exists(clock_key(k, 0, n_sys)) else np.nan for k in range(k0, n_t)])
        cov = None
        if self.covariances:
            try:
                marginals = gtsam.Marginals(graph, result)
                cov = np.array([marginals.marginalCovariance(X(k)) for k in range(k0, n_t)])
            except RuntimeError as err:
                self._warn_no_marginals(seq, err)
        return pos, vel, clk, n_used, cov

    @staticmethod
    def _settled(optimizer: gtsam.LevenbergMarquardtOptimizer, params: gtsam.LevenbergMarquardtParams) -> bool:
        """Whether an optimizer stopped at its last allowed iteration had converged: one more iteration (whose result
        is not used) lowers the error by less than the tolerances."""
        before = optimizer.error()
        optimizer.iterate()
        return bool(gtsam.checkConvergence(params.getRelativeErrorTol(), params.getAbsoluteErrorTol(),
                                           params.getErrorTol(), before, optimizer.error()))

    def _warn_not_converged(self, seq: Sequence, why: str) -> None:
        """Warn that the batch solve of ``seq`` ended unconverged for reason ``why`` (its positions are kept)."""
        warnings.warn(f"{type(self).__name__}: the batch solve of {seq.name!r} did not converge: {why}", UserWarning,
                      stacklevel=caller_stacklevel())

    def _warn_no_marginals(self, seq: Sequence, err: RuntimeError) -> None:
        """Warn that gtsam could not give the solved graph's marginal covariances: the positions stand, with the
        stand-in covariance of ``covariances=False``."""
        found = symbol_epoch(str(err), len(seq.systems))
        why = (f"an indeterminate linear system near variable {found[0]}" if found
               else (str(err).strip().splitlines() or [type(err).__name__])[0])
        warnings.warn(f"{type(self).__name__}: gtsam could not compute the marginal covariances of {seq.name!r} "
                      f"(gtsam: {why}); the positions are kept, with the stand-in covariance of covariances=False",
                      UserWarning, stacklevel=caller_stacklevel())

    def _solve_fixed_lag(self, seq, k0, z_m, sigma_m, psd_ecef, dv, still, info, ranges,
                         factorization: str = "CHOLESKY"):
        """Epoch by epoch in iSAM2 over a ``lag_s`` window (causal): ``_solve_batch``'s tuple, each epoch's state as
        estimated when it arrived; iSAM2 factorises by ``factorization`` (``"CHOLESKY"`` or ``"QR"``)."""
        n_t, n_sys = len(seq), len(seq.systems)
        t = seq.time_gps_s - seq.time_gps_s[k0]
        isam = gtsam.ISAM2Params()
        # per variable type: one threshold for all would be 0.01 s on the clocks (3000 km), whose linearisation
        # point would then never move, and the robust kernel would weigh every pseudorange by its first clock guess
        thresholds = gtsam.ISAM2ThresholdMap()
        for letter, size, threshold in (("x", 3, RELINEARIZE_M), ("v", 3, RELINEARIZE_M),
                                        ("b", 1, RELINEARIZE_M / SPEED_OF_LIGHT_M_S)):
            thresholds.insert((letter, np.full((size, 1), threshold)))
        isam.setRelinearizeThreshold(thresholds)
        isam.relinearizeSkip = 1
        isam.setFactorization(factorization)
        isam.findUnusedFactorSlots = True          # else every marginalised factor's slot stays: O(T^2) time
        smoother = gtsam.IncrementalFixedLagSmoother(self.lag_s, isam)
        motion = _MotionModel(psd_ecef)
        blind = ranges <= 0
        m = n_t - k0
        pos, vel, clk = np.empty((m, 3)), np.empty((m, 3)), np.full(m, np.nan)
        n_used = np.zeros(m, int)
        cov = np.empty((m, 3, 3)) if self.covariances else None
        last = k0                                   # latest epoch in the graph
        joint = None                                # marginal covariance blocks of X(last), V(last)
        fixed = np.all(np.isfinite(seq.coarse_ecef_m), axis=1)
        gap_open, restart = False, False            # after a long gap: no position until a coarse fix, then anew
        after_gap = np.zeros(m, bool)
        for k in epoch_range(k0, n_t, self.progress, self.name):
            i = k - k0
            if k > k0 and (gap_open or t[k] - t[k - 1] > MAX_GAP_S):
                if not fixed[k]:
                    gap_open, after_gap[i] = True, True
                    pos[i], vel[i] = np.nan, np.nan
                    if cov is not None:
                        cov[i] = np.nan
                    continue
                gap_open, restart = False, True
                smoother = gtsam.IncrementalFixedLagSmoother(self.lag_s, isam)
            if k > k0 and blind[k] and not restart:
                # Kept out of the graph (module docstring): along a chain of short CV factors the Cholesky
                # pivot of the newest position shrinks until it is ~2^11 below the previous epoch's, which
                # gtsam's choleskyPartial takes for an underconstrained system.
                dt = float(t[k] - t[last])
                pos[i] = pos[last - k0] + dt * vel[last - k0]
                vel[i] = vel[last - k0]
                clk[i] = self._clock_only(k, seq, z_m, pos[i])
                if cov is not None:
                    try:
                        if joint is None:
                            joint = smoother.getISAM2().jointMarginalCovariance([X(last), V(last)])
                        cov[i] = _coasted_position_covariance(joint, X(last), V(last), dt, psd_ecef)
                    except RuntimeError as err:
                        self._warn_no_marginals(seq, err)
                        cov = None
                continue
            graph = gtsam.NonlinearFactorGraph()
            values = gtsam.Values()
            if k == k0 or restart:
                x_guess = seq.coarse_ecef_m[k]
                v_guess = self._first_velocity(k, dv)
                self._priors(k, x_guess, v_guess, graph)
                restart = False
            else:
                dt = float(t[k] - t[last])
                v_guess = vel[last - k0]
                x_guess = pos[last - k0] + dt * v_guess       # CV prediction from the filtered state
                if dt > self.lag_s and np.all(np.isfinite(seq.coarse_ecef_m[k])):
                    # X(last) leaves the window in this update, so this linearisation point is final for
                    # the epoch: start from the coarse fix, not from a prediction maybe 100+ m off, which
                    # would put every satellite deep in the robust kernel's tail.
                    x_guess = seq.coarse_ecef_m[k]
                graph.add(motion.factor(last, k, dt))
            values.insertPoint3(X(k), x_guess)
            values.insertPoint3(V(k), v_guess)
            n_used[i] = self._epoch(k, seq, z_m, sigma_m, x_guess, graph, values,
                                    loose_sigma_m=self.prior_pos_sigma_m if k > k0 and ranges[k] < 3 else None)
            self._velocity_prior(k, dv, still, graph)
            stamps = {key: float(t[k]) for key in values.keys()}
            smoother.update(graph, values, stamps)
            for _ in range(self.fixed_lag_iterations - 1):
                smoother.update()
            est = smoother.calculateEstimate()
            pos[i] = est.atPoint3(X(k))
            vel[i] = est.atPoint3(V(k))
            if est.exists(clock_key(k, 0, n_sys)):
                clk[i] = est.atDouble(clock_key(k, 0, n_sys)) * SPEED_OF_LIGHT_M_S
            if cov is not None:
                try:
                    cov[i] = smoother.marginalCovariance(X(k))
                except RuntimeError as err:
                    self._warn_no_marginals(seq, err)
                    cov = None
            last, joint = k, None
        info["coasted_outside_graph"] = int(np.count_nonzero(blind[k0 + 1:] & ~after_gap[1:]))
        info["after_gap"] = after_gap
        return pos, vel, clk, n_used, cov

    @staticmethod
    def _clock_only(k: int, seq: Sequence, z_m: np.ndarray, pos: np.ndarray) -> float:
        """Clock of ``systems[0]`` [m] at a position-blind epoch k, at position ``pos`` [m] (NaN: none of its sats).

        One satellite per constellation: its clock takes the whole residual, as in the graph.
        """
        used = np.flatnonzero(seq.mask[k])
        first = used[seq.system_index[k, used] == 0]
        if first.size == 0:
            return np.nan
        rho = geometric_range_m(seq.sat_pos_ecef_m[k, first[:1]], pos)[0]
        return float(z_m[k, first[0]] - rho)

    def _stand_in_covariance(self, seq: Sequence, k0: int, pos: np.ndarray, sigma_m: np.ndarray,
                             psd_ecef: np.ndarray) -> np.ndarray:
        """Snapshot WLS covariance (H^T R^-1 H)^-1 position block; where rank deficient, the last full-rank one plus
        q T^3 / 3 for the time T [s] since it (white-acceleration PSD q [m^2/s^3]).

        H rows ``[-los_i, e_j(i)]`` over position and one clock per constellation, weights 1/r_i.
        """
        n_t, n_sys = len(seq), len(seq.systems)
        placed = np.isfinite(pos[k0:]).all(axis=1)                # epochs left without a position: no snapshot
        mask = seq.mask[k0:] & placed[:, None]
        sysj = np.where(mask, seq.system_index[k0:], 0)
        h = np.zeros(mask.shape + (3 + n_sys,))
        h[..., :3] = -line_of_sight(seq.sat_pos_ecef_m[k0:], np.where(placed[:, None], pos[k0:], 0.0)[:, None, :])
        h[..., 3:] = sysj[..., None] == np.arange(n_sys)
        hw = np.where(mask[..., None], h / sigma_m[k0:, :, None], 0.0)
        info_m = np.einsum("tni,tnj->tij", hw, hw)
        present = np.einsum("tni->ti", hw[..., 3:] != 0)
        idx = np.arange(n_sys)
        info_m[:, 3 + idx, 3 + idx] += present == 0            # absent clocks: decoupled unit diagonal
        rank_ok = mask.sum(axis=1) >= 3 + (present > 0).sum(axis=1)
        rank_ok &= np.linalg.cond(info_m) < 1e12
        snap = np.linalg.inv(np.where(rank_ok[:, None, None], info_m, np.eye(3 + n_sys)))[:, :3, :3]
        out = np.empty((n_t - k0, 3, 3))
        t = seq.time_gps_s
        # a gap grows from the last epoch that had a fix as one step of its whole length: q T^3 / 3 over the gap T,
        # not the sum of q dt^3 / 3 over its epochs (which is T^2 / n^2 times smaller and depends on the rate)
        last, t_last = np.eye(3) * self.prior_pos_sigma_m ** 2, float(t[k0])
        for i in range(n_t - k0):
            if not placed[i]:
                out[i] = np.nan
                continue
            if rank_ok[i]:
                cur = last = snap[i]
                t_last = float(t[k0 + i])
            else:
                cur = last + (float(t[k0 + i]) - t_last) ** 3 / 3.0 * psd_ecef
            out[i] = 0.5 * (cur + cur.T)
        return out


@register("fgo")
@options_of(LfgnssFgo)
def create_lfgnss_fgo(noise: NoiseModel | str | os.PathLike | None = None, **options) -> LfgnssFgo:
    """``create("fgo")``: the LF-GNSS factor graph with ``noise`` (a model or its file), default the bundled model."""
    return LfgnssFgo(noise=default_noise() if noise is None else noise, **options)


__all__ = ["LfgnssFgo", "create_lfgnss_fgo", "cv_motion_factor", "cv_process_covariance", "clock_key",
           "position_blind_epochs", "position_ranges", "MODES", "ROBUST_KERNELS"]
