"""Closed-form harmonic cage basis: phi_v, psi_t, their gradients and Hessians.

The harmonic map of a closed, outward-oriented triangle cage (vertices ``x_v``, faces ``t``)
is ``f(p) = sum_v a_v phi_v(p) + sum_t b_t psi_t(p)`` (paper Section 2.1). ``phi_v`` is the
double-layer potential of the hat function of vertex ``v`` and ``psi_t`` the (positive)
single-layer potential of face ``t``; both have closed forms (Urago 2000, as in the paper's
Appendix A).

Layout of every result, for ``N`` points, ``n`` cage vertices and ``m`` faces (``n + m``
columns, vertex functions first):

* ``values``    ``(N, n + m)``
* ``gradients`` ``(N, 3, n + m)``, ``gradients[k, j, c] = d basis_c / d x_j`` at point ``k``
* ``hessians``  ``(N, 5, n + m)``, the five independent entries ``(xx, xy, xz, yy, yz)`` of
  the symmetric, traceless Hessian (``zz = -xx - yy``); :func:`hessian5_to_full` expands them.

Boundary behaviour (documented and tested):

* Points arbitrarily close to the cage are accurate: ``R - |d|`` of the edge terms is
  computed without cancellation (see :mod:`vhm_viz.core.basis_reference`).
* Points exactly on a face interior get the **interior limit** (the host face's solid angle
  counts as +1/2). It is detected when the point is exactly in the face's plane, or forced by
  ``host_faces`` -- use that for samples generated on faces, whose rounding puts them on
  either side of the plane.
* Points exactly on a cage edge or vertex get the interior-limit *values*; the derivatives of
  individual basis functions diverge there (logarithmically), so their gradients and Hessians
  are NaN. Such points are reported by :func:`classify_points`.
* Outside the cage the formulas still give a harmonic function, but not the deformation the
  user set up: the winding number (``sum_v phi_v``) is 0 there. :func:`winding_number`
  detects it; :class:`~vhm_viz.core.harmonic_map.HarmonicMap` refuses such points by default.

Three implementations: a plain numpy reference that follows the formulas face by face
(:mod:`vhm_viz.core.basis_reference`, readable, used by the tests); a numba per-point
kernel that shares the per-vertex distances and per-edge logarithms between neighbouring
faces and handles every special position (:mod:`vhm_viz.core.basis_kernel`); and, for
values and gradients of points away from the cage edges (nearly all points of a shape),
the SIMD kernel of :mod:`vhm_viz.core.basis_lanes`, 16 points at a time.
:func:`evaluate_basis` picks between the two compiled kernels point by point; the tests
hold all three to each other.

This module is the public face of the basis: the evaluation (:func:`evaluate_basis`,
:func:`evaluate_map`, :func:`evaluate_inside`), the memory bound of a chunk
(:func:`chunk_rows`), the domains of a cage of several shells (:func:`domain_columns`),
and, re-exported from :mod:`vhm_viz.core.inside`, the one inside test.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vhm_viz.core.basis_kernel import NEAR_EDGE, compiled_evaluation, per_point_evaluation
from vhm_viz.core.basis_lanes import ROWS_GRAIN, lanes_map_kernel
from vhm_viz.core.basis_reference import NUMPY_CHUNK, evaluate_reference
from vhm_viz.core.cage_tables import (
    CageTables,
    kernel_arrays,
    prepare_cage,
    read_only,
    separate_shells,
    shell_cages,
)
from vhm_viz.core.components import edge_components
from vhm_viz.core.devices import require_device
from vhm_viz.core.inside import (
    ON_SURFACE_RTOL,
    WINDING_TOLERANCE,
    classify_inside,
    classify_points,
    inside_cage,
    on_surface_tolerance,
    surface_hosts,
    surface_points_inside,
    winding_number,
)
from vhm_viz.core.limits import check_setting
from vhm_viz.core.points import as_points
from vhm_viz.core.row_threads import run_rows

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "HESSIAN_COMPONENTS",
    "ON_SURFACE_RTOL",
    "WINDING_TOLERANCE",
    "BasisEvaluation",
    "chunk_rows",
    "classify_inside",
    "classify_points",
    "domain_columns",
    "evaluate_basis",
    "evaluate_inside",
    "evaluate_map",
    "hessian5_to_full",
    "inside_cage",
    "on_surface_tolerance",
    "surface_hosts",
    "surface_points_inside",
    "winding_number",
]

HESSIAN_COMPONENTS = ("xx", "xy", "xz", "yy", "yz")
#: Working memory one chunk of basis evaluation may use (bytes), unless the caller says.
DEFAULT_MEMORY_BUDGET = 64 * 2**20


class BasisEvaluation(NamedTuple):
    """Basis functions (and optionally derivatives) at a set of points.

    Attributes
    ----------
    values : (N, n + m) float64
        ``phi_v`` for the ``n`` cage vertices, then ``psi_t`` for the ``m`` faces.
    gradients : (N, 3, n + m) float64 or None
        Gradients, ``gradients[k, j, c] = d basis_c / d x_j``.
    hessians : (N, 5, n + m) float64 or None
        Hessian entries ``(xx, xy, xz, yy, yz)``.
    """

    values: np.ndarray
    gradients: np.ndarray | None
    hessians: np.ndarray | None


def hessian5_to_full(h5: np.ndarray) -> np.ndarray:
    """Expand the five independent Hessian entries into full symmetric 3x3 matrices.

    Parameters
    ----------
    h5 : (..., 5) array
        Entries ``(xx, xy, xz, yy, yz)``.

    Returns
    -------
    (..., 3, 3) ndarray
        Symmetric, traceless matrices (``zz = -xx - yy``).
    """
    h5 = np.asarray(h5)
    xx, xy, xz, yy, yz = (h5[..., i] for i in range(5))
    zz = -xx - yy
    rows = [np.stack(r, axis=-1) for r in ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))]
    return np.stack(rows, axis=-2)


def evaluate_basis(
    points,
    vertices,
    faces,
    *,
    order: int = 0,
    host_faces=None,
    backend: str = "numba",
    chunk_size: int | None = None,
) -> BasisEvaluation:
    """Evaluate the harmonic cage basis (and its derivatives) at points.

    Parameters
    ----------
    points : (N, 3) array_like
        Evaluation points (same length unit as the cage).
    vertices : (n, 3) array_like
        Cage vertices.
    faces : (m, 3) array_like of int
        Cage triangles, oriented with outward normals (validate with ``Cage`` first).
    order : {0, 1, 2}
        0: values; 1: values and gradients; 2: values, gradients and Hessians.
    host_faces : (N,) array_like of int, optional
        For points lying exactly on a cage face: that face's index (``-1`` for other points).
        The host face then contributes its interior limit (solid angle 1/2, distance 0),
        which makes samples generated on the faces immune to rounding.
    backend : {"numba", "numpy"}
        The compiled kernels (default) or the plain numpy reference.
    chunk_size : int, optional
        Points per chunk (in [1, 1e7]) for the numpy reference (bounds its temporaries, which are
        ``O(chunk_size * m)``). The numba kernels need no temporaries beyond the output
        (and a scratch per thread that grows with the cage, not with the points).

    Returns
    -------
    BasisEvaluation
        ``values (N, n+m)``, ``gradients (N, 3, n+m)`` or None, ``hessians (N, 5, n+m)``
        or None. Rows of points exactly on a cage edge or vertex hold the interior-limit
        values and NaN derivatives (the individual basis functions are not differentiable
        there).

    Notes
    -----
    Memory of the result is ``8 * N * (n + m) * (1 + 3 [order>=1] + 5 [order>=2])`` bytes;
    to apply a map to millions of points use ``HarmonicMap``, which works in chunks.
    """
    if order not in (0, 1, 2):
        raise ValueError(f"order must be 0, 1 or 2; got {order!r}")
    p = as_points(points)
    cd = prepare_cage(vertices, faces)
    npts = p.shape[0]
    m = cd.faces.shape[0]
    host = _host_array(host_faces, npts, m)
    if backend == "numba":
        values, gradients, hessians, degenerate = compiled_evaluation(p, cd, order, host)
    elif backend == "numpy":
        chunk = NUMPY_CHUNK if chunk_size is None else check_setting("chunk_size", chunk_size)
        values, gradients, hessians, degenerate = evaluate_reference(p, cd, order, host, chunk)
    else:
        raise ValueError(f"backend must be 'numba' or 'numpy'; got {backend!r}")
    if degenerate.any():
        _fix_edge_and_vertex_points(p, cd, np.nonzero(degenerate)[0], values, gradients, hessians)
    if cd.shells:
        separate_shells(cd, values, gradients, hessians)
    return BasisEvaluation(values, gradients, hessians)


def evaluate_map(points, vertices, faces, coefficients, *, order: int = 1, device: str = "cpu"):
    """A map ``f = sum_v a_v phi_v + sum_t b_t psi_t`` and its Jacobian, without the basis.

    The same numbers as ``evaluate_basis(...).values @ coefficients`` (and the gradients),
    but the basis of each group of points is contracted with the coefficients inside the
    kernel: nothing of size ``(N, n + m)`` is stored, which makes it several times faster
    for large cages. Points near a cage edge go through the careful per-point kernel, as
    in :func:`evaluate_basis`. A cage of several outward shells is evaluated shell by
    shell: each point keeps the shells that contain it (and the hole shells), as in
    :func:`evaluate_basis`.

    Parameters
    ----------
    points : (N, 3) array_like
    vertices : (n, 3) array_like
    faces : (m, 3) array_like of int
        Outward-oriented cage triangles.
    coefficients : (n + m, 3) array_like
        ``z = [a; b]``.
    order : {0, 1}
        Values only, or values and Jacobians.
    device : {"cpu", "cuda"}
        Where the points away from the cage edges are evaluated: the CPU kernel, or the
        GPU (:mod:`vhm_viz.core.cuda_map`; :class:`~vhm_viz.core.errors.DeviceUnavailableError`
        without one). Points near an edge always take the per-point CPU kernel.

    Returns
    -------
    values : (N, 3) ndarray
    jacobians : (N, 3, 3) ndarray or None
        ``J[k, i, j] = d f_i / d x_j`` (NaN on a cage edge or vertex).
    winding : (N,) ndarray
        The winding number (sum of the vertex functions), for :func:`inside_cage`.
    """
    if order not in (0, 1):
        raise ValueError(f"order must be 0 or 1; got {order!r}")
    require_device(device)
    p = as_points(points)
    cd = prepare_cage(vertices, faces)
    z = np.ascontiguousarray(coefficients, dtype=np.float64)
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    if z.shape != (n + m, 3):
        raise ValueError(f"coefficients must have shape ({n + m}, 3); got {z.shape}")
    npts = p.shape[0]
    if npts == 0:
        return np.zeros((0, 3)), (np.zeros((0, 3, 3)) if order else None), np.zeros(0)
    if not cd.shells:
        return _evaluate_map_one(p, cd, z, order, device)
    # Several outward shells: a shell's basis functions involve its own faces only, so
    # each shell is a cage of its own for the fused kernel. A point keeps the shells whose
    # own winding number puts it inside (the rule of separate_shells) and every hole
    # shell. Each face is evaluated once per point, as for one shell, and no basis matrix
    # is stored.
    values = np.zeros((npts, 3))
    jac = np.zeros((npts, 3, 3)) if order else None
    winding = np.zeros(npts)
    for cols, sub, every_point in shell_cages(cd):
        v_s, j_s, w_s = _evaluate_map_one(p, sub, np.ascontiguousarray(z[cols]), order, device)
        keep = slice(None) if every_point else w_s >= 0.5
        values[keep] += v_s[keep]
        winding[keep] += w_s[keep]
        if order:
            jac[keep] += j_s[keep]
    return values, jac, winding


def _evaluate_map_one(p, cd: CageTables, z, order: int, device: str = "cpu"):
    """:func:`evaluate_map` for a cage of one outward shell (and any holes)."""
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    npts = p.shape[0]
    kernel_args = kernel_arrays(cd)
    if device == "cuda":
        from vhm_viz.core.cuda_map import map_on_gpu  # imports numba.cuda: only on request

        values, jac, winding, flagged = map_on_gpu(p, kernel_args, NEAR_EDGE, order, z)
    else:
        values = np.empty((npts, 3))
        jac = np.empty((npts, 3, 3)) if order else np.zeros((0, 3, 3))
        winding = np.empty(npts)
        flagged = np.zeros(npts, dtype=np.bool_)
        run_rows(
            lanes_map_kernel, npts, read_only(p), *kernel_args, NEAR_EDGE, order,
            read_only(z), values, jac, winding, flagged, grain=ROWS_GRAIN,
        )  # fmt: skip
    rows = np.nonzero(flagged)[0]
    if rows.size:
        host = np.full(rows.size, -1, dtype=np.int64)
        vals, grads, _, degenerate = per_point_evaluation(p[rows], cd, order, host)
        if degenerate.any():
            _fix_edge_and_vertex_points(p[rows], cd, np.nonzero(degenerate)[0], vals, grads, None)
        values[rows] = vals @ z
        winding[rows] = vals[:, :n].sum(axis=1)
        if order:
            jac[rows] = np.swapaxes((grads.reshape(-1, n + m) @ z).reshape(rows.size, 3, 3), 1, 2)
    return values, (jac if order else None), winding


def _host_array(host_faces, npts: int, m: int) -> np.ndarray | None:
    if host_faces is None:
        return np.full(npts, -1, dtype=np.int64)
    host = np.ascontiguousarray(host_faces, dtype=np.int64).ravel()
    if host.shape[0] != npts:
        raise ValueError(f"host_faces must have one entry per point ({npts}); got {host.shape[0]}")
    if (host >= m).any() or (host < -1).any():
        raise ValueError(f"host_faces entries must be -1 or a face index < {m}")
    return host


def _fix_edge_and_vertex_points(p, cd: CageTables, rows, values, gradients, hessians) -> None:
    """Interior-limit values at points exactly on a cage edge or vertex.

    The kernels drop the solid angle and the (divergent) edge terms of the faces that
    contain such a point; the double layer's jump is then restored as ``c * Gamma_v(p)`` with
    ``c = 1 - sum_t w_t`` (the interior solid-angle fraction, so that the winding number is 1)
    and ``Gamma_v`` the hat functions at ``p`` on the edge or vertex.
    """
    n = cd.vertices.shape[0]
    for k in rows:
        x = p[k]
        dist = np.linalg.norm(cd.vertices - x, axis=1)
        gamma = np.zeros(n)
        hit = np.nonzero(dist == 0.0)[0]
        if hit.size:
            gamma[hit[0]] = 1.0
        else:
            a, b = cd.vertices[cd.edges[:, 0]] - x, cd.vertices[cd.edges[:, 1]] - x
            on = (np.linalg.norm(np.cross(a, b), axis=1) == 0.0) & (
                np.einsum("ij,ij->i", a, b) <= 0
            )
            q = np.nonzero(on)[0]
            if q.size == 0:  # pragma: no cover - kernel and this test agree by construction
                continue
            i, j = cd.edges[q[0]]
            gamma[i] = dist[j] / cd.edge_length[q[0]]
            gamma[j] = dist[i] / cd.edge_length[q[0]]
        c = 1.0 - values[k, :n].sum()
        values[k, :n] += c * gamma
        if gradients is not None:
            gradients[k] = np.nan
        if hessians is not None:
            hessians[k] = np.nan


#: Tolerance on the winding number for "inside the cage". Points on the cage surface have
#: winding number exactly 1/2 and count as inside; the winding number jumps from 0 to 1
#: across the surface (it does not pass through 1/2), so points even 1e-9 off the surface


def evaluate_inside(points, vertices, faces, *, order: int = 0):
    """:func:`evaluate_basis` together with the one inside test.

    Points on the cage surface that rounding put outside, and those on an edge or at a
    vertex, where the derivatives are undefined, are evaluated just inside
    (:func:`surface_points_inside`), so the surface belongs to the inside consistently.

    Returns
    -------
    basis : BasisEvaluation
        Rows of points outside the cage hold the (meaningless) exterior values.
    inside : (N,) bool
    """
    b = evaluate_basis(points, vertices, faces, order=order)
    n = len(vertices)
    undefined = None if b.gradients is None else ~np.isfinite(b.gradients).all(axis=(1, 2))
    inside, hosts = classify_inside(
        points, vertices, faces, b.values[:, :n].sum(axis=1), undefined
    )
    on = np.nonzero(hosts >= 0)[0]
    if on.size:
        p = surface_points_inside(points, hosts, vertices, faces)[on]
        again = evaluate_basis(p, vertices, faces, order=order)
        for whole, part in zip(b, again, strict=True):
            if whole is not None:
                whole[on] = part
    return b, inside


def chunk_rows(n_columns: int, order: int = 0, memory_budget: int | None = None) -> int:
    """Points per chunk so that one chunk's basis arrays fit in ``memory_budget`` bytes.

    A chunk holds the values (``n_columns`` per point), gradients (3 x) and Hessians (5 x)
    up to ``order``, each once more for the product with the caller's coefficients.

    Parameters
    ----------
    n_columns : int
        Basis functions (cage vertices plus faces).
    order : {0, 1, 2}
    memory_budget : int, optional
        Bytes, in [1, 2**40]; default :data:`DEFAULT_MEMORY_BUDGET`.

    Returns
    -------
    int
        At least 16 (one SIMD group of the kernel).
    """
    budget = DEFAULT_MEMORY_BUDGET
    if memory_budget is not None:
        budget = check_setting("memory_budget", memory_budget)
    per_point = (1 + 3 * (order >= 1) + 5 * (order >= 2)) * max(int(n_columns), 1) * 8 * 2
    return max(16, budget // per_point)


def domain_columns(vertices, faces) -> tuple[np.ndarray, ...]:
    """Basis columns of each separate domain of a cage (one per outward shell).

    A cage of several disjoint outward shells bounds several separate domains, and by
    Green's third identity the map inside one of them depends only on that shell's
    coefficients (and those of the inward hole shells inside it; paper Figure 11), so a
    solver can tell which coefficients each domain owns.

    Parameters
    ----------
    vertices, faces : (n, 3) array_like, (m, 3) array_like of int
        The outward-oriented cage, as for :func:`~vhm_viz.core.cage_tables.prepare_cage`.

    Returns
    -------
    tuple of int64 arrays
        Column ids (vertex ``v`` is column ``v``, face ``t`` column ``n + t``), one array
        per outward shell in the order of ``CageTables.shells``; a single array of all
        ``n + m`` columns for a cage of one outward shell. A hole shell belongs to the
        outward shell whose winding number is 1 on it.
    """
    cd = prepare_cage(vertices, faces)
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    if not cd.shells:
        return (np.arange(n + m, dtype=np.int64),)
    cols = [list(np.concatenate([vids, n + fids])) for vids, fids in cd.shells]
    owned = np.zeros(n + m, dtype=bool)
    for c in cols:
        owned[c] = True
    hole_faces = np.flatnonzero(~owned[n:])
    if len(hole_faces):
        f = cd.faces[hole_faces]
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
        _, labels = edge_components(n, e)
        for lab in np.unique(labels[f[:, 0]]):
            fids = hole_faces[labels[f[:, 0]] == lab]
            vids = np.unique(cd.faces[fids])
            probe = cd.vertices[vids[:1]]
            for k, (_, shell_faces) in enumerate(cd.shells):
                if winding_number(probe, cd.vertices, cd.faces[shell_faces])[0] > 0.5:
                    cols[k].extend(np.concatenate([vids, n + fids]).tolist())
                    break
    return tuple(np.unique(np.asarray(c, dtype=np.int64)) for c in cols)
