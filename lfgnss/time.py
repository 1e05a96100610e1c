"""Time scales: GPS time as float seconds since 1980-01-06, week/TOW, BDT, GLONASS time, UTC."""
from __future__ import annotations

import numpy as np

GPS_EPOCH = np.datetime64("1980-01-06T00:00:00", "ns")
SECONDS_PER_WEEK = 604_800.0
BDT_MINUS_GPST_S = -14.0  # BDT = GPST - 14 s (both continuous)

# (UTC date from which the offset applies, GPST - UTC in seconds)
_LEAP_TABLE = [
    ("1981-07-01", 1), ("1982-07-01", 2), ("1983-07-01", 3), ("1985-07-01", 4), ("1988-01-01", 5),
    ("1990-01-01", 6), ("1991-01-01", 7), ("1992-07-01", 8), ("1993-07-01", 9), ("1994-07-01", 10),
    ("1996-01-01", 11), ("1997-07-01", 12), ("1999-01-01", 13), ("2006-01-01", 14), ("2009-01-01", 15),
    ("2012-07-01", 16), ("2015-07-01", 17), ("2017-01-01", 18),
]
_LEAP_UTC_S = np.array([(np.datetime64(d, "ns") - GPS_EPOCH) / np.timedelta64(1, "s") for d, _ in _LEAP_TABLE])
_LEAP_VALUE_S = np.array([v for _, v in _LEAP_TABLE], dtype=float)
_LEAP_GPS_S = _LEAP_UTC_S + _LEAP_VALUE_S  # the same instants on the GPS scale


def datetime64_to_gps_s(t: np.ndarray) -> np.ndarray:
    """GPS seconds since 1980-01-06 from datetime64 stamps that are already on the GPS scale [s]."""
    t = np.asarray(t, dtype="datetime64[ns]")
    return (t - GPS_EPOCH).astype("int64") * 1e-9


def gps_s_to_datetime64(gps_s: np.ndarray) -> np.ndarray:
    """datetime64[ns] on the GPS scale from GPS seconds [s]."""
    return GPS_EPOCH + (np.round(np.asarray(gps_s, dtype=float) * 1e9)).astype("timedelta64[ns]")


def gpst_stamp(gps_s: float, decimals: int = 3) -> str:
    """GPS seconds [s] as a GPST calendar stamp to ``decimals`` (1 to 3) places: ``2016-06-06 11:11:40.500``."""
    ms = int(round(round(gps_s, decimals) * 1000))    # whole ms: through float ns 25.1 s was 25.0999999, cut to 25.0
    text = str(GPS_EPOCH.astype("datetime64[ms]") + np.timedelta64(ms, "ms")).replace("T", " ")
    return text[:len(text) - 3 + decimals]


def week_tow_to_gps_s(week: np.ndarray, tow_s: np.ndarray) -> np.ndarray:
    """GPS seconds from GPS week and time of week [s]."""
    return np.asarray(week, dtype=float) * SECONDS_PER_WEEK + np.asarray(tow_s, dtype=float)


def gps_s_to_week_tow(gps_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GPS week number and time of week [s] from GPS seconds."""
    gps_s = np.asarray(gps_s, dtype=float)
    week = np.floor(gps_s / SECONDS_PER_WEEK)
    return week.astype(int), gps_s - week * SECONDS_PER_WEEK


def leap_seconds(gps_s: np.ndarray) -> np.ndarray:
    """GPST - UTC [s] at the given GPS time (table up to the 2017-01-01 leap second).

    A leap second counts from the GPS second at which UTC reaches the table date: 2015-07-01 00:00:17
    GPST is 2015-07-01 00:00:00 UTC, GPST - UTC = 17 s; one second earlier it is still 16 s (RTKLIB
    ``gpst2utc``; the inserted second 23:59:60 itself has no distinct value on a count of seconds).
    """
    gps_s = np.asarray(gps_s, dtype=float)
    idx = np.searchsorted(_LEAP_GPS_S, gps_s, side="right") - 1
    return np.where(idx >= 0, _LEAP_VALUE_S[np.clip(idx, 0, None)], 0.0)


def utc_to_gps_s(utc_s: np.ndarray) -> np.ndarray:
    """GPS seconds from UTC expressed as seconds since 1980-01-06 UTC [s]."""
    utc_s = np.asarray(utc_s, dtype=float)
    idx = np.searchsorted(_LEAP_UTC_S, utc_s, side="right") - 1
    return utc_s + np.where(idx >= 0, _LEAP_VALUE_S[np.clip(idx, 0, None)], 0.0)


def glonass_to_gps_s(glot_s: np.ndarray) -> np.ndarray:
    """GPS seconds from GLONASS system time (UTC(SU) + 3 h) expressed as seconds since 1980-01-06 [s].

    Only for times on the GLONASS system scale itself (e.g. t_b of the navigation message as broadcast).
    RINEX writes GLONASS times as UTC(SU), without the 3 h: observation epochs of time system ``GLO``
    and navigation epochs take :func:`utc_to_gps_s`, as RTKLIB does (``utc2gpst``).
    """
    return utc_to_gps_s(np.asarray(glot_s, dtype=float) - 10_800.0)


def bdt_to_gps_s(bdt_s: np.ndarray) -> np.ndarray:
    """GPS seconds from BDT seconds counted since 1980-01-06 on the BDT scale [s]."""
    return np.asarray(bdt_s, dtype=float) - BDT_MINUS_GPST_S
