"""LF-GNSS extended Kalman filter as an estimator plug-in, on filterpy's ``ExtendedKalmanFilter`` (with numpy's
inverse of S: ``extended_kalman_filter``).

Per epoch ``k`` (models in ``estimators.models``)::

    predict:  x^- = F(dt) x,  P^- = F P F^T + Q(dt)
    measure:  z_i = pr_i + vc_i              (v^c enters here, ``compensated_pseudorange``)
              v_i = z_i - h_i(x^-),  S = H P^- H^T + R,  R = diag(r_i)
    gate:     keep satellite i if t_i = |v_i| / sqrt(S_ii) <= gate_sigma
    soften:   r_i *= max(1, t_i / huber_k)          (only with EkfConfig.huber_k; Huber's weight, pseudoranges)
    stand:    add 0 = v + n, n ~ N(0, zupt_sigma^2 I_3), zupt_sigma [m/s]  (only with EkfConfig.zupt_sigma_m_s,
              at epochs the Dopplers find standing still, ``models.stationary_epochs``; ``info["stationary"]``
              marks them; an epoch updated by it alone counts as updated, not coasted)
    update:   K = P^- H^T S^-1,  x = x^- + K v,  P = (I - K H) P^- (I - K H)^T + K R K^T   (Joseph)

so ``x = x^- + K (pr - h + vc)`` as in the paper. The Solution reports ``P_pos max(1, f)``, f a running mean of
the pseudorange residuals' variance factor (``estimators.consistency``; ``inflate_cov=False``: ``P_pos``).
Initialisation and resets take the coarse fix
(``Sequence.coarse_ecef_m`` / ``coarse_clock_m``; where only the clock is NaN, the epoch's pseudoranges give it,
``coarse_clocks``, which ``learning.torch_ekf`` does not do: the sequences training builds have both) with covariance
P0 and then update with the
epoch's satellites, twice if a satellite's post-fit residual exceeds ``gate_sigma sqrt(r)`` (the
second time without those satellites). Resets happen when the filter has no state yet, at the first coarse fix
after a gap longer than ``max_gap_s`` (the epochs before it get no position), when most usable satellites fail the
gate (``reset_gated_fraction``; not in the epoch right after a reset) with a median innovation of at least
``clock_jump_min_m`` and still do after the prior's clock was realigned to it (a receiver clock jump,
``models.realign_clock``), or when the updated position is farther than ``reset_distance_m`` from a coarse fix with
a redundancy of at least ``reset_min_redundancy`` satellites. ``learning.torch_ekf`` implements exactly this logic,
batched and differentiable.

A noise model that is ``online`` (a model trained with ``model.innovation``) is asked epoch by epoch, after
the predict step: ``noise.predict(features_k, mask_k, innovation_feature(pr - h(x^-) - median))``, with zero
innovations where the epoch has no prior (start, re-initialisation after a gap). ``info["r_m2"]`` and
``info["vc_m"]`` keep the noise every epoch used: R as the filter weighed it before its gate, the noise model's
times ``EkfConfig.glonass_sigma_factor`` squared on GLONASS satellites (``models.pseudorange_variance_factor``; a
``huber_k`` update further scales a far-off satellite's R by t / k, which is not kept), and 1 on slots left out or
switched off; ``info["noise_r_m2"]`` the noise model's R itself, as it gave it.
"""
from __future__ import annotations

import functools
import math
import numbers
import os
import warnings
from dataclasses import fields

import numpy as np

from lfgnss.features import innovation_feature
from lfgnss.sequence import Sequence

from . import models
from .base import (STATUS_COASTED, STATUS_NONE, STATUS_RESET, STATUS_UPDATED, Solution, caller_stacklevel,
                   check_flag, check_sequence, epoch_range, options_of, register, usable_doppler, usable_measurements,
                   warn_unusable)
from .consistency import covariance_inflation, residual_variance_factor
from .models import EkfConfig
from .noise import (HeuristicNoise, NoiseModel, checked_noise, default_noise, describe_noise, noise_output,
                    resolve_noise, switched_on, switched_on_warned, warn_no_filter_settings, warn_noise)
from .smoother import lag_horizon, rts_smooth


def compensated_pseudorange(pr_m: np.ndarray, vc_m: np.ndarray) -> np.ndarray:
    """The one place the innovation compensation enters: ``z = pr + v^c`` [m], so ``v + v^c = z - h``."""
    return pr_m + vc_m


def coarse_available(sequence: Sequence, coarse_clock_m: np.ndarray | None = None) -> np.ndarray:
    """(T,) bool: epochs whose coarse fix can (re-)initialise the filter (position and clock finite); the clock
    from ``coarse_clock_m`` (T, C) [m] where given (``coarse_clocks``), else the sequence's."""
    clock = sequence.coarse_clock_m if coarse_clock_m is None else coarse_clock_m
    return np.isfinite(sequence.coarse_ecef_m).all(-1) & np.isfinite(clock[:, 0])


def coarse_clocks(sequence: Sequence, usable: np.ndarray, owner: str) -> np.ndarray:
    """(T, C) coarse receiver clock and ISBs [m]: ``coarse_clock_m``, and at an epoch with a coarse position but no
    coarse clock, the one its ``usable`` (T, N) pseudoranges give at that position (``models.pseudorange_clock_m``).

    Where no usable satellite gives one, a warning naming ``owner`` and ``coarse_clock_m`` says the epoch cannot
    (re)start the filter. Finite coarse clocks are kept as they are.
    """
    clock = np.array(sequence.coarse_clock_m, float)
    missing = np.isfinite(sequence.coarse_ecef_m).all(-1) & ~np.isfinite(clock[:, 0])
    n_sys = len(sequence.systems)
    for k in np.flatnonzero(missing):
        clock[k] = models.pseudorange_clock_m(sequence.pr_m[k], sequence.sat_pos_ecef_m[k], sequence.system_index[k],
                                              usable[k], sequence.coarse_ecef_m[k], n_sys)
    left = missing & ~np.isfinite(clock[:, 0])
    if left.any():
        warnings.warn(f"{owner}: coarse_clock_m of {sequence.name!r} is NaN at {int(left.sum())} epochs with a coarse "
                      f"position and no usable pseudorange to take a clock from (first at epoch "
                      f"{int(np.argmax(left))}): they cannot (re)start the filter; give finite coarse clocks "
                      f"(lfgnss.build_sequence does)", UserWarning, stacklevel=caller_stacklevel())
    return clock


def config_of(noise: NoiseModel | str | os.PathLike | None) -> EkfConfig:
    """The EkfConfig a learned model was trained with (its file's ``ekf_config``), else the defaults
    (``models.stored_ekf_config``); a warning names the settings this version does not know.

    ``noise`` may be a model file's path or a bundled model's name (``"hk-tst-2019"``), read as ``noise=`` is
    (``estimators.noise.resolve_noise``); anything else without a model file's metadata (None, a function, a
    hand-set noise model) gets the defaults, ``EkfConfig()``.
    """
    if isinstance(noise, (str, os.PathLike)):
        noise = resolve_noise(noise, "estimators.config_of")
    stored = (getattr(noise, "metadata", None) or {}).get("ekf_config")
    unknown = sorted(set(stored or {}) - {f.name for f in fields(EkfConfig)})
    if unknown:
        warnings.warn(f"estimators/ekf.py: the model file's filter settings {unknown} are unknown "
                      f"to this version of lfgnss and ignored: the model runs in a filter other than its own "
                      f"(update lfgnss)", stacklevel=caller_stacklevel())
    return models.stored_ekf_config(stored)


def smoothed_name(base: str, smooth: bool, smooth_lag_s: float) -> str:
    """Backend label of a run as ``python -m lfgnss.solve`` names its files: ``ekf``, ``ekf-rts``, ``ekf-rts-lag2s``."""
    if not smooth:
        return base
    return base + "-rts" + (f"-lag{smooth_lag_s:g}s" if math.isfinite(smooth_lag_s) else "")


def config_changes(config: EkfConfig) -> str:
    """``EkfConfig(...)`` with only the settings that differ from the defaults (``EkfConfig()`` when none do)."""
    default = EkfConfig()
    changed = ", ".join(f"{f.name}={getattr(config, f.name)!r}" for f in fields(EkfConfig)
                        if getattr(config, f.name) != getattr(default, f.name))
    return f"EkfConfig({changed})"


def _given(_x: np.ndarray, value: np.ndarray) -> np.ndarray:
    """HJacobian/Hx for filterpy: H and h already evaluated at the prior state filterpy passes in."""
    return value


@functools.cache
def extended_kalman_filter() -> type:
    """filterpy's ``ExtendedKalmanFilter`` with an accurate ``S^-1`` (``NumpyInverseEkf``), imported on first use:
    filterpy.kalman's package pulls scipy.stats, half a second that ``import estimators`` (the command line's --help
    and its errors, the graph and least-squares back ends) need not pay. An EKF imports it when built, so that timing
    a solve does not count it."""
    from filterpy.kalman import ExtendedKalmanFilter

    class NumpyInverseEkf(ExtendedKalmanFilter):
        """filterpy's EKF; ``update`` is filterpy's (``K = P H^T S^-1``, Joseph form) with ``S^-1`` from numpy.

        filterpy takes ``S^-1`` from ``scipy.linalg.inv``, whose inverse of an ill-conditioned S is far off where
        numpy's (LU with a solve) and a Cholesky solve are not: at a reset's P0 (1e4 m^2) beside R = 1e-4 m^2,
        |S S^-1 - I| = 1.8 and a 13 m error on a simulated drive, 0.27 m at 1e-3 m^2, 6 mm at 0.01 m^2 (a network's
        default floor) against ``learning.torch_ekf``'s Cholesky solve, which numpy's inverse agrees with. It is also
        faster here than scipy's (and than a Cholesky solve through scipy, which runs BLAS threads).
        """

        def update(self, z, HJacobian, Hx, R, args=(), hx_args=()):
            H = HJacobian(self.x, *args)
            PHT = self.P @ H.T
            self.S = H @ PHT + R
            self.SI = np.linalg.inv(self.S)
            self.K = PHT @ self.SI
            self.y = z - Hx(self.x, *hx_args)
            self.x = self.x + self.K @ self.y
            I_KH = self._I - self.K @ H
            self.P = I_KH @ self.P @ I_KH.T + self.K @ R @ self.K.T
            self._log_likelihood = self._likelihood = self._mahalanobis = None
            self.z = np.array(z, copy=True)
            self.x_post, self.P_post = self.x.copy(), self.P.copy()

    return NumpyInverseEkf


class LfgnssEkf:
    """EKF with per-satellite noise ``R`` and innovation compensation ``v^c`` from a noise model.

    Parameters
    ----------
    noise : NoiseModel, str or Path
        ``noise(sequence) -> (r_m2, vc_m)``, each (T, N); a learned model (``learning.export.load_model``, or the
        path of its file, read with it) or ``HeuristicNoise``, which None means here (the plain EKF).
        ``create("ekf")`` gives the bundled model. An R above ``estimators.noise.R_OFF_M2`` (1e12 m^2; 1e30 or inf, say)
        switches the satellite off: its pseudorange and Doppler are left out as if masked (``switched_on``).
    config : EkfConfig
        Process noise, initial covariance, gate and reset settings; default: those the noise model
        was trained with (``config_of``), else ``EkfConfig()``.
    name : str, optional
        Backend label written into the Solution; default the backend's name, with ``smooth`` as the command line
        names the run's files (``smoothed_name``: ``ekf-rts``, ``ekf-rts-lag2s``). The default is ``ekf`` with
        ``noise=None`` too, where the hand-set ``HeuristicNoise`` runs: ``PlainEkf()`` (or ``name="plain-ekf"``)
        labels that run as the plain EKF.
    use_compensation : bool
        Add ``v^c`` to the innovation (False: ignore the model's ``v^c``).
    smooth : bool
        Post-process the forward run with the Rauch-Tung-Striebel smoother (``estimators.smoother``): each
        epoch then uses the epochs after it too, up to the next re-initialisation. Gates, resets and
        statuses are the forward filter's; ``info["filtered_state"]`` keeps its states. Every Solution's
        ``info["smooth"]`` and ``info["smooth_lag_s"]`` (0 for the forward filter) say which it is.
    smooth_lag_s : float
        With ``smooth``: use only the epochs up to this many seconds later (a fixed-lag smoother, whose
        estimate of an epoch is ready that much later); ``inf``: the whole run. Without ``smooth`` only 0
        (the forward filter, which a zero lag is) or ``inf``; another lag is a ValueError, as ``--smooth-lag``
        without ``--smooth``.
    progress : bool
        Show a tqdm bar over the epochs on a terminal (``python -m lfgnss.solve`` does, unless ``--quiet``).
    inflate_cov : bool
        Multiply the reported position covariance by ``estimators.consistency.covariance_inflation`` (>= 1: how far
        the pseudoranges' residuals at the filtered position exceed the noise model's R, over the last seconds),
        so the sds are closer to the errors in a street canyon; ``info["cov_inflation"]`` holds the factor and
        ``info["cov"]`` the filter's own covariance. False: the formal covariance (docs/sd_consistency.md).
    """

    #: The backend's name, the start of ``name`` (``smoothed_name``).
    default_name = "ekf"
    #: Whether an online model's run ends with the warnings on its R (``warn_noise``); off only where an online model
    #: runs this filter to make its R for another estimator, which judges that R under its own name.
    _judges_noise = True

    def __init__(self, noise: NoiseModel | str | os.PathLike | None = None, config: EkfConfig | None = None,
                 name: str | None = None, use_compensation: bool = True, smooth: bool = False,
                 smooth_lag_s: float = math.inf, progress: bool = False, inflate_cov: bool = True) -> None:
        owner = type(self).__name__
        smooth = check_flag(smooth, "smooth", owner)
        use_compensation = check_flag(use_compensation, "use_compensation", owner)
        progress = check_flag(progress, "progress", owner)
        self.inflate_cov = check_flag(inflate_cov, "inflate_cov", owner)
        if name is not None and not isinstance(name, str):
            raise TypeError(f"{owner}: name must be a string, got {type(name).__name__}")
        if isinstance(smooth_lag_s, bool) or not isinstance(smooth_lag_s, numbers.Real):
            raise TypeError(f"{type(self).__name__}: smooth_lag_s must be a number of seconds, got {smooth_lag_s!r}")
        if not smooth_lag_s >= 0:
            raise ValueError(f"{type(self).__name__}: smooth_lag_s must be >= 0, got {smooth_lag_s}")
        if not smooth and 0 < smooth_lag_s < math.inf:
            raise ValueError(f"{type(self).__name__}: smooth_lag_s={float(smooth_lag_s):g} needs smooth=True (without "
                             f"it the forward filter runs, whose lag is 0)")
        if config is not None and not isinstance(config, EkfConfig):
            raise TypeError(f"{type(self).__name__}: config must be an estimators.EkfConfig (EkfConfig(**settings) "
                            f"for a dict), got {type(config).__name__}")
        noise = resolve_noise(noise, type(self).__name__)
        self.noise = HeuristicNoise() if noise is None else noise
        if config is None:
            warn_no_filter_settings(self.noise, owner, "it runs in the default EkfConfig",
                                    "config=estimators.config_of(model) (or say config=EkfConfig())")
        self.config = config_of(self.noise) if config is None else config
        self.smooth = smooth
        self.smooth_lag_s = float(smooth_lag_s)
        self.name = smoothed_name(self.default_name, smooth, self.smooth_lag_s) if name is None else name
        self.use_compensation = use_compensation
        self.progress = progress
        extended_kalman_filter()

    def __repr__(self) -> str:
        """The settings: name, noise model, config changes from the defaults, and options off their defaults."""
        parts = [f"name={self.name!r}", f"noise={describe_noise(self.noise)}", f"config={config_changes(self.config)}"]
        parts += ["use_compensation=False"] if not self.use_compensation else []
        if self.smooth:
            parts += ["smooth=True"] + ([f"smooth_lag_s={self.smooth_lag_s:g}"] if math.isfinite(self.smooth_lag_s)
                                        else [])
        parts += ["progress=True"] if self.progress else []
        parts += ["inflate_cov=False"] if not self.inflate_cov else []
        return f"{type(self).__name__}({', '.join(parts)})"

    def noise_arrays(self, sequence: Sequence, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(r_m2, vc_m), each (T, N), from the noise model, checked on the usable slots."""
        return self._checked(sequence, usable, *noise_output(type(self).__name__, self.noise(sequence), self.noise))

    def _checked(self, sequence: Sequence, usable: np.ndarray, r: object, vc: object
                 ) -> tuple[np.ndarray, np.ndarray]:
        """``(r, vc)`` with positive finite R and finite v^c on the usable slots (v^c 0 without compensation)."""
        r, vc = checked_noise(type(self).__name__, sequence.name, usable, r,
                              vc if self.use_compensation else np.zeros(np.shape(r)), self.noise)
        return r, vc

    def solve(self, sequence: Sequence) -> Solution:
        """Filter every epoch of ``sequence``; one Solution row per epoch (positions [m], covariances [m^2])."""
        sequence = check_sequence(sequence, type(self).__name__)
        cfg = self.config
        n_sys = len(sequence.systems)
        t_len, _ = sequence.mask.shape
        n = models.n_states(n_sys)
        time = np.array(sequence.time_gps_s, float)      # a copy: the Solution must not share the Sequence's
        dt_all = np.diff(time)
        if np.any(~(dt_all > 0)):
            k = int(np.nonzero(~(dt_all > 0))[0][0]) + 1
            raise ValueError(f"{type(self).__name__}: epoch times of {sequence.name!r} do not increase at epoch {k}")

        usable, doppler_ok = usable_measurements(sequence), usable_doppler(sequence)
        warn_unusable(sequence, usable, type(self).__name__, doppler_ok if cfg.doppler_sigma_m_s > 0 else None)
        pr_all = np.where(usable, sequence.pr_m, 0.0)
        online = bool(getattr(self.noise, "online", False))
        if online:
            features = self.noise.features(sequence)
            usable_before_noise = usable.copy()      # ask_noise switches slots off epoch by epoch
            r_all, vc_all = np.ones(usable.shape), np.zeros(usable.shape)
            r_noise = np.ones(usable.shape)          # every epoch asks (ask_noise) before anything reads it
        else:
            r_all, vc_all = self.noise_arrays(sequence, usable)
            r_noise = r_all.copy()
            usable = switched_on_warned(type(self).__name__, sequence, usable, r_all)
            vc_all = np.where(usable, vc_all, 0.0)
        z_all = compensated_pseudorange(pr_all, vc_all)
        glonass = models.glonass_slots(sequence.system_index, sequence.systems)
        r_factor = models.pseudorange_variance_factor(glonass, cfg)
        r_all = np.where(usable, r_all * r_factor, 1.0)
        doppler_ok = usable & doppler_ok if cfg.doppler_sigma_m_s > 0 else np.zeros_like(usable)
        prr_all = np.where(doppler_ok, sequence.prr_m_s, 0.0)
        satvel_all = sequence.sat_vel_ecef_m_s
        r_doppler_all = models.used_doppler_variance_m2_s2(sequence.cn0_dbhz, doppler_ok, cfg, type(self).__name__,
                                                           sequence.name)
        sat_all = sequence.sat_pos_ecef_m
        sys_all = sequence.system_index
        coarse_clock = coarse_clocks(sequence, usable, type(self).__name__)
        coarse_ok = coarse_available(sequence, coarse_clock)
        coarse_judges = coarse_ok & models.fix_can_judge(usable, sys_all, n_sys, cfg)
        p0 = models.initial_covariance(n_sys, cfg)
        q1, q2, q3 = models.process_noise_coefficients(n_sys, cfg)
        a = models.transition_generator(n_sys)
        eye = np.eye(n)
        cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

        ekf = extended_kalman_filter()(dim_x=n, dim_z=1)
        state = np.full((t_len, n), np.nan)
        cov = np.full((t_len, n, n), np.nan)
        kept = t_len if self.smooth else 0           # priors and transitions: only the RTS smoother reads them
        prior = np.full((kept, n), np.nan)
        prior_cov = np.full((kept, n, n), np.nan)
        steps = np.full((kept, n, n), np.nan)
        status = np.full(t_len, STATUS_NONE, dtype=np.int8)
        n_used = np.zeros(t_len, dtype=np.int32)
        n_gated = np.zeros(t_len, dtype=np.int32)
        n_doppler = np.zeros(t_len, dtype=np.int32)
        clock_realigned = np.zeros(t_len, dtype=bool)
        clock_known = np.zeros(n_sys, dtype=bool)     # each constellation's clock term measured since the (re)start
        drift_found = np.zeros(1, dtype=bool)         # the last (re)start took its drift from the Dopplers
        reference_seen = (usable & (sys_all == 0)).any(axis=1)      # systems[0] holds coarse_clock's first column
        gate_sigma = cfg.gate_sigma
        started = False
        still = models.stationary_epochs(prr_all, doppler_ok, sat_all, satvel_all, sequence.coarse_ecef_m,
                                         r_doppler_all, cfg)
        zupt_r = np.full(3, (cfg.zupt_sigma_m_s or 0.0) ** 2)

        def normalised(v: np.ndarray, H: np.ndarray, r: np.ndarray) -> np.ndarray:
            return np.abs(v) / np.sqrt(np.einsum("ij,jk,ik->i", H, ekf.P, H) + r)    # |v| / sqrt(diag(H P^- H^T + R))

        def keep_mask(t: np.ndarray) -> np.ndarray:
            return t <= gate_sigma if gate_sigma > 0 else np.ones(t.size, bool)

        def gate(k: int, idx: np.ndarray, jdx: np.ndarray) -> tuple:
            """(h, H, z, r, keep) of the pseudoranges ``idx`` and of the Dopplers ``jdx`` at the current prior."""
            h, H = models.measurement(ekf.x, sat_all[k, idx], sys_all[k, idx])
            z, r = z_all[k, idx], r_all[k, idx]
            t = normalised(z - h, H, r)
            g, G = models.doppler_measurement(ekf.x, sat_all[k, jdx], satvel_all[k, jdx])
            y, rd = prr_all[k, jdx], r_doppler_all[k, jdx]
            return ((h, H, z, r * models.huber_scale(t, cfg.huber_k), keep_mask(t)),
                    (g, G, y, rd, keep_mask(normalised(y - g, G, rd))))

        def update(k: int, gated: tuple) -> None:
            """Joseph-form update with the kept measurements (and a standstill's zero velocity); records n_used,
            n_doppler and n_gated of epoch k."""
            blocks = []
            for j, (h, H, z, r, keep) in enumerate(gated):
                used = int(keep.sum())
                if j == 0:
                    n_gated[k] = keep.size - used
                if used < cfg.min_sats_for_update:
                    used = 0
                (n_used if j == 0 else n_doppler)[k] = used
                if used:
                    blocks.append((h[keep], H[keep], z[keep], r[keep]))
            if still[k]:
                blocks.append(models.zero_velocity_measurement(ekf.x) + (np.zeros(3), zupt_r))
            if blocks:
                h, H, z, r = (np.concatenate(part) for part in zip(*blocks))
                try:
                    ekf.update(z, _given, _given, R=np.diag(r), args=(H,), hx_args=(h,))
                    # an S numerically singular but not exactly inverts to garbage, and so would the state:
                    # |S S^-1 - I| tells (at a reset on a simulated drive: 1e-11 for R = 1 m^2, 6e-6 for 1e-6 m^2,
                    # 0.07 for 1e-10 m^2; 1e-12 m^2 is exactly singular to numpy). A coarse test: just above 1e-10
                    # m^2 it passes while the first fix is up to 0.5 m off (1.2 cm at 1e-8, 0.15 mm at 1e-6)
                    check = ekf.S @ ekf.SI
                    check.flat[::len(r) + 1] -= 1.0
                    singular = not np.abs(check).max() <= 0.05
                except np.linalg.LinAlgError:
                    singular = True
                if singular:
                    raise ValueError(f"{type(self).__name__}: the update at epoch {k} of {sequence.name!r} is "
                                     f"numerically singular (its smallest R is {r.min():.3g} m^2): R must be a "
                                     f"pseudorange variance in m^2, not near 0")

        def ask_noise(k: int, idx: np.ndarray, prior_x: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
            """Epoch k's R and v^c from an online noise model, given the prior state (None: no prior); returns the
            epoch's pseudorange and Doppler slots left switched on (``switched_on``)."""
            innovation = np.zeros(usable.shape[1])
            if prior_x is not None:
                innovation[idx] = models.prior_innovation_m(prior_x, sat_all[k, idx], sys_all[k, idx], pr_all[k, idx])
            r, vc = self._checked(sequence, usable[k], *noise_output(type(self).__name__, self.noise.predict(
                features[k], sequence.mask[k], innovation_feature(innovation)), self.noise))
            r_noise[k] = r
            on = switched_on(usable[k], r)
            if not np.array_equal(on, usable[k]):       # as if masked out: redo what the epoch's slots decided
                usable[k], doppler_ok[k] = on, doppler_ok[k] & on
                coarse_judges[k] = coarse_ok[k] & models.fix_can_judge(on, sys_all[k], n_sys, cfg)
                row = slice(k, k + 1)
                still[k] = models.stationary_epochs(prr_all[row], doppler_ok[row], sat_all[row], satvel_all[row],
                                                    sequence.coarse_ecef_m[row], r_doppler_all[row], cfg)[0]
            r_all[k] = np.where(usable[k], r * r_factor[k], 1.0)
            vc_all[k] = np.where(usable[k], vc, 0.0)
            z_all[k] = compensated_pseudorange(pr_all[k], vc_all[k])
            return np.flatnonzero(usable[k]), np.flatnonzero(doppler_ok[k])

        def mostly_gated(gated: tuple, idx: np.ndarray) -> bool:
            return idx.size - int(gated[0][-1].sum()) > cfg.reset_gated_fraction * idx.size

        def reset(k: int, idx: np.ndarray, jdx: np.ndarray) -> None:
            drift, drift_found[0] = models.coarse_drift(prr_all[k], doppler_ok[k], sat_all[k], satvel_all[k],
                                                        sequence.coarse_ecef_m[k])
            x0 = models.initial_state(sequence.coarse_ecef_m[k], coarse_clock[k], float(drift))
            known = np.concatenate([[np.any(sys_all[k, idx] == 0)], np.isfinite(coarse_clock[k, 1:n_sys])])
            x0, clock_known[:] = models.first_sight_clocks(x0, known, pr_all[k, idx], sat_all[k, idx],
                                                           sys_all[k, idx])
            ekf.x, ekf.P = x0, p0.copy()
            update(k, gate(k, idx, jdx))
            if gate_sigma > 0:
                # P0's wide gate lets outliers in: drop satellites whose post-fit residual exceeds
                # gate_sigma sqrt(r) and update the reset prior again without them.
                h, _ = models.measurement(ekf.x, sat_all[k, idx], sys_all[k, idx])
                ok = np.abs(z_all[k, idx] - h) <= gate_sigma * np.sqrt(r_all[k, idx])
                if 0 < ok.sum() < idx.size:
                    ekf.x, ekf.P = x0, p0.copy()
                    update(k, gate(k, idx[ok], jdx))
                    n_gated[k] += idx.size - int(ok.sum())
            status[k] = STATUS_RESET

        for k in epoch_range(0, t_len, self.progress, self.name):
            dt = dt_all[k - 1] if k > 0 else 0.0
            idx = np.flatnonzero(usable[k])
            jdx = np.flatnonzero(doppler_ok[k])
            if dt > cfg.max_gap_s:
                started = False     # the state is stale: restart at the first coarse fix from here on, as at the start
            if not started:
                if online:
                    idx, jdx = ask_noise(k, idx, None)
                if not coarse_ok[k]:
                    continue
                reset(k, idx, jdx)
                started = True
            else:
                if status[k - 1] == STATUS_RESET and not drift_found[0] and reference_seen[k - 1:k + 1].all():
                    # a start without a Doppler drift: the second epoch takes it from the two coarse clocks
                    drift = models.coarse_clock_drift_m_s(coarse_clock[k - 1, 0], coarse_clock[k, 0], dt)
                    if np.isfinite(drift):
                        x = ekf.x.copy()
                        x[models.DRIFT] = drift
                        ekf.x = x
                if dt not in cache:
                    cache[dt] = (eye + dt * a, q1 * dt + q2 * dt ** 2 + q3 * dt ** 3)
                ekf.F, ekf.Q = cache[dt]
                if cfg.q_vel_up_m2_s3 is not None:
                    ekf.Q = ekf.Q + models.vertical_noise_increment(dt, ekf.x[:3], n_sys, cfg)
                ekf.predict()
                if kept:
                    steps[k] = ekf.F
                ekf.x, clock_known[:] = models.first_sight_clocks(ekf.x, clock_known, pr_all[k, idx],
                                                                  sat_all[k, idx], sys_all[k, idx])
                if online:
                    idx, jdx = ask_noise(k, idx, ekf.x)
                gated = gate(k, idx, jdx)
                inconsistent = False
                if (gate_sigma > 0 and idx.size >= cfg.reset_min_sats
                        and status[k - 1] != STATUS_RESET and mostly_gated(gated, idx)):
                    # Most satellites disagree with the prior by a clock-jump-sized median: realign the
                    # clock; reset if that does not help. A smaller median is street-canyon multipath:
                    # the update goes on with the kept satellites (the coarse fix is usually worse).
                    shift = models.lower_median(gated[0][2] - gated[0][0])
                    if abs(shift) >= cfg.clock_jump_min_m:
                        before = ekf.x
                        ekf.x = models.realign_clock(ekf.x, shift)
                        regated = gate(k, idx, jdx)
                        inconsistent = mostly_gated(regated, idx)
                        if inconsistent and not coarse_ok[k]:
                            ekf.x, inconsistent = before, False     # no fix to reset to: the prior goes on
                        else:
                            gated, clock_realigned[k] = regated, True
                if kept:
                    prior[k], prior_cov[k] = ekf.x, ekf.P
                if inconsistent:
                    reset(k, idx, jdx)      # not (just) the clock: the state is inconsistent with the data
                else:
                    update(k, gated)
                    status[k] = STATUS_UPDATED if n_used[k] + n_doppler[k] or still[k] else STATUS_COASTED
                    if (coarse_judges[k]
                            and np.linalg.norm(ekf.x[:3] - sequence.coarse_ecef_m[k]) > cfg.reset_distance_m):
                        reset(k, idx, jdx)  # diverged from the coarse fix
            state[k] = ekf.x
            cov[k] = ekf.P

        if online and self._judges_noise:
            warn_noise(type(self).__name__, sequence, usable_before_noise, usable, r_noise)
        info = {"n_gated": n_gated, "n_usable": usable.sum(1), "n_doppler": n_doppler, "stationary": still,
                "clock_realigned": clock_realigned, "config": cfg, "filtered_state": state, "r_m2": r_all,
                "noise_r_m2": r_noise,
                "vc_m": vc_all, "smooth": self.smooth, "smooth_lag_s": self.smooth_lag_s if self.smooth else 0.0}
        # From the forward run for the smoother too: the factor stays causal, as the filter's sds are.
        info["residual_factor"] = residual_variance_factor(sequence, state[:, models.POS], r_all, usable)
        inflation = (covariance_inflation(time, info["residual_factor"]) if self.inflate_cov else np.ones(t_len))
        info["cov_inflation"] = inflation
        if self.smooth:
            horizon = lag_horizon(time, self.smooth_lag_s) if math.isfinite(self.smooth_lag_s) else None
            state, cov = rts_smooth(state, cov, prior, prior_cov, steps, status == STATUS_RESET, horizon)
        return Solution(backend=self.name, time_gps_s=time, pos_ecef_m=state[:, models.POS].copy(),
                        cov_ecef_m2=cov[:, models.POS, models.POS] * inflation[:, None, None],
                        clock_m=state[:, models.CLOCK].copy(),
                        n_used=n_used, status=status, vel_ecef_m_s=state[:, models.VEL].copy(),
                        info=info | {"state": state, "cov": cov})


@register("ekf")
@options_of(LfgnssEkf)
def create_lfgnss_ekf(noise: NoiseModel | str | os.PathLike | None = None, **options) -> LfgnssEkf:
    """``create("ekf")``: the LF-GNSS EKF with ``noise`` (a model or its file), by default the bundled model."""
    return LfgnssEkf(noise=default_noise() if noise is None else noise, **options)


@register("plain-ekf")
class PlainEkf(LfgnssEkf):
    """The baseline: the same EKF, gate and resets with hand-set ``HeuristicNoise`` R and no v^c."""

    default_name = "plain-ekf"

    def __init__(self, noise: HeuristicNoise | None = None, config: EkfConfig | None = None,
                 name: str | None = None, smooth: bool = False, smooth_lag_s: float = math.inf,
                 progress: bool = False, inflate_cov: bool = True) -> None:
        super().__init__(noise=HeuristicNoise() if noise is None else noise, config=config, name=name,
                         use_compensation=False, smooth=smooth, smooth_lag_s=smooth_lag_s, progress=progress,
                         inflate_cov=inflate_cov)
        if isinstance(getattr(self.noise, "metadata", None), dict):
            # its R in its own filter under the baseline's name: a learned run labelled plain in tables and files
            raise TypeError(f"PlainEkf: noise {describe_noise(self.noise)} is a learned model; the plain EKF is the "
                            f"baseline with hand-set noise (HeuristicNoise, FixedNoise or your own function): use "
                            f"create('ekf', noise=...) for a learned model")


__all__ = ["config_of", "config_changes", "smoothed_name", "LfgnssEkf", "create_lfgnss_ekf", "PlainEkf",
           "compensated_pseudorange", "usable_measurements", "coarse_available", "coarse_clocks"]
