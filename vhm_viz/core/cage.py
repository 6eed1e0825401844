"""The validated cage: a closed, consistently outward-oriented, embedded triangle mesh.

Pure numpy/scipy. :class:`Cage` checks its input once, at construction, and stores
read-only arrays, so a cage can be shared and cached safely. The public
``vhm_viz.Cage`` subclasses it to add file and PyVista I/O.

Checks, in the order they are made (the most basic problem is reported first):

1. array shapes and dtypes (``vertices`` (n, 3) real, ``faces`` (m, 3) integer),
2. finite coordinates,
3. face indices in range,
4. at least 4 vertices and 4 faces,
5. degenerate faces (area below ``area_rtol * diagonal**2``, repeated indices included),
   and near-degenerate ones ("slivers", :data:`MIN_FACE_ANGLE`), checked after the
   orientation (10a below),
6. duplicate faces (the same vertices with the same orientation; a copy with the opposite
   orientation is a zero-thickness fin, reported by the edge checks as non-manifold or
   by the self-intersection check),
7. boundary edges (the cage is not closed),
8. non-manifold edges (an edge shared by more than two faces),
9. inconsistent orientation (an edge traversed in the same direction by its two faces),
   9a. slivers: faces whose smallest angle is below ``min_angle`` degrees
   (:data:`MIN_FACE_ANGLE`); :class:`Cage` repairs them by edge flips and collapses
   (:func:`repair_slivers`, reported in :attr:`Cage.repairs`) or refuses the cage naming
   the faces, their angles and the threshold,
10. self-intersections (pairs of faces that intersect other than along their shared
    vertices or edge), and
11. nested components (a shell inside another with the same orientation, or a hollow
    with the wrong one), only when the cage has several connected components.

Every failure raises :class:`~vhm_viz.core.errors.CageError` naming the problem and the
offending indices; ``CageError.indices`` holds them:

- vertex problems (non-finite coordinates): vertex indices, shape (k,);
- face problems (index range, degenerate, duplicate, orientation, nesting): face indices,
  shape (k,);
- edge problems (boundary, non-manifold): vertex pairs, shape (k, 2);
- self-intersections: face pairs, shape (k, 2).

Vertices where two shells touch (a "pinched", non-manifold vertex with manifold edges)
are accepted: the harmonic basis is well defined there.

A closed, consistent cage whose signed volume is negative (normals pointing inward) is
not an error: its faces are flipped and a :class:`UserWarning` says so.

Unreferenced vertices (used by no face) are allowed, with a :class:`UserWarning` naming
them: they keep their index (so vertex numbering matches the input file) but their basis
function ``phi_v`` is identically zero, so a solver must not rely on their coefficient.
"""

from __future__ import annotations

import warnings
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .errors import CageError, describe_indices
from .geometry import face_normals_and_areas, signed_volume

__all__ = [
    "Cage",
    "MIN_FACE_ANGLE",
    "SliverError",
    "face_angles",
    "repair_slivers",
    "self_intersections",
    "validate_cage",
]

#: Faces with area below ``AREA_RTOL * diagonal**2`` are degenerate.
AREA_RTOL = 1e-12
#: Smallest angle (degrees) a cage triangle may have. Thinner triangles ("slivers": a needle
#: with one very short edge, or a cap with one angle near 180 degrees) ruin the solve: the
#: smoothness samples on them see huge Hessians, the smoothness weight lambda (normalised by
#: the largest Hessian row) collapses, and the result is garbage while the solver reports
#: convergence. Measured on the bar's cage (bend-u) with one needle inserted: 3.3 to 4.5
#: degrees gave E_rigid within 4% of the clean cage's 0.067 (lambda is smaller, so the map
#: differs by 2-4% of the diagonal) after 8,000-15,000 iterations; 2.8 degrees did not
#: converge in 20,000; 1.4 degrees and below gave E_rigid 0.33-0.71 (0.37 diagonals away).
MIN_FACE_ANGLE = 3.0
#: Two faces closer than ``DIST_RTOL * diagonal`` are considered to touch (intersect).
DIST_RTOL = 1e-10


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


def _fmt_pairs(pairs: np.ndarray, limit: int = 6) -> str:
    shown = ", ".join(f"({int(a)}, {int(b)})" for a, b in pairs[:limit])
    if len(pairs) > limit:
        shown += f", ... ({len(pairs)} in all)"
    return shown


# ----------------------------------------------------------------------------------------
# Self-intersection
# ----------------------------------------------------------------------------------------


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


# ----------------------------------------------------------------------------------------
# Validation
# ----------------------------------------------------------------------------------------


def _as_arrays(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    try:
        v = np.asarray(vertices)
    except Exception as exc:  # ragged input etc.
        raise CageError(f"vertices cannot be converted to an array: {exc}") from exc
    try:
        f = np.asarray(faces)
    except Exception as exc:
        raise CageError(f"faces cannot be converted to an array: {exc}") from exc
    if v.ndim != 2 or v.shape[1] != 3:
        raise CageError(f"vertices must have shape (n, 3), got {v.shape}")
    if v.dtype == object or not (
        np.issubdtype(v.dtype, np.floating) or np.issubdtype(v.dtype, np.integer)
    ):
        raise CageError(f"vertices must be real numbers, got dtype {v.dtype}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise CageError(
            f"faces must have shape (m, 3) (triangles; triangulate polygons first), got {f.shape}"
        )
    if f.size and not np.issubdtype(f.dtype, np.integer):
        integral = np.issubdtype(f.dtype, np.floating) and np.all(np.isfinite(f))
        if not (integral and np.all(f == np.round(f))):  # integral floats are accepted
            raise CageError(f"faces must be integer vertex indices, got dtype {f.dtype}")
    return v.astype(np.float64), f.astype(np.int64)


def _edge_table(f: np.ndarray):
    """Half-edges, their face, and the undirected edge id of each."""
    m = len(f)
    he = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    he_face = np.repeat(np.arange(m), 3)
    key = np.sort(he, axis=1)
    edges, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return he, he_face, edges, inverse.ravel(), counts


def validate_cage(
    vertices,
    faces,
    *,
    check_self_intersection: bool = True,
    area_rtol: float = AREA_RTOL,
    dist_rtol: float = DIST_RTOL,
    min_angle: float = 0.0,
    stacklevel: int = 2,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Check a triangle mesh for use as a cage; flip it if it is oriented inward.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
    faces : (m, 3) array_like of int
    check_self_intersection : bool
        Skip the (most expensive) self-intersection and nesting checks when False.
    area_rtol : float
        Faces with area ``< area_rtol * diagonal**2`` are degenerate.
    dist_rtol : float
        Faces closer than ``dist_rtol * diagonal`` touch (count as intersecting).
    min_angle : float
        Faces whose smallest angle is below this many degrees are slivers
        (:class:`SliverError`); 0 (the default here, a purely structural check) disables
        it. :class:`Cage` checks :data:`MIN_FACE_ANGLE`.
    stacklevel : int
        For the warnings issued.

    Returns
    -------
    vertices : (n, 3) float64
    faces : (m, 3) int64
        Outward oriented (a copy with columns 1 and 2 swapped if the input was inward).
    flipped : bool
        Whether the faces were flipped.

    Raises
    ------
    CageError
        See the module docstring for the checks, their order and ``indices``.
    """
    v, f = _as_arrays(vertices, faces)
    n, m = len(v), len(f)

    bad = np.flatnonzero(~np.isfinite(v).all(axis=1))
    if len(bad):
        raise CageError(
            f"{len(bad)} vertices have non-finite coordinates (NaN or inf): "
            f"vertices {describe_indices(bad)}",
            bad,
        )

    bad = np.flatnonzero(((f < 0) | (f >= n)).any(axis=1))
    if len(bad):
        vals = np.unique(f[bad][(f[bad] < 0) | (f[bad] >= n)])
        raise CageError(
            f"{len(bad)} faces use vertex indices outside [0, {n}) "
            f"(values {describe_indices(vals)}): faces {describe_indices(bad)}",
            bad,
        )

    if n < 4 or m < 4:
        raise CageError(
            f"a cage needs at least 4 vertices and 4 faces, got {n} vertices and {m} faces"
        )

    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    normals, areas = face_normals_and_areas(v, f)
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    bad = np.flatnonzero(repeated | (areas < area_rtol * diag * diag))
    if len(bad):
        raise CageError(
            f"{len(bad)} degenerate (zero-area) faces: faces {describe_indices(bad)} "
            f"(area below {area_rtol:g} x diagonal^2 or a repeated vertex)",
            bad,
        )

    # duplicates: same vertex set with the same orientation (an exact copy, up to a
    # rotation of the corners). Opposite-orientation copies (zero-thickness fins) are
    # topological problems, reported by the edge checks below.
    key = np.sort(f, axis=1)
    rot = np.argmin(f, axis=1)
    canon = f[np.arange(m)[:, None], (rot[:, None] + np.arange(3)) % 3]
    _, inv, cnt = np.unique(canon, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    bad = np.flatnonzero(cnt[inv] > 1)
    if len(bad):
        groups = [np.flatnonzero(inv == g) for g in np.unique(inv[bad])]
        shown = "; ".join(describe_indices(g) for g in groups[:5])
        raise CageError(
            f"{len(bad)} duplicate faces (same vertices, same orientation): faces {shown}"
            + (f"; ... ({len(groups)} groups in all)" if len(groups) > 5 else ""),
            bad,
        )
    _, kinv, kcnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    kinv = kinv.ravel()
    fins = np.flatnonzero(kcnt[kinv] > 1)

    he, he_face, edges, inverse, counts = _edge_table(f)
    bad = np.flatnonzero(counts == 1)
    if len(bad):
        bfaces = np.unique(he_face[np.isin(inverse, bad)])
        raise CageError(
            f"cage is not closed: {len(bad)} boundary edges (vertex pairs "
            f"{_fmt_pairs(edges[bad])}) on faces {describe_indices(bfaces)}",
            edges[bad],
        )
    bad = np.flatnonzero(counts > 2)
    if len(bad):
        bfaces = np.unique(he_face[np.isin(inverse, bad)])
        note = ""
        fin = np.intersect1d(bfaces, fins)
        if len(fin):
            note = (
                f"; faces {describe_indices(fin)} repeat the vertices of another face with "
                "opposite orientation (zero-thickness fins)"
            )
        raise CageError(
            f"cage is non-manifold: {len(bad)} edges shared by more than two faces "
            f"(vertex pairs {_fmt_pairs(edges[bad])}) on faces {describe_indices(bfaces)}" + note,
            edges[bad],
        )

    # every edge has exactly two half-edges now
    order = np.argsort(inverse, kind="stable")
    h0, h1 = order[0::2], order[1::2]
    f0, f1 = he_face[h0], he_face[h1]
    same_dir = he[h0, 0] == he[h1, 0]
    # face components, and orientation classes on the doubled graph (face, parity)
    adj = sp.coo_matrix((np.ones(len(f0)), (f0, f1)), shape=(m, m))
    ncomp, comp = connected_components(adj, directed=False)
    src = np.concatenate([f0, f0 + m])
    dst = np.concatenate([f1 + m * same_dir, f1 + m * (~same_dir)])
    dbl = sp.coo_matrix((np.ones(len(src)), (src, dst)), shape=(2 * m, 2 * m))
    _, lab = connected_components(dbl, directed=False)
    if same_dir.any():
        nonorientable = lab[:m] == lab[m:]
        if nonorientable.any():
            bad = np.unique(np.concatenate([f0[same_dir], f1[same_dir]]))
            raise CageError(
                f"cage is not orientable: {int(same_dir.sum())} edges are traversed in the "
                f"same direction by both their faces, around faces {describe_indices(bad)}",
                bad,
            )
        cls = lab[:m] < lab[m:]
        bad = []
        for c in np.unique(comp[np.concatenate([f0[same_dir], f1[same_dir]])]):
            members = np.flatnonzero(comp == c)
            ones = members[cls[members]]
            zeros = members[~cls[members]]
            bad.append(ones if len(ones) <= len(zeros) else zeros)
        bad = np.sort(np.concatenate(bad))
        edges_bad = np.sort(he[h0[same_dir]], axis=1)
        raise CageError(
            f"inconsistent orientation: faces {describe_indices(bad)} are oriented opposite "
            f"to their neighbours ({int(same_dir.sum())} edges traversed in the same "
            f"direction by both faces, e.g. vertex pairs {_fmt_pairs(edges_bad, 4)})",
            bad,
        )

    smallest = face_angles(v, f).min(axis=1)
    bad = np.flatnonzero(smallest < min_angle)
    if len(bad):
        worst = bad[np.argsort(smallest[bad])]
        shown = ", ".join(f"{int(t)} ({smallest[t]:.3g} deg)" for t in worst[:6])
        more = f", ... ({len(bad)} in all)" if len(bad) > 6 else ""
        raise SliverError(
            f"{len(bad)} near-degenerate faces (slivers): faces {shown}{more} have an angle "
            f"below the {min_angle:g} degree minimum (vhm_viz.core.cage.MIN_FACE_ANGLE); "
            "they would ruin the smoothness term",
            worst,
        )

    if check_self_intersection:
        pairs = self_intersections(v, f, tol=dist_rtol * diag)
        if len(pairs):
            raise CageError(
                f"cage self-intersects: {len(pairs)} pairs of faces intersect "
                f"(face pairs {_fmt_pairs(pairs)})",
                pairs,
            )

    flipped = False
    if signed_volume(v, f) < 0:
        f = f[:, [0, 2, 1]]
        flipped = True
        warnings.warn(
            "cage faces are oriented inward (negative signed volume); flipped them to "
            "point outward",
            UserWarning,
            stacklevel=stacklevel,
        )

    if check_self_intersection and ncomp > 1:
        _check_nesting(v, f, comp, ncomp)

    unused = np.setdiff1d(np.arange(n), f.ravel())
    if len(unused):
        warnings.warn(
            f"{len(unused)} cage vertices are used by no face (vertices "
            f"{describe_indices(unused)}); they are kept, with an identically zero basis "
            "function",
            UserWarning,
            stacklevel=stacklevel,
        )
    return v, f, flipped


def _check_nesting(v: np.ndarray, f: np.ndarray, comp: np.ndarray, ncomp: int) -> None:
    """Each shell must see winding number 0 (outward shell) or 1 (inward hollow) from the rest."""
    from .basis import winding_number

    bad = []
    for c in range(ncomp):
        mine = comp == c
        others = f[~mine]
        probe = v[f[np.flatnonzero(mine)[0]]].mean(axis=0)[None, :]  # a face centroid
        w = float(np.asarray(winding_number(probe, v, others)).ravel()[0])
        expected = 0.0 if signed_volume(v, f[mine]) > 0 else 1.0
        if abs(w - expected) > 0.25:
            bad.append(np.flatnonzero(mine))
    if bad:
        bad = np.concatenate(bad)
        raise CageError(
            "cage components are nested with the wrong orientation (the winding number "
            f"would leave {{0, 1}}): faces {describe_indices(bad)}",
            bad,
        )


# ----------------------------------------------------------------------------------------
# Slivers
# ----------------------------------------------------------------------------------------


class SliverError(CageError):
    """Faces whose smallest angle is below the minimum; ``indices``: those faces."""


def face_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Interior angles of triangles, in degrees.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int

    Returns
    -------
    (m, 3) float64
        Angle at each corner; 0 at a corner of a zero-length edge.
    """
    x = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    out = np.zeros(x.shape[:2])
    for i in range(3):
        a = x[:, (i + 1) % 3] - x[:, i]
        b = x[:, (i + 2) % 3] - x[:, i]
        # atan2 of |a x b| and a.b: accurate for angles near 0 and 180 degrees
        out[:, i] = np.degrees(
            np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
        )
    return out


def repair_slivers(
    vertices,
    faces,
    min_angle: float = MIN_FACE_ANGLE,
    *,
    error: SliverError | None = None,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Remove slivers from a closed, consistently oriented triangle mesh.

    Worst face first: the edge opposite the largest angle is flipped, or the shortest edge
    collapsed (to an end point or the midpoint), whichever leaves the larger smallest angle.
    A step is taken only if it keeps the mesh a closed manifold (no duplicate edge, the
    link condition for collapses), turns no face over (each changed face's normal within
    90 degrees of the old ones), improves the smallest angle where it acts, and moves no
    part of the surface inward (a flip adds volume or none, a collapse moves no vertex
    through a face around it): the repaired cage holds everything the input held, so a
    cage that enclosed the data still does. The caller validates the result
    (self-intersection).

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
    min_angle : float
        Degrees.
    error : SliverError, optional
        Re-raised (with the faces still thin) when a sliver cannot be repaired.

    Returns
    -------
    vertices : (n', 3) float64
        Collapsed vertices removed; the others keep their order.
    faces : (m', 3) int64
    notes : list of str
        One line per step, with the input's vertex numbers.

    Raises
    ------
    SliverError
        A sliver that no flip or collapse can remove; the message names it.
    """
    v = np.array(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.int64)
    alive = np.ones(len(v), dtype=bool)
    notes: list[str] = []
    stuck: set[tuple] = set()  # slivers no step removes (by their corners)
    for _ in range(2 * len(f)):
        ang = face_angles(v, f)
        smallest = ang.min(axis=1)
        open_ = [u for u in np.argsort(smallest) if tuple(sorted(f[u])) not in stuck]
        if not open_ or smallest[open_[0]] >= min_angle:
            break
        t = int(open_[0])
        # of the flip and the collapse that are allowed, the one leaving the larger angle
        steps = [x for x in (_flip_cap(v, f, t, ang), _collapse_needle(v, f, t)) if x]
        if not steps:
            stuck.add(tuple(sorted(f[t])))
            continue
        f, note, _, collapse = max(steps, key=lambda x: x[2])
        if collapse is not None:
            a, b, point = collapse
            v[a] = point
            alive[b] = False
        notes.append(f"{note} (face {t} had an angle of {smallest[t]:.3g} degrees)")
    else:  # pragma: no cover - each step removes a face or improves one
        raise SliverError("sliver repair did not finish", [])
    thin = np.flatnonzero(face_angles(v, f).min(axis=1) < min_angle)
    if len(thin):
        t = int(thin[0])
        msg = (
            f"{len(thin)} slivers left: face {t} has an angle of "
            f"{face_angles(v, f[[t]]).min():.3g} degrees, below the {min_angle:g} degree "
            "minimum (vhm_viz.core.cage.MIN_FACE_ANGLE), and no edge flip or collapse "
            "removes it without moving the cage into what it encloses; move its vertices "
            f"{', '.join(str(int(i)) for i in f[t])}"
        )
        raise SliverError(msg if error is None else f"{error} -- {msg}", thin)
    keep = np.flatnonzero(alive)
    renumber = np.full(len(v), -1, dtype=np.int64)
    renumber[keep] = np.arange(len(keep))
    return v[keep], renumber[f], notes


def _faces_with_edge(f: np.ndarray, a: int, b: int) -> np.ndarray:
    return np.flatnonzero((f == a).any(axis=1) & (f == b).any(axis=1))


def _normals_kept(v, old_faces, new_faces) -> bool:
    """Whether every new face is non-degenerate and within 90 degrees of an old face."""
    n_old, _ = face_normals_and_areas(v, old_faces)
    n_new, a_new = face_normals_and_areas(v, new_faces)
    if (a_new <= 0).any():
        return False
    return bool(((n_new @ n_old.T) > 0).any(axis=1).all())


def _flat(v, faces) -> float:
    """What counts as no volume next to ``faces``: rounding of their size cubed."""
    x = v[faces]
    size = float(np.linalg.norm(x.max(axis=(0, 1)) - x.min(axis=(0, 1))))
    return 1e-9 * size**3


def _volume_change(v_old, old_faces, v_new, new_faces) -> float:
    """Volume the replacement of ``old_faces`` by ``new_faces`` adds (both closing a patch)."""
    origin = v_old[old_faces].reshape(-1, 3).mean(axis=0)  # origin-free, like signed_volume

    def cones(v, faces):
        x = v[faces] - origin
        return float(np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0)

    return cones(v_new, new_faces) - cones(v_old, old_faces)


def _moves_outward(v, f, moves: dict) -> bool:
    """Whether moving vertices (``{vertex: new position}``) keeps the surface outside.

    Every moved vertex must not go inward through any face around it (beyond rounding):
    the repaired cage then still holds all it held, which a cage around data must.
    """
    normals, _ = face_normals_and_areas(v, f)
    for vid, point in moves.items():
        around = np.flatnonzero((f == vid).any(axis=1))
        step = np.asarray(point) - v[vid]
        if (normals[around] @ step < -1e-9 * np.linalg.norm(step) - 1e-300).any():
            return False
    return True


def _flip_cap(v, f, t, ang):
    """Flip the edge opposite face ``t``'s largest angle; None if that is not allowed.

    Returns the new faces, a note, the smallest angle of the changed faces and None (no
    vertex moves).
    """
    k = int(np.argmax(ang[t]))
    c, a, b = f[t, k], f[t, (k + 1) % 3], f[t, (k + 2) % 3]  # face (c, a, b), edge a-b
    other = [u for u in _faces_with_edge(f, a, b) if u != t]
    if len(other) != 1:
        return None
    u = other[0]
    d = int(next(x for x in f[u] if x not in (a, b)))
    if d == c or len(_faces_with_edge(f, c, d)):
        return None
    new = np.array([[c, a, d], [d, b, c]])  # keeps the orientation of (c, a, b), (b, a, d)
    if not _normals_kept(v, f[[t, u]], new):
        return None
    worst = face_angles(v, new).min()
    if worst <= min(ang[t].min(), face_angles(v, f[[u]]).min()):
        return None
    if _volume_change(v, f[[t, u]], v, new) < -_flat(v, f[[t, u]]):
        return None  # the new edge would cut into the cage: what it held could be lost
    g = f.copy()
    g[t], g[u] = new
    return g, f"flipped edge ({a}, {b}) to ({c}, {d})", worst, None


def _collapse_needle(v, f, t):
    """Collapse face ``t``'s shortest edge; None if no position keeps the cage valid.

    Returns the new faces, a note, the smallest angle of the changed faces and the move
    ``(a, b, point)``: vertex ``a`` goes to ``point``, vertex ``b`` is gone.
    """
    x = v[f[t]]
    lengths = np.linalg.norm(x[[1, 2, 0]] - x, axis=1)
    k = int(np.argmin(lengths))
    a, b = int(f[t, k]), int(f[t, (k + 1) % 3])
    shared = _faces_with_edge(f, a, b)
    ring = lambda p: set(f[(f == p).any(axis=1)].ravel()) - {p}  # noqa: E731
    opposite = {int(i) for s in shared for i in f[s] if i not in (a, b)}
    if len(shared) != 2 or (ring(a) & ring(b)) != opposite or len(f) < 6:
        return None  # the link condition (a collapse would pinch the surface); a tetrahedron
    moved = np.flatnonzero((f == a).any(axis=1) | (f == b).any(axis=1))
    kept = np.setdiff1d(moved, shared)
    before = face_angles(v, f[moved]).min()
    best = None
    for where, point in (("midpoint", 0.5 * (v[a] + v[b])), (str(a), v[a]), (str(b), v[b])):
        w = v.copy()
        w[a] = point
        g = np.where(f == b, a, f)
        new = g[kept]
        if not _normals_kept(w, f[kept], new):
            continue
        # normals of the kept faces against their own old normals, one by one
        n_old, _ = face_normals_and_areas(v, f[kept])
        n_new, _ = face_normals_and_areas(w, new)
        if (np.einsum("ij,ij->i", n_old, n_new) <= 0).any():
            continue
        worst = face_angles(w, new).min()
        if worst <= before or (best is not None and worst <= best[0]):
            continue
        if not _moves_outward(v, f, {a: point, b: point}):
            continue  # the surface would move inward: what it held could be lost
        best = (worst, where, point, g)
    if best is None:
        return None
    worst, where, point, g = best
    return (
        np.delete(g, shared, axis=0),
        f"collapsed edge ({a}, {b}) to {where}",
        worst,
        (a, b, point),
    )


# ----------------------------------------------------------------------------------------
# The Cage
# ----------------------------------------------------------------------------------------


class Cage:
    """A closed, consistently outward-oriented, non-self-intersecting triangle mesh.

    Construction validates the input (see :func:`validate_cage` and the module
    docstring for the checks and the ``CageError.indices`` conventions). An inward
    cage is flipped with a :class:`UserWarning`; unreferenced vertices are kept with a
    warning. All array attributes are read-only.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
        Cage vertex positions.
    faces : (m, 3) array_like of int
        Triangles (0-based vertex indices).
    check_self_intersection : bool
        Skip the self-intersection test when False (only for input known to be embedded).
    min_angle : float
        Faces whose smallest angle is below this many degrees are slivers (default
        :data:`MIN_FACE_ANGLE`; 0 accepts any face, see :attr:`thin_faces`).
    repair : bool
        Repair slivers by edge flips and collapses that move no part of the surface inward
        (:func:`repair_slivers`; each step is listed in :attr:`repairs`, and a collapse
        removes a vertex, so vertex numbers then differ from the input's). When False, or
        when no such repair exists, a sliver is a :class:`SliverError` naming the face.

    Raises
    ------
    CageError
        If the mesh cannot be a cage; the message names the problem and the indices.
    """

    def __init__(
        self,
        vertices,
        faces,
        *,
        check_self_intersection: bool = True,
        min_angle: float = MIN_FACE_ANGLE,
        repair: bool = True,
    ):
        self._repairs: tuple[str, ...] = ()
        self._min_angle = float(min_angle)
        checks = {"check_self_intersection": check_self_intersection, "min_angle": min_angle}
        try:
            v, f, flipped = validate_cage(vertices, faces, stacklevel=3, **checks)
        except SliverError as exc:
            if not repair:
                raise
            v0, f0 = _as_arrays(vertices, faces)
            v1, f1, notes = repair_slivers(v0, f0, min_angle, error=exc)
            try:
                v, f, flipped = validate_cage(v1, f1, stacklevel=3, **checks)
            except CageError:  # the repair broke the cage: the slivers are the problem
                raise exc from None
            self._repairs = tuple(notes)
        self._vertices = _readonly(v)
        self._faces = _readonly(f)
        self._flipped = flipped
        normals, areas = face_normals_and_areas(v, f)
        self._normals = _readonly(normals)
        self._areas = _readonly(areas)
        self._bounds = _readonly(np.stack([v.min(axis=0), v.max(axis=0)]))

    # --- basic data
    @property
    def vertices(self) -> np.ndarray:
        """(n, 3) float64, read-only: vertex positions."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """(m, 3) int64, read-only: triangles, counter-clockwise about the outward normal."""
        return self._faces

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``."""
        return len(self._vertices)

    @property
    def n_faces(self) -> int:
        """Number of faces ``m``."""
        return len(self._faces)

    @property
    def flipped(self) -> bool:
        """Whether the input was oriented inward and its faces were flipped."""
        return self._flipped

    @property
    def repairs(self) -> tuple[str, ...]:
        """What was done to repair slivers (empty when the input had none)."""
        return self._repairs

    @property
    def min_angle(self) -> float:
        """The smallest face angle (degrees) this cage was checked against."""
        return self._min_angle

    @cached_property
    def thin_faces(self) -> np.ndarray:
        """Faces whose smallest angle is below :data:`MIN_FACE_ANGLE` (read-only).

        Empty unless the cage was made with a smaller ``min_angle`` (automatic cages are):
        such faces make the smoothness weight collapse, and the command line says so.
        """
        return _readonly(
            np.flatnonzero(face_angles(self._vertices, self._faces).min(1) < MIN_FACE_ANGLE)
        )

    @property
    def face_normals(self) -> np.ndarray:
        """(m, 3) float64, read-only: unit outward normals ``N_t``."""
        return self._normals

    normals = face_normals

    @property
    def areas(self) -> np.ndarray:
        """(m,) float64, read-only: face areas ``A_t``."""
        return self._areas

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64, read-only: ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``."""
        return self._bounds

    @property
    def diagonal(self) -> float:
        """Length of the bounding-box diagonal."""
        return float(np.linalg.norm(self._bounds[1] - self._bounds[0]))

    @property
    def volume(self) -> float:
        """Enclosed volume (positive: the cage is outward oriented)."""
        return signed_volume(self._vertices, self._faces)

    @cached_property
    def face_centroids(self) -> np.ndarray:
        """(m, 3) float64, read-only: face centroids."""
        return _readonly(self._vertices[self._faces].mean(axis=1))

    @cached_property
    def edges(self) -> np.ndarray:
        """(3m/2, 2) int64, read-only: undirected edges ``(i, j)``, ``i < j``, sorted."""
        _, _, edges, _, _ = _edge_table(self._faces)
        return _readonly(edges)

    @cached_property
    def vertex_faces(self) -> sp.csr_matrix:
        """Vertex-face incidence, a read-only ``scipy.sparse.csr_matrix`` of shape (n, m).

        Entry ``(v, t)`` is 1 when face ``t`` uses vertex ``v``. The faces around vertex
        ``v`` are ``vertex_faces.indices[vertex_faces.indptr[v]:vertex_faces.indptr[v+1]]``
        (sorted ascending); ``vertex_faces @ x`` sums a per-face quantity onto vertices.
        """
        m = self.n_faces
        mat = sp.csr_matrix(
            (
                np.ones(3 * m, dtype=np.int8),
                (self._faces.ravel(), np.repeat(np.arange(m), 3)),
            ),
            shape=(self.n_vertices, m),
        )
        mat.sum_duplicates()
        mat.sort_indices()
        for a in (mat.data, mat.indices, mat.indptr):
            a.flags.writeable = False
        return mat

    def faces_of_vertex(self, v: int) -> np.ndarray:
        """Return the indices of the faces using vertex ``v`` (ascending)."""
        vf = self.vertex_faces
        return vf.indices[vf.indptr[v] : vf.indptr[v + 1]]

    # --- point classification
    def winding_number(self, points) -> np.ndarray:
        """Generalized winding number ``sum_v phi_v(p)``: 1 inside, 0 outside, 1/2 on faces.

        Parameters
        ----------
        points : (k, 3) array_like of float

        Returns
        -------
        (k,) float64
        """
        from .basis import winding_number

        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.asarray(winding_number(p, self._vertices, self._faces), dtype=np.float64)

    def contains(self, points) -> np.ndarray:
        """Whether points lie inside the cage or on its surface.

        The one inside test (:func:`~vhm_viz.core.basis.classify_inside`): winding number
        at least 1/2, or within rounding of the surface (points computed on a face land a
        few ulps to either side of it).

        Parameters
        ----------
        points : (k, 3) or (3,) array_like of float

        Returns
        -------
        (k,) bool array
        """
        from .basis import classify_inside

        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return classify_inside(p, self._vertices, self._faces)[0]

    # --- misc
    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(n_vertices={self.n_vertices}, n_faces={self.n_faces}, "
            f"diagonal={self.diagonal:.4g})"
        )

    def __eq__(self, other) -> bool:
        """Compare vertices and faces exactly."""
        if not isinstance(other, Cage):
            return NotImplemented
        return np.array_equal(self._vertices, other._vertices) and np.array_equal(
            self._faces, other._faces
        )

    def __hash__(self) -> int:
        """Hash of the (immutable) vertex and face arrays, so cages can key caches."""
        return hash((self._vertices.tobytes(), self._faces.tobytes()))
