"""Accuracy metrics of the benchmark protocol: ENU errors, RMSE, percentiles, availability.

Every figure is computed over the *labelled epochs that have a solution*; the share of labelled
epochs with a solution (availability) is always reported beside it (``BENCHMARK.md``, Metrics).
"""
from __future__ import annotations

from typing import Iterable, Mapping

import numpy as np

from .frames import check_near_surface, ecef_to_lla

#: Keys of an accuracy row, in table order, with column titles.
METRIC_COLUMNS: dict[str, str] = {
    "n_labelled": "labelled",
    "n_solved": "solved",
    "availability": "avail. [%]",
    "rmse_e_m": "E RMSE [m]",
    "rmse_n_m": "N RMSE [m]",
    "rmse_u_m": "U RMSE [m]",
    "rmse_2d_m": "2D RMSE [m]",
    "rmse_3d_m": "3D RMSE [m]",
    "p50_2d_m": "2D p50 [m]",
    "p95_2d_m": "2D p95 [m]",
    "p50_3d_m": "3D p50 [m]",
    "p95_3d_m": "3D p95 [m]",
}


def enu_rotations(ref_ecef_m: np.ndarray) -> np.ndarray:
    """ECEF-to-ENU rotation matrices (T, 3, 3) at each reference point (T, 3) [m]; NaN rows give NaN."""
    lat, lon, _ = np.moveaxis(ecef_to_lla(np.asarray(ref_ecef_m, dtype=float)), -1, 0)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    zero = np.zeros_like(lat)
    return np.stack([np.stack([-so, co, zero], axis=-1),
                     np.stack([-sl * co, -sl * so, cl], axis=-1),
                     np.stack([cl * co, cl * so, sl], axis=-1)], axis=-2)


def enu_errors(est_ecef_m: np.ndarray, truth_ecef_m: np.ndarray) -> np.ndarray:
    """Error of estimates in the local east-north-up frame of each ground-truth point.

    ``e_t = R(lat_t, lon_t) (x_est,t - x_true,t)`` with R the ECEF-to-ENU rotation at the truth point.

    Parameters
    ----------
    est_ecef_m, truth_ecef_m : (T, 3) float
        Estimated and true ECEF positions [m]; NaN rows allowed.

    Returns
    -------
    (T, 3) float
        ENU error [m]; NaN where either input row has a NaN.
    """
    est = np.asarray(est_ecef_m, dtype=float)
    truth = np.asarray(truth_ecef_m, dtype=float)
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != truth.shape:
        raise ValueError(f"enu_errors: need two (T, 3) arrays, got {est.shape} and {truth.shape}")
    with np.errstate(invalid="ignore"):
        return np.einsum("tij,tj->ti", enu_rotations(truth), est - truth)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else float("nan")


def _pct(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if x.size else float("nan")


def accuracy_table(est_ecef_m: np.ndarray, truth_ecef_m: np.ndarray, available: np.ndarray | None = None,
                   **labels: str) -> dict:
    """Accuracy row of one estimator on one split.

    Parameters
    ----------
    est_ecef_m : (T, 3) float, or an estimator's Solution
        Estimated ECEF positions [m]; NaN where no solution. A ``Solution`` gives its ``pos_ecef_m`` and, unless
        ``available`` is given, its ``available``.
    truth_ecef_m : (T, 3) float
        Ground truth ECEF [m]; NaN where the epoch has no label.
    available : (T,) bool, optional
        True where the estimator gave a solution (``Solution.available``); default: finite estimate.
        An epoch counts as solved only if it is available *and* its estimate is finite.
    **labels : str
        Extra string fields stored first in the row, e.g. ``dataset="hk-tst-2019", method="ekf"``.

    Returns
    -------
    dict
        ``labels``, then ``n_labelled``, ``n_solved``, ``availability`` (share in [0, 1], NaN when no
        epoch is labelled) and the metrics of :data:`METRIC_COLUMNS` [m], computed over labelled and
        solved epochs; NaN when there are none. RMSE_2D = sqrt(mean(e^2 + n^2)),
        RMSE_3D = sqrt(mean(e^2 + n^2 + u^2)); percentiles by linear interpolation.
    """
    if hasattr(est_ecef_m, "pos_ecef_m") and hasattr(est_ecef_m, "available"):      # a Solution
        available = est_ecef_m.available if available is None else available
        est_ecef_m = est_ecef_m.pos_ecef_m
    est = np.asarray(est_ecef_m, dtype=float)
    truth = np.asarray(truth_ecef_m, dtype=float)
    for name, value, given in (("est_ecef_m", est, est_ecef_m), ("truth_ecef_m", truth, truth_ecef_m)):
        if value.ndim != 2 or value.shape[1] != 3:     # one epoch as (3,), or None: not an xyz axis read as epochs
            got = "is None" if given is None else f"has shape {value.shape}"
            raise ValueError(f"accuracy_table: {name} {got}, expected (T, 3) ECEF metres (one epoch: (1, 3))")
    t = est.shape[0]
    if truth.shape[0] != t:
        raise ValueError(f"accuracy_table: est_ecef_m has {t} epochs and truth_ecef_m {truth.shape[0]}; they must be "
                         f"the same epochs")
    avail = np.isfinite(est).all(axis=-1) if available is None else np.asarray(available, dtype=bool)
    if avail.shape != (t,):
        raise ValueError(f"accuracy_table: available has shape {avail.shape}, expected ({t},)")
    check_near_surface("accuracy_table", "truth_ecef_m", truth)
    inner = np.linalg.norm(np.where(np.isfinite(est), est, np.inf), axis=-1) < 1.0e6   # a diverged fix is not in there
    if inner.any():
        raise ValueError(f"accuracy_table: est_ecef_m has {int(inner.sum())} row(s) within 1000 km of the Earth's "
                         f"centre (first {est[inner][0].tolist()}): it must be ECEF metres, not latitude/longitude/"
                         "height (Solution.pos_ecef_m, not Solution.geodetic())")
    err = enu_errors(est, truth)
    labelled = np.isfinite(truth).all(axis=1)
    solved = labelled & avail & np.isfinite(est).all(axis=1)
    e = err[solved]
    h = np.hypot(e[:, 0], e[:, 1])
    d3 = np.linalg.norm(e, axis=1)
    n_lab, n_sol = int(labelled.sum()), int(solved.sum())
    row: dict = dict(labels)
    row.update({
        "n_labelled": n_lab,
        "n_solved": n_sol,
        "availability": n_sol / n_lab if n_lab else float("nan"),
        "rmse_e_m": _rms(e[:, 0]),
        "rmse_n_m": _rms(e[:, 1]),
        "rmse_u_m": _rms(e[:, 2]),
        "rmse_2d_m": _rms(h),
        "rmse_3d_m": _rms(d3),
        "p50_2d_m": _pct(h, 50),
        "p95_2d_m": _pct(h, 95),
        "p50_3d_m": _pct(d3, 50),
        "p95_3d_m": _pct(d3, 95),
    })
    return row


def _columns(rows: list[Mapping]) -> list[str]:
    """Label keys (in first-seen order) then the metric keys."""
    labels: list[str] = []
    for row in rows:
        labels += [k for k in row if k not in METRIC_COLUMNS and k not in labels]
    return labels + list(METRIC_COLUMNS)


def _cell(key: str, value, digits: int) -> str:
    if value is None:
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            return "-"
        if key == "availability":
            return f"{100.0 * value:.1f}"
        if key == "epochs_per_s":            # a timing that moves by tens of % between runs: whole epochs
            return f"{value:.0f}"
        return f"{value:.{digits}f}"
    return str(value)


def _table(rows: Iterable[Mapping], digits: int) -> tuple[list[str], list[list[str]]]:
    rows = list(rows)
    cols = _columns(rows)
    head = [METRIC_COLUMNS.get(c, c) for c in cols]
    body = [[_cell(c, row.get(c), digits) for c in cols] for row in rows]
    return head, body


def format_markdown(rows: Iterable[Mapping], digits: int = 2, columns: list[str] | None = None) -> str:
    """Rows of :func:`accuracy_table` as a Markdown table (labels left, numbers right-aligned).

    ``columns``: only these keys (e.g. ``["method", "rmse_2d_m", "rmse_3d_m"]``), in that order; default: the labels
    and every metric. Missing or non-finite values print as ``-``; availability prints in percent.
    """
    rows = list(rows)
    cols = _columns(rows) if columns is None else list(columns)
    head = [METRIC_COLUMNS.get(c, c) for c in cols]
    body = [[_cell(c, row.get(c), digits) for c in cols] for row in rows]
    return _markdown(head, body, ["---:" if c in METRIC_COLUMNS else "---" for c in cols])


def markdown_table(rows: Iterable[Mapping], keys: list[str] | None = None, digits: int = 2) -> str:
    """Any dict rows as a Markdown table of ``keys`` (default: the first row's); cells as in format_markdown."""
    rows = list(rows)
    keys = list(rows[0]) if keys is None and rows else list(keys or [])
    return _markdown(keys, [[_cell(k, r.get(k), digits) for k in keys] for r in rows], ["---"] * len(keys))


def _markdown(head: list[str], body: list[list[str]], align: list[str]) -> str:
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(r) + " |" for r in body]
    return "\n".join(lines) + "\n"


def format_text(rows: Iterable[Mapping], digits: int = 2) -> str:
    """Rows of :func:`accuracy_table` as a fixed-width plain-text table."""
    head, body = _table(rows, digits)
    n_lab = len(head) - len(METRIC_COLUMNS)
    widths = [max(len(head[i]), *(len(r[i]) for r in body)) if body else len(head[i]) for i in range(len(head))]

    def line(cells: list[str]) -> str:
        return "  ".join(c.ljust(w) if i < n_lab else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    out = [line(head), "  ".join("-" * w for w in widths)] + [line(r) for r in body]
    return "\n".join(s.rstrip() for s in out) + "\n"
