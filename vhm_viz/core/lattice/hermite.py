"""Tricubic Hermite cells: a cell's polynomial, its Bezier net, and its voxels (compiled).

A cell of size ``h`` (voxels) has 8 corners, each with a row of node data: the value
``f``, the first derivatives ``f_u, f_v, f_w`` in voxel index coordinates and the mixed
derivatives ``f_uv, f_uw, f_vw, f_uvw`` (:data:`N_TERMS` terms of 3 components). The
tensor product of cubic Hermite segments interpolates them; its 64 Bezier control points
contain the cell's image.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.lattice import cell_formulas
from vhm_viz.core.work_items import claim

#: Node data terms, in order: f, f_u, f_v, f_w, f_uv, f_uw, f_vw, f_uvw.
N_TERMS = 8
# Leaves that a worker of the voxel kernels claims at a time.
_LEAVES_PER_CLAIM = 2


@numba.njit(cache=True)
def _term(du, dv, dw):  # pragma: no cover - compiled
    """Index of the node term ``d^(du+dv+dw) f / du^du dv^dv dw^dw``."""
    if du + dv + dw == 0:
        return 0
    if du + dv + dw == 1:
        return 1 if du else (2 if dv else 3)
    if du + dv + dw == 2:
        return 6 if du == 0 else (5 if dv == 0 else 4)
    return 7


# The cell's polynomial, one home for the CPU's kernels and the GPU's
# (vhm_viz.core.lattice.cell_formulas); cell_eval and inverse3 with fused multiply-adds.
_weights = numba.njit(cache=True)(cell_formulas.hermite_weights)
cell_eval = numba.njit(fastmath={"contract"})(cell_formulas.cell_evaluator(_weights))
inverse3 = numba.njit(cache=True, fastmath={"contract"})(cell_formulas.inverse3)


@numba.njit(cache=True)
def control_points(data, rows, h, cp):  # pragma: no cover - compiled
    """The 64 Bezier control points of a cell's polynomial (convex hull of its image).

    A cubic Hermite segment with end values ``p0, p1`` and end derivatives ``m0, m1``
    (per unit of ``t``) has Bezier points ``p0, p0 + m0/3, p1 - m1/3, p1``; the tensor
    product gives ``P[a, b, c] = f + s_a (h/3) f_u + ... + s_a s_b s_c (h/3)^3 f_uvw`` at
    the corner nearest to ``(a, b, c) / 3``, with ``s = 0, +1, -1, 0`` for 0..3.
    """
    k3 = h / 3.0
    for c in range(4):
        for b in range(4):
            for a in range(4):
                r = rows[(a >= 2) + 2 * (b >= 2) + 4 * (c >= 2)]
                sa = k3 * (1.0 if a == 1 else (-1.0 if a == 2 else 0.0))
                sb = k3 * (1.0 if b == 1 else (-1.0 if b == 2 else 0.0))
                sc = k3 * (1.0 if c == 1 else (-1.0 if c == 2 else 0.0))
                n = a + 4 * b + 16 * c
                for i in range(3):
                    cp[n, i] = (
                        data[r, 0, i]
                        + sa * data[r, 1, i]
                        + sb * data[r, 2, i]
                        + sc * data[r, 3, i]
                        + sa * sb * data[r, 4, i]
                        + sa * sc * data[r, 5, i]
                        + sb * sc * data[r, 6, i]
                        + sa * sb * sc * data[r, 7, i]
                    )


@numba.njit(parallel=True, cache=True)
def leaf_summaries(data, rows, size, centre_f, centre_ginv, rho):  # pragma: no cover
    """Per leaf: value and inverse u-Jacobian at the centre, and the nonlinearity ``rho``.

    ``rho`` bounds ``|G_c^-1 (f(u) - f_c) - (u - u_c)|_inf`` over the cell: the control
    points of that tricubic minus those of the linear function ``u - u_c`` (at the cell's
    thirds) bound it. A point whose linear pre-image estimate is farther than ``rho`` from
    the cell has no pre-image in it.
    """
    for n in numba.prange(rows.shape[0]):
        h = float(size[n])
        g = np.empty((3, 3))
        f = np.empty(3)
        cell_eval(data, rows[n], h, 0.5, 0.5, 0.5, f, g, True)
        # NaN where g is singular, filled in a loop (np.full compiles a function of its own)
        gi = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                gi[i, j] = np.nan
        inverse3(g, gi)
        for i in range(3):
            centre_f[n, i] = f[i]
            for j in range(3):
                centre_ginv[n, i, j] = gi[i, j]
        cp = np.empty((64, 3))
        control_points(data, rows[n], h, cp)
        worst = net_nonlinearity(cp, f, gi, h)
        rho[n] = worst if np.isfinite(worst) else np.inf


@numba.njit(cache=True)
def net_nonlinearity(cp, f, gi, h):  # pragma: no cover - compiled
    """Bound of ``|G_c^-1 (f(u) - f_c) - (u - u_c)|_inf`` over a cell from its Bezier net.

    ``cp`` (64, 3): the cell's control points; ``f``, ``gi``: value and inverse Jacobian
    at its centre; ``h``: its size. The net of that tricubic is ``cp`` mapped the same
    way minus the net of the linear ``u - u_c`` (points at the cell's thirds).
    """
    worst = 0.0
    for q in range(64):
        lin = ((q % 4) / 3.0 - 0.5, ((q // 4) % 4) / 3.0 - 0.5, (q // 16) / 3.0 - 0.5)
        for i in range(3):
            d = -lin[i] * h
            for j in range(3):
                d += gi[i, j] * (cp[q, j] - f[j])
            worst = max(worst, abs(d))
    return worst


@numba.njit(cache=True)
def _owned_range(o, h, end, lo, hi):  # pragma: no cover - compiled
    """Voxels ``[a, b]`` (inclusive) of one axis owned by a leaf, within ``[lo, hi]``.

    A leaf owns ``[o, o + h)``; the lattice's far end belongs to the last leaf.
    """
    a = max(o, lo)
    b = o + h - 1
    if o + h == end:
        b = o + h
    return a, min(b, hi)


@numba.njit(cache=True)
def _owned_box(leaves, q, origin, size, end, box):  # pragma: no cover - compiled
    """Leaf ``n = leaves[q]``, its size as a float and the voxels of ``box`` it owns.

    Returns ``(n, h, ia, ib, ja, jb, ka, kb)``, the voxel ranges inclusive.
    """
    n = leaves[q]
    h = size[n]
    ia, ib = _owned_range(origin[n, 0], h, end[0], box[0], box[1])
    ja, jb = _owned_range(origin[n, 1], h, end[1], box[2], box[3])
    ka, kb = _owned_range(origin[n, 2], h, end[2], box[4], box[5])
    return n, float(h), ia, ib, ja, jb, ka, kb


@numba.njit(cache=True)
def leaf_owning(x0, x1, x2, origin, size, root_start, root_count, n_root, root):  # pragma: no cover
    """The leaf owning the point ``(x0, x1, x2)`` (voxel indices), or -1 (a pruned cell).

    Leaves own half-open boxes ``[o, o + h)``, closed at the lattice's far end; a point
    beyond the lattice is clamped onto it. ``root_start``, ``root_count``: each root
    cell's leaves; ``n_root``: root cells per axis; ``root``: their size.
    """
    x = (x0, x1, x2)
    c = np.empty(3)
    r = 0
    scale = 1
    for a in range(3):
        top = n_root[a] * root
        c[a] = min(max(x[a], 0.0), float(top))
        r += min(int(math.floor(c[a] / root)), n_root[a] - 1) * scale
        scale *= n_root[a]
    for n in range(root_start[r], root_start[r] + root_count[r]):
        inside = True
        for a in range(3):
            lo = origin[n, a]
            hi = lo + size[n]
            if c[a] < lo or c[a] > hi or (c[a] == hi and hi != n_root[a] * root):
                inside = False
                break
        if inside:
            return n
    return -1


@numba.njit(parallel=True, cache=True)
def leaf_voxels(data, rows, origin, size, leaves, end, box, mask, out, workers):  # pragma: no cover
    """Interpolated positions of the inside voxels of a box, leaf by leaf.

    ``box = (i0, i1, j0, j1, k0, k1)`` (inclusive voxel ranges); ``out`` is the box's
    (P, 3) positions, i fastest. Positions are evaluated separably: per voxel row the
    polynomial is reduced to 4 cubic terms in u, then each voxel costs 12 products.
    Leaves of different sizes cost different times: ``workers``
    (:func:`~vhm_viz.core.work_items.worker_count`) claim them a few at a time.
    """
    counter = np.zeros(1, dtype=np.int64)
    n_leaves = leaves.shape[0]
    for _ in numba.prange(workers):
        weights = np.empty((2, 4))  # the v and w weights of a voxel row
        qrow = np.empty((2, 2, 3))
        while True:
            first = claim(counter, _LEAVES_PER_CLAIM)
            if first >= n_leaves:
                break
            for q in range(first, min(first + _LEAVES_PER_CLAIM, n_leaves)):
                _leaf_voxels_of(data, rows, origin, size, leaves, q, end, box, mask, out,
                                weights, qrow)  # fmt: skip


@numba.njit(cache=True)
def _leaf_voxels_of(data, rows, origin, size, leaves, q, end, box, mask, out, weights,
                    qrow):  # pragma: no cover - compiled  # fmt: skip
    """The voxels of leaf ``leaves[q]`` for :func:`leaf_voxels` (``weights``, ``qrow``: scratch)."""
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    n, hf, ia, ib, ja, jb, ka, kb = _owned_box(leaves, q, origin, size, end, box)
    wv, ww = weights[0], weights[1]
    r = rows[n]
    for k in range(ka, kb + 1):
        ww[0], ww[1], ww[2], ww[3], _, _, _, _ = _weights((k - origin[n, 2]) / hf, hf)
        for j in range(ja, jb + 1):
            base = ((k - box[4]) * ny + (j - box[2])) * nx - box[0]
            wv[0], wv[1], wv[2], wv[3], _, _, _, _ = _weights((j - origin[n, 1]) / hf, hf)
            # reduce to 4 terms in u: qrow[a, ku] = sum over (b, c, kv, kw)
            qrow[:] = 0.0
            for c in range(2):
                for b in range(2):
                    for kw in range(2):
                        for kv in range(2):
                            s = wv[2 * b + kv] * ww[2 * c + kw]
                            for a in range(2):
                                node = r[a + 2 * b + 4 * c]
                                for ku in range(2):
                                    t = _term(ku, kv, kw)
                                    for i in range(3):
                                        qrow[a, ku, i] += s * data[node, t, i]
            for i_ in range(ia, ib + 1):
                if not mask[k, j, i_]:
                    continue
                a0, a1, a2, a3, _, _, _, _ = _weights((i_ - origin[n, 0]) / hf, hf)
                for i in range(3):
                    out[base + i_, i] = (
                        a0 * qrow[0, 0, i]
                        + a1 * qrow[0, 1, i]
                        + a2 * qrow[1, 0, i]
                        + a3 * qrow[1, 1, i]
                    )


@numba.njit(parallel=True, cache=True)
def leaf_jacobians(data, rows, origin, size, leaves, end, box, mask, to_index, out, workers):
    """World Jacobians ``df/du @ to_index`` of the inside voxels of a box, leaf by leaf.

    As :func:`leaf_voxels`, with ``out`` the box's (P, 3, 3) Jacobians (``to_index`` =
    du/dx): a kernel of its own, so that a command that only warps never compiles it.
    """
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    counter = np.zeros(1, dtype=np.int64)
    n_leaves = leaves.shape[0]
    for _ in numba.prange(workers):
        f = np.empty(3)
        g = np.empty((3, 3))
        while True:
            first = claim(counter, _LEAVES_PER_CLAIM)
            if first >= n_leaves:
                break
            for q in range(first, min(first + _LEAVES_PER_CLAIM, n_leaves)):
                n, hf, ia, ib, ja, jb, ka, kb = _owned_box(leaves, q, origin, size, end, box)
                r = rows[n]
                for k in range(ka, kb + 1):
                    for j in range(ja, jb + 1):
                        base = ((k - box[4]) * ny + (j - box[2])) * nx - box[0]
                        for i_ in range(ia, ib + 1):
                            if not mask[k, j, i_]:
                                continue
                            cell_eval(
                                data, r, hf, (i_ - origin[n, 0]) / hf, (j - origin[n, 1]) / hf,
                                (k - origin[n, 2]) / hf, f, g, True,
                            )  # fmt: skip
                            for a in range(3):
                                for b in range(3):
                                    out[base + i_, a, b] = (
                                        g[a, 0] * to_index[0, b]
                                        + g[a, 1] * to_index[1, b]
                                        + g[a, 2] * to_index[2, b]
                                    )


@numba.njit(parallel=True, cache=True)
def eval_points(data, rows, origin, size, leaf, u, f, g):  # pragma: no cover - compiled
    """Value ``f`` (P, 3) and u-gradient ``g`` (P, 3, 3) at points ``u`` of leaves ``leaf``."""
    for p in numba.prange(u.shape[0]):
        n = leaf[p]
        h = float(size[n])
        fp = np.empty(3)
        gp = np.empty((3, 3))
        cell_eval(
            data, rows[n], h, (u[p, 0] - origin[n, 0]) / h, (u[p, 1] - origin[n, 1]) / h,
            (u[p, 2] - origin[n, 2]) / h, fp, gp, True,
        )  # fmt: skip
        for i in range(3):
            f[p, i] = fp[i]
            for j in range(3):
                g[p, i, j] = gp[i, j]
