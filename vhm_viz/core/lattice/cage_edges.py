"""Cage edges in voxel index units: which cells and points lie near them (compiled).

Next to a cage edge the map has a logarithmic singularity: the build splits the cells
near an edge down to single voxels, and resampling polishes the pre-images near one on
the exact map.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(parallel=True, cache=True)
def cells_near_edges(cells, h, a, b, band, out):  # pragma: no cover - compiled
    """Whether each cell may come within ``band`` voxels of a cage edge.

    ``out[c]`` is True when a segment ``a[e] b[e]`` (voxel index units) meets the box
    ``[cells[c], cells[c] + h]`` grown by ``band``, tested conservatively: the distance
    from the cell's centre to the segment against ``band`` plus the half diagonal, after a
    bounding-box rejection.
    """
    reach = band + 0.8660254037844386 * h
    for c in numba.prange(cells.shape[0]):
        cx = cells[c, 0] + 0.5 * h
        cy = cells[c, 1] + 0.5 * h
        cz = cells[c, 2] + 0.5 * h
        hit = False
        for e in range(a.shape[0]):
            if (min(a[e, 0], b[e, 0]) > cx + reach or max(a[e, 0], b[e, 0]) < cx - reach
                    or min(a[e, 1], b[e, 1]) > cy + reach or max(a[e, 1], b[e, 1]) < cy - reach
                    or min(a[e, 2], b[e, 2]) > cz + reach or max(a[e, 2], b[e, 2]) < cz - reach):
                continue
            if _segment_distance2(cx, cy, cz, a, b, e) <= reach * reach:
                hit = True
                break
        out[c] = hit


def cage_edges_in_index(lat_geo, cage):
    """(E, 3) end points ``a``, ``b`` of the cage's edges in the lattice's index units."""
    e = cage.edges
    v = lat_geo.continuous_index(np.asarray(cage.vertices, dtype=np.float64))
    return np.ascontiguousarray(v[e[:, 0]]), np.ascontiguousarray(v[e[:, 1]])


# Edges are binned in cubes of this many voxels for :meth:`HermiteLattice.near_cage_edges`.
_EDGE_BIN = 4.0


def bin_edges(a, b, radius):
    """Bins of the edges ``a b`` (voxel index units) grown by ``radius``, as CSR lists.

    Returns ``lo`` (3,) the grid's first corner, ``shape`` (3,) bins per axis, ``start``
    (nbins + 1,) and ``ids`` (edge ids), bin ``(x, y, z)`` being ``x + nx (y + ny z)``.
    """
    if not len(a):
        return np.zeros(3), np.ones(3, np.int64), np.zeros(2, np.int64), np.zeros(0, np.int64)
    lo = np.minimum(a, b).min(axis=0) - radius
    hi = np.maximum(a, b).max(axis=0) + radius
    shape = np.maximum(1, np.ceil((hi - lo) / _EDGE_BIN).astype(np.int64))
    counts = np.zeros(int(np.prod(shape)) + 1, dtype=np.int64)
    _edge_bin_entries(a, b, radius, lo, shape, counts, np.zeros(0, np.int64), False)
    start = np.zeros(len(counts), dtype=np.int64)
    start[1:] = np.cumsum(counts[:-1])
    ids = np.empty(int(start[-1]), dtype=np.int64)
    _edge_bin_entries(a, b, radius, lo, shape, start.copy(), ids, True)
    return lo, shape, start, ids


@numba.njit(cache=True)
def _segment_distance2(px, py, pz, a, b, e):  # pragma: no cover - compiled
    """Squared distance from a point to segment ``a[e] b[e]``."""
    dx, dy, dz = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1], b[e, 2] - a[e, 2]
    qx, qy, qz = px - a[e, 0], py - a[e, 1], pz - a[e, 2]
    ll = dx * dx + dy * dy + dz * dz
    s = 0.0 if ll == 0.0 else min(1.0, max(0.0, (qx * dx + qy * dy + qz * dz) / ll))
    qx, qy, qz = qx - s * dx, qy - s * dy, qz - s * dz
    return qx * qx + qy * qy + qz * qz


@numba.njit(cache=True)
def _edge_bin_entries(a, b, radius, lo, shape, cursor, ids, fill):  # pragma: no cover
    """Count (``fill`` False) or write the edge ids of each bin the grown edge meets."""
    reach = radius + 0.8660254037844386 * _EDGE_BIN  # bin centre to anything in it
    for e in range(a.shape[0]):
        r0 = np.empty(3, np.int64)
        r1 = np.empty(3, np.int64)
        for ax in range(3):
            r0[ax] = max(0, int((min(a[e, ax], b[e, ax]) - radius - lo[ax]) // _EDGE_BIN))
            r1[ax] = min(shape[ax] - 1,
                         int((max(a[e, ax], b[e, ax]) + radius - lo[ax]) // _EDGE_BIN))
        for z in range(r0[2], r1[2] + 1):
            for y in range(r0[1], r1[1] + 1):
                for x in range(r0[0], r1[0] + 1):
                    cx = lo[0] + (x + 0.5) * _EDGE_BIN
                    cy = lo[1] + (y + 0.5) * _EDGE_BIN
                    cz = lo[2] + (z + 0.5) * _EDGE_BIN
                    if _segment_distance2(cx, cy, cz, a, b, e) > reach * reach:
                        continue
                    k = x + shape[0] * (y + shape[1] * z)
                    if fill:
                        ids[cursor[k]] = e
                    cursor[k] += 1


@numba.njit(parallel=True, cache=True)
def points_near_binned_edges(u, a, b, radius, lo, shape, start, ids, out):  # pragma: no cover
    """``out[p]``: point ``u[p]`` within ``radius`` of an edge of its bin."""
    r2 = radius * radius
    for p in numba.prange(u.shape[0]):
        x = int(math.floor((u[p, 0] - lo[0]) / _EDGE_BIN))
        y = int(math.floor((u[p, 1] - lo[1]) / _EDGE_BIN))
        z = int(math.floor((u[p, 2] - lo[2]) / _EDGE_BIN))
        if not (0 <= x < shape[0] and 0 <= y < shape[1] and 0 <= z < shape[2]):
            continue  # bins cover every edge grown by radius: nothing out there
        k = x + shape[0] * (y + shape[1] * z)
        for q in range(start[k], start[k + 1]):
            if _segment_distance2(u[p, 0], u[p, 1], u[p, 2], a, b, ids[q]) <= r2:
                out[p] = True
                break
