"""State layout, motion model and pseudorange model shared by every filter of lfgnss.

The numpy plug-in (``estimators.ekf``) and the batched torch filter (``learning.torch_ekf``) both
build their matrices from the functions here, so the two cannot drift apart.

State layout, ``n = 8 + (C - 1)`` for ``C`` constellations::

    x = [p_x, p_y, p_z,      # receiver position, ECEF [m]
         v_x, v_y, v_z,      # receiver velocity, ECEF [m/s]
         b,                  # receiver clock of systems[0], times c [m]
         d,                  # receiver clock drift, times c [m/s]
         isb_1 .. isb_{C-1}] # inter-system bias of systems[1:] relative to systems[0] [m]

Motion model (constant velocity; clock as phase + frequency; ISBs as random walks)::

    x_k = F(dt) x_{k-1} + w,   w ~ N(0, Q(dt))

    F(dt) = I + dt * A,   A[p, v] = I_3,  A[b, d] = 1

Process noise from per-second (spectral) densities, exact for white noise on the derivatives::

    Q_pp = q_pos dt + q_vel dt^3 / 3,  Q_pv = q_vel dt^2 / 2,  Q_vv = q_vel dt
    Q_bb = q_clock dt + q_drift dt^3 / 3,  Q_bd = q_drift dt^2 / 2,  Q_dd = q_drift dt
    Q_isb = q_isb dt

so ``Q(dt) = Q1 dt + Q2 dt^2 + Q3 dt^3`` with constant matrices (``process_noise_coefficients``);
the torch filter uses the same coefficients. With a vertical density ``q_up`` other than ``q_vel`` (a car
changes height slowly), the velocity's white-noise density is ``q_vel I + (q_up - q_vel) u u^T`` with ``u`` the
local up at the prior position, and ``vertical_noise_increment`` adds the difference to ``Q(dt)``.

Measurement model of satellite ``i`` of constellation ``s_i`` (pseudorange corrected for satellite
clock and atmosphere, see ``lfgnss.sequence.Sequence``)::

    h_i(x) = rho(sat_i, p) + b + isb_{s_i}     (isb_0 = 0)
    rho(s, p) = |s - p| + omega_e / c (s_x p_y - s_y p_x)     (lfgnss.corrections.geometric_range_m)
    H_i = [-e_i^T, 0 0 0, 1, 0, onehot(s_i)]   e_i = (s - p) / |s - p|

The Sagnac derivative (~1e-6 relative) is neglected in ``H`` but the Sagnac term is in ``h``.

Doppler model of satellite ``i`` (pseudorange rate ``-lambda D`` corrected for the satellite clock
drift, ``Sequence.prr_m_s``), used where ``Sequence.prr_mask``::

    g_i(x) = e_i . (v_sat_i - v) + d + omega_e / c (vs_x p_y + s_x v_y - vs_y p_x - s_y v_x)
    G_i = [0 0 0, -e_i^T, 0, 1, 0 ...]     (position derivative ~1e-4 /s, neglected)

with variance ``doppler_variance_m2_s2`` (``doppler_sigma_m_s^2``, growing below ``doppler_cn0_ref_dbhz``):
Doppler measures velocity and clock drift directly, so the constant-velocity model no longer has to infer
them from differences of noisy pseudoranges.

Zero-velocity update (``zupt_sigma_m_s``): at an epoch whose Dopplers say the receiver stands still
(``stationary_epochs``), the pseudo-measurement ``0 = v + n``, ``n ~ N(0, zupt_sigma^2 I_3)``::

    H_zupt = [0_3, I_3, 0 ...]

A car waiting at a light stands exactly still, which the white-acceleration model cannot know: without it the
velocity wanders at a few tenths of a m/s and the position with it, driven by the street's multipath.
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Union

import numpy as np

if TYPE_CHECKING:
    import torch

ArrayOrTensor = Union[np.ndarray, "torch.Tensor"]

from lfgnss.corrections import geometric_range_m, line_of_sight
from lfgnss.dop import satellites_per_system
from lfgnss.velocity import DopplerVelocity, cn0_doppler_variance_m2_s2, doppler_design, doppler_velocity

#: Indices into the state vector.
POS = slice(0, 3)
VEL = slice(3, 6)
CLOCK = 6
DRIFT = 7
ISB0 = 8  # first ISB (systems[1]); ISB of systems[s] is at ISB0 + s - 1


def n_states(n_systems: int) -> int:
    """Length of the state vector for ``n_systems`` constellations: 8 + (n_systems - 1)."""
    if n_systems < 1:
        raise ValueError(f"estimators/models.py: need at least one constellation, got {n_systems}")
    return 8 + n_systems - 1


def clock_column(system_index: np.ndarray) -> np.ndarray:
    """State column of the ISB of each measurement's constellation, (N,) int; -1 for ``systems[0]``.

    ``systems[0]`` has no ISB (its clock is the reference); padded slots (-1) also give -1.
    """
    s = np.asarray(system_index)
    return np.where(s >= 1, ISB0 + s - 1, -1)


@dataclass(frozen=True)
class EkfConfig:
    """Tuning of the EKF (numpy plug-in and torch filter alike). Units: metres and seconds.

    Attributes
    ----------
    p0_pos_m2, p0_vel_m2_s2, p0_clock_m2, p0_drift_m2_s2, p0_isb_m2 : float
        Initial (and reset) covariance diagonal. Position/clock/ISB follow the notes (code: 100^2).
        Velocity and drift start at zero, so their variances are set for a car, (10 m/s)^2, and for a
        receiver oscillator, (100 m/s)^2 (TCXO ~3e-7), rather than the code's 1: with a drift of tens
        of m/s the first predictions would otherwise fail the gate for every satellite.
    q_pos_m2_s : float
        Position random walk on top of the constant-velocity model [m^2/s] (notes, code: 1e-4).
    q_vel_m2_s3 : float
        Velocity random walk (white acceleration) density [(m/s)^2/s]; a car in a city 1-4.
    q_vel_up_m2_s3 : float or None
        The same density along the local vertical [(m/s)^2/s]; None: ``q_vel_m2_s3`` (isotropic). A car's
        height changes slowly, so a smaller value keeps street-canyon errors out of the height (the factor
        graph's ``accel_psd_enu_m2_s3`` does the same).
    q_clock_m2_s, q_drift_m2_s3, q_isb_m2_s : float
        Clock phase, clock drift and ISB random-walk densities [m^2/s], [(m/s)^2/s], [m^2/s].
        Lenient on purpose (receivers with steered or poor oscillators); tune on validation data.
        ``q_clock_m2_s = 100`` (10 m per sqrt(s)) was chosen with the plain EKF on the train and
        validation splits (3D RMSE train / val, hk; berlin; static): 1: 18.2 / 7.4; 41.3 / 22.8;
        3.2 / 2.9 m. 30: 18.4 / 7.6; 30.8 / 10.6; 3.5 / 2.9. 100: 18.8 / 7.6; 24.2 / 10.9; 3.5 / 2.9.
        300: 28.1 / 7.7; 19.5 / 12.3; 3.5 / 2.9. A stiff clock takes the common part of street-canyon
        errors as a clock error once and keeps it; in berlin-pp it then leaked into height for minutes
        (the factor graph, with a free clock per epoch, never had this problem).
    gate_sigma : float
        Per-satellite innovation gate: satellite ``i`` is dropped when
        ``|v_i + vc_i| > gate_sigma * sqrt(S_ii)``, ``S = H P^- H^T + R``. 0 disables the gate.
    reset_gated_fraction : float
        If at least ``reset_min_sats`` satellites are usable, more than this fraction of them is gated
        and their median innovation is at least ``clock_jump_min_m``, the receiver clock jumped: the
        clock is realigned (``realign_clock``; no coarse fix needed); if that fraction still fails the gate,
        re-initialise from the coarse fix (at an epoch without one, the prior goes on unrealigned). Values >= 1
        disable both. Not applied in the epoch right after a reset.
    reset_min_sats : int
        Minimum number of usable satellites before ``reset_gated_fraction`` applies.
    reset_distance_m : float
        After the update, if ``|p - p_coarse| > reset_distance_m`` the state is re-initialised from
        the coarse fix (divergence reset). ``inf`` disables it. 300 m, not 100 m: urban coarse fixes are
        often 100+ m off (p95 104-138 m on the benchmark sets), and resetting to them cost 2.5x on the
        static validation split (19.0 m vs 7.8 m 3D RMSE).
    reset_min_redundancy : int
        The divergence reset trusts a coarse fix only where the epoch has at least this many usable satellites
        more than a snapshot fix's unknowns (3 + a clock per constellation present; ``snapshot_redundancy``).
        With fewer, nothing shows that the fix, not the filter, is wrong: on hk-tst-2019 (12:51:23 and :26 GPST,
        no truth there) 6- and 5-satellite GPS + BeiDou fixes 360 m below and 250 m beside the street pulled the
        filter to them. 0 restores the reset to any fix.
    max_gap_s : float
        A time step longer than this [s] restarts the filter from the first coarse fix at or after it; the epochs
        before that fix get no position, as before a run's first fix (predicted across a long gap the state is one
        the data cannot mend: a day's gap left it 52 km off, twelve days an update too ill-conditioned to compute).
    min_sats_for_update : int
        Fewer ungated satellites than this: predict only (coast). Applies to pseudoranges and Dopplers
        separately.
    clock_jump_min_m : float
        When most satellites fail the gate, the prior's clock is realigned to the median innovation
        (``realign_clock``) only if that median is at least this large [m]: receiver clock jumps are
        microseconds to milliseconds (300 m to 3e5 m), while a median innovation of tens of metres in a
        street canyon is multipath, which realigning the clock would absorb into the clock state.
    doppler_sigma_m_s : float
        Standard deviation of a Doppler pseudorange rate [m/s]; 0 ignores Doppler. Dopplers pass the
        same ``gate_sigma`` gate; they never trigger the clock realignment or a reset.
    doppler_cn0_ref_dbhz : float or None
        With a value, the Doppler variance grows as the signal weakens:
        ``doppler_sigma_m_s^2 (1 + 10^((doppler_cn0_ref_dbhz - C/N0) / 5))``, twice the base at this C/N0 [dB-Hz]
        and tenfold in sigma per 10 dB below it (the C/N0 law of ``HeuristicNoise``'s pseudorange variance).
        None: every Doppler has ``doppler_sigma_m_s``.
    huber_k : float or None
        With a value, a soft robust update on top of the gate: a kept pseudorange whose normalised innovation
        ``t = |v_i + vc_i| / sqrt(S_ii)`` exceeds ``huber_k`` has its variance scaled by ``t / huber_k`` (Huber's
        weight ``min(1, huber_k / t)``, one step, weights taken as constants). None: the hard gate alone.
    zupt_sigma_m_s : float or None
        With a value, a zero-velocity update of this sigma per axis [m/s] at every epoch ``stationary_epochs``
        finds standing still (needs Dopplers, ``doppler_sigma_m_s > 0``). None: no zero-velocity update.
    zupt_max_speed_m_s : float
        The standstill test's speed bound [m/s]: the epoch's Doppler velocity must be slower than this, as well as
        consistent with zero at 99 % (``stationary_epochs``).
    glonass_sigma_factor : float
        Factor on the pseudorange sigma of every GLONASS satellite: its R (the noise model's) is multiplied by the
        square (``pseudorange_variance_factor``). RTKLIB's single-point solution uses 1.5 (``EFACT_GLO``, pntpos.c):
        broadcast GLONASS orbits and clocks, and the inter-frequency biases of FDMA signals, leave metres that the
        other constellations' broadcast errors do not. 1 keeps R as the noise model gives it.
    """

    p0_pos_m2: float = 100.0 ** 2
    p0_vel_m2_s2: float = 10.0 ** 2
    p0_clock_m2: float = 100.0 ** 2
    p0_drift_m2_s2: float = 100.0 ** 2
    p0_isb_m2: float = 100.0 ** 2
    q_pos_m2_s: float = 1.0e-4
    q_vel_m2_s3: float = 2.0
    q_vel_up_m2_s3: float | None = None
    q_clock_m2_s: float = 100.0
    q_drift_m2_s3: float = 0.1
    q_isb_m2_s: float = 1.0e-3
    gate_sigma: float = 3.0
    reset_gated_fraction: float = 0.5
    reset_min_sats: int = 4
    reset_distance_m: float = 300.0
    reset_min_redundancy: int = 2
    max_gap_s: float = 30.0
    min_sats_for_update: int = 1
    doppler_sigma_m_s: float = 0.5
    clock_jump_min_m: float = 1000.0
    doppler_cn0_ref_dbhz: float | None = None
    huber_k: float | None = None
    zupt_sigma_m_s: float | None = None
    zupt_max_speed_m_s: float = 0.5
    glonass_sigma_factor: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("q_vel_up_m2_s3", "doppler_cn0_ref_dbhz", "huber_k", "zupt_sigma_m_s"):  # None allowed
                continue
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ValueError(f"estimators/models.py: EkfConfig.{f.name} must be a number, got {value!r}")
        for name in ("p0_pos_m2", "p0_vel_m2_s2", "p0_clock_m2", "p0_drift_m2_s2", "p0_isb_m2", "q_pos_m2_s",
                     "q_vel_m2_s3", "q_clock_m2_s", "q_drift_m2_s3", "q_isb_m2_s", "doppler_sigma_m_s",
                     "zupt_max_speed_m_s"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"estimators/models.py: EkfConfig.{name} must be finite, got {getattr(self, name)}")
        for name in ("reset_min_sats", "min_sats_for_update", "reset_min_redundancy"):
            if not float(getattr(self, name)).is_integer():
                raise ValueError(f"estimators/models.py: EkfConfig.{name} must be a whole number, "
                                 f"got {getattr(self, name)!r}")
            object.__setattr__(self, name, int(getattr(self, name)))    # 4.0 (a TOML float) is stored as 4
        if not self.reset_gated_fraction >= 0:
            raise ValueError(f"estimators/models.py: EkfConfig.reset_gated_fraction must be >= 0 (>= 1 disables), "
                             f"got {self.reset_gated_fraction}")
        for name in ("p0_pos_m2", "p0_vel_m2_s2", "p0_clock_m2", "p0_drift_m2_s2", "p0_isb_m2"):
            if not getattr(self, name) > 0:
                raise ValueError(f"estimators/models.py: EkfConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("q_pos_m2_s", "q_vel_m2_s3", "q_clock_m2_s", "q_drift_m2_s3", "q_isb_m2_s", "gate_sigma",
                     "reset_distance_m", "max_gap_s", "doppler_sigma_m_s", "clock_jump_min_m", "zupt_max_speed_m_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"estimators/models.py: EkfConfig.{name} must be >= 0, got {getattr(self, name)}")
        up = self.q_vel_up_m2_s3
        if up is not None and (isinstance(up, bool) or not isinstance(up, numbers.Real) or not 0 <= up < np.inf):
            raise ValueError(f"estimators/models.py: EkfConfig.q_vel_up_m2_s3 must be a finite number >= 0 "
                             f"[(m/s)^2/s] or None, got {up!r}")
        ref = self.doppler_cn0_ref_dbhz
        if ref is not None and (isinstance(ref, bool) or not isinstance(ref, (int, float)) or not np.isfinite(ref)):
            raise ValueError(f"estimators/models.py: EkfConfig.doppler_cn0_ref_dbhz must be a number of dB-Hz or None, "
                             f"got {ref!r}")
        k = self.huber_k
        if k is not None and (isinstance(k, bool) or not isinstance(k, (int, float)) or not k > 0 or k == np.inf):
            raise ValueError(f"estimators/models.py: EkfConfig.huber_k must be a positive number or None, got {k!r}")
        z = self.zupt_sigma_m_s
        if z is not None and (isinstance(z, bool) or not isinstance(z, (int, float)) or not z > 0 or z == np.inf):
            raise ValueError(f"estimators/models.py: EkfConfig.zupt_sigma_m_s must be a positive number of m/s or "
                             f"None, got {z!r}")
        if z is not None and not self.doppler_sigma_m_s > 0:
            raise ValueError("estimators/models.py: EkfConfig.zupt_sigma_m_s needs Dopplers to detect a standstill; "
                             "doppler_sigma_m_s is 0")
        if not 1e-3 <= self.glonass_sigma_factor <= 1e3:         # its square multiplies R: keep it a variance
            raise ValueError(f"estimators/models.py: EkfConfig.glonass_sigma_factor must be a sigma factor in [0.001, "
                             f"1000] (RTKLIB: 1.5; to leave GLONASS out, select the other systems), got "
                             f"{self.glonass_sigma_factor!r}")
        if self.min_sats_for_update < 1:
            raise ValueError("estimators/models.py: EkfConfig.min_sats_for_update must be >= 1")


def stored_ekf_config(stored: dict | None) -> EkfConfig:
    """The EkfConfig a model file's ``ekf_config`` describes (keys this version does not know are left out).

    A file older than Doppler support has no ``doppler_sigma_m_s``; it gets 0 (pseudoranges only), the filter it
    was trained in. No ``ekf_config`` at all: the defaults.
    """
    if not stored:
        return EkfConfig()
    known = {f.name for f in fields(EkfConfig)}
    return EkfConfig(**{"doppler_sigma_m_s": 0.0, **{k: v for k, v in stored.items() if k in known}})


#: 99 % point of the chi-square distribution with 3 degrees of freedom (scipy.stats.chi2.ppf(0.99, 3)).
CHI2_3DOF_99 = 11.344866730144373


def stationary_epochs(prr_m_s: np.ndarray, doppler_ok: np.ndarray, sat_pos_ecef_m: np.ndarray,
                      sat_vel_ecef_m_s: np.ndarray, rcv_ecef_m: np.ndarray, variance_m2_s2: np.ndarray,
                      config: EkfConfig) -> np.ndarray:
    """(T,) bool: epochs where the receiver stands still, by its Dopplers; all False without ``zupt_sigma_m_s``.

    The epoch's robust Doppler velocity (``lfgnss.velocity.doppler_velocity`` with the filter's Doppler variances,
    at ``rcv_ecef_m`` [m], e.g. the coarse fix) must pass ``still_fixes``. Shapes: pseudorange rates ``prr_m_s`` and
    ``doppler_ok`` (T, N); satellite positions [m] and velocities [m/s] (T, N, 3); ``rcv_ecef_m`` (T, 3); Doppler
    variances ``variance_m2_s2`` [(m/s)^2] (T, N).

    Resolution: in simulation the chi-square test alone tells a 1.5 m/s creep from a standstill, not a 0.5 m/s one;
    the speed bound does the rest. A creep under ``zupt_max_speed_m_s`` (e.g. 0.3 m/s in a jam) is often taken as
    still and held at zero velocity while the pseudoranges keep the position: lower the bound where traffic creeps.
    """
    ok = np.asarray(doppler_ok, bool)
    if config.zupt_sigma_m_s is None or not ok.any():
        return np.zeros(ok.shape[0], bool)
    fix = doppler_velocity(np.where(ok, prr_m_s, 0.0), ok, sat_pos_ecef_m, sat_vel_ecef_m_s, rcv_ecef_m,
                           sigma_m_s=np.sqrt(np.where(ok, variance_m2_s2, 1.0)))
    return still_fixes(fix, config.zupt_max_speed_m_s)


def still_fixes(fix: DopplerVelocity, max_speed_m_s: float) -> np.ndarray:
    """(T,) bool: Doppler velocity fixes ``v`` slower than ``max_speed_m_s`` [m/s] and consistent with zero at 99 %.

    Consistent: ``v^T C^-1 v < CHI2_3DOF_99``, ``C`` the fix's covariance [(m/s)^2].
    """
    v = np.nan_to_num(fix.vel_ecef_m_s)
    cov = np.where(fix.ok[:, None, None], fix.cov_m2_s2, np.eye(3))
    distance2 = np.einsum("ti,ti->t", v, np.linalg.solve(cov, v[..., None])[..., 0])
    return fix.ok & (np.linalg.norm(v, axis=1) < max_speed_m_s) & (distance2 < CHI2_3DOF_99)


def zero_velocity_measurement(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted velocity [m/s] (3,) and its Jacobian (3, n) at state ``x``: the zero-velocity update's model."""
    H = np.zeros((3, x.shape[0]))
    H[:, VEL] = np.eye(3)
    return x[VEL].copy(), H


def huber_scale(t: ArrayOrTensor, huber_k: float | None) -> ArrayOrTensor:
    """Variance factor ``max(1, t / huber_k)`` of a measurement with normalised innovation ``|t|``; 1 when None."""
    if huber_k is None:
        return t * 0 + 1
    return (abs(t) / huber_k).clip(min=1.0)


def initial_covariance(n_systems: int, config: EkfConfig) -> np.ndarray:
    """P0 (n, n), diagonal, from ``config``."""
    n = n_states(n_systems)
    d = np.empty(n)
    d[POS] = config.p0_pos_m2
    d[VEL] = config.p0_vel_m2_s2
    d[CLOCK] = config.p0_clock_m2
    d[DRIFT] = config.p0_drift_m2_s2
    d[ISB0:] = config.p0_isb_m2
    return np.diag(d)


def initial_state(coarse_ecef_m: np.ndarray, coarse_clock_m: np.ndarray, drift_m_s: float = 0.0) -> np.ndarray:
    """State (n,) from a coarse fix: position, zero velocity, clock, drift, ISBs (NaN ISB -> 0).

    Parameters
    ----------
    coarse_ecef_m : (3,) position [m]
    coarse_clock_m : (C,) receiver clock of systems[0] then ISBs of systems[1:] [m]
    drift_m_s : receiver clock drift [m/s] (``coarse_drift``)
    """
    c = np.asarray(coarse_clock_m, float)
    x = np.zeros(n_states(c.shape[0]))
    x[POS] = coarse_ecef_m
    x[CLOCK] = c[0]
    x[DRIFT] = drift_m_s
    x[ISB0:] = np.nan_to_num(c[1:], nan=0.0)
    return x


#: Spread [m/s] of an epoch's Doppler rates about the drift at zero velocity that ``coarse_drift`` allows: the
#: receiver's speed along the lines of sight (180 km/h).
COARSE_DRIFT_SPREAD_M_S = 50.0


def coarse_drift(prr_m_s: np.ndarray, doppler_ok: np.ndarray, sat_pos_ecef_m: np.ndarray,
                 sat_vel_ecef_m_s: np.ndarray, rcv_ecef_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((...,) receiver clock drift [m/s], (...,) bool: found) from each epoch's Dopplers at ``rcv_ecef_m`` and zero
    velocity; drift 0 and found False where they do not agree on one.

    The lower median of ``prr - a`` (``doppler_design``'s offsets) over the epoch's ``doppler_ok`` satellites: the
    drift give or take the receiver's speed. A (re)start takes it as the coarse fix gives the clock: from zero, a drift
    beyond 3 sd of ``p0_drift_m2_s2`` (300 m/s, a 1 ppm oscillator) failed every Doppler's gate and, unobservable
    from one epoch's pseudoranges, pushed them out of the gate too. Taken only from 3 Dopplers or more, more than
    half of them within ``COARSE_DRIFT_SPREAD_M_S`` of it: a drift fitted to an outlier would keep every later
    Doppler out of the gate, where one started from 0 lets the gate drop the outlier. Shapes: ``prr_m_s``,
    ``doppler_ok`` (..., N); satellites (..., N, 3) [m], [m/s]; ``rcv_ecef_m`` (..., 3) [m].
    """
    ok = np.array(doppler_ok, dtype=bool)                         # a copy: the caller's mask stays as it is
    with np.errstate(invalid="ignore", divide="ignore"):          # unused slots or receivers at the origin
        a, _ = doppler_design(sat_pos_ecef_m, sat_vel_ecef_m_s, rcv_ecef_m)
        v = np.where(ok, np.asarray(prr_m_s, float) - a, np.nan)
    ok &= np.isfinite(v)
    n = ok.sum(-1)
    if v.shape[-1] == 0:                                         # no satellite slot at all
        return np.zeros(n.shape), np.zeros(n.shape, bool)
    lower = np.take_along_axis(np.sort(np.where(ok, v, np.inf), axis=-1),   # unusable slots last
                               np.maximum(n - 1, 0)[..., None] // 2, axis=-1)
    near = (ok & (np.abs(np.where(ok, v, 0.0) - lower) <= COARSE_DRIFT_SPREAD_M_S)).sum(-1)
    found = (n >= 3) & (2 * near > n)
    return np.where(found, lower[..., 0], 0.0), found


#: Largest clock drift [m/s] taken from two coarse fixes' clocks (10 ppm): a receiver clock jump between them
#: (u-blox: whole milliseconds, 3e5 m) is no drift, and stays for ``realign_clock``.
MAX_COARSE_CLOCK_DRIFT_M_S = 3000.0


def coarse_clock_drift_m_s(clock_before_m: np.ndarray, clock_m: np.ndarray, dt_s: np.ndarray) -> np.ndarray:
    """(...,) receiver clock drift [m/s] from two consecutive coarse fixes' clocks [m] ``dt_s`` [s] apart, NaN where
    either is not finite or the drift exceeds ``MAX_COARSE_CLOCK_DRIFT_M_S``.

    The second epoch after a (re)start without a Doppler drift (``coarse_drift`` found none: no Dopplers, or too few)
    takes it so: from 0 with P0's 100 m/s, a drift beyond about 300 m/s (a 1 ppm oscillator) failed the gate at 1 Hz
    and 65 % of a simulated drive's epochs coasted."""
    with np.errstate(invalid="ignore", divide="ignore"):
        drift = (np.asarray(clock_m, float) - np.asarray(clock_before_m, float)) / np.asarray(dt_s, float)
    return np.where(np.isfinite(drift) & (np.abs(drift) <= MAX_COARSE_CLOCK_DRIFT_M_S), drift, np.nan)


def pseudorange_clock_m(pr_m: np.ndarray, sat_pos_ecef_m: np.ndarray, system_index: np.ndarray,
                        usable: np.ndarray, rcv_ecef_m: np.ndarray, n_systems: int) -> np.ndarray:
    """(C,) receiver clock of systems[0] and ISBs of systems[1:] [m] from one epoch's pseudoranges at ``rcv_ecef_m``.

    Each constellation's median of ``pr - rho(sat, rcv)`` over its ``usable`` satellites (``pr_m``,
    ``system_index``, ``usable``: (N,); ``sat_pos_ecef_m``: (N, 3) [m]); where systems[0] has none, the first
    constellation present takes the clock (its ISB 0), as ``lfgnss.spp`` does. NaN for a constellation without a
    usable satellite, and all NaN where there is none.
    """
    sys = np.asarray(system_index)
    ok = np.asarray(usable, bool) & (sys >= 0) & (sys < n_systems)
    out = np.full(n_systems, np.nan)
    if not ok.any():
        return out
    raw = np.asarray(pr_m, float)[ok] - geometric_range_m(np.asarray(sat_pos_ecef_m, float)[ok],
                                                          np.asarray(rcv_ecef_m, float))
    median = np.array([np.median(raw[sys[ok] == j]) if np.any(sys[ok] == j) else np.nan for j in range(n_systems)])
    clock = median[np.flatnonzero(np.isfinite(median))[0]]
    out[1:] = median[1:] - clock
    out[0] = clock
    return out


def transition_generator(n_systems: int) -> np.ndarray:
    """A (n, n) with ``F(dt) = I + dt A``: position integrates velocity, clock integrates drift."""
    a = np.zeros((n_states(n_systems),) * 2)
    a[0, 3] = a[1, 4] = a[2, 5] = 1.0
    a[CLOCK, DRIFT] = 1.0
    return a


def transition(dt_s: float, n_systems: int) -> np.ndarray:
    """F(dt) (n, n) of the constant-velocity / clock-drift model."""
    return np.eye(n_states(n_systems)) + dt_s * transition_generator(n_systems)


def process_noise_coefficients(n_systems: int, config: EkfConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Q1, Q2, Q3), each (n, n), with ``Q(dt) = Q1 dt + Q2 dt^2 + Q3 dt^3`` (see module docstring)."""
    n = n_states(n_systems)
    q1, q2, q3 = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    for k in range(3):
        p, v = k, 3 + k
        q1[p, p] = config.q_pos_m2_s
        q1[v, v] = config.q_vel_m2_s3
        q2[p, v] = q2[v, p] = config.q_vel_m2_s3 / 2.0
        q3[p, p] = config.q_vel_m2_s3 / 3.0
    q1[CLOCK, CLOCK] = config.q_clock_m2_s
    q1[DRIFT, DRIFT] = config.q_drift_m2_s3
    q2[CLOCK, DRIFT] = q2[DRIFT, CLOCK] = config.q_drift_m2_s3 / 2.0
    q3[CLOCK, CLOCK] = config.q_drift_m2_s3 / 3.0
    for j in range(ISB0, n):
        q1[j, j] = config.q_isb_m2_s
    return q1, q2, q3


def process_noise(dt_s: float, n_systems: int, config: EkfConfig, pos_ecef_m: np.ndarray | None = None
                  ) -> np.ndarray:
    """Q(dt) (n, n) [m^2, m^2/s, (m/s)^2]; at ``pos_ecef_m`` [m] when the vertical density differs."""
    q1, q2, q3 = process_noise_coefficients(n_systems, config)
    q = q1 * dt_s + q2 * dt_s ** 2 + q3 * dt_s ** 3
    if config.q_vel_up_m2_s3 is not None and pos_ecef_m is not None:
        q = q + vertical_noise_increment(dt_s, pos_ecef_m, n_systems, config)
    return q


def vertical_noise_increment(dt_s: float, pos_ecef_m: np.ndarray, n_systems: int, config: EkfConfig) -> np.ndarray:
    """Q(dt) (n, n) to add for ``q_vel_up_m2_s3`` at ``pos_ecef_m`` [m]; zeros when it is None.

    ``d [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) u u^T`` on (position, velocity), ``d = q_vel_up - q_vel``, ``u``
    the geocentric up ``p / |p|`` (within 0.2 deg of the ellipsoid normal, which is immaterial for a noise
    density). A position near the Earth's centre (no fix yet) adds nothing.
    """
    q = np.zeros((n_states(n_systems),) * 2)
    norm = float(np.linalg.norm(pos_ecef_m))
    if config.q_vel_up_m2_s3 is None or norm < 1.0:
        return q
    u = np.asarray(pos_ecef_m, float) / norm
    k = np.array([[dt_s ** 3 / 3.0, dt_s ** 2 / 2.0], [dt_s ** 2 / 2.0, dt_s]])
    uu = u[:, None] * u[None, :]
    kron = (k[:, None, :, None] * uu[None, :, None, :]).reshape(6, 6)    # np.kron(k, uu), without its 40 us a call
    q[:6, :6] = (config.q_vel_up_m2_s3 - config.q_vel_m2_s3) * kron
    return q


def snapshot_redundancy(usable: np.ndarray, system_index: np.ndarray, n_systems: int) -> np.ndarray:
    """(...,) int: usable satellites (``usable``, ``system_index``: (..., N)) beyond a snapshot fix's unknowns,
    3 position coordinates and a clock per constellation present; negative where the fix is underdetermined."""
    present = satellites_per_system(system_index, usable, n_systems) > 0
    return usable.sum(-1) - 3 - present.sum(-1)


def fix_can_judge(usable: np.ndarray, system_index: np.ndarray, n_systems: int, config: EkfConfig) -> np.ndarray:
    """(...,) bool: whether the snapshot fix of these satellites (``usable``, ``system_index``: (..., N)) is redundant
    enough (``config.reset_min_redundancy``) for the divergence reset to trust it over the filter."""
    return snapshot_redundancy(usable, system_index, n_systems) >= config.reset_min_redundancy


def lower_median(values: np.ndarray) -> float:
    """Median that picks the lower middle element for even counts (as ``torch.nanmedian`` does)."""
    v = np.sort(np.asarray(values, float))
    return float(v[(v.size - 1) // 2])


def first_sight_clocks(x: np.ndarray, known: np.ndarray, pr_m: np.ndarray, sat_pos_ecef_m: np.ndarray,
                       system_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(state, known): the prior with the clock terms of each constellation first seen since the (re)start set from
    its satellites, and ``known`` (C,) bool (the constellations measured since then) updated.

    A constellation absent from the coarse fix the filter started from has ISB 0 with P0's sigma (100 m), and where
    systems[0] was absent the clock is another constellation's: one that appeared later with an offset of some
    hundred metres (receivers differ) was gated out for the rest of the run. Its offset is the lower median of its
    satellites' ``pr - h`` less that of the known constellations' satellites (so a receiver clock jump at the same
    epoch, common to all, stays for ``realign_clock``; with no known satellite, the whole median): a new systems[j]
    moves ISB j, a new systems[0] moves the clock and every ISB the other way. The raw pseudoranges ``pr_m`` [m] (N,)
    are used, not the compensated ones (an online model's v^c is asked for at the prior this corrects). The
    covariance is kept: an offset never measured has no correlation to lose."""
    s = np.asarray(system_index)
    present = np.unique(s[s >= 0]).tolist()
    new = [j for j in present if not known[j]]
    if not new:
        return x, known
    h, _ = measurement(x, sat_pos_ecef_m, s)
    v = np.asarray(pr_m, float) - h
    old = np.isin(s, np.flatnonzero(known))
    ref = lower_median(v[old]) if old.any() else 0.0
    x, known = np.array(x, float), np.array(known, bool)
    shift = {j: lower_median(v[s == j]) - ref for j in new}
    if 0 in shift:
        x[CLOCK] += shift[0]
        x[ISB0:] -= shift[0]
    for j in new:
        if j > 0:
            x[ISB0 + j - 1] += shift[j]
        known[j] = True
    return x, known


def realign_clock(x: np.ndarray, shift_m: float) -> np.ndarray:
    """Prior state with the receiver clock moved by ``shift_m`` [m], the (lower) median innovation.

    A receiver clock jump (u-blox receivers steer their clock in whole milliseconds, ~3e5 m) shifts
    every pseudorange alike, so the median innovation estimates it while position, velocity, drift
    and ISBs keep their values. The covariance is kept: widening the clock variance would open the
    gate to every outlier, and to states that are wrong in more than the clock, which must fail the
    gate again and reset.
    """
    x = x.copy()
    x[CLOCK] += shift_m
    return x


def measurement(x: np.ndarray, sat_pos_ecef_m: np.ndarray, system_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Predicted pseudoranges and their Jacobian at state ``x``.

    Parameters
    ----------
    x : (n,) state
    sat_pos_ecef_m : (N, 3) satellite positions at transmission [m]
    system_index : (N,) int, constellation of each satellite (index into ``systems``)

    Returns
    -------
    h : (N,) ``rho(sat, p) + b + isb[s]`` [m] (Sagnac included)
    H : (N, n) ``dh/dx``; position columns ``-e^T`` (Sagnac derivative neglected)
    """
    p = x[POS]
    d = sat_pos_ecef_m - p
    los = d / np.linalg.norm(d, axis=1, keepdims=True)
    col = clock_column(system_index)
    n_sat = sat_pos_ecef_m.shape[0]
    H = np.zeros((n_sat, x.shape[0]))
    H[:, POS] = -los
    H[:, CLOCK] = 1.0
    rows = np.nonzero(col >= 0)[0]
    H[rows, col[rows]] = 1.0
    h = geometric_range_m(sat_pos_ecef_m, p) + x[CLOCK] + x[np.maximum(col, 0)] * (col >= 0)
    return h, H


def prior_innovation_m(x: np.ndarray, sat_pos_ecef_m: np.ndarray, system_index: np.ndarray, pr_m: np.ndarray
                       ) -> np.ndarray:
    """(N,) innovations ``pr - h(x)`` of a prior state minus their lower median [m] (clock errors cancel)."""
    if pr_m.size == 0:
        return np.zeros(0)
    v = pr_m - measurement(x, sat_pos_ecef_m, system_index)[0]
    return v - lower_median(v)


def glonass_slots(system_index: np.ndarray, systems: tuple[str, ...]) -> np.ndarray:
    """(T, N) bool: the slots whose satellite is GLONASS (``system_index`` into ``systems``; -1 padded)."""
    if "R" not in systems:
        return np.zeros(np.shape(system_index), bool)
    return np.asarray(system_index) == systems.index("R")


def pseudorange_variance_factor(glonass: ArrayOrTensor, config: EkfConfig) -> ArrayOrTensor:
    """Factor on each slot's pseudorange variance R from its GLONASS flag (numpy bool array or torch bool tensor):
    ``config.glonass_sigma_factor`` squared on GLONASS slots, 1 elsewhere (float64)."""
    flags = glonass.double() if hasattr(glonass, "double") else np.asarray(glonass, float)   # torch, else numpy
    return 1.0 + (float(config.glonass_sigma_factor) ** 2 - 1.0) * flags


def doppler_variance_m2_s2(cn0_dbhz: ArrayOrTensor, config: EkfConfig) -> ArrayOrTensor:
    """Variance of each Doppler pseudorange rate [(m/s)^2] at C/N0 ``cn0_dbhz`` [dB-Hz] (numpy array or torch tensor).

    ``doppler_sigma_m_s^2 (1 + 10^((doppler_cn0_ref_dbhz - C/N0) / 5))``; without a reference C/N0 the constant
    ``doppler_sigma_m_s^2``, shaped like ``cn0_dbhz`` whatever its values (NaN included).
    """
    if config.doppler_cn0_ref_dbhz is None:
        base = config.doppler_sigma_m_s ** 2
        if hasattr(cn0_dbhz, "new_full"):                  # a torch tensor (this module does not import torch)
            return cn0_dbhz.new_full(cn0_dbhz.shape, base)
        return np.full(np.shape(cn0_dbhz), base)
    return cn0_doppler_variance_m2_s2(cn0_dbhz, config.doppler_sigma_m_s, config.doppler_cn0_ref_dbhz)


def used_doppler_variance_m2_s2(cn0_dbhz: np.ndarray, used: np.ndarray, config: EkfConfig, owner: str,
                                sequence_name: str) -> np.ndarray:
    """(T, N) ``doppler_variance_m2_s2`` of the ``used`` Dopplers [(m/s)^2] (other slots at a neutral 45 dB-Hz).

    ValueError naming ``owner`` and the first epoch where a used Doppler lacks the finite C/N0 that
    ``doppler_cn0_ref_dbhz`` needs (the constant sigma reads no C/N0).
    """
    if config.doppler_cn0_ref_dbhz is not None and not np.all(np.isfinite(cn0_dbhz[used])):
        k = int(np.argwhere(used & ~np.isfinite(cn0_dbhz))[0, 0])
        raise ValueError(f"{owner}: a C/N0-dependent Doppler variance (doppler_cn0_ref_dbhz) needs a finite C/N0 on "
                         f"every Doppler used; {sequence_name!r} has none at epoch {k}")
    return doppler_variance_m2_s2(np.where(used, cn0_dbhz, 45.0), config)


def doppler_measurement(x: np.ndarray, sat_pos_ecef_m: np.ndarray, sat_vel_ecef_m_s: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Predicted pseudorange rates [m/s] (N,) and their Jacobian (N, n) at state ``x`` (see module docstring).

    The model is ``lfgnss.velocity.doppler_design``'s; ``G`` leaves out its Sagnac velocity terms, as ``H`` does.
    """
    a, A = doppler_design(sat_pos_ecef_m, sat_vel_ecef_m_s, x[POS])
    g = a + A @ np.r_[x[VEL], x[DRIFT]]
    G = np.zeros((sat_pos_ecef_m.shape[0], x.shape[0]))
    G[:, VEL] = -line_of_sight(sat_pos_ecef_m, x[POS])
    G[:, DRIFT] = 1.0
    return g, G


__all__ = ["EkfConfig", "n_states", "clock_column", "initial_covariance", "initial_state", "pseudorange_clock_m",
           "transition_generator", "coarse_drift", "coarse_clock_drift_m_s",
           "MAX_COARSE_CLOCK_DRIFT_M_S",
           "transition", "process_noise_coefficients", "process_noise", "vertical_noise_increment", "measurement",
           "doppler_measurement", "doppler_variance_m2_s2", "used_doppler_variance_m2_s2", "prior_innovation_m",
           "lower_median", "first_sight_clocks", "realign_clock", "stationary_epochs", "still_fixes",
           "zero_velocity_measurement", "CHI2_3DOF_99", "COARSE_DRIFT_SPREAD_M_S", "POS", "VEL", "CLOCK", "DRIFT",
           "ISB0"]
