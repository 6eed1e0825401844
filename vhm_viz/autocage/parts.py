"""Separate parts of an input and the gaps between them, for gap-preserving cages.

A *part* is a connected piece of the input: a connected component of a surface (or of a
tet mesh's boundary), a 26-connected region of a thresholded volume, or a cluster of a
point cloud. :func:`automatic cages <vhm_viz.autocage.cage.auto_cage>` give parts that are
farther apart than the clearance separate shells, and shrink the clearance between them
so that the space between parts stays outside the cage:

* :func:`shape_samples` -- the input's points on its boundary plus samples on its
  triangles, each with the part it belongs to (the cage comes closest to the boundary, and
  the nearest point of one part to another lies on it);
* :func:`group_parts` -- parts closer than a distance merged into groups (one shell each),
  exactly: by nearest-sample distances, never by voxels;
* :func:`gap_to_other_groups` -- for every sample, the distance to the nearest sample of
  another group (the gap the cage must keep open there).

Everything here is numbers (numpy/scipy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.mesh import edge_components
from vhm_viz.core.scipy_extensions import kd_tree

__all__ = ["ShapeSamples", "shape_samples", "group_parts", "gap_to_other_groups"]


@dataclass
class ShapeSamples:
    """Points on a shape's boundary, with the part each belongs to.

    Attributes
    ----------
    points : (N, 3) float64
        The input's points on the boundary first (``n_input`` of them: a surface's
        vertices, a tet mesh's surface points, a volume region's rim voxels, every cloud
        point), then samples on its triangles.
    n_input : int
        How many of ``points`` are input points.
    part : (N,) int64
        Part label of every point, ``0 .. n_parts - 1``.
    n_parts : int
    """

    points: np.ndarray
    n_input: int
    part: np.ndarray
    n_parts: int


def _components(n: int, edges: np.ndarray) -> np.ndarray:
    """Connected component of each of ``n`` vertices joined by ``edges``."""
    return edge_components(n, edges)[1]


def _compact_labels(labels: np.ndarray) -> tuple[np.ndarray, int]:
    uniq, inv = np.unique(labels, return_inverse=True)
    return inv.reshape(labels.shape).astype(np.int64), len(uniq)


def shape_samples(samples, spacing: float) -> ShapeSamples:
    """The input's boundary points and triangle samples, labelled by part.

    Parameters
    ----------
    samples : vhm_viz.autocage.cage.InputSamples
        The input (``part`` set for volumes; ``spacing`` set for point clouds).
    spacing : float
        Largest distance between triangle samples (world units).

    Returns
    -------
    ShapeSamples
    """
    pts = np.asarray(samples.points, dtype=np.float64)
    n_in = len(pts)
    if samples.tri_faces is not None and len(samples.tri_faces):
        tv, tf = samples.tri_vertices, samples.tri_faces
        edges = np.concatenate([tf[:, [0, 1]], tf[:, [1, 2]]])
        vlab = _components(len(tv), edges)
        extra, owner = vx.sample_triangles(tv, tf, spacing, return_faces=True)
        # input points are the surface's vertices (surfaces) or the tet mesh's points,
        # which lie inside the component whose boundary vertex is nearest
        used = np.unique(tf)
        dist, near = kd_tree(tv[used]).query(pts)
        on = dist == 0  # a tet mesh's inner points are not on its boundary
        part, n_parts = _compact_labels(np.concatenate([vlab[used[near[on]]], vlab[tf[owner, 0]]]))
        return ShapeSamples(np.concatenate([pts[on], extra]), int(on.sum()), part, n_parts)
    if samples.part is not None:  # volumes: regions labelled on the image, rim voxels
        rim = (
            np.asarray(samples.boundary, dtype=bool)
            if samples.boundary is not None
            else np.ones(n_in, dtype=bool)
        )
        part, n_parts = _compact_labels(np.asarray(samples.part)[rim])
        return ShapeSamples(pts[rim], int(rim.sum()), part, n_parts)
    # point clouds: points within twice the typical spacing are connected
    step = 2.0 * float(samples.spacing or 0.0)
    if step > 0 and n_in > 1:
        pairs = kd_tree(pts).query_pairs(step, output_type="ndarray")
        part, n_parts = _compact_labels(_components(n_in, pairs))
    else:
        part, n_parts = np.zeros(n_in, dtype=np.int64), 1
    return ShapeSamples(pts, n_in, part, n_parts)


def _bbox(points: np.ndarray, labels: np.ndarray, n: int):
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    for k in range(3):
        np.minimum.at(lo[:, k], labels, points[:, k])
        np.maximum.at(hi[:, k], labels, points[:, k])
    return lo, hi


def _close_pairs(points, labels, n, radius):
    """Label pairs ``(a, b, distance)`` whose nearest samples are within ``radius``.

    Exact nearest-sample distances: for every label, one k-d tree query of the samples
    of all smaller labels whose boxes come within ``radius`` of its box (and that lie in
    its box grown by ``radius``).
    """
    lo, hi = _bbox(points, labels, n)
    gap = np.maximum(0.0, np.maximum(lo[:, None, :] - hi[None, :, :], lo[None] - hi[:, None]))
    near = np.linalg.norm(gap, axis=2) <= radius
    np.fill_diagonal(near, False)
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n + 1))
    size = np.diff(starts)
    out = []
    for a in np.flatnonzero(near.any(axis=1)):
        # the larger label of each pair queries the smaller ones (ties: the lower index)
        partners = np.flatnonzero(
            near[a] & ((size < size[a]) | ((size == size[a]) & (np.arange(n) > a)))
        )
        if len(partners) == 0:
            continue
        q = np.concatenate([order[starts[b] : starts[b + 1]] for b in partners])
        qlab = labels[q]
        inside = np.all((points[q] >= lo[a] - radius) & (points[q] <= hi[a] + radius), axis=1)
        if not inside.any():
            continue
        q, qlab = q[inside], qlab[inside]
        d, _ = kd_tree(points[order[starts[a] : starts[a + 1]]]).query(
            points[q], distance_upper_bound=radius
        )
        best = np.full(n, np.inf)
        np.minimum.at(best, qlab, d)
        out += [(int(a), int(b), float(best[b])) for b in np.flatnonzero(np.isfinite(best))]
    return out


def group_parts(
    shape: ShapeSamples, distance: float, reach: float | None = None
) -> tuple[np.ndarray, int, float, float]:
    """Merge parts closer than ``distance`` (nearest samples) into groups.

    Parameters
    ----------
    shape : ShapeSamples
    distance : float
        Parts whose nearest samples are at most this far apart share a group (world units).
    reach : float, optional
        How far apart to look for pairs of parts (default ``3 * distance``); the pairs
        found are kept on ``shape`` and reused by later calls that reach no farther.

    Returns
    -------
    group : (N,) int64
        Group of every sample, ``0 .. n_groups - 1`` (largest group first).
    n_groups : int
    bridged : float
        Largest gap between two parts that were merged (0 if none).
    kept : float
        Smallest gap between two parts left in different groups, as far as it is below
        ``3 * distance`` (``inf`` otherwise).
    """
    n = shape.n_parts
    if n == 1:
        return np.zeros(len(shape.points), dtype=np.int64), 1, 0.0, float("inf")
    reach = max(3.0 * distance, reach or 0.0)
    cached = getattr(shape, "_pairs", None)
    if cached is None or cached[0] < reach:
        shape._pairs = (reach, _close_pairs(shape.points, shape.part, n, reach))
    pairs = [(a, b, d) for a, b, d in shape._pairs[1] if d <= 3.0 * distance]
    close = [(a, b, d) for a, b, d in pairs if d <= distance]
    if close:
        e = np.array([(a, b) for a, b, _ in close], dtype=np.int64)
        lab = _components(n, e)
    else:
        lab = np.arange(n)
    bridged = max((d for _, _, d in close), default=0.0)
    kept = min((d for a, b, d in pairs if lab[a] != lab[b]), default=float("inf"))
    group = lab[shape.part]
    # number the groups by size, largest first (stable, reproducible shell order)
    uniq, inv, counts = np.unique(group, return_inverse=True, return_counts=True)
    rank = np.empty(len(uniq), dtype=np.int64)
    rank[np.argsort(-counts, kind="stable")] = np.arange(len(uniq))
    return rank[inv], len(uniq), float(bridged), float(kept)


def merge_groups(group: np.ndarray, pairs) -> tuple[np.ndarray, int]:
    """Merge groups ``(a, b)`` of ``pairs``; returns the new labels and their count."""
    n = int(group.max()) + 1
    e = np.asarray(list(pairs), dtype=np.int64).reshape(-1, 2)
    lab = _components(n, e) if len(e) else np.arange(n)
    return _compact_labels(lab[group])


def gap_to_other_groups(points: np.ndarray, group: np.ndarray, radius: float) -> np.ndarray:
    """Distance from every boundary sample to the nearest one of another group.

    Parameters
    ----------
    points : (N, 3) float64
    group : (N,) int64
    radius : float
        Distances above this are not needed: ``inf`` is returned for them.

    Returns
    -------
    (N,) float64
    """
    n = int(group.max()) + 1 if len(group) else 0
    out = np.full(len(points), np.inf)
    if n < 2:
        return out
    lo, hi = _bbox(points, group, n)
    order = np.argsort(group, kind="stable")
    starts = np.searchsorted(group[order], np.arange(n + 1))
    members = [order[starts[k] : starts[k + 1]] for k in range(n)]
    rims = members

    def within(idx, lo_, hi_):
        return idx[np.all((points[idx] >= lo_) & (points[idx] <= hi_), axis=1)]

    for a in range(n):
        others = [
            within(rims[b], lo[a] - radius, hi[a] + radius)
            for b in range(n)
            if b != a and np.all(lo[b] <= hi[a] + radius) and np.all(hi[b] >= lo[a] - radius)
        ]
        others = np.concatenate(others) if others else np.empty(0, dtype=np.int64)
        if len(others) == 0:
            continue
        mine = within(
            members[a], points[others].min(axis=0) - radius, points[others].max(axis=0) + radius
        )
        if len(mine):
            d, _ = kd_tree(points[others]).query(points[mine], distance_upper_bound=radius)
            out[mine] = d
    return out
