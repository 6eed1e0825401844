"""The one inside test of a cage: winding numbers, and points on its surface.

A point is inside a closed, outward-oriented cage when its generalised winding number
(the sum of the faces' solid angles over ``4 pi``, which equals ``sum_v phi_v``) is 1, and
outside when it is 0. Points computed on the cage surface land a few ulps to either side
of it; :func:`classify_inside` counts them as inside and names the face each one lies on,
and :func:`surface_points_inside` says where to evaluate them so that the map takes its
interior limit there.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.basis_lanes import ROWS_GRAIN, winding_kernel
from vhm_viz.core.basis_reference import NUMPY_CHUNK
from vhm_viz.core.cage_tables import read_only
from vhm_viz.core.geometry import face_normals_and_areas, point_triangle_distance2
from vhm_viz.core.points import as_points
from vhm_viz.core.row_threads import run_rows

__all__ = [
    "ON_SURFACE_RTOL",
    "WINDING_TOLERANCE",
    "classify_inside",
    "classify_points",
    "inside_cage",
    "on_surface_tolerance",
    "surface_hosts",
    "surface_points_inside",
    "winding_number",
]

_TWO_PI = 2.0 * math.pi

#: Tolerance on the winding number for "inside the cage". Points on the cage surface have
#: winding number exactly 1/2 and count as inside; the winding number jumps from 0 to 1
#: across the surface (it does not pass through 1/2), so points even 1e-9 off the surface
#: are classified correctly.
WINDING_TOLERANCE = 1e-8
#: Points this close to the cage surface (relative to the bounding-box diagonal) are on it,
#: whichever side rounding put them (see :func:`on_surface_tolerance`).
ON_SURFACE_RTOL = 1e-12


def inside_cage(winding: np.ndarray) -> np.ndarray:
    """The winding-number half of the inside test: ``winding >= 1/2 - WINDING_TOLERANCE``.

    Points that the winding number puts outside may still lie on the cage surface (within
    rounding); :func:`classify_inside` is the whole test.

    Parameters
    ----------
    winding : (N,) float64
        Winding numbers (:func:`winding_number`, or the sum of the ``phi`` columns).

    Returns
    -------
    (N,) bool
    """
    return np.asarray(winding) >= 0.5 - WINDING_TOLERANCE


def on_surface_tolerance(vertices) -> float:
    """Distance within which a point counts as on the cage surface (length units).

    ``ON_SURFACE_RTOL`` times the bounding-box diagonal, plus 16 units in the last place of
    the largest coordinate: a point computed on a face (barycentric combination of its
    corners) lies a few ulps off the face's plane, on either side, wherever the cage is.
    """
    v = np.asarray(vertices, dtype=np.float64)
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    return ON_SURFACE_RTOL * diag + 16.0 * float(np.spacing(np.abs(v).max()))


def surface_hosts(points, vertices, faces, tolerance: float | None = None) -> np.ndarray:
    """For each point, a face within ``tolerance`` of it (-1 for none).

    Of several faces within reach (a point on an edge or at a vertex) the lowest-numbered
    one is the host: ties are resolved the same way whatever the rounding of distances.

    Parameters
    ----------
    points : (N, 3) array_like
    vertices, faces : cage arrays
    tolerance : float, optional
        Default :func:`on_surface_tolerance`.

    Returns
    -------
    (N,) int64
    """
    p = as_points(points)
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    tol = on_surface_tolerance(v) if tolerance is None else float(tolerance)
    host = np.full(len(p), -1, dtype=np.int64)
    if not len(p) or not len(f):
        return host
    lo, hi = v.min(axis=0) - tol, v.max(axis=0) + tol
    near = np.nonzero(((p >= lo) & (p <= hi)).all(axis=1))[0]  # others are far outside
    if near.size:
        # faces bucketed in a grid over the cage's box: each point tests a few faces only
        cells = int(np.clip(round(2 * len(f) ** (1 / 3)), 1, 64))
        size = np.maximum((hi - lo) / cells, 1e-300)
        tri = v[f]
        first = np.clip(((tri.min(axis=1) - tol - lo) / size).astype(np.int64), 0, cells - 1)
        last = np.clip(((tri.max(axis=1) + tol - lo) / size).astype(np.int64), 0, cells - 1)
        start, members = _face_grid(first, last, cells)
        cell = np.clip(((p[near] - lo) / size).astype(np.int64), 0, cells - 1)
        out = np.full(near.size, -1, dtype=np.int64)
        pts = p[near]
        run_rows(_surface_host_kernel, len(pts), pts, v, f, cell, start, members, cells, tol, out)
        host[near] = out
    return host


def _face_grid(first, last, cells):
    """CSR lists of the faces whose (grown) boxes overlap each grid cell."""
    pairs = []
    for t in range(len(first)):
        ix, iy, iz = (np.arange(first[t, a], last[t, a] + 1) for a in range(3))
        ids = (ix[:, None, None] * cells + iy[None, :, None]) * cells + iz[None, None, :]
        pairs.append(np.column_stack([ids.ravel(), np.full(ids.size, t)]))
    pairs = np.concatenate(pairs)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]  # by cell, then face index
    start = np.searchsorted(pairs[:, 0], np.arange(cells**3 + 1))
    return start.astype(np.int64), np.ascontiguousarray(pairs[:, 1])


@numba.njit(cache=True, nogil=True)
def _surface_host_kernel(  # pragma: no cover - compiled
    start, stop, points, V, F, cell, cell_start, members, cells, tol, host
):
    tol2 = tol * tol
    for k in range(start, stop):
        c = (cell[k, 0] * cells + cell[k, 1]) * cells + cell[k, 2]
        found = -1
        for s in range(cell_start[c], cell_start[c + 1]):
            t = members[s]  # ascending: the lowest-numbered face within reach is the host
            d2 = point_triangle_distance2(points[k], V[F[t, 0]], V[F[t, 1]], V[F[t, 2]])
            if d2 <= tol2:
                found = t
                break
        host[k] = found


#: Points on the surface that rounding put outside are evaluated this many
#: :func:`on_surface_tolerance` inside (see :func:`surface_points_inside`).
_PULL_IN = 8.0


def surface_points_inside(points, hosts, vertices, faces) -> np.ndarray:
    """Where to evaluate points on the cage surface that rounding put outside.

    Such a point (``hosts >= 0``, :func:`classify_inside`) is moved ``8 x``
    :func:`on_surface_tolerance` inside, against the summed normals of the faces within
    reach (one face; two or more next to an edge or a vertex, where one face's normal
    could lead out through the other). The map is continuous up to the cage from inside,
    so its value there is the interior limit to ~1e-11 of the diagonal times the size of
    the Jacobian -- also next to edges and vertices, where the host face's own limit alone
    would mix interior and exterior parts.

    Returns
    -------
    (N, 3) float64
        ``points`` with the host rows moved (a copy).
    """
    p = as_points(points).copy()
    rows = np.nonzero(np.asarray(hosts) >= 0)[0]
    if rows.size:
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        tol = on_surface_tolerance(v)
        normals, _ = face_normals_and_areas(v, f)
        direction = np.zeros((rows.size, 3))
        _reach_normals(p[rows], v, f, normals, 2.0 * tol, direction)
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        p[rows] -= _PULL_IN * tol * direction
    return p


@numba.njit(cache=True)
def _reach_normals(points, V, F, normals, reach, out):  # pragma: no cover - compiled
    """Sum of the normals of the faces within ``reach`` of each point (few points: serial)."""
    r2 = reach * reach
    for k in range(points.shape[0]):
        for t in range(F.shape[0]):
            if point_triangle_distance2(points[k], V[F[t, 0]], V[F[t, 1]], V[F[t, 2]]) <= r2:
                out[k, 0] += normals[t, 0]
                out[k, 1] += normals[t, 1]
                out[k, 2] += normals[t, 2]


def classify_inside(
    points, vertices, faces, winding=None, undefined=None
) -> tuple[np.ndarray, np.ndarray]:
    """The one inside test: inside the cage, or on its surface.

    A point is inside when its winding number is at least 1/2 (:func:`inside_cage`), or
    when it lies within :func:`on_surface_tolerance` of a face: points computed on the
    cage surface land a few ulps to either side of it. Points on the surface get a host
    face and are evaluated just inside (:func:`surface_points_inside`): those the winding
    number puts outside, and those where an evaluation's derivatives are undefined (on a
    cage edge or at a vertex, whatever side the winding number gives them).

    Parameters
    ----------
    points : (N, 3) array_like
    vertices, faces : cage arrays
    winding : (N,) array_like, optional
        Winding numbers already computed (the sum of the ``phi`` columns).
    undefined : (N,) array_like of bool, optional
        Rows whose derivatives an evaluation found non-finite.

    Returns
    -------
    inside : (N,) bool
    hosts : (N,) int64
        The host face of points on the surface that the winding number put outside or
        whose derivatives are undefined; -1 for every other point.
    """
    p = as_points(points)
    w = winding_number(p, vertices, faces) if winding is None else np.asarray(winding)
    inside = inside_cage(w)
    hosts = np.full(len(p), -1, dtype=np.int64)
    test = ~inside if undefined is None else ~inside | np.asarray(undefined, dtype=bool)
    rows = np.nonzero(test)[0]
    if rows.size:
        hosts[rows] = surface_hosts(p[rows], vertices, faces)
        inside[rows] |= hosts[rows] >= 0
    return inside, hosts


def winding_number(points, vertices, faces, *, backend: str = "numba") -> np.ndarray:
    """Generalised winding number of a closed cage at points (``sum_v phi_v``).

    Parameters
    ----------
    points : (N, 3) array_like
    vertices, faces : (n, 3) array_like, (m, 3) array_like of int
        The closed cage, its triangles outward-oriented.
    backend : {"numba", "numpy"}

    Returns
    -------
    (N,) ndarray
        1 inside, 0 outside (up to rounding); 1/2 exactly on a face.
    """
    p = as_points(points)
    v = read_only(np.ascontiguousarray(vertices, dtype=np.float64))
    f = read_only(np.ascontiguousarray(faces, dtype=np.int64))
    if backend == "numba":
        out = np.zeros(p.shape[0])
        if p.shape[0]:
            run_rows(winding_kernel, p.shape[0], read_only(p), v, f, out, grain=ROWS_GRAIN)
        return out
    if backend != "numpy":
        raise ValueError(f"backend must be 'numba' or 'numpy'; got {backend!r}")
    out = np.empty(p.shape[0])
    x = v[f]
    for s in range(0, p.shape[0], NUMPY_CHUNK):
        e = x[None] - p[s : s + NUMPY_CHUNK, None, None, :]
        le = np.linalg.norm(e, axis=-1)
        e0, e1, e2 = e[:, :, 0], e[:, :, 1], e[:, :, 2]
        l0, l1, l2 = le[..., 0], le[..., 1], le[..., 2]
        det = np.einsum("...i,...i->...", e0, np.cross(e1, e2))
        den = (
            l0 * l1 * l2
            + np.einsum("...i,...i->...", e0, e1) * l2
            + np.einsum("...i,...i->...", e0, e2) * l1
            + np.einsum("...i,...i->...", e1, e2) * l0
        )
        w = np.arctan2(det, den) / _TWO_PI
        w = np.where((det == 0.0) & (den < 0.0), 0.5, np.where((det == 0.0) & (den == 0.0), 0.0, w))
        out[s : s + NUMPY_CHUNK] = w.sum(axis=1)
    return out


def classify_points(points, vertices, faces, *, tolerance: float = 1e-9) -> np.ndarray:
    """Classify points against a cage: inside, outside or on its surface.

    Parameters
    ----------
    points : (N, 3) array_like
    vertices, faces : cage arrays
    tolerance : float
        Winding numbers within ``tolerance`` of 1 count as inside, within it of 0 as
        outside; anything else (points on or within rounding of the surface) as surface.

    Returns
    -------
    (N,) int8 ndarray
        ``1`` inside, ``0`` outside, ``-1`` on (or numerically at) the cage surface.
    """
    wn = winding_number(points, vertices, faces)
    out = np.full(wn.shape, -1, dtype=np.int8)
    out[np.abs(wn - 1.0) <= tolerance] = 1
    out[np.abs(wn) <= tolerance] = 0
    return out
