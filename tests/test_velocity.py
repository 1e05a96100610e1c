"""Doppler velocity fixes (lfgnss.velocity): the model, robustness, and accuracy against truth."""
import numpy as np
import pytest

from estimators import models
from lfgnss.simulate import simulate_sequence
from lfgnss.velocity import doppler_design, doppler_velocity


def _fix(seq, **kw):
    return doppler_velocity(seq.prr_m_s, seq.prr_mask, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s,
                            seq.truth_ecef_m, **kw)


def test_design_is_the_filters_doppler_model():
    """a + A [v; d] equals estimators.models.doppler_measurement, and A its Jacobian (Sagnac terms too)."""
    seq = simulate_sequence(5, seed=3)
    x = np.zeros(models.n_states(2))
    x[models.POS] = seq.truth_ecef_m[2]
    x[models.VEL] = [3.0, -7.0, 0.5]
    x[models.DRIFT] = 42.0
    g, G = models.doppler_measurement(x, seq.sat_pos_ecef_m[2], seq.sat_vel_ecef_m_s[2])
    a, A = doppler_design(seq.sat_pos_ecef_m[2], seq.sat_vel_ecef_m_s[2], x[models.POS])
    np.testing.assert_allclose(a + A @ np.r_[x[models.VEL], x[models.DRIFT]], g, atol=1e-9)
    np.testing.assert_allclose(A[:, 3], 1.0)
    np.testing.assert_allclose(A[:, :3], G[:, models.VEL], atol=1e-5)   # G neglects the Sagnac part (~1e-6)


def test_noise_free_doppler_gives_the_exact_velocity():
    seq = simulate_sequence(30, seed=1)
    x_true = np.array([2.0, -5.0, 0.3, 17.0])
    a, A = doppler_design(seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s, seq.truth_ecef_m)
    prr = a + A @ x_true
    dv = doppler_velocity(prr, seq.prr_mask, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s, seq.truth_ecef_m)
    assert dv.ok.all()
    np.testing.assert_allclose(dv.vel_ecef_m_s, np.broadcast_to(x_true[:3], (30, 3)), atol=1e-6)
    np.testing.assert_allclose(dv.drift_m_s, 17.0, atol=1e-6)
    assert np.all(np.linalg.eigvalsh(dv.cov_m2_s2) > 0)


def test_simulated_drive_velocity_and_outlier_resistance():
    """On the simulated drive (0.1-1.5 m/s Doppler noise) the fix is within 0.5 m/s RMS of the truth; a
    30 m/s outlier on one satellite moves the robust fix far less than the equal-weight one."""
    seq = simulate_sequence(200, seed=2)
    t = seq.time_gps_s
    v_true = np.gradient(seq.truth_ecef_m, t, axis=0)
    dv = _fix(seq)
    err = np.linalg.norm(dv.vel_ecef_m_s - v_true, axis=1)[2:-2]     # the truth's gradient is one-sided at the ends
    assert dv.ok.mean() > 0.95
    assert np.sqrt(np.nanmean(err ** 2)) < 0.5

    prr = seq.prr_m_s.copy()
    prr[:, 0] += np.where(seq.prr_mask[:, 0], 30.0, 0.0)
    bad = doppler_velocity(prr, seq.prr_mask, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s, seq.truth_ecef_m)
    flat = doppler_velocity(prr, seq.prr_mask, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s, seq.truth_ecef_m,
                            iterations=0)
    e_bad = np.linalg.norm(bad.vel_ecef_m_s - v_true, axis=1)[2:-2]
    e_flat = np.linalg.norm(flat.vel_ecef_m_s - v_true, axis=1)[2:-2]
    assert np.nanmedian(e_bad) < 0.5 < 2.0 < np.nanmedian(e_flat)


def test_too_few_dopplers_or_no_position_give_no_fix():
    seq = simulate_sequence(4, seed=0)
    mask = seq.prr_mask.copy()
    mask[0] = False
    mask[1, 4:] = False                 # 4 Dopplers: no redundancy, no fix
    pos = seq.truth_ecef_m.copy()
    pos[2] = np.nan
    dv = doppler_velocity(seq.prr_m_s, mask, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s, pos)
    assert dv.ok.tolist() == [False, False, False, True]
    assert dv.n_used.tolist()[:2] == [0, 4]
    assert np.isnan(dv.vel_ecef_m_s[:3]).all() and np.isnan(dv.drift_m_s[:3]).all()
    assert np.isfinite(dv.vel_ecef_m_s[3]).all()


def test_per_doppler_sigma_weights_each_doppler():
    """A (T, N) sigma equal everywhere is the scalar fit; a huge sigma on one satellite takes it out of the fit
    as a mask would, without the reweighting; a zero or NaN sigma on a used Doppler is refused."""
    seq = simulate_sequence(60, seed=4)
    same = _fix(seq, sigma_m_s=np.full(seq.prr_m_s.shape, 0.5))
    scalar = _fix(seq)
    np.testing.assert_allclose(same.vel_ecef_m_s, scalar.vel_ecef_m_s, atol=1e-9)
    np.testing.assert_allclose(same.cov_m2_s2, scalar.cov_m2_s2, rtol=1e-9)

    prr = seq.prr_m_s.copy()
    prr[:, 0] += np.where(seq.prr_mask[:, 0], 30.0, 0.0)
    sigma = np.full(prr.shape, 0.5)
    sigma[:, 0] = 1.0e3
    without = seq.prr_mask.copy()
    without[:, 0] = False
    fix = lambda mask, **kw: doppler_velocity(prr, mask, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s,  # noqa: E731
                                              seq.truth_ecef_m, iterations=0, **kw)
    weighted, masked, flat = fix(seq.prr_mask, sigma_m_s=sigma), fix(without), fix(seq.prr_mask)
    ok = weighted.ok & masked.ok
    assert ok.sum() > 50
    np.testing.assert_allclose(weighted.vel_ecef_m_s[ok], masked.vel_ecef_m_s[ok], atol=1e-3)
    assert np.max(np.abs(flat.vel_ecef_m_s[ok] - masked.vel_ecef_m_s[ok])) > 1.0
    for bad in (0.0, np.nan):
        sigma[5, np.flatnonzero(seq.prr_mask[5])[0]] = bad
        with pytest.raises(ValueError, match="positive, finite sigma_m_s"):
            fix(seq.prr_mask, sigma_m_s=sigma)


@pytest.mark.shared_data
def test_static_receiver_doppler_velocity_is_near_zero(shared_data):
    """hk-tst-static-2020 (u-blox F9P, G/R/E/J/C, a static antenna): real Dopplers at the coarse fix give
    a velocity within 0.2 m/s of zero at the median and 1 m/s at the 99th percentile."""
    from lfgnss import datasets

    shared_data("hk-tst-static-20200603")
    seq = datasets.build("hk-tst-static-2020")
    dv = doppler_velocity(seq.prr_m_s, seq.prr_mask & seq.mask, seq.sat_pos_ecef_m, seq.sat_vel_ecef_m_s,
                          seq.coarse_ecef_m)
    speed = np.linalg.norm(dv.vel_ecef_m_s[dv.ok], axis=1)
    assert dv.ok.mean() > 0.99
    assert np.median(speed) < 0.2 and np.percentile(speed, 99) < 1.0


def test_dopplers_of_satellites_in_one_spot_give_no_fix_not_an_error():
    """A singular normal matrix (every satellite within km of the first) ended in numpy's LinAlgError."""
    seq = simulate_sequence(20, seed=1)
    sat, vel = seq.sat_pos_ecef_m.copy(), seq.sat_vel_ecef_m_s.copy()
    sat[5] = sat[5, :1] + 1000.0 * np.arange(seq.n_slots)[:, None]
    vel[5] = vel[5, :1]
    dv = doppler_velocity(seq.prr_m_s, seq.prr_mask, sat, vel, seq.truth_ecef_m)
    assert not dv.ok[5] and dv.ok[np.arange(20) != 5].all()
