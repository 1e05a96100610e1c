"""estimators.consistency: the pseudorange residuals' variance factor and the covariance inflation it drives."""
from dataclasses import replace

import numpy as np
import pytest

from estimators import LfgnssEkf, LfgnssFgo, PlainEkf, create
from estimators.consistency import INFLATION_TAU_S, covariance_inflation, residual_variance_factor
from lfgnss.metrics import enu_errors
from lfgnss.simulate import simulate_sequence


def _true_sigma_m(seq):
    """The simulator's pseudorange noise sd [m] at each slot's C/N0 (lfgnss/simulate.py)."""
    return 0.5 + 120.0 * 10 ** (-seq.cn0_dbhz / 20.0)


def test_factor_is_about_one_at_the_truth_with_the_true_noise():
    seq = simulate_sequence(200, nlos_fraction=0.0, seed=3)
    r = _true_sigma_m(seq) ** 2
    g = residual_variance_factor(seq, seq.truth_ecef_m, r, seq.mask)
    assert np.isfinite(g).all()
    # Each constellation's median removes about one degree of freedom of its 7 satellites: E[g] a bit under 1.
    assert 0.6 < g.mean() < 1.1
    np.testing.assert_allclose(residual_variance_factor(seq, seq.truth_ecef_m, r / 100.0, seq.mask), 100.0 * g)


def test_factor_flags_biased_pseudoranges_and_epochs_without_a_position():
    clean = simulate_sequence(200, nlos_fraction=0.0, seed=3)
    nlos = simulate_sequence(200, nlos_fraction=0.4, seed=3)
    g_clean = residual_variance_factor(clean, clean.truth_ecef_m, _true_sigma_m(clean) ** 2, clean.mask)
    g_nlos = residual_variance_factor(nlos, nlos.truth_ecef_m, _true_sigma_m(nlos) ** 2, nlos.mask)
    assert np.median(g_nlos) > 10 * np.median(g_clean)
    pos = clean.truth_ecef_m.copy()
    pos[5] = np.nan
    mask = clean.mask.copy()
    mask[7] = False
    g = residual_variance_factor(clean, pos, np.ones(mask.shape), mask)
    assert np.isnan(g[[5, 7]]).all() and np.isfinite(np.delete(g, [5, 7])).all()


def test_a_constellations_lone_satellite_is_no_evidence():
    """A lone satellite is its constellation's median (its clock): residual 0 by construction. It is left out, and an
    epoch with one per constellation (position-blind) has no factor, so it keeps the running mean."""
    seq = simulate_sequence(20, nlos_fraction=0.4, seed=3)
    r = _true_sigma_m(seq) ** 2
    mask = seq.mask.copy()
    first = [np.flatnonzero(mask[4] & (seq.system_index[4] == j))[0] for j in range(len(seq.systems))]
    mask[4] = False
    mask[4, first] = True                                          # epoch 4: one per constellation
    mask[6] &= seq.system_index[6] != 1
    mask[6, np.flatnonzero(seq.mask[6] & (seq.system_index[6] == 1))[0]] = True   # epoch 6: one of constellation 1
    g = residual_variance_factor(seq, seq.truth_ecef_m, r, mask)
    assert np.isnan(g[4]) and np.isfinite(np.delete(g, 4)).all()
    without = mask[6] & (seq.system_index[6] != 1)
    np.testing.assert_allclose(g[6], residual_variance_factor(seq, seq.truth_ecef_m, r,
                                                              np.where(np.arange(20)[:, None] == 6, without, mask))[6])
    f = covariance_inflation(seq.time_gps_s, g)
    assert f[4] == f[3]


def test_inflation_is_a_running_mean_never_below_one():
    time = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    g = np.array([np.nan, 4.0, np.nan, 0.25, 9.0])
    f = covariance_inflation(time, g, tau_s=5.0)
    w9, w1 = np.exp(-9.0 / 5.0), np.exp(-1.0 / 5.0)   # epoch 3 weighs the last factor, epoch 1's, 9 s older
    m3 = w9 * 4.0 + (1 - w9) * 0.25
    np.testing.assert_allclose(f, [1.0, 4.0, 4.0, max(1.0, m3), w1 * m3 + (1 - w1) * 9.0])
    np.testing.assert_allclose(covariance_inflation(time, g, tau_s=0.0), [1.0, 4.0, 4.0, 1.0, 9.0])
    assert INFLATION_TAU_S > 0


@pytest.mark.parametrize("cls", [LfgnssEkf, PlainEkf])
def test_ekf_reports_the_formal_covariance_times_the_factor(cls):
    seq = simulate_sequence(150, nlos_fraction=0.3, seed=1)
    formal, inflated = cls(inflate_cov=False).solve(seq), cls().solve(seq)
    np.testing.assert_array_equal(formal.pos_ecef_m, inflated.pos_ecef_m)
    np.testing.assert_allclose(formal.cov_ecef_m2, formal.info["cov"][:, :3, :3])
    np.testing.assert_array_equal(formal.info["cov_inflation"], np.ones(len(seq)))
    factor = inflated.info["cov_inflation"]
    assert (factor >= 1).all() and (factor > 1).any()
    np.testing.assert_allclose(inflated.cov_ecef_m2, formal.cov_ecef_m2 * factor[:, None, None])
    np.testing.assert_allclose(factor, covariance_inflation(seq.time_gps_s, inflated.info["residual_factor"]))
    assert "inflate_cov=False" in repr(cls(inflate_cov=False)) and "inflate_cov" not in repr(cls())
    with pytest.raises(TypeError, match="inflate_cov"):
        cls(inflate_cov="yes")


@pytest.mark.parametrize("mode", ["batch", "fixed-lag"])
def test_factor_graph_inflates_its_marginals_not_its_stand_in(mode):
    seq = simulate_sequence(60, nlos_fraction=0.3, seed=1)
    formal = LfgnssFgo(mode=mode, covariances=True, inflate_cov=False).solve(seq)
    inflated = LfgnssFgo(mode=mode, covariances=True).solve(seq)
    np.testing.assert_array_equal(formal.pos_ecef_m, inflated.pos_ecef_m)
    np.testing.assert_array_equal(formal.info["cov_inflation"], np.ones(len(seq)))
    factor = inflated.info["cov_inflation"]
    assert (factor >= 1).all() and (factor > 1).any()
    np.testing.assert_allclose(inflated.cov_ecef_m2, formal.cov_ecef_m2 * factor[:, None, None])
    np.testing.assert_allclose(factor, covariance_inflation(seq.time_gps_s, inflated.info["residual_factor"]))
    np.testing.assert_allclose(inflated.info["residual_factor"],
                               residual_variance_factor(seq, inflated.pos_ecef_m, LfgnssFgo().noise(seq)[0], seq.mask))
    stand_in = LfgnssFgo(mode=mode).solve(seq)           # the snapshot stand-in is wide already: not inflated
    np.testing.assert_array_equal(stand_in.info["cov_inflation"], np.ones(len(seq)))
    np.testing.assert_allclose(stand_in.info["residual_factor"], inflated.info["residual_factor"])
    assert "inflate_cov=False" in repr(LfgnssFgo(inflate_cov=False)) and "inflate_cov" not in repr(LfgnssFgo())
    with pytest.raises(TypeError, match="inflate_cov"):
        LfgnssFgo(inflate_cov="yes")


def test_inflation_brings_the_sds_closer_to_the_errors_on_the_bundled_berlin_drive():
    """Real street-canyon data with truth: the bundled model's formal sds (the EKF's, the factor graph's marginals)
    are far too small (mean NEES in the hundreds against 3); inflated by the residuals they are much closer
    (docs/sd_consistency.md has the splits)."""
    import lfgnss
    from lfgnss.datasets import read_truth
    from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH

    meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
    truth = read_truth(SAMPLE_TRUTH, meas.time_gps_s, "smartloc")
    seq = lfgnss.build_sequence(meas, lfgnss.spp(meas), truth_ecef_m=truth)

    def nees_and_share(sol):
        e, c = enu_errors(sol.pos_ecef_m, seq.truth_ecef_m), sol.cov_enu_m2()
        ok = np.isfinite(e).all(1) & np.isfinite(c).all((1, 2))
        z = np.abs(e[ok]) / np.sqrt(np.diagonal(c[ok], axis1=1, axis2=2))
        return float(np.mean(np.einsum("ti,tij,tj->t", e[ok], np.linalg.inv(c[ok]), e[ok]))), float((z < 3).mean())

    formal, inflated = create("ekf", inflate_cov=False).solve(seq), create("ekf").solve(seq)   # the bundled model
    (nees_formal, share_formal), (nees, share) = nees_and_share(formal), nees_and_share(inflated)
    assert nees_formal > 100 and nees < nees_formal / 10
    assert share_formal < 0.5 < 0.8 < share          # errors within 3 sd: calibrated would be 99.7 %
    graph = create("fgo", covariances=True).solve(seq)
    marginals = replace(graph, cov_ecef_m2=graph.cov_ecef_m2 / graph.info["cov_inflation"][:, None, None])
    (nees_formal, share_formal), (nees, share) = nees_and_share(marginals), nees_and_share(graph)
    assert nees_formal > 100 and nees < nees_formal / 10
    assert share_formal < 0.5 < 0.75 < share


def test_benchmark_rows_count_errors_within_their_sds():
    """benchmarks/sd_consistency.py: a solution whose ENU errors are 0.5, 2 and 4 sd scores 1/3 within 1 sd."""
    import sys
    from pathlib import Path

    from estimators.base import STATUS_UPDATED, Solution
    from lfgnss.frames import ecef_to_lla, enu_rotation

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import sd_consistency

    seq = simulate_sequence(3, nlos_fraction=0.0)
    lat, lon, _ = ecef_to_lla(seq.truth_ecef_m[0])
    rot = enu_rotation(lat, lon)                                    # rows: east, north, up in ECEF
    sd_enu = np.array([1.0, 2.0, 3.0])
    err_enu = np.array([0.5, 2.0, 4.0])[:, None] * sd_enu[None, :]
    cov_ecef = rot.T @ np.diag(sd_enu ** 2) @ rot
    sol = Solution(backend="x", time_gps_s=seq.time_gps_s, pos_ecef_m=seq.truth_ecef_m + err_enu @ rot,
                   cov_ecef_m2=np.repeat(cov_ecef[None], 3, axis=0), clock_m=np.zeros(3), n_used=np.full(3, 5),
                   status=np.full(3, STATUS_UPDATED, dtype=np.int8))
    row = sd_consistency.consistency_row("x", [seq], [sol])
    assert row["epochs"] == 3 and row["within 1 sd E/N/U [%]"] == "33/33/33" and row["within 3 sd E/N/U [%]"] == "67/67/67"
    np.testing.assert_allclose(row["mean NEES"], np.mean([3 * 0.25, 3 * 4.0, 3 * 16.0]), rtol=1e-4)
