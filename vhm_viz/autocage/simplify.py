"""Topology-safe quadric edge-collapse simplification (compiled; Python reference).

VTK's quadric decimation is fast but does not check the link condition, so at high
reduction it can pinch thin tubes (fingers) into non-manifold edges. :func:`simplify`
finishes the job from a moderately decimated, valid mesh: every collapse keeps the mesh a
closed 2-manifold (link condition), never flips a face, and never leaves a component with
fewer than 4 vertices (or a chosen minimum); optionally it refuses collapses that make faces
touch (:mod:`vhm_viz.autocage.collapse_guard`).

The collapse loop is compiled (:mod:`vhm_viz.autocage.edge_collapse`), which makes the
automatic cage's retries cheap; it runs the same algorithm in the same heap order as the
pure-Python reference (:mod:`vhm_viz.autocage.edge_collapse_reference`,
``backend="python"``). The first call in a fresh environment compiles it (cached on disk
afterwards).
"""

from __future__ import annotations

import numpy as np

from vhm_viz.autocage.edge_collapse import collapse_edges
from vhm_viz.autocage.edge_collapse_reference import collapse_edges_reference
from vhm_viz.autocage.mesh import compact, edge_components, face_edges
from vhm_viz.core.cage import DIST_RTOL

__all__ = ["simplify", "plane_quadrics"]


def plane_quadrics(V, F):
    """Garland-Heckbert quadrics: per vertex, the area-weighted sum of its faces' planes.

    Parameters
    ----------
    V, F : (n, 3) float array, (m, 3) int array
        The triangle mesh.

    Returns
    -------
    (n, 4, 4) float64
        ``Q[i]`` such that ``[x, 1] @ Q[i] @ [x, 1]`` is the area-weighted sum of squared
        distances from ``x`` to the planes of the faces around vertex ``i``.
    """
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area = 0.5 * np.linalg.norm(n, axis=1)
    n = n / np.maximum(2 * area, 1e-300)[:, None]
    d = -np.einsum("ij,ij->i", n, V[F[:, 0]])
    p = np.concatenate([n, d[:, None]], axis=1)  # (m, 4)
    q = (area[:, None, None] * p[:, :, None] * p[:, None, :]).reshape(-1, 16)
    # summed per vertex by bincount, one column of the 4x4 blocks at a time
    idx = F.ravel()
    Q = np.stack(
        [np.bincount(idx, weights=np.repeat(q[:, e], 3), minlength=len(V)) for e in range(16)],
        axis=1,
    )
    return Q.reshape(len(V), 4, 4)


def _components(n: int, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Connected component of every vertex, and the vertex count of every component."""
    _, comp = edge_components(n, face_edges(F))
    comp = comp.astype(np.int64)
    return comp, np.bincount(comp[np.unique(F)], minlength=int(comp.max()) + 1)


def _clash_tolerance(V) -> float:
    """Contact distance of the intersection guard: the cage validator's."""
    return DIST_RTOL * float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def simplify(
    vertices,
    faces,
    target_faces: int,
    max_normal_turn: float = 0.2,
    outside: bool = False,
    no_intersections: bool = False,
    min_component_vertices: int = 4,
    backend: str = "numba",
):
    """Collapse edges (cheapest quadric error first) until ``target_faces`` remain.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (m, 3) int array
        A closed, consistently oriented 2-manifold.
    target_faces : int
        Stop at or below this many faces (or when no collapse is allowed).
    max_normal_turn : float
        A collapse is refused when a surrounding face's unit normal would change by a dot
        product below this value (0.2 ~ 78 degrees), or would vanish.
    outside : bool
        Only place a collapsed vertex on the outer side of the planes of all faces around
        the collapsed edge (Calderon and Boubekeur's bounding condition), so the simplified
        surface stays (locally) outside the original; moved outward along the mean normal
        when needed, refused when impossible.
    no_intersections : bool
        Refuse a collapse that makes a moved face touch another face (the contact test
        of :func:`vhm_viz.core.cage.self_intersections`) or sweeps the surface over
        another connected component (which would end up nested), so a mesh of disjoint,
        non-nested shells stays one. A brute-force check per collapse: fine for
        the few thousand faces the automatic cage simplifies.
    min_component_vertices : int
        No connected component is collapsed below this many vertices (4, a tetrahedron,
        at least; 6 keeps small shells octahedra, which enclose what they surround more
        tightly).
    backend : {"numba", "python"}
        ``"numba"`` (compiled, default) or ``"python"`` (the reference implementation of
        the same algorithm; slow, used to test the compiled one).

    Returns
    -------
    vertices : (n', 3) float64
    faces : (m', 3) int64
    """
    if backend not in ("numba", "python"):
        raise ValueError(f"simplify: unknown backend {backend!r} (numba, python)")
    V = np.array(vertices, dtype=np.float64)
    F = np.array(faces, dtype=np.int64)
    if len(F) == 0:
        return V[:0], F.reshape(0, 3)
    Q = plane_quadrics(V, F)
    tol = _clash_tolerance(V) if no_intersections else -1.0
    comp, comp_size = _components(len(V), F)
    min_verts = max(4, int(min_component_vertices))
    args = (V, F, Q, int(target_faces), float(max_normal_turn), bool(outside))
    if backend == "python":
        alive = collapse_edges_reference(*args, tol, comp, comp_size, min_verts)
    else:
        alive = collapse_edges(*args, 16, tol, comp, comp_size, min_verts)
    V, F = compact(V, F[alive])
    return V, F.astype(np.int64)
