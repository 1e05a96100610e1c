"""HEM loss against a hand computation; RMSE loss; masking; safe gradients."""
import math

import numpy as np
import pytest
import torch

from learning.loss import hem_loss, hem_weights, make_loss, rmse_loss


def _case():
    truth = torch.zeros(4, 3, dtype=torch.float64)
    pos = torch.tensor([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 4.0], [0.3, 0.4, 0]], dtype=torch.float64)
    return pos, truth            # L = 1, 2, 4, 0.5


def test_hem_matches_hand_computation():
    pos, truth = _case()
    alpha, gamma, lam = 0.75, 1.5, 0.5
    Ls = [1.0, 2.0, 4.0, 0.5]
    samples = []
    for L in Ls:
        w = (1 - math.sqrt(L / 4.0)) ** (gamma * math.exp(-lam * L))
        samples.append(alpha * w * L)
    expect = math.sqrt(sum(s * s for s in samples) / 4)
    got = hem_loss(pos, truth, alpha=alpha, gamma=gamma, lam=lam)
    assert float(got) == pytest.approx(expect, rel=1e-12)
    # e.g. L = 1: w = 0.5 ** (1.5 e^-0.5) = 0.5 ** 0.909796 = 0.532260
    assert float(hem_weights(torch.tensor([1.0, 4.0], dtype=torch.float64), gamma=1.5, lam=0.5)[0]) == \
        pytest.approx(0.532260, abs=1e-6)


def test_rmse_and_unlabelled_epochs_ignored():
    pos, truth = _case()
    assert float(rmse_loss(pos, truth)) == pytest.approx(math.sqrt((1 + 4 + 16 + 0.25) / 4))
    truth2 = truth.clone()
    truth2[2] = float("nan")          # unlabelled: dropped from both losses
    assert float(rmse_loss(pos, truth2)) == pytest.approx(math.sqrt((1 + 4 + 0.25) / 3))
    assert torch.isfinite(hem_loss(pos, truth2))
    with pytest.raises(ValueError):
        rmse_loss(pos, torch.full_like(truth, float("nan")))


def test_gradients_finite_including_max_and_zero_error():
    pos, truth = _case()
    pos = torch.cat([pos, torch.zeros(1, 3, dtype=torch.float64)]).requires_grad_(True)
    truth = torch.cat([truth, torch.zeros(1, 3, dtype=torch.float64)])
    hem_loss(pos, truth).backward()
    assert torch.isfinite(pos.grad).all()
    assert pos.grad.abs().sum() > 0


@pytest.mark.parametrize("errors_m", [[5.0], [3.0, 3.0, 3.0]])
def test_a_batch_hem_weighs_zero_has_a_zero_loss_and_zero_gradients(errors_m):
    """One labelled sample, or all errors equal, is the maximum everywhere: every HEM weight is 0, so the loss is 0;
    its gradient must be 0 too, not the NaN of sqrt'(0) times 0 (one Adam step with it made every weight NaN)."""
    pos = torch.tensor([[e, 0.0, 0.0] for e in errors_m], dtype=torch.float64, requires_grad=True)
    loss = hem_loss(pos, torch.zeros_like(pos))
    loss.backward()
    assert float(loss) == 0.0 and torch.equal(pos.grad, torch.zeros_like(pos))
    perfect = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    rmse_loss(perfect, torch.zeros(2, 3, dtype=torch.float64)).backward()
    assert torch.equal(perfect.grad, torch.zeros_like(perfect))


def test_max_detached_and_batched_shapes():
    pos = torch.randn(2, 5, 3, dtype=torch.float64, requires_grad=True)
    loss = make_loss("hem")(pos, torch.zeros(2, 5, 3, dtype=torch.float64))
    loss.backward()
    assert torch.isfinite(pos.grad).all()
    with pytest.raises(ValueError):
        make_loss("huber")


def test_up_weight_scales_the_vertical_error_in_the_local_frame():
    """Errors made in ENU (lfgnss.frames, geodetic) at Hong Kong: up_weight 0 leaves the 2D error, 0.5 halves U."""
    import numpy as np

    from lfgnss.frames import enu_to_ecef, lla_to_ecef

    truth = lla_to_ecef(np.radians(22.30), np.radians(114.18), 10.0) * np.ones((3, 1))
    enu = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 8.0], [1.0, 2.0, 2.0]])
    pos = np.stack([enu_to_ecef(e, t) for e, t in zip(enu, truth)])
    pos_t, truth_t = torch.tensor(pos), torch.tensor(truth)
    for w in (0.0, 0.5, 1.0):
        expect = math.sqrt(np.mean(enu[:, 0] ** 2 + enu[:, 1] ** 2 + (w * enu[:, 2]) ** 2))
        assert float(make_loss("rmse", up_weight=w)(pos_t, truth_t)) == pytest.approx(expect, abs=1e-6)
    assert float(make_loss("hem", up_weight=0.0)(pos_t, truth_t)) < float(make_loss("hem")(pos_t, truth_t))
    with pytest.raises(ValueError, match="up_weight"):
        make_loss("rmse", up_weight=-1.0)


def test_pseudorange_error_matches_the_truth_noise_error_of_a_simulated_sequence():
    """The torch error at the truth is the simulator's injected error about its constellation's median (the
    numpy twin in estimators.TruthNoise), and 0 where the slot is unusable or the epoch unlabelled."""
    import numpy as np

    from lfgnss.features import system_median_m
    from lfgnss.simulate import simulate_sequence
    from learning.loss import pseudorange_error_m

    seq = simulate_sequence(25, seed=7)
    seq.truth_ecef_m[4] = np.nan
    injected = seq.features[..., seq.feature_names.index("residual")]
    usable = seq.mask & np.isfinite(seq.truth_ecef_m).all(axis=-1)[:, None]
    want = injected - system_median_m(injected, usable, seq.system_index, len(seq.systems))
    got = pseudorange_error_m(torch.as_tensor(seq.pr_m), torch.as_tensor(seq.sat_pos_ecef_m),
                              torch.as_tensor(seq.truth_ecef_m), torch.as_tensor(usable),
                              torch.as_tensor(seq.system_index), len(seq.systems)).numpy()
    assert np.allclose(got[usable], want[usable], atol=1e-6)
    assert np.all(got[~usable] == 0.0) and np.all(np.isfinite(got))


def test_compensation_loss_is_zero_for_the_perfect_correction_up_to_a_constellation_shift():
    """Huber of v^c + e about each constellation's median: one 40 m error does not move the others' score."""
    from learning.loss import compensation_loss

    error = torch.tensor([[3.0, -1.0, 40.0, 2.0, -2.0, 0.0]], dtype=torch.float64)
    system = torch.tensor([[0, 0, 0, 1, 1, 1]])
    usable = torch.tensor([[True, True, True, True, True, False]])
    shift = torch.tensor([[5.0, 5.0, 5.0, -7.0, -7.0, 99.0]], dtype=torch.float64)  # one per system; slot 5 unusable
    assert float(compensation_loss(-error + shift, error, usable, system, 2)) == pytest.approx(0.0, abs=1e-12)
    vc = torch.zeros_like(error, requires_grad=True)
    loss = compensation_loss(vc, error, usable, system, 2, delta_m=5.0)
    d = torch.tensor([0.0, -4.0, 37.0, 2.0, -2.0])     # centred on the medians: 3 (system 0) and 0 (system 1)
    want = torch.where(d.abs() <= 5.0, 0.5 * d ** 2, 5.0 * (d.abs() - 2.5)).mean()
    assert float(loss.detach()) == pytest.approx(float(want))
    loss.backward()
    assert torch.all(torch.isfinite(vc.grad)) and float(vc.grad[0, 5]) == 0.0
    none = torch.zeros_like(usable)
    assert float(compensation_loss(vc, error, none, system, 2).detach()) == 0.0


def test_variance_loss_is_the_gaussian_nll_of_the_centred_error_and_teaches_r_only():
    """0.5 (ln R + c^2 / R) over the usable satellites, c = v^c + e less its constellation's median; least at R = c^2;
    no gradient reaches v^c; 0 when nothing is usable."""
    from learning.loss import variance_loss

    error = torch.tensor([[3.0, -1.0, 40.0, 2.0, -2.0, 0.0]], dtype=torch.float64)
    system = torch.tensor([[0, 0, 0, 1, 1, 1]])
    usable = torch.tensor([[True, True, True, True, True, False]])
    r = torch.tensor([[1.0, 4.0, 100.0, 2.0, 8.0, 0.5]], dtype=torch.float64, requires_grad=True)
    vc = torch.full_like(error, 0.5, requires_grad=True)
    loss = variance_loss(r, vc, error, usable, system, 2)
    c = torch.tensor([0.0, -4.0, 37.0, 2.0, -2.0], dtype=torch.float64)    # medians 3.5 and 0.5 of v^c + e removed
    rr = r.detach()[usable]
    assert float(loss.detach()) == pytest.approx(float(0.5 * torch.mean(torch.log(rr) + c ** 2 / rr)))
    loss.backward()
    assert vc.grad is None or torch.all(vc.grad == 0)
    assert float(r.grad[0, 5]) == 0.0
    want = 0.5 / 5 * (1 / rr - c ** 2 / rr ** 2)                           # d/dR: zero at R = c^2
    assert torch.allclose(r.grad[usable], want)
    at_c2 = torch.tensor([[1.0, 16.0, 37.0 ** 2, 4.0, 4.0, 1.0]], dtype=torch.float64, requires_grad=True)
    variance_loss(at_c2, vc.detach(), error, usable, system, 2).backward()    # R = c^2 (slot 0: c = 0, R = 1)
    assert torch.allclose(at_c2.grad[0, 1:5], torch.zeros(4, dtype=torch.float64), atol=1e-12)
    assert float(variance_loss(r, vc, error, torch.zeros_like(usable), system, 2).detach()) == 0.0
    padded = r.detach().clone()
    padded[0, 5] = float("nan")                                   # an unusable slot may hold anything
    assert float(variance_loss(padded, vc, error, torch.zeros_like(usable), system, 2)) == 0.0
    assert torch.isfinite(variance_loss(padded, vc, error, usable, system, 2))


def test_the_strongest_clock_centres_on_the_three_strongest_of_five_or_more():
    """The "strongest" clock: the median of a constellation's three highest-C/N0 usable slots, only with five usable
    satellites or more in the epoch; the R term then reads only those slots (the script's labelling,
    benchmarks/bad_pseudoranges.py, on the same numbers)."""
    import importlib
    import sys as _sys
    from pathlib import Path as _Path

    from learning.loss import strongest_centred, variance_loss

    d = torch.tensor([[1.0, 25.0, 2.0, 30.0, 3.0, 40.0, 7.0, 8.0]], dtype=torch.float64)
    cn0 = torch.tensor([[48.0, 30.0, 47.0, 31.0, 46.0, 29.0, 50.0, 20.0]], dtype=torch.float64)
    system = torch.tensor([[0, 0, 0, 0, 0, 0, 1, 1]])
    usable = torch.tensor([[True] * 8])
    centred, kept = strongest_centred(d, cn0, usable, system, 2)
    assert kept.tolist() == [[True] * 6 + [False, False]]             # system 1 has two satellites: no clock
    assert centred[0, :6].tolist() == [-1.0, 23.0, 0.0, 28.0, 1.0, 38.0]   # clock 2: median of 1, 2, 3
    _sys.path.insert(0, str(_Path(__file__).resolve().parents[1] / "benchmarks"))
    bp = importlib.import_module("bad_pseudoranges")
    clock = bp.strongest_clock_m(d.numpy(), cn0.numpy(), usable.numpy(), system.numpy(), 2)
    assert np.allclose((d.numpy() - clock)[kept.numpy()], centred[kept].numpy())
    tied = torch.tensor([[45.0] * 8], dtype=torch.float64)            # equal C/N0: the lower slots, as the script
    centred_tied, _ = strongest_centred(d, tied, usable, system, 2)
    clock_tied = bp.strongest_clock_m(d.numpy(), tied.numpy(), usable.numpy(), system.numpy(), 2)
    assert np.allclose((d.numpy() - clock_tied)[kept.numpy()], centred_tied[kept].numpy())
    assert centred_tied[0, 0] == d[0, 0] - 2.0                         # slots 0, 1, 2: median of 1, 25, 2
    blind, low = cn0.clone(), d.clone()
    blind[0, 5], low[0, 5] = float("nan"), -100.0                      # an unknown C/N0 is the weakest, not chosen
    assert float(strongest_centred(low, blind, usable, system, 2)[0][0, 0]) == -1.0       # clock still 2
    r = torch.full_like(d, 4.0)
    want = 0.5 * torch.mean(torch.log(r[kept]) + centred[kept] ** 2 / r[kept])
    assert float(variance_loss(r, torch.zeros_like(d), d, usable, system, 2, cn0)) == pytest.approx(float(want))
    assert float(variance_loss(r, torch.zeros_like(d), d, usable & (system == 1), system, 2, cn0)) == 0.0
