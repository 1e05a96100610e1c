"""DOP and leave-one-out DOP contribution against brute-force inversion."""
from __future__ import annotations

import numpy as np
import pytest

from lfgnss.dop import DOP_CAP, Dop, design_matrix, dop, dop_contribution


# ---------------------------------------------------------------- brute-force reference
def _brute_epoch(el, az, sys, n_systems):
    """[GDOP, PDOP, HDOP, VDOP] or None if singular; clock columns follow the systems present.

    Independent of lfgnss.dop: builds H column by column for one epoch and inverts it.
    """
    present = sorted(set(int(s) for s in sys))
    if not present:
        return None
    ref = present[0]
    isb_systems = [s for s in present if s != ref]
    cols = [-np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), -np.sin(el), np.ones_like(el)]
    cols += [(sys == s).astype(float) for s in isb_systems]
    h = np.stack(cols, axis=1)
    if h.shape[0] < h.shape[1] or np.linalg.matrix_rank(h, tol=1e-9) < h.shape[1]:
        return None
    q = np.linalg.inv(h.T @ h)
    d = np.diag(q)
    return np.sqrt([d.sum(), d[:3].sum(), d[:2].sum(), d[2]])


def _brute(el, az, sys, mask, n_systems, cap=DOP_CAP):
    t, n = mask.shape
    full = np.zeros((t, 4))
    valid = np.zeros(t, bool)
    dpc = np.zeros((t, n, 4))
    for k in range(t):
        idx = np.flatnonzero(mask[k])
        f = _brute_epoch(el[k, idx], az[k, idx], sys[k, idx], n_systems)
        if f is None:
            continue
        valid[k] = True
        full[k] = f
        for i in idx:
            keep = idx[idx != i]
            g = _brute_epoch(el[k, keep], az[k, keep], sys[k, keep], n_systems)
            loo = np.full(4, cap) if g is None else np.minimum(g, cap)
            dpc[k, i] = np.minimum(f, cap) - loo
    return full, valid, dpc


def _random_geometry(rng, t, n, n_systems, p_mask=0.2, junk=True):
    el = rng.uniform(np.radians(5), np.radians(89), (t, n))
    az = rng.uniform(0, 2 * np.pi, (t, n))
    sys = rng.integers(0, n_systems, (t, n))
    mask = rng.random((t, n)) > p_mask
    if junk:  # padded slots carry garbage that must not matter
        el = np.where(mask, el, np.nan)
        az = np.where(mask, az, 1e9)
        sys = np.where(mask, sys, -7)
    return el, az, sys, mask


def _check_against_brute(el, az, sys, mask, n_systems, atol=1e-8):
    full, valid, dpc = _brute(el, az, sys, mask, n_systems)
    d = dop(el, az, sys, mask, n_systems)
    np.testing.assert_array_equal(d.valid, valid)
    got = np.stack([d.gdop, d.pdop, d.hdop, d.vdop], axis=1)
    np.testing.assert_allclose(got[valid], full[valid], rtol=1e-9, atol=atol)
    assert np.all(got[~valid] == 0.0)
    c = dop_contribution(el, az, sys, mask, n_systems)
    assert c.shape == mask.shape + (4,)
    assert np.isfinite(c).all()
    np.testing.assert_allclose(c, dpc, rtol=1e-7, atol=atol)
    return c


# ---------------------------------------------------------------- design matrix
def test_design_matrix_rows_and_padding():
    el = np.array([[np.pi / 2, 0.0, np.nan]])
    az = np.array([[0.3, np.pi / 2, np.nan]])
    sys = np.array([[0, 2, -1]])
    mask = np.array([[True, True, False]])
    h = design_matrix(el, az, sys, mask, n_systems=3)
    assert h.shape == (1, 3, 6)
    np.testing.assert_allclose(h[0, 0], [0, 0, -1, 1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(h[0, 1], [-1, 0, 0, 1, 0, 1], atol=1e-15)
    assert np.all(h[0, 2] == 0)


@pytest.mark.parametrize("bad", ["shape", "system", "mask_dtype"], ids=["shape", "system-range", "mask-dtype"])
def test_bad_inputs_raise(bad):
    el = np.zeros((2, 3))
    sys = np.zeros((2, 3), int)
    mask = np.ones((2, 3), bool)
    with pytest.raises(ValueError):
        if bad == "shape":
            dop(el, el[:, :2], sys, mask, 1)
        elif bad == "system":
            dop(el, el, sys + 1, mask, 1)
        else:
            dop(el, el, sys, mask.astype(int), 1)


def test_angles_in_degrees_are_refused():
    """Degrees given for radians used to give a median PDOP of 0.96 on the bundled drive (1.36 in radians)."""
    el = np.array([[10.0, 35.0, 60.0, 80.0]])
    az = np.array([[0.0, 90.0, 180.0, 270.0]])
    sys, mask = np.zeros((1, 4), int), np.ones((1, 4), bool)
    with pytest.raises(ValueError, match=r"^dop: el_rad of used satellites must lie in \[-pi/2, pi/2\], got up to 80: "
                                         r"degrees\?"):
        dop(el, np.radians(az), sys, mask, 1)
    with pytest.raises(ValueError, match=r"^dop: az_rad .* got up to 270: degrees\?"):
        dop(np.radians(el), az, sys, mask, 1)
    assert np.isfinite(dop(np.radians(el), np.radians(az), sys, mask, 1).pdop).all()


# ---------------------------------------------------------------- analytic value
@pytest.mark.parametrize("el_deg", [0.0, 30.0, 45.0], ids=["el0", "el30", "el45"])
@pytest.mark.parametrize("n_ring", [3, 4, 6], ids=["ring3", "ring4", "ring6"])
def test_symmetric_geometry_analytic(el_deg, n_ring):
    """n satellites evenly spaced in azimuth at elevation e, plus one at zenith.

    HDOP^2 = 4 / (n cos^2 e); the (up, clock) block has det n (1 - sin e)^2, so
    VDOP^2 = (n + 1) / det and TDOP^2 = (n sin^2 e + 1) / det.
    """
    e = np.radians(el_deg)
    el = np.array([[e] * n_ring + [np.pi / 2]])
    az = np.array([[2 * np.pi * k / n_ring + 0.1 for k in range(n_ring)] + [0.0]])
    sys = np.zeros_like(el, dtype=int)
    mask = np.ones_like(el, dtype=bool)
    det = n_ring * (1 - np.sin(e)) ** 2
    h2, v2, t2 = 4 / (n_ring * np.cos(e) ** 2), (n_ring + 1) / det, (n_ring * np.sin(e) ** 2 + 1) / det
    d = dop(el, az, sys, mask, 1)
    assert d.valid[0]
    np.testing.assert_allclose([d.gdop[0], d.pdop[0], d.hdop[0], d.vdop[0]],
                               np.sqrt([h2 + v2 + t2, h2 + v2, h2, v2]), rtol=1e-12)
    if (el_deg, n_ring) == (0.0, 3):
        np.testing.assert_allclose(d.gdop[0], np.sqrt(3.0), rtol=1e-12)


# ---------------------------------------------------------------- against brute force
@pytest.mark.parametrize("n_systems", [1, 2, 3, 4], ids=lambda c: f"C{c}")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_geometries_match_brute_force(seed, n_systems):
    rng = np.random.default_rng(seed)
    el, az, sys, mask = _random_geometry(rng, t=40, n=12, n_systems=n_systems)
    c = _check_against_brute(el, az, sys, mask, n_systems)
    # Position DOPs never improve when a satellite is removed.
    assert np.all(c[..., 1:] <= 1e-9)


@pytest.mark.parametrize("n_systems", [1, 2, 3], ids=lambda c: f"C{c}")
def test_sparse_geometries_with_singular_leave_one_out(n_systems):
    """Few satellites: minimal sets, sole satellites of a constellation, absent systems, 1-3 sats."""
    rng = np.random.default_rng(42)
    el, az, sys, mask = _random_geometry(rng, t=300, n=7, n_systems=n_systems, p_mask=0.35)
    _check_against_brute(el, az, sys, mask, n_systems)


def test_exactly_minimal_satellites_caps_leave_one_out():
    """4 + C - 1 satellites: every leave-one-out is unsolvable -> leave-one-out DOP = cap."""
    rng = np.random.default_rng(3)
    n_systems = 2
    el = rng.uniform(0.2, 1.4, (1, 5))
    az = rng.uniform(0, 2 * np.pi, (1, 5))
    sys = np.array([[0, 0, 0, 1, 1]])
    mask = np.ones((1, 5), bool)
    d = dop(el, az, sys, mask, n_systems)
    assert d.valid[0]
    full = np.minimum([d.gdop[0], d.pdop[0], d.hdop[0], d.vdop[0]], DOP_CAP)
    c = dop_contribution(el, az, sys, mask, n_systems)
    np.testing.assert_allclose(c[0], np.broadcast_to(full - DOP_CAP, (5, 4)), rtol=1e-12)
    _check_against_brute(el, az, sys, mask, n_systems)


@pytest.mark.parametrize("sole_system", [0, 1, 2], ids=["sole-ref-clock", "sole-isb1", "sole-isb2"])
def test_single_satellite_of_a_system(sole_system):
    """Removing the only satellite of a constellation removes its clock: P/H/V DPC = 0."""
    rng = np.random.default_rng(7)
    el = rng.uniform(0.2, 1.4, (1, 10))
    az = rng.uniform(0, 2 * np.pi, (1, 10))
    sys = np.array([[0, 0, 0, 0, 1, 1, 1, 2, 2, 2]])
    others = [s for s in range(3) if s != sole_system]
    sys = np.where(sys == sole_system, others[0], sys)
    sys[0, 0] = sole_system
    mask = np.ones((1, 10), bool)
    c = _check_against_brute(el, az, sys, mask, 3)
    np.testing.assert_allclose(c[0, 0, 1:], 0.0, atol=1e-12)
    assert c[0, 0, 0] != 0.0


def test_padding_does_not_change_results():
    rng = np.random.default_rng(11)
    el, az, sys, mask = _random_geometry(rng, t=20, n=9, n_systems=2, junk=False)
    base_d = dop(el, az, sys, mask, 2)
    base_c = dop_contribution(el, az, sys, mask, 2)
    # Junk in masked slots, and extra padded slots at the end.
    el2 = np.where(mask, el, np.inf)
    az2 = np.where(mask, az, np.nan)
    sys2 = np.where(mask, sys, 99)
    pad = lambda a, v: np.concatenate([a, np.full((a.shape[0], 3), v, dtype=a.dtype)], axis=1)
    el2, az2, sys2, mask2 = pad(el2, np.nan), pad(az2, -5.0), pad(sys2, -1), pad(mask, False)
    d = dop(el2, az2, sys2, mask2, 2)
    c = dop_contribution(el2, az2, sys2, mask2, 2)
    for f in ("gdop", "pdop", "hdop", "vdop", "valid"):
        np.testing.assert_array_equal(getattr(d, f), getattr(base_d, f))
    np.testing.assert_array_equal(c[:, :9], base_c)
    assert np.all(c[:, 9:] == 0.0)
    assert np.all(c[~mask2] == 0.0)


def test_invalid_epochs_are_zero_not_nan():
    el = np.array([[0.5, 0.6, 0.7, np.nan], [0.5] * 4, [0.1, 0.2, 0.3, 1.2]])
    az = np.array([[0.0, 1.0, 2.0, 0.0], [0.0, 1.0, 2.0, 3.0], [0.0, 2.0, 4.0, 1.0]])
    sys = np.zeros((3, 4), int)
    mask = np.array([[True, True, True, False], [True] * 4, [False] * 4])
    d = dop(el, az, sys, mask, 1)
    assert isinstance(d, Dop)
    # 3 satellites; 4 at equal elevation (up and clock inseparable); none.
    np.testing.assert_array_equal(d.valid, [False, False, False])
    for f in ("gdop", "pdop", "hdop", "vdop"):
        assert np.all(getattr(d, f) == 0.0)
    c = dop_contribution(el, az, sys, mask, 1)
    assert np.all(c == 0.0)


def test_contribution_is_full_minus_leave_one_out_sign():
    rng = np.random.default_rng(5)
    el, az, sys, mask = _random_geometry(rng, t=10, n=10, n_systems=1, p_mask=0.0, junk=False)
    c = dop_contribution(el, az, sys, mask, 1)
    assert np.all(c <= 1e-12)
    assert np.all(c[..., 0] < 0)


def test_large_batch_is_vectorised_and_fast():
    import time
    rng = np.random.default_rng(0)
    el, az, sys, mask = _random_geometry(rng, t=20000, n=30, n_systems=4)
    t0 = time.perf_counter()
    c = dop_contribution(el, az, sys, mask, 4)
    assert np.isfinite(c).all()
    assert time.perf_counter() - t0 < 10.0
