"""Weighted least-squares fix: against scipy's solver on a simulated epoch, known noise values, the residual feature."""
import numpy as np
import pytest
from scipy.optimize import least_squares

import lfgnss
from estimators.noise import HeuristicNoise
from lfgnss.corrections import geometric_range_m
from lfgnss.frames import lla_to_ecef
from lfgnss.sequence import DEFAULT_FEATURES
from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS
from lfgnss.weighted_fix import cn0_elevation_variance_m2, weighted_least_squares


def _epoch(rng, n_gps=7, n_bds=5):
    """One epoch: receiver in Hong Kong, satellites at 20,000 km, GPS clock 3 km, BeiDou ISB 12 m."""
    rcv = lla_to_ecef(np.radians(22.3), np.radians(114.2), 10.0)
    up = rcv / np.linalg.norm(rcv)
    n = n_gps + n_bds
    dirs = rng.normal(size=(n, 3)) + 2.5 * up
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    sats = rcv + 2.2e7 * dirs
    sys_idx = np.r_[np.zeros(n_gps, int), np.ones(n_bds, int)]
    pr = geometric_range_m(sats, rcv) + 3000.0 + 12.0 * sys_idx
    return rcv, sats, sys_idx, pr


def test_noiseless_epoch_recovers_position_clock_and_isb():
    rcv, sats, sys_idx, pr = _epoch(np.random.default_rng(0))
    mask = np.ones((1, pr.size), bool)
    fix = weighted_least_squares(pr[None], sats[None], sys_idx[None], mask, 2, (rcv + [80.0, -50.0, 30.0])[None],
                                 np.linspace(1.0, 50.0, pr.size)[None])
    assert fix.ok[0]
    np.testing.assert_allclose(fix.pos_ecef_m[0], rcv, atol=1e-6)
    np.testing.assert_allclose(fix.clock_m[0], [3000.0, 3012.0], atol=1e-6)
    np.testing.assert_allclose(fix.residual_m[0], 0.0, atol=1e-6)


def test_matches_scipy_weighted_solution_with_a_reflected_signal():
    rng = np.random.default_rng(1)
    rcv, sats, sys_idx, pr = _epoch(rng)
    pr = pr + rng.normal(0.0, 2.0, pr.size)
    pr[3] += 40.0                                   # a reflected (NLOS) signal ...
    r = np.full(pr.size, 4.0)
    r[3] = 400.0                                    # ... that the C/N0 weighting distrusts
    mask = np.ones((1, pr.size), bool)
    fix = weighted_least_squares(pr[None], sats[None], sys_idx[None], mask, 2, rcv[None] + 100.0, r[None])

    def whitened(x):
        return (pr - geometric_range_m(sats, x[:3]) - x[3:][sys_idx]) / np.sqrt(r)

    ref = least_squares(whitened, np.r_[rcv + 100.0, 0.0, 0.0], xtol=1e-12, ftol=1e-12).x
    np.testing.assert_allclose(fix.pos_ecef_m[0], ref[:3], atol=1e-4)
    np.testing.assert_allclose(fix.residual_m[0], whitened(ref) * np.sqrt(r), atol=1e-4)
    # the weighted fix leaves most of the 40 m on the reflected satellite; equal weights spread it out
    equal = weighted_least_squares(pr[None], sats[None], sys_idx[None], mask, 2, rcv[None] + 100.0,
                                   np.ones((1, pr.size)))
    assert fix.residual_m[0, 3] > 30.0 > equal.residual_m[0, 3]


def test_too_few_satellites_or_no_start_is_not_ok():
    rcv, sats, sys_idx, pr = _epoch(np.random.default_rng(2), n_gps=3, n_bds=1)
    mask = np.ones((2, pr.size), bool)
    start = np.stack([rcv, [np.nan] * 3])
    fix = weighted_least_squares(np.stack([pr, pr]), np.stack([sats, sats]), np.stack([sys_idx, sys_idx]), mask, 2,
                                 start, np.ones((2, pr.size)))
    assert not fix.ok.any()                          # 4 satellites, 5 unknowns; and no start
    assert np.all(np.isfinite(fix.residual_m))


def test_variance_known_values():
    """Zenith sigma 2.2 m at 45 dB-Hz, 3.7 m at 40, 10 m at 35, 32 m at 30; 1 / sin(el) below zenith, 5 deg floor."""
    sigma = np.sqrt(cn0_elevation_variance_m2(np.array([45.0, 40.0, 35.0, 30.0]), np.full(4, np.pi / 2)))
    np.testing.assert_allclose(sigma, [np.sqrt(5.0), np.sqrt(14.0), np.sqrt(104.0), np.sqrt(1004.0)])
    low = cn0_elevation_variance_m2(np.array([45.0, 45.0]), np.radians([30.0, 1.0]))
    np.testing.assert_allclose(low, [10.0, 5.0 / np.sin(np.radians(5.0))])


@pytest.fixture(scope="module")
def sample():
    meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
    fix = lfgnss.spp(meas)
    return meas, fix, lfgnss.build_sequence(meas, fix, feature_names=DEFAULT_FEATURES + ("residual_weighted",))


def test_residual_weighted_feature_is_the_weighted_fix_residual(sample):
    _, _, seq = sample
    feat = seq.features[..., 8]
    assert np.all(np.isfinite(feat)) and np.all(feat[~seq.mask] == 0.0)
    np.testing.assert_array_equal(seq.features[..., :8], lfgnss.build_sequence(*sample[:2]).features)
    r, _ = HeuristicNoise()(seq)
    fix = weighted_least_squares(seq.pr_m, seq.sat_pos_ecef_m, seq.system_index, seq.mask, len(seq.systems),
                                 seq.coarse_ecef_m, r)
    ok = fix.ok[:, None] & seq.mask
    assert ok.sum() > 0.9 * seq.mask.sum()
    np.testing.assert_allclose(feat[ok], fix.residual_m[ok], atol=1e-3)
    # the sample is an open-sky recording: weighted residuals centre on zero
    assert abs(np.median(feat[seq.mask])) < 5.0
