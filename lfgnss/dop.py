"""Dilution of precision (DOP) and each satellite's DOP contribution, vectorised over epochs and satellites.

Inputs are padded ``(T, N)`` arrays with a boolean ``mask`` (True = satellite used). Padded slots
may hold any values (NaN included); they never influence a result and get 0 in per-satellite outputs.

Unknowns and the clock convention
---------------------------------
The unit design matrix (:func:`design_matrix`) has the columns ``[e, n, u, clock, ISB_1 .. ISB_{C-1}]``
in the local ENU frame; ``system_index == 0`` owns the receiver clock, every further system an
inter-system bias (ISB), as in :class:`lfgnss.sequence.Sequence`.

For DOP (:func:`dop`, :func:`dop_contribution`) the clock unknowns follow the satellites actually
present in the epoch, as a least-squares solver would set them up:

* an ISB column whose constellation has no satellite in the epoch is dropped (no unknown, no
  variance term in GDOP);
* if system 0 has no satellite, the lowest-index system present takes over the receiver clock
  (its ISB column is dropped, the others become ISBs relative to it).

Position DOPs (PDOP, HDOP, VDOP) do not depend on this choice; GDOP does, through its clock terms.
RTKLIB's ``dops()`` has one clock column whatever the constellations, so with several of them its DOPs are lower
than these (hk-tst-static-2020, five constellations, one epoch: G/P/H/V 2.70 / 2.18 / 1.14 / 1.86 against 3.31 /
2.44 / 1.24 / 2.10; GPS alone they agree), and its GDOP <= 30 cut reads another quantity than ``lfgnss.spp``'s.
The layout of :func:`design_matrix` itself is fixed and does not apply these rules.

Invalid epochs
--------------
``Dop.valid`` is False where the geometry cannot be solved: fewer satellites than unknowns or a
(numerically) singular normal matrix ``H^T H`` (smallest/largest eigenvalue < ``RCOND_MIN``). There
all four DOP values are 0 (never NaN or inf); always read them together with ``valid``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Relative eigenvalue floor of H^T H below which an epoch's geometry counts as singular.
RCOND_MIN = 1e-12
#: ``1 - h_i^T Q h_i`` below which removing satellite i leaves the geometry singular.
LEVERAGE_TOL = 1e-9
#: Default cap on DOP values inside :func:`dop_contribution` (see there).
DOP_CAP = 100.0

_N_GEOM = 4  # e, n, u, clock


@dataclass(frozen=True)
class Dop:
    """DOP per epoch, all ``(T,)``; the four values are 0 where ``valid`` is False."""

    gdop: np.ndarray
    pdop: np.ndarray
    hdop: np.ndarray
    vdop: np.ndarray
    valid: np.ndarray


def _check_inputs(el_rad, az_rad, system_index, mask, n_systems):
    """Shapes, dtypes and the system index range of used slots; returns sanitised arrays."""
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != bool:
        raise ValueError(f"dop: mask must be a (T, N) bool array, got dtype {mask.dtype} shape {mask.shape}")
    el = np.asarray(el_rad, dtype=float)
    az = np.asarray(az_rad, dtype=float)
    sys_idx = np.asarray(system_index)
    for name, arr in (("el_rad", el), ("az_rad", az), ("system_index", sys_idx)):
        if arr.shape != mask.shape:
            raise ValueError(f"dop: {name} has shape {arr.shape}, expected {mask.shape} like mask")
    if not np.issubdtype(sys_idx.dtype, np.integer):
        raise ValueError(f"dop: system_index must be integer, got {sys_idx.dtype}")
    if int(n_systems) < 1:
        raise ValueError(f"dop: n_systems must be >= 1, got {n_systems}")
    used = sys_idx[mask]
    if used.size and (used.min() < 0 or used.max() >= n_systems):
        raise ValueError(f"dop: system_index of used satellites must lie in [0, {n_systems}), "
                         f"got range [{used.min()}, {used.max()}]")
    if not (np.isfinite(el[mask]).all() and np.isfinite(az[mask]).all()):
        raise ValueError("dop: elevation/azimuth of used satellites must be finite")
    if el[mask].size and np.abs(el[mask]).max() > np.pi / 2 + 1e-9:
        raise ValueError(f"dop: el_rad of used satellites must lie in [-pi/2, pi/2], got up to "
                         f"{np.abs(el[mask]).max():g}: degrees? (np.radians converts them)")
    if az[mask].size and np.abs(az[mask]).max() > 2 * np.pi + 1e-9:
        raise ValueError(f"dop: az_rad of used satellites must lie in [-2 pi, 2 pi], got up to "
                         f"{np.abs(az[mask]).max():g}: degrees? (np.radians converts them)")
    el = np.where(mask, el, 0.0)
    az = np.where(mask, az, 0.0)
    sys_idx = np.where(mask, sys_idx, 0)
    return el, az, sys_idx, mask, int(n_systems)


def _design(el, az, sys_idx, mask, n_systems) -> np.ndarray:
    """Fixed-layout unit design matrix from sanitised inputs, (T, N, 4 + C - 1)."""
    ce = np.cos(el)
    geom = np.stack([-ce * np.sin(az), -ce * np.cos(az), -np.sin(el), np.ones_like(el)], axis=-1)
    isb = (sys_idx[..., None] == np.arange(1, n_systems)).astype(float)  # (T, N, C-1)
    return np.concatenate([geom, isb], axis=-1) * mask[..., None]


def design_matrix(el_rad: np.ndarray, az_rad: np.ndarray, system_index: np.ndarray, mask: np.ndarray,
                  n_systems: int) -> np.ndarray:
    """Unit design matrix in ENU with clock and ISB columns, rows zero where masked.

    Row of satellite i (line of sight from receiver to satellite is ``(cos el sin az, cos el cos az,
    sin el)`` in ENU; the pseudorange derivative with respect to the receiver position is minus it)::

        h_i = [-cos(el) sin(az), -cos(el) cos(az), -sin(el), 1, onehot(system_index - 1)]

    where the one-hot block has ``n_systems - 1`` columns and is all zero for system 0.

    Parameters
    ----------
    el_rad, az_rad : (T, N) float
        Elevation and azimuth [rad]; anything in masked slots.
    system_index : (T, N) int
        Constellation index in ``[0, n_systems)`` for used slots; anything in masked slots.
    mask : (T, N) bool
        True where the satellite is used.
    n_systems : int
        Number of constellations C (one receiver clock + C - 1 ISBs).

    Returns
    -------
    (T, N, 4 + C - 1) float
    """
    return _design(*_check_inputs(el_rad, az_rad, system_index, mask, n_systems))


def satellites_per_system(system_index: np.ndarray, mask: np.ndarray, n_systems: int) -> np.ndarray:
    """(..., C) int: the ``mask`` satellites of each system in each epoch (``system_index``, ``mask``: (..., N)).

    A system is present where its count is > 0; the epoch's reference (clock) system is the lowest-index
    system present, ``np.argmax(counts > 0, axis=1)`` (0 if none is), the convention of this module, of
    ``lfgnss.spp`` and of the factor graph's clocks.
    """
    return ((system_index[..., None] == np.arange(n_systems)) & mask[..., None]).sum(axis=-2)


def _active_columns(sys_idx, mask, n_systems):
    """Satellites per system (T, C), active ISB columns (T, C-1) and reference system (T,).

    Reference system = lowest-index system present (0 if none is); ISB column s-1 is active iff
    system s is present and is not the reference.
    """
    counts = satellites_per_system(sys_idx, mask, n_systems)
    present = counts > 0
    ref = np.argmax(present, axis=1)  # first True; 0 when none present
    sys_ids = np.arange(1, n_systems)
    active_isb = present[:, 1:] & (sys_ids[None, :] != ref[:, None])
    return counts, active_isb, ref


def _solve_geometry(el, az, sys_idx, mask, n_systems):
    """Design matrix with the epoch's active columns, covariance Q (T, K, K) and validity (T,)."""
    counts, active_isb, ref = _active_columns(sys_idx, mask, n_systems)
    t = mask.shape[0]
    active = np.concatenate([np.ones((t, _N_GEOM), bool), active_isb], axis=1)  # (T, K)
    h = _design(el, az, sys_idx, mask, n_systems)
    # The reference system's satellites keep only the clock column: zero inactive columns.
    h = h * active[:, None, :]
    normal = np.einsum("tnk,tnl->tkl", h, h)
    # Inactive columns are all zero: put 1 on their diagonal so the matrix stays invertible and the
    # column decouples; its variance is zeroed after inversion.
    inactive_eye = np.einsum("tk,kl->tkl", (~active).astype(float), np.eye(active.shape[1]))
    normal = normal + inactive_eye
    eig = np.linalg.eigvalsh(normal)
    n_unknowns = active.sum(axis=1)
    valid = (mask.sum(axis=1) >= n_unknowns) & (eig[:, 0] > RCOND_MIN * np.maximum(eig[:, -1], 1.0))
    safe = np.where(valid[:, None, None], normal, np.eye(normal.shape[1]))
    q = np.linalg.inv(safe)                                   # Q = (H^T H)^-1
    q = q * (active[:, :, None] & active[:, None, :]) * valid[:, None, None]
    return h, q, valid, counts, active_isb, ref


def _dops_from_diag(diag: np.ndarray) -> np.ndarray:
    """(..., 4) [GDOP, PDOP, HDOP, VDOP] from the diagonal of Q (..., K); inactive terms are 0."""
    d = np.maximum(diag, 0.0)
    return np.sqrt(np.stack([d.sum(axis=-1), d[..., :3].sum(axis=-1), d[..., :2].sum(axis=-1), d[..., 2]],
                            axis=-1))


def dop(el_rad: np.ndarray, az_rad: np.ndarray, system_index: np.ndarray, mask: np.ndarray,
        n_systems: int) -> Dop:
    """GDOP, PDOP, HDOP and VDOP per epoch.

    ``Q = (H^T H)^-1`` with H the unit design matrix (module docstring: clock columns follow the
    systems present), then::

        GDOP = sqrt(trace Q),  PDOP = sqrt(Qee + Qnn + Quu),  HDOP = sqrt(Qee + Qnn),  VDOP = sqrt(Quu)

    Parameters
    ----------
    el_rad, az_rad, system_index, mask, n_systems
        As :func:`design_matrix`, shapes (T, N).

    Returns
    -------
    Dop
        (T,) arrays; values 0 where ``valid`` is False (too few satellites, singular geometry).
    """
    el, az, sys_idx, mask, n_systems = _check_inputs(el_rad, az_rad, system_index, mask, n_systems)
    _, q, valid, *_ = _solve_geometry(el, az, sys_idx, mask, n_systems)
    vals = _dops_from_diag(np.diagonal(q, axis1=1, axis2=2))
    return Dop(gdop=vals[:, 0], pdop=vals[:, 1], hdop=vals[:, 2], vdop=vals[:, 3], valid=valid)


def dop_contribution(el_rad: np.ndarray, az_rad: np.ndarray, system_index: np.ndarray, mask: np.ndarray,
                     n_systems: int, cap: float = DOP_CAP) -> np.ndarray:
    """DOP contribution (DPC) of every satellite: full minus leave-this-satellite-out DOP.

    All leave-one-out covariances come from one inversion by the rank-one downdate
    (Sherman-Morrison; RTKLIB has no equivalent)::

        Q_-i = Q + (Q h_i)(Q h_i)^T / (1 - h_i^T Q h_i)

    of which only the diagonal is formed. With both DOPs capped at ``cap``::

        DPC_i = min(DOP_full, cap) - min(DOP_-i, cap)        for (GDOP, PDOP, HDOP, VDOP)

    which is <= 0 when removing a satellite weakens the geometry, continuous in the geometry, and
    bounded by ``cap`` in magnitude.

    Singular leave-one-out (leverage ``h_i^T Q h_i`` = 1):

    * satellite i is the only one of its constellation: its clock unknown leaves with it (module
      docstring). Its measurement only fixed that unknown, so PDOP/HDOP/VDOP are unchanged (DPC 0)
      and GDOP drops that clock's variance: ``Q_ss`` for an ISB, or, for the reference clock, the
      next system present takes over the clock and GDOP is evaluated in those unknowns. The GDOP
      contribution can then be positive.
    * otherwise (e.g. exactly as many satellites as unknowns) the rest cannot be solved: all four
      leave-one-out DOPs are taken as ``cap``.

    Parameters
    ----------
    el_rad, az_rad, system_index, mask, n_systems
        As :func:`design_matrix`, shapes (T, N).
    cap : float
        Upper limit applied to full and leave-one-out DOPs (default :data:`DOP_CAP`).

    Returns
    -------
    (T, N, 4) float
        Contributions ``[dGDOP, dPDOP, dHDOP, dVDOP]``; 0 in masked slots and in epochs whose full
        geometry is invalid (``dop(...).valid`` False).
    """
    if not cap > 0:
        raise ValueError(f"dop_contribution: cap must be positive, got {cap}")
    el, az, sys_idx, mask, n_systems = _check_inputs(el_rad, az_rad, system_index, mask, n_systems)
    h, q, valid, counts, active_isb, ref = _solve_geometry(el, az, sys_idx, mask, n_systems)
    t, n = mask.shape
    diag = np.diagonal(q, axis1=1, axis2=2)                        # (T, K)
    full = np.minimum(_dops_from_diag(diag), cap)                  # (T, 4)

    qh = np.einsum("tkl,tnl->tnk", q, h)                           # Q h_i, (T, N, K)
    lev = np.einsum("tnk,tnk->tn", h, qh)                          # h_i^T Q h_i
    denom = 1.0 - lev
    regular = denom > LEVERAGE_TOL
    loo_diag = diag[:, None, :] + qh ** 2 / np.where(regular, denom, 1.0)[..., None]
    loo = _dops_from_diag(loo_diag)                                # (T, N, 4)

    # Sole satellite of its constellation.
    sole = np.take_along_axis(counts, sys_idx, axis=1) == 1        # (T, N)
    is_ref = sys_idx == ref[:, None]
    # (a) an ISB's only satellite: drop that ISB's variance term.
    isb_var = np.concatenate([np.zeros((t, 1)), diag[:, _N_GEOM:]], axis=1)       # (T, C) by system
    g_isb = np.sqrt(np.maximum(diag.sum(axis=1)[:, None] - np.take_along_axis(isb_var, sys_idx, axis=1), 0.0))
    # (b) the reference clock's only satellite: the next system present (r2) takes over the clock;
    # clock' = clock + isb_r2, isb'_s = isb_s - isb_r2 for the other active s.
    if n_systems > 1:
        next_ref = np.argmax(active_isb, axis=1)                   # ISB column index of r2 (0 if none)
        has_next = active_isb.any(axis=1)
        qc = q[:, _N_GEOM:, _N_GEOM:]                              # ISB block (T, C-1, C-1)
        r2 = _N_GEOM + next_ref
        ti = np.arange(t)
        q_cc = q[:, 3, 3]
        q_c2 = q[ti, 3, r2]
        q_22 = q[ti, r2, r2]
        q_s2 = np.take_along_axis(q[:, _N_GEOM:, :], r2[:, None, None], axis=2)[..., 0]  # Q[s, r2], (T, C-1)
        others = active_isb & (np.arange(n_systems - 1)[None, :] != next_ref[:, None])
        var_others = (np.diagonal(qc, axis1=1, axis2=2) - 2.0 * q_s2 + q_22[:, None]) * others
        g_ref2 = diag[:, :3].sum(axis=1) + (q_cc + 2.0 * q_c2 + q_22) + var_others.sum(axis=1)
        g_ref = np.sqrt(np.maximum(g_ref2, 0.0))
    else:
        g_ref = np.zeros(t)
        has_next = np.zeros(t, bool)
    sole_isb = sole & ~is_ref
    sole_ref = sole & is_ref & has_next[:, None]
    pos_full = _dops_from_diag(diag)[:, None, 1:]                  # unchanged P/H/V DOP, (T, 1, 3)
    loo = np.where(sole_isb[..., None],
                   np.concatenate([g_isb[..., None], np.broadcast_to(pos_full, (t, n, 3))], axis=-1), loo)
    loo = np.where(sole_ref[..., None],
                   np.concatenate([np.broadcast_to(g_ref[:, None, None], (t, n, 1)),
                                   np.broadcast_to(pos_full, (t, n, 3))], axis=-1), loo)
    # Any other singular leave-one-out: cap.
    singular = ~regular & ~sole_isb & ~sole_ref
    loo = np.where(singular[..., None], cap, np.minimum(loo, cap))
    out = full[:, None, :] - loo
    return np.where((mask & valid[:, None])[..., None], out, 0.0)
