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
  computed without cancellation (see ``_edge_terms_numpy``).
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
(readable, used by the tests); a numba per-point kernel (``parallel=True``, ``cache=True``)
that shares the per-vertex distances and per-edge logarithms between neighbouring faces and
handles every special position; and, for values and gradients of points away from the cage
edges (nearly all points of a shape), the SIMD kernel of :mod:`vhm_viz.core.basis_lanes`,
16 points at a time, about 3x faster. :func:`evaluate_basis` picks between the two compiled
kernels point by point; the tests hold all three to each other.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numba
import numpy as np
import scipy.sparse as sp

from vhm_viz.core.basis_lanes import lanes_kernel, lanes_map_kernel, winding_kernel
from vhm_viz.core.geometry import face_normals_and_areas

HESSIAN_COMPONENTS = ("xx", "xy", "xz", "yy", "yz")
_FOUR_PI = 4.0 * math.pi
_TWO_PI = 2.0 * math.pi
# Default number of points per chunk of the numpy reference (bounds its temporaries).
_NUMPY_CHUNK = 256


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


# --------------------------------------------------------------------------------------
# cage preprocessing shared by both backends
# --------------------------------------------------------------------------------------
class _CageData(NamedTuple):
    vertices: np.ndarray  # (n, 3)
    faces: np.ndarray  # (m, 3) int64
    normals: np.ndarray  # (m, 3)
    twice_area: np.ndarray  # (m,)
    d: np.ndarray  # (m, 3, 3): d[t, v] = x_{v+1} - x_{v+2}, edge opposite local vertex v
    n_cross_d: np.ndarray  # (m, 3, 3): N_t x d[t, v]
    edges: np.ndarray  # (E, 2) unique undirected edges
    edge_length: np.ndarray  # (E,)
    face_edges: np.ndarray  # (m, 3) index of the edge opposite local vertex v
    face_edge_sign: np.ndarray  # (m, 3) +1 if edges[..] = (v+1, v+2) in that order, else -1
    shells: tuple  # ((vertex ids, face ids), ...) of outward shells; empty for one shell


def _prepare_cage(vertices: np.ndarray, faces: np.ndarray) -> _CageData:
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(
            f"cage vertices must be (n, 3) and faces (m, 3); got {v.shape} and {f.shape}"
        )
    # Maps and bindings evaluate the same cage chunk after chunk: keyed on the arrays'
    # contents, the edge table, normals and shells (~1.5 ms for 500 faces) are built once.
    return _prepare_cage_cached(v.shape, v.tobytes(), f.shape, f.tobytes())


@functools.lru_cache(maxsize=8)
def _prepare_cage_cached(vshape, vbytes, fshape, fbytes) -> _CageData:
    v = np.frombuffer(vbytes, dtype=np.float64).reshape(vshape)
    f = np.frombuffer(fbytes, dtype=np.int64).reshape(fshape)
    normals, areas = face_normals_and_areas(v, f)
    x = v[f]  # (m, 3 corners, 3)
    d = np.stack([x[:, (i + 1) % 3] - x[:, (i + 2) % 3] for i in range(3)], axis=1)
    n_cross_d = np.cross(normals[:, None, :], d)
    # edge opposite local vertex i joins corners i+1 and i+2
    a = np.stack([f[:, (i + 1) % 3] for i in range(3)], axis=1)
    b = np.stack([f[:, (i + 2) % 3] for i in range(3)], axis=1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys = np.stack([lo.ravel(), hi.ravel()], axis=1)
    edges, inverse = np.unique(keys, axis=0, return_inverse=True)
    face_edges = inverse.reshape(f.shape).astype(np.int64)
    face_edge_sign = np.where(a == lo, 1.0, -1.0)
    edge_length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    return _CageData(
        v,
        f,
        normals,
        2.0 * areas,
        np.ascontiguousarray(d),
        np.ascontiguousarray(n_cross_d),
        np.ascontiguousarray(edges.astype(np.int64)),
        edge_length,
        face_edges,
        face_edge_sign,
        _outward_shells(v, f, edges),
    )


def _outward_shells(v: np.ndarray, f: np.ndarray, edges: np.ndarray) -> tuple:
    """Vertex and face ids of each outward shell of a cage made of several shells.

    A cage of several disjoint outward shells bounds several separate domains, and by
    Green's third identity the map inside one of them needs only that shell's basis
    functions (plus inward "hole" shells, which are kept for every point). Evaluating the
    other shells' potentials there would couple parts of the shape that the cage
    separates (paper Figure 11), so :func:`evaluate_basis` zeroes them. Returns ``()``
    for a single shell (nothing to separate).
    """
    import scipy.sparse.csgraph as csgraph

    n = len(v)
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    count, labels = csgraph.connected_components(graph, directed=False)
    used = np.unique(f)
    shell_ids = np.unique(labels[used])
    if len(shell_ids) < 2:
        return ()
    face_label = labels[f[:, 0]]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c))
    shells = []
    for k in shell_ids:
        faces_k = np.nonzero(face_label == k)[0]
        if vol[faces_k].sum() > 0:  # outward shell: a separate domain
            shells.append((np.nonzero(labels == k)[0], faces_k))
    return tuple(shells) if len(shells) > 1 else ()


def _separate_shells(cd: _CageData, values, gradients, hessians) -> None:
    """Zero, for each point, the basis functions of outward shells that do not contain it."""
    n = cd.vertices.shape[0]
    for vids, fids in cd.shells:
        outside = values[:, vids].sum(axis=1) < 0.5  # this shell's own winding number
        if not outside.any():
            continue
        rows = np.nonzero(outside)[0]
        cols = np.concatenate([vids, n + fids])
        for arr in (values, gradients, hessians):
            if arr is not None:
                arr[np.ix_(rows, *([np.arange(arr.shape[1])] if arr.ndim == 3 else []), cols)] = 0.0


# --------------------------------------------------------------------------------------
# numpy reference (face by face, no sharing between faces)
# --------------------------------------------------------------------------------------
def _edge_terms_numpy(u, q, lu, lq, dlen):
    """``C`` and ``Ct`` of an edge with end vectors ``u``, ``q`` (cancellation-free)."""
    uq = np.einsum("...i,...i->...", u, q)
    cr = np.cross(u, q)
    cr2 = np.einsum("...i,...i->...", cr, cr)
    big = lu + lq + dlen
    with np.errstate(divide="ignore", invalid="ignore"):
        # when u.q <= 0 (p next to the segment) R - |d| cancels: use the exact rewrite
        # R - |d| = 2 (l_u l_q + u.q) / (R + |d|), and when u.q <= 0 the bracket itself
        # cancels: l_u l_q + u.q = |u x q|^2 / (l_u l_q - u.q). Both branches are exact.
        small = np.where(uq <= 0.0, 2.0 * cr2 / ((lu * lq - uq) * big), 2.0 * (lu * lq + uq) / big)
        on_edge = small <= 0.0
        c = np.where(on_edge, 0.0, np.log1p(2.0 * dlen / small) / (_FOUR_PI * dlen))
        ct = np.where(on_edge, 0.0, 1.0 / (_TWO_PI * big * small))
    return c, ct, on_edge


def _basis_numpy_chunk(p, cd: _CageData, order: int, host):
    npts = p.shape[0]
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    x = cd.vertices[cd.faces]  # (m, 3, 3)
    e = x[None, :, :, :] - p[:, None, None, :]  # (N, m, 3, 3)
    le = np.linalg.norm(e, axis=-1)  # (N, m, 3)
    e0 = e[:, :, 0]
    dot = lambda a, b: np.einsum("...i,...i->...", a, b)  # noqa: E731
    C, Ct, Jv = [], [], []
    degenerate = np.zeros(npts, dtype=bool)
    for v in range(3):
        u, q = e[:, :, (v + 1) % 3], e[:, :, (v + 2) % 3]
        lu, lq = le[:, :, (v + 1) % 3], le[:, :, (v + 2) % 3]
        c, ct, on_edge = _edge_terms_numpy(u, q, lu, lq, np.linalg.norm(cd.d[:, v], axis=-1)[None])
        degenerate |= on_edge.any(axis=1)
        C.append(c)
        Ct.append(ct)
        Jv.append(np.cross(q, u))  # e_{v+2} x e_{v+1}
    near = _solid_angle_pivot(e, le, np.argmax(np.stack(C, -1), axis=-1), cd.d)
    det, denom = _solid_angle_terms(e, le, near, cd.d)
    w = np.arctan2(det, denom) / _TWO_PI
    in_plane = det == 0.0
    w = np.where(in_plane & (denom < 0.0), 0.5, w)  # exactly on the face: interior limit
    w = np.where(in_plane & (denom == 0.0), 0.0, w)  # on an edge/vertex: see fix-up
    h_dist = dot(e0, cd.normals[None])  # signed distance to the plane (inside > 0)
    if host is not None:
        rows = np.nonzero(host >= 0)[0]
        w[rows, host[rows]] = 0.5
        h_dist[rows, host[rows]] = 0.0

    N = cd.normals[None]  # (1, m, 3)
    P = -w[..., None] * N
    for v in range(3):
        P = P + C[v][..., None] * cd.n_cross_d[None, :, v]
    psi = -w * h_dist - sum(C[v] * dot(Jv[v], N) for v in range(3))

    nm = n + m
    values = np.zeros((npts, nm))
    values[:, n:] = psi
    incid = [
        sp.csr_matrix((np.ones(m), (np.arange(m), cd.faces[:, v])), shape=(m, n)) for v in range(3)
    ]
    inv2a = 1.0 / cd.twice_area[None]
    for v in range(3):
        values[:, :n] += (incid[v].T @ (dot(P, Jv[v]) * inv2a).T).T
    gradients = hessians = None
    if order >= 1:
        gradients = np.zeros((npts, 3, nm))
        gradients[:, :, n:] = -np.moveaxis(P, 2, 1)
        for v in range(3):
            g = np.cross(P, cd.d[None, :, v]) * inv2a[..., None]  # (N, m, 3)
            for j in range(3):
                gradients[:, j, :n] += (incid[v].T @ g[:, :, j].T).T
    if order >= 2:
        with np.errstate(divide="ignore", invalid="ignore"):
            ehat = np.where(le[..., None] > 0, e / le[..., None], 0.0)
            inv_le = np.where(le > 0, 1.0 / le, 0.0)
        grad_w = sum(
            (Ct[v] * (inv_le[:, :, (v + 1) % 3] + inv_le[:, :, (v + 2) % 3]))[..., None] * Jv[v]
            for v in range(3)
        )
        Q = sum(
            (Ct[v][..., None] * (ehat[:, :, (v + 1) % 3] + ehat[:, :, (v + 2) % 3]))[..., :, None]
            * cd.d[None, :, v][..., None, :]
            for v in range(3)
        )
        nx = _cross_matrix(cd.normals)  # (m, 3, 3)
        M = Q @ np.swapaxes(nx, -1, -2)[None] + grad_w[..., :, None] * N[..., None, :]
        hessians = np.zeros((npts, 5, nm))
        hessians[:, :, n:] = np.moveaxis(_sym5(-M), -1, 1)
        dx = _cross_matrix(cd.d.reshape(-1, 3)).reshape(m, 3, 3, 3)
        for v in range(3):
            hv = -(dx[None, :, v] @ M) * inv2a[..., None, None]
            h5 = _sym5(hv)  # (N, m, 5)
            for j in range(5):
                hessians[:, j, :n] += (incid[v].T @ h5[:, :, j].T).T
    return values, gradients, hessians, degenerate


def _solid_angle_pivot(e, le, opposite_nearest_edge, d):
    """Local vertex to write the solid angle around (see :func:`_solid_angle_terms`).

    Next to an edge's interior, pivot on the vertex opposite that edge; next to a vertex
    (closer to it than twice the distance to the nearest edge's line), pivot on the vertex
    itself, where the plain formula has no cancellation but the edge rewrite would.
    """
    a = opposite_nearest_edge
    take = lambda arr, k: np.take_along_axis(arr, k[..., None, None], axis=2)[:, :, 0]  # noqa: E731
    eb, ec = take(e, (a + 1) % 3), take(e, (a + 2) % 3)
    dlen = np.linalg.norm(take(np.broadcast_to(d[None], e.shape), a), axis=-1)
    to_line = np.linalg.norm(np.cross(eb, ec), axis=-1) / dlen
    return np.where(le.min(-1) <= 2.0 * to_line, le.argmin(-1), a)


def _solid_angle_terms(e, le, a, d):
    """Numerator and denominator of the solid-angle ``atan2``, written around edge (b, c).

    ``den = l_a (l_b l_c + e_b.e_c) + e_a.(l_c e_b + l_b e_c)``. Next to edge (b, c) both
    brackets cancel catastrophically; they are rewritten exactly as
    ``l_b l_c + e_b.e_c = |e_b x e_c|^2 / (l_b l_c - e_b.e_c)`` and
    ``l_c e_b + l_b e_c = (s/2)(e_b + e_c) - (delta/2)(e_c - e_b)`` with ``s = l_b + l_c``,
    ``delta = l_c - l_b = (e_c - e_b).(e_b + e_c) / s``.
    ``a`` holds, per (point, face), the local vertex opposite the edge to write around.
    """
    take = lambda arr, k: np.take_along_axis(arr, k[..., None, None], axis=2)[:, :, 0]  # noqa: E731
    ea, eb, ec = take(e, a), take(e, (a + 1) % 3), take(e, (a + 2) % 3)
    la = np.take_along_axis(le, a[..., None], axis=2)[..., 0]
    lb = np.take_along_axis(le, ((a + 1) % 3)[..., None], axis=2)[..., 0]
    lc = np.take_along_axis(le, ((a + 2) % 3)[..., None], axis=2)[..., 0]
    dot = lambda x, y: np.einsum("...i,...i->...", x, y)  # noqa: E731
    cr = np.cross(eb, ec)
    det = dot(ea, cr)
    bc = dot(eb, ec)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = np.where(bc < 0.0, dot(cr, cr) / (lb * lc - bc), lb * lc + bc)
        s = lb + lc
        ssum = eb + ec
        dv = -np.take_along_axis(np.broadcast_to(d[None], e.shape), a[..., None, None], axis=2)[
            :, :, 0
        ]
        delta = np.where(s > 0, dot(dv, ssum) / s, 0.0)
    vec = 0.5 * s[..., None] * ssum - 0.5 * delta[..., None] * dv
    return det, la * t1 + dot(ea, vec)


def _cross_matrix(a: np.ndarray) -> np.ndarray:
    """``[a]_x`` for a stack of vectors ``(..., 3)`` -> ``(..., 3, 3)``."""
    z = np.zeros(a.shape[:-1])
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    return np.stack(
        [np.stack([z, -az, ay], -1), np.stack([az, z, -ax], -1), np.stack([-ay, ax, z], -1)], -2
    )


def _sym5(h: np.ndarray) -> np.ndarray:
    """Five entries of the symmetric part of ``(..., 3, 3)`` matrices."""
    return np.stack(
        [
            h[..., 0, 0],
            0.5 * (h[..., 0, 1] + h[..., 1, 0]),
            0.5 * (h[..., 0, 2] + h[..., 2, 0]),
            h[..., 1, 1],
            0.5 * (h[..., 1, 2] + h[..., 2, 1]),
        ],
        axis=-1,
    )


# --------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------
_BLOCK = 16  # points per parallel work item (amortises the scratch allocations)
# An edge counts as "near" when R - |d| < _NEAR_EDGE |d| (p within ~1% of its length from the
# edge's interior): only then is the solid angle rewritten around it (see _solid_angle_terms).
_NEAR_EDGE = 1e-4


@numba.njit(cache=True, parallel=True, fastmath=False, error_model="numpy")
def _basis_kernel(
    points,
    V,
    F,
    N,
    inv_twice_area,
    D,
    NxD,
    edges,
    edge_len,
    inv_4pi_len,
    face_edges,
    face_edge_sign,
    host,
    order,
    values,
    gradients,
    hessians,
    degenerate,
):  # pragma: no cover - compiled
    npts = points.shape[0]
    n = V.shape[0]
    m = F.shape[0]
    ne = edges.shape[0]
    nblocks = (npts + _BLOCK - 1) // _BLOCK
    for blk in numba.prange(nblocks):
        e = np.empty((n, 3))
        le = np.empty(n)
        ecr = np.empty((ne, 3))  # e_i x e_j for edge (i, j)
        edot = np.empty(ne)  # e_i . e_j
        ec = np.empty(ne)
        ect = np.empty(ne)
        enear = np.empty(ne, dtype=np.bool_)  # p is next to this edge's interior
        jv = np.empty((3, 3))
        cv = np.empty(3)
        Q = np.empty((3, 3))
        gw = np.empty(3)
        M = np.empty((3, 3))
        for k in range(blk * _BLOCK, min(npts, (blk + 1) * _BLOCK)):
            px, py, pz = points[k, 0], points[k, 1], points[k, 2]
            for a in range(n):
                ex = V[a, 0] - px
                ey = V[a, 1] - py
                ez = V[a, 2] - pz
                e[a, 0] = ex
                e[a, 1] = ey
                e[a, 2] = ez
                le[a] = math.sqrt(ex * ex + ey * ey + ez * ez)
            degen = False
            for q in range(ne):
                i = edges[q, 0]
                j = edges[q, 1]
                ux, uy, uz = e[i, 0], e[i, 1], e[i, 2]
                wx, wy, wz = e[j, 0], e[j, 1], e[j, 2]
                cx = uy * wz - uz * wy
                cy = uz * wx - ux * wz
                cz = ux * wy - uy * wx
                ecr[q, 0] = cx
                ecr[q, 1] = cy
                ecr[q, 2] = cz
                uw = ux * wx + uy * wy + uz * wz
                edot[q] = uw
                dl = edge_len[q]
                big = le[i] + le[j] + dl
                if uw <= 0.0:
                    denom = (le[i] * le[j] - uw) * big
                    small = 2.0 * (cx * cx + cy * cy + cz * cz) / denom if denom > 0.0 else 0.0
                else:
                    small = 2.0 * (le[i] * le[j] + uw) / big
                enear[q] = small < _NEAR_EDGE * dl
                if small <= 0.0:
                    degen = True
                    ec[q] = 0.0
                    ect[q] = 0.0
                else:
                    ec[q] = math.log1p(2.0 * dl / small) * inv_4pi_len[q]
                    ect[q] = 1.0 / (2.0 * math.pi * big * small)
            degenerate[k] = degen
            for t in range(m):
                i0 = F[t, 0]
                nx, ny, nz = N[t, 0], N[t, 1], N[t, 2]
                # Jv_v = e_{v+2} x e_{v+1} = -sign * (e_i x e_j) of the stored edge
                for v in range(3):
                    q = face_edges[t, v]
                    s = -face_edge_sign[t, v]
                    jv[v, 0] = s * ecr[q, 0]
                    jv[v, 1] = s * ecr[q, 1]
                    jv[v, 2] = s * ecr[q, 2]
                    cv[v] = ec[q]
                if not (
                    enear[face_edges[t, 0]] or enear[face_edges[t, 1]] or enear[face_edges[t, 2]]
                ):
                    # away from the edges the plain solid-angle formula is accurate
                    i1 = F[t, 1]
                    i2 = F[t, 2]
                    det = -(e[i0, 0] * jv[0, 0] + e[i0, 1] * jv[0, 1] + e[i0, 2] * jv[0, 2])
                    den = (
                        le[i0] * le[i1] * le[i2]
                        + edot[face_edges[t, 2]] * le[i2]
                        + edot[face_edges[t, 1]] * le[i1]
                        + edot[face_edges[t, 0]] * le[i0]
                    )
                else:
                    # Solid angle, written around the face's nearest edge (largest C) so that
                    # the denominator does not cancel next to that edge (see _solid_angle_den).
                    la = 0
                    if cv[1] > cv[la]:
                        la = 1
                    if cv[2] > cv[la]:
                        la = 2
                    # ... unless p is next to a vertex rather than an edge: pivot on that vertex
                    lmin = 0
                    if le[F[t, 1]] < le[F[t, lmin]]:
                        lmin = 1
                    if le[F[t, 2]] < le[F[t, lmin]]:
                        lmin = 2
                    qn = face_edges[t, la]
                    cn2 = ecr[qn, 0] ** 2 + ecr[qn, 1] ** 2 + ecr[qn, 2] ** 2
                    lm = le[F[t, lmin]]
                    if lm * lm * edge_len[qn] * edge_len[qn] <= 4.0 * cn2:
                        la = lmin
                    ia = F[t, la]
                    ib = F[t, (la + 1) % 3]
                    ic = F[t, (la + 2) % 3]
                    q = face_edges[t, la]
                    # det = e_a . (e_b x e_c) = -e_a . Jv_a
                    det = -(e[ia, 0] * jv[la, 0] + e[ia, 1] * jv[la, 1] + e[ia, 2] * jv[la, 2])
                    lb = le[ib]
                    lc = le[ic]
                    bc = edot[q]
                    if bc < 0.0:
                        c2 = ecr[q, 0] ** 2 + ecr[q, 1] ** 2 + ecr[q, 2] ** 2
                        t1 = c2 / (lb * lc - bc)
                    else:
                        t1 = lb * lc + bc
                    ssum = lb + lc
                    sx = e[ib, 0] + e[ic, 0]
                    sy = e[ib, 1] + e[ic, 1]
                    sz = e[ic, 2] + e[ib, 2]
                    # Dv = x_c - x_b = -d_a
                    dvx = -D[t, la, 0]
                    dvy = -D[t, la, 1]
                    dvz = -D[t, la, 2]
                    dlt = (dvx * sx + dvy * sy + dvz * sz) / ssum if ssum > 0.0 else 0.0
                    vx = 0.5 * ssum * sx - 0.5 * dlt * dvx
                    vy = 0.5 * ssum * sy - 0.5 * dlt * dvy
                    vz = 0.5 * ssum * sz - 0.5 * dlt * dvz
                    den = le[ia] * t1 + (e[ia, 0] * vx + e[ia, 1] * vy + e[ia, 2] * vz)
                hdist = e[i0, 0] * nx + e[i0, 1] * ny + e[i0, 2] * nz
                if host[k] == t:
                    w = 0.5
                    hdist = 0.0
                elif det == 0.0 and den <= 0.0:
                    w = 0.5 if den < 0.0 else 0.0
                else:
                    w = math.atan2(det, den) / (2.0 * math.pi)
                Px = -w * nx
                Py = -w * ny
                Pz = -w * nz
                psi = -w * hdist
                for v in range(3):
                    Px += cv[v] * NxD[t, v, 0]
                    Py += cv[v] * NxD[t, v, 1]
                    Pz += cv[v] * NxD[t, v, 2]
                    psi -= cv[v] * (jv[v, 0] * nx + jv[v, 1] * ny + jv[v, 2] * nz)
                values[k, n + t] = psi
                inv2a = inv_twice_area[t]
                for v in range(3):
                    col = F[t, v]
                    values[k, col] += (Px * jv[v, 0] + Py * jv[v, 1] + Pz * jv[v, 2]) * inv2a
                if order >= 1:
                    gradients[k, 0, n + t] = -Px
                    gradients[k, 1, n + t] = -Py
                    gradients[k, 2, n + t] = -Pz
                    for v in range(3):
                        col = F[t, v]
                        dx, dy, dz = D[t, v, 0], D[t, v, 1], D[t, v, 2]
                        gradients[k, 0, col] += (Py * dz - Pz * dy) * inv2a
                        gradients[k, 1, col] += (Pz * dx - Px * dz) * inv2a
                        gradients[k, 2, col] += (Px * dy - Py * dx) * inv2a
                if order >= 2:
                    # Q = sum_v Ct_v (e^_{v+1} + e^_{v+2}) d_v^T ;  grad w = sum_v Ct_v (..) Jv_v
                    Q[:, :] = 0.0
                    gw[:] = 0.0
                    for v in range(3):
                        q = face_edges[t, v]
                        ct = ect[q]
                        a1 = F[t, (v + 1) % 3]
                        a2 = F[t, (v + 2) % 3]
                        r1 = 1.0 / le[a1] if le[a1] > 0.0 else 0.0
                        r2 = 1.0 / le[a2] if le[a2] > 0.0 else 0.0
                        for r in range(3):
                            h = ct * (e[a1, r] * r1 + e[a2, r] * r2)
                            for c in range(3):
                                Q[r, c] += h * D[t, v, c]
                            gw[r] += ct * (r1 + r2) * jv[v, r]
                    # M = Q [N]_x^T + grad_w N^T ;  [N]_x^T = -[N]_x
                    for r in range(3):
                        q0, q1, q2 = Q[r, 0], Q[r, 1], Q[r, 2]
                        M[r, 0] = -(q1 * nz - q2 * ny) + gw[r] * nx
                        M[r, 1] = -(q2 * nx - q0 * nz) + gw[r] * ny
                        M[r, 2] = -(q0 * ny - q1 * nx) + gw[r] * nz
                    hessians[k, 0, n + t] = -M[0, 0]
                    hessians[k, 1, n + t] = -0.5 * (M[0, 1] + M[1, 0])
                    hessians[k, 2, n + t] = -0.5 * (M[0, 2] + M[2, 0])
                    hessians[k, 3, n + t] = -M[1, 1]
                    hessians[k, 4, n + t] = -0.5 * (M[1, 2] + M[2, 1])
                    for v in range(3):
                        col = F[t, v]
                        dx, dy, dz = D[t, v, 0], D[t, v, 1], D[t, v, 2]
                        # -[d]_x M / 2A: rows of [d]_x are (0,-dz,dy), (dz,0,-dx), (-dy,dx,0)
                        h00 = -(-dz * M[1, 0] + dy * M[2, 0])
                        h01 = -(-dz * M[1, 1] + dy * M[2, 1])
                        h02 = -(-dz * M[1, 2] + dy * M[2, 2])
                        h10 = -(dz * M[0, 0] - dx * M[2, 0])
                        h11 = -(dz * M[0, 1] - dx * M[2, 1])
                        h12 = -(dz * M[0, 2] - dx * M[2, 2])
                        h20 = -(-dy * M[0, 0] + dx * M[1, 0])
                        h21 = -(-dy * M[0, 1] + dx * M[1, 1])
                        hessians[k, 0, col] += h00 * inv2a
                        hessians[k, 1, col] += 0.5 * (h01 + h10) * inv2a
                        hessians[k, 2, col] += 0.5 * (h02 + h20) * inv2a
                        hessians[k, 3, col] += h11 * inv2a
                        hessians[k, 4, col] += 0.5 * (h12 + h21) * inv2a


# --------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------
def _as_points(points) -> np.ndarray:
    p = np.ascontiguousarray(points, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == 3:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3); got {np.shape(points)}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        from vhm_viz.core.errors import describe_indices

        raise ValueError(
            f"points have non-finite coordinates at indices {describe_indices(np.nonzero(bad)[0])}"
        )
    return p


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
        Points per chunk for the numpy reference (bounds its temporaries, which are
        ``O(chunk_size * m)``). The numba kernels need no temporaries beyond the output
        (and ~0.3 MB of scratch per thread).

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
    p = _as_points(points)
    cd = _prepare_cage(vertices, faces)
    npts = p.shape[0]
    m = cd.faces.shape[0]
    host = _host_array(host_faces, npts, m)
    if backend == "numba":
        values, gradients, hessians, degenerate = _evaluate_numba(p, cd, order, host)
    elif backend == "numpy":
        chunk = int(chunk_size or _NUMPY_CHUNK)
        parts = [
            _basis_numpy_chunk(
                p[s : s + chunk], cd, order, None if host is None else host[s : s + chunk]
            )
            for s in range(0, npts, chunk)
        ] or [_basis_numpy_chunk(p, cd, order, None)]
        values = np.concatenate([q[0] for q in parts])
        gradients = np.concatenate([q[1] for q in parts]) if order >= 1 else None
        hessians = np.concatenate([q[2] for q in parts]) if order >= 2 else None
        degenerate = np.concatenate([q[3] for q in parts])
    else:
        raise ValueError(f"backend must be 'numba' or 'numpy'; got {backend!r}")
    if degenerate.any():
        _fix_edge_and_vertex_points(p, cd, np.nonzero(degenerate)[0], values, gradients, hessians)
    if cd.shells:
        _separate_shells(cd, values, gradients, hessians)
    return BasisEvaluation(values, gradients, hessians)


def evaluate_map(points, vertices, faces, coefficients, *, order: int = 1):
    """A map ``f = sum_v a_v phi_v + sum_t b_t psi_t`` and its Jacobian, without the basis.

    The same numbers as ``evaluate_basis(...).values @ coefficients`` (and the gradients),
    but the basis of each group of points is contracted with the coefficients inside the
    kernel: nothing of size ``(N, n + m)`` is stored, which makes it several times faster
    for large cages. Points near a cage edge go through the careful per-point kernel, as
    in :func:`evaluate_basis`. A cage of several outward shells takes the basis path
    (the shells' functions are switched per point).

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
    p = _as_points(points)
    cd = _prepare_cage(vertices, faces)
    z = np.ascontiguousarray(coefficients, dtype=np.float64)
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    if z.shape != (n + m, 3):
        raise ValueError(f"coefficients must have shape ({n + m}, 3); got {z.shape}")
    npts = p.shape[0]
    if cd.shells or npts == 0:
        b = evaluate_basis(p, vertices, faces, order=order)
        jac = None
        if order:
            jac = np.swapaxes((b.gradients.reshape(-1, n + m) @ z).reshape(npts, 3, 3), 1, 2)
        return b.values @ z, jac, b.values[:, :n].sum(axis=1)
    values = np.empty((npts, 3))
    jac = np.empty((npts, 3, 3)) if order else np.zeros((0, 3, 3))
    winding = np.empty(npts)
    flagged = np.zeros(npts, dtype=np.bool_)
    kernel_args = _kernel_arrays(cd)
    lanes_map_kernel(
        p, *kernel_args, _NEAR_EDGE, order, z, values, jac, winding, flagged
    )
    rows = np.nonzero(flagged)[0]
    if rows.size:
        host = np.full(rows.size, -1, dtype=np.int64)
        vals, grads, _, degenerate = _evaluate_per_point(p[rows], kernel_args, cd, order, host)
        if degenerate.any():
            _fix_edge_and_vertex_points(
                p[rows], cd, np.nonzero(degenerate)[0], vals, grads, None
            )
        values[rows] = vals @ z
        winding[rows] = vals[:, :n].sum(axis=1)
        if order:
            jac[rows] = np.swapaxes(
                (grads.reshape(-1, n + m) @ z).reshape(rows.size, 3, 3), 1, 2
            )
    return values, (jac if order else None), winding


def _evaluate_numba(p, cd: _CageData, order: int, host: np.ndarray):
    """Run the compiled kernels: the SIMD one where it applies, the per-point one elsewhere.

    Values and gradients of points away from the cage edges come from
    :func:`~vhm_viz.core.basis_lanes.lanes_kernel` (16 points at a time, about 3x faster);
    the points it flags, and every point when Hessians are asked for, go through
    :func:`_basis_kernel`.
    """
    npts = p.shape[0]
    nm = cd.vertices.shape[0] + cd.faces.shape[0]
    kernel_args = _kernel_arrays(cd)
    degenerate = np.zeros(npts, dtype=np.bool_)
    if order <= 1 and npts:
        # every row is written by one of the two kernels: no need to zero the output
        values = np.empty((npts, nm))
        gradients = np.empty((npts, 3, nm)) if order >= 1 else np.zeros((0, 3, 0))
        flagged = np.zeros(npts, dtype=np.bool_)
        lanes_kernel(p, *kernel_args, host, _NEAR_EDGE, order, values, gradients, flagged)
        rows = np.nonzero(flagged)[0]
        if rows.size:
            sub = _evaluate_per_point(p[rows], kernel_args, cd, order, host[rows])
            values[rows] = sub[0]
            if order >= 1:
                gradients[rows] = sub[1]
            degenerate[rows] = sub[3]
        return values, gradients if order >= 1 else None, None, degenerate
    return _evaluate_per_point(p, kernel_args, cd, order, host)


def _kernel_arrays(cd: _CageData) -> tuple:
    """The cage arrays both compiled kernels take, in their order."""
    return (
        cd.vertices,
        cd.faces,
        cd.normals,
        1.0 / cd.twice_area,
        cd.d,
        cd.n_cross_d,
        cd.edges,
        cd.edge_length,
        1.0 / (4.0 * math.pi * cd.edge_length),
        cd.face_edges,
    )


def _evaluate_per_point(p, kernel_args, cd: _CageData, order: int, host: np.ndarray):
    npts = p.shape[0]
    nm = cd.vertices.shape[0] + cd.faces.shape[0]
    values = np.zeros((npts, nm))
    gradients = np.zeros((npts, 3, nm)) if order >= 1 else np.zeros((0, 3, 0))
    hessians = np.zeros((npts, 5, nm)) if order >= 2 else np.zeros((0, 5, 0))
    degenerate = np.zeros(npts, dtype=np.bool_)
    if npts:
        # the per-point kernel takes face_edge_sign after face_edges
        _basis_kernel(
            p,
            *kernel_args,
            cd.face_edge_sign,
            host,
            order,
            values,
            gradients,
            hessians,
            degenerate,
        )
    return (
        values,
        gradients if order >= 1 else None,
        hessians if order >= 2 else None,
        degenerate,
    )


def _host_array(host_faces, npts: int, m: int) -> np.ndarray | None:
    if host_faces is None:
        return np.full(npts, -1, dtype=np.int64)
    host = np.ascontiguousarray(host_faces, dtype=np.int64).ravel()
    if host.shape[0] != npts:
        raise ValueError(f"host_faces must have one entry per point ({npts}); got {host.shape[0]}")
    if (host >= m).any() or (host < -1).any():
        raise ValueError(f"host_faces entries must be -1 or a face index < {m}")
    return host


def _fix_edge_and_vertex_points(p, cd: _CageData, rows, values, gradients, hessians) -> None:
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
#: are classified correctly.
WINDING_TOLERANCE = 1e-8
#: Working memory one chunk of basis evaluation may use (bytes), unless the caller says.
DEFAULT_MEMORY_BUDGET = 64 * 2**20


def inside_cage(winding: np.ndarray) -> np.ndarray:
    """The one inside test: ``winding >= 1/2 - WINDING_TOLERANCE``.

    Parameters
    ----------
    winding : (N,) float64
        Winding numbers (:func:`winding_number`, or the sum of the ``phi`` columns).

    Returns
    -------
    (N,) bool
    """
    return np.asarray(winding) >= 0.5 - WINDING_TOLERANCE


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
        Bytes; default :data:`DEFAULT_MEMORY_BUDGET`.

    Returns
    -------
    int
        At least 16 (one SIMD group of the kernel).
    """
    budget = DEFAULT_MEMORY_BUDGET if memory_budget is None else int(memory_budget)
    if budget <= 0:
        raise ValueError(f"memory_budget must be a positive number of bytes; got {budget}")
    per_point = (1 + 3 * (order >= 1) + 5 * (order >= 2)) * max(int(n_columns), 1) * 8 * 2
    return max(16, budget // per_point)


def winding_number(points, vertices, faces, *, backend: str = "numba") -> np.ndarray:
    """Generalised winding number of a closed cage at points (``sum_v phi_v``).

    Parameters
    ----------
    points : (N, 3) array_like
    vertices : (n, 3) array_like
    faces : (m, 3) array_like of int
        Outward-oriented cage triangles.
    backend : {"numba", "numpy"}

    Returns
    -------
    (N,) ndarray
        1 inside, 0 outside (up to rounding); 1/2 exactly on a face.
    """
    p = _as_points(points)
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if backend == "numba":
        out = np.zeros(p.shape[0])
        if p.shape[0]:
            winding_kernel(p, v, f, out)
        return out
    if backend != "numpy":
        raise ValueError(f"backend must be 'numba' or 'numpy'; got {backend!r}")
    out = np.empty(p.shape[0])
    x = v[f]
    for s in range(0, p.shape[0], _NUMPY_CHUNK):
        e = x[None] - p[s : s + _NUMPY_CHUNK, None, None, :]
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
        out[s : s + _NUMPY_CHUNK] = w.sum(axis=1)
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
