"""Observations joined with broadcast satellite states: what the coarse fix and the features need."""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

import numpy as np

from . import qc
from .constants import (BDS_B1I_HZ, GAL_E1_HZ, GLO_L1_BASE_HZ, GLO_L1_STEP_HZ, GPS_L1_HZ, SPEED_OF_LIGHT_M_S,
                        SYSTEMS, unknown_systems)
from .errors import RinexError
from .navigation import Navigation, load_nav
from .observations import Observations
from .rinex import RinexWarning, load_obs

if TYPE_CHECKING:
    import pandas as pd

#: C/N0 assumed for a constellation whose file carries no C/N0 at all [dB-Hz].
ASSUMED_CN0_DBHZ = 40.0


@dataclass(frozen=True)
class Measurements:
    """Pseudoranges with satellite states at transmission time, (T epochs, S satellites).

    ``reason`` holds the coarse quality-control code of every observation (``lfgnss.qc``); checks that
    need the receiver position (elevation mask, gross residuals) are applied by ``lfgnss.spp``.
    """

    obs: Observations
    nav: Navigation
    systems: tuple[str, ...]          # constellations with at least one usable observation, GPS first
    system_index: np.ndarray          # (S,) index into systems (-1: constellation not used)
    sat_pos_ecef_m: np.ndarray        # (T, S, 3) at transmission, ECEF frame of transmission time [m]
    sat_vel_ecef_m_s: np.ndarray      # (T, S, 3) [m/s]
    sat_clock_s: np.ndarray           # (T, S) satellite clock incl. relativistic term [s]
    group_delay_s: np.ndarray         # (T, S) TGD/BGD of the code used [s]
    carrier_hz: np.ndarray            # (S,) carrier frequency of the code used [Hz]
    reason: np.ndarray                # (T, S) int8 qc code
    warnings: tuple[str, ...] = field(default=())
    sat_clock_drift_s_s: np.ndarray | None = None   # (T, S) satellite clock drift [s/s]; None: unknown (zeros)

    @property
    def time_gps_s(self) -> np.ndarray:
        """(T,) epoch times, GPS seconds."""
        return self.obs.time_gps_s

    @property
    def sv(self) -> np.ndarray:
        """(S,) satellite ids."""
        return self.obs.sv

    @property
    def pr_m(self) -> np.ndarray:
        """(T, S) raw pseudoranges [m] (NaN where not observed)."""
        return self.obs.pr_m

    @property
    def cn0_dbhz(self) -> np.ndarray:
        """(T, S) C/N0 [dB-Hz]."""
        return self.obs.cn0_dbhz

    def satclock_corrected_pr_m(self) -> np.ndarray:
        """(T, S) pseudorange plus satellite clock minus group delay [m] (no atmosphere yet)."""
        return self.obs.pr_m + SPEED_OF_LIGHT_M_S * (self.sat_clock_s - self.group_delay_s)

    def satclock_corrected_prr_m_s(self) -> np.ndarray:
        """(T, S) pseudorange rate from Doppler, ``-lambda D``, plus satellite clock drift times c [m/s]."""
        drift = 0.0 if self.sat_clock_drift_s_s is None else self.sat_clock_drift_s_s
        return -SPEED_OF_LIGHT_M_S / self.carrier_hz * self.obs.doppler_hz + SPEED_OF_LIGHT_M_S * drift

    def to_frame(self) -> pd.DataFrame:
        """Tidy table, one row per observed (epoch, satellite), with qc reasons spelt out."""
        import pandas as pd

        t_idx, s_idx = np.nonzero(np.isfinite(self.obs.pr_m))
        return pd.DataFrame({
            "time_gps_s": self.time_gps_s[t_idx], "sv": self.sv[s_idx], "pr_m": self.pr_m[t_idx, s_idx],
            "cn0_dbhz": self.cn0_dbhz[t_idx, s_idx], "doppler_hz": self.obs.doppler_hz[t_idx, s_idx],
            "sat_x_m": self.sat_pos_ecef_m[t_idx, s_idx, 0], "sat_y_m": self.sat_pos_ecef_m[t_idx, s_idx, 1],
            "sat_z_m": self.sat_pos_ecef_m[t_idx, s_idx, 2], "sat_clock_s": self.sat_clock_s[t_idx, s_idx],
            "group_delay_s": self.group_delay_s[t_idx, s_idx],
            "qc": [qc.REASONS[int(r)] for r in self.reason[t_idx, s_idx]],
        })


def carrier_frequency_hz(sv: np.ndarray, nav: Navigation) -> np.ndarray:
    """(S,) carrier of the single-frequency code lfgnss uses for each satellite [Hz]."""
    freq = np.full(len(sv), GPS_L1_HZ)
    letters = np.array([s[0] for s in sv])
    freq[letters == "C"] = BDS_B1I_HZ
    freq[letters == "E"] = GAL_E1_HZ
    glo = np.flatnonzero(letters == "R")
    if glo.size:
        channel = dict(zip(nav.glonass.sv.tolist(), nav.glonass.k.tolist()))
        freq[glo] = [GLO_L1_BASE_HZ + GLO_L1_STEP_HZ * channel.get(sv[i], 0) for i in glo]
    return freq


def _coverage(navigation: Navigation, observations: Observations) -> str:
    """'; ephemerides of ... to ..., observations ...' when the navigation does not cover the epochs."""
    from .time import gps_s_to_datetime64

    toe = np.concatenate([navigation.kepler.toe_gps_s, navigation.glonass.toe_gps_s])
    t = observations.time_gps_s
    if toe.size == 0 or t.size == 0 or (toe.min() <= t[-1] and toe.max() >= t[0]):
        return ""
    day = [str(gps_s_to_datetime64(v).astype("datetime64[s]")).replace("T", " ")
           for v in (toe.min(), toe.max(), t[0], t[-1])]
    return f"; its ephemerides span {day[0]} to {day[1]} GPST, the observations {day[2]} to {day[3]}"


def load(obs: str | Path | Observations, nav: str | Path | Iterable[str | Path] | Navigation, *,
         systems: Iterable[str] | None = None, qc_config: qc.QcConfig = qc.QcConfig(),
         cache: bool = True) -> Measurements:
    """Read observations and broadcast navigation, evaluate satellite states, run coarse QC.

    ``systems`` restricts the constellations (letters G, C, E, R, J, either case); default: all present.
    """
    from .ephemeris import satellite_states

    def is_path(x: object) -> bool:
        return isinstance(x, (str, os.PathLike))

    if not (isinstance(obs, Observations) or is_path(obs)):
        raise TypeError(f"lfgnss.load: obs must be a RINEX observation file (str or Path) or an Observations, "
                        f"got {type(obs).__name__}")
    if not (isinstance(nav, Navigation) or is_path(nav)):
        nav = list(nav) if isinstance(nav, Iterable) else nav
        if not isinstance(nav, list) or not all(is_path(p) for p in nav):
            raise TypeError(f"lfgnss.load: nav must be a RINEX navigation file (str or Path), a list of them or a "
                            f"Navigation, got {type(nav).__name__}")
    systems = None if systems is None else tuple(systems)      # read once: it may be a generator
    unknown = unknown_systems(systems or ())
    if unknown:                                                 # before any file is read
        raise ValueError(f"unknown constellation letter(s) {unknown} in the requested systems; use {''.join(SYSTEMS)}")
    observations = obs if isinstance(obs, Observations) else load_obs(obs, cache=cache)
    navigation = nav if isinstance(nav, Navigation) else load_nav(nav)
    notes = list(observations.warnings) + list(navigation.warnings)
    if "GPS" not in navigation.iono:  # lfgnss.spp then falls back to corrections.KLOBUCHAR_DEFAULT, as RTKLIB does
        note = (f"{', '.join(navigation.sources) or 'navigation'}: no GPS ionosphere coefficients (ION ALPHA/BETA or "
                f"GPSA/GPSB header lines) in the navigation file(s); the Klobuchar ionosphere uses default "
                f"coefficients (RTKLIB's, of 2004-01-01), which can be off by metres")
        notes.append(note)
        warnings.warn(note, RinexWarning, stacklevel=2)
    asked = None if systems is None else {s.upper() for s in systems}
    present = {s[0] for s in observations.sv}
    wanted = tuple(s for s in SYSTEMS if asked is None or s in asked)
    for system in sorted((asked or set()) - present):
        notes.append(f"{observations.path}: no {system} observations (requested)")
        warnings.warn(notes[-1], RinexWarning, stacklevel=2)
    observations = observations.select_systems(wanted)
    if observations.sv.size == 0 and not present:
        raise RinexError(observations.path, "no pseudorange observations of any constellation")
    if observations.sv.size == 0:
        raise RinexError(observations.path, f"no observations of the requested constellations {''.join(wanted)} "
                                            f"(the file has {''.join(s for s in SYSTEMS if s in present)})")

    if observations.pr_m.shape[0] == 0:
        raise RinexError(observations.path, "no epoch: the Observations given hold none (an empty selection of the "
                                            "file?)")
    # C/N0 of 0 (written by converters for "not recorded"), negative or absurd (damaged field): missing
    cn0 = observations.cn0_dbhz.copy()
    cn0[~((cn0 > 0.0) & (cn0 <= qc_config.cn0_max_dbhz))] = np.nan
    letters = np.array([s[0] for s in observations.sv])
    # systems with a pseudorange in these epochs (a selection of a file's epochs can miss one the file has)
    observed = {s for s in set(letters) if np.isfinite(observations.pr_m[:, letters == s]).any()}
    for system in sorted(observed):
        cols = letters == system
        if not np.any(np.isfinite(cn0[:, cols])):
            note = f"{observations.path}: no C/N0 for {system}; assuming {ASSUMED_CN0_DBHZ} dB-Hz"
            notes.append(note)
            warnings.warn(note, RinexWarning, stacklevel=2)
            cn0[:, cols] = np.where(np.isfinite(observations.pr_m[:, cols]), ASSUMED_CN0_DBHZ, np.nan)
    observations = replace(observations, cn0_dbhz=cn0)

    n_t, n_s = observations.pr_m.shape
    # satellite states only for plausible pseudoranges: the transmission time comes from them, and an
    # absurd one (1e308 m) would ask for an orbit propagated over ages; qc marks them out of range
    t_idx, s_idx = np.nonzero((observations.pr_m >= qc_config.pr_min_m) & (observations.pr_m <= qc_config.pr_max_m))
    states = satellite_states(navigation, observations.sv[s_idx], observations.time_gps_s[t_idx],
                              observations.pr_m[t_idx, s_idx])
    pos = np.zeros((n_t, n_s, 3))
    vel = np.zeros((n_t, n_s, 3))
    clock = np.zeros((n_t, n_s))
    clock_drift = np.zeros((n_t, n_s))
    tgd = np.zeros((n_t, n_s))
    eph_code = np.full((n_t, n_s), qc.OK, dtype=np.int8)
    pos[t_idx, s_idx] = np.nan_to_num(states.pos_ecef_m)
    vel[t_idx, s_idx] = np.nan_to_num(states.vel_ecef_m_s)
    clock[t_idx, s_idx] = np.nan_to_num(states.clock_s)
    clock_drift[t_idx, s_idx] = np.nan_to_num(states.clock_drift_s_s)
    tgd[t_idx, s_idx] = np.nan_to_num(states.group_delay_s)
    eph_code[t_idx, s_idx] = np.where(states.ok, qc.OK, qc.ephemeris_reason(states.reason))
    reason = qc.observation_reasons(observations.pr_m, cn0, eph_code, qc_config)

    usable_systems = tuple(s for s in SYSTEMS if np.any(reason[:, letters == s] == qc.OK))
    if not usable_systems:
        counts = qc.count_reasons(reason)
        raise RinexError(observations.path, "no usable observation: " + ", ".join(f"{k}: {v}" for k, v in counts.items())
                         + f" (navigation: {', '.join(navigation.sources)}{_coverage(navigation, observations)})")
    for system in sorted(observed - set(usable_systems)):
        notes.append(f"{observations.path}: no usable {system} observation "
                     f"({', '.join(f'{k}: {v}' for k, v in qc.count_reasons(reason[:, letters == system]).items())})")
    sys_index = np.array([usable_systems.index(c) if c in usable_systems else -1 for c in letters], dtype=int)
    reason = np.where((sys_index[None, :] < 0) & (reason == qc.OK), qc.SYSTEM_EXCLUDED, reason).astype(np.int8)
    return Measurements(observations, navigation, usable_systems, sys_index, pos, vel, clock, tgd,
                        carrier_frequency_hz(observations.sv, navigation), reason, tuple(notes), clock_drift)
