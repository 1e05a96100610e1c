"""A noise model's R above ``estimators.noise.R_OFF_M2`` (1e30, say) switches a satellite off: every estimator leaves
it out as if masked, without scipy's LinAlgWarning of an ill-conditioned innovation covariance."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy.linalg import LinAlgWarning

from estimators import create
from estimators.ekf import LfgnssEkf
from estimators.models import EkfConfig
from estimators.noise import R_OFF_M2, FixedNoise, HeuristicNoise, NoiseWarning
from lfgnss.simulate import simulate_sequence


@pytest.fixture(scope="module")
def case():
    """(sequence with a stop, R [m^2], v^c [m], off): a slot switched off throughout and another at every third
    epoch."""
    seq = simulate_sequence(80, seed=3, n_slots=18, stops_s=((30.0, 60.0),))
    r, _ = HeuristicNoise()(seq)
    vc = np.where(seq.mask, 0.5, 0.0)
    seen = np.argsort(seq.mask.sum(0))[::-1]
    off = np.zeros_like(seq.mask)
    off[:, seen[0]] = True
    off[::3, seen[1]] = True
    return seq, r, vc, off & seq.mask


def _removed(seq, off):
    """``seq`` with the ``off`` slots masked out, pseudoranges and Dopplers."""
    return replace(seq, mask=seq.mask & ~off, prr_mask=seq.prr_mask & ~off)


def _solve_quietly(estimator, seq):
    """The Solution, failing on any LinAlgWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", LinAlgWarning)
        return estimator.solve(seq)


def _assert_same(a, b, atol_m: float) -> None:
    np.testing.assert_allclose(a.pos_ecef_m, b.pos_ecef_m, rtol=0, atol=atol_m)
    np.testing.assert_array_equal(a.n_used, b.n_used)
    np.testing.assert_array_equal(a.status, b.status)


@pytest.mark.parametrize("r_off", [1e30, 10 * R_OFF_M2])
def test_ekf_with_a_satellite_switched_off_equals_it_removed(case, r_off):
    seq, r, vc, off = case
    config = EkfConfig(doppler_sigma_m_s=0.5)
    switched = _solve_quietly(LfgnssEkf(noise=FixedNoise(np.where(off, r_off, r), vc), config=config), seq)
    removed = LfgnssEkf(noise=FixedNoise(r, vc), config=config).solve(_removed(seq, off))
    _assert_same(switched, removed, 1e-6)
    np.testing.assert_array_equal(switched.info["n_usable"], removed.info["n_usable"])
    np.testing.assert_array_equal(switched.info["n_doppler"], removed.info["n_doppler"])


class _OnlineNoise:
    """An online noise model (asked epoch by epoch, as a model trained with innovations) giving fixed arrays."""

    online = True
    metadata: dict = {}

    def __init__(self, r_m2: np.ndarray, vc_m: np.ndarray) -> None:
        self.r_m2, self.vc_m = r_m2, vc_m

    def __call__(self, sequence):
        return self.r_m2, self.vc_m

    def features(self, sequence):
        return np.arange(len(sequence))

    def predict(self, k, mask, innovation):
        return self.r_m2[k], self.vc_m[k]


def test_online_ekf_with_a_satellite_switched_off_equals_it_removed(case):
    seq, r, vc, off = case
    config = EkfConfig(doppler_sigma_m_s=0.5, zupt_sigma_m_s=0.05)
    switched = _solve_quietly(LfgnssEkf(noise=_OnlineNoise(np.where(off, 1e30, r), vc), config=config), seq)
    removed = LfgnssEkf(noise=FixedNoise(r, vc), config=config).solve(_removed(seq, off))
    _assert_same(switched, removed, 1e-6)
    np.testing.assert_array_equal(switched.info["stationary"], removed.info["stationary"])
    assert removed.info["stationary"].any()


@pytest.mark.parametrize("mode", ["batch", "fixed-lag"])
def test_fgo_with_a_satellite_switched_off_equals_it_removed(case, mode):
    pytest.importorskip("gtsam")
    from estimators.fgo import LfgnssFgo

    seq, r, vc, off = case
    switched = _solve_quietly(LfgnssFgo(noise=FixedNoise(np.where(off, 1e30, r), vc), mode=mode), seq)
    removed = LfgnssFgo(noise=FixedNoise(r, vc), mode=mode).solve(_removed(seq, off))
    _assert_same(switched, removed, 1e-6)


def test_weighted_least_squares_with_a_satellite_switched_off_equals_it_removed(case):
    seq, r, vc, off = case
    switched = _solve_quietly(create("wls-weighted", noise=FixedNoise(np.where(off, 1e30, r), vc)), seq)
    removed = create("wls-weighted", noise=FixedNoise(r, vc)).solve(_removed(seq, off))
    _assert_same(switched, removed, 1e-6)


def test_a_large_but_finite_variance_still_counts(case):
    """Below ``R_OFF_M2`` a satellite is down-weighted, not switched off: it is still used."""
    seq, r, vc, off = case
    config = EkfConfig(doppler_sigma_m_s=0.0)
    weak = LfgnssEkf(noise=FixedNoise(np.where(off, R_OFF_M2 / 10, r), vc), config=config).solve(seq)
    removed = LfgnssEkf(noise=FixedNoise(r, vc), config=config).solve(_removed(seq, off))
    assert np.all(weak.n_used >= removed.n_used) and np.any(weak.n_used > removed.n_used)
    np.testing.assert_allclose(weak.pos_ecef_m, removed.pos_ecef_m, rtol=0, atol=1e-3)


def _every_estimator(r_m2: np.ndarray, vc_m: np.ndarray) -> tuple:
    """Each estimator given fixed noise (R [m^2], v^c [m]): EKF forward, smoothed and with an online model, the batch
    and fixed-lag graph, the weighted fix."""
    from estimators.fgo import LfgnssFgo

    return (LfgnssEkf(noise=FixedNoise(r_m2, vc_m), config=EkfConfig()),
            LfgnssEkf(noise=FixedNoise(r_m2, vc_m), config=EkfConfig(), smooth=True),
            LfgnssEkf(noise=_OnlineNoise(r_m2, vc_m), config=EkfConfig()),
            LfgnssFgo(noise=FixedNoise(r_m2, vc_m)),
            LfgnssFgo(noise=FixedNoise(r_m2, vc_m), mode="fixed-lag"),
            create("wls-weighted", noise=FixedNoise(r_m2, vc_m)))


def _warned(estimator, seq, words: str) -> list[str]:
    """The noise warnings (``NoiseWarning``) containing ``words`` that solving ``seq`` gives."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        estimator.solve(seq)
    return [str(w.message) for w in caught if issubclass(w.category, NoiseWarning) and words in str(w.message)]


def test_every_estimator_warns_when_the_noise_model_switches_a_whole_epoch_off(case):
    """Epochs whose every pseudorange the noise model switches off place no position: said once, with the count and
    the first epoch; switching single satellites off (the other tests) says nothing."""
    pytest.importorskip("gtsam")
    seq, r, vc, off = case
    dark = np.zeros_like(seq.mask)
    dark[20:25] = True
    said = "at 5 of 80 epochs of 'synthetic' (first at epoch 20): no satellite places a position there"
    for r_given, expected in ((np.where(dark | off, 1e30, r), 1), (np.where(off, 1e30, r), 0)):
        for estimator in _every_estimator(r_given, vc):
            lines = _warned(estimator, seq, "switched off every usable pseudorange")
            assert len(lines) == expected, (estimator, lines)
            assert all(said in line for line in lines), lines


def test_every_estimator_warns_when_r_looks_given_in_another_unit(case):
    """A median R given in cm^2 or km^2 (the hand-set one x 1e4 or x 1e-6) runs, with one warning naming its ratio to
    the hand-set variance, the median and its sd, an online model's too (judged on the whole run, not epoch by
    epoch); the hand-set R says nothing, on weak signals (sd over 100 m) too."""
    pytest.importorskip("gtsam")
    seq, r, vc, _ = case
    for scale, said in ((1e4, True), (1e-6, True), (1.0, False)):
        given = r * scale
        for estimator in _every_estimator(given, vc):
            lines = _warned(estimator, seq, "R is a variance in m^2")
            assert len(lines) == said, (estimator, lines)
            median = float(np.median(given[seq.mask]))
            assert all(f"is a median {scale:.3g} times the hand-set C/N0-elevation variance (median R {median:.3g} "
                       f"m^2, sd {np.sqrt(median):.3g} m), outside 0.0001-100" in x for x in lines), lines
    weak = replace(seq, cn0_dbhz=np.where(seq.mask, seq.cn0_dbhz - 20.0, seq.cn0_dbhz))      # 20 dB weaker signals
    r_weak, _ = HeuristicNoise()(weak)
    assert np.median(r_weak[weak.mask]) > 1e4                       # hand-set R of sd > 100 m, in m^2 all the same
    assert not _warned(create("wls-weighted", noise=FixedNoise(r_weak, vc)), weak, "R is a variance in m^2")
