"""Automatic cages: :func:`auto_cage` builds a valid enclosing cage for any input.

Two methods, tried in this order by ``method="auto"``:

``"offset"`` (shape-following)
    The input's boundary samples (surface vertices and samples on its triangles, a tet
    mesh's surface, a volume region's rim voxels, cloud points) are split into *parts*
    (:mod:`vhm_viz.autocage.parts`); parts closer than ``offset``, or nested, form a
    group, and every group gets its own shell: the boundary of the union of balls around
    its samples, of radius ``offset`` lowered to a third of the gap to the nearest other
    group, extracted from a signed field (flying edges) on the group's own grid. VTK's
    quadric decimation and the compiled simplifier (which refuses collapses that make
    faces touch or swallow a shell) take the shells to ``max_faces``; where that cut into
    the clearance, vertices are pushed outward until every boundary sample is half its
    local clearance inside. The result is checked (closed, 2-manifold, outward, no
    self-intersection, gap midpoints outside, winding number 1 at every input point).
    When that fails ``"auto"`` retries at 2 and 4 times the offset (more parts share a
    shell), then falls back to ``"voxel"``.

``"voxel"`` (the paper's Section 4 cage: uniform decomposition of space with coplanar
faces merged)
    The union of the voxels within the clearance of the input, made well composed, its
    boundary squares merged into maximal coplanar polygons and triangulated. Valid by
    construction; coarser (the voxel size is the largest one that fits ``max_faces``);
    parts closer than about twice the clearance share a shell.

The report (:class:`AutoCageReport`) gives the clearance used, the smallest gap kept open
between shells and the largest gap bridged inside one.
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

__all__ = [
    "auto_cage",
    "AutoCageReport",
    "InputSamples",
    "collect_samples",
    "volume_values",
    "resolve_threshold",
]

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


def volume_values(ds, scalars: str | None = None, what: str = "volume"):
    """The scalar a volume is thresholded on, per point (or per cell), and its name.

    Parameters
    ----------
    ds : pyvista.ImageData, RectilinearGrid or StructuredGrid
    scalars : str, optional
        Array name (default: the active scalars, else the first array).
    what : str
        Prefix for error messages.

    Returns
    -------
    values : (n,) ndarray
        The array (vectors: their length).
    name : str
    """
    name = scalars or ds.active_scalars_name or (ds.array_names[0] if ds.array_names else None)
    if name is None:
        raise ValueError(f"{what}: the volume has no scalars to threshold")
    vals = np.asarray(ds.get_array(name))
    if vals.ndim > 1:
        vals = np.linalg.norm(vals, axis=1)
    return vals, name


def resolve_threshold(values: np.ndarray, threshold) -> float:
    """A threshold as a number: ``"otsu"`` becomes Otsu's threshold of ``values``.

    The region of a volume is the voxels whose value is strictly above it.
    """
    if isinstance(threshold, str):
        if threshold.lower() != "otsu":
            raise ValueError(f"threshold must be a number or 'otsu', got {threshold!r}")
        return _otsu(values)
    return float(threshold)


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
        vals, name = volume_values(ds, scalars, what)
        on_cells = len(vals) == ds.n_cells and len(vals) != ds.n_points
        thr = resolve_threshold(vals, threshold)
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
        Smallest distance from an input point on the shape's boundary to the cage (world
        units, > 0): every point of a surface or cloud, a tet mesh's surface points, a
        volume region's rim voxels.
    clearance_relative : float
        ``clearance`` divided by the input's bounding-box diagonal.
    min_winding_number : float
        Smallest generalized winding number over all input points (1 when enclosed).
    enclosed : bool
        Every input point strictly inside (winding number > 0.5 and clearance > 0).
    voxel_size : float
        Grid spacing used.
    grid_shape : tuple of int
    n_points : int
        Input points checked.
    n_components : int
        Connected components (shells) of the cage.
    threshold : float or None
        Volumes: the threshold whose region (voxels strictly above it) the cage encloses,
        Otsu's value resolved; None otherwise.
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
    threshold: float | None = None
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
            + (f" (the voxels above {self.threshold:.6g})" if self.threshold is not None else "")
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


def _on_boundary(samples: InputSamples) -> np.ndarray:
    """Which input points lie on the shape's boundary (where the cage comes closest).

    A volume's rim voxels, a tet mesh's surface points; every point of a surface or a
    cloud.
    """
    if samples.boundary is not None:
        return np.asarray(samples.boundary, dtype=bool)
    if samples.kind == "tetmesh" and samples.tri_faces is not None and len(samples.tri_faces):
        surface = samples.tri_vertices[np.unique(samples.tri_faces)]
        d, _ = cKDTree(surface).query(samples.points)
        return d == 0
    return np.ones(len(samples.points), dtype=bool)


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
        where = grid.centers(idx)
        d, j = cKDTree(points).query(where, k=1, workers=-1)
        values = -d - clear[j]
        if solid_radius is not None and varies:
            k = min(8, len(points))
            d, j = cKDTree(points).query(where, k=k, workers=-1)
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


def _nested_groups(groups_inside, points, group):
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
class _Groups:
    """Groups of parts that get one shell each, and the local clearance of every sample."""

    label: np.ndarray  # (N,) group of every shape sample
    count: int
    clear: np.ndarray  # (N,) local clearance of every shape sample (world units)
    bridged: float  # largest gap between parts that share a shell
    kept: float  # smallest gap between parts in different shells (inf: none near)
    inside: list  # (grid, mask) per group


def _make_groups(
    shape: ShapeSamples,
    offset: float,
    h: float,
    spacing,
    max_groups: int,
    merged=None,
    reach: float | None = None,
) -> _Groups:
    """Group the parts (closer than ``offset``, or nested) and set local clearances.

    ``merged`` (a previous :class:`_Groups` whose labels were merged further) skips the
    distance grouping.
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
        nested = _nested_groups(inside, shape.points, group) if count > 1 else []
        if not nested:
            break
        group, count = merge_groups(group, nested)
    if count > 1:
        gap = gap_to_other_groups(shape.points, group, 3.0 * offset)
        clear = np.minimum(offset, _GAP_SHARE * gap)
        finite = np.isfinite(gap)
        kept = float(gap[finite].min()) if finite.any() else float("inf")
    else:
        clear = np.full(len(shape.points), float(offset))
        kept = float("inf")
    return _Groups(group, count, clear, bridged, kept, inside)


def _offset_surface(shape: ShapeSamples, groups: _Groups, offset: float, solid_radius=None):
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
    all_points = points
    all_clear = np.broadcast_to(np.asarray(min_clear, dtype=np.float64), (len(points),))
    points, min_clear = all_points, all_clear
    previous = None
    for it in range(rounds):
        sd, face = _near_sd(V, F, points, radius)
        if it == 0:
            # only points near the cage can be reached by the small steps below; the
            # others are checked again at the end
            near = np.isfinite(sd)
            points, min_clear, sd, face = points[near], min_clear[near], sd[near], face[near]
        viol = np.flatnonzero(np.isfinite(sd) & (sd > -min_clear))
        if len(viol) == 0:
            sd, _ = _near_sd(V, F, all_points, radius)
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
    sd, _ = _near_sd(V, F, all_points, radius)
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
    """The offset surfaces taken down to a few times ``target`` faces.

    VTK's quadric decimation (fast) when its result is a closed 2-manifold, else the
    compiled simplifier.
    """
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
    # the compiled simplifier keeps the surface a 2-manifold (link condition): slower
    # from a large contour, but it does not fail
    if any(edge_problems(F).values()):
        raise RuntimeError("the offset surface is not a closed 2-manifold")
    return simplify(V, F, 4 * target, outside=True, min_component_vertices=6)


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


def _offset_cage(samples, shape, lo, hi, offset, max_faces, resolution, notes, reach=None):
    """(grid, vertices, faces, components, Cage, groups, sd) of the "offset" method.

    Parts closer than ``offset`` (and nested parts) are grouped; every group gets its own
    offset surface, at the clearance ``offset`` narrowed to a third of the gap near other
    groups. VTK's quadric decimation takes the surfaces down to a few times ``max_faces``
    (fast, still manifold there),
    :func:`vhm_viz.autocage.simplify.simplify` finishes with link-condition-checked
    collapses, then the cage is pushed out where needed (every boundary sample at least
    half its local clearance inside) and checked to leave the space between groups
    outside. ``sd``: signed distances of the input's boundary points (``inf`` beyond twice
    the offset); ``reach``: how far to look for pairs of parts (reused by retries).
    """
    ext = float((hi - lo).max())
    if resolution is None:
        resolution = int(np.clip(np.ceil(1.5 * ext / offset), 32, 112))
    h = ext / int(resolution)
    max_groups = max(1, max_faces // _FACES_PER_SHELL)
    groups = _make_groups(shape, offset, h, samples.spacing, max_groups, reach=reach)
    # point sets: a voxel centre is in the shape when within a sample's voxel (volumes)
    # or a typical neighbour distance (clouds) of a sample
    solid_radius = None
    if samples.tri_faces is None and samples.spacing:
        solid_radius = (0.5 * np.sqrt(3.0) if samples.kind == "volume" else 1.0) * samples.spacing
    while True:
        meshes, solids = _offset_surface(shape, groups, offset, solid_radius)
        # an offset surface that closes over a pocket holding another group would nest
        # that group's shell inside it: such groups share a shell
        nested = _nested_groups(solids, shape.points, groups.label) if groups.count > 1 else []
        if not nested:
            break
        groups.label, groups.count = merge_groups(groups.label, nested)
        groups = _make_groups(shape, offset, h, samples.spacing, max_groups, merged=groups)
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
    check = np.ones(len(shape.points), dtype=bool)
    check[shape.n_input :] = groups.clear[shape.n_input :] < offset
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
        if len(mids) and (winding_number(mids, V2, F2) > 0.5).any():
            # pushing out only grows the cage: the gap stays closed
            raise RuntimeError("the cage closes a gap between parts")
        V3, sd = _push_out(V2, F2, check_points, min_clear, radius)
        short = np.isfinite(sd) & (sd > -min_clear * 0.999)
        if short.any():
            if (min_clear[short] < 0.5 * offset).any():
                # near a gap the faces are too coarse to keep it open: another variant of
                # the same face count will not do better, a larger offset (merging) does
                raise RuntimeError("the faces cannot keep the gaps between parts open")
            notes.append(
                f"push-out did not restore the clearance ({len(F2)} faces, normal turn "
                f"{turn}); retrying"
            )
            continue
        if ncomp < groups.count:
            notes.append(f"{ncomp} shells for {groups.count} part groups; retrying")
            continue
        if len(mids) and (winding_number(mids, V3, F2) > 0.5).any():
            raise RuntimeError("the cage closes a gap between parts")
        try:
            cage = _make_cage(V3, F2)
        except CageError as exc:
            notes.append(f"offset cage rejected ({exc}); retrying")
            continue
        grid = vx.Grid(lo, h, (int(resolution),) * 3)
        return grid, V3, F2, ncomp, cage, groups, sd[: shape.n_input]
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
        the input's bounding-box diagonal). The ``"offset"`` method keeps at least half
        of it (where simplification cut in, the cage is pushed back out to that), and
        between separate parts at most a third of their gap; the ``"voxel"`` method all
        of it. Separate parts farther apart than the offset used (``offset_used`` in the
        report) get separate shells and the space between them stays outside; closer
        ones may share a shell.
    max_faces : int
        Largest number of triangles (default 500, the paper's range is 200-500).
    resolution : int, optional
        Voxels along the longest bounding-box side. ``"offset"``: the grid the offset
        surface is extracted on (default ``1.5 * side / offset`` within 32-112).
        ``"voxel"``: the cube size (default: the finest that fits ``max_faces``).
    method : {"auto", "offset", "voxel"}
        See the module documentation. ``"auto"`` uses ``"offset"``, retries it at two
        and four times the offset when no valid cage comes out (too many separate parts
        for the faces, gaps the faces cannot keep open), then falls back to ``"voxel"``.
        Volumes without a threshold get their bounding box grown by ``offset`` (12
        triangles).
    threshold : float, "otsu" or None
        Volumes: None encloses the bounding box, a value every voxel strictly above it
        (the region; see :func:`resolve_threshold`).
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
    sd = np.empty(0)
    if used in ("auto", "offset"):
        # when the cage cannot be made at the requested offset (too many separate parts
        # for the faces, gaps the faces cannot keep open), "auto" retries at two and four
        # times the offset -- parts closer than it then share a shell -- before falling
        # back to the voxel cage
        tries = (offset, 2.0 * offset, 4.0 * offset) if method == "auto" else (offset,)
        ext = float((hi - lo).max())
        res0 = resolution or int(np.clip(np.ceil(1.5 * ext / offset), 32, 112))
        shape = shape_samples(samples, 0.5 * ext / res0)
        for k, off in enumerate(tries):
            try:
                grid, V, F, ncomp, cage, groups, sd = _offset_cage(
                    samples, shape, lo, hi, off, max_faces, resolution, notes, 3.0 * tries[-1]
                )
                used = "offset"
                offset_used, bridged, kept = off, groups.bridged, groups.kept
                n_parts = shape.n_parts
                if k:
                    notes.append(
                        f"used offset {off:.4g} ({off / offset:g} times the requested one)"
                    )
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
        cage = _make_cage(V, F, check_self_intersection=False)  # embedded by construction
    # independent of how the cage was built: the distance from the boundary points (the
    # closest to the cage) and the winding number of every point, on the cage returned
    V, F = np.asarray(cage.vertices), np.asarray(cage.faces)
    for _ in range(3):
        if not cage.repairs or winding_number(pts, V, F).min() > 0.5:
            break
        # sliver repair (edge collapses) cut into the shape: push those faces back out
        notes.append(f"sliver repair moved the cage ({len(cage.repairs)} steps); pushed out")
        V, _sd = _push_out(V, F, pts, 0.5 * offset_used, 2.0 * offset_used)
        cage = _make_cage(V, F)
        V, F = np.asarray(cage.vertices), np.asarray(cage.faces)
    if cage.repairs or used != "offset" or not np.isfinite(sd).any():
        sd, _ = _clearance(V, F, pts[_on_boundary(samples)], 2.0 * offset_used)
    clearance = float(-sd[np.isfinite(sd)].max())
    wmin = float(winding_number(pts, V, F).min())
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
        threshold=samples.threshold,
        offset_used=offset_used,
        n_parts=int(n_parts),
        bridged_gap=bridged,
        min_gap_kept=kept,
        seconds=time.perf_counter() - t0,
        notes=notes,
    )
    return (cage, report) if return_report else cage


def _make_cage(V, F, check_self_intersection=True):
    """A validated :class:`vhm_viz.Cage` from arrays (raises CageError).

    Thin faces are kept and reported (``Cage.thin_faces``), not repaired: a repair moves the
    surface. :func:`auto_cage` still checks the enclosure on the cage returned here, and
    pushes the surface back out should a repair ever have cut into the shape.
    """
    from vhm_viz.core.cage import Cage

    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # an inward or unreferenced cage is a bug
        return Cage(
            np.asarray(V, dtype=np.float64),
            np.asarray(F, dtype=np.int64),
            check_self_intersection=check_self_intersection,
            # thin faces are not refused or repaired here: a repair may not move the surface
            # inward and the simplified cages have many; Cage.thin_faces reports them
            min_angle=0.0,
        )
