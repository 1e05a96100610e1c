"""ENU errors, accuracy rows and their tables."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from lfgnss.frames import enu_to_ecef, lla_to_ecef
from lfgnss.metrics import METRIC_COLUMNS, accuracy_table, enu_errors, format_markdown, format_text


def _truth_track(t=50):
    lat = np.radians(52.5 + 1e-4 * np.arange(t))
    lon = np.radians(13.37 + 2e-4 * np.arange(t))
    return lla_to_ecef(lat, lon, np.full(t, 40.0))


def test_enu_errors_recovers_offsets_in_local_frames():
    rng = np.random.default_rng(0)
    truth = np.concatenate([_truth_track(20), lla_to_ecef(np.radians([-33.9, 22.3]), np.radians([151.2, 114.2]),
                                                           np.array([10.0, 5.0]))])
    enu = rng.normal(0, 20, truth.shape)
    est = np.stack([enu_to_ecef(enu[k], truth[k]) for k in range(len(truth))])
    np.testing.assert_allclose(enu_errors(est, truth), enu, atol=1e-6)


def test_enu_errors_nan_rows_and_shape_check():
    truth = _truth_track(3)
    est = truth + 1.0
    est[1] = np.nan
    truth[2] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        err = enu_errors(est, truth)
    assert np.isfinite(err[0]).all() and np.isnan(err[1:]).all()
    with pytest.raises(ValueError):
        enu_errors(est[:, :2], truth[:, :2])


def test_accuracy_table_known_values_and_availability():
    truth = _truth_track(6)
    enu = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 12.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0],
                    [99.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    est = np.stack([enu_to_ecef(enu[k], truth[k]) for k in range(6)])
    available = np.array([True, True, True, False, True, True])
    truth[4] = np.nan          # unlabelled: ignored even though solved
    est[5] = np.nan            # claims availability but no position -> not solved
    row = accuracy_table(est, truth, available, dataset="x", method="m")
    assert list(row)[:2] == ["dataset", "method"]
    assert row["n_labelled"] == 5 and row["n_solved"] == 3
    assert row["availability"] == pytest.approx(3 / 5)
    used = enu[:3]
    assert row["rmse_e_m"] == pytest.approx(np.sqrt(np.mean(used[:, 0] ** 2)), abs=1e-6)
    assert row["rmse_u_m"] == pytest.approx(np.sqrt(144 / 3), abs=1e-6)
    assert row["rmse_2d_m"] == pytest.approx(np.sqrt((25 + 0 + 1) / 3), abs=1e-6)
    assert row["rmse_3d_m"] == pytest.approx(np.sqrt((25 + 144 + 1) / 3), abs=1e-6)
    assert row["p50_2d_m"] == pytest.approx(1.0, abs=1e-6)
    assert row["p50_3d_m"] == pytest.approx(5.0, abs=1e-6)
    assert row["p95_3d_m"] == pytest.approx(np.percentile([5.0, 12.0, 1.0], 95), abs=1e-6)


def test_accuracy_table_default_available_and_empty():
    truth = _truth_track(4)
    est = np.full((4, 3), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        row = accuracy_table(est, truth)
        empty = accuracy_table(est, np.full((4, 3), np.nan))
    assert row["n_solved"] == 0 and row["availability"] == 0.0 and np.isnan(row["rmse_3d_m"])
    assert empty["n_labelled"] == 0 and np.isnan(empty["availability"])
    with pytest.raises(ValueError):
        accuracy_table(est, truth, np.ones(3, bool))


@pytest.mark.parametrize("est, truth, message", [
    ("one", "one", r"est_ecef_m has shape \(3,\), expected \(T, 3\) ECEF metres \(one epoch: \(1, 3\)\)"),
    ("all", None, r"truth_ecef_m is None, expected \(T, 3\)"),
    ("all", "half", r"est_ecef_m has 4 epochs and truth_ecef_m 2; they must be the same epochs"),
])
def test_accuracy_table_says_which_array_is_misshapen(est, truth, message):
    """Review: one epoch as (3,) arrays was 'available has shape (), expected (3,)' (its xyz read as epochs), and a
    truth of None 'cannot reshape array of size 1 into shape (3)'."""
    track = _truth_track(4)
    pick = {"one": track[0], "all": track, "half": track[:2], None: None}
    with pytest.raises(ValueError, match=r"^accuracy_table: " + message):
        accuracy_table(pick[est] + 1.0, pick[truth])


def test_tables_format_rows():
    truth = _truth_track(10)
    est = truth + 2.0
    rows = [accuracy_table(est, truth, method="ekf"), accuracy_table(np.full_like(est, np.nan), truth, method="ls")]
    md = format_markdown(rows)
    lines = md.strip().splitlines()
    assert len(lines) == 4
    assert lines[0].startswith("| method | labelled | solved | avail. [%] |")
    assert lines[1].count("---:") == len(METRIC_COLUMNS)
    assert "| ekf | 10 | 10 | 100.0 |" in md
    assert "| ls | 10 | 0 | 0.0 | - |" in md
    assert "nan" not in md.lower()
    txt = format_text(rows)
    tl = txt.strip().splitlines()
    assert len(tl) == 4 and tl[0].startswith("method")
    assert len({len(tl[0]), len(tl[1])}) == 1
    assert "nan" not in txt.lower()


def test_format_markdown_takes_only_the_columns_asked_for():
    """A table of a few columns: their headings, numbers right-aligned, no "-" for the metrics not asked for."""
    from lfgnss.metrics import METRIC_COLUMNS, accuracy_table, format_markdown

    truth = np.zeros((4, 3)) + [6378137.0, 0.0, 0.0]
    row = accuracy_table(truth + [[0, 3, 4]] * 4, truth, np.ones(4, bool), method="x")
    lines = format_markdown([row], columns=["method", "availability", "rmse_3d_m"]).splitlines()
    assert lines[0] == f"| method | {METRIC_COLUMNS['availability']} | {METRIC_COLUMNS['rmse_3d_m']} |"
    assert lines[1] == "| --- | ---: | ---: |" and lines[2] == "| x | 100.0 | 5.00 |"
    assert format_markdown([row]) == format_markdown([row], columns=None)           # the default: every column
    assert " - " not in format_markdown([row])
    timed = format_markdown([row | {"epochs_per_s": 35540.66}], columns=["method", "epochs_per_s"])
    assert timed.splitlines()[2] == "| x | 35541 |"                     # a timing: whole epochs, not 35540.66
