"""Per-voxel work of the volume engine: boxes and slabs, outside voxels, sampling, measures.

The compiled kernels that :class:`~vhm_viz.core.volume.VolumeDeformation` runs on each
slab of voxels, and the box and slab bookkeeping around them. Boxes are inclusive voxel
ranges ``(i0, i1, j0, j1, k0, k1)``; a box's voxels are in VTK order (i fastest).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.basis import DEFAULT_MEMORY_BUDGET
from vhm_viz.core.cell_kernels import condition_number_3x3
from vhm_viz.core.image import (
    INTERPOLATIONS,
    ImageGeometry,
    sample_cubic,
    sample_linear,
    sample_nearest,
)
from vhm_viz.core.metrics import jacobian_measures
from vhm_viz.core.row_threads import run_rows

__all__ = ["fast_jacobian_measures"]


def box_of(geometry: ImageGeometry, box) -> np.ndarray:
    """A voxel box ``(i0, i1, j0, j1, k0, k1)`` (default: the whole grid), validated."""
    dims = geometry.dimensions
    if box is None:
        return np.array([0, dims[0] - 1, 0, dims[1] - 1, 0, dims[2] - 1], dtype=np.int64)
    b = np.asarray(box, dtype=np.int64).reshape(6)
    if (b[0::2] < 0).any() or (b[1::2] >= np.asarray(dims)).any() or (b[1::2] < b[0::2]).any():
        raise ValueError(f"box {b.tolist()} is not inside the grid of dimensions {dims}")
    return b


def check_out_arrays(arrays: dict, valid, foldover, shapes: dict, n: int) -> None:
    """Refuse ``out`` arrays of :meth:`VolumeDeformation.resample` that do not fit."""
    want = dict(shapes)
    want["valid"] = ((n,), np.dtype(np.uint8))
    want["foldover"] = ((n,), np.dtype(np.uint8))
    got = dict(arrays)
    got["valid"], got["foldover"] = valid, foldover
    if set(got) != set(want):
        raise ValueError(f"out holds the arrays {sorted(got)}, not {sorted(want)}")
    for name, (shape, dtype) in want.items():
        a = got[name]
        if a.shape != shape or a.dtype != dtype or not a.flags.c_contiguous:
            raise ValueError(
                f"out array {name!r} is {a.dtype}{list(a.shape)}; the box needs a "
                f"contiguous {np.dtype(dtype)}{list(shape)}"
            )


def slabs_of(box: np.ndarray, bytes_per_voxel: int, memory_budget: int | None):
    """Split a box into slabs of whole k-planes whose working arrays fit the budget."""
    budget = DEFAULT_MEMORY_BUDGET if memory_budget is None else int(memory_budget)
    plane = int((box[1] - box[0] + 1) * (box[3] - box[2] + 1))
    planes = max(1, budget // max(plane * bytes_per_voxel, 1))
    for k0 in range(int(box[4]), int(box[5]) + 1, planes):
        slab = box.copy()
        slab[4], slab[5] = k0, min(int(box[5]), k0 + planes - 1)
        yield slab


def box_ijk(box) -> np.ndarray:
    """(P, 3) voxel indices of a box, i fastest."""
    k, j, i = np.meshgrid(
        np.arange(box[4], box[5] + 1),
        np.arange(box[2], box[3] + 1),
        np.arange(box[0], box[1] + 1),
        indexing="ij",
    )
    return np.column_stack([i.ravel(), j.ravel(), k.ravel()])


def scaled_progress(progress, lo: float, hi: float):
    """``progress`` with its fractions mapped onto ``lo..hi`` (None stays None)."""
    if progress is None:
        return None

    def cb(fraction, message=""):
        progress(lo + (hi - lo) * float(fraction), message)

    return cb


@numba.njit(parallel=True, cache=True)
def fill_outside(origin, to_world, box, inside, nan, out):  # pragma: no cover - compiled
    """Outside voxels of a box: their own position, or NaN."""
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    for kk in numba.prange(box[5] - box[4] + 1):
        k = box[4] + kk
        for jj in range(ny):
            j = box[2] + jj
            for ii in range(nx):
                if inside[kk, jj, ii]:
                    continue
                p = (kk * ny + jj) * nx + ii
                i = box[0] + ii
                for a in range(3):
                    out[p, a] = (
                        np.nan
                        if nan
                        else origin[a] + to_world[a, 0] * i + to_world[a, 1] * j
                        + to_world[a, 2] * k
                    )  # fmt: skip


def finish_slab(state, fold, u, valid, foldover, samples, kind: str, fill_value: float,
                row_width: int, counts, shift=None) -> tuple[int, int, int]:  # fmt: skip
    """A pulled-back slab's masks and sampled arrays, in one pass over its voxels.

    ``valid = state > 0`` and ``foldover = fold``; each input volume is sampled at the
    pre-images where ``state > 0`` (:func:`~vhm_viz.core.image.sample_linear` and its
    kin) and takes the fill value elsewhere. One compiled pass per array, row by row on
    the row threads (:func:`~vhm_viz.core.row_threads.run_rows`): no slab-wide list of
    the voxels with a pre-image, no buffer of their values, no separate fill, nothing
    left serial.

    Parameters
    ----------
    state, fold : (P,) uint8
        The slab's (after :func:`~vhm_viz.core.preimages.settle_preimages`, which
        confirms and polishes them, and :func:`~vhm_viz.core.preimages.pass_through`).
    u : (P, 3) float64
        Pre-images (input voxel indices) where ``state > 0``.
    valid, foldover : (P,) uint8 out
    samples : list of (out, volume)
        ``out`` (P,) or (P, c) of the volume's dtype, written; ``volume`` (nz, ny, nx, c).
    kind : {"linear", "nearest", "cubic"}
    fill_value : float
        Value where there is no pre-image, held exactly by every array's dtype
        (:func:`~vhm_viz.core.image.check_fill_value`).
    row_width : int
        Voxels per output row (``P`` is a multiple): the unit of the threads' chunks.
    counts : (R, 3) int64 scratch, ``R >= P / row_width``
    shift : (3,) array_like, optional
        The input voxel where the volumes start (they hold a box of the input grid);
        default the first.

    Returns
    -------
    valid, identity, foldover : int
        How many voxels have a pre-image, are left in place (``state`` 3), are folded.
    """
    code = INTERPOLATIONS.index(kind)
    shift = np.zeros(3) if shift is None else np.asarray(shift, dtype=np.float64).reshape(3)
    n_rows = len(state) // row_width
    if not samples:  # the masks alone: a volume without components (no voxel takes a fill)
        samples = [(np.empty((len(state), 0), dtype=np.uint8), np.empty((1, 1, 1, 0), np.uint8))]
        fill_value = 0
    for a, (out, volume) in enumerate(samples):
        dtype = volume.dtype
        integer = np.issubdtype(dtype, np.integer)
        lo, hi = 0.0, 0.0
        if integer:
            info = np.iinfo(dtype)
            lo, hi = float(info.min), float(info.max)
        fill = np.asarray(fill_value, dtype=dtype).reshape(1)
        run_rows(_finisher(code), n_rows, row_width, state, fold, u, shift, volume,
                 integer and kind != "nearest", lo, hi, fill, a == 0, valid, foldover, counts,
                 out.reshape(len(out), -1), grain=64)  # fmt: skip
    total = counts[:n_rows].sum(axis=0)
    return int(total[0]), int(total[1]), int(total[2])


def _finisher(kind: int):
    """The compiled :func:`_finish_rows` of one interpolation (compiled when first used)."""
    if kind not in _FINISHERS:
        _FINISHERS[kind] = numba.njit(cache=True, nogil=True)(_finish_rows(kind))
    return _FINISHERS[kind]


_FINISHERS: dict = {}


def _finish_rows(kind: int):
    """:func:`finish_slab`'s kernel for one array, with the interpolation ``kind`` fixed.

    A serial kernel over a range of output rows, run on the row threads: a parallel loop
    would compile many times slower for the same work, and a kernel that chose the kind
    as it runs would compile all three where a command uses one (``kind`` is a constant
    here: the branches of the other kinds are dropped before they are compiled). Each
    row is done in passes without a branch per voxel (a row's states alternate too
    often): the masks, the list of its voxels with a pre-image, the fill, then the
    sampling of the listed voxels.
    """

    def finish_rows(start, stop, width, state, fold, u, shift, vol, round_clip, lo, hi, fill, masks,
                    valid, foldover, counts, out):  # pragma: no cover - compiled  # fmt: skip
        """Rows ``start <= r < stop`` of a slab (its masks too if ``masks``)."""
        weights = np.empty((3, 4))
        found = np.empty(width + 1, dtype=np.int64)
        nc = out.shape[1]
        flat = out.reshape(-1)
        value = fill[0]
        for r in range(start, stop):
            first = r * width
            if masks:
                with_preimage = 0
                identity = 0
                folded = 0
                for p in range(first, first + width):
                    s = state[p]
                    valid[p] = s != 0
                    foldover[p] = fold[p]
                    with_preimage += s != 0
                    identity += s == 3
                    folded += fold[p]
                counts[r, 0] = with_preimage
                counts[r, 1] = identity
                counts[r, 2] = folded
            count = 0
            for p in range(first, first + width):
                found[count] = p
                count += state[p] != 0
            for q in range(first * nc, (first + width) * nc):
                flat[q] = value
            if kind == 0:
                for t in range(count):
                    sample_linear(vol, u, found[t], shift, weights, round_clip, lo, hi, out)
            elif kind == 1:
                for t in range(count):
                    sample_nearest(vol, u, found[t], shift, weights, round_clip, lo, hi, out)
            else:
                for t in range(count):
                    sample_cubic(vol, u, found[t], shift, weights, round_clip, lo, hi, out)

    return finish_rows


@numba.njit(parallel=True, cache=True)
def _measures(jac, det, cond, angle, hard):  # pragma: no cover - compiled
    """Det J, s_max / s_min and the polar rotation's angle of 3x3 matrices, fast.

    The condition number from :func:`~vhm_viz.core.cell_kernels.condition_number_3x3`
    (closed form where it keeps the digits); the rotation from
    Higham's scaled Newton iteration ``X <- (g X + X^-T / g) / 2`` (Higham 1986), a few
    3x3 inverses. Matrices with ``det J <= 0`` or that do not converge are flagged in
    ``hard`` (the caller takes the SVD's values there). NaN matrices give NaN.
    """
    for p in numba.prange(jac.shape[0]):
        a0, a1, a2 = jac[p, 0, 0], jac[p, 0, 1], jac[p, 0, 2]
        a3, a4, a5 = jac[p, 1, 0], jac[p, 1, 1], jac[p, 1, 2]
        a6, a7, a8 = jac[p, 2, 0], jac[p, 2, 1], jac[p, 2, 2]
        d = a0 * (a4 * a8 - a5 * a7) - a1 * (a3 * a8 - a5 * a6) + a2 * (a3 * a7 - a4 * a6)
        det[p] = d
        if not d > 0.0:
            hard[p] = np.isfinite(d)
            cond[p] = np.nan
            angle[p] = np.nan
            continue
        c = condition_number_3x3(a0, a1, a2, a3, a4, a5, a6, a7, a8)
        if not c < 1e6:  # nearly singular: the polar iteration below may not converge
            hard[p] = True
            continue
        cond[p] = c
        # polar rotation: X <- (g X + X^-T / g) / 2, X^-T = cofactor(X) / det(X)
        x0, x1, x2, x3, x4, x5, x6, x7, x8 = a0, a1, a2, a3, a4, a5, a6, a7, a8
        dx = d
        ok = False
        for _ in range(30):
            c0, c1, c2 = x4 * x8 - x5 * x7, x5 * x6 - x3 * x8, x3 * x7 - x4 * x6
            c3, c4, c5 = x2 * x7 - x1 * x8, x0 * x8 - x2 * x6, x1 * x6 - x0 * x7
            c6, c7, c8 = x1 * x5 - x2 * x4, x2 * x3 - x0 * x5, x0 * x4 - x1 * x3
            nx = x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3 + x4 * x4 + x5 * x5
            nx += x6 * x6 + x7 * x7 + x8 * x8
            nc = c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3 + c4 * c4 + c5 * c5
            nc += c6 * c6 + c7 * c7 + c8 * c8
            g = math.sqrt(math.sqrt(nc / (dx * dx * nx)))
            h = 0.5 / (g * dx)
            y0, y1, y2 = 0.5 * g * x0 + h * c0, 0.5 * g * x1 + h * c1, 0.5 * g * x2 + h * c2
            y3, y4, y5 = 0.5 * g * x3 + h * c3, 0.5 * g * x4 + h * c4, 0.5 * g * x5 + h * c5
            y6, y7, y8 = 0.5 * g * x6 + h * c6, 0.5 * g * x7 + h * c7, 0.5 * g * x8 + h * c8
            change = (y0 - x0) ** 2 + (y4 - x4) ** 2 + (y8 - x8) ** 2 + (y1 - x1) ** 2
            change += (y2 - x2) ** 2 + (y3 - x3) ** 2 + (y5 - x5) ** 2 + (y6 - x6) ** 2
            change += (y7 - x7) ** 2
            x0, x1, x2, x3, x4, x5, x6, x7, x8 = y0, y1, y2, y3, y4, y5, y6, y7, y8
            dx = x0 * (x4 * x8 - x5 * x7) - x1 * (x3 * x8 - x5 * x6) + x2 * (x3 * x7 - x4 * x6)
            if change < 1e-24:
                ok = True
                break
        if not ok:
            hard[p] = True
            continue
        angle[p] = math.acos(min(1.0, max(-1.0, 0.5 * (x0 + x4 + x8 - 1.0))))


def fast_jacobian_measures(jac, out=None) -> dict:
    """Determinant, condition number and rotation angle of 3x3 matrices, fast.

    Closed-form singular values and Higham's polar iteration (:func:`_measures`) for
    the matrices with a positive determinant that converge; the others (mirrored,
    nearly singular) take the SVD's values of
    :func:`~vhm_viz.core.metrics.jacobian_measures`. NaN matrices give NaN.

    Parameters
    ----------
    jac : (P, 3, 3) float64 array_like
    out : (det, cond, angle), optional
        Three (P,) float64 arrays to write into (say, views of a larger box's rows).

    Returns
    -------
    dict
        ``determinant``, ``condition_number``, ``rotation_angle`` (radians), each (P,)
        float64 (``out``'s arrays where given).
    """
    jac = np.ascontiguousarray(jac, dtype=np.float64).reshape(-1, 3, 3)
    det, cond, angle = (np.empty(len(jac)) for _ in range(3)) if out is None else out
    hard = np.zeros(len(jac), dtype=np.bool_)
    _measures(jac, det, cond, angle, hard)
    if hard.any():  # folded or degenerate: the SVD's definitions
        m = jacobian_measures(jac[hard])
        for name, dst in (("determinant", det), ("condition_number", cond),
                          ("rotation_angle", angle)):  # fmt: skip
            dst[hard] = m[name]
    return {"determinant": det, "condition_number": cond, "rotation_angle": angle}
