"""The feature packer shared by every estimator and the trainer (LF-GNSS step 2).

Per satellite and epoch: C/N0, elevation, azimuth, coarse pseudorange residual and the DOP
contribution (full minus leave-one-out GDOP, PDOP, HDOP, VDOP). Optional extras are selected by
name, so ablations are configuration only: ``residual_weighted``, the post-fit residual of the
C/N0-elevation-weighted least-squares fix of the epoch (``lfgnss.weighted_fix``), ``code_doppler``, how far
each pseudorange's change since the previous epoch disagrees with its Doppler (changing code multipath),
``cross_street``, how far across the direction of travel each satellite lies (a street canyon blocks those), and
the constellation one-hot ``sys_G`` .... One more input is not packed here because it needs the filter:
``innovation_feature``, each pseudorange's innovation against the filter's prior (``model.innovation``).
"""
from __future__ import annotations

import warnings

import numpy as np

from .constants import SYSTEMS
from .dop import dop_contribution, satellites_per_system
from .errors import LfgnssError
from .frames import ecef_to_lla, enu_rotation
from .measurements import Measurements
from .sequence import DEFAULT_FEATURES, Sequence
from .spp import CoarseFix, SppConfig, _geometry
from . import qc
from .velocity import cn0_doppler_variance_m2_s2, doppler_velocity
from .weighted_fix import cn0_elevation_variance_m2, weighted_least_squares

#: Every feature the packer knows, in a stable order.
AVAILABLE_FEATURES = (DEFAULT_FEATURES + ("residual_weighted", "code_doppler", "cross_street", "track_age", "cn0_std")
                      + tuple(f"sys_{s}" for s in SYSTEMS))

#: Code-Doppler disagreement: larger values are capped here [m]; so is a satellite with no previous epoch.
CODE_DOPPLER_CAP_M = 100.0
#: Epochs further apart than this [s] are not compared (the Doppler integral would be meaningless).
CODE_DOPPLER_MAX_GAP_S = 2.0
#: Slower than this [m/s], the Doppler velocity gives no heading; the last heading is kept.
HEADING_MIN_SPEED_M_S = 1.0
#: ``cross_street`` before the receiver has ever moved: the mean of |sin| over a uniform angle.
CROSS_STREET_UNKNOWN = 2.0 / np.pi
#: Doppler sigma law of the heading fit (``velocity.cn0_doppler_variance_m2_s2``): berlin-pp's train Dopplers
#: at the true velocity (benchmarks/doppler_noise.py), as in learning/configs/berlin.toml. Against equal weights it
#: halves the heading error on the bundled drive's first 180 s (median 9 -> 4 deg; 75th percentile 20 -> 11).
HEADING_DOPPLER_SIGMA_M_S = 0.1
HEADING_DOPPLER_CN0_REF_DBHZ = 45.0


def check_feature_names(names: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The names as a tuple (one name may be given as a str), or a ValueError naming the unknown ones."""
    names = (names,) if isinstance(names, str) else names
    unknown = [n for n in names if n not in AVAILABLE_FEATURES]
    if unknown:
        raise ValueError(f"unknown feature(s) {unknown}; available: {', '.join(AVAILABLE_FEATURES)}")
    return tuple(names)


def _reference_positions(fix: CoarseFix, approx_ecef_m: np.ndarray) -> np.ndarray:
    """(T, 3) the coarse fix, or for epochs without one the last earlier fix [m] (before the first fix: the first).

    Never a later fix after the first: a forward filter's features must not depend on epochs still to come (the
    nearest fix in time did, up to 14 s ahead on hk-tst-2019). Epochs before the first fix start no estimator."""
    ok = np.flatnonzero(fix.ok)
    if ok.size == 0:
        if np.linalg.norm(approx_ecef_m) > 6e6:
            return np.broadcast_to(approx_ecef_m, fix.pos_ecef_m.shape).copy()
        raise LfgnssError("no epoch has a coarse fix and the file has no approximate position; "
                          "nothing to build features from")
    last = np.maximum.accumulate(np.where(fix.ok, np.arange(len(fix.ok)), -1))
    return fix.pos_ecef_m[np.where(last >= 0, last, ok[0])]


def fill_from_nearest_epoch(values: np.ndarray) -> np.ndarray:
    """(T, C) copy with each NaN replaced by its column's last earlier value, else its first later one."""
    values = np.asarray(values, float)
    t = np.arange(values.shape[0])[:, None]
    known = ~np.isnan(values)
    before = np.maximum.accumulate(np.where(known, t, -1), axis=0)
    after = np.minimum.accumulate(np.where(known, t, values.shape[0])[::-1], axis=0)[::-1]
    source = np.clip(np.where(before >= 0, before, after), 0, max(values.shape[0] - 1, 0))
    return np.take_along_axis(values, source, axis=0)


def code_doppler_disagreement_m(time_gps_s: np.ndarray, pr_m: np.ndarray, prr_m_s: np.ndarray,
                                ok: np.ndarray) -> np.ndarray:
    """(T, N) |code change minus Doppler-integrated change| since the previous epoch [m], capped.

    For satellite i between epochs t-1 and t, ``d_i = (pr_i(t) - pr_i(t-1)) - (prr_i(t) + prr_i(t-1)) dt / 2``,
    minus the epoch's median over satellites (receiver clock jumps and the clock drift in the Doppler are
    common to all). The Doppler follows the carrier, so changing code multipath shows here. Where the
    satellite lacks ``ok`` (a usable pseudorange and Doppler) at either epoch, or the epochs are more than
    ``CODE_DOPPLER_MAX_GAP_S`` apart, the value is ``CODE_DOPPLER_CAP_M``: in a city a satellite just
    (re)acquired is suspect (berlin-pp and hk-tst-2019 train + val: 87 % and 43 % of them are off by over
    10 m, against 43 % and 25 % of the others).
    """
    pr = np.where(ok, pr_m, np.nan)
    prr = np.where(ok, prr_m_s, np.nan)
    d = np.full(pr.shape, np.nan)
    dt = np.diff(np.asarray(time_gps_s, float))
    close = (dt > 0) & (dt <= CODE_DOPPLER_MAX_GAP_S)
    d[1:] = np.where(close[:, None], (pr[1:] - pr[:-1]) - 0.5 * (prr[1:] + prr[:-1]) * dt[:, None], np.nan)
    with warnings.catch_warnings():  # epochs where no satellite has a previous one: all-NaN rows
        warnings.simplefilter("ignore", RuntimeWarning)
        d -= np.nanmedian(d, axis=1, keepdims=True)
    return np.where(np.isfinite(d), np.minimum(np.abs(d), CODE_DOPPLER_CAP_M), CODE_DOPPLER_CAP_M)


#: A satellite's track restarts after a gap in its pseudoranges longer than this [s].
TRACK_MAX_GAP_S = 2.0
#: Track ages are capped here [s]; a track already running at the file's first epoch counts as this old.
TRACK_AGE_CAP_S = 60.0
#: C/N0 spread window [s]: the last seconds of the current track.
CN0_STD_WINDOW_S = 5.0


def track_start(time_gps_s: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """(T, N) index of the epoch where each satellite's current continuous track began (-1 where not tracked)."""
    t = np.asarray(time_gps_s, float)
    gap = np.concatenate([[True], ~((np.diff(t) > 0) & (np.diff(t) <= TRACK_MAX_GAP_S))])
    prev = np.vstack([np.zeros((1, tracked.shape[1]), bool), tracked[:-1]])
    begins = tracked & (gap[:, None] | ~prev)
    start = np.maximum.accumulate(np.where(begins, np.arange(len(t))[:, None], -1), axis=0)
    return np.where(tracked, start, -1)


def track_age_s(time_gps_s: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """(T, N) seconds since each satellite's current track began, capped at ``TRACK_AGE_CAP_S`` (0 untracked).

    In a city a satellite just (re)acquired is suspect (``code_doppler_disagreement_m``); the age says how long
    its pseudoranges have been continuous. A track that runs from the first epoch has an unknown age: the cap.
    """
    t = np.asarray(time_gps_s, float)
    start = track_start(t, tracked)
    age = t[:, None] - t[np.maximum(start, 0)]
    age = np.where(start == 0, TRACK_AGE_CAP_S, np.minimum(age, TRACK_AGE_CAP_S))
    return np.where(tracked, age, 0.0)


def cn0_std_dbhz(time_gps_s: np.ndarray, cn0_dbhz: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """(T, N) standard deviation of C/N0 [dB-Hz] over the last ``CN0_STD_WINDOW_S`` of each satellite's track.

    Multipath makes C/N0 fade and recover as the receiver moves; a steady line of sight does not. 0 for a
    track's first epoch and where untracked.
    """
    t = np.asarray(time_gps_s, float)
    start = track_start(t, tracked)
    known = tracked & np.isfinite(cn0_dbhz)                           # a missing C/N0 is left out, not 0 dB-Hz
    x = np.where(known, cn0_dbhz, 0.0)
    zero = np.zeros((1, x.shape[1]))
    s0, s1, s2 = (np.vstack([zero, np.cumsum(v, axis=0)]) for v in (known.astype(float), x, x * x))
    first = np.searchsorted(t, t - CN0_STD_WINDOW_S + 1e-6)          # first epoch inside each epoch's window
    lo = np.maximum(first[:, None], start)                            # ... and inside the current track
    hi = np.arange(len(t))[:, None] + 1
    cols = np.arange(x.shape[1])[None, :]
    n = s0[hi, cols] - s0[lo, cols]
    mean = (s1[hi, cols] - s1[lo, cols]) / np.maximum(n, 1)
    var = (s2[hi, cols] - s2[lo, cols]) / np.maximum(n, 1) - mean * mean
    return np.where(tracked & (n > 1), np.sqrt(np.maximum(var, 0.0)), 0.0)


def heading_rad(vel_ecef_m_s: np.ndarray, ref_ecef_m: np.ndarray,
                min_speed_m_s: float = HEADING_MIN_SPEED_M_S) -> np.ndarray:
    """(T,) direction of travel, clockwise from north [rad], from ECEF velocities (T, 3) [m/s]; NaN if unknown.

    Below ``min_speed_m_s`` (or with no velocity) an epoch keeps the last heading before it; epochs before the
    first motion get the first heading, and NaN is left only if the receiver never moved. The ENU frame is the
    one of ``ref_ecef_m`` (3,): over a city drive of kilometres it turns by hundredths of a degree.
    """
    lat, lon, _ = ecef_to_lla(np.asarray(ref_ecef_m, float))
    enu = np.asarray(vel_ecef_m_s, float) @ enu_rotation(lat, lon).T
    moving = np.hypot(enu[:, 0], enu[:, 1]) >= min_speed_m_s  # False for NaN velocities
    heading = np.where(moving, np.arctan2(enu[:, 0], enu[:, 1]), np.nan)
    return fill_from_nearest_epoch(heading[:, None])[:, 0]


def cross_street(az_rad: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(T, N) |sin(azimuth - heading)|: 0 along the direction of travel, 1 straight across it.

    In a street canyon the street runs along the direction of travel, so a satellite across it is behind the
    buildings of one side unless it is high. Of the pseudoranges below 30 deg on the train + val splits, those
    under 0.3 are off by over 10 m (against the truth) in 42 % (berlin-pp) and 12 % (hk-tst-2019) of cases, those
    over 0.7 in 70 % and 54 % (yet no model gains from it: docs/training/cv-cross-street.md). ``heading`` (T,)
    [rad] is ``heading_rad``'s; where it is NaN the value is ``CROSS_STREET_UNKNOWN``.
    """
    value = np.abs(np.sin(np.asarray(az_rad, float) - np.asarray(heading, float)[:, None]))
    return np.where(np.isfinite(value), value, CROSS_STREET_UNKNOWN)


def innovation_feature(innovation_m: np.ndarray) -> np.ndarray:
    """Network input from prior innovations whose epoch median is removed [m]: ``sign(v) ln(1 + |v|)``.

    The filter's prior is metres off where the coarse fix is tens of metres off, so this separates
    pseudoranges off by over 10 m (against the truth) far better than the coarse ``residual``: area under the
    ROC curve 0.83-0.95 against 0.56-0.60 on berlin-pp train / val, 0.91 against 0.76 on hk-tst-2019 train
    (prior of the plain EKF). The log keeps street-canyon outliers of hundreds of metres in the network's range.
    ``learning.torch_ekf.innovation_feature`` is its torch twin.
    """
    v = np.asarray(innovation_m, float)
    return np.sign(v) * np.log1p(np.abs(v))


def system_median_m(values_m: np.ndarray, mask: np.ndarray, system_index: np.ndarray, n_systems: int) -> np.ndarray:
    """(T, N): each slot's epoch median of ``values_m`` over the masked satellites of its constellation [m]; 0 if none.

    Of pseudorange residuals, that median is the epoch's receiver clock (plus the constellation's ISB).
    """
    values = np.asarray(values_m, float)
    out = np.zeros(values.shape)
    for k in range(n_systems):
        in_sys = mask & (system_index == k)
        if not in_sys.any():
            continue
        with warnings.catch_warnings():  # epochs without a satellite of this system: all-NaN rows
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(np.where(in_sys, values, np.nan), axis=1)
        out = np.where(system_index == k, np.nan_to_num(med)[:, None], out)
    return out


def pack_features(names: tuple[str, ...], *, cn0_dbhz, el_rad, az_rad, residual_m, dpc, system_index,
                  systems: tuple[str, ...], mask, residual_weighted_m=None, code_doppler_m=None,
                  cross_street=None, track_age_s=None, cn0_std_dbhz=None) -> np.ndarray:
    """(T, N, d) raw features by name; zeros in masked slots.

    ``code_doppler`` is ``log10(1 + code_doppler_m)`` (``code_doppler_disagreement_m``): the raw metres are
    heavy-tailed, and the network sees standardised inputs; so is ``track_age``, ``log10(1 + track_age_s)``.
    """
    if "residual_weighted" in names and residual_weighted_m is None:
        raise ValueError("the residual_weighted feature needs residual_weighted_m")
    if "code_doppler" in names and code_doppler_m is None:
        raise ValueError("the code_doppler feature needs code_doppler_m")
    for name, given in (("cross_street", cross_street), ("track_age", track_age_s), ("cn0_std", cn0_std_dbhz)):
        if name in names and given is None:
            raise ValueError(f"the {name} feature needs its values")
    columns = {"cn0": cn0_dbhz, "elevation": el_rad, "azimuth": az_rad, "residual": residual_m,
               "residual_weighted": residual_weighted_m,
               "code_doppler": None if code_doppler_m is None else np.log10(1.0 + code_doppler_m),
               "cross_street": cross_street, "cn0_std": cn0_std_dbhz,
               "track_age": None if track_age_s is None else np.log10(1.0 + track_age_s),
               "dpc_gdop": dpc[..., 0], "dpc_pdop": dpc[..., 1], "dpc_hdop": dpc[..., 2], "dpc_vdop": dpc[..., 3]}
    for letter in SYSTEMS:
        idx = systems.index(letter) if letter in systems else -2
        columns[f"sys_{letter}"] = (system_index == idx).astype(float)
    out = np.stack([np.broadcast_to(columns[n], mask.shape) for n in check_feature_names(names)], axis=-1)
    return np.where(mask[..., None], np.nan_to_num(out), 0.0)


#: Pseudorange rates beyond this are not Doppler measurements [m/s] (satellite ~1 km/s, car, oscillator).
MAX_ABS_PRR_M_S = 1.0e4


def _reference_clock(fix: CoarseFix, system_index: np.ndarray) -> np.ndarray:
    """(T, C) clock of systems[0] and ISBs [m] in every epoch: an ISB unseen in an epoch is the nearest epoch's.

    Where systems[0] has no satellite, spp gives the clock to the first system present (its ISB 0); that
    epoch's clock is brought back to systems[0] with the nearest ISB of that system seen beside systems[0].
    """
    present = satellites_per_system(system_index, fix.used, fix.clock_m.shape[1]) > 0
    own = present[:, 0]
    isb = fill_from_nearest_epoch(np.where(own[:, None], fix.clock_m, np.nan))
    clock_system = np.argmax(present, axis=1)
    shift = np.where(~own & (clock_system > 0), isb[np.arange(len(own)), clock_system], 0.0)
    clock = np.where(own, fix.clock_m[:, 0], fix.clock_m[:, 0] - np.nan_to_num(shift))
    return np.concatenate([clock[:, None], isb[:, 1:]], axis=1)


def build_sequence(meas: Measurements, fix: CoarseFix, *, feature_names: tuple[str, ...] = DEFAULT_FEATURES,
                   name: str = "", truth_ecef_m: np.ndarray | None = None,
                   spp_config: SppConfig = SppConfig()) -> Sequence:
    """Pack measurements and their coarse fix into a Sequence (one slot per satellite of the file).

    Epochs without a coarse fix keep their satellites: geometry comes from the last earlier fix (the first fix
    before it) and the residual from a per-constellation median clock, so the estimators can still use them.
    """
    if not isinstance(meas, Measurements) or not isinstance(fix, CoarseFix):
        raise TypeError(f"lfgnss.build_sequence(meas, fix): expected lfgnss.load's Measurements and lfgnss.spp's "
                        f"CoarseFix, got {type(meas).__name__} and {type(fix).__name__}")
    if fix.used.shape != meas.reason.shape or fix.systems != meas.systems:
        raise ValueError(f"lfgnss.build_sequence: the fix ({fix.used.shape[0]} epochs x {fix.used.shape[1]} "
                         f"satellites, {''.join(fix.systems)}) is not of these measurements ({meas.reason.shape[0]} x "
                         f"{meas.reason.shape[1]}, {''.join(meas.systems)}); use lfgnss.spp(meas)")
    feature_names = check_feature_names(feature_names)
    n_t, n_s = meas.reason.shape
    ref = _reference_positions(fix, meas.obs.approx_ecef_m)
    rng, _, az, el, tropo, iono = _geometry(meas, ref)
    pr_corr = np.nan_to_num(meas.satclock_corrected_pr_m()) - tropo - iono
    sysi = np.broadcast_to(meas.system_index, (n_t, n_s))
    mask = (meas.reason == qc.OK) & (el >= np.radians(spp_config.elevation_mask_deg)) & (sysi >= 0)
    mask &= fix.reason != qc.GROSS_RESIDUAL

    raw_res = np.where(mask, pr_corr - rng, np.nan)
    clock = system_median_m(raw_res, mask, sysi, len(meas.systems))
    residual = np.where(fix.ok[:, None] & fix.used, fix.residual_m, raw_res - clock)
    residual = np.where(mask, np.nan_to_num(residual), 0.0)
    sys_used = np.where(mask, sysi, -1)
    pr_used = np.where(mask, pr_corr, 0.0)
    sat_used = np.where(mask[..., None], meas.sat_pos_ecef_m, 0.0)
    dpc = dop_contribution(el, az, sys_used, mask, len(meas.systems))
    cn0 = np.where(mask, np.nan_to_num(meas.cn0_dbhz), 0.0)
    weighted = None
    if "residual_weighted" in feature_names:  # epochs too thin for the weighted fix keep the coarse residual
        wfix = weighted_least_squares(pr_used, sat_used, sys_used, mask, len(meas.systems), ref,
                                      cn0_elevation_variance_m2(cn0, el))
        weighted = np.where(wfix.ok[:, None] & mask, wfix.residual_m, residual)
    prr = meas.satclock_corrected_prr_m_s()
    prr_mask = mask & np.isfinite(prr) & (np.abs(np.nan_to_num(prr)) < MAX_ABS_PRR_M_S) & (meas.obs.doppler_hz != 0)
    code_doppler = (code_doppler_disagreement_m(meas.time_gps_s, pr_corr, prr, prr_mask)
                    if "code_doppler" in feature_names else None)
    across = None
    if "cross_street" in feature_names:
        sigma = np.sqrt(cn0_doppler_variance_m2_s2(cn0, HEADING_DOPPLER_SIGMA_M_S, HEADING_DOPPLER_CN0_REF_DBHZ))
        vel = doppler_velocity(np.where(prr_mask, prr, 0.0), prr_mask, meas.sat_pos_ecef_m, meas.sat_vel_ecef_m_s,
                               ref, sigma_m_s=sigma)
        across = cross_street(az, heading_rad(vel.vel_ecef_m_s, np.median(ref, axis=0)))
    tracked = np.isfinite(meas.obs.pr_m)
    age = track_age_s(meas.time_gps_s, tracked) if "track_age" in feature_names else None
    spread = cn0_std_dbhz(meas.time_gps_s, meas.cn0_dbhz, tracked) if "cn0_std" in feature_names else None
    feats = pack_features(tuple(feature_names), cn0_dbhz=cn0, el_rad=el, az_rad=az, residual_m=residual, dpc=dpc,
                          system_index=sysi, systems=meas.systems, mask=mask, residual_weighted_m=weighted,
                          code_doppler_m=code_doppler, cross_street=across, track_age_s=age,
                          cn0_std_dbhz=spread)
    coarse_clock = _reference_clock(fix, np.broadcast_to(meas.system_index, fix.used.shape))
    coarse_clock = np.where(fix.ok[:, None], coarse_clock, np.nan)
    truth = np.full((n_t, 3), np.nan) if truth_ecef_m is None else np.asarray(truth_ecef_m, float)
    return Sequence(
        name=name or meas.obs.path, systems=meas.systems, time_gps_s=meas.time_gps_s.copy(),
        sv=np.broadcast_to(meas.sv, (n_t, n_s)).copy(), system_index=sys_used, mask=mask,
        pr_m=pr_used, sat_pos_ecef_m=sat_used,
        cn0_dbhz=cn0, el_rad=np.where(mask, el, 0.0), az_rad=np.where(mask, az, 0.0), features=feats,
        feature_names=tuple(feature_names), coarse_ecef_m=fix.pos_ecef_m.copy(), coarse_clock_m=coarse_clock,
        truth_ecef_m=truth, prr_m_s=np.where(prr_mask, prr, 0.0), prr_mask=prr_mask,
        sat_vel_ecef_m_s=np.where(prr_mask[..., None], meas.sat_vel_ecef_m_s, 0.0))
