"""A lattice cell's polynomial and the pull-back's per-voxel steps, as plain functions.

The arithmetic that each output voxel of a resample needs, written once and compiled for
each target: :mod:`vhm_viz.core.lattice.hermite` and :mod:`vhm_viz.core.lattice.pullback`
compile it with ``numba.njit`` for the CPU, :mod:`vhm_viz.core.lattice.cuda_pullback` with
``numba.cuda.jit(device=True)`` for an NVIDIA GPU (as :mod:`vhm_viz.core.face_formulas`
is shared by the map's kernels). The functions are free of ``numba``; those that call
another are made by a factory that is given the target's compiled callee
(:func:`cell_evaluator`, :func:`newton_solver`), since a compiled function can only call
compiled ones. Larger and smaller values are picked with conditional expressions, not
``max`` and ``min``, which numba's CUDA target does not compile for two scalars; they
select as numba's ``max`` and ``min`` do (``b if b > a else a``), so that the CPU's
results do not change.

* :func:`hermite_weights` and :func:`cell_evaluator`: the tricubic Hermite polynomial of
  a cell (:mod:`~vhm_viz.core.lattice.hermite` describes its node data);
* :func:`inverse3`: a 3x3 inverse by the adjugate;
* :func:`linear_estimate`, :func:`known_inside`, :func:`newton_solver`,
  :func:`inside_around` and :func:`preimage_keeper`: one (voxel, leaf) pair of the
  pull-back (:func:`~vhm_viz.core.lattice.pullback.pull_back_rows` documents
  what they decide).
"""

from __future__ import annotations

import math

from vhm_viz.core.image import BORDER

__all__ = [
    "FLAG_BLOCK",
    "MARGIN",
    "NEWTON_ITERATIONS",
    "NEWTON_STEP",
    "cell_evaluator",
    "hermite_weights",
    "inside_around",
    "inverse3",
    "known_inside",
    "linear_estimate",
    "newton_solver",
    "preimage_keeper",
]

#: Newton on a cell's polynomial: converged when the step is below this (voxels; the step
#: is applied, and convergence is quadratic, so the pre-image is then good to ~1e-6 voxel,
#: far below the tolerance; a smaller step costs a further evaluation for most voxels) ...
NEWTON_STEP = 1e-3
#: ... within this many iterations.
NEWTON_ITERATIONS = 12
#: Edge of the blocks in which the inside and surface flags around the leaves the cage
#: crosses are kept for the pull-back
#: (:func:`~vhm_viz.core.lattice.pullback.cut_blocks`): 8^3 lattice points, 512 bytes.
FLAG_BLOCK = 8
#: How far (voxels) outside its cell a pre-image may lie: cells of different sizes meet
#: with mismatches of the order of the tolerance, which would otherwise leave gaps.
MARGIN = 0.25


def hermite_weights(t, h):
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


def cell_evaluator(weights):
    """``cell_eval`` of a target, calling its compiled :func:`hermite_weights` ``weights``."""

    def cell_eval(data, rows, h, tu, tv, tw, f, grad, want_grad):
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
        u0, u1, u2, u3, du0, du1, du2, du3 = weights(tu, h)
        v0, v1, v2, v3, dv0, dv1, dv2, dv3 = weights(tv, h)
        w0, w1, w2, w3, dw0, dw1, dw2, dw3 = weights(tw, h)
        # separably: the 8 corners' terms reduced along w (corners c = 0, 1), then along v
        # (b = 0, 1), then along u (a = 0, 1); about half the products of a sum over every
        # corner and term
        for i in range(3):
            fi = 0.0
            gu = 0.0
            gv = 0.0
            gw = 0.0
            for a in range(2):
                s0 = 0.0  # reduced along v and w: the u-value (s0) and u-derivative (s1)
                s1 = 0.0  # terms, their v-derivatives (sv0, sv1) and w-derivatives (sw0, sw1)
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

    return cell_eval


def inverse3(g, out):
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


def linear_estimate(centre_f, centre_ginv, origin, n, h, lim, y, ul):
    """Linear pre-image estimate ``ul`` of world point ``y`` from leaf ``n``'s centre.

    ``ul = u_c + G_c^-1 (y - f_c)`` (input voxel indices). Returns True when the estimate
    lies farther than ``lim`` from the centre along an axis (or is not finite): no
    pre-image in the leaf then.
    """
    far = False
    for a in range(3):
        d = 0.0
        for b in range(3):
            d += centre_ginv[n, a, b] * (y[b] - centre_f[n, b])
        ul[a] = origin[n, a] + 0.5 * h + d
        if not abs(d) <= lim:  # also catches NaN
            far = True
    return far


def known_inside(state, quality, u_out, v, ul, rho_n, origin, n, h, margin_n):
    """Whether voxel ``v``'s known pre-image makes leaf ``n`` (estimate ``ul``) moot.

    True when the voxel already has a pre-image inside the cage and inside its own leaf,
    and every pre-image in this leaf (within ``rho_n`` of ``ul`` and within the leaf's
    margin ``margin_n`` of its cell, of size ``h`` at ``origin[n]``) would lie within a
    voxel of it, so that it could neither mark a fold nor replace it.
    """
    if not (state[v] & 3 == 1 and quality[v] == 0.0):
        return False
    for a in range(3):
        near_lo = ul[a] - rho_n
        cell_lo = origin[n, a] - margin_n
        near_lo = cell_lo if cell_lo > near_lo else near_lo
        near_hi = ul[a] + rho_n
        cell_hi = origin[n, a] + h + margin_n
        near_hi = cell_hi if cell_hi < near_hi else near_hi
        if not (near_lo > u_out[v, a] - 1.0 and near_hi < u_out[v, a] + 1.0):
            return False
    return True


def newton_solver(cell_eval, inverse3):
    """``newton_on_cell`` of a target, calling its compiled ``cell_eval`` and ``inverse3``."""

    def newton_on_cell(data, corners, h, ox, oy, oz, y, u, f, g, gi):
        """Newton's method on a cell's polynomial for ``f(u) = y``, from ``u`` (in place).

        Parameters
        ----------
        data : (Q, 8, 3) float64
        corners : (8,) int
            The cell's data rows.
        h : float
            Cell size (voxels).
        ox, oy, oz : float
            The cell's lowest corner (voxel indices).
        y : (3,) float64
            The target (world).
        u : (3,) float64
            Start, then the last iterate (input voxel indices).
        f, g, gi : (3,), (3, 3), (3, 3) scratch
            The last value, u-Jacobian and its inverse.

        Returns
        -------
        bool
            Converged: a step below :data:`NEWTON_STEP` within :data:`NEWTON_ITERATIONS`;
            False when the Jacobian is singular or a step exceeds ``2 h`` (diverging).
        """
        for _ in range(NEWTON_ITERATIONS):
            cell_eval(data, corners, h, (u[0] - ox) / h, (u[1] - oy) / h, (u[2] - oz) / h,
                      f, g, True)  # fmt: skip
            if not inverse3(g, gi):
                return False
            big = 0.0
            for a in range(3):
                d = 0.0
                for b in range(3):
                    d += gi[a, b] * (y[b] - f[b])
                u[a] += d
                big = abs(d) if abs(d) > big else big
            if not big < 2.0 * h:  # diverging (or NaN)
                return False
            if big < NEWTON_STEP:
                return True
        return False

    return newton_on_cell


def inside_around(block_of, pool, dims, u):
    """Whether ``u`` is inside the cage, from the grid cube around it.

    8 (inside) or 0 (outside) when the cage does not cross the cube's edges and the
    corners agree; -1 (ask the winding number) when the surface runs next to the cube, or
    the cube's flags were not kept (:func:`~vhm_viz.core.lattice.pullback.cut_blocks`).
    """
    i0 = int(math.floor(u[0]))
    j0 = int(math.floor(u[1]))
    k0 = int(math.floor(u[2]))
    i0 = dims[0] - 2 if dims[0] - 2 < i0 else (i0 if i0 > 0 else 0)
    j0 = dims[1] - 2 if dims[1] - 2 < j0 else (j0 if j0 > 0 else 0)
    k0 = dims[2] - 2 if dims[2] - 2 < k0 else (k0 if k0 > 0 else 0)
    count = 0
    for c in range(2):
        for b in range(2):
            for a in range(2):
                k, j, i = k0 + c, j0 + b, i0 + a
                blk = block_of[k // FLAG_BLOCK, j // FLAG_BLOCK, i // FLAG_BLOCK]
                if blk < 0:
                    return -1
                flags = pool[blk, k % FLAG_BLOCK, j % FLAG_BLOCK, i % FLAG_BLOCK]
                if flags & 2:
                    return -1
                if flags & 1:
                    count += 1
    return count if count == 0 or count == 8 else -1


def preimage_keeper(inside_around):
    """``keep_preimage`` of a target, calling its compiled :func:`inside_around`."""

    def keep_preimage(state, fold, quality, u_out, v, u, n, origin, size, cut, mark, last,
                      block_of, pool, dims):  # fmt: skip
        """Keep pre-image ``u`` of voxel ``v``, found in leaf ``n``, if it counts.

        It counts within :data:`MARGIN` of its leaf (beyond the volume's boundary the
        half-voxel border takes over from the margin) and within the volume's half-voxel
        border; in a leaf the cage crosses (``cut``), where the grid cube around it is
        not outside (:func:`inside_around`): ``s`` 1 inside, 2 to be confirmed.

        It is merged with what the voxel has: the first pre-image is kept (a confirmed
        one replaces one to be confirmed, with ``mark`` added to its ``state``:
        :data:`~vhm_viz.core.lattice.pullback.NEAR_EDGE` or 0); another of the same kind
        more than one voxel away marks a fold; a nearer one (the same point from a
        neighbouring leaf) replaces it when it lies deeper inside its leaf (``quality``:
        the distance outside its leaf).
        """
        q = 0.0
        h = size[n]
        for a in range(3):
            below = origin[n, a] - u[a] - (BORDER if origin[n, a] <= 0 else 0.0)
            above = u[a] - origin[n, a] - h - (BORDER if origin[n, a] + h >= last[a] else 0.0)
            q = below if below > q else q
            q = above if above > q else q
            if u[a] < -BORDER or u[a] > last[a] + BORDER:
                return
        if q > MARGIN:
            return
        s = 1
        if cut[n]:
            around = inside_around(block_of, pool, dims, u)
            if around == 0:
                return
            if around < 0:
                s = 2
        known = state[v] & 3
        if known == 0 or (known == 2 and s == 1):
            state[v] = s | mark
            quality[v] = q
            for a in range(3):
                u_out[v, a] = u[a]
        elif known == s:
            apart = 0.0
            for a in range(3):
                d = abs(u[a] - u_out[v, a])
                apart = d if d > apart else apart
            if apart > 1.0:
                fold[v] = 1
            elif q < quality[v]:
                state[v] = s | mark
                quality[v] = q
                for a in range(3):
                    u_out[v, a] = u[a]

    return keep_preimage
