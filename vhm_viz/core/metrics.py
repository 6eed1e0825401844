"""Quality metrics of a deformation: the paper's E_rigid and E_volume, Jacobian measures.

Surface measures (paper Section 4) compare a triangle mesh before and after deformation:

* :func:`rigidity_distortion` -- the area-weighted ``(s1 - 1)^2 + (s2 - 1)^2`` of the
  singular values of each triangle's 2x2 map (Liu et al. 2008, as in the paper's Table 1).
* :func:`volume_change` -- ``|V_new - V_orig| / V_orig`` of the enclosed volume.

Point measures take Jacobians ``J[k, i, j] = d f_i / d x_j`` of shape ``(N, 3, 3)`` (as
returned by ``HarmonicMap.jacobian``): :func:`jacobian_determinant`,
:func:`condition_number` (``s_max / s_min``), :func:`rotation_angle` (angle of the rotation
of the polar decomposition), :func:`stretch` (largest singular value), :func:`foldover_count`
(``det J <= 0``), and :func:`jacobian_measures` for all of them at once.

Cell measures judge the linear tetrahedra a user gets back, which can invert while the map
is positive at every vertex (and the other way round): :func:`tetrahedron_gradients` (the
deformation gradient ``D_def D_rest^-1`` of each tet's edge matrices), :func:`cell_measures`
(per cell, over the tets a cell was split into) and :func:`cell_summary` (the counts).
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.cell_kernels import DEGENERATE_RTOL, tetrahedron_measures
from vhm_viz.core.geometry import signed_volume
from vhm_viz.core.points import as_points

__all__ = [
    "rigidity_distortion",
    "triangle_singular_values",
    "volume_change",
    "singular_values",
    "jacobian_determinant",
    "condition_number",
    "rotation_angle",
    "stretch",
    "foldover_count",
    "jacobian_measures",
    "tetrahedron_gradients",
    "cell_measures",
    "cell_summary",
    "finite_or_none",
]


def _simplices(s, n_points: int, corners: int = 3, name: str = "triangles") -> np.ndarray:
    """Validated (m, corners) int64 indices into ``n_points`` points (triangles or tets)."""
    f = np.asarray(s)
    if f.ndim != 2 or f.shape[1] != corners:
        raise ValueError(f"{name} must have shape (m, {corners}); got {f.shape}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= n_points):
        raise ValueError(f"{name} indices must lie in [0, {n_points})")
    return f


def _frame_coords(p0, p1, p2):
    """2D coordinates of the edges ``p1 - p0`` and ``p2 - p0`` in each triangle's plane.

    Returns the (m, 2, 2) matrix whose columns are the two edge vectors, and twice the area.
    """
    e1 = p1 - p0
    e2 = p2 - p0
    l1 = np.linalg.norm(e1, axis=1)
    n = np.cross(e1, e2)
    twice_area = np.linalg.norm(n, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = e1 / l1[:, None]
        v = np.cross(n / twice_area[:, None], u)
    m = np.empty((len(p0), 2, 2))
    m[:, 0, 0] = l1
    m[:, 1, 0] = 0.0
    m[:, 0, 1] = np.einsum("ij,ij->i", e2, u)
    m[:, 1, 1] = np.einsum("ij,ij->i", e2, v)
    return m, twice_area


def _sv2(a, b, c, d):
    """Singular values (s1 >= s2 >= 0) of 2x2 matrices [[a, b], [c, d]] in closed form."""
    e = 0.5 * (a + d)
    f = 0.5 * (a - d)
    g = 0.5 * (c + b)
    h = 0.5 * (c - b)
    q = np.hypot(e, h)
    r = np.hypot(f, g)
    return q + r, np.abs(q - r)


def triangle_singular_values(source_points, deformed_points, triangles):
    """Singular values of the 2x2 map of each triangle from its source to its deformed shape.

    Parameters
    ----------
    source_points, deformed_points : (N, 3) array_like
        Vertex positions before and after the deformation (same connectivity).
    triangles : (m, 3) array_like of int
        Triangles.

    Returns
    -------
    s : (m, 2) float64
        ``s[:, 0] >= s[:, 1] >= 0``; NaN for triangles that are degenerate in the source.
    source_areas : (m,) float64
        Source triangle areas.
    """
    x = as_points(source_points, "source_points")
    y = as_points(deformed_points, "deformed_points")
    if x.shape != y.shape:
        raise ValueError(f"source and deformed points differ in shape: {x.shape} vs {y.shape}")
    f = _simplices(triangles, len(x))
    ms, twice_area = _frame_coords(x[f[:, 0]], x[f[:, 1]], x[f[:, 2]])
    md, _ = _frame_coords(y[f[:, 0]], y[f[:, 1]], y[f[:, 2]])
    # deformed triangles that collapsed to a segment/point: their frame is NaN; treat the
    # plane as arbitrary by measuring through the 3x2 map's Gram matrix instead.
    ok = twice_area > 0
    s = np.full((len(f), 2), np.nan)
    if ok.any():
        # 3x2 map M = E_def @ inv(E_src) where E are the 3x2 edge matrices; singular values of
        # M via its 2x2 Gram matrix would lose accuracy, so use the 2D frames when possible.
        inv = np.linalg.inv(ms[ok])
        j2 = md[ok] @ inv
        bad = ~np.isfinite(j2).all(axis=(1, 2))
        s1, s2 = _sv2(j2[:, 0, 0], j2[:, 0, 1], j2[:, 1, 0], j2[:, 1, 1])
        if bad.any():
            # collapsed deformed triangles: fall back to the 3x2 map
            idx = np.nonzero(ok)[0][bad]
            ed = np.stack([y[f[idx, 1]] - y[f[idx, 0]], y[f[idx, 2]] - y[f[idx, 0]]], axis=2)
            m32 = ed @ inv[bad]
            sv = np.linalg.svd(m32, compute_uv=False)
            s1[bad], s2[bad] = sv[:, 0], sv[:, 1]
        s[ok, 0], s[ok, 1] = s1, s2
    return s, 0.5 * twice_area


def rigidity_distortion(source_points, deformed_points, triangles) -> float:
    """The paper's rigidity distortion ``E_rigid`` of a deformed triangle mesh.

    ``E_rigid = sum_t A_t [(s1_t - 1)^2 + (s2_t - 1)^2] / sum_t A_t`` with ``A_t`` the source
    triangle area and ``s1_t, s2_t`` the singular values of the 2x2 linear map taking the
    source triangle (in its own plane) to the deformed triangle (in its plane). Rigid motions
    give 0. Source triangles of zero area are ignored (they carry no weight).

    Parameters
    ----------
    source_points, deformed_points : (N, 3) array_like
    triangles : (m, 3) array_like of int

    Returns
    -------
    float
    """
    s, area = triangle_singular_values(source_points, deformed_points, triangles)
    ok = area > 0
    if not ok.any():
        raise ValueError("all source triangles are degenerate (zero area)")
    e = ((s[ok] - 1.0) ** 2).sum(axis=1)
    return float((area[ok] * e).sum() / area[ok].sum())


def volume_change(source_points, deformed_points, triangles) -> float:
    """Relative change of the enclosed volume, ``|V_new - V_orig| / V_orig``.

    Parameters
    ----------
    source_points, deformed_points : (N, 3) array_like
        Vertices of a closed triangle mesh before and after deformation.
    triangles : (m, 3) array_like of int
        Consistently oriented triangles (either orientation: the sign cancels).

    Returns
    -------
    float
    """
    x = as_points(source_points, "source_points")
    y = as_points(deformed_points, "deformed_points")
    f = _simplices(triangles, len(x))
    v0 = signed_volume(x, f)
    if v0 == 0.0:
        raise ValueError("the source mesh encloses no volume")
    v1 = signed_volume(y, f)
    return float(abs(v1 - v0) / abs(v0))


# ----------------------------------------------------------------------------- Jacobians
def _jacobians(jacobians) -> np.ndarray:
    j = np.asarray(jacobians, dtype=np.float64)
    if j.shape == (3, 3):
        j = j[None]
    if j.ndim != 3 or j.shape[1:] != (3, 3):
        raise ValueError(f"jacobians must have shape (N, 3, 3); got {j.shape}")
    return j


def _svd(j: np.ndarray, compute_uv: bool = True):
    """SVD of each finite matrix; NaN factors for matrices with a NaN or inf entry.

    Points outside the cage get NaN Jacobians under the ``"nan"`` outside policy, and
    LAPACK refuses a batch with any of them ("SVD did not converge").
    """
    ok = np.isfinite(j).all(axis=(1, 2))
    if ok.all():
        return np.linalg.svd(j, compute_uv=compute_uv)
    s = np.full((len(j), 3), np.nan)
    if not compute_uv:
        s[ok] = np.linalg.svd(j[ok], compute_uv=False)
        return s
    u = np.full((len(j), 3, 3), np.nan)
    vt = np.full((len(j), 3, 3), np.nan)
    u[ok], s[ok], vt[ok] = np.linalg.svd(j[ok])
    return u, s, vt


def singular_values(jacobians) -> np.ndarray:
    """Singular values of each Jacobian, descending: shape (N, 3) (NaN for non-finite J)."""
    return _svd(_jacobians(jacobians), compute_uv=False)


def _det(m: np.ndarray) -> np.ndarray:
    """``numpy.linalg.det`` of a stack of matrices; NaN for a non-finite one, quietly.

    NaN Jacobians are the documented result outside the cage (``outside="nan"``), not a
    numerical accident to warn about.
    """
    with np.errstate(invalid="ignore"):
        return np.linalg.det(m)


def jacobian_determinant(jacobians) -> np.ndarray:
    """``det J`` per point (local volume ratio): shape (N,)."""
    return _det(_jacobians(jacobians))


def condition_number(jacobians) -> np.ndarray:
    """``s_max / s_min`` per point (``inf`` for singular Jacobians): shape (N,)."""
    s = singular_values(jacobians)
    return _cond(s)


def _cond(s: np.ndarray) -> np.ndarray:
    out = np.full(len(s), np.inf)
    out[np.isnan(s[:, 2])] = np.nan
    ok = s[:, 2] > 0
    out[ok] = s[ok, 0] / s[ok, 2]
    return out


def stretch(jacobians) -> np.ndarray:
    """Largest singular value ``s_max`` per point (largest length ratio): shape (N,)."""
    return singular_values(jacobians)[:, 0]


def _polar_rotation(j: np.ndarray) -> np.ndarray:
    """Closest proper rotation ``U diag(1, 1, det(U V^T)) V^T`` of each matrix."""
    u, _, vt = _svd(j)
    sign = np.sign(_det(u @ vt))
    sign[sign == 0] = 1.0
    u = u.copy()
    u[:, :, 2] *= sign[:, None]
    return u @ vt


def rotation_angle(jacobians, *, degrees: bool = False) -> np.ndarray:
    """Angle of the rotation factor of each Jacobian's polar decomposition.

    The rotation is the proper rotation closest to ``J`` in the Frobenius norm (for
    ``det J < 0`` the sign of the smallest singular direction is flipped, as in the solver's
    local step).

    Parameters
    ----------
    jacobians : (N, 3, 3) array_like
    degrees : bool
        Return degrees instead of radians.

    Returns
    -------
    (N,) float64 in ``[0, pi]`` (or ``[0, 180]``).
    """
    r = _polar_rotation(_jacobians(jacobians))
    c = np.clip((np.trace(r, axis1=1, axis2=2) - 1.0) * 0.5, -1.0, 1.0)
    a = np.arccos(c)
    return np.degrees(a) if degrees else a


def foldover_count(jacobians) -> int:
    """Number of points whose Jacobian has ``det J <= 0`` (the map folds over there)."""
    return int(np.count_nonzero(jacobian_determinant(jacobians) <= 0.0))


def jacobian_measures(jacobians) -> dict:
    """All per-point measures of an (N, 3, 3) Jacobian array in one SVD pass.

    Returns
    -------
    dict
        ``determinant``, ``condition_number`` (``s_max/s_min``), ``rotation_angle``
        (radians), ``stretch`` (``s_max``), ``min_stretch`` (``s_min``), arrays of shape
        (N,); and ``foldovers`` (int, count of ``det <= 0``).
    """
    j = _jacobians(jacobians)
    u, s, vt = _svd(j)
    det = _det(j)
    sign = np.where(_det(u @ vt) < 0, -1.0, 1.0)
    u = u.copy()
    u[:, :, 2] *= sign[:, None]
    r = u @ vt
    angle = np.arccos(np.clip((np.trace(r, axis1=1, axis2=2) - 1.0) * 0.5, -1.0, 1.0))
    cond = _cond(s)
    return {
        "determinant": det,
        "condition_number": cond,
        "rotation_angle": angle,
        "stretch": s[:, 0],
        "min_stretch": s[:, 2],
        "foldovers": int(np.count_nonzero(det <= 0.0)),
    }


# ----------------------------------------------------------------------------- cells
def _edge_matrices(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(T, 3, 3) edge matrices ``[x1 - x0 | x2 - x0 | x3 - x0]`` (edges as columns)."""
    x = points[tets]
    return np.swapaxes(x[:, 1:] - x[:, :1], 1, 2)


def tetrahedron_gradients(rest_points, deformed_points, tets):
    """Deformation gradient of each linear tetrahedron, ``F = D_def D_rest^-1``.

    ``D`` are the edge matrices ``[x1 - x0 | x2 - x0 | x3 - x0]``; ``F`` is the Jacobian of
    the affine map taking the rest tet onto the deformed one, so ``det F = det D_def /
    det D_rest`` is the tet's volume ratio, independent of the order its vertices are
    stored in (a tet stored inverted at rest is not blamed on the deformation).

    Parameters
    ----------
    rest_points, deformed_points : (N, 3) array_like
    tets : (T, 4) array_like of int

    Returns
    -------
    F : (T, 3, 3) float64
        NaN for tets degenerate at rest (see :data:`DEGENERATE_RTOL`).
    rest_det : (T,) float64
        ``det D_rest`` (six times the signed rest volume; negative: stored inverted).
    """
    x = np.asarray(rest_points, dtype=np.float64).reshape(-1, 3)
    y = np.asarray(deformed_points, dtype=np.float64).reshape(-1, 3)
    if x.shape != y.shape:
        raise ValueError(f"rest and deformed points differ in shape: {x.shape} vs {y.shape}")
    t = _simplices(tets, len(x), 4, "tets")
    d_rest = _edge_matrices(x, t)
    rest_det = np.linalg.det(d_rest)
    edge = np.linalg.norm(d_rest, axis=1).max(axis=1) if len(t) else np.zeros(0)
    ok = np.abs(rest_det) > DEGENERATE_RTOL * edge**3
    grads = np.full((len(t), 3, 3), np.nan)
    if ok.any():
        # F D_rest = D_def  <=>  D_rest^T F^T = D_def^T
        d_def = _edge_matrices(y, t[ok])
        grads[ok] = np.swapaxes(
            np.linalg.solve(np.swapaxes(d_rest[ok], 1, 2), np.swapaxes(d_def, 1, 2)), 1, 2
        )
    return grads, rest_det


def cell_measures(
    rest_points, deformed_points, tets, cells=None, n_cells=None, *, condition: bool = True
) -> dict:
    """Per-cell quality of a deformed mesh whose cells are (split into) tetrahedra.

    Compiled, one thread per tet (:func:`vhm_viz.core.cell_kernels.tetrahedron_measures`).

    Parameters
    ----------
    rest_points, deformed_points : (N, 3) array_like
    tets : (T, 4) array_like of int
    cells : (T,) array_like of int, optional
        The cell each tet belongs to (a hexahedron split into five or six tets, ...);
        default: each tet is a cell.
    n_cells : int, optional
        Number of cells (cells without tets, e.g. 2D cells of a mixed mesh, get NaN);
        default ``cells.max() + 1``.
    condition : bool
        Compute the condition numbers (NaN when False).

    Returns
    -------
    dict
        ``determinant`` (n_cells,): the smallest ``det F`` of the cell's tets (``<= 0``:
        the cell comes back inverted or flat); ``condition_number`` (n_cells,): the largest
        ``s_max / s_min`` of ``F`` (inf for a flattened tet); ``rest_inverted`` (n_cells,
        bool): a tet of the cell is stored with negative volume at rest; ``degenerate``
        (n_cells, bool): a tet of the cell has no volume at rest (its ``F`` is undefined).
        A tet with a NaN deformed corner (outside the cage under the "nan" policy) is not
        measured and not degenerate.
    """
    x = np.asarray(rest_points, dtype=np.float64).reshape(-1, 3)
    y = np.asarray(deformed_points, dtype=np.float64).reshape(-1, 3)
    if x.shape != y.shape:
        raise ValueError(f"rest and deformed points differ in shape: {x.shape} vs {y.shape}")
    index = _simplices(tets, len(x), 4, "tets")
    t = len(index)
    if cells is None:  # a cell per tet, in order (and cells after them without one)
        return tetrahedron_measures(x, y, index, None, n_cells, condition=condition)
    owner = np.asarray(cells, dtype=np.int64).reshape(-1)
    if owner.shape != (t,):
        raise ValueError(f"cells must have one entry per tet ({t}); got {owner.shape}")
    if n_cells is None:
        n_cells = int(owner.max()) + 1 if t else 0
    if t and (owner.min() < 0 or owner.max() >= n_cells):
        raise ValueError(f"cell ids must lie in [0, {n_cells})")
    return tetrahedron_measures(x, y, index, owner, n_cells, condition=condition)


def cell_summary(measures: dict) -> dict:
    """The counts of :func:`cell_measures` (what ``metrics.json`` reports as ``"cells"``).

    Returns
    -------
    dict
        ``cells`` (with a measure), ``inverted`` (cells with ``det F <= 0``: inverted or
        flattened by the deformation), ``det_min``, ``det_max``, ``cond_max``,
        ``rest_inverted`` (cells stored inverted at rest: reported, not blamed on the
        deformation) and ``degenerate`` (cells with a flat rest tet).
    """
    det = np.asarray(measures["determinant"], dtype=np.float64)
    cond = np.asarray(measures["condition_number"], dtype=np.float64)
    ok = np.isfinite(det)
    out = {
        "cells": int(ok.sum()),
        "inverted": int(np.count_nonzero(det[ok] <= 0.0)),
        "det_min": float(det[ok].min()) if ok.any() else float("nan"),
        "det_max": float(det[ok].max()) if ok.any() else float("nan"),
        "cond_max": float(np.nanmax(cond)) if (ok & ~np.isnan(cond)).any() else float("nan"),
        "rest_inverted": int(np.count_nonzero(measures["rest_inverted"])),
        "degenerate": int(np.count_nonzero(measures["degenerate"])),
    }
    return out


def finite_or_none(value):
    """``float(value)``, or None for NaN and infinity (strict JSON has neither)."""
    v = float(value)
    return v if np.isfinite(v) else None
