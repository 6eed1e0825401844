"""Pre-images on the lattice: where each leaf's image reaches, and Newton on its polynomial.

Each leaf keeps its value and inverse Jacobian at the centre and a bound ``rho`` of its
nonlinearity (:func:`~vhm_viz.core.lattice.hermite.leaf_summaries`): an output voxel
whose linear pre-image estimate misses the leaf by more than ``rho`` has no pre-image in
it; Newton's method on the leaf's polynomial finds the others. Pre-images in leaves the
cage crosses are checked against the inside and surface flags of the grid cube around
them (:func:`cut_blocks`), or the winding number where those cannot tell.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.image import inside_mask, surface_mask
from vhm_viz.core.lattice import cell_formulas
from vhm_viz.core.lattice.cell_formulas import FLAG_BLOCK
from vhm_viz.core.lattice.hermite import cell_eval, control_points, inverse3
from vhm_viz.core.work_items import claim

# Rows of an output box that a worker of the pull-back claims at a time.
_ROWS_PER_CLAIM = 4
#: Bit of a pull-back's ``state`` set when the pre-image lies in a leaf flagged
#: ``near_edge`` (:func:`pull_back_rows`): the caller looks closer at those only.
NEAR_EDGE = 4


@numba.njit(cache=True)
def _clip_net(cp, axis, t0, t1):  # pragma: no cover - compiled
    """Restrict a tricubic Bezier net to ``t0 <= t <= t1`` along one axis (de Casteljau).

    The new net's control points bound the image of the restricted cell only.
    """
    b = np.empty((4, 3))
    for line in range(16):
        # the 4 control points of this line along ``axis``
        idx = np.empty(4, dtype=np.int64)
        for q in range(4):
            if axis == 0:
                idx[q] = q + 4 * (line % 4) + 16 * (line // 4)
            elif axis == 1:
                idx[q] = (line % 4) + 4 * q + 16 * (line // 4)
            else:
                idx[q] = (line % 4) + 4 * (line // 4) + 16 * q
        for q in range(4):
            b[q] = cp[idx[q]]
        # keep [0, t1]: the left half of a split at t1
        for r in range(1, 4):
            for q in range(3, r - 1, -1):
                b[q] = (1.0 - t1) * b[q - 1] + t1 * b[q]
        # keep [t0 / t1, 1] of that: the right half of a split
        s = t0 / t1 if t1 > 0.0 else 0.0
        for r in range(1, 4):
            for q in range(0, 4 - r):
                b[q] = (1.0 - s) * b[q] + s * b[q + 1]
        for q in range(4):
            cp[idx[q]] = b[q]


@numba.njit(parallel=True, cache=True)
def output_boxes(data, rows, origin, size, lower, upper, origin_out, to_out, margin, lo, hi):
    """Per leaf: the box of output-grid indices its image can reach.

    The control points bound the image of the cell, restricted to the input region
    ``lower <= u <= upper`` (the volume: cells overhang it); ``margin[n]`` (input voxels)
    around that adds at most that times the largest corner Jacobian (output voxels per
    input voxel), a first-order bound that the rounding of the box to whole voxels covers.
    """  # noqa: D401
    for n in numba.prange(rows.shape[0]):
        h = float(size[n])
        cp = np.empty((64, 3))
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


@numba.njit(parallel=True, cache=True)
def pull_back_rows(
    data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho, margin, block_of, pool,
    dims, last, origin_out, to_world_out, box, row_start, row_leaf, row_i0, row_i1,
    u_out, state, fold, quality, workers,
):  # pragma: no cover - compiled  # fmt: skip
    """Pre-images of the output voxels of a box: Newton on the leaves' polynomials.

    For every row of the box and every leaf whose image box crosses it, each voxel ``y``
    gets a linear pre-image estimate from the leaf's centre; a leaf more than ``rho`` plus
    the margin away is skipped, otherwise Newton's method on the leaf's polynomial starts
    from that estimate (or from the previous voxel's pre-image, advanced by the inverse
    Jacobian). A converged pre-image within the margin of its leaf and within the input
    volume's half-voxel border is kept:

    * ``state`` 1 (inside the cage), or 2 when the leaf crosses the cage and the voxels
      around it disagree (the caller checks those with the winding number), plus
      :data:`NEAR_EDGE` when the pre-image's leaf is flagged in ``near_edge``;
    * a second pre-image more than one voxel from the first marks a fold (``fold`` 1); a
      nearer one (the same point, found from a neighbouring leaf) replaces the first when
      it lies deeper inside its leaf (``quality`` = distance outside the leaf).

    Every voxel of the box is written: ``u_out``, ``state``, ``fold`` and ``quality`` are
    zero where no pre-image was found. Rows cost from nothing (no candidate leaf) to many
    Newton solves: ``workers`` (:func:`~vhm_viz.core.work_items.worker_count`) claim them
    a few at a time (:mod:`~vhm_viz.core.work_items`).
    """
    n_rows = row_start.shape[0] - 1
    counter = np.zeros(1, dtype=np.int64)
    for _ in numba.prange(workers):
        vectors = np.empty((6, 3))  # y, ul, u, f, prev1, prev2 of the row's voxels
        matrices = np.empty((2, 3, 3))  # g, gi
        while True:
            first = claim(counter, _ROWS_PER_CLAIM)
            if first >= n_rows:
                break
            for r in range(first, min(first + _ROWS_PER_CLAIM, n_rows)):
                _pull_back_row(
                    r, data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho, margin,
                    block_of, pool, dims, last, origin_out, to_world_out, box, row_start,
                    row_leaf, row_i0, row_i1, u_out, state, fold, quality, vectors, matrices,
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
        if slope != 0.0:
            t0 = (-lim - d0) / slope
            t1 = (lim - d0) / slope
            lo = max(lo, min(t0, t1) - 1.0)
            hi = min(hi, max(t0, t1) + 1.0)
        elif not abs(d0) <= 2.0 * lim:
            hi = lo - 1.0
        if not lo <= hi:  # empty, or NaN
            return i0, i0 - 1
    return max(int(math.floor(lo)), i0), min(int(math.ceil(hi)), i1)


# No reference counting: the row allocates nothing, and the inlined steps would count
# every array they are given, for every (voxel, leaf) pair.
@numba.njit(cache=True, _nrt=False)
def _pull_back_row(
    r, data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho, margin, block_of,
    pool, dims, last, origin_out, to_world_out, box, row_start, row_leaf, row_i0, row_i1,
    u_out, state, fold, quality, vectors, matrices,
):  # pragma: no cover - compiled  # fmt: skip
    """Row ``r`` of :func:`pull_back_rows` (``vectors``, ``matrices``: its scratch)."""
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    k = box[4] + r // ny
    j = box[2] + r % ny
    for v in range(r * nx, (r + 1) * nx):
        state[v] = 0
        fold[v] = 0
        quality[v] = 0.0
        for a in range(3):
            u_out[v, a] = 0.0
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
        chained = 0  # consecutive converged voxels before this one
        for i_ in range(i_lo, i_hi + 1):
            for a in range(3):
                y[a] = origin_out[a] + to_world_out[a, 0] * i_ + (
                    to_world_out[a, 1] * j + to_world_out[a, 2] * k
                )
            if _linear_estimate(centre_f, centre_ginv, origin, n, h, lim, y, ul):
                chained = 0
                continue
            v = ((k - box[4]) * ny + (j - box[2])) * nx + (i_ - box[0])
            if _known_inside(state, quality, u_out, v, ul, rho[n]):
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
