"""Filter faults on real data: outliers, a receiver clock jump and a 60 s outage, for the EKF and the FGO.

The bundled Berlin drive (u-blox GPS+GLONASS, 5 Hz, deep urban canyon) is turned into a Sequence with
``lfgnss.load`` / ``spp`` / ``build_sequence``; its first ``N_EPOCHS`` epochs (123 s) are the fault-free
run. Faults are injected into the Sequence arrays, as the measurements would carry them:

* outlier: +300 m on the most observed satellite every 10 epochs;
* clock jump: +1 ms (299.8 km) on every pseudorange from epoch 200 on; the coarse least-squares fix of
  those epochs absorbs it in its clock (``coarse_clock_m``), as it would on such data;
* outage: no satellite and no coarse fix for 60 s (masked epochs: a tunnel), or the same 60 s with no
  epoch at all (a time gap, as a receiver writes it).

What is asserted ("recover within a few epochs and never end more than 100 m from the coarse fix"):
the urban coarse fix of this drive is itself often 100+ m off (the fault-free EKF is up to ~130 m from
it), so the bound is taken as: from ``RECOVERY_EPOCHS`` (2 s) after each fault event on (the first outlier
for the outliers, which come every ``RECOVERY_EPOCHS``), every epoch
with a coarse fix is within 100 m of it, or no more than ``MARGIN_M`` farther from it than the fault-free
run of the same estimator; the same at the last epoch. The stronger form is asserted too: those
epochs are all within 100 m of the ground truth (the faulted runs stay within ~60 m of it). Per fault: outliers never move the solution more
than ``OUTLIER_TOL_M`` farther from the truth than the fault-free one; the clock jump leaves the factor
graph unchanged (a free clock per epoch) and the EKF realigns only its clock in the jump epoch; outage epochs are coasted with a
growing covariance, and the filter updates again right after; a time gap re-initialises the EKF.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import estimators
import lfgnss
from lfgnss.constants import SPEED_OF_LIGHT_M_S
import lfgnss.datasets
from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH

N_EPOCHS = 600
RECOVERY_EPOCHS = 10          # 2 s at 5 Hz
BOUND_M = 100.0
MARGIN_M = 10.0
OUTLIER_TOL_M = 15.0
CLOCK_JUMP_EPOCH = 200
OUTAGE_START_S, OUTAGE_S = 30.0, 60.0
BACKENDS = {"ekf": ("ekf", {}), "fgo": ("fgo", {}), "fgo-fixed-lag": ("fgo", {"mode": "fixed-lag"})}


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LFGNSS_CACHE", str(tmp_path_factory.mktemp("cache")))
        meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
        seq = lfgnss.build_sequence(meas, lfgnss.spp(meas))
    seq = seq.subset(slice(0, N_EPOCHS))
    assert np.isfinite(seq.coarse_ecef_m).all()
    return seq


@pytest.fixture(scope="module")
def truth(sequence) -> np.ndarray:
    return _sample_truth(sequence)


_CLEAN: dict = {}


def _sample_truth(seq) -> np.ndarray:
    """(T, 3) ground truth of the bundled drive at the sequence's epochs [m] (NaN where none)."""
    spec = lfgnss.datasets.DatasetSpec("sample", (SAMPLE_OBS,), tuple(SAMPLE_NAV), SAMPLE_TRUTH, "smartloc",
                                       match_tolerance_s=0.05, time_origin_gps_s=float(seq.time_gps_s[0]))
    return lfgnss.datasets.align_truth(seq.time_gps_s, spec)[0]


def _clean(seq, backend: str):
    if backend not in _CLEAN:
        name, options = BACKENDS[backend]
        _CLEAN[backend] = estimators.create(name, **options).solve(seq)
    return _CLEAN[backend]


# ----------------------------------------------------------------------------------------------- faults
def with_outliers(seq):
    """+300 m on the most observed satellite slot every 10 epochs; returns (sequence, event epochs)."""
    j = int(np.argmax(seq.mask.sum(axis=0)))
    epochs = np.arange(5, len(seq), 10)
    epochs = epochs[seq.mask[epochs, j]]
    pr = seq.pr_m.copy()
    pr[epochs, j] += 300.0
    return replace(seq, pr_m=pr), epochs


def with_clock_jump(seq, k0: int = CLOCK_JUMP_EPOCH, jump_s: float = 1e-3):
    pr = seq.pr_m.copy()
    pr[k0:] = np.where(seq.mask[k0:], pr[k0:] + SPEED_OF_LIGHT_M_S * jump_s, 0.0)
    clock = seq.coarse_clock_m.copy()
    clock[k0:, 0] += SPEED_OF_LIGHT_M_S * jump_s
    return replace(seq, pr_m=pr, coarse_clock_m=clock), np.array([k0])


def _outage_epochs(seq) -> np.ndarray:
    t = seq.time_gps_s - seq.time_gps_s[0]
    return (t >= OUTAGE_START_S) & (t < OUTAGE_START_S + OUTAGE_S)


def with_outage(seq):
    """60 s of epochs without any satellite and without a coarse fix; events: first epoch after it."""
    out = _outage_epochs(seq)

    def blank(a, value=0):
        return np.where(out.reshape((-1,) + (1,) * (a.ndim - 1)), value, a)

    faulted = replace(seq, mask=seq.mask & ~out[:, None], system_index=blank(seq.system_index, -1),
                      pr_m=blank(seq.pr_m), sat_pos_ecef_m=blank(seq.sat_pos_ecef_m), cn0_dbhz=blank(seq.cn0_dbhz),
                      el_rad=blank(seq.el_rad), az_rad=blank(seq.az_rad), features=blank(seq.features),
                      coarse_ecef_m=blank(seq.coarse_ecef_m, np.nan), coarse_clock_m=blank(seq.coarse_clock_m, np.nan))
    idx = np.flatnonzero(out)
    return faulted, np.array([idx[-1] + 1])


def with_gap(seq):
    """The same 60 s removed: one time step of 60 s; event: first epoch after the gap."""
    out = _outage_epochs(seq)
    return seq.subset(~out), np.array([int(np.flatnonzero(out)[0])])


FAULTS = {"outlier": with_outliers, "clock_jump": with_clock_jump, "outage": with_outage, "gap": with_gap}


# ----------------------------------------------------------------------------------------------- checks
def _check_recovery(seq, faulted, events, sol, clean, truth) -> None:
    keep = np.isin(seq.time_gps_s, faulted.time_gps_s)
    ref = clean.pos_ecef_m[keep]
    coarse = faulted.coarse_ecef_m
    has_coarse = np.isfinite(coarse).all(axis=1)
    d = np.linalg.norm(sol.pos_ecef_m - coarse, axis=1)
    d_clean = np.linalg.norm(ref - coarse, axis=1)
    limit = np.maximum(BOUND_M, d_clean) + MARGIN_M
    settled = np.ones(len(faulted), bool)
    for k in [0, *np.atleast_1d(events)]:
        settled[k: k + RECOVERY_EPOCHS] = False
    check = settled & has_coarse
    assert check.sum() > len(faulted) // 3, "too few epochs to check"
    bad = np.flatnonzero(check & ~(d <= limit))
    assert bad.size == 0, (f"{bad.size} epochs beyond the bound, first {bad[:5]}: "
                           f"{d[bad[:5]].round(1)} m from the coarse fix, fault-free {d_clean[bad[:5]].round(1)} m")
    last = np.flatnonzero(has_coarse)[-1]
    assert d[last] <= limit[last], (d[last], d_clean[last])
    # the stronger form of the bound: the same epochs are within BOUND_M of the truth (the coarse fix
    # itself is up to ~140 m from it on this drive)
    err = np.linalg.norm(sol.pos_ecef_m - truth[keep], axis=1)
    assert np.isfinite(err[check]).mean() > 0.9, "too few epochs with ground truth"
    far = np.flatnonzero(check & ~(err <= BOUND_M) & np.isfinite(err))
    assert far.size == 0, (f"{far.size} epochs more than {BOUND_M} m from the truth, first {far[:5]}: "
                           f"{err[far[:5]].round(1)}")


def _check_solution(faulted, sol) -> None:
    assert sol.pos_ecef_m.shape == (len(faulted), 3)
    has = sol.status != estimators.STATUS_NONE
    assert has.all(), "every epoch has a position (the first one has a coarse fix)"
    assert np.isfinite(sol.pos_ecef_m).all() and np.isfinite(sol.cov_ecef_m2).all()


CASES = [(b, f) for b in BACKENDS for f in FAULTS]


@pytest.mark.parametrize("backend, fault", CASES)
def test_fault_recovery(sequence, truth, backend, fault):
    faulted, events = FAULTS[fault](sequence)
    name, options = BACKENDS[backend]
    sol = estimators.create(name, **options).solve(faulted)
    clean = _clean(sequence, backend)
    _check_solution(faulted, sol)
    # outliers come every 10 epochs, as long as the recovery time: the bound holds from the first one on
    _check_recovery(sequence, faulted, events[:1] if fault == "outlier" else events, sol, clean, truth)

    status = sol.status
    if fault == "outlier":
        # Against the truth: an outlier may shift when a reset happens (a reset is discontinuous, and
        # the fault-free run on this drive is itself sometimes stuck 80+ m off), but it must never make
        # the position worse by more than OUTLIER_TOL_M.
        err = np.linalg.norm(sol.pos_ecef_m - truth, axis=1)
        err_clean = np.linalg.norm(clean.pos_ecef_m - truth, axis=1)
        worse = np.nan_to_num(err - err_clean)
        assert np.isfinite(truth).mean() > 0.9 and worse.max() <= OUTLIER_TOL_M, (worse.max(), int(np.argmax(worse)))
    elif fault == "clock_jump":
        if backend == "ekf":
            # only the clock is realigned: no reset, and the track stays on the fault-free one
            assert sol.info["clock_realigned"][CLOCK_JUMP_EPOCH] and status[CLOCK_JUMP_EPOCH] == estimators.STATUS_UPDATED
            assert not np.any(status == estimators.STATUS_COASTED)
            gap = np.linalg.norm(sol.pos_ecef_m - clean.pos_ecef_m, axis=1)
            # the median innovation misses the jump by a few metres (multipath), which the track
            # absorbs over some seconds; a reset to this drive's coarse fix would move it ~100 m
            assert gap[CLOCK_JUMP_EPOCH:].max() < 20.0, gap[CLOCK_JUMP_EPOCH:].max()
        else:                                   # a free clock per epoch: the jump changes nothing
            np.testing.assert_allclose(sol.pos_ecef_m, clean.pos_ecef_m, atol=0.5)
    elif fault == "outage":
        out = _outage_epochs(sequence)
        assert np.all(status[out] == estimators.STATUS_COASTED)
        after = events[0]
        assert status[after] in (estimators.STATUS_UPDATED, estimators.STATUS_RESET)
        assert np.all(sol.n_used[after: after + RECOVERY_EPOCHS] > 0)
        if backend == "ekf":                    # uncertainty grows while coasting, shrinks again after
            trace = np.trace(sol.cov_ecef_m2, axis1=1, axis2=2)
            idx = np.flatnonzero(out)
            assert np.all(np.diff(trace[idx]) > 0) and trace[after] < trace[idx[-1]]
        if backend == "fgo-fixed-lag":          # causal: back on the satellites in the first epoch after it
            assert np.linalg.norm(sol.pos_ecef_m[after] - faulted.coarse_ecef_m[after]) <= BOUND_M
    elif fault == "gap":
        after = events[0]
        dt = np.diff(faulted.time_gps_s)[after - 1]
        assert dt >= OUTAGE_S - 0.5
        if backend == "ekf":
            assert status[after] == estimators.STATUS_RESET
        assert np.all(sol.n_used[after: after + RECOVERY_EPOCHS] > 0)


def test_fault_free_reference_is_sane(sequence):
    """The reference runs themselves: finite, updated almost everywhere, close to the coarse fix overall."""
    for backend in ("ekf", "fgo"):
        sol = _clean(sequence, backend)
        _check_solution(sequence, sol)
        d = np.linalg.norm(sol.pos_ecef_m - sequence.coarse_ecef_m, axis=1)
        assert np.median(d) < BOUND_M, (backend, np.median(d))
        assert np.mean(sol.status == estimators.STATUS_UPDATED) > 0.95
