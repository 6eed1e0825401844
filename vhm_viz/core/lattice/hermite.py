"""Tricubic Hermite cells: a cell's polynomial, its Bezier net, and its voxels (compiled).

A cell of size ``h`` (voxels) has 8 corners, each with a row of node data: the value
``f``, the first derivatives ``f_u, f_v, f_w`` in voxel index coordinates and the mixed
derivatives ``f_uv, f_uw, f_vw, f_uvw`` (:data:`N_TERMS` terms of 3 components). The
tensor product of cubic Hermite segments interpolates them; its 64 Bezier control points
contain the cell's image.
"""

from __future__ import annotations

import numba
import numpy as np

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


@numba.njit(cache=True)
def _weights(t, h):  # pragma: no cover - compiled
    """Cubic Hermite weights on ``[0, h]`` at ``t * h`` and their u-derivatives.

    Returns ``(w0, w1, w2, w3, d0, d1, d2, d3)``: the left value, left derivative (times
    ``h``, so that it multiplies ``df/du``), right value and right derivative weights,
    then their derivatives in ``u``.
    """
    t2 = t * t
    t3 = t2 * t
    return (
        2.0 * t3 - 3.0 * t2 + 1.0,
        h * (t3 - 2.0 * t2 + t),
        -2.0 * t3 + 3.0 * t2,
        h * (t3 - t2),
        (6.0 * t2 - 6.0 * t) / h,
        3.0 * t2 - 4.0 * t + 1.0,
        (-6.0 * t2 + 6.0 * t) / h,
        3.0 * t2 - 2.0 * t,
    )


@numba.njit(cache=True, fastmath={"contract"})  # fused multiply-adds
def cell_eval(data, rows, h, tu, tv, tw, f, grad, want_grad):  # pragma: no cover
    """Value (and u-gradient) of a cell's tricubic Hermite polynomial.

    Parameters
    ----------
    data : (Q, 8, 3) float64
        Node data rows.
    rows : (8,) int
        Data rows of the corners, corner ``a + 2 b + 4 c`` at offset ``(a, b, c) * h``.
    h : float
        Cell size (voxels).
    tu, tv, tw : float
        Local coordinates (0..1 inside the cell; the polynomial extrapolates outside).
    f : (3,) out
    grad : (3, 3) out
        ``grad[i, j] = d f_i / d u_j`` when ``want_grad``.
    want_grad : bool
    """
    u0, u1, u2, u3, du0, du1, du2, du3 = _weights(tu, h)
    v0, v1, v2, v3, dv0, dv1, dv2, dv3 = _weights(tv, h)
    w0, w1, w2, w3, dw0, dw1, dw2, dw3 = _weights(tw, h)
    # separably: the 8 corners' terms reduced along w (corners c = 0, 1), then along v
    # (b = 0, 1), then along u (a = 0, 1); about half the products of a sum over every
    # corner and term
    for i in range(3):
        fi = 0.0
        gu = 0.0
        gv = 0.0
        gw = 0.0
        for a in range(2):
            s0 = 0.0  # reduced along v and w: the u-value (s0) and u-derivative (s1) terms,
            s1 = 0.0  # their v-derivatives (sv0, sv1) and w-derivatives (sw0, sw1)
            sv0 = 0.0
            sv1 = 0.0
            sw0 = 0.0
            sw1 = 0.0
            for b in range(2):
                r0 = rows[a + 2 * b]
                r1 = rows[a + 2 * b + 4]
                # terms (u kind, v kind) reduced along w: f, f_u, f_v, f_uv
                p00, p10 = data[r0, 0, i], data[r1, 0, i]
                p01, p11 = data[r0, 3, i], data[r1, 3, i]
                q00, q10 = data[r0, 1, i], data[r1, 1, i]
                q01, q11 = data[r0, 5, i], data[r1, 5, i]
                m00, m10 = data[r0, 2, i], data[r1, 2, i]
                m01, m11 = data[r0, 6, i], data[r1, 6, i]
                n00, n10 = data[r0, 4, i], data[r1, 4, i]
                n01, n11 = data[r0, 7, i], data[r1, 7, i]
                e00 = w0 * p00 + w1 * p01 + w2 * p10 + w3 * p11
                e10 = w0 * q00 + w1 * q01 + w2 * q10 + w3 * q11
                e01 = w0 * m00 + w1 * m01 + w2 * m10 + w3 * m11
                e11 = w0 * n00 + w1 * n01 + w2 * n10 + w3 * n11
                y0, y1, dy0, dy1 = (v0, v1, dv0, dv1) if b == 0 else (v2, v3, dv2, dv3)
                s0 += y0 * e00 + y1 * e01
                s1 += y0 * e10 + y1 * e11
                if want_grad:
                    sv0 += dy0 * e00 + dy1 * e01
                    sv1 += dy0 * e10 + dy1 * e11
                    d00 = dw0 * p00 + dw1 * p01 + dw2 * p10 + dw3 * p11
                    d10 = dw0 * q00 + dw1 * q01 + dw2 * q10 + dw3 * q11
                    d01 = dw0 * m00 + dw1 * m01 + dw2 * m10 + dw3 * m11
                    d11 = dw0 * n00 + dw1 * n01 + dw2 * n10 + dw3 * n11
                    sw0 += y0 * d00 + y1 * d01
                    sw1 += y0 * d10 + y1 * d11
            x0, x1, dx0, dx1 = (u0, u1, du0, du1) if a == 0 else (u2, u3, du2, du3)
            fi += x0 * s0 + x1 * s1
            if want_grad:
                gu += dx0 * s0 + dx1 * s1
                gv += x0 * sv0 + x1 * sv1
                gw += x0 * sw0 + x1 * sw1
        f[i] = fi
        if want_grad:
            grad[i, 0] = gu
            grad[i, 1] = gv
            grad[i, 2] = gw


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


@numba.njit(cache=True, fastmath={"contract"})  # fused multiply-adds
def inverse3(g, out):  # pragma: no cover - compiled
    """``out = g^-1`` of a 3x3 matrix by its adjugate; False when ``g`` is singular.

    Singular: ``|det g| <= 1e-300`` or not finite; ``out`` is then left untouched.
    """
    c00 = g[1, 1] * g[2, 2] - g[1, 2] * g[2, 1]
    c01 = g[1, 2] * g[2, 0] - g[1, 0] * g[2, 2]
    c02 = g[1, 0] * g[2, 1] - g[1, 1] * g[2, 0]
    det = g[0, 0] * c00 + g[0, 1] * c01 + g[0, 2] * c02
    if not abs(det) > 1e-300:
        return False
    r = 1.0 / det
    out[0, 0] = c00 * r
    out[1, 0] = c01 * r
    out[2, 0] = c02 * r
    out[0, 1] = (g[0, 2] * g[2, 1] - g[0, 1] * g[2, 2]) * r
    out[1, 1] = (g[0, 0] * g[2, 2] - g[0, 2] * g[2, 0]) * r
    out[2, 1] = (g[0, 1] * g[2, 0] - g[0, 0] * g[2, 1]) * r
    out[0, 2] = (g[0, 1] * g[1, 2] - g[0, 2] * g[1, 1]) * r
    out[1, 2] = (g[0, 2] * g[1, 0] - g[0, 0] * g[1, 2]) * r
    out[2, 2] = (g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0]) * r
    return True


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
