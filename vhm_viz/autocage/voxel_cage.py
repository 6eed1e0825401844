"""The ``"voxel"`` cage: the union of voxels within the clearance, coplanar faces merged.

The paper's Section 4 cage (uniform decomposition of space). The voxel size is the
largest one whose cage fits the face budget; :mod:`vhm_viz.autocage.voxel` builds the
well-composed voxel set and its merged, triangulated boundary.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.samples import InputSamples
from vhm_viz.autocage.voxel_surface import cage_surface, count_cage_faces

__all__ = ["voxel_cage"]


def _voxel_solid(samples: InputSamples, lo, hi, resolution, offset):
    """Well-composed voxel union for one resolution; returns (grid, solid)."""
    ext = float((hi - lo).max())
    h = ext / resolution
    off_vox = offset / h
    pad = int(np.ceil(max(off_vox, 1.0))) + 3
    grid = vx.make_grid(lo, hi, resolution, pad)
    solid = vx.make_well_composed(vx.grow(samples.voxelise(grid), off_vox))
    return grid, solid


def _fitting_solid(samples, lo, hi, offset, max_faces, resolution, notes):
    """(grid, solid) at ``resolution``, else at the finest one whose cage fits ``max_faces``."""
    ext = float((hi - lo).max())
    if resolution is not None:
        return _voxel_solid(samples, lo, hi, int(resolution), offset)
    # the clearance never needs voxels finer than offset / 2
    cap = int(min(256, max(2, np.ceil(2 * ext / offset))))
    cache = {}

    def faces_at(r):
        if r not in cache:
            g, s = _voxel_solid(samples, lo, hi, r, offset)
            cache[r] = (count_cage_faces(s), g, s)
        return cache[r][0]

    r, good, bad = 2, None, None
    while r <= cap:
        if faces_at(r) <= max_faces:
            good = r
            r = int(np.ceil(r * 1.5))
        else:
            bad = r
            break
    if good is None:
        raise ValueError(
            f"automatic cage: even the coarsest voxel cage needs {cache[2][0]} faces, more than "
            f"max_faces={max_faces} (the input has many separate parts); raise max_faces"
        )
    if bad is None:
        bad = cap + 1
    while bad - good > 1:
        mid = (good + bad) // 2
        if faces_at(mid) <= max_faces:
            good = mid
        else:
            bad = mid
    _, grid, solid = cache[good]
    notes.append(f"voxel resolution {good} ({cache[good][0]} faces)")
    return grid, solid


def voxel_cage(samples: InputSamples, lo, hi, offset, max_faces, resolution, notes):
    """The voxel cage of the samples.

    Parameters
    ----------
    samples : InputSamples
    lo, hi : (3,) float arrays
        The input's bounding box (world units).
    offset : float
        Clearance: every sample at least this far inside (world units).
    max_faces : int
        Face budget.
    resolution : int or None
        Voxels along the longest side; None picks the finest that fits ``max_faces``.
    notes : list of str
        The resolution picked is appended.

    Returns
    -------
    grid : Grid
    V : (n, 3) float64
    F : (m, 3) int64
        Closed, manifold, free of self-intersections (orientation not fixed yet).

    Raises
    ------
    ValueError
        Even the coarsest cage, or the one at ``resolution``, has more than ``max_faces``.
    """
    grid, solid = _fitting_solid(samples, lo, hi, offset, max_faces, resolution, notes)
    Vi, F = cage_surface(solid)
    if len(F) > max_faces:
        raise ValueError(
            f"automatic cage: the voxel cage at resolution {resolution} has {len(F)} faces, "
            f"more than max_faces={max_faces}"
        )
    return grid, grid.vertex_positions(Vi), F
