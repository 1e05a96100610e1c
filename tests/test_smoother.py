"""RTS smoother (estimators.smoother) against filterpy's and a batch solution, and as the EKF's ``smooth`` option."""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from estimators.base import STATUS_NONE, STATUS_RESET, create
from estimators.smoother import lag_horizon, rts_smooth
from lfgnss.constants import SPEED_OF_LIGHT_M_S
from lfgnss.simulate import simulate_sequence

N, M, T = 4, 2, 30


def _linear_system(seed: int):
    """A random linear-Gaussian system: x0 prior, F_k, Q_k, H_k, R_k, inputs u_k and measurements z_k."""
    rng = np.random.default_rng(seed)
    f = np.eye(N) + 0.1 * rng.normal(size=(T, N, N))
    q = np.stack([a @ a.T + 0.1 * np.eye(N) for a in 0.3 * rng.normal(size=(T, N, N))])
    h = rng.normal(size=(T, M, N))
    r = np.stack([np.diag(d) for d in rng.uniform(0.5, 2.0, size=(T, M))])
    u = np.zeros((T, N))
    u[17] = [300.0, 0.0, -50.0, 0.0]                 # a deterministic jump, like the EKF's clock realignment
    z = rng.normal(scale=3.0, size=(T, M))
    return np.zeros(N), 10.0 * np.eye(N), f, q, h, r, u, z


def _kalman_filter(m0, p0, f, q, h, r, u, z):
    """Posteriors and priors of the textbook filter (Joseph update), priors ``F x + u``."""
    xs, ps, xp, pp = (np.zeros((T, N)), np.zeros((T, N, N)), np.zeros((T, N)), np.zeros((T, N, N)))
    x, p = m0, p0
    for k in range(T):
        if k:
            x, p = f[k] @ x + u[k], f[k] @ p @ f[k].T + q[k]
        xp[k], pp[k] = x, p
        gain = p @ h[k].T @ np.linalg.inv(h[k] @ p @ h[k].T + r[k])
        a = np.eye(N) - gain @ h[k]
        x, p = x + gain @ (z[k] - h[k] @ x), a @ p @ a.T + gain @ r[k] @ gain.T
        xs[k], ps[k] = x, p
    return xs, ps, xp, pp


def _batch(m0, p0, f, q, h, r, u, z):
    """Mean and marginal covariances of p(x_0..x_T-1 | z) from the stacked whitened least-squares problem."""
    rows, rhs = [], []

    def add(block_of: dict, residual: np.ndarray, cov: np.ndarray) -> None:
        w = np.linalg.cholesky(np.linalg.inv(cov)).T
        row = np.zeros((residual.size, T * N))
        for k, a in block_of.items():
            row[:, k * N:(k + 1) * N] = a
        rows.append(w @ row)
        rhs.append(w @ residual)

    add({0: np.eye(N)}, m0, p0)
    for k in range(T):
        if k:
            add({k: np.eye(N), k - 1: -f[k]}, u[k], q[k])
        add({k: h[k]}, z[k], r[k])
    a, b = np.vstack(rows), np.concatenate(rhs)
    cov = np.linalg.inv(a.T @ a)
    mean = cov @ a.T @ b
    return mean.reshape(T, N), np.stack([cov[k * N:(k + 1) * N, k * N:(k + 1) * N] for k in range(T)])


def test_smoother_equals_the_batch_solution_with_inputs():
    system = _linear_system(0)
    xs, ps, xp, pp = _kalman_filter(*system)
    restart = np.zeros(T, bool)
    restart[0] = True
    mean, cov = rts_smooth(xs, ps, xp, pp, system[2], restart)
    want_mean, want_cov = _batch(*system)
    np.testing.assert_allclose(mean, want_mean, atol=1e-8 * np.abs(want_mean).max())
    np.testing.assert_allclose(cov, want_cov, atol=1e-9 * np.abs(want_cov).max())
    assert not np.allclose(mean, xs)                                     # it did smooth


def test_smoother_matches_filterpy_without_inputs():
    m0, p0, f, q, h, r, _, z = _linear_system(1)
    kf = KalmanFilter(dim_x=N, dim_z=M)
    kf.x, kf.P = m0.copy(), p0.copy()
    # filterpy's batch_filter predicts before the first update; give it identity/zero there, as ours starts at x0.
    f0, q0 = f.copy(), q.copy()
    f0[0], q0[0] = np.eye(N), np.zeros((N, N))
    xs, ps, xp, pp = kf.batch_filter(z, Fs=list(f0), Qs=list(q0), Hs=list(h), Rs=list(r))
    want, want_p, _, _ = kf.rts_smoother(xs, ps, Fs=list(f0), Qs=list(q0))
    mean, cov = rts_smooth(xs, ps, xp, pp, f0, np.eye(1, T, dtype=bool)[0])
    np.testing.assert_allclose(mean, want, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(cov, want_p, rtol=1e-9, atol=1e-9)


def _filtered_run(seed: int, restarts: list[int]):
    """A filter run of a random system: posteriors, priors, transitions and a restart mask."""
    system = _linear_system(seed)
    restart = np.zeros(T, bool)
    restart[restarts] = True
    return (*_kalman_filter(*system), system[2], restart)


def test_restarts_split_the_run_and_empty_epochs_stay_empty():
    xs, ps, xp, pp, f, restart = _filtered_run(2, [0, 12])
    xs[:3], ps[:3] = np.nan, np.nan                                      # no state yet
    restart[3] = True
    mean, cov = rts_smooth(xs, ps, xp, pp, f, restart)
    assert np.isnan(mean[:3]).all() and np.isnan(cov[:3]).all()
    first, _ = rts_smooth(xs[3:12], ps[3:12], xp[3:12], pp[3:12], f[3:12], np.eye(1, 9, dtype=bool)[0])
    second, _ = rts_smooth(xs[12:], ps[12:], xp[12:], pp[12:], f[12:], np.eye(1, T - 12, dtype=bool)[0])
    np.testing.assert_allclose(mean[3:12], first)
    np.testing.assert_allclose(mean[12:], second)
    np.testing.assert_array_equal(mean[11], xs[11])                      # a segment's last epoch is its filter's


def test_fixed_lag_is_the_whole_run_smoother_on_the_data_up_to_the_horizon():
    xs, ps, xp, pp, f, restart = _filtered_run(3, [0, 20])
    full = rts_smooth(xs, ps, xp, pp, f, restart)
    horizon = np.minimum(np.arange(T) + 4, T - 1)
    lagged = rts_smooth(xs, ps, xp, pp, f, restart, horizon)
    for k in (0, 7, 16, 17, 19, 20, 25, T - 1):
        h = horizon[k] + 1
        want = rts_smooth(xs[:h], ps[:h], xp[:h], pp[:h], f[:h], restart[:h])
        np.testing.assert_allclose(lagged[0][k], want[0][k], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(lagged[1][k], want[1][k], rtol=1e-12, atol=1e-9)
    for a, b in zip(rts_smooth(xs, ps, xp, pp, f, restart, np.full(T, T - 1)), full):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-9)                  # horizon at the end: the full run
    for a, b in zip(rts_smooth(xs, ps, xp, pp, f, restart, np.arange(T)), (xs, ps)):
        np.testing.assert_array_equal(a, b)                                      # no lag: the filter
    np.testing.assert_array_equal(lag_horizon(np.array([0.0, 0.2, 0.4, 1.0, 3.0]), 0.5), [2, 2, 2, 3, 4])
    np.testing.assert_array_equal(lag_horizon(np.arange(6) * 0.2, 0.6), [3, 4, 5, 5, 5, 5])   # 0.2 * 3 != 0.6


def _err(sol, seq) -> np.ndarray:
    return np.linalg.norm(sol.pos_ecef_m - seq.truth_ecef_m, axis=1)


def test_smoothed_ekf_is_more_accurate_and_keeps_the_forward_run():
    seq = simulate_sequence(300, seed=3, n_slots=18)
    forward = create("plain-ekf").solve(seq)
    smoothed = create("plain-ekf", smooth=True).solve(seq)
    np.testing.assert_array_equal(smoothed.status, forward.status)
    np.testing.assert_array_equal(smoothed.info["filtered_state"], forward.info["state"])
    np.testing.assert_allclose(smoothed.pos_ecef_m[-1], forward.pos_ecef_m[-1])
    rms = [float(np.sqrt(np.mean(_err(s, seq)[10:] ** 2))) for s in (forward, smoothed)]
    assert rms[1] < 0.8 * rms[0]
    # the smoothed covariance is smaller (it uses more data) and still positive definite
    assert (np.trace(smoothed.cov_ecef_m2[:-1], axis1=1, axis2=2) < np.trace(forward.cov_ecef_m2[:-1], axis1=1,
                                                                              axis2=2)).all()
    assert (np.linalg.eigvalsh(smoothed.cov_ecef_m2) > 0).all()
    # a fixed lag lies in between: no lag is the filter, a lag longer than the run is the whole-run smoother
    lags = {lag: create("plain-ekf", smooth=True, smooth_lag_s=lag).solve(seq) for lag in (0.0, 5.0, 1e6)}
    np.testing.assert_array_equal(lags[0.0].pos_ecef_m, forward.pos_ecef_m)
    np.testing.assert_allclose(lags[1e6].pos_ecef_m, smoothed.pos_ecef_m, rtol=0, atol=1e-6)
    lag5 = float(np.sqrt(np.mean(_err(lags[5.0], seq)[10:] ** 2)))
    assert rms[1] <= lag5 < rms[0]


def test_smoothing_neither_smears_a_clock_jump_nor_crosses_a_reset():
    seq = simulate_sequence(300, seed=3, n_slots=18)
    base = create("plain-ekf", smooth=True).solve(seq)
    jump = 1e-3 * SPEED_OF_LIGHT_M_S
    pr = seq.pr_m.copy()
    pr[150:] += np.where(seq.mask[150:], jump, 0.0)
    clock = seq.coarse_clock_m.copy()
    clock[150:, 0] += jump
    jumped = create("plain-ekf", smooth=True).solve(replace(seq, pr_m=pr, coarse_clock_m=clock))
    assert jumped.info["clock_realigned"][150]
    # the realignment is an input of the prior: the smoothed clock before the jump stays the unjumped one
    np.testing.assert_allclose(jumped.clock_m[:150], base.clock_m[:150], atol=1.0)
    assert np.abs(_err(jumped, seq) - _err(base, seq)).max() < 1.0

    time = seq.time_gps_s.copy()
    time[200:] += 100.0
    coarse = seq.coarse_ecef_m.copy()
    coarse[:5] = np.nan                                                   # no fix yet
    gap = create("plain-ekf", smooth=True).solve(replace(seq, time_gps_s=time, coarse_ecef_m=coarse))
    assert gap.status[200] == STATUS_RESET and (gap.status[:5] == STATUS_NONE).all()
    assert np.isnan(gap.pos_ecef_m[:5]).all() and np.isfinite(gap.pos_ecef_m[5:]).all()
    np.testing.assert_array_equal(gap.pos_ecef_m[199], gap.info["filtered_state"][199, :3])


def test_smoothing_helps_the_shipped_model_on_the_bundled_drive():
    """Real data: the bundled Berlin drive (smartLoc) with the bundled model, forward against smoothed."""
    import lfgnss
    from learning.export import load_model
    from lfgnss.datasets import DatasetSpec, align_truth
    from lfgnss.metrics import accuracy_table
    from lfgnss.solve import DEFAULT_MODEL, SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH

    meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
    spec = DatasetSpec("sample", (SAMPLE_OBS,), SAMPLE_NAV, SAMPLE_TRUTH, "smartloc",
                       time_origin_gps_s=meas.time_gps_s[0])
    truth, _ = align_truth(meas.time_gps_s, spec)
    seq = lfgnss.build_sequence(meas, lfgnss.spp(meas), truth_ecef_m=truth)
    noise = load_model(DEFAULT_MODEL)
    rows = [accuracy_table(sol.pos_ecef_m, truth, sol.available)
            for sol in (create("ekf", noise=noise).solve(seq), create("ekf", noise=noise, smooth=True).solve(seq))]
    assert rows[0]["availability"] == rows[1]["availability"] == 1.0
    assert rows[1]["rmse_3d_m"] < 0.9 * rows[0]["rmse_3d_m"] and rows[1]["rmse_2d_m"] < rows[0]["rmse_2d_m"]


def test_lag_benchmark_script_on_a_validation_split(tmp_path):
    """``benchmarks/smoothing_lag.py``: its forward column is the filter, its last the whole-run smoother."""
    from lfgnss import datasets
    from lfgnss.metrics import accuracy_table

    if datasets.get("hk-tst-static-2020").missing():
        pytest.skip(f"shared data missing ({datasets.get('hk-tst-static-2020').missing()[0]})")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import smoothing_lag

    rows = smoothing_lag.run(["hk-tst-static-2020"], "val")
    assert len(rows) == 2 * len(smoothing_lag.LAGS_S) and all(r["availability"] == 1.0 for r in rows)
    seq = datasets.load_split("hk-tst-static-2020", "val")[0]
    for smooth, lag in ((False, 0.0), (True, float("inf"))):
        sol = create("plain-ekf", smooth=smooth).solve(seq)
        want = accuracy_table(sol.pos_ecef_m, seq.truth_ecef_m, sol.available)["rmse_3d_m"]
        assert [r["rmse_3d_m"] for r in rows if r["filter"] == "plain EKF" and r["lag_s"] == lag] == [want]
    page = smoothing_lag.markdown(rows, "val", "cmd")
    assert "| forward | 1 s |" in page and "whole run |" in page and page.count("| plain EKF |") == 1
    assert smoothing_lag.plot(rows, tmp_path / "lag.png", "val").stat().st_size > 10_000
