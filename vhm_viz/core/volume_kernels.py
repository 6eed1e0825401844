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
from vhm_viz.core.image import ImageGeometry, sample
from vhm_viz.core.metrics import jacobian_measures

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


def sample_into(out, volume, u, rows, kind: str, fill_value: float) -> None:
    """Sample ``volume`` at ``u[rows]`` into ``out`` (its dtype), fill elsewhere."""
    dtype = volume.dtype
    comps = volume.shape[3]
    integer = np.issubdtype(dtype, np.integer)
    fill = fill_value
    lo = hi = 0.0
    if integer:
        info = np.iinfo(dtype)
        fill = np.clip(np.rint(fill_value), info.min, info.max)
        lo, hi = float(info.min), float(info.max)
    flat = out.reshape(len(out), comps)
    flat[...] = np.asarray(fill).astype(dtype)
    if not rows.size:
        return
    # one buffer row per slab voxel (the kernels write the rows asked for in place); the
    # rows are stored with no temporaries (a slab is a million voxels)
    buf = np.empty((len(u), comps), dtype=dtype if kind == "nearest" else np.float64)
    sample(volume, u, rows, kind, buf)
    _store_rows(buf, rows, integer and kind != "nearest", lo, hi, flat)


@numba.njit(cache=True)
def _store_rows(buf, rows, round_clip, lo, hi, out):  # pragma: no cover - compiled
    """``out[rows] = buf[rows]``, rounded and clipped to ``[lo, hi]`` if ``round_clip``."""
    if round_clip:
        for r in rows:
            for c in range(buf.shape[1]):
                out[r, c] = min(max(np.rint(buf[r, c]), lo), hi)
    else:  # (no float in between: 64-bit labels are copied exactly)
        for r in rows:
            for c in range(buf.shape[1]):
                out[r, c] = buf[r, c]


@numba.njit(parallel=True, cache=True)
def _measures(jac, det, cond, angle, hard):  # pragma: no cover - compiled
    """Det J, s_max / s_min and the polar rotation's angle of 3x3 matrices, fast.

    The singular values come from the eigenvalues of ``J^T J`` in closed form
    (trigonometric solution of the characteristic cubic, Smith 1961); the rotation from
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
        # eigenvalues of the symmetric S = J^T J
        s00 = a0 * a0 + a3 * a3 + a6 * a6
        s11 = a1 * a1 + a4 * a4 + a7 * a7
        s22 = a2 * a2 + a5 * a5 + a8 * a8
        s01 = a0 * a1 + a3 * a4 + a6 * a7
        s02 = a0 * a2 + a3 * a5 + a6 * a8
        s12 = a1 * a2 + a4 * a5 + a7 * a8
        q = (s00 + s11 + s22) / 3.0
        off = s01 * s01 + s02 * s02 + s12 * s12
        r = math.sqrt(((s00 - q) ** 2 + (s11 - q) ** 2 + (s22 - q) ** 2 + 2.0 * off) / 6.0)
        if r <= 1e-300:
            lmax = lmin = q
        else:
            b00, b11, b22 = (s00 - q) / r, (s11 - q) / r, (s22 - q) / r
            b01, b02, b12 = s01 / r, s02 / r, s12 / r
            half = 0.5 * (
                b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                + b02 * (b01 * b12 - b11 * b02)
            )  # fmt: skip
            phi = math.acos(min(1.0, max(-1.0, half))) / 3.0
            lmax = q + 2.0 * r * math.cos(phi)
            lmin = q + 2.0 * r * math.cos(phi + 2.0 * math.pi / 3.0)
        if not lmin > 1e-12 * lmax:  # nearly singular: the cubic loses s_min
            hard[p] = True
            continue
        cond[p] = math.sqrt(lmax / lmin)
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
