"""Coarse quality control: per-observation reason codes and the thresholds that set them."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OK = 0
NO_EPHEMERIS = 1
EPHEMERIS_EXPIRED = 2
UNHEALTHY = 3
PR_OUT_OF_RANGE = 4
LOW_CN0 = 5
NO_CN0 = 6
LOW_ELEVATION = 7
GROSS_RESIDUAL = 8
SYSTEM_EXCLUDED = 9
NOT_OBSERVED = 10
INVALID_EPHEMERIS = 11
INACCURATE_EPHEMERIS = 12

REASONS = {OK: "ok", NO_EPHEMERIS: "no ephemeris", EPHEMERIS_EXPIRED: "ephemeris expired", UNHEALTHY: "unhealthy",
           PR_OUT_OF_RANGE: "pseudorange out of range", LOW_CN0: "C/N0 below threshold", NO_CN0: "no C/N0",
           LOW_ELEVATION: "below elevation mask", GROSS_RESIDUAL: "gross residual", SYSTEM_EXCLUDED: "system excluded",
           NOT_OBSERVED: "not observed", INVALID_EPHEMERIS: "invalid ephemeris",
           INACCURATE_EPHEMERIS: "inaccurate ephemeris"}
_EPHEMERIS_REASON = {"": OK, "no ephemeris": NO_EPHEMERIS, "ephemeris expired": EPHEMERIS_EXPIRED, "unhealthy": UNHEALTHY,
                     "invalid ephemeris": INVALID_EPHEMERIS, "inaccurate ephemeris": INACCURATE_EPHEMERIS}


@dataclass(frozen=True)
class QcConfig:
    """Thresholds of the coarse quality control (LF-GNSS step 1) that need no receiver position.

    The elevation mask and the gross-residual limit need one, so they are ``lfgnss.spp.SppConfig``'s.
    """

    cn0_min_dbhz: float = 20.0
    cn0_max_dbhz: float = 100.0    # above: not a C/N0 (damaged field), treated as missing
    pr_min_m: float = 1.5e7
    pr_max_m: float = 4.5e7


def ephemeris_reason(reason: np.ndarray) -> np.ndarray:
    """Reason codes (int8) from the ephemeris module's reason strings."""
    codes = np.full(np.shape(reason), NO_EPHEMERIS, dtype=np.int8)
    for text, code in _EPHEMERIS_REASON.items():
        codes[np.asarray(reason) == text] = code
    return codes


def observation_reasons(pr_m: np.ndarray, cn0_dbhz: np.ndarray, eph_code: np.ndarray, config: QcConfig) -> np.ndarray:
    """Reason codes (T, S) of the checks that need no receiver position; the first failing check wins."""
    reason = np.where(np.isfinite(pr_m), OK, NOT_OBSERVED).astype(np.int8)
    checks = [
        (eph_code != OK, eph_code),
        (~((pr_m >= config.pr_min_m) & (pr_m <= config.pr_max_m)), PR_OUT_OF_RANGE),
        (~(np.isfinite(cn0_dbhz) & (cn0_dbhz <= config.cn0_max_dbhz)), NO_CN0),
        (cn0_dbhz < config.cn0_min_dbhz, LOW_CN0),
    ]
    for failed, code in checks:
        reason = np.where((reason == OK) & failed, code, reason).astype(np.int8)
    return reason


def count_reasons(reason: np.ndarray) -> dict[str, int]:
    """How many observations carry each reason (observed ones only)."""
    values, counts = np.unique(reason[reason != NOT_OBSERVED], return_counts=True)
    return {REASONS[int(v)]: int(c) for v, c in zip(values, counts)}
