"""Compiled per-cell measures of a deformation: tetrahedra and voxel hexahedra.

Two kernels, one thread per cell, no per-cell Python and no temporary ``(T, 3, 3)``
arrays:

* :func:`tetrahedron_measures` -- the deformation gradient ``F = D_def D_rest^-1`` of each
  linear tetrahedron, its determinant and (where asked) its condition number
  ``s_max / s_min`` from a one-sided Jacobi SVD (Hestenes), which keeps the singular
  values accurate relative to the largest one, like LAPACK's;
* :func:`hexahedron_corner_determinants` -- for a deformed voxel grid (a warped image),
  the determinant of the trilinear cell's Jacobian at each of its eight corners, relative
  to the rest voxel's. A trilinear cell is inverted where one of them is ``<= 0``; the
  smallest one per cell is returned. :func:`inverted_hexahedra` counts the cells as the
  same kernel goes and keeps the inverted ones alone.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.mat3 import cofactors3
from vhm_viz.core.row_threads import run_rows

__all__ = [
    "DEGENERATE_RTOL",
    "singular_values_3x3",
    "condition_number_3x3",
    "tetrahedron_measures",
    "KUHN_PATHS",
    "kuhn_corners",
    "lattice_tetrahedron_measures",
    "hexahedron_corner_determinants",
    "inverted_hexahedra",
]

#: Rest tetrahedra with ``|det D_rest|`` at most this times their longest edge cubed are
#: degenerate: their deformation gradient is undefined (NaN), never counted as inverted.
DEGENERATE_RTOL = 1e-12

#: Sweeps of the one-sided Jacobi SVD at most (it converges quadratically: 3 x 3 matrices
#: need a handful).
_JACOBI_SWEEPS = 30
#: Tetrahedra per chunk of :func:`~vhm_viz.core.row_threads.run_rows` at least.
_TETS_GRAIN = 4096


@numba.njit(cache=True)
def _rotate_columns(x0, x1, x2, y0, y1, y2):  # pragma: no cover - compiled
    """One Jacobi rotation making columns ``x`` and ``y`` orthogonal.

    Returns the rotated columns and whether they were not orthogonal already (to
    rounding).
    """
    alpha = x0 * x0 + x1 * x1 + x2 * x2
    beta = y0 * y0 + y1 * y1 + y2 * y2
    gamma = x0 * y0 + x1 * y1 + x2 * y2
    if gamma == 0.0 or abs(gamma) <= 2.220446049250313e-16 * math.sqrt(alpha * beta):
        return x0, x1, x2, y0, y1, y2, False
    zeta = (beta - alpha) / (2.0 * gamma)
    t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
    c = 1.0 / math.sqrt(1.0 + t * t)
    s = c * t
    return (
        c * x0 - s * y0, c * x1 - s * y1, c * x2 - s * y2,
        s * x0 + c * y0, s * x1 + c * y1, s * x2 + c * y2, True,
    )  # fmt: skip


#: Squared Frobenius norms within which products of a matrix's squared entries neither
#: overflow nor underflow (the Jacobi rotations' ``alpha beta``).
_SAFE_NORM2 = 1e-150, 1e150


@numba.njit(cache=True)
def _unit_scale(a00, a01, a02, a10, a11, a12, a20, a21, a22):  # pragma: no cover - compiled
    """The power of two that brings a matrix's largest entry into ``[0.5, 1)``.

    Exact to multiply by; 1 for a zero or non-finite matrix.
    """
    m = max(abs(a00), abs(a01), abs(a02), abs(a10), abs(a11), abs(a12))
    m = max(m, max(abs(a20), max(abs(a21), abs(a22))))
    if not (m > 0.0 and m < math.inf):
        return 1.0
    return math.ldexp(1.0, -math.frexp(m)[1])


@numba.njit(cache=True)
def _jacobi_rotations(a00, a01, a02, a10, a11, a12, a20, a21, a22):  # pragma: no cover
    """:func:`_jacobi_singular_values` of a matrix of a safe norm (:data:`_SAFE_NORM2`)."""
    u0, u1, u2 = a00, a10, a20
    v0, v1, v2 = a01, a11, a21
    w0, w1, w2 = a02, a12, a22
    for _ in range(_JACOBI_SWEEPS):
        u0, u1, u2, v0, v1, v2, r1 = _rotate_columns(u0, u1, u2, v0, v1, v2)
        u0, u1, u2, w0, w1, w2, r2 = _rotate_columns(u0, u1, u2, w0, w1, w2)
        v0, v1, v2, w0, w1, w2, r3 = _rotate_columns(v0, v1, v2, w0, w1, w2)
        if not (r1 or r2 or r3):
            break
    s0 = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    s1 = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    s2 = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if s0 < s1:
        s0, s1 = s1, s0
    if s1 < s2:
        s1, s2 = s2, s1
    if s0 < s1:
        s0, s1 = s1, s0
    return s0, s1, s2


@numba.njit(cache=True)
def _jacobi_singular_values(a00, a01, a02, a10, a11, a12, a20, a21, a22):  # pragma: no cover
    """Singular values of a 3 x 3 matrix by one-sided Jacobi rotations of its columns.

    Returns ``(s_max, s_mid, s_min)``; NaN for a matrix with a NaN entry. A matrix whose
    squared entries would over- or underflow turns scaled by a power of two
    (:func:`_unit_scale`).
    """
    n2 = a00 * a00 + a01 * a01 + a02 * a02 + a10 * a10 + a11 * a11 + a12 * a12
    n2 += a20 * a20 + a21 * a21 + a22 * a22
    if _SAFE_NORM2[0] < n2 < _SAFE_NORM2[1]:
        return _jacobi_rotations(a00, a01, a02, a10, a11, a12, a20, a21, a22)
    k = _unit_scale(a00, a01, a02, a10, a11, a12, a20, a21, a22)
    s0, s1, s2 = _jacobi_rotations(
        a00 * k, a01 * k, a02 * k, a10 * k, a11 * k, a12 * k, a20 * k, a21 * k, a22 * k
    )
    return s0 / k, s1 / k, s2 / k


#: Bound on the closed form's relative error in ``cond F`` below which it is taken.
_CLOSED_FORM_RTOL = 1e-13
_EPS = 2.220446049250313e-16


@numba.njit(cache=True)
def condition_number_3x3(f00, f01, f02, f10, f11, f12, f20, f21, f22):  # pragma: no cover
    """``s_max / s_min`` of a finite 3 x 3 matrix ``F`` (inf where ``s_min`` is 0).

    The eigenvalues of ``S = F^T F`` in closed form (the trigonometric solution of its
    characteristic cubic, Smith 1961) where a first-order bound on their rounding keeps
    ``cond F`` within :data:`_CLOSED_FORM_RTOL`: ``S`` is formed to ``eps |F|^2`` (a
    relative error ``eps cond^2`` in ``s_min^2``), and the angle of the solution loses
    accuracy as two eigenvalues meet (``sin 3 phi -> 0``). Elsewhere (nearly flat
    matrices, nearly double eigenvalues) the one-sided Jacobi SVD
    (:func:`_jacobi_singular_values`), accurate relative to ``s_max``.
    """
    s00 = f00 * f00 + f10 * f10 + f20 * f20
    s11 = f01 * f01 + f11 * f11 + f21 * f21
    s22 = f02 * f02 + f12 * f12 + f22 * f22
    if not _SAFE_NORM2[0] < s00 + s11 + s22 < _SAFE_NORM2[1]:  # cond F = cond kF
        k = _unit_scale(f00, f01, f02, f10, f11, f12, f20, f21, f22)
        f00, f01, f02, f10, f11, f12 = f00 * k, f01 * k, f02 * k, f10 * k, f11 * k, f12 * k
        f20, f21, f22 = f20 * k, f21 * k, f22 * k
        s00 = f00 * f00 + f10 * f10 + f20 * f20
        s11 = f01 * f01 + f11 * f11 + f21 * f21
        s22 = f02 * f02 + f12 * f12 + f22 * f22
    s01 = f00 * f01 + f10 * f11 + f20 * f21
    s02 = f00 * f02 + f10 * f12 + f20 * f22
    s12 = f01 * f02 + f11 * f12 + f21 * f22
    q = (s00 + s11 + s22) / 3.0
    a, b, c = s00 - q, s11 - q, s22 - q
    r = math.sqrt((a * a + b * b + c * c + 2.0 * (s01 * s01 + s02 * s02 + s12 * s12)) / 6.0)
    if q > 0.0:  # not F = 0
        if r <= 1e-150 * q:
            return 1.0  # S = q I to rounding: a scaled rotation or mirror
        a, b, c = a / r, b / r, c / r
        d01, d02, d12 = s01 / r, s02 / r, s12 / r
        h = 0.5 * (
            a * (b * c - d12 * d12) - d01 * (d01 * c - d12 * d02) + d02 * (d01 * d12 - b * d02)
        )
        h = min(1.0, max(-1.0, h))
        phi = math.acos(h) / 3.0
        cos_phi = math.cos(phi)
        sin_phi = math.sin(phi)
        # the largest and smallest roots: phi and phi + 2 pi / 3
        lmax = q + 2.0 * r * cos_phi
        lmin = q - r * (cos_phi + 1.7320508075688772 * sin_phi)
        sin_3phi = math.sqrt(max(0.0, 1.0 - h * h))
        sin_min = abs(0.8660254037844386 * cos_phi - 0.5 * sin_phi)
        if lmin > 0.0 and sin_3phi > 0.0:
            bound = 20.0 * _EPS * q * (sin_phi / lmax + sin_min / lmin) / sin_3phi
            bound += 4.0 * _EPS * lmax / lmin
            if bound <= _CLOSED_FORM_RTOL:
                return math.sqrt(lmax / lmin)
    s0, _, s2 = _jacobi_rotations(f00, f01, f02, f10, f11, f12, f20, f21, f22)
    return s0 / s2 if s2 > 0.0 else np.inf


@numba.njit(cache=True, nogil=True)
def _singular_values_rows(start, stop, m, out):  # pragma: no cover - compiled
    for k in range(start, stop):
        out[k, 0], out[k, 1], out[k, 2] = _jacobi_singular_values(
            m[k, 0, 0], m[k, 0, 1], m[k, 0, 2], m[k, 1, 0], m[k, 1, 1], m[k, 1, 2],
            m[k, 2, 0], m[k, 2, 1], m[k, 2, 2],
        )  # fmt: skip


def singular_values_3x3(matrices) -> np.ndarray:
    """Singular values of 3 x 3 matrices, largest first (compiled one-sided Jacobi).

    Parameters
    ----------
    matrices : (N, 3, 3) array_like

    Returns
    -------
    (N, 3) float64
        ``s_max, s_mid, s_min`` per matrix; NaN rows for matrices with a NaN entry.
    """
    m = np.ascontiguousarray(matrices, dtype=np.float64).reshape(-1, 3, 3)
    out = np.empty((len(m), 3))
    if len(m):
        run_rows(_singular_values_rows, len(m), m, out, grain=4096)
    return out


@numba.njit(cache=True, nogil=True)
def _tet_measure(x, y, i0, i1, i2, i3, rtol, want_cond):  # pragma: no cover - compiled
    """``(det F, cond F, det D_rest, state)`` of the tet of points ``i0 .. i3``.

    ``state``: 0 measured, 1 degenerate at rest, 2 a corner not finite (deformed); the
    measures are NaN unless it is 0 (``cond F`` NaN too where not ``want_cond``).
    """
    # rest edge matrix R = [x1 - x0 | x2 - x0 | x3 - x0] (columns)
    r00, r10, r20 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
    r01, r11, r21 = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
    r02, r12, r22 = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
    # cofactors of R (rows of adj(R)^T)
    k00, k01, k02, k10, k11, k12, k20, k21, k22 = cofactors3(
        r00, r01, r02, r10, r11, r12, r20, r21, r22
    )
    dr = r00 * k00 + r01 * k01 + r02 * k02
    e0 = math.sqrt(r00 * r00 + r10 * r10 + r20 * r20)
    e1 = math.sqrt(r01 * r01 + r11 * r11 + r21 * r21)
    e2 = math.sqrt(r02 * r02 + r12 * r12 + r22 * r22)
    edge = max(e0, max(e1, e2))
    if not abs(dr) > rtol * edge * edge * edge:
        return np.nan, np.nan, dr, 1
    # deformed edge matrix D
    d00, d10, d20 = y[i1, 0] - y[i0, 0], y[i1, 1] - y[i0, 1], y[i1, 2] - y[i0, 2]
    d01, d11, d21 = y[i2, 0] - y[i0, 0], y[i2, 1] - y[i0, 1], y[i2, 2] - y[i0, 2]
    d02, d12, d22 = y[i3, 0] - y[i0, 0], y[i3, 1] - y[i0, 1], y[i3, 2] - y[i0, 2]
    s = d00 + d10 + d20 + d01 + d11 + d21 + d02 + d12 + d22
    if not math.isfinite(s):
        return np.nan, np.nan, dr, 2
    # det F = det D / det R, from the deformed edges directly
    inv = 1.0 / dr
    dd = (
        d00 * (d11 * d22 - d12 * d21)
        - d01 * (d10 * d22 - d12 * d20)
        + d02 * (d10 * d21 - d11 * d20)
    )
    if not want_cond:
        return dd * inv, np.nan, dr, 0
    # F = D R^-1, R^-1 = adj(R) / det R, adj(R)[i][j] = cofactor k_ji
    f00 = (d00 * k00 + d01 * k01 + d02 * k02) * inv
    f01 = (d00 * k10 + d01 * k11 + d02 * k12) * inv
    f02 = (d00 * k20 + d01 * k21 + d02 * k22) * inv
    f10 = (d10 * k00 + d11 * k01 + d12 * k02) * inv
    f11 = (d10 * k10 + d11 * k11 + d12 * k12) * inv
    f12 = (d10 * k20 + d11 * k21 + d12 * k22) * inv
    f20 = (d20 * k00 + d21 * k01 + d22 * k02) * inv
    f21 = (d20 * k10 + d21 * k11 + d22 * k12) * inv
    f22 = (d20 * k20 + d21 * k21 + d22 * k22) * inv
    return dd * inv, condition_number_3x3(f00, f01, f02, f10, f11, f12, f20, f21, f22), dr, 0


@numba.njit(cache=True, nogil=True)
def _tet_kernel(  # pragma: no cover - compiled
    start, stop, x, y, tets, rtol, want_cond, det, cond, rest_det, state
):
    """:func:`_tet_measure` of each tet ``start <= t < stop`` into the arrays' row ``t``."""
    for t in range(start, stop):
        det[t], cond[t], rest_det[t], state[t] = _tet_measure(
            x, y, tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3], rtol, want_cond
        )


@numba.njit(cache=True)
def _add_tet(low, high, flags, det, cond, rest_det, state):  # pragma: no cover - compiled
    """A cell's ``(smallest det, largest cond, flags)`` with one more tet's measures.

    ``flags``: bit 0 a tet of the cell is stored inverted at rest, bit 1 a tet of the cell
    is degenerate at rest, bit 2 the cell has a measured tet (``state`` of
    :func:`_tet_measure`).
    """
    if rest_det < 0.0:
        flags |= 1
    if state == 1:
        flags |= 2
    elif state == 0:
        flags |= 4
        if det < low:
            low = det
        if cond > high:
            high = cond
    return low, high, flags


@numba.njit(cache=True)
def _cell_values(low, high, flags):  # pragma: no cover - compiled
    """A cell's ``(det, cond)`` from :func:`_add_tet`'s: NaN without a measured tet."""
    if flags & 4:
        return low, high
    return np.nan, np.nan


@numba.njit(cache=True)
def _reduce_cells(  # pragma: no cover - compiled
    owner, det, cond, rest_det, state, n_cells, out_det, out_cond, flags
):
    """Smallest ``det`` and largest ``cond`` of each cell's measured tets (serial, O(T)).

    ``flags``: as :func:`_add_tet`'s.
    """
    for c in range(n_cells):
        out_det[c] = np.inf
        out_cond[c] = -np.inf
        flags[c] = 0
    for t in range(owner.shape[0]):
        c = owner[t]
        out_det[c], out_cond[c], flags[c] = _add_tet(
            out_det[c], out_cond[c], flags[c], det[t], cond[t], rest_det[t], state[t]
        )
    for c in range(n_cells):
        out_det[c], out_cond[c] = _cell_values(out_det[c], out_cond[c], flags[c])


def tetrahedron_measures(
    rest_points, deformed_points, tets, owner=None, n_cells=None, *, condition=True
) -> dict:
    """Per-cell ``det F`` and ``cond F`` of a deformed mesh split into tetrahedra.

    ``F = D_def D_rest^-1`` is the Jacobian of the affine map taking a rest tetrahedron
    (edge matrix ``D_rest = [x1 - x0 | x2 - x0 | x3 - x0]``) onto its deformed one, so
    ``det F`` is the volume ratio, whatever order the vertices are stored in.

    Parameters
    ----------
    rest_points, deformed_points : (N, 3) array_like
        Positions at rest and after the deformation (NaN rows: not mapped).
    tets : (T, 4) array_like of int
        Vertex indices, each in ``[0, N)`` (checked by the caller).
    owner : (T,) array_like of int, optional
        The cell each tet belongs to, in ``[0, n_cells)``; default: each tet is a cell.
    n_cells : int, optional
        Number of cells; default ``T`` (cells without tets get NaN).
    condition : bool
        Compute ``cond F`` (skipped work when False: NaN).

    Returns
    -------
    dict
        ``determinant`` (n_cells,): the smallest ``det F`` of the cell's tets;
        ``condition_number`` (n_cells,): the largest ``s_max / s_min`` (inf for a
        flattened tet); ``rest_inverted`` (n_cells, bool): a tet stored with negative
        volume at rest; ``degenerate`` (n_cells, bool): a tet of the cell has no volume at
        rest (:data:`DEGENERATE_RTOL`). Cells with no measured tet get NaN measures.
    """
    x = np.ascontiguousarray(rest_points, dtype=np.float64).reshape(-1, 3)
    y = np.ascontiguousarray(deformed_points, dtype=np.float64).reshape(-1, 3)
    t = np.ascontiguousarray(tets, dtype=np.int64).reshape(-1, 4)
    n_tets = len(t)
    own = (
        np.arange(n_tets, dtype=np.int64)
        if owner is None
        else np.ascontiguousarray(owner, dtype=np.int64).reshape(-1)
    )
    n = n_tets if n_cells is None else int(n_cells)
    if owner is None and n < n_tets:
        raise ValueError(
            f"cell ids must lie in [0, {n}): {n_tets} tets, each its own cell, need "
            f"n_cells >= {n_tets}"
        )
    det = np.empty(n_tets)
    cond = np.empty(n_tets)
    rest_det = np.empty(n_tets)
    state = np.empty(n_tets, dtype=np.int8)
    if n_tets:
        run_rows(
            _tet_kernel, n_tets, x, y, t, DEGENERATE_RTOL, bool(condition), det, cond,
            rest_det, state, grain=_TETS_GRAIN,
        )  # fmt: skip
    if owner is None and n == n_tets:  # a cell per tet: _reduce_cells' numbers, in numpy
        measured = state == 0
        out_det = np.where(measured, np.where(det < np.inf, det, np.inf), np.nan)
        out_cond = np.where(measured, np.where(cond > -np.inf, cond, -np.inf), np.nan)
        rest_inverted, degenerate = rest_det < 0.0, state == 1
    else:
        out_det = np.empty(n)
        out_cond = np.empty(n)
        flags = np.empty(n, dtype=np.int8)
        _reduce_cells(own, det, cond, rest_det, state, n, out_det, out_cond, flags)
        rest_inverted, degenerate = (flags & 1).astype(bool), (flags & 2).astype(bool)
    if not condition:
        out_cond[:] = np.nan
    return {
        "determinant": out_det,
        "condition_number": out_cond,
        "rest_inverted": rest_inverted,
        "degenerate": degenerate,
    }


#: Kuhn's split of a voxel: one tet per monotone path from corner (0, 0, 0) to (1, 1, 1),
#: the axes in the order taken; the odd permutations swap their middle corners, so every
#: tet of a positively oriented voxel has a positive volume.
KUHN_PATHS = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))
_ODD_PATHS = ((0, 2, 1), (1, 0, 2), (2, 1, 0))


def kuhn_corners() -> np.ndarray:
    """(6, 4, 3) int64: the voxel corners ``(di, dj, dk)`` of Kuhn's six tets, in order."""
    out = np.zeros((len(KUHN_PATHS), 4, 3), dtype=np.int64)
    for q, order in enumerate(KUHN_PATHS):
        for step, axis in enumerate(order):
            out[q, step + 1 :, axis] = 1
        if order in _ODD_PATHS:
            out[q, [1, 2]] = out[q, [2, 1]]
    return out


#: Rows of lattice cells per chunk of :func:`lattice_tetrahedron_measures` at least.
_LATTICE_GRAIN = 16


@numba.njit(cache=True, nogil=True)
def _lattice_kernel(  # pragma: no cover - compiled
    start, stop, x, y, nx, ny, delta, rtol, want_cond, out_det, out_cond, flags
):
    """:func:`_reduce_cells` of the Kuhn tets of the lattice cells in rows ``start .. stop``.

    Row ``r`` holds the cells ``(i, j, k)`` with ``r = j + (ny - 1) k``, ``i`` fastest;
    ``delta`` (6, 4): each tet's point ids less that of the cell's corner (0, 0, 0).
    """
    for r in range(start, stop):
        j = r % (ny - 1)
        k = r // (ny - 1)
        for i in range(nx - 1):
            base = i + nx * (j + ny * k)
            c = i + (nx - 1) * r
            low, high, f = np.inf, -np.inf, 0
            for q in range(delta.shape[0]):
                d, g, rest, state = _tet_measure(
                    x, y, base + delta[q, 0], base + delta[q, 1], base + delta[q, 2],
                    base + delta[q, 3], rtol, want_cond,
                )  # fmt: skip
                low, high, f = _add_tet(low, high, f, d, g, rest, state)
            out_det[c], out_cond[c] = _cell_values(low, high, f)
            flags[c] = f


def lattice_tetrahedron_measures(
    rest_points, deformed_points, dimensions, *, condition=True
) -> dict:
    """:func:`tetrahedron_measures` of a lattice's cells, each split into Kuhn's six tets.

    The cells of an image, rectilinear or structured grid, measured where they lie: no
    tet or owner arrays are made.

    Parameters
    ----------
    rest_points, deformed_points : (N, 3) array_like
        The lattice's points at rest and after the deformation, in VTK's order (``i``
        fastest), ``N = nx * ny * nz``.
    dimensions : (3,) int
        ``(nx, ny, nz)`` points, each at least 2.
    condition : bool
        Compute ``cond F`` (skipped work when False: NaN).

    Returns
    -------
    dict
        As :func:`tetrahedron_measures` for the ``(nx - 1) (ny - 1) (nz - 1)`` cells in
        VTK's order, with the tets of :func:`kuhn_corners`.
    """
    nx, ny, nz = (int(d) for d in dimensions)
    if min(nx, ny, nz) < 2:
        raise ValueError(f"a lattice of {nx} x {ny} x {nz} points has no 3D cells")
    x = np.ascontiguousarray(rest_points, dtype=np.float64).reshape(-1, 3)
    y = np.ascontiguousarray(deformed_points, dtype=np.float64).reshape(-1, 3)
    if len(x) != nx * ny * nz or y.shape != x.shape:
        raise ValueError(
            f"a lattice of {nx} x {ny} x {nz} points needs {nx * ny * nz} rest and deformed "
            f"points; got {len(x)} and {len(y)}"
        )
    corners = kuhn_corners()
    delta = corners[..., 0] + nx * (corners[..., 1] + ny * corners[..., 2])
    n = (nx - 1) * (ny - 1) * (nz - 1)
    out_det, out_cond = np.empty(n), np.empty(n)
    flags = np.empty(n, dtype=np.int8)
    run_rows(
        _lattice_kernel, (ny - 1) * (nz - 1), x, y, nx, ny, delta, DEGENERATE_RTOL,
        bool(condition), out_det, out_cond, flags, grain=_LATTICE_GRAIN,
    )  # fmt: skip
    if not condition:
        out_cond[:] = np.nan
    return {
        "determinant": out_det,
        "condition_number": out_cond,
        "rest_inverted": (flags & 1).astype(bool),
        "degenerate": (flags & 2).astype(bool),
    }


#: Rows of cells (along j) that :func:`_hex_kernel` sweeps through every layer at a time:
#: a band's point and cross-product planes stay in a core's cache.
_HEX_BAND = 16
#: Boxes of cells that a thread of :func:`inverted_hexahedra` takes at a time at least.
_HEX_BOXES = 16
#: Inverted cells a chunk of the hexahedron kernels has room for at first (:func:`_with_room`).
_HEX_FIRST_ROOM = 1024


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _hex_kernel(
    start, stop, p, sign, scale, out, planes, cross, ez, scratch, bad_cell, bad_value
):  # pragma: no cover - compiled
    """Smallest corner determinant of the cells in rows ``start <= j < stop``, every layer.

    The determinant at corner ``(a, b, c)`` is ``ez(a, b) . (ex(b, c) x ey(a, c))``; the
    cross products of a point plane serve the layers of cells below and above it, so
    each is made once. A band of rows goes through the layers; per plane, one array per
    coordinate (the loops along a row run in SIMD lanes). ``ez`` is multiplied by
    ``sign`` (that of the rest voxel's determinant, an exact product), so the smallest
    product is the smallest ratio to the rest voxel once divided by ``scale`` (its
    absolute value). A cell with a corner determinant that is not finite (a point that
    is not finite) gets NaN: the sum of its eight determinants less itself is added.

    Each row of cells' values go to ``out[k, j]`` where ``out`` has a layer per layer
    of cells, else to ``scratch`` (a row). The inverted cells (value ``<= 0``) go to
    ``bad_cell`` (their indices ``(k * (ny - 1) + j) * (nx - 1) + i``, in the order met)
    and ``bad_value`` while there is room. Returns ``(not finite, inverted)`` counts: where
    the second exceeds the room, the call is to be repeated with more.

    The working planes come from the caller (:func:`_run_hex_kernel`), as does all memory:
    a kernel that allocates carries numba's allocation and error paths, code that every
    process loads from the cache before the kernel's first call.
    """
    nz, ny, nx = p.shape[0] - 1, p.shape[1] - 1, p.shape[2] - 1
    band = min(_HEX_BAND, stop - start)
    write = out.shape[0] == nz
    n_nan = 0
    n_bad = 0
    for j0 in range(start, stop, band):
        rows = min(band, stop - j0)
        for k in range(nz + 1):
            q = k % 2
            plane = planes[q]
            for j in range(rows + 1):
                for i in range(nx + 1):
                    plane[0, j, i] = p[k, j0 + j, i, 0]
                    plane[1, j, i] = p[k, j0 + j, i, 1]
                    plane[2, j, i] = p[k, j0 + j, i, 2]
            for j in range(rows):
                for b in range(2):
                    for a in range(2):
                        x = cross[q, a + 2 * b]
                        for i in range(nx):
                            x0 = plane[0, j + b, i + 1] - plane[0, j + b, i]
                            x1 = plane[1, j + b, i + 1] - plane[1, j + b, i]
                            x2 = plane[2, j + b, i + 1] - plane[2, j + b, i]
                            y0 = plane[0, j + 1, i + a] - plane[0, j, i + a]
                            y1 = plane[1, j + 1, i + a] - plane[1, j, i + a]
                            y2 = plane[2, j + 1, i + a] - plane[2, j, i + a]
                            x[0, j, i] = x1 * y2 - x2 * y1
                            x[1, j, i] = x2 * y0 - x0 * y2
                            x[2, j, i] = x0 * y1 - x1 * y0
            if k == 0:
                continue
            below = planes[1 - q]
            for e in range(3):
                for j in range(rows + 1):
                    for i in range(nx + 1):
                        ez[e, j, i] = (plane[e, j, i] - below[e, j, i]) * sign
            c0, c1 = cross[1 - q], cross[q]  # the layer's bottom and top planes
            for j in range(rows):
                row = out[k - 1, j0 + j] if write else scratch
                for i in range(nx):
                    low = np.inf
                    total = 0.0
                    for b in range(2):
                        for a in range(2):
                            c = a + 2 * b
                            z0 = ez[0, j + b, i + a]
                            z1 = ez[1, j + b, i + a]
                            z2 = ez[2, j + b, i + a]
                            d0 = z0 * c0[c, 0, j, i] + z1 * c0[c, 1, j, i] + z2 * c0[c, 2, j, i]
                            d1 = z0 * c1[c, 0, j, i] + z1 * c1[c, 1, j, i] + z2 * c1[c, 2, j, i]
                            low = d0 if d0 < low else low  # branch-free: SIMD lanes
                            low = d1 if d1 < low else low
                            total += d0 + d1
                    row[i] = low / scale + (total - total)  # + 0, or NaN
                row_nan = 0
                row_bad = 0
                for i in range(nx):
                    v = row[i]
                    row_nan += v != v
                    row_bad += v <= 0.0
                n_nan += row_nan
                if row_bad == 0:
                    continue
                first = ((k - 1) * ny + j0 + j) * nx
                for i in range(nx):
                    if row[i] <= 0.0:
                        if n_bad < bad_cell.size:
                            bad_cell[n_bad] = first + i
                            bad_value[n_bad] = row[i]
                        n_bad += 1
    return n_nan, n_bad


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _hex_box_kernel(
    start, stop, p, boxes, sign, scale, bad_cell, bad_value
):  # pragma: no cover - compiled
    """:func:`_hex_kernel`'s values for the cells of ``boxes[start:stop]`` alone.

    ``boxes`` (K, 6): inclusive cell ranges ``i0, i1, j0, j1, k0, k1``. Each cell's eight
    corner determinants are made from its own points (the boxes are small and scattered:
    rows too short to share work along), with the same operations in the same order as
    :func:`_hex_kernel` (the same numbers, bit for bit). The inverted cells go to
    ``bad_cell`` and ``bad_value`` while there is room, as in :func:`_hex_kernel`.
    Returns ``(cells measured, not finite, inverted)``.
    """
    ny, nx = p.shape[1] - 1, p.shape[2] - 1
    n_cells = 0
    n_nan = 0
    n_bad = 0
    for q in range(start, stop):
        i0, i1, j0, j1 = boxes[q, 0], boxes[q, 1], boxes[q, 2], boxes[q, 3]
        k0, k1 = boxes[q, 4], boxes[q, 5]
        n_cells += (i1 - i0 + 1) * (j1 - j0 + 1) * (k1 - k0 + 1)
        for k in range(k0, k1 + 1):
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    low = np.inf
                    total = 0.0
                    for b in range(2):
                        for a in range(2):
                            z0 = (p[k + 1, j + b, i + a, 0] - p[k, j + b, i + a, 0]) * sign
                            z1 = (p[k + 1, j + b, i + a, 1] - p[k, j + b, i + a, 1]) * sign
                            z2 = (p[k + 1, j + b, i + a, 2] - p[k, j + b, i + a, 2]) * sign
                            d0 = _corner(p[k], j, i, a, b, z0, z1, z2)
                            d1 = _corner(p[k + 1], j, i, a, b, z0, z1, z2)
                            low = d0 if d0 < low else low
                            low = d1 if d1 < low else low
                            total += d0 + d1
                    v = low / scale + (total - total)  # + 0, or NaN
                    if v != v:
                        n_nan += 1
                    elif v <= 0.0:
                        if n_bad < bad_cell.size:
                            bad_cell[n_bad] = (k * ny + j) * nx + i
                            bad_value[n_bad] = v
                        n_bad += 1
    return n_cells, n_nan, n_bad


@numba.njit(cache=True, inline="always")
def _corner(plane, j, i, a, b, z0, z1, z2):  # pragma: no cover - compiled
    """``z . (x x y)`` at a cell's corner ``(a, b)`` in a plane of points.

    As in :func:`_hex_kernel`: ``x`` is the edge along i at row ``j + b``, ``y`` the edge
    along j at column ``i + a``.
    """
    x0 = plane[j + b, i + 1, 0] - plane[j + b, i, 0]
    x1 = plane[j + b, i + 1, 1] - plane[j + b, i, 1]
    x2 = plane[j + b, i + 1, 2] - plane[j + b, i, 2]
    y0 = plane[j + 1, i + a, 0] - plane[j, i + a, 0]
    y1 = plane[j + 1, i + a, 1] - plane[j, i + a, 1]
    y2 = plane[j + 1, i + a, 2] - plane[j, i + a, 2]
    w0 = x1 * y2 - x2 * y1
    w1 = x2 * y0 - x0 * y2
    w2 = x0 * y1 - x1 * y0
    return z0 * w0 + z1 * w1 + z2 * w2


def _hex_grid(points, dimensions, rest_det):
    """Points as ``(nz, ny, nx, 3)`` and the cells' shape ``(nz-1, ny-1, nx-1)``."""
    nx, ny, nz = (int(d) for d in dimensions)
    if not rest_det or not math.isfinite(rest_det):
        raise ValueError(f"rest_det must be finite and non-zero; got {rest_det}")
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(nz, ny, nx, 3))
    return p, (max(nz - 1, 0), max(ny - 1, 0), max(nx - 1, 0))


def _run_hex_kernel(p, cells, rest_det: float, out) -> tuple[int, np.ndarray, np.ndarray]:
    """:func:`_hex_kernel` over every row of cells, on threads.

    Returns the cells that are not finite, and the inverted cells (indices ascending, in
    VTK's cell order) with their values.
    """
    sign, scale = math.copysign(1.0, rest_det), abs(float(rest_det))
    chunks = []

    def chunk(start, stop):
        band, nx = min(_HEX_BAND, stop - start), cells[2]
        planes = np.empty((2, 3, band + 1, nx + 1))  # [plane parity, xyz, j, i]
        cross = np.empty((2, 4, 3, band, nx))  # [plane parity, corner a + 2 b, xyz, j, i]
        ez, scratch = np.empty((3, band + 1, nx + 1)), np.empty(nx)

        def kernel(bad_cell, bad_value):
            return _hex_kernel(start, stop, p, sign, scale, out, planes, cross, ez, scratch,
                               bad_cell, bad_value)  # fmt: skip

        (n_nan, _), bad, value = _with_room(kernel)
        chunks.append((start, n_nan, bad, value))

    if 0 not in cells:
        run_rows(chunk, cells[1], grain=_HEX_BAND)
    chunks.sort(key=lambda c: c[0])
    n_nan = sum(c[1] for c in chunks)
    bad = np.concatenate([np.zeros(0, np.int64)] + [c[2] for c in chunks])
    value = np.concatenate([np.zeros(0)] + [c[3] for c in chunks])
    order = np.argsort(bad, kind="stable")
    return n_nan, bad[order], value[order]


def _with_room(kernel):
    """``kernel(bad_cell, bad_value)`` with room for the inverted cells it meets.

    The kernel returns counts ending with the inverted cells it met, and keeps as many as
    there is room for; it is called again with room for all of them where they did not
    fit (a chunk with more than :data:`_HEX_FIRST_ROOM` inverted cells). Returns
    ``(counts, cell indices, values)``.
    """
    room = _HEX_FIRST_ROOM
    while True:
        bad_cell, bad_value = np.empty(room, dtype=np.int64), np.empty(room)
        counts = kernel(bad_cell, bad_value)
        if counts[-1] <= room:
            return counts, bad_cell[: counts[-1]], bad_value[: counts[-1]]
        room = counts[-1]


def hexahedron_corner_determinants(points, dimensions, rest_det: float) -> np.ndarray:
    """Smallest corner Jacobian determinant of each cell of a deformed voxel grid.

    The grid's cell ``(i, j, k)`` is the trilinear image of a rest voxel; at each of its
    eight corners the Jacobian of the trilinear map has the cell's three edges from that
    corner (along i, j and k) as columns. Its determinant, divided by the rest voxel's
    (``rest_det``), is the local volume ratio there; the cell is inverted where one is
    ``<= 0``. (:func:`inverted_hexahedra` gives the same numbers for the inverted cells
    alone, without an array per cell.)

    Parameters
    ----------
    points : (nx * ny * nz, 3) array_like
        Deformed positions in VTK's point order (i fastest, then j, then k).
    dimensions : (3,) int
        Points along i, j and k (``nx, ny, nz``).
    rest_det : float
        ``det`` of the rest voxel's edge matrix: ``sx * sy * sz * det(direction)`` for an
        image with spacing ``s`` and direction matrix ``direction``; not 0 (negative for
        a left-handed frame).

    Returns
    -------
    ((nx - 1) * (ny - 1) * (nz - 1),) float64
        Per cell in VTK's cell order, the smallest of the eight ratios; NaN where one is
        not finite (a point that is not finite).
    """
    p, cells = _hex_grid(points, dimensions, rest_det)
    out = np.empty(cells)
    _run_hex_kernel(p, cells, rest_det, out)
    return out.reshape(-1)


def inverted_hexahedra(points, dimensions, rest_det: float, boxes=None) -> dict:
    """The inverted cells of a deformed voxel grid, and how many cells were measured.

    The numbers of :func:`hexahedron_corner_determinants` (bit for bit) for the cells
    whose smallest ratio is ``<= 0``, counted as the kernel goes: no array of a value per
    cell is made or scanned.

    Parameters
    ----------
    points, dimensions, rest_det
        As for :func:`hexahedron_corner_determinants`: ``(nx * ny * nz, 3)`` positions in
        VTK's point order, ``(nx, ny, nz)`` and the rest voxel's determinant.
    boxes : (K, 6) int array_like, optional
        Only the cells of these boxes (inclusive cell ranges ``i0, i1, j0, j1, k0, k1``,
        disjoint, within the grid's ``nx - 1`` by ``ny - 1`` by ``nz - 1`` cells) are
        measured, each from its own eight points: the cells a proof leaves over
        (:meth:`~vhm_viz.core.volume.VolumeDeformation.unproven_cells`). Default: all.

    Returns
    -------
    dict
        ``cells`` (int): measured cells whose eight ratios are finite; ``inverted`` (K,)
        int64: the inverted cells in VTK's cell order, ascending; ``determinant`` (K,)
        float64: their smallest corner ratio (``<= 0``).
    """
    p, cells = _hex_grid(points, dimensions, rest_det)
    if boxes is None:
        n_nan, bad, value = _run_hex_kernel(p, cells, rest_det, np.empty((0, 0, 0)))
        return {"cells": cells[0] * cells[1] * cells[2] - n_nan, "inverted": bad,
                "determinant": value}  # fmt: skip
    boxes = np.ascontiguousarray(boxes, dtype=np.int64).reshape(-1, 6)
    top = np.repeat(np.asarray(cells[::-1], dtype=np.int64) - 1, 2)
    if boxes.size and (
        (boxes < 0).any() or (boxes > top).any() or (boxes[:, 1::2] < boxes[:, 0::2]).any()
    ):
        raise ValueError(f"boxes must be non-empty cell ranges within {cells[::-1]} cells")
    sign, scale = math.copysign(1.0, rest_det), abs(float(rest_det))
    chunks = []

    def chunk(start, stop):
        def kernel(bad_cell, bad_value):
            return _hex_box_kernel(start, stop, p, boxes, sign, scale, bad_cell, bad_value)

        chunks.append(_with_room(kernel))

    run_rows(chunk, len(boxes), grain=_HEX_BOXES)
    bad = np.concatenate([np.zeros(0, np.int64)] + [c[1] for c in chunks])
    value = np.concatenate([np.zeros(0)] + [c[2] for c in chunks])
    order = np.argsort(bad, kind="stable")
    measured = sum(c[0][0] - c[0][1] for c in chunks)
    return {"cells": int(measured), "inverted": bad[order], "determinant": value[order]}
