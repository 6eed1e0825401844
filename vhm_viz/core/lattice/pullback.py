"""Pre-images on the lattice: where each leaf's image reaches, and Newton on its polynomial.

Each leaf keeps its value and inverse Jacobian at the centre and a bound ``rho`` of its
nonlinearity (:func:`~vhm_viz.core.lattice.hermite.leaf_summaries`): an output voxel
whose linear pre-image estimate misses the leaf by more than ``rho`` has no pre-image in
it; the same test on each of its sub-cells (:func:`subcell_tests`), whose bounds are far
tighter, skips most of the voxels next to the leaf; Newton's method on the leaf's
polynomial finds the others. Pre-images in leaves the
cage crosses are checked against the inside and surface flags of the grid cube around
them (:func:`cut_blocks`), or the winding number where those cannot tell.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.image import BORDER, inside_mask, surface_mask
from vhm_viz.core.lattice import cell_formulas
from vhm_viz.core.lattice.cell_formulas import FLAG_BLOCK
from vhm_viz.core.lattice.hermite import cell_eval, control_points, inverse3, net_nonlinearity
from vhm_viz.core.row_threads import run_rows
from vhm_viz.core.work_items import claim

# Rows of an output box that a worker of the pull-back claims at a time.
_ROWS_PER_CLAIM = 4
#: Bit of a pull-back's ``state`` set when the pre-image lies in a leaf flagged
#: ``near_edge`` (:func:`pull_back_rows`): the caller looks closer at those only.
NEAR_EDGE = 4
#: Sub-cells per axis into which :func:`subcell_tests` splits a leaf: each has its own
#: linear estimate and nonlinearity bound, far tighter than the leaf's.
SUBCELLS = 2
# How much wider (voxels) than the exact interval of a row's voxels that pass a sub-cell's
# test its range is taken: the rounding of the interval's ends.
_HAIR = 1e-6
# Numbers per sub-cell and axis ``a`` in :func:`subcell_tests`: the coefficients of
# ``d_a = c_a + p_a j + q_a k + s_a i``, then the bound on ``|d_a|``.
_TEST_WIDTH = 5


@numba.njit(cache=True)
def _clip_net(cp, axis, t0, t1):  # pragma: no cover - compiled
    """Restrict a tricubic Bezier net to ``t0 <= t <= t1`` along one axis (de Casteljau).

    The new net's control points bound the image of the restricted cell only. Written in
    scalar loops: row arithmetic (array expressions) compiles many times slower, for the
    same operations.
    """
    b = np.empty((4, 3))
    idx = np.empty(4, dtype=np.int64)
    stride = 1 if axis == 0 else (4 if axis == 1 else 16)
    s = t0 / t1 if t1 > 0.0 else 0.0
    for line in range(16):
        # the 4 control points of this line along ``axis``
        lo, hi = line % 4, line // 4
        if axis == 0:
            first = 4 * lo + 16 * hi
        elif axis == 1:
            first = lo + 16 * hi
        else:
            first = lo + 4 * hi
        for q in range(4):
            idx[q] = first + stride * q
            for a in range(3):
                b[q, a] = cp[idx[q], a]
        # keep [0, t1]: the left half of a split at t1
        for r in range(1, 4):
            for q in range(3, r - 1, -1):
                for a in range(3):
                    b[q, a] = (1.0 - t1) * b[q - 1, a] + t1 * b[q, a]
        # keep [t0 / t1, 1] of that: the right half of a split
        for r in range(1, 4):
            for q in range(0, 4 - r):
                for a in range(3):
                    b[q, a] = (1.0 - s) * b[q, a] + s * b[q + 1, a]
        for q in range(4):
            for a in range(3):
                cp[idx[q], a] = b[q, a]


def output_boxes(data, rows, origin, size, lower, upper, origin_out, to_out, margin, lo, hi):
    """Per leaf: the box of output-grid indices its image can reach.

    The control points bound the image of the cell, restricted to the input region
    ``lower <= u <= upper`` (the volume: cells overhang it); ``margin[n]`` (input voxels)
    around that adds at most that times the largest corner Jacobian (output voxels per
    input voxel), a first-order bound that the rounding of the box to whole voxels covers.
    Written into ``lo``, ``hi`` ((L, 3) float64), on the row threads.
    """  # noqa: D401
    run_rows(_output_boxes, rows.shape[0], data, rows, origin, size, lower, upper, origin_out,
             to_out, margin, lo, hi, grain=64)  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _output_boxes(start, stop, data, rows, origin, size, lower, upper, origin_out, to_out,
                  margin, lo, hi):  # pragma: no cover - compiled  # fmt: skip
    """:func:`output_boxes` of leaves ``start <= n < stop``."""
    cp = np.empty((64, 3))
    for n in range(start, stop):
        h = float(size[n])
        control_points(data, rows[n], h, cp)
        for a in range(3):
            t0 = max((lower[a] - origin[n, a]) / h, 0.0)
            t1 = min((upper[a] - origin[n, a]) / h, 1.0)
            if t0 > 0.0 or t1 < 1.0:
                _clip_net(cp, a, t0, max(t1, t0))
        for a in range(3):
            lo[n, a] = np.inf
            hi[n, a] = -np.inf
        for q in range(64):
            for a in range(3):
                v = 0.0
                for b in range(3):
                    v += to_out[a, b] * (cp[q, b] - origin_out[b])
                lo[n, a] = min(lo[n, a], v)
                hi[n, a] = max(hi[n, a], v)
        for a in range(3):
            pad = 0.0
            for corner in range(8):
                r = rows[n, corner]
                s = 0.0
                for t in range(1, 4):  # |d(out_a)/du_t| summed over t
                    d = 0.0
                    for b in range(3):
                        d += to_out[a, b] * data[r, t, b]
                    s += abs(d)
                pad = max(pad, s)
            lo[n, a] -= margin[n] * pad
            hi[n, a] += margin[n] * pad


def subcell_tests(lattice, geometry) -> np.ndarray:
    """Per leaf and sub-cell, the test that an output voxel may have a pre-image there.

    A leaf is split into ``SUBCELLS``^3 sub-cells. A pre-image ``u`` in sub-cell ``s``
    (grown by the leaf's margin) of an output voxel ``y`` has its linear estimate
    ``d = G_s^-1 (y - f_s)`` (value and inverse Jacobian at the sub-cell's centre) within
    ``rho_s`` of ``u - u_s``, ``rho_s`` bounding the sub-cell polynomial's nonlinearity
    as :func:`~vhm_viz.core.lattice.hermite.leaf_summaries` bounds the leaf's; so
    ``|d|_inf <= h_s / 2 + rho_s + margin``, and ``u_s + d`` lies within ``rho_s`` of the
    input volume grown by its half-voxel border (the pull-back keeps no pre-image
    beyond). Both bound each axis's ``d_a`` to an interval; on an output grid ``d`` is
    affine in the voxel index: the test is stored as those coefficients, shifted to the
    interval's middle, and its half-width.

    Parameters
    ----------
    lattice : HermiteLattice
    geometry : ImageGeometry
        The output grid.

    Returns
    -------
    (L, SUBCELLS**3, 3, 5) float64
        For sub-cell ``a + 2 b + 4 c`` of leaf ``n`` and axis ``x``: ``c, p, q, s, bound``:
        the voxel ``(i, j, k)`` passes where ``|c + p j + q k + s i| <= bound`` on every
        axis. A sub-cell whose Jacobian is singular gets zeros and infinite bounds (any
        voxel may be there), one out of the volume's reach a bound of -1 (none).
    """
    tests = np.empty((len(lattice.leaf_size), SUBCELLS**3, 3, _TEST_WIDTH))
    run_rows(_subcell_tests, len(tests), lattice.data, lattice.leaf_rows, lattice.leaf_origin,
             lattice.leaf_size, lattice.margins(), lattice.last.astype(np.float64),
             np.asarray(geometry.origin, dtype=np.float64),
             np.ascontiguousarray(geometry.index_to_world, dtype=np.float64), tests,
             grain=64)  # fmt: skip
    return tests


# A serial kernel over a range of leaves, run on the row threads, with scalar loops and
# no allocation per leaf: a parallel loop or slice assignments compile many times slower.
@numba.njit(cache=True, nogil=True)
def _subcell_tests(start, stop, data, rows, origin, size, margin, last, origin_out,
                   to_world_out, tests):  # pragma: no cover - compiled  # fmt: skip
    """:func:`subcell_tests` of leaves ``start <= n < stop`` into ``tests``."""
    net = np.empty((64, 3))
    cp = np.empty((64, 3))
    f = np.empty(3)
    g = np.empty((3, 3))
    gi = np.empty((3, 3))
    width = tests.shape[3]
    for n in range(start, stop):
        h = float(size[n])
        hs = h / SUBCELLS
        control_points(data, rows[n], h, net)
        for s in range(SUBCELLS**3):
            c0, c1, c2 = s % SUBCELLS, (s // SUBCELLS) % SUBCELLS, s // SUBCELLS**2
            for q in range(64):
                for a in range(3):
                    cp[q, a] = net[q, a]
            for a in range(3):  # (a loop: one specialisation of _clip_net's axis)
                corner = c0 if a == 0 else (c1 if a == 1 else c2)
                _clip_net(cp, a, corner / SUBCELLS, (corner + 1.0) / SUBCELLS)
            cell_eval(data, rows[n], h, (c0 + 0.5) / SUBCELLS, (c1 + 0.5) / SUBCELLS,
                      (c2 + 0.5) / SUBCELLS, f, g, True)  # fmt: skip
            worst = net_nonlinearity(cp, f, gi, hs) if inverse3(g, gi) else np.inf
            for a in range(3):
                for w in range(width):
                    tests[n, s, a, w] = 0.0
                if not np.isfinite(worst):
                    tests[n, s, a, width - 1] = np.inf
                    continue
                lim = 0.5 * hs + worst + margin[n]
                corner = c0 if a == 0 else (c1 if a == 1 else c2)
                centre = origin[n, a] + (corner + 0.5) * hs
                lower = max(-lim, -BORDER - centre - worst)
                upper = min(lim, last[a] + BORDER - centre + worst)
                if not lower <= upper:
                    tests[n, s, a, width - 1] = -1.0
                    continue
                c = -0.5 * (lower + upper)
                for b in range(3):
                    c += gi[a, b] * (origin_out[b] - f[b])
                tests[n, s, a, 0] = c
                for t in range(3):
                    d = 0.0
                    for b in range(3):
                        d += gi[a, b] * to_world_out[b, t]
                    # (j, k, i) order: the row's constant part first
                    tests[n, s, a, 1 + (t + 2) % 3] = d
                tests[n, s, a, width - 1] = 0.5 * (upper - lower)


@numba.njit(cache=True)
def candidate_rows(leaves, ilo, ihi, box, row_start, row_leaf, row_i0, row_i1):  # pragma: no cover
    """Rows of an output box and the leaves whose image boxes cross each (CSR).

    ``ilo, ihi`` (L, 3) int: inclusive output index boxes of the leaves; the box is
    ``(i0, i1, j0, j1, k0, k1)``. First call with ``row_leaf`` empty counts into
    ``row_start`` (length rows + 1); the second fills.
    """
    ny = box[3] - box[2] + 1
    fill = row_leaf.shape[0] > 0
    pos = row_start.copy()
    for q in range(leaves.shape[0]):
        n = leaves[q]
        a = max(ilo[n, 0], box[0])
        b = min(ihi[n, 0], box[1])
        if a > b:
            continue
        for k in range(max(ilo[n, 2], box[4]), min(ihi[n, 2], box[5]) + 1):
            for j in range(max(ilo[n, 1], box[2]), min(ihi[n, 1], box[3]) + 1):
                r = (k - box[4]) * ny + (j - box[2])
                if fill:
                    row_leaf[pos[r]] = n
                    row_i0[pos[r]] = a
                    row_i1[pos[r]] = b
                    pos[r] += 1
                else:
                    row_start[r + 1] += 1


@numba.njit(cache=True)
def _mark_cut_blocks(origin, size, cut, margin, dims, marks):  # pragma: no cover
    """Mark the blocks holding the grid cubes around the pre-images of the cut leaves.

    A pre-image lies within its leaf grown by its margin (:meth:`HermiteLattice.margins`);
    :func:`inside_around` reads the 8 corners of the grid cube around it.
    """
    lo = np.empty(3, dtype=np.int64)
    hi = np.empty(3, dtype=np.int64)
    for n in range(origin.shape[0]):
        if not cut[n]:
            continue
        for a in range(3):
            lo[a] = min(max(int(math.floor(origin[n, a] - margin[n])), 0), dims[a] - 2)
            hi[a] = min(max(int(math.floor(origin[n, a] + size[n] + margin[n])), 0), dims[a] - 2)
            hi[a] += 1
        for kb in range(lo[2] // FLAG_BLOCK, hi[2] // FLAG_BLOCK + 1):
            for jb in range(lo[1] // FLAG_BLOCK, hi[1] // FLAG_BLOCK + 1):
                for ib in range(lo[0] // FLAG_BLOCK, hi[0] // FLAG_BLOCK + 1):
                    marks[kb, jb, ib] = True


def cut_blocks(lattice, lat_geo=None, vertices=None, faces=None):
    """The inside and surface flags around the leaves the cage crosses, in blocks.

    Returns ``(block_of, pool, dims)``: ``pool`` (B, 8, 8, 8) uint8 holds the flags of
    blocks of ``FLAG_BLOCK``^3 lattice points (bit 0 inside, bit 1 next to the surface).
    ``block_of[kb, jb, ib]``: the block's row of ``pool`` (-1: not kept); ``dims``: the
    lattice's points per axis. Taken from the lattice's masks, or computed from the cage
    (``lat_geo``, ``vertices``, ``faces``) for a lattice without them (a joined one): the
    same values, a row's flags not depending on which other rows are computed.
    """
    dims = np.asarray(lattice.end + 1, dtype=np.int64)  # (nx, ny, nz)
    nb = -(-dims // FLAG_BLOCK)
    marks = np.zeros((nb[2], nb[1], nb[0]), dtype=np.bool_)
    if len(lattice.leaf_size):
        _mark_cut_blocks(lattice.leaf_origin, lattice.leaf_size, lattice.leaf_cut,
                         lattice.margins(), dims, marks)  # fmt: skip
    block_of = np.full(marks.shape, -1, dtype=np.int64)
    block_of[marks] = np.arange(int(marks.sum()))
    pool = np.zeros((int(marks.sum()), FLAG_BLOCK, FLAG_BLOCK, FLAG_BLOCK), dtype=np.uint8)
    for kb in np.nonzero(marks.any(axis=(1, 2)))[0]:
        kb_marks = marks[kb]
        jbs = np.nonzero(kb_marks.any(axis=1))[0]
        k0, k1 = kb * FLAG_BLOCK, min((kb + 1) * FLAG_BLOCK, dims[2])
        j0, j1 = jbs[0] * FLAG_BLOCK, min((jbs[-1] + 1) * FLAG_BLOCK, dims[1])
        if lattice.mask is not None:
            inside = lattice.mask[k0:k1, j0:j1]
            near = lattice.near[k0:k1, j0:j1]
        else:
            inside = inside_mask(lat_geo, vertices, faces, rows=(j0, j1, k0, k1))
            near = surface_mask(lat_geo, vertices, faces, rows=(j0, j1, k0, k1))
        flags = inside.astype(np.uint8) | (near.astype(np.uint8) << 1)
        for jb, ib in zip(*np.nonzero(kb_marks), strict=True):
            a, b = jb * FLAG_BLOCK - j0, ib * FLAG_BLOCK
            block = flags[:, a : a + FLAG_BLOCK, b : b + FLAG_BLOCK]
            pool[block_of[kb, jb, ib], : block.shape[0], : block.shape[1], : block.shape[2]] = block
    return block_of, pool, dims


# One (voxel, leaf) pair of the pull-back: the arithmetic's one home, shared with the
# GPU's kernel (vhm_viz.core.lattice.cuda_pullback), is cell_formulas. Its steps are
# inlined into the row's loop (calls into separately compiled functions would slow it);
# the cell's polynomial and the inverse are not, being compiled with fused multiply-adds.
_INLINE = dict(inline="always")
_linear_estimate = numba.njit(**_INLINE)(cell_formulas.linear_estimate)
_known_inside = numba.njit(**_INLINE)(cell_formulas.known_inside)
_newton_on_cell = numba.njit(**_INLINE)(cell_formulas.newton_solver(cell_eval, inverse3))
inside_around = numba.njit(cache=True)(cell_formulas.inside_around)
_keep_preimage = numba.njit(**_INLINE)(cell_formulas.preimage_keeper(inside_around))


def pull_back_rows(
    data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho, margin, tests, block_of,
    pool, dims, last, origin_out, to_world_out, box, row_start, row_leaf, row_i0, row_i1,
    u_out, state, fold, quality, workers,
) -> None:  # fmt: skip
    """Pre-images of the output voxels of a box: Newton on the leaves' polynomials.

    For every row of the box and every leaf whose image box crosses it, each voxel ``y``
    gets a linear pre-image estimate from the leaf's centre; a leaf more than ``rho`` plus
    the margin away is skipped, and so is one none of whose sub-cells' tests passes
    (``tests``: :func:`subcell_tests`, or empty for none); otherwise Newton's method on
    the leaf's polynomial starts from that estimate (or from the previous voxel's
    pre-image, advanced by the inverse Jacobian). A voxel whose pre-image inside another
    leaf is known is skipped where every pre-image this leaf may hold lies within a voxel
    of it (the same point). A converged pre-image within the margin of its leaf and within the input
    volume's half-voxel border is kept:

    * ``state`` 1 (inside the cage), or 2 when the leaf crosses the cage and the voxels
      around it disagree (the caller checks those with the winding number), plus
      :data:`NEAR_EDGE` when the pre-image's leaf is flagged in ``near_edge``;
    * a second pre-image more than one voxel from the first marks a fold (``fold`` 1); a
      nearer one (the same point, found from a neighbouring leaf) replaces the first when
      it lies deeper inside its leaf (``quality`` = distance outside the leaf).

    ``state`` and ``fold`` are written for every voxel of the box (zero where no
    pre-image was found), ``u_out`` and ``quality`` only where ``state > 0``: nothing
    reads them elsewhere, and zeroing them would write 32 bytes per output voxel. Rows
    cost from nothing (no candidate leaf) to many Newton solves: ``workers``
    (:func:`~vhm_viz.core.work_items.worker_count`) claim them a few at a time
    (:mod:`~vhm_viz.core.work_items`), each a serial compiled worker on the row threads
    (:func:`~vhm_viz.core.row_threads.run_rows`): numba's parallel loop would cost far
    more to compile, for the same schedule.
    """
    counter = np.zeros(1, dtype=np.int64)
    run_rows(
        _pull_back_worker, workers, counter, data, rows, origin, size, cut, near_edge, centre_f,
        centre_ginv, rho, margin, tests, block_of, pool, dims, last, origin_out, to_world_out,
        box, row_start, row_leaf, row_i0, row_i1, u_out, state, fold, quality, grain=1,
    )  # fmt: skip


@numba.njit(cache=True, nogil=True)
def _pull_back_worker(
    start, stop, counter, data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho,
    margin, tests, block_of, pool, dims, last, origin_out, to_world_out, box, row_start,
    row_leaf, row_i0, row_i1, u_out, state, fold, quality,
):  # pragma: no cover - compiled  # fmt: skip
    """Workers ``start <= w < stop`` of :func:`pull_back_rows`, one after the other."""
    n_rows = row_start.shape[0] - 1
    for _ in range(start, stop):
        vectors = np.empty((6, 3))  # y, ul, u, f, prev1, prev2 of the row's voxels
        matrices = np.empty((2, 3, 3))  # g, gi
        spans = np.empty((SUBCELLS**3, 2), dtype=np.int64)  # voxels passing sub-cell tests
        while True:
            first = claim(counter, _ROWS_PER_CLAIM)
            if first >= n_rows:
                break
            for r in range(first, min(first + _ROWS_PER_CLAIM, n_rows)):
                _pull_back_row(
                    r, data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho, margin,
                    tests, block_of, pool, dims, last, origin_out, to_world_out, box, row_start,
                    row_leaf, row_i0, row_i1, u_out, state, fold, quality, vectors, matrices,
                    spans,
                )  # fmt: skip


@numba.njit(cache=True)
def _near_span(n, lim, centre_f, centre_ginv, origin_out, to_world_out, j, k, i0,
               i1):  # pragma: no cover - compiled  # fmt: skip
    """The voxels ``i0..i1`` of output row ``(j, k)`` whose estimate may lie near leaf ``n``.

    The linear pre-image estimate's offset from the leaf's centre, ``d = G_c^-1 (y - f_c)``,
    is affine in ``i``: each axis's ``|d_a| <= lim`` is an interval of ``i``. Returned one
    voxel wider than those intervals' intersection (rounding), which the row's loop tests
    voxel by voxel all the same; ``i_lo > i_hi`` when there is none (or the estimate is
    not finite).
    """
    lo = float(i0)
    hi = float(i1)
    for a in range(3):
        d0 = 0.0
        slope = 0.0
        for b in range(3):
            yb = origin_out[b] + to_world_out[b, 1] * j + to_world_out[b, 2] * k - centre_f[n, b]
            d0 += centre_ginv[n, a, b] * yb
            slope += centre_ginv[n, a, b] * to_world_out[b, 0]
        lo, hi = _axis_span(d0, slope, lim, 2.0 * lim, 1.0, lo, hi)
        if not lo <= hi:  # empty, or NaN
            return i0, i0 - 1
    return max(int(math.floor(lo)), i0), min(int(math.ceil(hi)), i1)


@numba.njit(cache=True)
def _axis_span(d0, slope, lim, flat_lim, pad, lo, hi):  # pragma: no cover - compiled
    """``[lo, hi]`` cut to where ``|d0 + slope i| <= lim``, ``pad`` wider (rounding).

    With no slope: all of it where ``|d0| <= flat_lim``, else empty (``lo > hi``).
    """
    if slope != 0.0:
        t0 = (-lim - d0) / slope
        t1 = (lim - d0) / slope
        return max(lo, min(t0, t1) - pad), min(hi, max(t0, t1) + pad)
    if not abs(d0) <= flat_lim:
        return lo, lo - 1.0
    return lo, hi


@numba.njit(cache=True)
def _subcell_spans(test, j, k, i0, i1, spans):  # pragma: no cover - compiled
    """The voxels of output row ``(j, k)`` that pass each sub-cell test of one leaf.

    ``test``: the leaf's rows of :func:`subcell_tests`. Writes the voxel ranges of
    ``i0..i1`` that pass a sub-cell's test (a hair wider than the exact intervals, for
    rounding) into the first rows of ``spans`` and returns ``(i_lo, i_hi, count)``:
    the range they cover together and how many were written.
    """
    i_lo = i1 + 1
    i_hi = i0 - 1
    count = 0
    for s in range(test.shape[0]):
        lo = float(i0)
        hi = float(i1)
        for a in range(3):
            t = test[s, a]
            if not t[4] >= 0.0:  # out of the volume's reach
                hi = lo - 1.0
                break
            lo, hi = _axis_span(t[0] + t[1] * j + t[2] * k, t[3], t[4], t[4], _HAIR, lo, hi)
            if not lo <= hi:  # empty, or NaN
                break
        if not lo <= hi:
            continue
        a, b = max(int(math.ceil(lo)), i0), min(int(math.floor(hi)), i1)
        if a > b:
            continue
        spans[count, 0] = a
        spans[count, 1] = b
        count += 1
        i_lo = min(i_lo, a)
        i_hi = max(i_hi, b)
    return i_lo, i_hi, count


@numba.njit(cache=True)
def _in_spans(spans, count, i):  # pragma: no cover - compiled
    """Whether voxel ``i`` lies in one of the first ``count`` ranges of ``spans``."""
    for s in range(count):
        if spans[s, 0] <= i <= spans[s, 1]:
            return True
    return False


# No reference counting: the row allocates nothing, and the inlined steps would count
# every array they are given, for every (voxel, leaf) pair.
@numba.njit(cache=True, _nrt=False)
def _pull_back_row(
    r, data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho, margin, tests,
    block_of, pool, dims, last, origin_out, to_world_out, box, row_start, row_leaf, row_i0,
    row_i1, u_out, state, fold, quality, vectors, matrices, spans,
):  # pragma: no cover - compiled  # fmt: skip
    """Row ``r`` of :func:`pull_back_rows` (``vectors``, ``matrices``, ``spans``: scratch)."""
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    k = box[4] + r // ny
    j = box[2] + r % ny
    for v in range(r * nx, (r + 1) * nx):  # (u_out and quality are read where state > 0)
        state[v] = 0
        fold[v] = 0
    y, ul, u, f, prev1, prev2 = (vectors[0], vectors[1], vectors[2], vectors[3],
                                 vectors[4], vectors[5])  # fmt: skip
    g, gi = matrices[0], matrices[1]
    step = to_world_out[:, 0]
    for c in range(row_start[r], row_start[r + 1]):
        n = row_leaf[c]
        h = float(size[n])
        lim = 0.5 * h + rho[n] + margin[n]
        i_lo, i_hi = _near_span(n, lim, centre_f, centre_ginv, origin_out, to_world_out, j, k,
                                row_i0[c], row_i1[c])  # fmt: skip
        tested = tests.shape[0] > 0
        kept = 0  # voxel ranges in ``spans`` that pass a sub-cell test
        if tested and i_lo <= i_hi:
            i_lo, i_hi, kept = _subcell_spans(tests[n], j, k, i_lo, i_hi, spans)
        chained = 0  # consecutive converged voxels before this one
        for i_ in range(i_lo, i_hi + 1):
            if tested and not _in_spans(spans, kept, i_):
                chained = 0
                continue
            for a in range(3):
                y[a] = origin_out[a] + to_world_out[a, 0] * i_ + (
                    to_world_out[a, 1] * j + to_world_out[a, 2] * k
                )
            if _linear_estimate(centre_f, centre_ginv, origin, n, h, lim, y, ul):
                chained = 0
                continue
            v = ((k - box[4]) * ny + (j - box[2])) * nx + (i_ - box[0])
            if _known_inside(state, quality, u_out, v, ul, rho[n], origin, n, h, margin[n]):
                chained = 0
                continue
            if chained >= 3:
                # the pre-images of a row are smooth: quadratic extrapolation
                for a in range(3):
                    nxt = 3.0 * u[a] - 3.0 * prev1[a] + prev2[a]
                    prev2[a] = prev1[a]
                    prev1[a] = u[a]
                    u[a] = nxt
            elif chained > 0:
                # previous pre-image advanced by the inverse Jacobian (one voxel along i)
                for a in range(3):
                    d = 0.0
                    for b in range(3):
                        d += gi[a, b] * step[b]
                    prev2[a] = prev1[a]
                    prev1[a] = u[a]
                    u[a] += d
            else:
                for a in range(3):
                    u[a] = ul[a]
            ok = _newton_on_cell(data, rows[n], h, origin[n, 0], origin[n, 1], origin[n, 2],
                                 y, u, f, g, gi)  # fmt: skip
            chained = chained + 1 if ok else 0
            if not ok:
                continue
            _keep_preimage(
                state, fold, quality, u_out, v, u, n, origin, size, cut,
                NEAR_EDGE if near_edge[n] else 0, last, block_of, pool, dims,
            )  # fmt: skip
