"""Self-intersections of a triangle mesh: the pairs of faces that cross or touch.

Candidate pairs come from a sort-and-sweep of the faces' bounding boxes; each pair is then
decided by the separating-axis test (face normals and the cross products of edge
directions). Faces that share vertices intersect only where they meet beyond those
vertices. Used by :func:`vhm_viz.core.cage_validation.validate_cage` and by the automatic
cage's simplification.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.geometry import face_normals_and_areas

__all__ = ["DIST_RTOL", "self_intersections"]

#: Two faces closer than ``DIST_RTOL * diagonal`` are considered to touch (intersect).
DIST_RTOL = 1e-10


def _candidate_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i < j in sweep order) of boxes that overlap (touching counts), sort-and-sweep.

    The sweep runs along the axis of largest extent; the other two axes are then filtered.
    """
    m = len(lo)
    axis = int(np.argmax(hi.max(axis=0) - lo.min(axis=0)))
    order = np.argsort(lo[:, axis], kind="stable")
    s_lo = lo[order, axis]
    s_hi = hi[order, axis]
    # boxes order[i+1 : end[i]] start before box order[i] ends
    end = np.searchsorted(s_lo, s_hi, side="right")
    start = np.arange(1, m + 1)
    counts = np.maximum(end - start, 0)
    total = int(counts.sum())
    if total == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    ii = np.repeat(np.arange(m), counts)
    offsets = np.repeat(np.cumsum(counts) - counts, counts)
    jj = ii + 1 + (np.arange(total) - offsets)
    a = order[ii]
    b = order[jj]
    keep = np.ones(total, dtype=bool)
    for ax in range(3):
        if ax == axis:
            continue
        keep &= (lo[a, ax] <= hi[b, ax]) & (lo[b, ax] <= hi[a, ax])
    return a[keep], b[keep]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    out = np.zeros_like(v)
    np.divide(v, n, out=out, where=n > 0)
    return out


def _sat_intersect(t1: np.ndarray, t2: np.ndarray, tol: float) -> np.ndarray:
    """Whether triangles ``t1[k]`` and ``t2[k]`` (each (P, 3, 3)) intersect or touch.

    Separating-axis test over the two normals, the nine edge-edge cross products and the
    in-plane edge normals (``n_a x e_b`` for both normals and all six edges), which is a
    complete set for non-coplanar, coplanar and degenerate (segment: ``(a, b, b)``)
    triangles. Intervals closer than ``tol`` count as touching, i.e. intersecting.
    """
    origin = t1[:, :1, :]
    t1 = t1 - origin
    t2 = t2 - origin
    e1 = t1[:, [1, 2, 0]] - t1  # (P, 3, 3) edges
    e2 = t2[:, [1, 2, 0]] - t2
    n1 = np.cross(e1[:, 0], e1[:, 1])[:, None, :]
    n2 = np.cross(e2[:, 0], e2[:, 1])[:, None, :]
    ee = np.cross(e1[:, :, None, :], e2[:, None, :, :]).reshape(-1, 9, 3)
    edges = np.concatenate([e1, e2], axis=1)  # (P, 6, 3)
    axes = np.concatenate(
        [n1, n2, ee, np.cross(n1, edges), np.cross(n2, edges)], axis=1
    )  # (P, 23, 3)
    axes = _unit(axes)
    p1 = np.einsum("pak,pvk->pav", axes, t1)
    p2 = np.einsum("pak,pvk->pav", axes, t2)
    sep = (p1.max(axis=2) < p2.min(axis=2) - tol) | (p2.max(axis=2) < p1.min(axis=2) - tol)
    return ~sep.any(axis=1)


def _plane_separated(t1: np.ndarray, t2: np.ndarray, n1: np.ndarray, tol: float) -> np.ndarray:
    """Whether all corners of ``t2`` lie strictly on one side of the plane of ``t1``."""
    d = np.einsum("pvk,pk->pv", t2 - t1[:, :1, :], n1)
    return (d > tol).all(axis=1) | (d < -tol).all(axis=1)


def self_intersections(
    vertices: np.ndarray, faces: np.ndarray, *, tol: float | None = None, chunk: int = 50_000
) -> np.ndarray:
    """Pairs of faces of a triangle mesh that intersect improperly.

    Faces sharing no vertex intersect if they touch anywhere (closer than ``tol``). Faces
    sharing one vertex intersect if the edge of either opposite the shared vertex meets the
    other face (this covers every transversal and coplanar overlap). Faces sharing an edge
    intersect if they fold onto each other (coplanar, on the same side of the edge).
    Candidates come from a sort-and-sweep on the faces' bounding boxes, so the cost is
    roughly linear in the number of faces for a well-shaped mesh.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (m, 3) int array
        Non-degenerate triangles (as :class:`Cage` checks before calling this). Two faces
        on the same three vertices always count as intersecting.
    tol : float, optional
        Contact distance; default ``DIST_RTOL`` times the bounding-box diagonal.
    chunk : int
        Pairs tested per vectorised batch (bounds the memory use).

    Returns
    -------
    (k, 2) int64 array
        Intersecting face pairs, ``i < j``, sorted lexicographically.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    if tol is None:
        tol = DIST_RTOL * float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    tri = v[f]  # (m, 3, 3)
    normals, _ = face_normals_and_areas(v, f)
    lo = tri.min(axis=1) - tol
    hi = tri.max(axis=1) + tol
    a, b = _candidate_pairs(lo, hi)
    if len(a) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    # shared-vertex structure
    same = f[a][:, :, None] == f[b][:, None, :]  # (P, 3, 3): same[p, i, j] = fa[i] == fb[j]
    nshared = same.sum(axis=(1, 2))
    hits = []

    # --- no shared vertex: full triangle-triangle test
    idx = np.flatnonzero(nshared == 0)
    for s in range(0, len(idx), chunk):
        k = idx[s : s + chunk]
        t1, t2 = tri[a[k]], tri[b[k]]
        far = _plane_separated(t1, t2, normals[a[k]], tol) | _plane_separated(
            t2, t1, normals[b[k]], tol
        )
        k = k[~far]
        if len(k):
            hits.append(k[_sat_intersect(tri[a[k]], tri[b[k]], tol)])

    # --- one shared vertex: opposite edge of each face against the other face
    idx = np.flatnonzero(nshared == 1)
    if len(idx):
        sm = same[idx]
        ia = np.argmax(sm.any(axis=2), axis=1)  # position of the shared vertex in face a
        ib = np.argmax(sm.any(axis=1), axis=1)  # ... in face b
        r = np.arange(len(idx))
        ta, tb = tri[a[idx]], tri[b[idx]]
        seg_a = np.stack([ta[r, (ia + 1) % 3], ta[r, (ia + 2) % 3], ta[r, (ia + 2) % 3]], 1)
        seg_b = np.stack([tb[r, (ib + 1) % 3], tb[r, (ib + 2) % 3], tb[r, (ib + 2) % 3]], 1)
        hit = np.zeros(len(idx), dtype=bool)
        for s in range(0, len(idx), chunk):
            sl = slice(s, s + chunk)
            hit[sl] = _sat_intersect(seg_a[sl], tb[sl], tol) | _sat_intersect(
                seg_b[sl], ta[sl], tol
            )
        hits.append(idx[hit])

    # --- shared edge: fold (the two faces coplanar and on the same side of the edge)
    idx = np.flatnonzero(nshared == 2)
    if len(idx):
        # vertex of b not in a, distance to the plane of a
        ob = np.argmin(same[idx].any(axis=1), axis=1)
        pb = tri[b[idx], ob]
        d = np.abs(np.einsum("pk,pk->p", pb - tri[a[idx], 0], normals[a[idx]]))
        oa = np.argmin(same[idx].any(axis=2), axis=1)
        pa = tri[a[idx], oa]
        d = np.minimum(d, np.abs(np.einsum("pk,pk->p", pa - tri[b[idx], 0], normals[b[idx]])))
        fold = (d <= tol) & (np.einsum("pk,pk->p", normals[a[idx]], normals[b[idx]]) < 0)
        hits.append(idx[fold])

    # --- same three vertices (opposite-orientation copies): coincident
    hits.append(np.flatnonzero(nshared == 3))

    k = np.concatenate(hits) if hits else np.zeros(0, dtype=np.int64)
    pairs = np.sort(np.stack([a[k], b[k]], axis=1), axis=1)
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
