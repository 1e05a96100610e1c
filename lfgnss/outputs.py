"""Solution writers (RTKLIB ``.pos``, CSV, GeoJSON, KML), a ``.pos`` reader, and plots.

No file ever contains NaN or inf: an epoch *has a position* when its status is not
``STATUS_NONE`` and its ECEF position is finite. Epochs without one are left out of ``.pos``,
GeoJSON and KML, and written with empty fields and status ``none`` in CSV.

RTKLIB ``.pos`` (``rnx2rtkp`` 2.4.3, ``outsolheads``/``outpos`` in ``solution.c``)
-----------------------------------------------------------------------------------
Byte layout as ``rnx2rtkp -p 0 [-t]`` writes it: ``%`` header lines (the first block ending in
``\\n``, the two column-header lines and the data lines in ``\\r\\n``, as RTKLIB does), then per epoch
GPST (``yyyy/mm/dd hh:mm:ss.sss`` or ``week tow``), latitude, longitude [deg] (``%14.9f``), ellipsoidal
height [m] (``%10.4f``), Q, ns (``%3d``), sdn sde sdu sdne sdeu sdun [m] (``%8.4f``; the cross terms are
signed square roots of the ENU covariances, RTKLIB ``sqvar``), age [s] (``%6.2f``), ratio (``%6.1f``).

Q codes written: ``5`` (single) for ``updated`` and ``reset`` epochs, ``7`` for ``coasted`` ones
(RTKLIB ``SOLQ_DR``, "dead reckoning": a prediction with no measurement update; ``rtkplot`` shows
it as DR). Pass ``coasted_q=5`` to mark them single. :func:`read_pos` maps 7 back to ``coasted``
and every other Q to ``updated``, and keeps the raw codes in ``info["q"]``.
"""
from __future__ import annotations

import csv
import io
import json
import math
import re
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence
from xml.sax.saxutils import escape

import numpy as np

from estimators.base import (STATUS_COASTED, STATUS_NAMES, STATUS_NONE, STATUS_RESET, STATUS_UPDATED,
                             Solution)

from . import __version__
from .frames import NEAR_SURFACE_RADIUS_M, check_near_surface, ecef_to_lla, lla_to_ecef
from .metrics import enu_errors, enu_rotations
from .paths import write_output
from .time import GPS_EPOCH, SECONDS_PER_WEEK, gpst_stamp, leap_seconds, utc_to_gps_s

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.figure import Figure

#: RTKLIB solution quality codes (rtklib.h).
Q_SINGLE = 5
Q_DR = 7
_MS_PER_WEEK = int(SECONDS_PER_WEEK * 1000)
#: RTKLIB's legend line, with 7 (its SOLQ_DR, dead reckoning): what lfgnss writes for a coasted epoch.
_POS_QLINE = ("% (lat/lon/height=WGS84/ellipsoidal,Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,7:dr,"
              "ns=# of satellites)")
_POS_COLS = ("latitude(deg)", "longitude(deg)", "height(m)", "Q", "ns", "sdn(m)", "sde(m)", "sdu(m)",
             "sdne(m)", "sdeu(m)", "sdun(m)", "age(s)", "ratio")
_POS_WIDTHS = (14, 14, 10, 3, 3, 8, 8, 8, 8, 8, 8, 6, 6)


# ---------------------------------------------------------------- helpers
def _check_args(writer: str, path: object, solution: object, where: str = "path") -> None:
    """TypeError naming ``writer`` when ``solution`` is not a Solution or ``path`` not a path (arguments swapped)."""
    call = f"{writer}({where}, solution)"
    if isinstance(path, Solution) and not isinstance(solution, Solution):
        raise TypeError(f"{call}: the arguments are swapped, the {where} comes first")
    if not isinstance(solution, Solution):
        raise TypeError(f"{call}: solution must be an estimators.Solution (what an estimator's solve returns), "
                        f"got {type(solution).__name__}")
    if not isinstance(path, (str, Path)) and not hasattr(path, "__fspath__"):
        raise TypeError(f"{call}: {where} must be a str or Path, got {type(path).__name__}")


def _on_earth(solution: Solution) -> np.ndarray:
    """(T,) bool: epochs whose position lies near the Earth's surface (``NEAR_SURFACE_RADIUS_M``), where latitude,
    longitude and height mean something; a diverged estimate (the Earth's centre, 1e12 m) does not."""
    with np.errstate(over="ignore"):                # 1e300 m: inf, outside too
        r = np.linalg.norm(np.nan_to_num(np.asarray(solution.pos_ecef_m, float), nan=0.0), axis=1)
    return (r >= NEAR_SURFACE_RADIUS_M[0]) & (r <= NEAR_SURFACE_RADIUS_M[1])


def _placed(writer: str, path: Path, solution: Solution, stacklevel: int = 3) -> np.ndarray:
    """(T,) bool: the epochs ``writer`` writes with a position (``has_position`` and ``_on_earth``), with one warning
    naming the file for those left out: latitude 180 and a height of -6378137 m are no place to draw."""
    ok = solution.has_position()
    far = ok & ~_on_earth(solution)
    if far.any():
        k = int(np.argmax(far))
        with np.errstate(over="ignore"):
            r = float(np.linalg.norm(np.asarray(solution.pos_ecef_m, float)[k]))
        warnings.warn(f"{writer} {path}: {int(far.sum())} epoch(s) of {solution.backend!r} have a position far from "
                      f"the Earth's surface (first: epoch {k}, {r:.6g} m from its centre, outside "
                      f"[{NEAR_SURFACE_RADIUS_M[0]:g}, {NEAR_SURFACE_RADIUS_M[1]:g}] m): written without one (a "
                      f"diverged estimate?)", UserWarning, stacklevel=stacklevel)
    return ok & ~far


#: RTKLIB's names of the constellations in a .pos header's ``navi sys`` line.
_RTKLIB_SYSTEM_NAMES = {"G": "gps", "R": "glonass", "E": "galileo", "C": "beidou", "J": "qzss", "S": "sbas"}


def _write_text(path: Path, text: str) -> None:
    """``text`` as ``path`` (UTF-8), written whole where it can be (:func:`lfgnss.paths.write_output`): an
    interrupted run leaves the previous file, never half a file."""
    write_output(path, lambda target: target.write_text(text, encoding="utf-8", newline=""))


def _sqvar(c: np.ndarray) -> np.ndarray:
    """Signed square root of a covariance (RTKLIB ``sqvar``)."""
    return np.sign(c) * np.sqrt(np.abs(c))


def _gpst_ms(time_gps_s: np.ndarray) -> np.ndarray:
    """GPS time rounded to integer milliseconds (int64)."""
    return np.round(np.asarray(time_gps_s, dtype=float) * 1000.0).astype(np.int64)


def _calendar(ms: np.ndarray, decimals: int = 3) -> list[str]:
    """``yyyy/mm/dd hh:mm:ss.sss`` strings (``decimals`` 0..3) from GPS milliseconds, rounded first.

    Rounding the integer milliseconds before formatting avoids RTKLIB's ``11:10:60`` display slip.
    """
    step = 10 ** (3 - decimals)
    ms = (np.round(np.asarray(ms, dtype=np.int64) / step) * step).astype(np.int64)
    stamps = GPS_EPOCH.astype("datetime64[ms]") + ms.astype("timedelta64[ms]")
    width = 19 + (decimals + 1 if decimals else 0)
    return [s.replace("-", "/").replace("T", " ")[:width]
            for s in np.atleast_1d(np.datetime_as_string(stamps, unit="ms"))]


def _fmt(value: float, digits: int) -> str:
    """Fixed-point text of a finite value, '' otherwise (CSV never holds NaN or inf); no '-0.0000'."""
    if not math.isfinite(value):
        return ""
    text = f"{value:.{digits}f}"
    return text[1:] if text.startswith("-") and not float(text) else text


# ---------------------------------------------------------------- RTKLIB .pos
def write_pos(path: str | Path, solution: Solution, *, time_format: str = "calendar",
              coasted_q: int = Q_DR, inputs: Sequence[str | Path] = (), systems: str = "") -> Path:
    """Write a Solution as an RTKLIB ``.pos`` file in latitude/longitude/height (``rnx2rtkp -p 0``).

    Parameters
    ----------
    path : str or Path
        Output file.
    solution : Solution
        Estimator output; epochs without a position are left out. An epoch with a position but no finite
        covariance gets six sds of 0, as RTKLIB writes an unknown one (its ``SQRT``); :func:`read_pos` reads that
        back as unknown.
    time_format : {"calendar", "tow"}
        ``yyyy/mm/dd hh:mm:ss.sss`` GPST (``rnx2rtkp -t``) or ``week tow`` (RTKLIB default).
    coasted_q : int
        Q code for coasted epochs (default 7, RTKLIB ``SOLQ_DR``); updated/reset epochs get 5.
    inputs : sequence of paths
        The observation and navigation files the solution comes from, one ``% inp file  :`` header line each (as
        rnx2rtkp writes), so two runs of one observation file with other inputs can be told apart.
    systems : str
        The constellations the solution used (letters, ``"GR"``), as a ``% navi sys  : gps glonass`` line.

    Returns
    -------
    Path
        The file written.
    """
    _check_args("write_pos", path, solution)
    if time_format not in ("calendar", "tow"):
        raise ValueError(f"write_pos {path}: time_format must be 'calendar' or 'tow', got {time_format!r}")
    path = Path(path)
    ok = _placed("write_pos", path, solution)
    ms_all = _gpst_ms(solution.time_gps_s)
    ms = ms_all[ok]
    llh = ecef_to_lla(solution.pos_ecef_m[ok])
    cov = solution.cov_enu_m2()[ok]
    status = np.asarray(solution.status)[ok]
    q = np.where(status == STATUS_COASTED, coasted_q, Q_SINGLE)
    ns = np.asarray(solution.n_used)[ok].astype(int)
    sd = np.stack([np.sqrt(np.maximum(cov[:, 1, 1], 0)), np.sqrt(np.maximum(cov[:, 0, 0], 0)),
                   np.sqrt(np.maximum(cov[:, 2, 2], 0)), _sqvar(cov[:, 1, 0]), _sqvar(cov[:, 0, 2]),
                   _sqvar(cov[:, 2, 1])], axis=1)
    if time_format == "calendar":
        times = _calendar(ms)
        time_width = 16 + 3 + 1
    else:
        times = [f"{m // _MS_PER_WEEK:4d} {(m % _MS_PER_WEEK) / 1000.0:10.3f}" for m in ms]
        time_width = 8 + 3 + 1
    lines = [f"% program   : lfgnss ver.{__version__} backend {solution.backend}\n"]
    lines += [f"% inp file  : {source}\n" for source in inputs]
    if systems:
        lines.append(f"% navi sys  : {' '.join(_RTKLIB_SYSTEM_NAMES.get(c, c) for c in systems)}\n")
    if len(ms_all):
        for label, m in (("obs start", ms_all.min()), ("obs end  ", ms_all.max())):
            week, tow = divmod(int(m), _MS_PER_WEEK)
            lines.append(f"% {label} : {_calendar(np.array([m]), 1)[0]} GPST (week{week:04d} {tow / 1000.0:8.1f}s)\n")
    lines.append("%\n")
    lines.append(_POS_QLINE + "\r\n")
    lines.append("%  " + "GPST".ljust(time_width) + " "
                 + " ".join(c.rjust(w) for c, w in zip(_POS_COLS, _POS_WIDTHS)) + "\r\n")
    rows = zip(times, np.degrees(llh[:, :2]).tolist(), llh[:, 2].tolist(), q.tolist(), ns.tolist(), sd.tolist())
    for tstr, (lat, lon), h, qk, nk, sdk in rows:        # Python numbers: formatting numpy scalars costs 3x
        lines.append(f"{tstr} {lat:14.9f} {lon:14.9f} {h:10.4f} {qk:3d} {nk:3d} "
                     + " ".join(f"{v:8.4f}" for v in sdk) + f" {0.0:6.2f} {0.0:6.1f}\r\n")
    _write_text(path, "".join(lines))
    return path


_CAL_RE = re.compile(r"^\d{4}/\d{1,2}/\d{1,2}$")


def _parse_pos_time(fields: list[str], scale: str) -> float:
    """GPS seconds from the time fields of a ``.pos`` line (calendar or week/tow)."""
    if _CAL_RE.match(fields[0]):
        date = fields[0].replace("/", "-")
        hms, _, frac = fields[1].partition(".")
        h, m, s = (int(x) for x in hms.split(":"))
        day = np.datetime64(date, "D")
        secs = ((day - GPS_EPOCH.astype("datetime64[D]")).astype(np.int64) * 86400
                + h * 3600 + m * 60 + s + (float("0." + frac) if frac else 0.0))
    else:
        secs = int(fields[0]) * SECONDS_PER_WEEK + float(fields[1])
    return float(utc_to_gps_s(secs)) if scale == "UTC" else float(secs)      # rnx2rtkp -u, week/TOW or calendar


def read_pos(path: str | Path, backend: str | None = None) -> Solution:
    """Read an RTKLIB ``.pos`` solution file (RTKLIB's own or :func:`write_pos`'s) into a Solution.

    Handles time as calendar or week/tow, GPST or UTC (converted to GPST), positions as
    latitude/longitude/height in decimal degrees or as ECEF x/y/z, with ``\\n`` or ``\\r\\n`` line ends.

    Parameters
    ----------
    path : str or Path
        ``.pos`` file.
    backend : str, optional
        Name for ``Solution.backend``; default ``"rtklib"`` for rnx2rtkp files, the name stored by
        :func:`write_pos`, else the file stem.

    Returns
    -------
    Solution
        One row per line. ``status``: ``coasted`` for Q = 7, ``updated`` otherwise; ``cov_ecef_m2``
        rebuilt from the six standard deviations (NaN where all six are 0: unknown); ``clock_m`` NaN (not in the file);
        ``info`` holds ``q``, ``age_s``, ``ratio`` (T,; 0 for lines without those columns, 13 fields instead of
        RTKLIB's 15) and ``source`` (the path).
    """
    path = Path(path)
    scale, posf, program = "GPST", None, None
    times, pos, sds, qs, ns, ages, ratios = [], [], [], [], [], [], []
    with open(path, "r", newline=None, encoding="utf-8-sig") as fh:      # a byte order mark is read past
        for lineno, raw in enumerate(fh, 1):
            line = raw.strip()
            if not line:
                continue
            if line.startswith("%"):
                body = line[1:].strip()
                frame = re.match(r"\((lat/lon/height|x/y/z-ecef)=([^,/]*)/?([^,]*),", body)
                if frame and (frame[2] != "WGS84" or frame[3] not in ("", "ellipsoidal")):
                    # rnx2rtkp's out-datum / out-height: Tokyo or PZ90.02 coordinates, or heights above the
                    # geoid ("geodetic", tens of metres off), would be read as WGS84 ellipsoidal ones
                    raise ValueError(f"read_pos {path}:{lineno}: positions are {frame[2]}/{frame[3] or '-'}; only "
                                     f"WGS84 with ellipsoidal heights is read (rnx2rtkp: out-datum=wgs84, "
                                     f"out-height=ellipsoidal)")
                if body.startswith("program"):
                    program = body.split(":", 1)[1].strip()
                elif body.startswith(("GPST", "UTC", "JST")):
                    scale = body.split()[0]
                    if scale == "JST":
                        raise ValueError(f"read_pos {path}:{lineno}: JST time is not supported")
                    if "latitude(deg)" in body:
                        posf = "llh"
                    elif "x-ecef(m)" in body:
                        posf = "xyz"
                    else:
                        raise ValueError(f"read_pos {path}:{lineno}: unsupported position columns "
                                         f"(need lat/lon/height in degrees or x/y/z-ecef): {body!r}")
                continue
            fields = line.split()
            if len(fields) < 13:        # age and ratio (RTKLIB writes them) may be missing: read as 0
                raise ValueError(f"read_pos {path}:{lineno}: expected at least 13 fields (time, position, Q, ns, six "
                                 f"sds; age and ratio may follow), got {len(fields)}")
            try:
                times.append(_parse_pos_time(fields[:2], scale))
                vals = [float(v) for v in fields[2:15]]
            except ValueError as exc:
                raise ValueError(f"read_pos {path}:{lineno}: cannot parse {line!r}: {exc}") from None
            pos.append(vals[0:3])
            qs.append(int(vals[3]))
            ns.append(int(vals[4]))
            sds.append(vals[5:11])
            ages.append(vals[11] if len(vals) > 11 else 0.0)
            ratios.append(vals[12] if len(vals) > 12 else 0.0)
    n = len(times)
    pos = np.asarray(pos, dtype=float).reshape(n, 3)
    sds = np.asarray(sds, dtype=float).reshape(n, 6)
    sds[(sds == 0).all(axis=1)] = np.nan      # RTKLIB (and write_pos) write an unknown covariance as sds of 0
    if posf is None:  # no column header: ECEF coordinates are millions of metres
        posf = "xyz" if n and np.abs(pos[:, 0]).max() > 1e4 else "llh"
    if posf == "llh":
        ecef = lla_to_ecef(np.radians(pos[:, 0]), np.radians(pos[:, 1]), pos[:, 2]).reshape(n, 3)
        # sdn sde sdu sdne sdeu sdun -> ENU covariance -> ECEF: C_ecef = R^T C_enu R
        sn, se, su, sne, seu, sun = (sds[:, k] for k in range(6))
        sq = lambda x: np.sign(x) * x * x
        c = np.empty((n, 3, 3))
        c[:, 0, 0], c[:, 1, 1], c[:, 2, 2] = se ** 2, sn ** 2, su ** 2
        c[:, 0, 1] = c[:, 1, 0] = sq(sne)
        c[:, 0, 2] = c[:, 2, 0] = sq(seu)
        c[:, 1, 2] = c[:, 2, 1] = sq(sun)
        rot = enu_rotations(ecef)
        cov = np.einsum("tji,tjk,tkl->til", rot, c, rot)
    else:
        ecef = pos
        sx, sy, sz, sxy, syz, szx = (sds[:, k] for k in range(6))
        sq = lambda x: np.sign(x) * x * x
        cov = np.empty((n, 3, 3))
        cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2] = sx ** 2, sy ** 2, sz ** 2
        cov[:, 0, 1] = cov[:, 1, 0] = sq(sxy)
        cov[:, 1, 2] = cov[:, 2, 1] = sq(syz)
        cov[:, 2, 0] = cov[:, 0, 2] = sq(szx)
    q = np.asarray(qs, dtype=int)
    if backend is None:
        m = re.match(r"lfgnss ver\.\S+ backend (\S+)", program or "")
        backend = m.group(1) if m else ("rtklib" if (program or "").startswith("rnx2rtkp") else path.stem)
    return Solution(backend=backend, time_gps_s=np.asarray(times, dtype=float), pos_ecef_m=ecef,
                    cov_ecef_m2=cov, clock_m=np.full(n, np.nan), n_used=np.asarray(ns, dtype=int),
                    status=np.where(q == Q_DR, STATUS_COASTED, STATUS_UPDATED),
                    info={"q": q, "age_s": np.asarray(ages, float), "ratio": np.asarray(ratios, float),
                          "source": str(path)})


# ---------------------------------------------------------------- CSV
CSV_COLUMNS = ("time_gpst", "time_utc", "time_gps_s", "week", "tow_s", "x_m", "y_m", "z_m", "lat_deg", "lon_deg", "h_m",
               "sd_e_m", "sd_n_m", "sd_u_m", "vel_e_m_s", "vel_n_m_s", "vel_u_m_s", "clock_m", "n_used", "status")
CSV_TRUTH_COLUMNS = ("err_e_m", "err_n_m", "err_u_m", "err_2d_m", "err_3d_m")


def write_csv(path: str | Path, solution: Solution, truth_ecef_m: np.ndarray | None = None) -> Path:
    """One CSV row per epoch: time, ECEF, geodetic, ENU standard deviations, n_used, status.

    Columns :data:`CSV_COLUMNS` (``time_gpst`` as ``yyyy/mm/dd hh:mm:ss.sss`` GPST; ``time_utc`` the same instant in
    ISO 8601 UTC, leap seconds removed; WGS84 ``h_m`` ellipsoidal; ``vel_*`` the velocity in the local ENU frame
    (empty for an estimator without one), ``clock_m`` the receiver clock of the reference constellation; ``sd_*``
    from the position covariance rotated to the local ENU frame), plus :data:`CSV_TRUTH_COLUMNS` [m] when
    ``truth_ecef_m`` (T, 3) is given (empty where the epoch is unlabelled). Epochs without a position
    have empty numeric fields and status ``none``.
    """
    _check_args("write_csv", path, solution)
    path = Path(path)
    t = len(solution.time_gps_s)
    if truth_ecef_m is not None and np.shape(truth_ecef_m) != (t, 3):
        raise ValueError(f"write_csv {path}: truth_ecef_m has shape {np.shape(truth_ecef_m)}, expected ({t}, 3)")
    columns = _solution_columns(f"write_csv {path}", solution, truth_ecef_m)
    ok = solution.has_position()
    digits = {"time_gps_s": 3, "tow_s": 3, "lat_deg": 9, "lon_deg": 9}      # the others: 4 (0.1 mm, 0.1 mm/s)
    text = {}
    for col, values in columns.items():
        if col in ("time_gpst", "time_utc", "status"):
            text[col] = values
        elif col in ("week", "n_used"):
            text[col] = [str(int(v)) if has or col == "week" else "" for v, has in zip(values, ok)]
        else:
            text[col] = [_fmt(v, digits.get(col, 4)) for v in np.asarray(values, float).tolist()]
    buffer = io.StringIO(newline="")
    writer = csv.writer(buffer)
    writer.writerow(columns)
    writer.writerows(zip(*text.values()))
    _write_text(path, buffer.getvalue())
    return path


def solution_frame(solution: Solution, truth_ecef_m: np.ndarray | None = None) -> "pd.DataFrame":
    """pandas DataFrame of a Solution, one row per epoch, with :func:`write_csv`'s columns [m, deg, s, m/s].

    Numbers as floats (NaN where the epoch has no position or covariance, never in the CSV), ``status`` by name,
    ``time_gpst`` and ``time_utc`` as text; with ``truth_ecef_m`` (T, 3) [m] also :data:`CSV_TRUTH_COLUMNS`.
    """
    import pandas as pd

    return pd.DataFrame(_solution_columns("solution_frame", solution, truth_ecef_m))


def _solution_columns(owner: str, solution: Solution, truth_ecef_m: np.ndarray | None) -> dict[str, object]:
    """:func:`solution_frame`'s columns as arrays (and lists of text), without pandas: ``write_csv`` writes them."""
    if not isinstance(solution, Solution):
        raise TypeError(f"{owner}: expected an estimators.Solution, got {type(solution).__name__}")
    t = len(solution.time_gps_s)
    ok = solution.has_position()
    pos = np.where(ok[:, None], np.asarray(solution.pos_ecef_m, float), np.nan)
    ms = _gpst_ms(solution.time_gps_s)      # week and TOW from the milliseconds time_gpst shows: the same instant
    llh = np.where(_on_earth(solution)[:, None], solution.geodetic(), np.nan)     # ECEF stays: what it estimated
    sd = solution.sd_enu_m()
    vel = solution.vel_enu_m_s()
    status = np.asarray(solution.status)
    columns = {"time_gpst": _calendar(ms) if t else [], "time_utc": _utc_iso(ms / 1000.0) if t else [],
               "time_gps_s": np.asarray(solution.time_gps_s, float), "week": ms // _MS_PER_WEEK,
               "tow_s": (ms % _MS_PER_WEEK) / 1000.0, "x_m": pos[:, 0], "y_m": pos[:, 1], "z_m": pos[:, 2],
               "lat_deg": llh[:, 0], "lon_deg": llh[:, 1], "h_m": llh[:, 2], "sd_e_m": sd[:, 0], "sd_n_m": sd[:, 1],
               "sd_u_m": sd[:, 2], "vel_e_m_s": vel[:, 0], "vel_n_m_s": vel[:, 1], "vel_u_m_s": vel[:, 2],
               "clock_m": np.where(ok, np.asarray(solution.clock_m, float), np.nan),
               "n_used": np.where(ok, np.asarray(solution.n_used), 0).astype(int),
               "status": [STATUS_NAMES.get(int(v), str(int(v))) if has else STATUS_NAMES[STATUS_NONE]
                          for v, has in zip(status, ok)]}
    if truth_ecef_m is not None:
        truth = np.asarray(truth_ecef_m, dtype=float)
        if truth.shape != (t, 3):
            raise ValueError(f"{owner}: truth_ecef_m has shape {truth.shape}, expected ({t}, 3)")
        check_near_surface(owner, "truth_ecef_m", truth)
        e = enu_errors(pos, truth).reshape(-1, 3)
        for key, value in zip(CSV_TRUTH_COLUMNS, (e[:, 0], e[:, 1], e[:, 2], np.hypot(e[:, 0], e[:, 1]),
                                                  np.linalg.norm(e, axis=1))):
            columns[key] = value
    return columns


# ---------------------------------------------------------------- GeoJSON / KML
def _track(writer: str, path: Path, solution: Solution) -> tuple[np.ndarray, np.ndarray]:
    """Indices of epochs with a position (``_placed``) and their (lon [deg], lat [deg], h [m]) rows."""
    idx = np.flatnonzero(_placed(writer, path, solution, stacklevel=4))
    llh = ecef_to_lla(solution.pos_ecef_m[idx]).reshape(-1, 3)
    return idx, np.column_stack([np.degrees(llh[:, 1]), np.degrees(llh[:, 0]), llh[:, 2]])


def _pieces(idx: np.ndarray) -> tuple[list[np.ndarray], list[int]]:
    """The track's rows in lines and lone fixes: runs of consecutive epochs with a position (a line where it holds
    two rows or more; a lone fix's row otherwise), so that a track is not drawn straight across epochs without one."""
    from .datasets import contiguous_runs

    runs = [np.searchsorted(idx, run) for run in contiguous_runs(idx)]     # epochs -> the track's rows
    return [r for r in runs if r.size >= 2], [int(r[0]) for r in runs if r.size == 1]


def write_geojson(path: str | Path, solution: Solution, *, points: bool = False) -> Path:
    """GeoJSON FeatureCollection (RFC 7946: WGS84 ``[lon, lat, h]``) of the epochs with a position.

    A ``LineString`` feature of the track (a ``Point`` where only one epoch has a position; where epochs without a
    position cut it, a ``MultiLineString`` of its pieces and a ``MultiPoint`` feature of the lone fixes between them),
    and with ``points=True`` one ``Point`` feature per epoch with ``time_gps_s``, ``time_utc`` (ISO 8601), ``status``
    and ``n_used`` properties.
    """
    _check_args("write_geojson", path, solution)
    path = Path(path)
    idx, lonlath = _track("write_geojson", path, solution)
    coords = [[round(float(a), 9), round(float(b), 9), round(float(c), 4)] for a, b, c in lonlath]
    lines, lone = _pieces(idx)
    features = []
    properties = {"backend": solution.backend, "n_epochs": len(coords)}
    if len(lines) == 1 and not lone:
        features.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
                         "properties": properties})
    elif len(lines) == 0 and len(lone) == 1:
        if not points:                                  # a lone position: a Point (points=True writes it anyway)
            features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": coords[0]},
                             "properties": properties})
    elif lines or lone:
        if lines:
            features.append({"type": "Feature", "properties": properties | {"n_pieces": len(lines)},
                             "geometry": {"type": "MultiLineString",
                                          "coordinates": [[coords[i] for i in run] for run in lines]}})
        if lone and not points:
            features.append({"type": "Feature", "properties": {"backend": solution.backend, "lone_fixes": len(lone)},
                             "geometry": {"type": "MultiPoint", "coordinates": [coords[i] for i in lone]}})
    if points:
        status = np.asarray(solution.status)
        utc = _utc_iso(np.asarray(solution.time_gps_s, float)[idx])
        for k, c, when in zip(idx, coords, utc):
            features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": c},
                             "properties": {"time_gps_s": round(float(solution.time_gps_s[k]), 3), "time_utc": when,
                                            "status": STATUS_NAMES.get(int(status[k]), str(int(status[k]))),
                                            "n_used": int(solution.n_used[k])}})
    doc = {"type": "FeatureCollection", "features": features}
    _write_text(path, json.dumps(doc, allow_nan=False))
    return path


def write_kml(path: str | Path, solution: Solution, *, points: bool = False) -> Path:
    """KML track of the epochs with a position (``lon,lat,h``; a point where only one has), clamped to the ground.

    Heights are ellipsoidal while KML altitudes are above mean sea level, so the track uses
    ``altitudeMode clampToGround``. Where epochs without a position cut it, the track is a ``MultiGeometry`` of its
    pieces (and the lone fixes between them as points). With ``points=True`` one Placemark per epoch as well.
    """
    _check_args("write_kml", path, solution)
    path = Path(path)
    idx, lonlath = _track("write_kml", path, solution)
    rows = [f"{a:.9f},{b:.9f},{c:.4f}" for a, b, c in lonlath]
    lines, lone = _pieces(idx)
    name = escape(str(solution.backend))
    parts = ['<?xml version="1.0" encoding="UTF-8"?>',
             '<kml xmlns="http://www.opengis.net/kml/2.2">', "<Document>", f"<name>{name}</name>",
             '<Style id="track"><LineStyle><color>ff0000ff</color><width>2</width></LineStyle></Style>']
    line_kml = ["<LineString><tessellate>1</tessellate><altitudeMode>clampToGround</altitudeMode>"
                f"<coordinates>{' '.join(rows[i] for i in run)}</coordinates></LineString>" for run in lines]
    lone_kml = [f"<Point><altitudeMode>clampToGround</altitudeMode><coordinates>{rows[i]}</coordinates></Point>"
                for i in ([] if points else lone)]          # points=True writes every epoch's point anyway
    shapes = line_kml + lone_kml
    if len(shapes) == 1:                                    # one line, or a lone position
        label = f"{name} track</name><styleUrl>#track</styleUrl>" if line_kml else f"{name} fix</name>"
        parts += [f"<Placemark><name>{label}{shapes[0]}</Placemark>"]
    elif shapes:
        parts += [f"<Placemark><name>{name} track</name><styleUrl>#track</styleUrl><MultiGeometry>", *shapes,
                  "</MultiGeometry></Placemark>"]
    if points:
        status = np.asarray(solution.status)
        utc = _utc_iso(solution.time_gps_s)
        for k, (a, b, c) in zip(idx, lonlath):
            st = STATUS_NAMES.get(int(status[k]), str(int(status[k])))
            parts.append(f"<Placemark><name>{solution.time_gps_s[k]:.3f}</name>"      # KML 2.2's element order
                         f"<description>{escape(st)}, {int(solution.n_used[k])} satellites</description>"
                         f"<TimeStamp><when>{utc[k]}</when></TimeStamp>"      # Google Earth's time slider
                         f"<Point><coordinates>{a:.9f},{b:.9f},{c:.4f}</coordinates></Point></Placemark>")
    parts += ["</Document>", "</kml>"]
    _write_text(path, "\n".join(parts) + "\n")
    return path


def _utc_iso(time_gps_s: np.ndarray) -> list[str]:
    """``2016-06-06T11:10:24.700Z`` UTC texts (ms) of GPS times [s], the leap seconds removed."""
    gps = np.asarray(time_gps_s, float)
    utc = gps - leap_seconds(gps)
    inserted = leap_seconds(gps + 1.0) > leap_seconds(gps)        # within the inserted second 23:59:60: no such text
    utc = np.where(inserted, np.floor(utc) - 0.001, utc)          # ... so 23:59:59.999, never a step back
    ms = np.round(utc * 1000.0).astype(np.int64)
    stamps = (GPS_EPOCH.astype("datetime64[ms]") + ms.astype("timedelta64[ms]")).astype(str)
    return [f"{s}Z" for s in stamps]


# ---------------------------------------------------------------- plots
def align_to(time_gps_s: np.ndarray, other: Solution) -> np.ndarray:
    """Positions (T, 3) of ``other`` at the epochs ``time_gps_s`` [s]: each epoch takes ``other``'s nearest epoch
    within 0.05 s (the benchmark's 0.1 s time match), or within half the time to its neighbouring epochs where that
    is shorter (a receiver faster than 10 Hz), so an epoch of ``other`` serves two only at an exact midpoint.

    NaN where ``other`` has no position at that epoch (benchmark rule for matching epochs).
    """
    t = np.asarray(time_gps_s, dtype=float)
    ot = np.asarray(other.time_gps_s, dtype=float)
    opos = np.where(other.has_position()[:, None], other.pos_ecef_m, np.nan)
    out = np.full((len(t), 3), np.nan)
    if not len(ot) or not len(t):
        return out
    times = np.unique(t)                                             # a repeated epoch is one time, not a 0 s gap
    gaps = np.diff(times)
    nearest = np.minimum(np.r_[np.inf, gaps], np.r_[gaps, np.inf])    # to each time's nearer neighbour
    tol = np.minimum(0.05, 0.5 * nearest)[np.searchsorted(times, t)]
    other_order = np.argsort(ot, kind="stable")
    st = ot[other_order]
    right = np.clip(np.searchsorted(st, t), 0, len(st) - 1)
    left = np.clip(right - 1, 0, len(st) - 1)
    j = np.where(np.abs(st[left] - t) <= np.abs(st[right] - t), left, right)
    hit = np.abs(st[j] - t) <= tol + 1e-9       # times are rounded to ms in .pos files: a float's last bits aside
    out[hit] = opos[other_order[j[hit]]]
    return out


def _legend(ax) -> None:
    """Legend only when something is labelled (no matplotlib warning on empty plots); beside the axes, not over the
    curves, when there are more than four entries."""
    n = len(ax.get_legend_handles_labels()[0])
    if n > 4:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", borderaxespad=0.0)
    elif n:
        ax.legend(loc="best")


#: Line styles of successive groups of ten runs (with :func:`run_styles`' colours).
_LINESTYLES = ("-", "--", ":", "-.")


def run_styles(names: Sequence[str]) -> dict[str, tuple[tuple[float, float, float], str]]:
    """``name -> (RGB colour, line style)`` for the runs of a plot, by their order: the same in every figure.

    The first ten get tab10's colours with solid lines, the next ten the light shades of those hues (tab20's) with
    dashed lines: up to 20 runs get 20 distinct colours, and a light shade also differs from its dark hue's run in line
    style. Beyond 20 the colours repeat with dotted, then dash-dotted lines (40 distinct pairs).
    """
    import matplotlib

    tab20 = matplotlib.colormaps["tab20"].colors
    palette = tab20[::2] + tab20[1::2]              # tab10's colours (the dark hues), then their light ones
    out: dict[str, tuple[tuple[float, float, float], str]] = {}
    for i, name in enumerate(dict.fromkeys(names)):
        out[name] = (tuple(palette[i % len(palette)]), _LINESTYLES[(i // 10) % len(_LINESTYLES)])
    return out


def _log_ticks(axis) -> None:
    """Plain decimal tick labels on a log ``axis`` (0.01, 0.5, 20; not ScalarFormatter's "0.0" for 0.01): decades
    always, the 2 and 5 (or all) minor ticks as well when the view spans few decades, as matplotlib's LogFormatter
    chooses."""
    from matplotlib.ticker import LogFormatter

    class _Plain(LogFormatter):
        def __call__(self, x, pos=None):
            return f"{x:g}" if super().__call__(x, pos) else ""

    axis.set_major_formatter(_Plain(labelOnlyBase=False))
    axis.set_minor_formatter(_Plain(labelOnlyBase=False))


def _named(extra: Mapping[str, Solution] | Sequence[Solution] | None) -> list[tuple[str, Solution]]:
    if extra is None:
        return []
    if isinstance(extra, Mapping):
        return list(extra.items())
    return [(s.backend, s) for s in extra]


def plot_solution(out_dir: str | Path, solution: Solution, truth_ecef_m: np.ndarray | None = None,
                  extra_solutions: Mapping[str, Solution] | Sequence[Solution] | None = None,
                  prefix: str = "", label: str | None = None, title: str | None = None) -> list[Path]:
    """PNG figures of a solution (matplotlib Agg canvas; pyplot's global state is untouched).

    * ``{prefix}track.png``: horizontal track in ENU [m] about the first truth point (else the first
      position), with the truth and any extra solutions;
    * with ``truth_ecef_m`` (T, 3): ``{prefix}errors.png``, 2D and vertical error against time, and
      ``{prefix}cdf.png``, the CDF of 2D and 3D errors of every solution on one plot;
    * ``{prefix}quality.png``: what ``solution`` says of itself against time, truth or not: its standard deviations
      east, north and up [m], and the satellites it used, with the coasted, reset and unsolved epochs marked.

    Extra solutions (a name -> Solution mapping, or Solutions named by their backend) are matched to
    ``solution``'s epochs by GPS time rounded to 0.1 s. ``label`` names ``solution`` (default: its backend), which
    is drawn thicker and above the others; ``title`` heads every figure (what data, which run). Every run gets its
    own colour and line style (:func:`run_styles`), the same in every figure. Log axes are labelled in plain decimals
    (0.01, 0.1, 1, 10 m).

    Returns
    -------
    list of Path
        The files written, in the order above.

    Raises
    ------
    OSError
        The first figure that could not be written (naming its file), after every other one is written.
    """
    _check_args("plot_solution", out_dir, solution, "out_dir")
    figures = solution_figures(solution, truth_ecef_m, extra_solutions, label, title)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    failed: list[OSError] = []
    for name, fig in figures.items():
        try:
            written.append(save_figure(out_dir / f"{prefix}{name}", fig))
        except OSError as err:
            failed.append(err)
    if failed:
        raise failed[0]
    return written


def save_figure(path: str | Path, fig: "Figure", dpi: int = 120) -> Path:
    """A matplotlib figure as ``path``, in the format its suffix names (``.png``, ``.pdf``, ``.svg``; PNG without
    one), written whole where it can be (:func:`lfgnss.paths.write_output`)."""
    path = Path(path)
    kind = path.suffix.lstrip(".").lower() or "png"
    write_output(path, lambda target: fig.savefig(target, dpi=dpi, format=kind))
    return path


#: The figures of :func:`solution_figures` with a truth, by file name (without one: the track and the quality).
TRUTH_FIGURES = ("track.png", "errors.png", "cdf.png", "quality.png")
#: ... and without a truth.
FIGURES = ("track.png", "quality.png")


def solution_figures(solution: Solution, truth_ecef_m: np.ndarray | None = None,
                     extra_solutions: Mapping[str, Solution] | Sequence[Solution] | None = None,
                     label: str | None = None, title: str | None = None) -> dict[str, "Figure"]:
    """:func:`plot_solution`'s figures (matplotlib ``Figure`` on an Agg canvas) by file name, not yet saved."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    t = np.asarray(solution.time_gps_s, dtype=float)
    runs = [(label or solution.backend, np.where(solution.has_position()[:, None], solution.pos_ecef_m, np.nan))]
    runs += [(name, align_to(t, s)) for name, s in _named(extra_solutions)]
    truth = None
    if truth_ecef_m is not None:
        truth = np.asarray(truth_ecef_m, dtype=float)
        if truth.shape != (len(t), 3):
            raise ValueError(f"plot_solution: truth_ecef_m has shape {truth.shape}, expected ({len(t)}, 3)")
    candidates = [truth] if truth is not None else []
    candidates += [p for _, p in runs]
    ref = next((c[np.isfinite(c).all(axis=1)][0] for c in candidates if np.isfinite(c).all(axis=1).any()), None)
    figures: dict = {}
    style = run_styles([name for name, _ in runs])            # the same in every figure
    main = runs[0][0]

    def width(name: str, lw: float) -> dict:
        """The main run thicker and on top: with a dozen benchmark rows it is the one to find."""
        return {"lw": 2 * lw, "zorder": 4} if name == main and len(runs) > 1 else {"lw": lw}

    def new_figure(name: str, figsize: tuple[float, float]) -> Figure:
        fig = Figure(figsize=figsize, layout="constrained")
        FigureCanvasAgg(fig)
        if title:
            fig.suptitle(title, fontsize="medium")
        figures[name] = fig
        return fig

    ax = new_figure("track.png", (7, 7)).add_subplot()
    if ref is not None:
        rot = enu_rotations(ref[None])[0]
        if truth is not None:
            enu = (truth - ref) @ rot.T
            known = enu[np.isfinite(enu).all(axis=1)]
            if len(known) and np.ptp(known[:, :2], axis=0).max() < 0.5:     # one point (static truth): a line shows nothing
                ax.plot(known[:1, 0], known[:1, 1], "k*", ms=14, zorder=5, label="truth")
            else:
                ax.plot(enu[:, 0], enu[:, 1], "k-", lw=2, label="truth")
        for name, p in runs:
            enu = (p[np.isfinite(p).all(axis=1)] - ref) @ rot.T  # join across epochs without position
            ax.plot(enu[:, 0], enu[:, 1], marker=".", ms=2, color=style[name][0], ls=style[name][1], label=name,
                    **width(name, 0.8))
        _legend(ax)
    else:
        ax.text(0.5, 0.5, "no position", ha="center", va="center", transform=ax.transAxes)
    origin = "the first truth point" if truth is not None and np.isfinite(truth).all(axis=1).any() else \
        "the first position"
    ax.set_xlabel(f"east of {origin} [m]")
    ax.set_ylabel(f"north of {origin} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    # the figure shows every run: name the run only when it is the only one
    ax.set_title("horizontal track" if len(runs) > 1 else f"horizontal track ({runs[0][0]})")

    t_rel = t - t[0] if len(t) else t
    time_label = f"time since {gpst_stamp(float(t[0]), 1)} GPST [s]" if len(t) else "time [s]"
    if truth is not None:
        _error_figures(new_figure, runs, truth, t_rel, time_label, style, width)
    _quality_figure(new_figure("quality.png", (10, 6)), solution, t_rel, time_label, label or solution.backend)
    return figures


def _error_figures(new_figure, runs, truth, t_rel, time_label, style, width) -> None:
    """errors.png and cdf.png of :func:`solution_figures`."""
    errors = [(name, enu_errors(p, truth)) for name, p in runs]
    ax2, axu = new_figure("errors.png", (10, 6)).subplots(2, 1, sharex=True)
    for name, e in errors:
        # dots: isolated epochs
        kw = dict(marker=".", ms=3, color=style[name][0], ls=style[name][1], label=name, **width(name, 0.8))
        ax2.plot(t_rel, np.hypot(e[:, 0], e[:, 1]), **kw)
        axu.plot(t_rel, e[:, 2], **kw)
    ax2.set_ylabel("2D error [m]")
    ax2.set_yscale("log")                   # 0.5 m and 50 m both readable when estimators differ tenfold
    _log_ticks(ax2.yaxis)
    axu.set_ylabel("up error [m]")
    axu.set_xlabel(time_label)
    for a in (ax2, axu):
        a.grid(True, alpha=0.3)
    _legend(ax2)

    ax_h, ax_3 = new_figure("cdf.png", (10, 5)).subplots(1, 2, sharey=True)
    labelled = np.isfinite(truth).all(axis=1)
    for name, e in errors:
        for a, v in ((ax_h, np.hypot(e[:, 0], e[:, 1])), (ax_3, np.linalg.norm(e, axis=1))):
            v = np.sort(v[np.isfinite(v)])
            if v.size:
                # CDF over labelled epochs: unsolved epochs count as missing, so curves end at availability.
                a.step(v, np.arange(1, v.size + 1) / max(labelled.sum(), 1), where="post", color=style[name][0],
                       ls=style[name][1], label=name, **width(name, 1.5))
    for a, title in ((ax_h, "2D error [m]"), (ax_3, "3D error [m]")):
        a.set_xlabel(title)
        a.set_xscale("log")
        _log_ticks(a.xaxis)
        a.grid(True, which="both", alpha=0.3)
    ax_h.set_ylabel("share of labelled epochs")
    ax_h.set_ylim(0, 1.0)
    _legend(ax_3)                           # beside the right panel: between the two it would cover the left one


def _quality_figure(fig: "Figure", solution: Solution, t_rel: np.ndarray, time_label: str, name: str) -> None:
    """quality.png of :func:`solution_figures`: standard deviations [m] and satellites used against time."""
    ax_sd, ax_n = fig.subplots(2, 1, sharex=True)
    sd = solution.sd_enu_m()
    for j, axis in enumerate(("east", "north", "up")):
        ax_sd.plot(t_rel, sd[:, j], marker=".", ms=2, lw=0.8, color=f"C{j}", label=axis)
    if (sd > 0).any():
        ax_sd.set_yscale("log")             # 0.5 m and 500 m (a coasting stretch) both readable
        _log_ticks(ax_sd.yaxis)
        _legend(ax_sd)
    else:
        ax_sd.text(0.5, 0.5, "no covariance", ha="center", va="center", transform=ax_sd.transAxes)
    ax_sd.set_ylabel("standard deviation [m]")
    ax_sd.set_title(f"{name}: its own standard deviations and satellites")
    has = solution.has_position()
    status = np.asarray(solution.status)
    used = np.where(has, np.asarray(solution.n_used, float), 0.0)     # marks on the line: a reset's at its satellites
    ax_n.plot(t_rel, np.where(has, used, np.nan), color="k", lw=0.8, drawstyle="steps-post", label="satellites used")
    for code, marker, colour in ((STATUS_COASTED, "v", "C1"), (STATUS_RESET, "o", "C3"), (STATUS_NONE, "x", "0.4")):
        at = status == code if code != STATUS_NONE else ~has
        if at.any():
            ax_n.plot(t_rel[at], used[at], ls="none", marker=marker, ms=4, color=colour,
                      label=f"{STATUS_NAMES[code] if code != STATUS_NONE else 'no position'} ({int(at.sum())})")
    from matplotlib.ticker import MaxNLocator

    ax_n.set_ylabel("satellites used")
    ax_n.set_ylim(bottom=-1)
    ax_n.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax_n.set_xlabel(time_label)
    for a in (ax_sd, ax_n):
        a.grid(True, alpha=0.3)
    _legend(ax_n)
