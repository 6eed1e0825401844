"""The cage's clearance: signed distances of the input to it, and pushing it out where short.

A cage built by simplification may cut into the clearance it should keep; :func:`push_out`
moves its vertices outward until every given point is at least its clearance inside.
Distances are exact (pseudo-normal signs, :mod:`vhm_viz.autocage.proximity`) and computed
only near the cage.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.autocage.proximity import NearDistance, grid_signed_distance

__all__ = ["signed_distances", "reaching_signed_distances", "push_out"]


def signed_distances(V, F, points, radius):
    """Signed distances of points to a closed, outward mesh, near it only.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        Closed, outward oriented 2-manifold.
    points : (N, 3) float array
    radius : float
        Points farther than this from the mesh are not evaluated (world units).

    Returns
    -------
    sd : (N,) float64
        Negative inside, ``inf`` beyond ``radius``.
    face : (N,) int64
        Nearest face, -1 beyond ``radius``.
    """
    return grid_signed_distance(NearDistance(V, F), points, radius)


def reaching_signed_distances(V, F, points, radius):
    """:func:`signed_distances`, the radius doubled until at least one point is within it.

    Returns
    -------
    sd : (N,) float64
        Negative inside, ``inf`` beyond the radius used.
    radius : float
        The radius used.
    """
    for _ in range(20):
        sd, _ = signed_distances(V, F, points, radius)
        if np.isfinite(sd).any():
            return sd, radius
        radius *= 2.0
    raise RuntimeError("no input point near the cage")  # pragma: no cover


def _vertex_normals(V, F):
    """Unit vertex normals, the faces' normals weighted by their areas."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area weighted
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def push_out(V, F, points, min_clear, radius, rounds=25):
    """Move cage vertices outward until every point is its ``min_clear`` inside.

    Each point closer than its ``min_clear`` (or outside) pushes the three vertices of
    its nearest face along their normals, far enough to move that face's plane by the
    missing distance (plus 20%), but at most the largest ``min_clear`` of the points that
    push it, per round: small steps with normals recomputed in between do not fold
    concave regions onto themselves, and near a narrow gap between parts (small
    ``min_clear``) the cage does not jump across the gap.

    Parameters
    ----------
    V : (n, 3) float array
    F : (m, 3) int array
        The cage: closed, outward oriented.
    points : (N, 3) float array
    min_clear : float or (N,) float array
        How far inside each point must end up (world units).
    radius : float
        Distances are evaluated within this radius of the cage only.
    rounds : int
        Most push rounds; fewer when the violations stop shrinking.

    Returns
    -------
    V : (n, 3) float64
        The moved vertices.
    sd : (N,) float64
        Signed distances of ``points`` to the moved cage (``inf`` beyond ``radius``).
    """
    V = V.copy()
    all_points = points
    all_clear = np.broadcast_to(np.asarray(min_clear, dtype=np.float64), (len(points),))
    points, min_clear = all_points, all_clear
    previous = None
    for it in range(rounds):
        sd, face = signed_distances(V, F, points, radius)
        if it == 0:
            # only points near the cage can be reached by the small steps below; the
            # others are checked again at the end
            near = np.isfinite(sd)
            points, min_clear, sd, face = points[near], min_clear[near], sd[near], face[near]
        viol = np.flatnonzero(np.isfinite(sd) & (sd > -min_clear))
        if len(viol) == 0:
            sd, _ = signed_distances(V, F, all_points, radius)
            if not (np.isfinite(sd) & (sd > -all_clear)).any():
                return V, sd
            near = np.isfinite(sd)  # a far point came near: carry on with them
            points, min_clear = all_points[near], all_clear[near]
            continue
        if previous is not None and it >= 2 and len(viol) > previous:
            break  # diverging (pushing one branch into another): give up early
        previous = len(viol)
        fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        vn = _vertex_normals(V, F)
        mc = min_clear[viol]
        deficit = 1.2 * (mc + sd[viol]) + 1e-3 * mc
        need = np.zeros(len(V))
        cap = np.zeros(len(V))
        fv = face[viol]
        for k in range(3):
            vk = F[fv, k]
            cos = np.einsum("ij,ij->i", vn[vk], fn[fv])
            np.maximum.at(need, vk, deficit / np.maximum(cos, 0.25))
            np.maximum.at(cap, vk, mc)
        V = V + vn * np.minimum(need, cap)[:, None]
    sd, _ = signed_distances(V, F, all_points, radius)
    return V, sd
