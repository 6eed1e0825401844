"""Validation of a triangle mesh as a cage: closed, oriented outward, embedded.

Checks, in the order they are made (the most basic problem is reported first):

1. array shapes and dtypes (``vertices`` (n, 3) real, ``faces`` (m, 3) integer),
2. finite coordinates,
3. face indices in range,
4. at least 4 vertices and 4 faces,
5. degenerate faces (area below ``area_rtol * diagonal**2``, repeated indices included),
   and near-degenerate ones ("slivers", :data:`MIN_FACE_ANGLE`), checked after the
   orientation (9a below),
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

import numpy as np

from vhm_viz.core.components import edge_components
from vhm_viz.core.errors import CageError, describe_indices
from vhm_viz.core.geometry import face_normals_and_areas, signed_volume
from vhm_viz.core.inside import winding_number
from vhm_viz.core.self_intersection import DIST_RTOL, self_intersections
from vhm_viz.core.slivers import SliverError, face_angles

__all__ = ["AREA_RTOL", "DIST_RTOL", "as_cage_arrays", "edge_table", "validate_cage"]

#: Faces with area below ``AREA_RTOL * diagonal**2`` are degenerate.
AREA_RTOL = 1e-12


def _fmt_pairs(pairs: np.ndarray, limit: int = 6) -> str:
    shown = ", ".join(f"({int(a)}, {int(b)})" for a, b in pairs[:limit])
    if len(pairs) > limit:
        shown += f", ... ({len(pairs)} in all)"
    return shown


def as_cage_arrays(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes and types of cage arrays; return them as float64 and int64.

    Parameters
    ----------
    vertices : (n, 3) array_like of real numbers
    faces : (m, 3) array_like of int (integral floats accepted)

    Returns
    -------
    vertices : (n, 3) float64
    faces : (m, 3) int64

    Raises
    ------
    CageError
        When the arrays cannot be cage arrays (the first two checks of
        :func:`validate_cage`).
    """
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


def edge_table(f: np.ndarray):
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
    v, f = as_cage_arrays(vertices, faces)
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

    he, he_face, edges, inverse, counts = edge_table(f)
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
    ncomp, comp = edge_components(m, np.stack([f0, f1], axis=1))
    src = np.concatenate([f0, f0 + m])
    dst = np.concatenate([f1 + m * same_dir, f1 + m * (~same_dir)])
    _, lab = edge_components(2 * m, np.stack([src, dst], axis=1))
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
