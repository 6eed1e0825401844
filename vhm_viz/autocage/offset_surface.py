"""The envelope of the ``"offset"`` cage: one offset surface per group of parts.

Parts of the input closer than the offset (or nested) form a group
(:mod:`vhm_viz.autocage.parts`); every group gets its own shell, the boundary of the union
of balls around its samples, of radius ``offset`` lowered to a third of the gap to the
nearest other group (:data:`GAP_SHARE`), extracted from a signed field (flying edges) on
the group's own grid. :func:`gap_midpoints` gives points in the open space between groups,
which every cage must leave outside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.parts import ShapeSamples, gap_to_other_groups, group_parts, merge_groups
from vhm_viz.core.scipy_extensions import kd_tree

__all__ = [
    "GAP_SHARE",
    "PartGroups",
    "make_groups",
    "nested_groups",
    "offset_surfaces",
    "gap_midpoints",
]


#: the clearance between two parts a gap ``g`` apart is at most ``g / 3``, so a third of
#: the gap stays open between their shells
GAP_SHARE = 1.0 / 3.0


def _group_inside(points, h, offset, spacing):
    """(grid, inside mask) of one group of samples: splatted, closed and filled."""
    grid = vx.make_grid(
        points.min(axis=0), points.max(axis=0), None, int(np.ceil(offset / h)) + 4, h
    )
    occ = vx.splat(grid, points)
    if spacing is not None:
        occ = vx.close_shell(occ, int(np.ceil(2 * spacing / h)) - 1)
    return grid, vx.fill_inside(occ)


def _group_offset_surface(points, clear, grid, inside, offset, solid_radius=None):
    """Surface at the local clearance ``clear`` outside one group of samples (PolyData).

    Outside the group the surface is the boundary of the union of the balls of radius
    ``clear[i]`` around the samples: the zero level of ``min_i |x - p_i| - clear[i]``
    (over the 8 nearest samples where the clearance varies). A sample whose clearance is a
    third of its gap to another group keeps its ball on its own side of that gap, so the
    surface never reaches the middle of a gap. Inside, the field is minus the distance to
    the nearest boundary sample minus its clearance: signed, it interpolates linearly
    across the surface, so the contour stays accurate where the clearance is much smaller
    than a voxel. Beyond a band around the surface, voxel distances stand in.

    ``inside`` (filled voxels holding samples) counts a voxel centre up to a voxel from
    the shape as inside; for point sets (volumes, clouds) ``solid_radius`` corrects that
    where the clearance varies (near another group): a centre farther than it from every
    sample is outside (at a coarse grid the error otherwise bulges the surface towards
    the close group).
    """
    # VTK (flying edges) is loaded on first use, so that importing the package stays light
    import pyvista as pv

    h = grid.h
    out_d = ndimage.distance_transform_edt(~inside) * h
    in_d = ndimage.distance_transform_edt(inside) * h
    cmax = float(clear.max())
    varies = bool(clear.min() < cmax)
    band_out = (~inside) & (out_d < cmax + 2 * h)
    band_in = inside & (in_d < 1.5 * h)
    field_ = np.where(inside, -in_d - cmax, out_d - cmax)
    idx = np.argwhere(band_out)
    if len(idx):
        k = min(8, len(points)) if varies else 1
        d, j = kd_tree(points).query(grid.centers(idx), k=k, workers=-1)
        field_[band_out] = (d - clear[j]).reshape(len(idx), k).min(axis=1)
    idx = np.argwhere(band_in)
    if len(idx):
        where = grid.centers(idx)
        d, j = kd_tree(points).query(where, k=1, workers=-1)
        values = -d - clear[j]
        if solid_radius is not None and varies:
            k = min(8, len(points))
            d, j = kd_tree(points).query(where, k=k, workers=-1)
            d, j = d.reshape(len(idx), k), j.reshape(len(idx), k)
            out = d[:, 0] > solid_radius
            values[out] = (d[out] - clear[j[out]]).min(axis=1)
        field_[band_in] = values
    # a pocket whose mouth the balls close over leaves a void inside the surface (an
    # inner shell that would be flipped outward, nested): the surface takes it in
    solid = ndimage.binary_fill_holes(field_ < 0)
    field_[solid & (field_ >= 0)] = -0.5 * h
    img = pv.ImageData(dimensions=grid.shape, spacing=(h, h, h), origin=grid.origin + 0.5 * h)
    img.point_data["f"] = field_.ravel(order="F")
    iso = img.contour([0.0], scalars="f", method="flying_edges").clean().triangulate()
    return iso, solid


def nested_groups(groups_inside, points, group):
    """Pairs (outer, inner) of groups whose samples lie inside another group's region.

    ``groups_inside`` holds a (grid, mask) per group: the filled voxels of its samples,
    or the inside of its offset surface (which can close over a pocket holding another
    group).
    """
    n = len(groups_inside)
    members = [np.flatnonzero(group == g) for g in range(n)]
    boxes = [(points[m].min(axis=0), points[m].max(axis=0)) for m in members]
    pairs = []
    for g, (grid, inside) in enumerate(groups_inside):
        lo = grid.origin
        hi = grid.origin + grid.h * np.asarray(grid.shape)
        for k in range(n):
            if k == g or np.any(boxes[k][0] > hi) or np.any(boxes[k][1] < lo):
                continue
            idx = np.floor((points[members[k]] - lo) / grid.h).astype(np.int64)
            ok = np.all((idx >= 0) & (idx < np.asarray(grid.shape)), axis=1)
            if inside[idx[ok, 0], idx[ok, 1], idx[ok, 2]].any():
                pairs.append((g, k))
    return pairs


@dataclass
class PartGroups:
    """Groups of parts that get one shell each, and the local clearance of every sample.

    Attributes
    ----------
    label : (N,) int array
        Group of every shape sample.
    count : int
        Number of groups.
    clear : (N,) float64
        Local clearance of every shape sample (world units).
    bridged : float
        Largest gap between parts that share a shell.
    kept : float
        Smallest gap between parts in different shells (``inf``: none near).
    inside : list of (Grid, (nx, ny, nz) bool)
        The filled voxels of every group's samples.
    """

    label: np.ndarray
    count: int
    clear: np.ndarray
    bridged: float
    kept: float
    inside: list


def make_groups(
    shape: ShapeSamples,
    offset: float,
    h: float,
    spacing,
    max_groups: int,
    merged=None,
    reach: float | None = None,
) -> PartGroups:
    """Group the parts (closer than ``offset``, or nested) and set local clearances.

    Parameters
    ----------
    shape : ShapeSamples
    offset : float
        Parts closer than this share a group (world units).
    h : float
        Voxel size of the groups' grids (small groups get finer ones).
    spacing : float or None
        Point sets: typical neighbour distance, to close their voxelisation.
    max_groups : int
        More groups than this raise RuntimeError.
    merged : PartGroups, optional
        Groups whose labels were merged further: skips the distance grouping.
    reach : float, optional
        How far apart to look for pairs of parts (see :func:`group_parts`).

    Returns
    -------
    PartGroups
    """
    if merged is None:
        group, count, bridged, kept = group_parts(shape, offset, reach)
    else:
        group, count, bridged = merged.label, merged.count, merged.bridged
    if count > max_groups:
        raise RuntimeError(
            f"{count} parts farther apart than the offset need more than {max_groups} shells"
        )
    while True:
        inside = []
        for g in range(count):
            pts = shape.points[group == g]
            # a small part (a speck of a volume) gets a grid fine enough to resolve the
            # ball around it: a coarse octahedron would have to grow far to enclose it
            hg = min(h, (float(np.ptp(pts, axis=0).max()) + 2.0 * offset) / 16.0)
            inside.append(_group_inside(pts, hg, offset, spacing))
        nested = nested_groups(inside, shape.points, group) if count > 1 else []
        if not nested:
            break
        group, count = merge_groups(group, nested)
    if count > 1:
        gap = gap_to_other_groups(shape.points, group, 3.0 * offset)
        clear = np.minimum(offset, GAP_SHARE * gap)
        finite = np.isfinite(gap)
        kept = float(gap[finite].min()) if finite.any() else float("inf")
    else:
        clear = np.full(len(shape.points), float(offset))
        kept = float("inf")
    return PartGroups(group, count, clear, bridged, kept, inside)


def offset_surfaces(shape: ShapeSamples, groups: PartGroups, offset: float, solid_radius=None):
    """Offset surface of every group at the groups' local clearance.

    Returns
    -------
    meshes : list of PolyData
        One per group.
    solids : list of (Grid, (nx, ny, nz) bool)
        The voxels inside each surface.
    """
    meshes, solids = [], []
    for g in range(groups.count):
        sel = groups.label == g
        grid, inside = groups.inside[g]
        iso, solid = _group_offset_surface(
            shape.points[sel],
            groups.clear[sel],
            grid,
            inside,
            offset,
            solid_radius,
        )
        if iso.n_cells == 0:
            raise RuntimeError(f"empty offset surface for part group {g}")
        meshes.append(iso)
        solids.append((grid, solid))
    return meshes, solids


def gap_midpoints(shape: ShapeSamples, groups: PartGroups, limit: int = 20_000) -> np.ndarray:
    """Points halfway between samples and the nearest sample of another group.

    They lie in the open space between two parts; the cage must leave them outside. At
    most ``limit`` of them (the narrowest gaps first).
    """
    if groups.count < 2:
        return np.empty((0, 3))
    tight = np.flatnonzero(groups.clear < np.max(groups.clear))
    if len(tight) == 0:
        return np.empty((0, 3))
    tight = tight[np.argsort(groups.clear[tight], kind="stable")[:limit]]
    mids = []
    for g in np.unique(groups.label[tight]):
        mine = tight[groups.label[tight] == g]
        others = np.flatnonzero(groups.label != g)
        _, j = kd_tree(shape.points[others]).query(shape.points[mine])
        mids.append(0.5 * (shape.points[mine] + shape.points[others[j]]))
    return np.concatenate(mids)
