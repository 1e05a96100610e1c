"""LfgnssNet: shapes, padding mask, empty epochs, any N."""
import pytest
import torch

from learning.network import PAD_R_M2, LfgnssNet


def _inputs(b=3, t=None, n=10, d=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    shape = (b, n) if t is None else (b, t, n)
    x = torch.randn(*shape, d, generator=g)
    mask = torch.rand(*shape, generator=g) > 0.3
    return x, mask


@pytest.mark.parametrize("t", [None, 5], ids=["BNd", "BTNd"])
def test_shapes_positive_r_and_inert_padding(t):
    torch.manual_seed(0)
    net = LfgnssNet(8, r_floor_m2=0.05)
    x, mask = _inputs(t=t)
    r, vc = net(x, mask)
    assert r.shape == mask.shape and vc.shape == mask.shape
    assert torch.all(r[mask] >= 0.05)
    assert torch.all(r[~mask] == PAD_R_M2) and torch.all(vc[~mask] == 0)


def test_padded_slots_do_not_influence_valid_outputs():
    torch.manual_seed(0)
    net = LfgnssNet(8).eval()
    x, mask = _inputs()
    r, vc = net(x, mask)
    x2 = torch.where(mask[..., None], x, torch.randn_like(x) * 100)
    r2, vc2 = net(x2, mask)
    torch.testing.assert_close(r, r2)
    torch.testing.assert_close(vc, vc2)
    # extra padded slots at the end change nothing either (any N)
    xp = torch.cat([x, torch.randn(3, 4, 8)], dim=1)
    mp = torch.cat([mask, torch.zeros(3, 4, dtype=torch.bool)], dim=1)
    r3, vc3 = net(xp, mp)
    torch.testing.assert_close(r3[:, :10], r)
    torch.testing.assert_close(vc3[:, :10], vc)


def test_permutation_equivariant():
    torch.manual_seed(0)
    net = LfgnssNet(8).eval()
    x, mask = _inputs(n=7)
    perm = torch.randperm(7)
    r, vc = net(x, mask)
    rp, vcp = net(x[:, perm], mask[:, perm])
    torch.testing.assert_close(rp, r[:, perm])
    torch.testing.assert_close(vcp, vc[:, perm])


def test_empty_epoch_gives_no_nan_in_values_or_gradients():
    torch.manual_seed(0)
    net = LfgnssNet(8)
    x, mask = _inputs(b=2, n=6)
    mask[0] = False
    r, vc = net(x, mask)
    assert torch.isfinite(r).all() and torch.isfinite(vc).all()
    (r.sum() + vc.sum()).backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)


def test_r_init_sets_initial_variance():
    net = LfgnssNet(8, r_init_m2=25.0)
    with torch.no_grad():
        net.head.weight.zero_()
    r, _ = net(torch.zeros(1, 3, 8), torch.ones(1, 3, dtype=torch.bool))
    torch.testing.assert_close(r, torch.full((1, 3), 25.0), rtol=1e-4, atol=1e-4)


def test_bad_shapes_raise():
    net = LfgnssNet(8)
    with pytest.raises(ValueError):
        net(torch.zeros(2, 5, 7), torch.ones(2, 5, dtype=torch.bool))


def test_innovation_input_is_one_more_column_and_required():
    """``innovation=True``: the innovation enters as column d + 1, and must be given (and only then)."""
    torch.manual_seed(0)
    net = LfgnssNet(8, innovation=True)
    x, mask = torch.randn(2, 5, 8), torch.ones(2, 5, dtype=torch.bool)
    assert net.embed.in_features == 9 and net.hyperparameters()["innovation"] is True
    r0, _ = net(x, mask, torch.zeros(2, 5))
    r1, _ = net(x, mask, torch.full((2, 5), 3.0))
    assert not torch.allclose(r0, r1)
    with pytest.raises(ValueError, match="needs an innovation"):
        net(x, mask)
    with pytest.raises(ValueError, match="takes no innovation"):
        LfgnssNet(8)(x, mask, torch.zeros(2, 5))
