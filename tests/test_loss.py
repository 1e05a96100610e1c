"""HEM loss against a hand computation; RMSE loss; masking; safe gradients."""
import math

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


def test_max_detached_and_batched_shapes():
    pos = torch.randn(2, 5, 3, dtype=torch.float64, requires_grad=True)
    loss = make_loss("hem")(pos, torch.zeros(2, 5, 3, dtype=torch.float64))
    loss.backward()
    assert torch.isfinite(pos.grad).all()
    with pytest.raises(ValueError):
        make_loss("huber")
