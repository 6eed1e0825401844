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
from vhm_viz.core.geometry import face_normals_and_areas, point_triangle_distance2
from vhm_viz.core.limits import check_setting

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
    # (A cage of several shells also caches one entry per shell, see _shell_cages.)
    return _prepare_cage_cached(v.shape, v.tobytes(), f.shape, f.tobytes())


@functools.lru_cache(maxsize=16)
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
    centred = v - v.mean(axis=0)  # cones from the centroid: origin-free (geometry.signed_volume)
    a, b, c = centred[f[:, 0]], centred[f[:, 1]], centred[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c))
    shells = []
    for k in shell_ids:
        faces_k = np.nonzero(face_label == k)[0]
        if vol[faces_k].sum() > 0:  # outward shell: a separate domain
            shells.append((np.nonzero(labels == k)[0], faces_k))
    return tuple(shells) if len(shells) > 1 else ()


def domain_columns(vertices, faces) -> tuple[np.ndarray, ...]:
    """Basis columns of each separate domain of a cage (one per outward shell).

    The map inside one outward shell depends only on that shell's coefficients (and those
    of the inward hole shells inside it), see :func:`_outward_shells`, so a solver can tell
    which coefficients each domain owns.

    Parameters
    ----------
    vertices : (n, 3) array_like
    faces : (m, 3) array_like of int
        Outward-oriented cage.

    Returns
    -------
    tuple of int64 arrays
        Column ids (vertex ``v`` is column ``v``, face ``t`` column ``n + t``), one array
        per outward shell in the order of :func:`_outward_shells`; a single array of all
        ``n + m`` columns for a cage of one outward shell. A hole shell belongs to the
        outward shell whose winding number is 1 on it.
    """
    cd = _prepare_cage(vertices, faces)
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    if not cd.shells:
        return (np.arange(n + m, dtype=np.int64),)
    cols = [list(np.concatenate([vids, n + fids])) for vids, fids in cd.shells]
    owned = np.zeros(n + m, dtype=bool)
    for c in cols:
        owned[c] = True
    hole_faces = np.flatnonzero(~owned[n:])
    if len(hole_faces):
        import scipy.sparse.csgraph as csgraph

        f = cd.faces[hole_faces]
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
        graph = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        _, labels = csgraph.connected_components(graph, directed=False)
        for lab in np.unique(labels[f[:, 0]]):
            fids = hole_faces[labels[f[:, 0]] == lab]
            vids = np.unique(cd.faces[fids])
            probe = cd.vertices[vids[:1]]
            for k, (_, shell_faces) in enumerate(cd.shells):
                if winding_number(probe, cd.vertices, cd.faces[shell_faces])[0] > 0.5:
                    cols[k].extend(np.concatenate([vids, n + fids]).tolist())
                    break
    return tuple(np.unique(np.asarray(c, dtype=np.int64)) for c in cols)


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
# exact arithmetic for the cross product next to an edge
# --------------------------------------------------------------------------------------
# Next to the interior of edge (b, c) the vectors e_b = x_b - p and e_c = x_c - p point in
# nearly opposite directions, and e_b x e_c (length ~ distance x edge length) cancels: with
# e_b and e_c rounded (error ~ eps |e|), its relative error is ~ eps |e| / distance, 1e-4 at
# 1e-12 of the diagonal, and every term built on it (R - |d|, the solid angle) inherits it.
# Computed from the exact differences (Knuth's two-sum: x - p = hi + lo) with exact
# products (Dekker's split), the cross product is correct to a few ulps at any distance.
_SPLIT = 134217729.0  # 2**27 + 1


def _two_diff_np(a, b):
    """``a - b = s + err`` exactly (Knuth)."""
    s = a - b
    bb = s - a
    return s, (a - (s - bb)) - (b + bb)


def _two_prod_np(a, b):
    """``a * b = p + err`` exactly (Dekker; no fused multiply-add needed)."""
    p = a * b
    ca, cb = _SPLIT * a, _SPLIT * b
    ah, bh = ca - (ca - a), cb - (cb - b)
    al, bl = a - ah, b - bh
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def _cross_exact_np(xu, xw, p):
    """``(xu - p) x (xw - p)`` to a few ulps of the result, for stacks ``(..., 3)``."""
    uh, ul = _two_diff_np(xu, p)
    wh, wl = _two_diff_np(xw, p)
    out = []
    for i, j in ((1, 2), (2, 0), (0, 1)):
        p1, e1 = _two_prod_np(uh[..., i], wh[..., j])
        p2, e2 = _two_prod_np(uh[..., j], wh[..., i])
        d, ed = _two_diff_np(p1, p2)
        tail = uh[..., i] * wl[..., j] + ul[..., i] * wh[..., j]
        tail -= uh[..., j] * wl[..., i] + ul[..., j] * wh[..., i]
        out.append(d + (ed + (e1 - e2) + tail))
    return np.stack(out, axis=-1)


# --------------------------------------------------------------------------------------
# numpy reference (face by face, no sharing between faces)
# --------------------------------------------------------------------------------------
def _edge_terms_numpy(u, q, lu, lq, dlen, cr):
    """``C`` and ``Ct`` of an edge with end vectors ``u``, ``q`` (cancellation-free).

    ``cr`` is ``u x q``, computed exactly (:func:`_cross_exact_np`).
    """
    uq = np.einsum("...i,...i->...", u, q)
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
    pp = np.broadcast_to(p[:, None, :], e[:, :, 0].shape)
    for v in range(3):
        u, q = e[:, :, (v + 1) % 3], e[:, :, (v + 2) % 3]
        lu, lq = le[:, :, (v + 1) % 3], le[:, :, (v + 2) % 3]
        cr = _cross_exact_np(x[None, :, (v + 1) % 3], x[None, :, (v + 2) % 3], pp)
        dlen = np.linalg.norm(cd.d[:, v], axis=-1)[None]
        c, ct, on_edge = _edge_terms_numpy(u, q, lu, lq, dlen, cr)
        degenerate |= on_edge.any(axis=1)
        C.append(c)
        Ct.append(ct)
        Jv.append(-cr)  # e_{v+2} x e_{v+1}
    near = _solid_angle_pivot(e, le, np.argmax(np.stack(C, -1), axis=-1), cd.d)
    det, denom = _solid_angle_terms(e, le, near, cd.d, np.stack(Jv, axis=2))
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


def _solid_angle_terms(e, le, a, d, jv):
    """Numerator and denominator of the solid-angle ``atan2``, written around edge (b, c).

    ``det = e_a . (e_b x e_c)``, ``den = l_a (l_b l_c + e_b.e_c) + e_a.(l_c e_b + l_b e_c)``.
    Next to edge (b, c) both brackets cancel catastrophically; with the exact
    ``cr = e_b x e_c`` they are rewritten exactly as
    ``l_b l_c + e_b.e_c = |cr|^2 / (l_b l_c - e_b.e_c)`` and, with ``u`` the unit vector
    along the edge, ``t_b = -e_b.u``, ``t_c = e_c.u`` (the foot of ``p`` along it),
    ``l_c e_b + l_b e_c = u x cr + (l_c - t_c) e_b + (l_b - t_b) e_c`` (the triple product
    ``u x (e_b x e_c) = (u.e_c) e_b - (u.e_b) e_c``), where ``l - t = r^2 / (l + t)`` with
    ``r = |cr| / |d|`` the distance to the edge's line when ``t > 0``.
    ``a`` holds, per (point, face), the local vertex opposite the edge to write around;
    ``jv[..., v, :] = e_{v+2} x e_{v+1}`` (exact), so ``cr = -jv[..., a, :]``.
    """
    take = lambda arr, k: np.take_along_axis(arr, k[..., None, None], axis=2)[:, :, 0]  # noqa: E731
    ea, eb, ec = take(e, a), take(e, (a + 1) % 3), take(e, (a + 2) % 3)
    la = np.take_along_axis(le, a[..., None], axis=2)[..., 0]
    lb = np.take_along_axis(le, ((a + 1) % 3)[..., None], axis=2)[..., 0]
    lc = np.take_along_axis(le, ((a + 2) % 3)[..., None], axis=2)[..., 0]
    dot = lambda x, y: np.einsum("...i,...i->...", x, y)  # noqa: E731
    cr = -take(jv, a)
    det = dot(ea, cr)
    bc = dot(eb, ec)
    dv = -take(np.broadcast_to(d[None], e.shape), a)  # x_c - x_b
    with np.errstate(divide="ignore", invalid="ignore"):
        cr2 = dot(cr, cr)
        t1 = np.where(bc < 0.0, cr2 / (lb * lc - bc), lb * lc + bc)
        dl = np.sqrt(dot(dv, dv))
        u = dv / dl[..., None]
        r2 = cr2 / (dl * dl)
        tb, tc = -dot(eb, u), dot(ec, u)
        gap_b = np.where(tb > 0.0, r2 / (lb + tb), lb - tb)
        gap_c = np.where(tc > 0.0, r2 / (lc + tc), lc - tc)
    vec = np.cross(u, cr) + gap_c[..., None] * eb + gap_b[..., None] * ec
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


@numba.njit(cache=True, inline="always")
def _two_diff(a, b):  # pragma: no cover - compiled
    """``a - b = s + err`` exactly (see :func:`_two_diff_np`)."""
    s = a - b
    bb = s - a
    return s, (a - (s - bb)) - (b + bb)


@numba.njit(cache=True, inline="always")
def _two_prod(a, b):  # pragma: no cover - compiled
    """``a * b = p + err`` exactly (see :func:`_two_prod_np`)."""
    p = a * b
    ca = _SPLIT * a
    cb = _SPLIT * b
    ah = ca - (ca - a)
    bh = cb - (cb - b)
    al = a - ah
    bl = b - bh
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


@numba.njit(cache=True, inline="always")
def _cross_component(ui, ul_i, uj, ul_j, wi, wl_i, wj, wl_j):  # pragma: no cover - compiled
    """``u_i w_j - u_j w_i`` from exact splits ``u = uh + ul``, ``w = wh + wl``."""
    p1, e1 = _two_prod(ui, wj)
    p2, e2 = _two_prod(uj, wi)
    d, ed = _two_diff(p1, p2)
    tail = (ui * wl_j + ul_i * wj) - (uj * wl_i + ul_j * wi)
    return d + (ed + (e1 - e2) + tail)


@numba.njit(cache=True)
def _cross_exact(V, i, j, px, py, pz, out):  # pragma: no cover - compiled
    """``out = (V[i] - p) x (V[j] - p)`` to a few ulps (see :func:`_cross_exact_np`)."""
    ux, uxl = _two_diff(V[i, 0], px)
    uy, uyl = _two_diff(V[i, 1], py)
    uz, uzl = _two_diff(V[i, 2], pz)
    wx, wxl = _two_diff(V[j, 0], px)
    wy, wyl = _two_diff(V[j, 1], py)
    wz, wzl = _two_diff(V[j, 2], pz)
    out[0] = _cross_component(uy, uyl, uz, uzl, wy, wyl, wz, wzl)
    out[1] = _cross_component(uz, uzl, ux, uxl, wz, wzl, wx, wxl)
    out[2] = _cross_component(ux, uxl, uy, uyl, wx, wxl, wy, wyl)


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
                    if small < _NEAR_EDGE * dl:
                        # next to the edge's interior the cross product cancels: exactly
                        _cross_exact(V, i, j, px, py, pz, ecr[q])
                        cx, cy, cz = ecr[q, 0], ecr[q, 1], ecr[q, 2]
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
                    # l_c e_b + l_b e_c = u x cr + (l_c - t_c) e_b + (l_b - t_b) e_c, with u
                    # along the edge and cr = e_b x e_c = -Jv_a (see _solid_angle_terms)
                    crx, cry, crz = -jv[la, 0], -jv[la, 1], -jv[la, 2]
                    inv_dl = 1.0 / edge_len[q]
                    ux_ = -D[t, la, 0] * inv_dl  # x_c - x_b = -d_a
                    uy_ = -D[t, la, 1] * inv_dl
                    uz_ = -D[t, la, 2] * inv_dl
                    r2 = (crx * crx + cry * cry + crz * crz) * inv_dl * inv_dl
                    tb = -(e[ib, 0] * ux_ + e[ib, 1] * uy_ + e[ib, 2] * uz_)
                    tc = e[ic, 0] * ux_ + e[ic, 1] * uy_ + e[ic, 2] * uz_
                    gb = r2 / (lb + tb) if tb > 0.0 else lb - tb
                    gc = r2 / (lc + tc) if tc > 0.0 else lc - tc
                    vx = (uy_ * crz - uz_ * cry) + gc * e[ib, 0] + gb * e[ic, 0]
                    vy = (uz_ * crx - ux_ * crz) + gc * e[ib, 1] + gb * e[ic, 1]
                    vz = (ux_ * cry - uy_ * crx) + gc * e[ib, 2] + gb * e[ic, 2]
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
        Points per chunk (in [1, 1e7]) for the numpy reference (bounds its temporaries, which are
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
        chunk = _NUMPY_CHUNK if chunk_size is None else check_setting("chunk_size", chunk_size)
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
    if npts == 0:
        return np.zeros((0, 3)), (np.zeros((0, 3, 3)) if order else None), np.zeros(0)
    if not cd.shells:
        return _evaluate_map_one(p, cd, z, order)
    # Several outward shells: a shell's basis functions involve its own faces only, so
    # each shell is a cage of its own for the fused kernel. A point keeps the shells whose
    # own winding number puts it inside (the rule of _separate_shells) and every hole
    # shell. Each face is evaluated once per point, as for one shell; the basis path this
    # replaces was 3.5x slower on the 500-face embryo cage (100,000 points: 1.40 s against
    # 0.40 s for its main shell alone).
    values = np.zeros((npts, 3))
    jac = np.zeros((npts, 3, 3)) if order else None
    winding = np.zeros(npts)
    for cols, sub, every_point in _shell_cages(cd):
        v_s, j_s, w_s = _evaluate_map_one(p, sub, np.ascontiguousarray(z[cols]), order)
        keep = slice(None) if every_point else w_s >= 0.5
        values[keep] += v_s[keep]
        winding[keep] += w_s[keep]
        if order:
            jac[keep] += j_s[keep]
    return values, jac, winding


def _shell_cages(cd: _CageData) -> list:
    """``(columns, cage data, every point)`` of each outward shell, then of the holes.

    ``columns`` are the shell's basis columns in the whole cage (its vertices, then ``n``
    plus its faces); the hole shells, which every point keeps, form one cage.
    """
    n = cd.vertices.shape[0]
    out = []
    owned = np.zeros(cd.faces.shape[0], dtype=bool)
    groups = []
    for _, fids in cd.shells:
        owned[fids] = True
        groups.append((fids, False))
    holes = np.flatnonzero(~owned)
    if holes.size:
        groups.append((holes, True))
    for fids, every_point in groups:
        vids = np.unique(cd.faces[fids])
        remap = np.full(n, -1, dtype=np.int64)
        remap[vids] = np.arange(len(vids))
        sub = _prepare_cage(cd.vertices[vids], remap[cd.faces[fids]])
        out.append((np.concatenate([vids, n + fids]), sub, every_point))
    return out


def _evaluate_map_one(p, cd: _CageData, z, order: int):
    """:func:`evaluate_map` for a cage of one outward shell (and any holes)."""
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    npts = p.shape[0]
    values = np.empty((npts, 3))
    jac = np.empty((npts, 3, 3)) if order else np.zeros((0, 3, 3))
    winding = np.empty(npts)
    flagged = np.zeros(npts, dtype=np.bool_)
    kernel_args = _kernel_arrays(cd)
    lanes_map_kernel(
        _read_only(p), *kernel_args, _NEAR_EDGE, order, _read_only(z), values, jac, winding,
        flagged,
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


def _read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a``.

    numba compiles a kernel once for each combination of writeable and read-only
    arrays; the cage's vertices and faces are read-only (cached), whereas a shell's
    coefficients, a caller's vertices or the points may not be: passed read-only
    everywhere, one compiled variant serves them all (each other one cost about 7 s on
    a first run). The kernels do not write to them.
    """
    view = a.view()
    view.flags.writeable = False
    return view


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
    p = _as_points(points)
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
        _surface_host_kernel(p[near], v, f, cell, start, members, cells, tol, out)
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


@numba.njit(cache=True, parallel=True)
def _surface_host_kernel(points, V, F, cell, start, members, cells, tol, host):  # pragma: no cover
    tol2 = tol * tol
    for k in numba.prange(points.shape[0]):
        c = (cell[k, 0] * cells + cell[k, 1]) * cells + cell[k, 2]
        found = -1
        for s in range(start[c], start[c + 1]):
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
    p = _as_points(points).copy()
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


@numba.njit(cache=True, parallel=True)
def _reach_normals(points, V, F, normals, reach, out):  # pragma: no cover - compiled
    """Sum of the normals of the faces within ``reach`` of each point (few points)."""
    r2 = reach * reach
    for k in numba.prange(points.shape[0]):
        for t in range(F.shape[0]):
            if point_triangle_distance2(points[k], V[F[t, 0]], V[F[t, 1]], V[F[t, 2]]) <= r2:
                out[k, 0] += normals[t, 0]
                out[k, 1] += normals[t, 1]
                out[k, 2] += normals[t, 2]


def evaluate_inside(points, vertices, faces, *, order: int = 0):
    """:func:`evaluate_basis` together with the one inside test.

    Points on the cage surface that rounding put outside are evaluated just inside
    (:func:`surface_points_inside`), so the surface belongs to the inside consistently.

    Returns
    -------
    basis : BasisEvaluation
        Rows of points outside the cage hold the (meaningless) exterior values.
    inside : (N,) bool
    """
    b = evaluate_basis(points, vertices, faces, order=order)
    n = len(vertices)
    inside, hosts = classify_inside(points, vertices, faces, b.values[:, :n].sum(axis=1))
    on = np.nonzero(hosts >= 0)[0]
    if on.size:
        p = surface_points_inside(points, hosts, vertices, faces)[on]
        again = evaluate_basis(p, vertices, faces, order=order)
        for whole, part in zip(b, again, strict=True):
            if whole is not None:
                whole[on] = part
    return b, inside


def classify_inside(points, vertices, faces, winding=None) -> tuple[np.ndarray, np.ndarray]:
    """The one inside test: inside the cage, or on its surface.

    A point is inside when its winding number is at least 1/2 (:func:`inside_cage`), or
    when it lies within :func:`on_surface_tolerance` of a face: points computed on the
    cage surface land a few ulps to either side of it, and those the winding number puts
    outside get a host face; they are evaluated just inside
    (:func:`surface_points_inside`).

    Parameters
    ----------
    points : (N, 3) array_like
    vertices, faces : cage arrays
    winding : (N,) array_like, optional
        Winding numbers already computed (the sum of the ``phi`` columns).

    Returns
    -------
    inside : (N,) bool
    hosts : (N,) int64
        The host face of points on the surface that the winding number put outside; -1
        for every other point.
    """
    p = _as_points(points)
    w = winding_number(p, vertices, faces) if winding is None else np.asarray(winding)
    inside = inside_cage(w)
    hosts = np.full(len(p), -1, dtype=np.int64)
    out = np.nonzero(~inside)[0]
    if out.size:
        hosts[out] = surface_hosts(p[out], vertices, faces)
        inside[out] = hosts[out] >= 0
    return inside, hosts


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
    v = _read_only(np.ascontiguousarray(vertices, dtype=np.float64))
    f = _read_only(np.ascontiguousarray(faces, dtype=np.int64))
    if backend == "numba":
        out = np.zeros(p.shape[0])
        if p.shape[0]:
            winding_kernel(_read_only(p), v, f, out)
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
