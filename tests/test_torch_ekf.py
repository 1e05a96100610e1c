"""Batched torch EKF (learning.torch_ekf) against the filterpy plug-in, padding and gradients."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from estimators.base import STATUS_NONE, STATUS_RESET, STATUS_UPDATED, usable_measurements  # noqa: E402
from estimators.ekf import LfgnssEkf  # noqa: E402
from estimators import models  # noqa: E402
from estimators.models import ISB0, EkfConfig  # noqa: E402
from estimators.noise import FixedNoise  # noqa: E402
from learning.torch_ekf import batch_ekf, geometric_range_m, rts_smooth  # noqa: E402
from learning.types import WindowBatch  # noqa: E402
from lfgnss.constants import SPEED_OF_LIGHT_M_S  # noqa: E402
from lfgnss.corrections import geometric_range_m as geometric_range_np  # noqa: E402
from lfgnss.simulate import simulate_sequence  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny batched matrices: intra-op threads only add overhead (and fight over shared CPUs)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def to_batch(seqs) -> WindowBatch:
    """Sequences of equal length and slot count as one WindowBatch (whole sequences as windows)."""
    def stack(name, dtype=torch.float64):
        return torch.as_tensor(np.stack([getattr(s, name) for s in seqs]), dtype=dtype)

    return WindowBatch(time_gps_s=stack("time_gps_s"), pr_m=stack("pr_m"), sat_pos_ecef_m=stack("sat_pos_ecef_m"),
                       system_index=stack("system_index", torch.int64), mask=stack("mask", torch.bool),
                       features=stack("features", torch.float32), coarse_ecef_m=stack("coarse_ecef_m"),
                       coarse_clock_m=stack("coarse_clock_m"), truth_ecef_m=stack("truth_ecef_m"),
                       prr_m_s=stack("prr_m_s"), prr_mask=stack("prr_mask", torch.bool),
                       sat_vel_ecef_m_s=stack("sat_vel_ecef_m_s"), cn0_dbhz=stack("cn0_dbhz"))


@pytest.fixture(scope="module")
def cases():
    """Three 120-epoch sequences, 20 slots (6 padded), with outliers, a late start, a clock jump, resets."""
    rng = np.random.default_rng(7)
    seqs, rs, vcs = [], [], []
    for i in range(3):
        s = simulate_sequence(120, seed=10 + i, n_slots=20)
        pr = s.pr_m.copy()
        outl = rng.random(s.mask.shape) < 0.03
        pr += np.where(s.mask & outl, rng.choice([-1, 1], s.mask.shape) * rng.uniform(80, 300, s.mask.shape), 0.0)
        coarse, clock = s.coarse_ecef_m.copy(), s.coarse_clock_m.copy()
        if i == 0:                      # one epoch inconsistent with any clock: the full reset path
            pr[40] += np.where(s.mask[40], np.resize([3000.0, -5000.0, 9000.0], s.mask.shape[1]), 0.0)
        if i == 1:                      # no coarse fix for the first epochs, nor inside an outage
            coarse[:4] = np.nan
            coarse[60:62] = np.nan
        if i == 2:                      # 1 ms receiver clock jump and a coarse fix far off (divergence reset)
            pr[70:] += np.where(s.mask[70:], 1e-3 * SPEED_OF_LIGHT_M_S, 0.0)
            clock[70:, 0] += 1e-3 * SPEED_OF_LIGHT_M_S
            coarse[100] += 400.0
        s = replace(s, pr_m=np.where(s.mask, pr, 0.0), coarse_ecef_m=coarse, coarse_clock_m=clock)
        seqs.append(s)
        scale = 4.0 if i == 2 else 1.0   # seq 2: R wide enough for its NLOS errors, so the clock realignment holds
        rs.append(np.where(s.mask, scale * rng.uniform(2.0, 80.0, s.mask.shape), 0.0))
        vcs.append(np.where(s.mask, rng.normal(0.0, 3.0, s.mask.shape), 0.0))
    return seqs, np.stack(rs), np.stack(vcs)


CONFIG = EkfConfig()


def test_geometric_range_twin():
    s = simulate_sequence(3, seed=2)
    sat, rcv = s.sat_pos_ecef_m, s.truth_ecef_m[:, None, :]
    got = geometric_range_m(torch.as_tensor(sat), torch.as_tensor(rcv)).numpy()
    np.testing.assert_allclose(got, geometric_range_np(sat, rcv), rtol=0, atol=1e-8)


def test_matches_filterpy_plugin(cases):
    seqs, r, vc = cases
    out = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    assert out.pos_ecef_m.shape == (3, 120, 3) and out.state.shape == (3, 120, 9) and out.cov.shape == (3, 120, 9, 9)
    for i, s in enumerate(seqs):
        sol = LfgnssEkf(noise=FixedNoise(r[i], vc[i]), config=CONFIG).solve(s)
        np.testing.assert_array_equal(out.status[i].numpy(), sol.status)
        np.testing.assert_array_equal(out.n_used[i].numpy(), sol.n_used)
        np.testing.assert_array_equal(out.n_gated[i].numpy(), sol.info["n_gated"])
        np.testing.assert_array_equal(out.n_doppler[i].numpy(), sol.info["n_doppler"])
        np.testing.assert_allclose(out.pos_ecef_m[i].numpy(), sol.pos_ecef_m, rtol=0, atol=1e-6, equal_nan=True)
        live = sol.status != STATUS_NONE
        np.testing.assert_allclose(out.state[i].numpy()[live], sol.info["state"][live], rtol=0, atol=1e-6)
        np.testing.assert_allclose(out.cov[i].numpy()[live], sol.info["cov"][live], rtol=1e-6, atol=1e-6)
    status = out.status.numpy()
    assert (out.n_gated.numpy() > 0).sum() > 10                          # the gate was active
    assert (status[1, :4] == STATUS_NONE).all() and status[1, 4] == STATUS_RESET
    assert status[0, 40] == STATUS_RESET                                       # not a clock jump: reset
    assert status[2, 70] == STATUS_UPDATED and status[2, 100] == STATUS_RESET  # clock realigned, divergence
    assert abs(out.state[2, 70, 6].item() - out.state[2, 69, 6].item() - out.state[2, 69, 7].item()
               - 1e-3 * SPEED_OF_LIGHT_M_S) < 10.0                                # clock + drift dt + jump


def test_vertical_process_noise_matches_the_plugin(cases):
    """q_vel_up_m2_s3 in both filters: the same positions and covariances, and not those of the isotropic filter."""
    seqs, r, vc = cases
    cfg = EkfConfig(q_vel_up_m2_s3=0.02)
    out = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=cfg)
    iso = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    for i, s in enumerate(seqs):
        sol = LfgnssEkf(noise=FixedNoise(r[i], vc[i]), config=cfg).solve(s)
        np.testing.assert_array_equal(out.status[i].numpy(), sol.status)
        live = sol.status != STATUS_NONE
        np.testing.assert_allclose(out.pos_ecef_m[i].numpy(), sol.pos_ecef_m, rtol=0, atol=1e-6, equal_nan=True)
        np.testing.assert_allclose(out.cov[i].numpy()[live], sol.info["cov"][live], rtol=1e-6, atol=1e-6)
        smoothed = LfgnssEkf(noise=FixedNoise(r[i], vc[i]), config=cfg, smooth=True).solve(s).pos_ecef_m
        np.testing.assert_allclose(rts_smooth(out)[i].numpy(), smoothed, rtol=0, atol=1e-6, equal_nan=True)
    assert not np.allclose(out.pos_ecef_m.numpy(), iso.pos_ecef_m.numpy(), rtol=0, atol=1e-3, equal_nan=True)


def test_cn0_dependent_doppler_variance_matches_the_plugin(cases):
    """doppler_cn0_ref_dbhz in both filters: the same positions, Doppler counts and covariances, not the constant's."""
    seqs, r, vc = cases
    cfg = EkfConfig(doppler_sigma_m_s=0.1, doppler_cn0_ref_dbhz=40.0)
    out = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=cfg)
    flat = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2,
                     config=EkfConfig(doppler_sigma_m_s=0.1))
    _assert_matches_plugin(out, seqs, r, vc, cfg)
    assert not np.allclose(out.pos_ecef_m.numpy(), flat.pos_ecef_m.numpy(), rtol=0, atol=1e-3, equal_nan=True)


def _assert_matches_plugin(out, seqs, r, vc, cfg) -> list:
    """The torch filter's statuses, counts, positions and covariances equal the filterpy plug-in's under ``cfg``;
    returns the plug-in's Solutions."""
    sols = []
    for i, s in enumerate(seqs):
        sol = LfgnssEkf(noise=FixedNoise(r[i], vc[i]), config=cfg).solve(s)
        sols.append(sol)
        np.testing.assert_array_equal(out.status[i].numpy(), sol.status)
        np.testing.assert_array_equal(out.n_used[i].numpy(), sol.n_used)
        np.testing.assert_array_equal(out.n_gated[i].numpy(), sol.info["n_gated"])
        np.testing.assert_array_equal(out.n_doppler[i].numpy(), sol.info["n_doppler"])
        live = sol.status != STATUS_NONE
        np.testing.assert_allclose(out.pos_ecef_m[i].numpy(), sol.pos_ecef_m, rtol=0, atol=1e-6, equal_nan=True)
        np.testing.assert_allclose(out.cov[i].numpy()[live], sol.info["cov"][live], rtol=1e-6, atol=1e-6)
    return sols


def _both_filters(s):
    """The plug-in's Solution of ``s`` with R = 25 m^2 on every usable slot and no v^c, asserted equal to the torch
    filter's run of it (``_assert_matches_plugin``)."""
    r, vc = np.where(s.mask, 25.0, 0.0)[None], np.zeros((1,) + s.mask.shape)
    out = batch_ekf(to_batch([s]), torch.as_tensor(r), torch.as_tensor(vc), n_systems=len(s.systems), config=CONFIG)
    return _assert_matches_plugin(out, [s], r, vc, CONFIG)[0]


def test_switched_off_slots_match_the_plugin(cases):
    """An R above R_OFF_M2 leaves the slot out of both filters, pseudorange and Doppler (estimators.noise.switched_on):
    the same states, counts and covariances, and not those of the same R kept in."""
    seqs, r, vc = cases
    rng = np.random.default_rng(3)
    off = np.stack([s.mask for s in seqs]) & (rng.random(r.shape) < 0.2)
    off[0, 30, :] = np.stack([s.mask for s in seqs])[0, 30]           # a whole epoch off: it coasts in both
    r_off = np.where(off, 1e30, r)
    cfg = EkfConfig(doppler_sigma_m_s=0.5)
    out = batch_ekf(to_batch(seqs), torch.as_tensor(r_off), torch.as_tensor(vc), n_systems=2, config=cfg)
    with pytest.warns(UserWarning, match="switched off every usable pseudorange .* at 1 of 120 epochs"):
        _assert_matches_plugin(out, seqs, r_off, vc, cfg)                 # the plug-in says so, for sequence 0
    full = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=cfg)
    assert out.n_doppler[0, 30].item() == 0 and out.n_used[0, 30].item() == 0
    assert (out.n_doppler.numpy() < full.n_doppler.numpy()).any()
    assert not np.allclose(out.pos_ecef_m.numpy(), full.pos_ecef_m.numpy(), rtol=0, atol=1e-3, equal_nan=True)


def test_huber_update_matches_the_plugin(cases):
    """huber_k in both filters: the same states, counts and covariances, and not those of the hard gate alone."""
    seqs, r, vc = cases
    cfg = EkfConfig(huber_k=1.0)
    out = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=cfg)
    hard = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    _assert_matches_plugin(out, seqs, r, vc, cfg)
    assert not np.allclose(out.pos_ecef_m.numpy(), hard.pos_ecef_m.numpy(), rtol=0, atol=1e-3, equal_nan=True)


def test_zero_velocity_update_matches_the_plugin(cases):
    """zupt_sigma_m_s in both filters, on drives with stops (and the cases' outliers and resets): the same states,
    counts and covariances, and not those without it."""
    seqs, r, vc = cases
    # Dopplers of a car that stops, pseudoranges of the cases (outliers, clock jump, resets): the twins must agree
    # on any data. Stop 2 spans the first fix, stop 3 the divergence reset at epoch 100.
    stops = ((20.0, 50.0), (0.0, 15.0), (85.0, 119.0))
    drives = [simulate_sequence(120, seed=10 + i, n_slots=20, stops_s=(stops[i],)) for i in range(len(seqs))]
    stopped = [replace(s, prr_m_s=d.prr_m_s, truth_ecef_m=d.truth_ecef_m) for s, d in zip(seqs, drives)]
    cfg = EkfConfig(zupt_sigma_m_s=0.02)
    out = batch_ekf(to_batch(stopped), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=cfg)
    free = batch_ekf(to_batch(stopped), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    _assert_matches_plugin(out, stopped, r, vc, cfg)
    assert LfgnssEkf(noise=FixedNoise(r[0], vc[0]), config=cfg).solve(stopped[0]).info["stationary"][20:51].mean() > 0.5
    assert not np.allclose(out.pos_ecef_m.numpy(), free.pos_ecef_m.numpy(), rtol=0, atol=1e-3, equal_nan=True)
    alone = replace(cfg, min_sats_for_update=30)            # no satellite update: epochs held by the ZUPT alone
    out_alone = batch_ekf(to_batch(stopped), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=alone)
    _assert_matches_plugin(out_alone, stopped, r, vc, alone)
    still = LfgnssEkf(noise=FixedNoise(r[0], vc[0]), config=alone).solve(stopped[0]).info["stationary"]
    held = out_alone.status[0].numpy()[still]
    assert np.isin(held, (STATUS_UPDATED, STATUS_RESET)).all() and (held == STATUS_UPDATED).sum() >= 10   # not coasted


@pytest.mark.parametrize("stops", [(), ((4.0, 20.0),)])
def test_gradcheck_tiny_case_with_zero_velocity(stops):
    """Finite differences agree with autograd through the ZUPT rows too: the car stops at epoch 4, where the prior
    velocity is ~8 m/s (a detached ZUPT innovation changed these gradients by up to 0.004 of 0.08)."""
    s = simulate_sequence(8, seed=4, sats_per_system=3, nlos_fraction=0.0, n_slots=8, stops_s=stops)
    batch = to_batch([s])
    cfg = EkfConfig(gate_sigma=0.0, zupt_sigma_m_s=0.05)
    still = LfgnssEkf(noise=FixedNoise(np.full((8, 8), 9.0), np.zeros((8, 8))), config=cfg).solve(s).info["stationary"]
    assert not still[:4].any() and still[4:6].all() == bool(stops)            # found from epoch 4 on
    rng = np.random.default_rng(0)
    r0 = torch.as_tensor(rng.uniform(5.0, 30.0, (1, 8, 8)), dtype=torch.float64).requires_grad_(True)

    def last_position(r):
        return batch_ekf(batch, r, torch.zeros_like(r), n_systems=2, config=cfg).pos_ecef_m[:, -1]

    assert torch.autograd.gradcheck(last_position, (r0,), eps=1e-3, atol=1e-5, rtol=1e-3)


def test_huber_k_must_be_positive():
    for bad in (0.0, -1.0, float("nan"), float("inf"), True, "2"):
        with pytest.raises(ValueError, match="huber_k must be a positive number or None"):
            EkfConfig(huber_k=bad)


def test_cn0_dependent_doppler_variance_needs_the_cn0(cases):
    """Without C/N0 the C/N0 law is refused in one line; the constant sigma runs exactly as with it."""
    seqs, r, vc = cases
    batch = to_batch(seqs)
    batch.cn0_dbhz = None
    batch.__post_init__()
    with pytest.raises(ValueError, match="needs the batch's cn0_dbhz, finite"):
        batch_ekf(batch, torch.as_tensor(r), torch.as_tensor(vc), n_systems=2,
                  config=EkfConfig(doppler_cn0_ref_dbhz=40.0))
    blind = batch_ekf(batch, torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    seen = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    assert int(seen.n_doppler.sum()) > 0
    np.testing.assert_array_equal(blind.n_doppler.numpy(), seen.n_doppler.numpy())
    np.testing.assert_array_equal(blind.pos_ecef_m.numpy(), seen.pos_ecef_m.numpy())


def test_smoother_matches_the_plugins(cases):
    """The torch RTS pass equals ``LfgnssEkf(smooth=True)`` through resets, a late start and a clock jump."""
    seqs, r, vc = cases
    r_t = torch.as_tensor(r).requires_grad_()
    out = batch_ekf(to_batch(seqs), r_t, torch.as_tensor(vc), n_systems=2, config=CONFIG)
    pos = rts_smooth(out)
    for i, s in enumerate(seqs):
        sol = LfgnssEkf(noise=FixedNoise(r[i], vc[i]), config=CONFIG, smooth=True).solve(s)
        np.testing.assert_allclose(pos[i].detach().numpy(), sol.pos_ecef_m, rtol=0, atol=1e-6, equal_nan=True)
        assert not np.allclose(sol.pos_ecef_m[5:], out.pos_ecef_m[i, 5:].detach().numpy(), rtol=0, atol=0.01)  # smoothed
    loss = torch.nan_to_num(pos - torch.as_tensor(np.stack([s.truth_ecef_m for s in seqs]))).square().sum()
    loss.backward()
    assert torch.isfinite(r_t.grad).all() and r_t.grad[:, -1].abs().sum() > 0   # the last epoch reaches back


def test_clock_jump_realigns_only_the_clock(cases):
    seqs, r, vc = cases
    sol = LfgnssEkf(noise=FixedNoise(r[2], vc[2]), config=CONFIG).solve(seqs[2])
    assert np.flatnonzero(sol.info["clock_realigned"]).tolist() == [70] and sol.status[70] == STATUS_UPDATED
    sol = LfgnssEkf(noise=FixedNoise(r[0], vc[0]), config=CONFIG).solve(seqs[0])
    assert sol.info["clock_realigned"][40] and sol.status[40] == STATUS_RESET   # tried first, then reset


def test_a_clock_jump_without_a_coarse_fix_is_realigned_in_both_filters():
    """The realignment needs no coarse fix, only the reset after a failed one: a 1 ms jump at an epoch without a
    fix used to drop every pseudorange until the next fix (a review). An inconsistency no realignment mends goes on
    from the prior when there is no fix to reset to, in both filters alike."""
    s = simulate_sequence(120, seed=3)
    jump = 1e-3 * SPEED_OF_LIGHT_M_S
    pr, clock, coarse = s.pr_m.copy(), s.coarse_clock_m.copy(), s.coarse_ecef_m.copy()
    pr[60:] += jump
    clock[60:, 0] += jump
    pr[90] += np.where(s.mask[90], np.resize([3000.0, -5000.0, 9000.0], s.mask.shape[1]), 0.0)   # no clock mends
    coarse[[60, 61, 62, 90]], clock[[60, 61, 62, 90]] = np.nan, np.nan
    s = replace(s, pr_m=np.where(s.mask, pr, 0.0), coarse_ecef_m=coarse, coarse_clock_m=clock)
    sol = _both_filters(s)
    assert np.flatnonzero(sol.info["clock_realigned"]).tolist() == [60]
    assert sol.status[60] == STATUS_UPDATED and sol.n_used[60] == s.mask[60].sum()
    assert sol.status[90] == STATUS_UPDATED and sol.n_used[90] < s.mask[90].sum() / 2     # no reset, nothing to it
    assert np.linalg.norm(sol.pos_ecef_m[60] - s.truth_ecef_m[60]) < 20.0


def _galileo_from_epoch_60(isb_m: float):
    """A G+C+E drive whose 3 Galileo satellites (ISB isb_m) appear at epoch 60, unseen by the coarse fix before."""
    s = simulate_sequence(120, systems=("G", "C", "E"), sats_per_system=7, nlos_fraction=0.0, seed=4)
    e = s.systems.index("E")
    galileo = s.system_index == e
    keep = np.zeros(s.mask.shape[1], bool)
    keep[np.flatnonzero(galileo[0])[:3]] = True
    mask = s.mask & (~galileo | keep)
    mask[:60] &= ~galileo[:60]
    clock = s.coarse_clock_m.copy()
    clock[:, e] += isb_m
    clock[:60, e] = np.nan
    return replace(s, pr_m=np.where(galileo, s.pr_m + isb_m, s.pr_m), mask=mask, prr_mask=s.prr_mask & mask,
                   coarse_clock_m=clock), e


def _every_satellite_used_from(sol, s, k: int, isb: tuple[int, float] | None = None) -> None:
    assert np.array_equal(sol.n_used[k:], s.mask[k:].sum(1)) and sol.info["n_gated"][k:].sum() == 0
    assert np.linalg.norm(sol.pos_ecef_m - s.truth_ecef_m, axis=1).max() < 10.0
    if isb is not None:
        column, value = isb
        assert abs(sol.info["filtered_state"][-1, column] - value) < 5.0


@pytest.mark.parametrize("isb_m", [50.0, 1000.0, 30000.0])
def test_a_constellation_appearing_mid_run_gets_its_isb_in_both_filters(isb_m):
    """Galileo absent for the first 60 s, then 3 satellites with an ISB of isb_m: its ISB started at 0 with P0's
    100 m sigma, so from some hundred metres on they were gated out for the rest of the run (a review: 1000 m and
    more, 100 % of the later epochs). Now the first epoch that sees them sets it from their pseudoranges."""
    s, e = _galileo_from_epoch_60(isb_m)
    _every_satellite_used_from(_both_filters(s), s, 60, (ISB0 + e - 1, s.coarse_clock_m[-1, e]))


@pytest.mark.parametrize("coarse_fix_there", [True, False])
def test_a_clock_jump_where_a_constellation_first_appears_stays_the_clocks(coarse_fix_there):
    """A 1 ms receiver clock jump at Galileo's first epoch: its ISB taken from its whole median innovation held the
    jump (300 km) after the clock realignment moved the clock, and Galileo was lost (a review); it is taken against
    the known constellations' median, so the jump is left to the realignment."""
    s, e = _galileo_from_epoch_60(1000.0)
    jump = 1e-3 * SPEED_OF_LIGHT_M_S
    pr, clock, coarse = s.pr_m.copy(), s.coarse_clock_m.copy(), s.coarse_ecef_m.copy()
    pr[60:] += np.where(s.mask[60:], jump, 0.0)
    clock[60:, 0] += jump
    if not coarse_fix_there:
        coarse[60], clock[60] = np.nan, np.nan
    s = replace(s, pr_m=np.where(s.mask, pr, 0.0), coarse_clock_m=clock, coarse_ecef_m=coarse)
    sol = _both_filters(s)
    assert np.flatnonzero(sol.info["clock_realigned"]).tolist() == [60]
    _every_satellite_used_from(sol, s, 60, (ISB0 + e - 1, s.coarse_clock_m[-1, e]))


def test_the_reference_constellation_appearing_mid_run_moves_the_clock_in_both_filters():
    """GPS (systems[0]) absent for the first 60 s: the coarse fix's clock is BeiDou's (ISB 0). When GPS appears the
    clock takes GPS's and BeiDou's ISB its 1000 m; before, GPS was gated out (7 of 12-14 satellites used)."""
    s = simulate_sequence(120, systems=("G", "C"), sats_per_system=7, nlos_fraction=0.0, seed=4)
    beidou = s.system_index == 1
    mask = s.mask.copy()
    mask[:60] &= ~(s.system_index[:60] == 0)
    clock = s.coarse_clock_m.copy()
    clock[:, 1] += 1000.0
    clock[:60, 0] += clock[:60, 1]
    clock[:60, 1] = 0.0
    s = replace(s, pr_m=np.where(mask, np.where(beidou, s.pr_m + 1000.0, s.pr_m), 0.0), mask=mask,
                prr_mask=s.prr_mask & mask, coarse_clock_m=clock)
    _every_satellite_used_from(_both_filters(s), s, 60, (ISB0, s.coarse_clock_m[-1, 1]))


def test_a_constellation_first_seen_at_a_restart_without_its_coarse_isb_in_both_filters():
    """A restart after a long gap whose coarse fix lacks Galileo while its satellites are there: the reset takes
    its ISB from them too (only the normal path was tested)."""
    s, e = _galileo_from_epoch_60(1000.0)
    time, clock = s.time_gps_s.copy(), s.coarse_clock_m.copy()
    time[60:] += 100.0
    clock[60:, e] = np.nan
    s = replace(s, time_gps_s=time, coarse_clock_m=clock)
    sol = _both_filters(s)
    assert sol.status[60] == STATUS_RESET
    _every_satellite_used_from(sol, s, 60)


@pytest.mark.parametrize("gap_s", [100.0, 86400.0, 1e6])
def test_a_long_gap_restarts_at_the_next_coarse_fix_in_both_filters(gap_s):
    """A gap beyond max_gap_s whose first epochs have no coarse fix: no position until the next fix, which resets
    (predicted across it, a day's gap left the filter 52 km off, twelve days raised the singular-update error)."""
    s = simulate_sequence(120, seed=4)
    time, coarse = s.time_gps_s.copy(), s.coarse_ecef_m.copy()
    time[60:] += gap_s
    coarse[60:63] = np.nan
    s = replace(s, time_gps_s=time, coarse_ecef_m=coarse)
    sol = _both_filters(s)
    assert (sol.status[60:63] == STATUS_NONE).all() and np.isnan(sol.pos_ecef_m[60:63]).all()
    assert sol.status[63] == STATUS_RESET and (sol.status[64:] == STATUS_UPDATED).all()
    assert np.linalg.norm(sol.pos_ecef_m[63:] - s.truth_ecef_m[63:], axis=1).max() < 30.0


def test_a_drift_beyond_the_initial_covariance_is_taken_from_the_dopplers_in_both_filters():
    """A 1.3 ppm oscillator (400 m/s of drift): from a zero drift at the start every Doppler failed the gate and,
    one epoch's pseudoranges not seeing the drift, they followed; 65 % of epochs coasted (a review). The start takes
    the drift from the Dopplers as it takes the clock from the coarse fix."""
    s = base = simulate_sequence(120, seed=3)
    extra = 350.0                                       # on top of the simulation's own drift
    t = s.time_gps_s - s.time_gps_s[0]
    clock = s.coarse_clock_m.copy()
    clock[:, 0] += extra * t
    s = replace(s, pr_m=np.where(s.mask, s.pr_m + extra * t[:, None], 0.0), coarse_clock_m=clock,
                prr_m_s=np.where(s.prr_mask, s.prr_m_s + extra, 0.0))
    drift, found = models.coarse_drift(s.prr_m_s[0], s.mask[0] & s.prr_mask[0], s.sat_pos_ecef_m[0],
                                       s.sat_vel_ecef_m_s[0], s.coarse_ecef_m[0])
    assert found and drift > 3 * np.sqrt(CONFIG.p0_drift_m2_s2)
    sol = _both_filters(s)
    assert np.all(sol.status[1:] == STATUS_UPDATED) and np.all(sol.info["n_doppler"] > 0)
    plain = LfgnssEkf(noise=FixedNoise(np.where(base.mask, 25.0, 0.0), np.zeros(base.mask.shape)),
                      config=CONFIG).solve(base)                                     # the simulation's drift only
    np.testing.assert_array_equal(sol.n_used, plain.n_used)
    np.testing.assert_allclose(sol.pos_ecef_m, plain.pos_ecef_m, rtol=0, atol=1e-3)


@pytest.mark.parametrize("extra", [350.0, -900.0])
def test_a_drift_without_dopplers_is_taken_from_the_coarse_clocks_in_both_filters(extra):
    """The same oscillator without Dopplers: the start could not see the drift, the pseudoranges of the next epoch
    failed the gate and most epochs coasted (docs/bad_input.md's known limitation). The epoch after a start without a
    Doppler drift takes it from the two coarse fixes' clocks."""
    base = simulate_sequence(120, seed=3)
    t = base.time_gps_s - base.time_gps_s[0]
    clock = base.coarse_clock_m.copy()
    clock[:, 0] += extra * t
    no_doppler = np.zeros_like(base.prr_mask)
    s = replace(base, pr_m=np.where(base.mask, base.pr_m + extra * t[:, None], 0.0), coarse_clock_m=clock,
                prr_mask=no_doppler)
    sol = _both_filters(s)
    assert np.all(sol.status[1:] == STATUS_UPDATED) and not sol.info["n_doppler"].any()
    plain = _both_filters(replace(base, prr_mask=no_doppler))                         # the simulation's drift only
    np.testing.assert_array_equal(sol.n_used, plain.n_used)
    np.testing.assert_allclose(sol.pos_ecef_m, plain.pos_ecef_m, rtol=0, atol=0.5)


def test_a_clock_jump_right_after_a_start_is_no_drift():
    """A 1 ms jump between a start's two coarse clocks is 3e5 m/s: no drift (MAX_COARSE_CLOCK_DRIFT_M_S), and the
    jump is left to the clock realignment."""
    got = models.coarse_clock_drift_m_s(np.array([0.0, 0.0, np.nan]), np.array([350.0, 3e5, 0.0]), np.ones(3))
    np.testing.assert_array_equal(got, [350.0, np.nan, np.nan])


def test_coarse_drift_is_the_lower_median_of_agreeing_dopplers_at_zero_velocity():
    """Vectorised over epochs; 0 where an epoch has fewer than 3 Dopplers or no majority within
    COARSE_DRIFT_SPREAD_M_S of the median (a drift fitted to an outlier kept every later Doppler out of the gate)."""
    from lfgnss.velocity import doppler_design

    s = simulate_sequence(6, seed=4)
    a, _ = doppler_design(s.sat_pos_ecef_m, s.sat_vel_ecef_m_s, s.coarse_ecef_m)
    cases = {0: [400.0, 410.0, 395.0, 2000.0],      # one outlier: the lower median of the rest
             1: [400.0],                             # one Doppler, or two: not enough to tell an outlier
             2: [400.0, -600.0],
             3: [-1000.0, -999.0, 48.0, 49.0],       # the median among outliers: no majority near it
             4: [30.0, -20.0, 10.0, 5.0, -35.0],     # a moving receiver's spread about a drift of 0
             5: []}
    ok = np.zeros_like(s.mask)
    prr = np.zeros(s.mask.shape)
    for k, rates in cases.items():
        slots = np.flatnonzero(s.mask[k])[:len(rates)]
        ok[k, slots] = True
        prr[k, slots] = a[k, slots] + np.array(rates)
    given = ok.copy()
    got, found = models.coarse_drift(prr, ok, s.sat_pos_ecef_m, s.sat_vel_ecef_m_s, s.coarse_ecef_m)
    np.testing.assert_allclose(got, [400.0, 0.0, 0.0, 0.0, 5.0, 0.0], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(found, [True, False, False, False, True, False])
    prr[4, np.flatnonzero(ok[4])[0]] = np.nan              # skipped (-20 of the other four), the caller's mask kept
    got = models.coarse_drift(prr, ok, s.sat_pos_ecef_m, s.sat_vel_ecef_m_s, s.coarse_ecef_m)[0]
    assert got[4] == pytest.approx(-20.0, abs=1e-6)
    np.testing.assert_array_equal(ok, given)


def test_a_drift_from_one_bad_doppler_is_not_taken():
    """The review's case: one Doppler 1000 m/s low at the first epoch, the only one there besides a second: the
    filter starts from drift 0 and gates it, as before (a drift fitted to it coasted half the drive)."""
    s = simulate_sequence(120, seed=3)
    prr_mask = s.prr_mask.copy()
    keep = np.flatnonzero(s.mask[0] & prr_mask[0])[:2]
    prr_mask[0] = False
    prr_mask[0, keep] = True
    prr = s.prr_m_s.copy()
    prr[0, keep[0]] -= 1000.0                     # the lower of two: their lower median
    s = replace(s, prr_mask=prr_mask, prr_m_s=prr)
    sol = _both_filters(s)
    assert np.all(sol.status[1:] == STATUS_UPDATED) and not sol.info["clock_realigned"].any()
    assert np.all(sol.info["n_doppler"][1:] > 0)


@pytest.mark.parametrize("min_redundancy, resets", [(2, False), (0, True)])
def test_a_coarse_fix_without_redundancy_resets_neither_filter(cases, min_redundancy, resets):
    """A far-off coarse fix at an epoch of 4 GPS + 1 BeiDou satellites (redundancy 0) cannot say it is the one that
    is right: neither twin resets to it (EkfConfig.reset_min_redundancy), unless the check is off."""
    seqs, r, vc = cases
    s = seqs[1]
    mask = s.mask.copy()
    for sys_id, keep in ((0, 4), (1, 1)):
        slots = np.flatnonzero(mask[80] & (s.system_index[80] == sys_id))
        mask[80, slots[keep:]] = False
    coarse = s.coarse_ecef_m.copy()
    coarse[80] += 400.0
    weak = replace(s, mask=mask, coarse_ecef_m=coarse, pr_m=np.where(mask, s.pr_m, 0.0))
    cfg = EkfConfig(reset_min_redundancy=min_redundancy)
    out = batch_ekf(to_batch([weak]), torch.as_tensor(r[1:2]), torch.as_tensor(vc[1:2]), n_systems=2, config=cfg)
    _assert_matches_plugin(out, [weak], r[1:2], vc[1:2], cfg)
    assert (out.status[0, 80].item() == STATUS_RESET) == resets
    assert models.snapshot_redundancy(mask[80], s.system_index[80], 2) == 0


def test_padded_slots_have_no_effect(cases):
    seqs, r, vc = cases
    batch = to_batch(seqs)
    rt = torch.as_tensor(r).clone().requires_grad_(True)
    vt = torch.as_tensor(vc).clone().requires_grad_(True)
    ref = batch_ekf(batch, rt, vt, n_systems=2, config=CONFIG)
    ref.pos_ecef_m[:, -1].nansum().backward()

    pad = ~batch.mask
    g = torch.Generator().manual_seed(0)
    junk = replace(batch,
                   pr_m=torch.where(pad, torch.rand(pad.shape, generator=g, dtype=torch.float64) * 1e7, batch.pr_m),
                   sat_pos_ecef_m=torch.where(pad[..., None], torch.full_like(batch.sat_pos_ecef_m, np.nan),
                                              batch.sat_pos_ecef_m),
                   system_index=torch.where(pad, torch.randint(-1, 2, pad.shape, generator=g), batch.system_index))
    r2 = torch.where(pad, torch.as_tensor(-5.0, dtype=torch.float64), torch.as_tensor(r)).requires_grad_(True)
    v2 = torch.where(pad, torch.as_tensor(1e4, dtype=torch.float64), torch.as_tensor(vc)).requires_grad_(True)
    got = batch_ekf(junk, r2, v2, n_systems=2, config=CONFIG)
    got.pos_ecef_m[:, -1].nansum().backward()

    assert torch.equal(torch.nan_to_num(got.pos_ecef_m), torch.nan_to_num(ref.pos_ecef_m))
    assert torch.equal(got.cov, ref.cov) and torch.equal(got.n_used, ref.n_used)
    assert torch.equal(r2.grad, rt.grad) and torch.equal(v2.grad, vt.grad)
    assert (r2.grad[pad] == 0).all() and (v2.grad[pad] == 0).all()


def test_gradient_reaches_early_epochs():
    seqs = [simulate_sequence(32, seed=s, n_slots=18) for s in range(4)]
    batch = to_batch(seqs)
    r = torch.full(batch.mask.shape, 20.0, dtype=torch.float64, requires_grad=True)
    vc = torch.zeros(batch.mask.shape, dtype=torch.float64, requires_grad=True)
    out = batch_ekf(batch, r, vc, n_systems=2, config=CONFIG)
    loss = (out.pos_ecef_m[:, -1] - batch.truth_ecef_m[:, -1]).norm(dim=-1).mean()
    loss.backward()
    for g in (r.grad, vc.grad):
        assert torch.isfinite(g).all()
        early = g[:, :3].abs().sum(dim=(1, 2))
        assert (early > 0).all(), early                  # every window, epochs 0-2, from a loss at epoch 31


def test_gradcheck_tiny_case():
    s = simulate_sequence(4, seed=4, sats_per_system=3, nlos_fraction=0.0, n_slots=8)
    s = replace(s, mask=np.where(np.arange(8) < 6, True, False)[None, :].repeat(4, 0))
    batch = to_batch([s])
    cfg = EkfConfig(gate_sigma=0.0)          # no hard decision near the finite-difference steps
    rng = np.random.default_rng(0)
    r0 = torch.as_tensor(rng.uniform(5.0, 30.0, (1, 4, 8)), dtype=torch.float64).requires_grad_(True)
    v0 = torch.as_tensor(rng.normal(0.0, 2.0, (1, 4, 8)), dtype=torch.float64).requires_grad_(True)

    def last_position(r, vc):
        return batch_ekf(batch, r, vc, n_systems=2, config=cfg).pos_ecef_m[:, -1]

    assert torch.autograd.gradcheck(last_position, (r0, v0), eps=1e-3, atol=1e-5, rtol=1e-3)


def test_shape_errors_raise(cases):
    seqs, r, vc = cases
    with pytest.raises(ValueError, match="must be"):
        batch_ekf(to_batch(seqs), torch.as_tensor(r[:, :5]), torch.as_tensor(vc), n_systems=2, config=CONFIG)


def test_non_finite_noise_on_a_usable_slot_is_refused(cases):
    """As the plug-in refuses it: a NaN R failed every gate test and dropped its satellite in silence, so a diverged
    network still scored finite positions. Unusable slots may hold anything."""
    seqs, r, vc = cases
    batch = to_batch(seqs)
    slot = np.argwhere(seqs[0].mask[50])[0, 0]
    for bad_r, bad_vc in ((np.nan, 0.0), (0.0, 0.0), (-1.0, 0.0), (1.0, np.inf)):
        r2, vc2 = r.copy(), vc.copy()
        r2[0, 50, slot], vc2[0, 50, slot] = bad_r, bad_vc
        with pytest.raises(FloatingPointError, match=r"gave 1 usable pseudorange\(s\) an R that is not finite"):
            batch_ekf(batch, torch.as_tensor(r2), torch.as_tensor(vc2), n_systems=2, config=CONFIG)
        with pytest.raises(FloatingPointError, match="diverged network"):
            batch_ekf(batch, None, None, n_systems=2, config=CONFIG,
                      noise_step=lambda k, inn: (torch.as_tensor(r2[:, k]), torch.as_tensor(vc2[:, k])))
    r2, vc2 = r.copy(), vc.copy()
    r2[~np.stack([q.mask for q in seqs])], vc2[~np.stack([q.mask for q in seqs])] = np.nan, np.nan
    out = batch_ekf(batch, torch.as_tensor(r2), torch.as_tensor(vc2), n_systems=2, config=CONFIG)
    ref = batch_ekf(batch, torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    assert torch.equal(torch.nan_to_num(out.pos_ecef_m), torch.nan_to_num(ref.pos_ecef_m))


def test_noise_step_given_fixed_noise_equals_the_arrays(cases):
    """``noise_step`` is asked once per epoch with that epoch's innovations; fixed answers reproduce the arrays."""
    seqs, r, vc = cases
    batch = to_batch(seqs)
    ref = batch_ekf(batch, torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    asked = []

    def step(k, innovation):
        asked.append((k, innovation))
        return torch.as_tensor(r[:, k]), torch.as_tensor(vc[:, k])

    got = batch_ekf(batch, None, None, n_systems=2, config=CONFIG, noise_step=step)
    assert [k for k, _ in asked] == list(range(120))
    assert torch.equal(torch.nan_to_num(got.pos_ecef_m), torch.nan_to_num(ref.pos_ecef_m))
    assert torch.equal(got.status, ref.status)
    inn = torch.stack([i for _, i in asked], 1)
    assert torch.all(inn[~batch.mask] == 0) and torch.all(inn[1, :5] == 0)   # padded; seq 1 before its first fix
    assert inn[0, 41].abs().max() > 0                                             # after a reset there is a prior
    with pytest.raises(ValueError, match="either"):
        batch_ekf(batch, torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG, noise_step=step)
    with pytest.raises(ValueError, match="either"):
        batch_ekf(batch, None, None, n_systems=2, config=CONFIG)


def test_prior_innovation_twin(cases):
    """``prior_innovation`` equals ``estimators.models.prior_innovation_m``; its feature, ``innovation_feature``."""
    from estimators import models
    from learning.torch_ekf import _clock_rows, innovation_feature, prior_innovation
    from lfgnss.features import innovation_feature as innovation_feature_np

    s = cases[0][1]
    k = 30
    x = models.initial_state(s.truth_ecef_m[k] + [5.0, -3.0, 8.0], s.coarse_clock_m[k] + [40.0, -7.0])
    usable = s.mask[k].copy()
    usable[:3] = False
    idx = np.flatnonzero(usable)
    want = np.zeros(s.mask.shape[1])
    want[idx] = models.prior_innovation_m(x, s.sat_pos_ecef_m[k, idx], s.system_index[k, idx], s.pr_m[k, idx])
    u = torch.as_tensor(usable)[None]
    got = prior_innovation(torch.as_tensor(x)[None], torch.as_tensor(s.sat_pos_ecef_m[k])[None],
                           _clock_rows(torch.as_tensor(s.system_index[k])[None], u, 9), torch.as_tensor(s.pr_m[k])[None],
                           u, torch.tensor([True]))[0].numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert np.sum(got[idx] < 0) in (idx.size // 2, (idx.size - 1) // 2)       # the lower median is removed
    np.testing.assert_allclose(innovation_feature(torch.as_tensor(want)).numpy(), innovation_feature_np(want))


def online_run(seqs, cfg: EkfConfig, seed: int, tmp_path):
    """A random online network (reads the prior innovations) exported to a model file of filter ``cfg``, and the
    positions the torch filter gives with it on ``seqs``: (model, (B, T, 3) positions)."""
    from learning.export import export_model, load_model
    from learning.network import LfgnssNet
    from learning.normalise import Normaliser
    from learning.train import run_filter
    from lfgnss.sequence import DEFAULT_FEATURES

    norm = Normaliser.fit(seqs, DEFAULT_FEATURES)
    torch.manual_seed(seed)
    net = LfgnssNet(len(DEFAULT_FEATURES), r_init_m2=30.0, innovation=True)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    ckpt = tmp_path / "last.pt"
    torch.save({"model": net.state_dict(), "model_hparams": net.hyperparameters(), "normaliser": norm.to_dict(),
                "config": {}, "epoch": 1, "history": [], "ekf_config": vars(cfg)}, ckpt)
    model = load_model(export_model(ckpt, tmp_path / "model.npz"))
    assert model.online
    batch = to_batch(seqs)
    batch.features = torch.as_tensor(np.stack([norm.apply(s.features, s.mask) for s in seqs]))
    batch.glonass = torch.as_tensor(np.stack([models.glonass_slots(s.system_index, s.systems) for s in seqs]))
    net64 = LfgnssNet(**net.hyperparameters()).double().eval()
    net64.load_state_dict(net.state_dict())
    with torch.no_grad():
        return model, run_filter(net64, batch, n_systems=2, ekf_cfg=cfg).numpy()


def test_online_network_plugin_matches_torch(cases, tmp_path):
    """A network that reads the prior innovations: the exported file in the numpy plug-in = the torch filter."""
    seqs = cases[0]
    model, pos = online_run(seqs, CONFIG, 0, tmp_path)
    for i, s in enumerate(seqs):
        sol = LfgnssEkf(model, config=CONFIG).solve(s)
        np.testing.assert_allclose(pos[i], sol.pos_ecef_m, rtol=0, atol=1e-4, equal_nan=True)  # float32 weights
        r, vc = model(s)                          # a NoiseModel too: the noise its own EKF run asked for
        np.testing.assert_array_equal(r, sol.info["noise_r_m2"])
        used = usable_measurements(s)
        np.testing.assert_array_equal(r[used], sol.info["r_m2"][used])
        assert np.all(r[s.mask] > 0) and np.any(vc[s.mask] != 0)
    fixed = LfgnssEkf(FixedNoise(r, vc), config=CONFIG).solve(seqs[-1])   # the same filter given those arrays
    np.testing.assert_array_equal(fixed.pos_ecef_m, sol.pos_ecef_m)


def test_glonass_sigma_factor_matches_the_plugin_and_scales_only_glonass():
    """glonass_sigma_factor in both filters: R of GLONASS slots times its square, the same run as giving that R."""
    rng = np.random.default_rng(3)
    seqs = [simulate_sequence(60, seed=40 + i, n_slots=16, systems=("G", "R")) for i in range(2)]
    r = np.stack([np.where(s.mask, rng.uniform(2.0, 60.0, s.mask.shape), 0.0) for s in seqs])
    vc = np.stack([np.where(s.mask, rng.normal(0.0, 2.0, s.mask.shape), 0.0) for s in seqs])
    cfg = EkfConfig(glonass_sigma_factor=1.5)
    glonass = np.stack([models.glonass_slots(s.system_index, s.systems) for s in seqs])
    assert glonass.any() and (~glonass & np.stack([s.mask for s in seqs])).any()
    batch = to_batch(seqs)
    batch.glonass = torch.as_tensor(glonass)
    out = batch_ekf(batch, torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=cfg)
    scaled = batch_ekf(to_batch(seqs), torch.as_tensor(np.where(glonass, 2.25 * r, r)), torch.as_tensor(vc),
                       n_systems=2, config=CONFIG)
    np.testing.assert_allclose(out.pos_ecef_m.numpy(), scaled.pos_ecef_m.numpy(), rtol=0, atol=1e-9, equal_nan=True)
    for i, s in enumerate(seqs):
        sol = LfgnssEkf(noise=FixedNoise(r[i], vc[i]), config=cfg).solve(s)
        np.testing.assert_array_equal(out.status[i].numpy(), sol.status)
        np.testing.assert_allclose(out.pos_ecef_m[i].numpy(), sol.pos_ecef_m, rtol=0, atol=1e-6, equal_nan=True)
        used = usable_measurements(s)
        assert (used & glonass[i]).any()
        np.testing.assert_allclose(sol.info["r_m2"][used], np.where(glonass[i], 2.25 * r[i], r[i])[used])
    plain = batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=CONFIG)
    assert not np.allclose(out.pos_ecef_m.numpy(), plain.pos_ecef_m.numpy(), rtol=0, atol=1e-3, equal_nan=True)
    with pytest.raises(ValueError, match="glonass_sigma_factor needs the batch's glonass flags"):
        batch_ekf(to_batch(seqs), torch.as_tensor(r), torch.as_tensor(vc), n_systems=2, config=cfg)


def test_glonass_sigma_factor_is_refused_unless_a_finite_positive_number():
    for bad in (0.0, -1.5, float("nan"), float("inf"), True, "1.5", 1e154, 1e-200):   # the last two: R times 1e308, 0
        with pytest.raises(ValueError, match="glonass_sigma_factor must be"):
            EkfConfig(glonass_sigma_factor=bad)
    flags = np.array([[True, False]])
    np.testing.assert_array_equal(models.pseudorange_variance_factor(flags, EkfConfig(glonass_sigma_factor=2.0)),
                                  [[4.0, 1.0]])
    np.testing.assert_array_equal(models.glonass_slots(np.array([[0, 1, -1]]), ("G", "C")), [[False, False, False]])
    np.testing.assert_array_equal(models.glonass_slots(np.array([[0, 1, -1]]), ("G", "R")), [[False, True, False]])


def test_collate_flags_glonass_slots_of_every_sequence():
    """Batches of a joint recipe mix sequences whose system_index means different letters: the flags follow each."""
    from learning.data import Window, collate
    from learning.normalise import Normaliser
    from lfgnss.sequence import DEFAULT_FEATURES

    gr = simulate_sequence(10, seed=1, n_slots=16, systems=("G", "R"))
    gc = simulate_sequence(10, seed=2, n_slots=16, systems=("G", "C"))
    batch = collate([gr, gc], [Window(0, 0, 10), Window(1, 0, 10)], Normaliser.fit([gr, gc], DEFAULT_FEATURES))
    expected = np.stack([np.char.startswith(gr.sv.astype(str), "R"), np.zeros(gc.sv.shape, bool)])
    assert expected[0].any()
    np.testing.assert_array_equal(batch.glonass.numpy(), expected)


def test_glonass_sigma_factor_online_network_matches_torch_and_is_not_applied_twice(tmp_path):
    """An online network in a GLONASS x 1.5 filter: plug-in = torch filter; the model as a NoiseModel gives the R it
    was asked for, so a filter given those arrays applies the factor once and repeats the run."""
    seqs = [simulate_sequence(60, seed=50 + i, n_slots=16, systems=("G", "R")) for i in range(2)]
    cfg = EkfConfig(glonass_sigma_factor=1.5)
    model, pos = online_run(seqs, cfg, 1, tmp_path)
    for i, s in enumerate(seqs):
        sol = LfgnssEkf(model).solve(s)                         # the file's filter: the factor 1.5
        assert sol.info["config"].glonass_sigma_factor == 1.5
        np.testing.assert_allclose(pos[i], sol.pos_ecef_m, rtol=0, atol=1e-4, equal_nan=True)  # float32 weights
        r, vc = model(s)
        used, glonass = usable_measurements(s), models.glonass_slots(s.system_index, s.systems)
        assert (used & glonass).any()
        np.testing.assert_allclose(sol.info["r_m2"][used], np.where(glonass, 2.25 * r, r)[used])
        fixed = LfgnssEkf(FixedNoise(r, vc), config=cfg).solve(s)
        np.testing.assert_allclose(fixed.pos_ecef_m, sol.pos_ecef_m, rtol=0, atol=1e-9, equal_nan=True)


def test_glonass_sigma_factor_applies_after_the_switch_off():
    """An R below R_OFF_M2 stays on however the factor scales it; one above is off, in both filters alike."""
    from estimators.noise import R_OFF_M2

    s = simulate_sequence(30, seed=61, n_slots=16, systems=("G", "R"))
    glonass = models.glonass_slots(s.system_index, s.systems)
    k = np.argwhere(s.mask & glonass)[0]
    cfg = EkfConfig(glonass_sigma_factor=1.5)
    for value, on in ((0.5 * R_OFF_M2, True), (2.0 * R_OFF_M2, False)):
        r = np.where(s.mask, 25.0, 0.0)
        r[k[0], k[1]] = value
        vc = np.zeros(r.shape)
        sol = LfgnssEkf(noise=FixedNoise(r, vc), config=cfg).solve(s)
        batch = to_batch([s])
        batch.glonass = torch.as_tensor(glonass[None])
        out = batch_ekf(batch, torch.as_tensor(r[None]), torch.as_tensor(vc[None]), n_systems=2, config=cfg)
        np.testing.assert_allclose(out.pos_ecef_m[0].numpy(), sol.pos_ecef_m, rtol=0, atol=1e-6, equal_nan=True)
        assert bool(sol.info["r_m2"][k[0], k[1]] == 2.25 * value) == on


def test_the_bundled_static_model_runs_with_rtklibs_glonass_factor():
    """Session 51's adoption is in the shipped file (the rows of docs/results.md read it), the others stay at 1."""
    from estimators.ekf import config_of

    assert config_of("hk-tst-static-2020").glonass_sigma_factor == 1.5
    for name in ("default", "berlin-pp", "hk-tst-2019"):
        assert config_of(name).glonass_sigma_factor == 1.0


def test_an_online_model_as_a_noise_model_keeps_its_switched_off_slots_off(cases, tmp_path):
    """model(seq) of an online model returns the R its network gave, 1e30 included: a graph or a weighted fix given
    those arrays leaves the satellite out too (it got R = 1 back before)."""
    seqs = cases[0][:1]
    model, _ = online_run(seqs, CONFIG, 2, tmp_path)
    predict = model.predict

    def predict_with_one_off(features, mask, innovation):
        r, vc = predict(features, mask, innovation)
        return np.where(np.arange(r.shape[-1]) == np.flatnonzero(mask)[0], 1e30, r), vc

    model.predict = predict_with_one_off
    r, _ = model(seqs[0])
    first = seqs[0].mask.argmax(axis=1)
    assert (r[np.arange(len(r)), first] == 1e30).all()
    assert (r[seqs[0].mask] > 0).all() and (r[seqs[0].mask] < 1e30).sum() > len(r)
