"""What every back end owes a library user: its own time array, checked noise, honest covariances and clocks."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import estimators
from estimators.base import STATUS_COASTED
from estimators.fgo import position_blind_epochs
from lfgnss.simulate import simulate_sequence


@pytest.fixture(scope="module")
def seq():
    return simulate_sequence(40, seed=3)


@pytest.mark.parametrize("backend", ["ekf", "plain-ekf", "fgo", "wls", "wls-weighted"])
def test_solution_time_is_a_copy_of_the_sequences(seq, backend):
    """Editing a Solution's times (seconds since start, for a plot) must not shift the Sequence's."""
    before = seq.time_gps_s.copy()
    sol = estimators.create(backend).solve(seq)
    t = sol.time_gps_s
    t -= t[0]
    np.testing.assert_array_equal(seq.time_gps_s, before)


def _bad_noise(kind):
    def noise(s):
        r, vc = np.where(s.mask, 25.0, 1.0), np.zeros(s.mask.shape)
        first = np.argwhere(s.mask)[3]
        if kind == "nan":
            r[tuple(first)] = np.nan
        elif kind == "negative":
            r[tuple(first)] = -4.0
        else:
            r = r[:, :3]
        return r, vc
    return noise


@pytest.mark.parametrize("backend", ["ekf", "fgo", "wls-weighted"])
@pytest.mark.parametrize("kind, message", [("nan", "non-positive or NaN R"),
                                           ("negative", "non-positive or NaN R"), ("shape", "shapes")])
def test_a_bad_noise_model_is_named_by_every_back_end(seq, backend, kind, message):
    with pytest.raises(ValueError, match=message):
        estimators.create(backend, noise=_bad_noise(kind)).solve(seq)


@pytest.mark.parametrize("backend", ["ekf", "fgo", "wls-weighted"])
def test_an_infinite_r_switches_a_satellite_off_as_a_huge_one_does(seq, backend):
    """Review: R = inf was refused as 'non-finite', though an R above R_OFF_M2 (1e30, say) switches a satellite off."""
    def noise(r_off, vc_off):
        def model(s):
            r, vc = np.full(s.mask.shape, 25.0), np.zeros(s.mask.shape)
            r[:, 0], vc[:, 0] = r_off, vc_off
            return r, vc
        return model

    off = estimators.create(backend, noise=noise(np.inf, np.nan)).solve(seq)
    huge = estimators.create(backend, noise=noise(1e30, 0.0)).solve(seq)
    np.testing.assert_array_equal(off.pos_ecef_m, huge.pos_ecef_m)


def test_least_squares_without_redundancy_keeps_a_plausible_covariance(seq):
    """An epoch with as many satellites as unknowns has zero residuals: its covariance must not collapse to 0."""
    mask = seq.mask.copy()
    k = 10
    keep = [np.flatnonzero(mask[k] & (seq.system_index[k] == j)) for j in range(len(seq.systems))]
    mask[k] = False
    mask[k, np.concatenate([keep[0][:3], keep[1][:2]])] = True             # 5 satellites, 3 + 2 unknowns
    sol = estimators.create("wls").solve(replace(seq, mask=mask))
    sd = np.sqrt(np.trace(sol.cov_ecef_m2, axis1=1, axis2=2))
    others = np.delete(sd, k)
    assert sd[k] > 0.5 * np.median(others)                                 # of the epochs' size, not 1e-7 m


def test_least_squares_clock_is_nan_where_the_reference_system_is_absent(seq):
    mask = seq.mask & ~((seq.system_index == 0) & (np.arange(len(seq))[:, None] < 5))
    for backend in ("wls", "wls-weighted"):
        sol = estimators.create(backend).solve(replace(seq, mask=mask))
        assert np.isnan(sol.clock_m[:5]).all() and np.isfinite(sol.clock_m[5:]).all()
        assert np.isfinite(sol.pos_ecef_m).all()


@pytest.mark.parametrize("mode", ["batch", "fixed-lag"])
def test_factor_graph_reports_position_blind_epochs_as_coasted(seq, mode):
    """One satellite per constellation goes to its clock: the position is the motion model's, status coasted."""
    mask = seq.mask.copy()
    for k in range(20, 24):
        keep = [np.flatnonzero(mask[k] & (seq.system_index[k] == j))[0] for j in range(len(seq.systems))]
        mask[k] = False
        mask[k, keep] = True
    blind_seq = replace(seq, mask=mask)
    assert np.flatnonzero(position_blind_epochs(blind_seq)).tolist() == [20, 21, 22, 23]
    sol = estimators.create("fgo", mode=mode).solve(blind_seq)
    assert np.all(sol.status[20:24] == STATUS_COASTED) and np.all(sol.n_used[20:24] == 0)
    assert np.isfinite(sol.clock_m[20:24]).all()


def test_progress_bar_is_tqdm_and_changes_nothing(seq, monkeypatch):
    import sys

    from tqdm.auto import tqdm

    from estimators.base import epoch_range

    assert epoch_range(0, 5, True, "x") == range(0, 5)          # stderr not a terminal: no bar, tqdm not imported
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert isinstance(epoch_range(0, 5, True, "x"), tqdm) and list(epoch_range(0, 5, True, "x")) == list(range(5))
    assert epoch_range(2, 5, False, "x") == range(2, 5)
    for backend, options in (("ekf", {}), ("fgo", {"mode": "fixed-lag"}), ("fgo", {})):
        quiet = estimators.create(backend, **options).solve(seq)
        shown = estimators.create(backend, progress=True, **options).solve(seq)
        np.testing.assert_array_equal(quiet.pos_ecef_m, shown.pos_ecef_m)


def test_noise_model_runs_in_chunks_of_epochs_with_the_same_result(seq, monkeypatch):
    """The network's memory is linear in the epochs of one pass; chunking must not change a bit."""
    import learning.export as export
    from lfgnss.paths import default_model_path

    model = export.load_model(default_model_path())
    whole = model(seq)
    monkeypatch.setattr(export, "PREDICT_CHUNK_EPOCHS", 7)
    for a, b in zip(whole, model(seq)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("backend", ["wls", "wls-weighted"])
def test_least_squares_leaves_out_fixes_the_coarse_fix_rejects(seq, backend):
    """A fix with its satellites in one spot of the sky (GDOP beyond 50) or kilometres underground had a position and
    status updated (an urbannav drive: 1699 epochs written where the coarse fix kept 1696, one 2 km underground)."""
    from estimators.baselines import plausible_fix
    from estimators.base import STATUS_NONE

    sat = seq.sat_pos_ecef_m.copy()
    sat[7] = sat[7, :1] + 1000.0 * np.arange(seq.n_slots)[:, None]     # every satellite within km of the first
    clustered = replace(seq, sat_pos_ecef_m=sat)
    sol = estimators.create(backend).solve(clustered)
    assert sol.status[7] == STATUS_NONE and np.isnan(sol.pos_ecef_m[7]).all()
    assert (sol.status[np.arange(len(seq)) != 7] != STATUS_NONE).all()
    if backend == "wls":            # equal weights need no stored elevation (wls-weighted's noise model reads them)
        blind = replace(seq, el_rad=np.zeros_like(seq.el_rad), az_rad=np.full_like(seq.az_rad, np.nan))
        np.testing.assert_array_equal(estimators.create(backend).solve(blind).pos_ecef_m,
                                      estimators.create(backend).solve(seq).pos_ecef_m)
    under = sol.pos_ecef_m.copy()
    under[3] *= 0.999                                           # 6 km below the ground
    assert plausible_fix(np.nan_to_num(under), seq)[[2, 3, 4]].tolist() == [True, False, True]
