"""The pull-back's Newton solves on an NVIDIA GPU (numba-cuda, float64).

The GPU counterpart of :func:`~vhm_viz.core.lattice.pullback.pull_back_rows`: the CPU
lists, per output row, the leaves whose image boxes cross it (the same candidate lists);
the GPU runs one thread per output voxel, which takes its row's candidate leaves in order
and, for each, the linear estimate, Newton's method on the leaf's polynomial and the
merge with what the voxel has, with the arithmetic of
:mod:`~vhm_viz.core.lattice.cell_formulas` compiled as device functions. Each Newton
solve starts from the linear estimate (the CPU starts most of a row's solves from the
previous voxel's pre-image): both converge to a step below
:data:`~vhm_viz.core.lattice.cell_formulas.NEWTON_STEP`, so the pre-images agree to about
1e-6 voxel, far below the tolerance.

The lattice's arrays go to the GPU once per lattice (kept while the lattice lives); the
voxels of a slab go in batches that fit the GPU's free memory. Importing this module
imports ``numba.cuda``: :meth:`~vhm_viz.core.lattice.HermiteLattice.pull_back` imports it
only for ``device="cuda"``.
"""

from __future__ import annotations

import weakref

import numba
import numpy as np
from numba import cuda

from vhm_viz.core.lattice import cell_formulas as cf
from vhm_viz.core.lattice.pullback import NEAR_EDGE

__all__ = ["THREADS_PER_BLOCK", "VOXEL_DEVICE_BYTES", "pull_back_on_gpu"]

#: Threads per block of the pull-back kernel (one output voxel each).
THREADS_PER_BLOCK = 128
#: GPU bytes per voxel of a batch: pre-image, state, fold, quality.
VOXEL_DEVICE_BYTES = 3 * 8 + 1 + 1 + 8
# Share of the GPU's free memory (after the lattice's arrays) that a batch may take.
_FREE_SHARE = 0.5

_weights = cuda.jit(device=True)(cf.hermite_weights)
_cell_eval = cuda.jit(device=True)(cf.cell_evaluator(_weights))
_inverse3 = cuda.jit(device=True)(cf.inverse3)
_newton_on_cell = cuda.jit(device=True)(cf.newton_solver(_cell_eval, _inverse3))
_linear_estimate = cuda.jit(device=True)(cf.linear_estimate)
_known_inside = cuda.jit(device=True)(cf.known_inside)
_inside_around = cuda.jit(device=True)(cf.inside_around)
_keep_preimage = cuda.jit(device=True)(cf.preimage_keeper(_inside_around))


@cuda.jit
def _pull_back_kernel(
    data, rows, origin, size, cut, near_edge, centre_f, centre_ginv, rho, margin, block_of,
    pool, dims, last, origin_out, to_world_out, box, first_row, row_start, row_leaf, row_i0,
    row_i1, u_out, state, fold, quality,
):  # pragma: no cover - compiled for the GPU  # fmt: skip
    """Pre-images of a batch of output voxels: rows ``first_row ..`` of the box, i fastest.

    Arguments as :func:`~vhm_viz.core.lattice.pullback.pull_back_rows`'s; the candidate
    lists (``row_start`` ...) are the whole box's, the outputs the batch's.
    """
    t = cuda.grid(1)
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    if t >= u_out.shape[0]:
        return
    r = first_row + t // nx
    i_ = box[0] + t % nx
    k = box[4] + r // ny
    j = box[2] + r % ny
    y = cuda.local.array(3, numba.float64)
    ul = cuda.local.array(3, numba.float64)
    u = cuda.local.array(3, numba.float64)
    f = cuda.local.array(3, numba.float64)
    g = cuda.local.array((3, 3), numba.float64)
    gi = cuda.local.array((3, 3), numba.float64)
    state[t] = 0
    fold[t] = 0
    quality[t] = 0.0
    for a in range(3):
        u_out[t, a] = 0.0
        y[a] = origin_out[a] + to_world_out[a, 0] * i_ + (
            to_world_out[a, 1] * j + to_world_out[a, 2] * k
        )
    for c in range(row_start[r], row_start[r + 1]):
        if i_ < row_i0[c] or i_ > row_i1[c]:
            continue
        n = row_leaf[c]
        h = float(size[n])
        lim = 0.5 * h + rho[n] + margin[n]
        if _linear_estimate(centre_f, centre_ginv, origin, n, h, lim, y, ul):
            continue
        if _known_inside(state, quality, u_out, t, ul, rho[n], origin, n, h, margin[n]):
            continue
        for a in range(3):
            u[a] = ul[a]
        if not _newton_on_cell(data, rows[n], h, origin[n, 0], origin[n, 1], origin[n, 2],
                               y, u, f, g, gi):  # fmt: skip
            continue
        _keep_preimage(state, fold, quality, u_out, t, u, n, origin, size, cut,
                       NEAR_EDGE if near_edge[n] else 0, last, block_of, pool, dims)


# The lattices' arrays on the GPU, kept while each lattice lives.
_ON_DEVICE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _lattice_on_device(lattice, near_edge) -> tuple:
    """The lattice's arrays that the kernel reads, on the GPU (sent once per lattice)."""
    held = _ON_DEVICE.get(lattice)
    if held is not None and held[0] is near_edge:
        return held[1]
    host = (
        lattice.data, lattice.leaf_rows, lattice.leaf_origin, lattice.leaf_size,
        lattice.leaf_cut, near_edge, lattice.centre_f, lattice.centre_ginv, lattice.rho,
        lattice.margins(), *lattice.cut_flags(), lattice.last,
    )  # fmt: skip
    arrays = tuple(cuda.to_device(np.ascontiguousarray(a)) for a in host)
    _ON_DEVICE[lattice] = (near_edge, arrays)
    return arrays


def _batch_voxels(voxels: int, plane: int) -> int:
    """Voxels per batch: whole output rows (``plane`` voxels each) fitting the free memory."""
    try:
        free = float(cuda.current_context().get_memory_info()[0])
    except (AttributeError, NotImplementedError):  # pragma: no cover - no memory query
        free = float("inf")
    fit = min(float(voxels), _FREE_SHARE * free / VOXEL_DEVICE_BYTES)
    return max(int(fit // plane), 1) * plane


def pull_back_on_gpu(lattice, geometry, box, row_start, row_leaf, row_i0, row_i1, near_edge,
                     u, state, fold, quality) -> None:  # fmt: skip
    """Pre-images of the voxels of an output box, on the GPU.

    As :meth:`~vhm_viz.core.lattice.HermiteLattice.pull_back` with ``device="cuda"``,
    given the box's candidate lists (:func:`~vhm_viz.core.lattice.pullback.candidate_rows`).

    Parameters
    ----------
    lattice : HermiteLattice
    geometry : ImageGeometry
        The output grid.
    box : (6,) int64
        Inclusive output voxel ranges.
    row_start, row_leaf, row_i0, row_i1 : int64 arrays
        The box's candidate lists (CSR over its rows).
    near_edge : (L,) bool
    u : (P, 3) float64 out
    state, fold : (P,) uint8 out
    quality : (P,) float64 out
    """
    lat = _lattice_on_device(lattice, near_edge)
    nx = int(box[1] - box[0] + 1)
    n_rows = len(row_start) - 1
    csr = tuple(cuda.to_device(np.ascontiguousarray(a))
                for a in (row_start, row_leaf, row_i0, row_i1))  # fmt: skip
    out_arrays = tuple(cuda.to_device(np.ascontiguousarray(a)) for a in (
        geometry.origin, geometry.index_to_world, box))  # fmt: skip
    batch = _batch_voxels(n_rows * nx, nx)
    for lo in range(0, n_rows * nx, batch):
        m = min(batch, n_rows * nx - lo)
        d_u = cuda.device_array((m, 3), dtype=np.float64)
        d_state = cuda.device_array(m, dtype=np.uint8)
        d_fold = cuda.device_array(m, dtype=np.uint8)
        d_quality = cuda.device_array(m, dtype=np.float64)
        blocks = (m + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
        _pull_back_kernel[blocks, THREADS_PER_BLOCK](
            *lat, *out_arrays, lo // nx, *csr, d_u, d_state, d_fold, d_quality
        )
        d_u.copy_to_host(u[lo : lo + m])
        d_state.copy_to_host(state[lo : lo + m])
        d_fold.copy_to_host(fold[lo : lo + m])
        d_quality.copy_to_host(quality[lo : lo + m])
        del d_u, d_state, d_fold, d_quality
