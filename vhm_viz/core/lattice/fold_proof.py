"""Voxel cells of a warped image that a lattice's polynomials prove not inverted.

A warped image's fold check measures the corner Jacobians of every voxel cell: the
trilinear cell whose corners are the deformed voxels. Inside a leaf the deformed voxels
are values of the leaf's polynomial ``P`` (voxel index coordinates ``u``), so a corner
Jacobian's column ``a`` is ``P(x + e_a) - P(x)``, the mean of ``dP/du_a`` along a cell
edge. With ``G`` the mean of the leaf's corner Jacobians (exact node data) and
``beta_a`` a bound of ``|G^-1 dP/du_a - e_a|`` over the leaf, the columns of
``G^-1 C`` are ``e_a + d_a`` with ``|d_a| <= beta_a``; where ``sum beta_a^2 < 1`` the
matrix ``I + D`` is non-singular along ``I + t D`` (``|D|_2 <= |D|_F < 1``), so
``det C`` has the sign of ``det G``. ``dP/du_a`` is a polynomial whose Bezier control
points are ``3 / h`` times the differences of the leaf's net along ``a`` (``h``: the
leaf's size), which contain its values: their largest distance bounds ``beta_a``.
A leaf whose ``det G`` has the sign of the rest voxel's and whose bound is at most
:data:`PROOF_BOUND` is *proven*: none of the cells between its own voxels is inverted.
A leaf whose bound fails is split in its eight octants (de Casteljau halves of its net,
the same polynomial): each octant is proven with its own reference ``G`` (the mean of
its derivative net; any non-singular reference serves the argument) and its own bound,
which is tighter on the smaller box. Every cell between a leaf's voxels lies in one
octant's closed box (the octants' sizes are whole voxels).
The bound's margin (``|D|_2 <= 0.9``, so every ratio is at least ``0.1^3`` of the
reference's) is far above the rounding of the warped points and of the determinants.

A leaf owns the voxels ``[o, o + h)``; the cells with a corner at ``o + h`` also have
corners owned by the neighbouring leaves. Those agree with ``P`` when each such neighbour
has the same size, shares its corner nodes' data rows with the leaf (a tricubic Hermite
polynomial on a face, an edge or a corner depends on those nodes' data alone) and has no
voxel outside the cage (a voxel outside is not the polynomial's value). Of a proven
leaf's ``h^3`` cells, the ``(h - 1)^3`` between its own voxels are proven, and each cell
with far corners where every neighbour owning one of them agrees.

Voxels in pruned cells (no voxel inside the cage) belong to no leaf: their cells are
measured.
"""

from __future__ import annotations

import numba
import numpy as np

from vhm_viz.core.lattice.hermite import control_points, leaf_owning

#: Largest ``sum beta_a^2`` (see the module documentation) of a proven leaf.
PROOF_BOUND = 0.81


@numba.njit(cache=True, error_model="numpy")
def _spread(data, r, h, sign, cp, g, gi):  # pragma: no cover - compiled
    """``sum_a beta_a^2`` of the leaf with corner rows ``r`` and size ``h``, or inf.

    inf where the reference Jacobian ``G`` does not have the sign ``sign`` of the rest
    voxel's determinant (or is singular, or the data is not finite). ``cp``: (64, 3), the
    leaf's net on return; ``g``, ``gi``: scratch (3, 3).
    """
    control_points(data, r, h, cp)
    g[:] = 0.0
    for c in range(8):
        for i in range(3):
            for a in range(3):
                g[i, a] += 0.125 * data[r[c], 1 + a, i]
    return _spread_against(cp, 3.0 / h, g, sign, gi)


@numba.njit(cache=True, error_model="numpy")
def _spread_against(cp, k, g, sign, gi):  # pragma: no cover - compiled
    """:func:`_bound` of a net against the reference ``g``, or inf.

    inf unless ``det g`` has the sign ``sign``. ``gi``: ``g``'s inverse on return.
    """
    det = (
        g[0, 0] * (g[1, 1] * g[2, 2] - g[1, 2] * g[2, 1])
        - g[0, 1] * (g[1, 0] * g[2, 2] - g[1, 2] * g[2, 0])
        + g[0, 2] * (g[1, 0] * g[2, 1] - g[1, 1] * g[2, 0])
    )
    if not det * sign > 0.0:
        return np.inf
    for i in range(3):  # the inverse from the cofactors
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for a in range(3):
            a1, a2 = (a + 1) % 3, (a + 2) % 3
            gi[a, i] = (g[i1, a1] * g[i2, a2] - g[i1, a2] * g[i2, a1]) / det
    return _bound(cp, k, gi)


@numba.njit(cache=True, error_model="numpy")
def _bound(cp, k, gi):  # pragma: no cover - compiled
    """``sum_a beta_a^2`` of a net against a reference ``G`` (``gi``: ``G^-1``).

    ``beta_a``: the largest ``|G^-1 d - e_a|`` over the points ``d`` of the derivative
    net along ``a`` (``k`` times the net's differences). inf when a point is not finite.
    """
    total = 0.0
    for a in range(3):
        stride = 1 if a == 0 else (4 if a == 1 else 16)
        worst = 0.0
        for m in range(64):
            if (m // stride) % 4 == 3:
                continue
            d0 = k * (cp[m + stride, 0] - cp[m, 0])
            d1 = k * (cp[m + stride, 1] - cp[m, 1])
            d2 = k * (cp[m + stride, 2] - cp[m, 2])
            s = 0.0
            for i in range(3):
                e = gi[i, 0] * d0 + gi[i, 1] * d1 + gi[i, 2] * d2 - (1.0 if i == a else 0.0)
                s += e * e
            if not s <= worst:  # NaN too: no proof
                worst = s if s == s else np.inf
        total += worst
    return total


@numba.njit(cache=True)
def _half(src, dst, axis, upper):  # pragma: no cover - compiled
    """``dst``: the half (``upper``: the far one) of the Bezier net ``src`` along ``axis``.

    De Casteljau at 1/2 along ``axis`` for each of the 16 rows of a (64, 3) net.
    """
    stride = 1 if axis == 0 else (4 if axis == 1 else 16)
    for m in range(64):
        if (m // stride) % 4 != 0:
            continue
        for i in range(3):
            p0 = src[m, i]
            p1 = src[m + stride, i]
            p2 = src[m + 2 * stride, i]
            p3 = src[m + 3 * stride, i]
            mid = 0.125 * (p0 + 3.0 * p1 + 3.0 * p2 + p3)
            if upper:
                dst[m, i] = mid
                dst[m + stride, i] = 0.25 * (p1 + 2.0 * p2 + p3)
                dst[m + 2 * stride, i] = 0.5 * (p2 + p3)
                dst[m + 3 * stride, i] = p3
            else:
                dst[m, i] = p0
                dst[m + stride, i] = 0.5 * (p0 + p1)
                dst[m + 2 * stride, i] = 0.25 * (p0 + 2.0 * p1 + p2)
                dst[m + 3 * stride, i] = mid


@numba.njit(cache=True, error_model="numpy")
def _net_spread(cp, h, sign, g, gi):  # pragma: no cover - compiled
    """``sum_a beta_a^2`` of a net of size ``h`` against the mean of its derivative net.

    inf where that reference's determinant does not have the sign ``sign`` (or the net
    is not finite). ``g``, ``gi``: scratch (3, 3).
    """
    k = 3.0 / h
    g[:] = 0.0
    for a in range(3):
        stride = 1 if a == 0 else (4 if a == 1 else 16)
        for m in range(64):
            if (m // stride) % 4 == 3:
                continue
            for i in range(3):
                g[i, a] += (k / 48.0) * (cp[m + stride, i] - cp[m, i])
    return _spread_against(cp, k, g, sign, gi)


@numba.njit(cache=True, error_model="numpy")
def _octants_proven(cp, h, sign, halves, g, gi, proven):  # pragma: no cover - compiled
    """Which octants of the net ``cp`` (size ``h``) their own bounds prove; how many.

    ``proven[c]`` for octant ``c`` (bit ``a``: the far half along axis ``a``).
    ``halves``: scratch (3, 64, 3).
    """
    count = 0
    for c in range(8):
        _half(cp, halves[0], 0, (c & 1) != 0)
        _half(halves[0], halves[1], 1, (c & 2) != 0)
        _half(halves[1], halves[2], 2, (c & 4) != 0)
        proven[c] = _net_spread(halves[2], 0.5 * h, sign, g, gi) <= PROOF_BOUND
        count += proven[c]
    return count


@numba.njit(cache=True)
def _neighbours_agree(n, origin, size, rows, cut, cells, lookup, agree):  # pragma: no cover
    """Which leaves owning the corners ``o + h`` of leaf ``n``'s cells agree with it.

    ``agree[off]`` for ``off = 1 .. 7`` (bit ``a`` set: ``o_a + h`` on axis ``a``): the
    leaf owning voxel ``o + off h`` has the leaf's size, is not cut and shares its data
    rows at their common corners (or owns no corner of the image's cells there).
    ``lookup``: ``(root_start, root_count, n_root, root)`` of
    :func:`~vhm_viz.core.lattice.hermite.leaf_owning`.
    """
    h = size[n]
    x = np.empty(3, dtype=np.int64)
    for off in range(1, 8):
        agree[off] = True
        needed = True
        for a in range(3):
            x[a] = origin[n, a] + ((off >> a) & 1) * h
            if (off >> a) & 1 and origin[n, a] + h - 1 > cells[a] - 1:
                needed = False  # no cell of the image has a corner there
        if not needed:
            continue
        m = leaf_owning(float(x[0]), float(x[1]), float(x[2]), origin, size, *lookup)
        if m == n:
            continue  # the lattice's far end: the leaf owns its far voxels
        if m < 0 or size[m] != h or cut[m]:
            agree[off] = False
            continue
        for c in range(8):  # corners of n on m's closed box: the same data rows
            cm = 0
            on = True
            for a in range(3):
                d = origin[n, a] + ((c >> a) & 1) * h - origin[m, a]
                if d == h:
                    cm += 1 << a
                elif d != 0:
                    on = False
            if on and rows[m, cm] != rows[n, c]:
                agree[off] = False


@numba.njit(cache=True)
def _add_box(boxes, count, lo, hi, first, last):  # pragma: no cover - compiled
    """Append the cell box ``[lo, hi]`` clipped to ``[first, last]``, relative to ``first``.

    Returns ``(boxes, count)``: a larger array when ``boxes`` is full.
    """
    for a in range(3):
        if max(lo[a], first[a]) > min(hi[a], last[a]):
            return boxes, count
    if count == boxes.shape[0]:
        grown = np.empty((2 * count + 16, 6), dtype=np.int64)
        grown[:count] = boxes
        boxes = grown
    for a in range(3):
        boxes[count, 2 * a] = max(lo[a], first[a]) - first[a]
        boxes[count, 2 * a + 1] = min(hi[a], last[a]) - first[a]
    return boxes, count + 1


@numba.njit(cache=True)
def _unowned_runs(r0, r1, origin, size, lo, root, free, boxes, count, first,
                  last):  # pragma: no cover - compiled  # fmt: skip
    """Add the cells of a root cell (lowest voxel ``lo``) whose voxels no leaf owns.

    ``r0 .. r1``: the root's leaves; ``free``: scratch ``(root, root, root)`` bool. The
    cells come in runs along i. Returns ``(boxes, count)``.
    """
    for k in range(root):  # loops, not slices: less code to load from the cache
        for j in range(root):
            for i in range(root):
                free[k, j, i] = True
    for n in range(r0, r1):
        h = size[n]
        for k in range(origin[n, 2] - lo[2], origin[n, 2] - lo[2] + h):
            for j in range(origin[n, 1] - lo[1], origin[n, 1] - lo[1] + h):
                for i in range(origin[n, 0] - lo[0], origin[n, 0] - lo[0] + h):
                    free[k, j, i] = False
    a = np.empty(3, dtype=np.int64)
    b = np.empty(3, dtype=np.int64)
    for k in range(root):
        for j in range(root):
            i = 0
            while i < root:
                if not free[k, j, i]:
                    i += 1
                    continue
                start = i
                while i < root and free[k, j, i]:
                    i += 1
                a[0], a[1], a[2] = lo[0] + start, lo[1] + j, lo[2] + k
                b[0], b[1], b[2] = lo[0] + i - 1, a[1], a[2]
                boxes, count = _add_box(boxes, count, a, b, first, last)
    return boxes, count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def unproven_boxes(start, stop, data, rows, origin, size, cut, sign, root_start, root_count,
                   n_root, root, cells, first, last):  # pragma: no cover - compiled  # fmt: skip
    """Boxes of the voxel cells that are not proven, in root cells ``start <= r < stop``.

    Cells in ``[first, last]`` (inclusive, per axis) only. ``sign``: that of the rest
    voxel's determinant; ``cells``: the image's cells per axis. A leaf not cut with a bound
    (``sum beta_a^2``) of at most :data:`PROOF_BOUND` proves its ``(h - 1)^3`` inner
    cells, and all its ``h^3`` cells where its neighbours agree with it (module
    documentation). Per root cell: each leaf's unproven cells (all of them, or those of
    its far faces, edges and corner where a neighbour does not agree), and the cells of
    voxels that no leaf owns (pruned cells).
    Returns ``(K, 6)`` int64 inclusive boxes relative to ``first``, disjoint.
    """
    leaves = 0 if stop <= start else root_start[stop - 1] + root_count[stop - 1] - root_start[start]
    boxes = np.empty((stop - start + 3 * leaves, 6), dtype=np.int64)
    lookup = (root_start, root_count, n_root, root)
    cp, g, gi = np.empty((64, 3)), np.empty((3, 3)), np.empty((3, 3))
    halves = np.empty((3, 64, 3))
    octant = np.empty(8, dtype=np.bool_)
    lo, hi = np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64)
    free = np.empty((root, root, root), dtype=np.bool_)
    agree = np.empty(8, dtype=np.bool_)
    count = 0
    for r in range(start, stop):
        corner = (r % n_root[0], (r // n_root[0]) % n_root[1], r // (n_root[0] * n_root[1]))
        clipped = 1
        for a in range(3):
            lo[a] = corner[a] * root
            hi[a] = lo[a] + root - 1
            clipped *= max(0, min(hi[a], last[a]) - max(lo[a], first[a]) + 1)
        if clipped == 0:
            continue
        owned = 0
        for n in range(root_start[r], root_start[r] + root_count[r]):
            vol = 1
            for a in range(3):
                o = origin[n, a]
                vol *= max(0, min(o + size[n] - 1, last[a]) - max(o, first[a]) + 1)
            owned += vol
        r0, r1 = root_start[r], root_start[r] + root_count[r]
        if owned != clipped:  # pruned cells: their voxels are no leaf's
            boxes, count = _unowned_runs(r0, r1, origin, size, lo, root, free, boxes,
                                         count, first, last)  # fmt: skip
        for n in range(r0, r1):
            h = size[n]
            for a in range(3):
                lo[a] = origin[n, a]
                hi[a] = lo[a] + h - 1
            if cut[n]:
                boxes, count = _add_box(boxes, count, lo, hi, first, last)
                continue
            octant[:] = True
            if not _spread(data, rows[n], float(h), sign, cp, g, gi) <= PROOF_BOUND:
                # (cp: the leaf's net) an octant proves its own cells
                if h < 2 or _octants_proven(cp, float(h), sign, halves, g, gi, octant) == 0:
                    boxes, count = _add_box(boxes, count, lo, hi, first, last)
                    continue
                for c in range(8):
                    if not octant[c]:
                        _octant_box(origin[n], h, c, lo, hi)
                        boxes, count = _add_box(boxes, count, lo, hi, first, last)
            _neighbours_agree(n, origin, size, rows, cut, cells, lookup, agree)
            # the inner (h - 1)^3 cells are proven (by the leaf or its octants); a cell at
            # o_a + h - 1 on the axes of a set S (bits) is where the leaves at every offset
            # within S agree. Its part in each octant on that side not proven by itself
            # (whose cells are measured already)
            for far in range(1, 8):
                proven = True
                for off in range(1, 8):
                    if off & ~far == 0 and not agree[off]:
                        proven = False
                if proven:
                    continue
                for c in range(8):
                    if c & far != far or not octant[c]:
                        continue
                    _octant_box(origin[n], h, c, lo, hi)
                    for a in range(3):
                        if (far >> a) & 1:
                            lo[a] = origin[n, a] + h - 1
                        else:
                            hi[a] = min(hi[a], origin[n, a] + h - 2)
                    if (lo <= hi).all():
                        boxes, count = _add_box(boxes, count, lo, hi, first, last)
    return boxes[:count]


@numba.njit(cache=True)
def _octant_box(o, h, c, lo, hi):  # pragma: no cover - compiled
    """``lo``, ``hi``: the cells of octant ``c`` of the leaf at ``o`` of size ``h``.

    The whole leaf for ``h`` 1 (no octants; then only ``c`` 7 is its box, the others
    empty). Cells with their lowest corner in the octant's voxels.
    """
    half = h // 2
    for a in range(3):
        upper = (c >> a) & 1
        if h < 2:
            lo[a], hi[a] = o[a], o[a] - 1 + upper
        else:
            lo[a] = o[a] + upper * half
            hi[a] = lo[a] + half - 1
