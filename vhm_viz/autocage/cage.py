"""Automatic cages: :func:`auto_cage` builds a valid enclosing cage for any input.

Two methods, tried in this order by ``method="auto"``:

``"offset"`` (shape-following)
    The input is voxelised (surface samples, points, tet-mesh boundary or the region of a
    volume above a threshold; inside filled by a flood fill from outside), the exact
    distance to the input samples is computed near an offset surface at distance
    ``offset``, that surface is extracted (flying edges) and simplified to ``max_faces``
    with quadric decimation. Where the simplification cut into the clearance, cage
    vertices are pushed outward until every input point is at least ``min_clearance``
    inside. The result is checked (closed, 2-manifold, outward, no self-intersection,
    winding number 1 at every input point); any failure falls back to ``"voxel"``.

``"voxel"`` (the paper's Section 4 cage: uniform decomposition of space with coplanar
faces merged)
    The union of the voxels within the clearance of the input, made well composed, its
    boundary squares merged into maximal coplanar polygons and triangulated. Valid by
    construction; coarser (the voxel size is the largest one that fits ``max_faces``).

Both keep parts apart when they are farther apart than about twice the clearance, so
fingers and legs get their own cage branches (paper Figure 11).
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.meshcheck import edge_problems
from vhm_viz.autocage.parts import (
    ShapeSamples,
    gap_to_other_groups,
    group_parts,
    merge_groups,
    shape_samples,
)
from vhm_viz.autocage.proximity import NearDistance, grid_signed_distance
from vhm_viz.autocage.simplify import simplify
from vhm_viz.core.basis import winding_number
from vhm_viz.core.cage import self_intersections
from vhm_viz.core.errors import CageError

__all__ = ["auto_cage", "AutoCageReport", "InputSamples", "collect_samples"]

#: more self-intersecting face pairs than this in the simplified offset surface (before
#: the push-out) means the offset is too small for the shape's gaps: skip the retries
_MAX_CROSSINGS = 12


# ---------------------------------------------------------------------------------------
# input
# ---------------------------------------------------------------------------------------


@dataclass
class InputSamples:
    """What an input contributes to a cage.

    Attributes
    ----------
    points : (N, 3) float64
        Points the cage must enclose (vertices, cloud points, voxel centres, ...).
    tri_vertices, tri_faces : arrays or None
        A triangle surface whose inside is part of the shape (surfaces, tet boundaries).
    kind : str
        ``"surface"``, ``"points"``, ``"tetmesh"``, ``"volume"`` or ``"volume-box"``.
    spacing : float or None
        Typical distance between neighbouring points for point sets (clouds, volumes),
        used to close their voxelisation; None for surfaces.
    threshold : float or None
        Volumes: the threshold the region was selected with (Otsu's value resolved).
    part, boundary : (N,) arrays or None
        Volumes: the 26-connected region of every point, and whether it is on the region's
        rim (see :mod:`vhm_viz.autocage.parts`).
    """

    points: np.ndarray
    tri_vertices: np.ndarray | None = None
    tri_faces: np.ndarray | None = None
    kind: str = "points"
    spacing: float | None = None
    threshold: float | None = None
    part: np.ndarray | None = None
    boundary: np.ndarray | None = None


def _otsu(values: np.ndarray) -> float:
    v = np.asarray(values).ravel()
    if v.dtype.kind == "f":
        v = v[np.isfinite(v)]
    hist, edges = np.histogram(v, bins=256)
    centers = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centers)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = w0 * w1 * (mu0 - mu1) ** 2
    return float(edges[1:][np.argmax(between)])


def _check_points(points: np.ndarray, what: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{what}: expected points of shape (N, 3), got {p.shape}")
    if len(p) == 0:
        raise ValueError(f"{what}: the input is empty (no points)")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(
            f"{what}: {len(idx)} point(s) have non-finite (NaN/inf) coordinates, "
            f"first indices {idx[:10].tolist()}"
        )
    if len(p) == 1:
        raise ValueError(f"{what}: a single point has no extent; a cage needs a 3D shape")
    c = p - p.mean(axis=0)
    ext = float(np.ptp(p, axis=0).max())
    if ext == 0:
        raise ValueError(f"{what}: all points coincide; a cage needs a 3D shape")
    sample = c if len(c) <= 200_000 else c[:: len(c) // 200_000 + 1]
    sv = np.linalg.svd(sample, compute_uv=False)
    if sv[-1] <= 1e-9 * sv[0] or sv.size < 3:
        kind = "collinear" if sv[1] <= 1e-9 * sv[0] else "coplanar"
        raise ValueError(
            f"{what}: all points are {kind} (no volume to enclose); a cage needs a 3D shape"
        )
    return p


def _volume_points(ds, index: np.ndarray, on_cells: bool) -> tuple[np.ndarray, float]:
    """Positions of the volume samples ``index`` (points, or cell centres) and their spacing.

    Image data are computed from the indices (materialising every point of a 256^3 image
    costs seconds and 400 MB); other grids use their points or cell centres.
    """
    import pyvista as pv

    if isinstance(ds, pv.ImageData):
        dims = np.asarray(ds.dimensions) - (1 if on_cells else 0)
        ijk = np.stack(np.unravel_index(index, tuple(dims[::-1])), axis=1)[:, ::-1]
        local = (ijk + (0.5 if on_cells else 0.0)) * np.asarray(ds.spacing, dtype=np.float64)
        direction = np.asarray(ds.direction_matrix, dtype=np.float64)
        pts = np.asarray(ds.origin, dtype=np.float64) + local @ direction.T
        return pts, float(np.max(ds.spacing))
    pts = np.asarray(ds.cell_centers().points if on_cells else ds.points, dtype=np.float64)
    dims = np.maximum(np.asarray(ds.dimensions) - 1, 1)
    return pts[index], float(np.max(np.ptp(pts, axis=0) / dims))


def _region_labels(mask: np.ndarray, dims, index: np.ndarray):
    """26-connected region of every selected sample, and whether it is on the region's rim.

    ``mask`` is the flat selection in VTK order (x fastest) of a ``dims`` lattice; the
    rim samples have a face neighbour outside the region (or on the lattice border).
    """
    from scipy import ndimage

    m = np.asarray(mask, dtype=bool).reshape(tuple(int(d) for d in dims[::-1]))
    labels, _ = ndimage.label(m, structure=np.ones((3, 3, 3), dtype=bool))
    rim = m & ~ndimage.binary_erosion(m, border_value=0)
    return labels.ravel()[index] - 1, rim.ravel()[index]


def collect_samples(data, *, threshold=None, scalars=None, what="auto_cage") -> InputSamples:
    """Turn any supported input into :class:`InputSamples`.

    Parameters
    ----------
    data : pyvista/VTK dataset, (N, 3) array, ``(vertices, faces)`` tuple or file path
        PolyData with polygons is a surface, without polygons a point cloud;
        UnstructuredGrid a tet mesh (its points and boundary surface); ImageData (and other
        grids) a volume: its bounding box when ``threshold`` is None, else the points whose
        scalar is above ``threshold`` (``"otsu"`` picks Otsu's threshold).
    threshold : float, "otsu" or None
        Volumes only.
    scalars : str, optional
        Name of the volume's scalar array (default: the active one).
    what : str
        Prefix for error messages.

    Returns
    -------
    InputSamples

    Raises
    ------
    ValueError
        Empty input, non-finite coordinates, a single point, coplanar or collinear points,
        an unsupported type or a threshold that selects nothing.
    """
    if isinstance(data, (str, os.PathLike)):
        from vhm_viz.io import read_dataset

        data = read_dataset(data)
    if isinstance(data, tuple) and len(data) == 2:
        verts = _check_points(data[0], what)
        faces = np.asarray(data[1])
        if faces.size == 0:
            return InputSamples(points=verts, kind="points")
        faces = faces.astype(np.int64).reshape(-1, 3)
        if faces.min() < 0 or faces.max() >= len(verts):
            raise ValueError(f"{what}: face indices out of range")
        used = np.unique(faces)
        return InputSamples(points=verts[used], tri_vertices=verts, tri_faces=faces, kind="surface")
    if isinstance(data, np.ndarray) or isinstance(data, list):
        return InputSamples(points=_check_points(data, what), kind="points")

    import pyvista as pv

    try:
        ds = data if isinstance(data, pv.DataSet) else pv.wrap(data)
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"{what}: unsupported input type {type(data).__name__}") from exc
    if ds is None or not isinstance(ds, pv.DataSet):
        raise ValueError(f"{what}: unsupported input type {type(data).__name__}")
    if ds.n_points == 0:
        raise ValueError(f"{what}: the input is empty (no points)")

    if isinstance(ds, (pv.ImageData, pv.RectilinearGrid, pv.StructuredGrid)):
        if threshold is None:
            b = np.asarray(ds.bounds, dtype=np.float64).reshape(3, 2)
            corners = np.array([[x, y, z] for x in b[0] for y in b[1] for z in b[2]])
            _check_points(corners, what)
            return InputSamples(points=corners, kind="volume-box")
        name = scalars or ds.active_scalars_name or (ds.array_names[0] if ds.array_names else None)
        if name is None:
            raise ValueError(f"{what}: the volume has no scalars to threshold")
        vals = np.asarray(ds.get_array(name))
        if vals.ndim > 1:
            vals = np.linalg.norm(vals, axis=1)
        on_cells = len(vals) == ds.n_cells and len(vals) != ds.n_points
        thr = (
            _otsu(vals)
            if (isinstance(threshold, str) and threshold.lower() == "otsu")
            else float(threshold)
        )
        sel = np.flatnonzero(vals > thr)
        if not len(sel):
            raise ValueError(f"{what}: no voxel of '{name}' is above the threshold {thr:g}")
        pts, spacing = _volume_points(ds, sel, on_cells)
        part, boundary = _region_labels(vals > thr, np.asarray(ds.dimensions) - on_cells, sel)
        return InputSamples(
            points=_check_points(pts, what),
            kind="volume",
            spacing=spacing,
            threshold=thr,
            part=part,
            boundary=boundary,
        )

    pts = _check_points(np.asarray(ds.points, dtype=np.float64), what)
    if isinstance(ds, pv.PolyData):
        if ds.GetNumberOfPolys() > 0 or ds.GetNumberOfStrips() > 0:
            surf = ds.triangulate()
            faces = (
                surf.regular_faces
                if hasattr(surf, "regular_faces")
                else surf.faces.reshape(-1, 4)[:, 1:]
            )
            used = np.unique(faces)
            return InputSamples(
                points=pts[used] if len(used) >= 2 else pts,
                tri_vertices=np.asarray(surf.points, dtype=np.float64),
                tri_faces=np.asarray(faces, dtype=np.int64),
                kind="surface",
            )
        return InputSamples(points=pts, kind="points")
    if isinstance(ds, (pv.UnstructuredGrid, pv.ExplicitStructuredGrid)):
        if ds.n_cells == 0:
            return InputSamples(points=pts, kind="points")
        surf = ds.extract_surface(algorithm="dataset_surface").triangulate()
        faces = (
            np.asarray(surf.faces).reshape(-1, 4)[:, 1:] if surf.n_cells else np.empty((0, 3), int)
        )
        return InputSamples(
            points=pts,
            tri_vertices=np.asarray(surf.points, dtype=np.float64),
            tri_faces=faces.astype(np.int64),
            kind="tetmesh",
        )
    return InputSamples(points=pts, kind="points")


def _point_spacing(points: np.ndarray) -> float:
    """A generous typical neighbour distance of a point set (90th percentile of NN)."""
    p = points if len(points) <= 50_000 else points[:: len(points) // 50_000 + 1]
    d, _ = cKDTree(p).query(p, k=2)
    return float(np.percentile(d[:, 1], 90))


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------


@dataclass
class AutoCageReport:
    """What :func:`auto_cage` built and how well it encloses the input.

    Attributes
    ----------
    method : str
        ``"offset"`` or ``"voxel"`` (the one that produced the cage).
    n_vertices, n_faces : int
    offset : float
        Requested clearance (world units).
    clearance : float
        Smallest distance from an input point to the cage (world units, > 0).
    clearance_relative : float
        ``clearance`` divided by the input's bounding-box diagonal.
    min_winding_number : float
        Smallest generalized winding number over the input points (1 when enclosed).
    enclosed : bool
        Every input point strictly inside (winding number > 0.5 and clearance > 0).
    voxel_size : float
        Grid spacing used.
    grid_shape : tuple of int
    n_points : int
        Input points checked.
    n_components : int
        Connected components (shells) of the cage.
    offset_used : float
        The clearance the cage was built for (the requested ``offset``, or twice it when
        the first attempt failed); parts farther apart than it get separate shells.
    n_parts : int
        Separate parts of the input (surface components, volume regions, point clusters).
    bridged_gap : float
        Largest gap between two parts that share a shell (0 if none; at most
        ``offset_used``; NaN for the voxel and box methods, which do not track parts).
    min_gap_kept : float
        Smallest gap between two parts in different shells (``inf`` when no two shells are
        within three clearances; NaN for the voxel and box methods). The cage's clearance
        there is at most a third of the gap.
    seconds : float
        Wall time of the whole call.
    notes : list of str
        Fallbacks taken and why.
    """

    method: str
    n_vertices: int
    n_faces: int
    offset: float
    clearance: float
    clearance_relative: float
    min_winding_number: float
    enclosed: bool
    voxel_size: float
    grid_shape: tuple
    n_points: int
    n_components: int
    offset_used: float = float("nan")
    n_parts: int = 1
    bridged_gap: float = float("nan")
    min_gap_kept: float = float("nan")
    seconds: float = 0.0
    notes: list = field(default_factory=list)

    def __str__(self) -> str:
        return (
            f"{self.method} cage: {self.n_faces} faces, {self.n_vertices} vertices, "
            f"{self.n_components} component(s); clearance {self.clearance:.4g} "
            f"({100 * self.clearance_relative:.2f}% of the diagonal), min winding number "
            f"{self.min_winding_number:.6f} over {self.n_points} points"
            + (
                f"; smallest gap kept between parts {self.min_gap_kept:.4g}"
                if np.isfinite(self.min_gap_kept)
                else ""
            )
            + f"; {self.seconds:.2f} s"
        )


# ---------------------------------------------------------------------------------------
# distances and enclosure
# ---------------------------------------------------------------------------------------


def _near_sd(V, F, points, radius):
    """Signed distance (negative inside) of the points within ``radius``; ``inf`` beyond."""
    return grid_signed_distance(NearDistance(V, F), points, radius)


def _verify_enclosure(vertices, faces, points, unsigned_dist) -> float:
    """Smallest winding number over ``points``, evaluated on few representatives.

    The winding number is constant on every ball that does not meet the cage: a point
    within ``unsigned_dist[r]`` of a representative ``r`` has ``r``'s winding number
    (``unsigned_dist`` may be a lower bound of the distance to the cage). Points are
    bucketed on a grid; in each bucket the point farthest from the cage represents the
    others it covers; uncovered points are evaluated themselves.
    """
    p = np.asarray(points, dtype=np.float64)
    d = np.abs(np.asarray(unsigned_dist, dtype=np.float64))
    cell = max(float(np.median(d)), 1e-12 * float(np.ptp(p, axis=0).max()))
    key = np.floor((p - p.min(axis=0)) / cell).astype(np.int64)
    _, bucket = np.unique(key, axis=0, return_inverse=True)
    bucket = bucket.ravel()
    order = np.lexsort((-d, bucket))
    first = np.ones(len(order), dtype=bool)
    first[1:] = bucket[order[1:]] != bucket[order[:-1]]
    rep_of_bucket = order[first]  # farthest point in each bucket
    rep = rep_of_bucket[bucket]
    covered = np.linalg.norm(p - p[rep], axis=1) < 0.999 * d[rep]
    evaluate = np.unique(np.concatenate([rep_of_bucket, np.flatnonzero(~covered)]))
    w = winding_number(p[evaluate], vertices, faces)
    return float(np.min(w)) if len(w) else 1.0


def _clearance(V, F, points, radius):
    """Signed distances (``inf`` beyond the radius) and the radius used.

    The radius is doubled until at least one point is within it.
    """
    for _ in range(20):
        sd, _ = _near_sd(V, F, points, radius)
        if np.isfinite(sd).any():
            return sd, radius
        radius *= 2.0
    raise RuntimeError("no input point near the cage")  # pragma: no cover


# ---------------------------------------------------------------------------------------
# method "voxel": union of cubes, coplanar faces merged
# ---------------------------------------------------------------------------------------


def _voxel_solid(samples: InputSamples, lo, hi, resolution, offset):
    """Well-composed voxel union for one resolution; returns (grid, solid)."""
    ext = float((hi - lo).max())
    h = ext / resolution
    off_vox = offset / h
    pad = int(np.ceil(max(off_vox, 1.0))) + 3
    grid = vx.make_grid(lo, hi, resolution, pad)
    pts = [samples.points]
    if samples.tri_faces is not None and len(samples.tri_faces):
        pts.append(vx.sample_triangles(samples.tri_vertices, samples.tri_faces, 0.5 * grid.h))
    occ = vx.splat(grid, np.concatenate(pts))
    if samples.spacing is not None:
        occ = vx.close_shell(occ, int(np.ceil(2 * samples.spacing / grid.h)) - 1)
    solid = vx.make_well_composed(vx.grow(occ, off_vox))
    return grid, solid


def _voxel_cage(samples, lo, hi, offset, max_faces, resolution, notes):
    ext = float((hi - lo).max())
    if resolution is not None:
        return _voxel_solid(samples, lo, hi, int(resolution), offset)
    # the clearance never needs voxels finer than offset / 2
    cap = int(min(256, max(2, np.ceil(2 * ext / offset))))
    cache = {}

    def faces_at(r):
        if r not in cache:
            g, s = _voxel_solid(samples, lo, hi, r, offset)
            cache[r] = (vx.count_cage_faces(s), g, s)
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
            f"auto_cage: even the coarsest voxel cage needs {cache[2][0]} faces, more than "
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


# ---------------------------------------------------------------------------------------
# method "offset": offset surface + quadric decimation + push-out
# ---------------------------------------------------------------------------------------


#: the clearance between two parts a gap ``g`` apart is at most ``g / 3``, so a third of
#: the gap stays open between their shells
_GAP_SHARE = 1.0 / 3.0
#: a shell needs about this many faces: more separate groups than max_faces / this at the
#: requested offset make the offset method retry with a larger one (fewer groups)
_FACES_PER_SHELL = 24


def _group_inside(points, h, offset, spacing):
    """(grid, inside mask) of one group of samples: splatted, closed and filled."""
    grid = vx.make_grid(
        points.min(axis=0), points.max(axis=0), None, int(np.ceil(offset / h)) + 4, h
    )
    occ = vx.splat(grid, points)
    if spacing is not None:
        occ = vx.close_shell(occ, int(np.ceil(2 * spacing / h)) - 1)
    inside = ndimage.binary_fill_holes(vx.grow(occ, 1.0))
    inside = ndimage.binary_erosion(inside, structure=np.ones((3, 3, 3), bool)) | occ
    return grid, inside


def _group_offset_surface(points, boundary, clear, grid, inside, offset):
    """Surface at the local clearance ``clear`` outside one group of samples (PolyData).

    Outside the group the surface is the boundary of the union of the balls of radius
    ``clear[i]`` around the samples: the zero level of ``min_i |x - p_i| - clear[i]``
    (over the 8 nearest samples where the clearance varies). A sample whose clearance is a
    third of its gap to another group keeps its ball on its own side of that gap, so the
    surface never reaches the middle of a gap. Inside, the field is minus the distance to
    the nearest boundary sample minus its clearance: signed, it interpolates linearly
    across the surface, so the contour stays accurate where the clearance is much smaller
    than a voxel. Beyond a band around the surface, voxel distances stand in.
    """
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
        d, j = cKDTree(points).query(grid.centers(idx), k=k, workers=-1)
        field_[band_out] = (d - clear[j]).reshape(len(idx), k).min(axis=1)
    idx = np.argwhere(band_in)
    if len(idx):
        bnd = np.flatnonzero(boundary) if boundary.any() else np.arange(len(points))
        d, j = cKDTree(points[bnd]).query(grid.centers(idx), k=1, workers=-1)
        field_[band_in] = -d - clear[bnd[j]]
    img = pv.ImageData(dimensions=grid.shape, spacing=(h, h, h), origin=grid.origin + 0.5 * h)
    img.point_data["f"] = field_.ravel(order="F")
    return img.contour([0.0], scalars="f", method="flying_edges").clean().triangulate()


def _nested_groups(groups_inside, points, group):
    """Pairs (outer, inner) of groups whose samples lie inside another group's region."""
    pairs = []
    for g, (grid, inside) in enumerate(groups_inside):
        other = np.flatnonzero(group != g)
        if len(other) == 0:
            continue
        idx = np.floor((points[other] - grid.origin) / grid.h).astype(np.int64)
        ok = np.all((idx >= 0) & (idx < np.asarray(grid.shape)), axis=1)
        hit = np.zeros(len(other), dtype=bool)
        hit[ok] = inside[idx[ok, 0], idx[ok, 1], idx[ok, 2]]
        pairs += [(g, int(k)) for k in np.unique(group[other[hit]])]
    return pairs


@dataclass
class _Groups:
    """Groups of parts that get one shell each, and the local clearance of every sample."""

    label: np.ndarray  # (N,) group of every shape sample
    count: int
    clear: np.ndarray  # (N,) local clearance of every shape sample (world units)
    bridged: float  # largest gap between parts that share a shell
    kept: float  # smallest gap between parts in different shells (inf: none near)
    inside: list  # (grid, mask) per group


def _make_groups(shape: ShapeSamples, offset: float, h: float, spacing, max_groups: int) -> _Groups:
    """Group the parts (closer than ``offset``, or nested) and set local clearances."""
    group, count, bridged, kept = group_parts(shape, offset)
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
        nested = _nested_groups(inside, shape.points, group) if count > 1 else []
        if not nested:
            break
        group, count = merge_groups(group, nested)
    if count > 1:
        gap = gap_to_other_groups(shape.points, group, shape.boundary, 3.0 * offset)
        clear = np.minimum(offset, _GAP_SHARE * gap)
        finite = np.isfinite(gap)
        kept = float(gap[finite].min()) if finite.any() else float("inf")
    else:
        clear = np.full(len(shape.points), float(offset))
        kept = float("inf")
    return _Groups(group, count, clear, bridged, kept, inside)


def _offset_surface(shape: ShapeSamples, groups: _Groups, offset: float, spacing):
    """Offset surface of every group (one PolyData each, at the groups' local clearance)."""
    meshes = []
    for g in range(groups.count):
        sel = groups.label == g
        grid, inside = groups.inside[g]
        iso = _group_offset_surface(
            shape.points[sel], shape.boundary[sel], groups.clear[sel], grid, inside, offset
        )
        if iso.n_cells == 0:
            raise RuntimeError(f"empty offset surface for part group {g}")
        meshes.append(iso)
    return meshes


def _faces_of(poly) -> np.ndarray:
    return np.asarray(poly.faces, dtype=np.int64).reshape(-1, 4)[:, 1:]


def _compact(V, F):
    """Drop unreferenced vertices."""
    used, inv = np.unique(F, return_inverse=True)
    return V[used], inv.reshape(F.shape)


def _polydata(vertices, faces):
    import pyvista as pv

    f = np.asarray(faces, dtype=np.int64)
    cells = np.hstack([np.full((len(f), 1), 3, dtype=np.int64), f]).ravel()
    return pv.PolyData(np.asarray(vertices, dtype=np.float64), cells)


def _orient_outward(V, F):
    """Flip every connected component whose signed volume is negative."""
    import scipy.sparse as sp

    n = len(V)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]]])
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    ncomp, lab = sp.csgraph.connected_components(adj, directed=False)
    flab = lab[F[:, 0]]
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    vol = np.bincount(flab, np.einsum("ij,ij->i", a, np.cross(b, c)), minlength=ncomp)
    flip = vol[flab] < 0
    F = F.copy()
    F[flip] = F[flip][:, ::-1]
    return F, ncomp


def _vertex_normals(V, F):
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area weighted
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def _push_out(V, F, points, min_clear, radius, rounds=25):
    """Move cage vertices outward until every point is its ``min_clear`` inside.

    Each point closer than its ``min_clear`` (or outside) pushes the three vertices of
    its nearest face along their normals, far enough to move that face's plane by the
    missing distance (plus 20%), but at most the largest ``min_clear`` of the points that
    push it, per round: small steps with normals recomputed in between do not fold
    concave regions onto themselves (larger steps made the CT head's cage
    self-intersect), and near a narrow gap between parts (small ``min_clear``) the cage
    does not jump across the gap. Returns the new vertices and the signed distances
    (``inf`` beyond ``radius``).
    """
    V = V.copy()
    min_clear = np.broadcast_to(np.asarray(min_clear, dtype=np.float64), (len(points),))
    previous = None
    for it in range(rounds):
        sd, face = _near_sd(V, F, points, radius)
        viol = np.flatnonzero(np.isfinite(sd) & (sd > -min_clear))
        if len(viol) == 0:
            return V, sd
        if previous is not None and it >= 2 and len(viol) > previous:
            return V, sd  # diverging (pushing one branch into another): give up early
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
    sd, _ = _near_sd(V, F, points, radius)
    return V, sd


def _gap_midpoints(shape: ShapeSamples, groups: _Groups, limit: int = 20_000) -> np.ndarray:
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
        _, j = cKDTree(shape.points[others]).query(shape.points[mine])
        mids.append(0.5 * (shape.points[mine] + shape.points[others[j]]))
    return np.concatenate(mids)


def _decimated(V, F, target: int, notes: list):
    """The offset surfaces taken down to a few times ``target`` faces (VTK, fast)."""
    F, _ = _orient_outward(V, F)
    for factor in (4, 8, 16):
        coarse = factor * target
        if len(F) > coarse:
            dec = _polydata(V, F).decimate(1.0 - coarse / len(F))
            V1, F1 = _compact(np.asarray(dec.points, dtype=np.float64), _faces_of(dec))
            F1, _ = _orient_outward(V1, F1)
        else:
            V1, F1 = V, F
        probs = edge_problems(F1)
        if not any(probs.values()):
            return V1, F1
        notes.append(f"quadric decimation to {coarse} faces not manifold ({probs})")
    raise RuntimeError("quadric decimation keeps producing non-manifold surfaces")


def _simplified(V1, F1, target: int, turn: float):
    """The decimated surfaces simplified together to ``target`` faces.

    Together, so that collapses that would make faces touch -- within a shell or between
    two shells -- are refused (``no_intersections``), a brute-force check per collapse:
    the first collapses, down to twice the target, run without it when they leave no
    intersection (the usual case), the rest with it. Every shell keeps at least 6
    vertices.
    """
    kw = {"outside": True, "max_normal_turn": turn, "min_component_vertices": 6}
    Vh, Fh = simplify(V1, F1, 2 * target, **kw)
    if len(self_intersections(Vh, Fh)):
        Vh, Fh = V1, F1
    return simplify(Vh, Fh, target, no_intersections=True, **kw)


def _offset_cage(samples, shape, lo, hi, offset, max_faces, resolution, notes):
    """(grid, vertices, faces, signed distances, components, Cage, groups) of "offset".

    Parts closer than ``offset`` (and nested parts) are grouped; every group gets its own
    offset surface, at the clearance ``offset`` narrowed to a third of the gap near other
    groups. VTK's quadric decimation takes the surfaces down to a few times ``max_faces``
    (fast, still manifold there),
    :func:`vhm_viz.autocage.simplify.simplify` finishes with link-condition-checked
    collapses, then the cage is pushed out where needed (every boundary sample at least
    half its local clearance inside) and checked to leave the space between groups
    outside. The signed distances returned are those of the input points
    (``shape.points[:shape.n_input]``, ``inf`` beyond twice the offset).
    """
    ext = float((hi - lo).max())
    if resolution is None:
        resolution = int(np.clip(np.ceil(1.5 * ext / offset), 32, 112))
    h = ext / int(resolution)
    max_groups = max(1, max_faces // _FACES_PER_SHELL)
    groups = _make_groups(shape, offset, h, samples.spacing, max_groups)
    meshes = _offset_surface(shape, groups, offset, samples.spacing)
    V = np.concatenate([np.asarray(m.points, dtype=np.float64) for m in meshes])
    first = np.cumsum([0] + [m.n_points for m in meshes])[:-1]
    F = np.concatenate([_faces_of(m) + o for m, o in zip(meshes, first, strict=True)])
    V1, F1 = _decimated(V, F, max_faces, notes)
    radius = 2.0 * offset
    # the clearance is kept at the boundary samples (the enclosure of the points inside
    # them is verified by winding numbers afterwards): the input points everywhere, the
    # samples on the input's triangles near gaps between groups (so that no triangle pokes
    # through where the cage hugs the shape); elsewhere the simplified cage may cut the
    # corner of a large input triangle between its (enclosed) corners
    check = shape.boundary.copy()
    check[shape.n_input :] &= groups.clear[shape.n_input :] < offset
    check_points = shape.points[check]
    min_clear = 0.5 * groups.clear[check]
    mids = _gap_midpoints(shape, groups)
    # simplification is cheap (compiled), so several variants are tried before the caller
    # falls back to a larger offset: fewer faces, then a stricter normal-turn limit
    # (flatter, less folded surfaces push out more cleanly)
    attempts = ((1.0, 0.2), (0.9, 0.2), (1.0, 0.5), (0.8, 0.5))
    for frac, turn in attempts:
        V2, F2 = _simplified(V1, F1, int(max_faces * frac), turn)
        if len(F2) > max_faces:
            notes.append(f"simplification stopped at {len(F2)} faces (> {max_faces}); retrying")
            continue
        F2, ncomp = _orient_outward(V2, F2)
        crossing = len(self_intersections(V2, F2))
        if crossing > _MAX_CROSSINGS:
            # branches closer than the face size at this offset (fingers): fewer faces or
            # a stricter simplification do not help, a larger offset does
            raise RuntimeError(
                f"the simplified offset surface self-intersects ({crossing} face pairs)"
            )
        V3, sd = _push_out(V2, F2, check_points, min_clear, radius)
        if (np.isfinite(sd) & (sd > -min_clear * 0.999)).any():
            notes.append(
                f"push-out did not restore the clearance ({len(F2)} faces, normal turn "
                f"{turn}); retrying"
            )
            continue
        if ncomp < groups.count:
            notes.append(f"{ncomp} shells for {groups.count} part groups; retrying")
            continue
        if len(mids) and (winding_number(mids, V3, F2) > 0.5).any():
            notes.append("the cage closes a gap between parts; retrying")
            continue
        try:
            cage = _make_cage(V3, F2)
        except CageError as exc:
            notes.append(f"offset cage rejected ({exc}); retrying")
            continue
        sd, _ = _near_sd(V3, F2, shape.points[: shape.n_input], radius)
        return vx.Grid(lo, h, (int(resolution),) * 3), V3, F2, sd, ncomp, cage, groups
    raise RuntimeError("could not simplify the offset surface into a valid cage")


# ---------------------------------------------------------------------------------------
# public entry point
# ---------------------------------------------------------------------------------------


def auto_cage(
    data,
    *,
    offset: float | None = None,
    max_faces: int = 500,
    resolution: int | None = None,
    method: str = "auto",
    threshold=None,
    scalars: str | None = None,
    return_report: bool = False,
):
    """Build a cage that strictly encloses ``data`` and follows its shape.

    Parameters
    ----------
    data : PolyData, UnstructuredGrid, ImageData, (N, 3) array, (vertices, faces) or path
        A surface, a point cloud, a tet mesh or a volume (see :func:`collect_samples`).
    offset : float, optional
        Target clearance between the input and the cage, in world units (default 1% of
        the input's bounding-box diagonal). The ``"offset"`` method guarantees at least
        half of it (where simplification cut in, the cage is pushed back out to that),
        the ``"voxel"`` method all of it. Parts closer than about ``2 * offset`` may
        share a cage branch; farther parts are kept apart.
    max_faces : int
        Largest number of triangles (default 500, the paper's range is 200-500).
    resolution : int, optional
        Voxels along the longest bounding-box side. ``"offset"``: the grid the offset
        surface is extracted on (default ``1.5 * side / offset`` within 32-112).
        ``"voxel"``: the cube size (default: the finest that fits ``max_faces``).
    method : {"auto", "offset", "voxel"}
        See the module documentation. ``"auto"`` uses ``"offset"``, retries it at twice
        the offset when the simplified surface cannot be made a valid cage (thin tubes
        such as fingers), then falls back to ``"voxel"``. Volumes without a threshold get
        their bounding box grown by ``offset`` (12 triangles).
    threshold : float, "otsu" or None
        Volumes: None encloses the bounding box, a value the points above it.
    scalars : str, optional
        Volume array to threshold.
    return_report : bool
        Also return an :class:`AutoCageReport` (clearance, winding numbers, timing).

    Returns
    -------
    Cage or (Cage, AutoCageReport)

    Raises
    ------
    ValueError
        Degenerate input (empty, NaN/inf, a single point, coplanar or collinear points),
        ``max_faces`` below 12, a bad offset/resolution or an unknown method.
    """
    t0 = time.perf_counter()
    if method not in ("auto", "offset", "voxel"):
        raise ValueError(f"auto_cage: unknown method {method!r} (auto, offset, voxel)")
    max_faces = int(max_faces)
    if max_faces < 12:
        raise ValueError(f"auto_cage: max_faces={max_faces} is below 12 (a box needs 12 triangles)")
    if resolution is not None and int(resolution) < 1:
        raise ValueError(f"auto_cage: resolution must be >= 1, got {resolution!r}")
    samples = collect_samples(data, threshold=threshold, scalars=scalars)
    if samples.kind == "points" and samples.spacing is None:
        samples.spacing = _point_spacing(samples.points)
    pts = samples.points
    lo = pts.min(axis=0)
    hi = pts.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if offset is None:
        offset = 0.01 * diag
    offset = float(offset)
    if not (np.isfinite(offset) and offset > 0):
        raise ValueError(f"auto_cage: offset must be a positive number, got {offset!r}")
    notes: list[str] = []
    used = "voxel" if samples.kind == "volume-box" else method
    cage = None
    offset_used, bridged, kept, n_parts = offset, float("nan"), float("nan"), 1
    if used in ("auto", "offset"):
        # thin tubes (fingers) sometimes cannot be simplified at the requested offset:
        # "auto" retries at twice the offset before falling back to the voxel cage
        tries = (offset, 2.0 * offset) if method == "auto" else (offset,)
        ext = float((hi - lo).max())
        res0 = resolution or int(np.clip(np.ceil(1.5 * ext / offset), 32, 112))
        shape = shape_samples(samples, 0.5 * ext / res0)
        for k, off in enumerate(tries):
            try:
                grid, V, F, sd, ncomp, cage, groups = _offset_cage(
                    samples, shape, lo, hi, off, max_faces, resolution, notes
                )
                used = "offset"
                radius_used = 2.0 * off
                offset_used, bridged, kept = off, groups.bridged, groups.kept
                n_parts = shape.n_parts
                if k:
                    notes.append(f"used offset {off:.4g} (twice the requested one)")
                break
            except (RuntimeError, ValueError) as exc:
                if method == "offset":
                    raise RuntimeError(f"auto_cage: offset method failed: {exc}") from exc
                notes.append(f"offset method failed at offset {off:.4g} ({exc})")
        else:
            notes.append("using the voxel cage")
            used = "voxel"
    if samples.kind == "volume-box":
        # the bounding box grown by the offset: 8 vertices, 12 triangles
        lo2, hi2 = lo - offset, hi + offset
        V = np.array(
            [
                [x, y, z]
                for x in (lo2[0], hi2[0])
                for y in (lo2[1], hi2[1])
                for z in (lo2[2], hi2[2])
            ]
        )
        F = np.array(
            [
                [0, 1, 3],
                [0, 3, 2],
                [4, 6, 7],
                [4, 7, 5],
                [0, 4, 5],
                [0, 5, 1],
                [2, 3, 7],
                [2, 7, 6],
                [0, 2, 6],
                [0, 6, 4],
                [1, 5, 7],
                [1, 7, 3],
            ]
        )
        F, ncomp = _orient_outward(V, F)
        grid = vx.make_grid(lo, hi, 1, 0)
        sd, radius_used = _clearance(V, F, pts, 2 * offset)
        cage = _make_cage(V, F)
        used = "box"
    if used == "voxel":
        grid, solid = _voxel_cage(samples, lo, hi, offset, max_faces, resolution, notes)
        Vi, F = vx.cage_surface(solid)
        V = grid.vertex_positions(Vi)
        if len(F) > max_faces:
            raise ValueError(
                f"auto_cage: the voxel cage at resolution {resolution} has {len(F)} faces, "
                f"more than max_faces={max_faces}"
            )
        F, ncomp = _orient_outward(V, F)
        sd, radius_used = _clearance(V, F, pts, offset + 3 * grid.h)
        cage = _make_cage(V, F, check_self_intersection=False)  # embedded by construction
    finite = np.isfinite(sd)
    if not finite.any():
        sd, radius_used = _clearance(V, F, pts, 4.0 * offset)
        finite = np.isfinite(sd)
    clearance = float(-sd[finite].max())
    # exact distances near the cage, the search radius (a lower bound) elsewhere
    lower = np.where(finite, np.abs(sd), radius_used)
    wmin = _verify_enclosure(V, F, pts, lower)
    enclosed = bool(clearance > 0 and wmin > 0.5)
    if not enclosed:  # pragma: no cover - guarded by construction
        raise RuntimeError(
            f"auto_cage: internal error, the cage does not enclose the input "
            f"(clearance {clearance:g}, min winding number {wmin:g})"
        )
    report = AutoCageReport(
        method=used,
        n_vertices=len(V),
        n_faces=len(F),
        offset=offset,
        clearance=clearance,
        clearance_relative=clearance / diag,
        min_winding_number=wmin,
        enclosed=enclosed,
        voxel_size=float(grid.h),
        grid_shape=tuple(grid.shape),
        n_points=len(pts),
        n_components=int(ncomp),
        offset_used=offset_used,
        n_parts=int(n_parts),
        bridged_gap=bridged,
        min_gap_kept=kept,
        seconds=time.perf_counter() - t0,
        notes=notes,
    )
    return (cage, report) if return_report else cage


def _make_cage(V, F, check_self_intersection=True):
    """A validated :class:`vhm_viz.Cage` from arrays (raises CageError)."""
    from vhm_viz.core.cage import Cage

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # an inward or unreferenced cage is a bug
        return Cage(
            np.asarray(V, dtype=np.float64),
            np.asarray(F, dtype=np.int64),
            check_self_intersection=check_self_intersection,
        )
