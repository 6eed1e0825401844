"""What an input contributes to a cage: :func:`collect_samples` turns any input into points.

Surfaces, point clouds, tet meshes and volumes (their bounding box, or the region above a
threshold, :mod:`vhm_viz.autocage.threshold`) all become :class:`InputSamples`: the points
the cage must enclose, the triangles whose inside is part of the shape, and for volumes
the connected region and rim of every point. Inputs without a volume to enclose (empty,
non-finite, a single point, coplanar or collinear points) are refused here, once.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.mesh import box_corners
from vhm_viz.autocage.threshold import resolve_threshold, volume_values
from vhm_viz.core.errors import SettingError
from vhm_viz.core.scipy_extensions import kd_tree
from vhm_viz.io import read_dataset

__all__ = ["InputSamples", "collect_samples", "check_points", "point_spacing"]


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

    def on_boundary(self) -> np.ndarray:
        """Which points lie on the shape's boundary (where the cage comes closest).

        Returns
        -------
        (N,) bool
            A volume's rim voxels, a tet mesh's surface points; every point of a surface
            or a cloud.
        """
        if self.boundary is not None:
            return np.asarray(self.boundary, dtype=bool)
        if self.kind == "tetmesh" and self.tri_faces is not None and len(self.tri_faces):
            surface = self.tri_vertices[np.unique(self.tri_faces)]
            d, _ = kd_tree(surface).query(self.points)
            return d == 0
        return np.ones(len(self.points), dtype=bool)

    def voxelise(self, grid: vx.Grid, closing: float = 2.0) -> np.ndarray:
        """The voxels of ``grid`` holding the shape's points or samples of its triangles.

        Parameters
        ----------
        grid : Grid
        closing : float
            Point sets (``spacing`` set): gaps up to ``closing * spacing`` between the
            occupied voxels are closed (:func:`vhm_viz.autocage.voxel.close_shell`).

        Returns
        -------
        (nx, ny, nz) bool
        """
        pts = [self.points]
        if self.tri_faces is not None and len(self.tri_faces):
            pts.append(vx.sample_triangles(self.tri_vertices, self.tri_faces, 0.5 * grid.h))
        occ = vx.splat(grid, np.concatenate(pts))
        if self.spacing is not None:
            occ = vx.close_shell(occ, int(np.ceil(closing * self.spacing / grid.h)) - 1)
        return occ


def check_points(points: np.ndarray, what: str) -> np.ndarray:
    """The points as (N, 3) float64, refused when they enclose no volume.

    Parameters
    ----------
    points : array_like, (N, 3)
    what : str
        Prefix for error messages.

    Returns
    -------
    (N, 3) float64

    Raises
    ------
    ValueError
        Wrong shape, no points, non-finite coordinates, a single point, coincident,
        collinear or coplanar points.
    """
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

    Image data are computed from the indices (materialising every point of a large image
    is slow and memory-hungry); other grids use their points or cell centres.
    """
    import pyvista as pv  # deferred with VTK: only volumes come here

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
        Volumes only (refused for other inputs).
    scalars : str, optional
        Name of the volume's scalar array (default: the active one); volumes only.
    what : str
        Prefix for error messages.

    Returns
    -------
    InputSamples

    Raises
    ------
    SettingError
        ``threshold`` or ``scalars`` for an input that is not a volume.
    ValueError
        Empty input, non-finite coordinates, a single point, coplanar or collinear points,
        an unsupported type or a threshold that selects nothing.
    """
    if isinstance(data, (str, os.PathLike)):
        data = read_dataset(data)
    samples = _collect(data, threshold, scalars, what)
    if not samples.kind.startswith("volume"):
        # a surface, cloud or tet mesh has no values to select a region by: an option
        # for volumes would silently do nothing
        for name, value in (("threshold", threshold), ("scalars", scalars)):
            if value is not None:
                raise SettingError(
                    name,
                    f"applies to volumes (images) only, and this input is a "
                    f"{_KIND_NAMES[samples.kind]}: leave it out",
                )
    return samples


#: what each kind of input is called in messages
_KIND_NAMES = {"surface": "surface", "points": "point cloud", "tetmesh": "tet mesh"}


def _collect(data, threshold, scalars, what) -> InputSamples:
    """:func:`collect_samples` of a dataset, array or tuple (not a path)."""
    if isinstance(data, tuple) and len(data) == 2:
        verts = check_points(data[0], what)
        faces = np.asarray(data[1])
        if faces.size == 0:
            return InputSamples(points=verts, kind="points")
        faces = faces.astype(np.int64).reshape(-1, 3)
        if faces.min() < 0 or faces.max() >= len(verts):
            raise ValueError(f"{what}: face indices out of range")
        used = np.unique(faces)
        return InputSamples(points=verts[used], tri_vertices=verts, tri_faces=faces, kind="surface")
    if isinstance(data, np.ndarray) or isinstance(data, list):
        return InputSamples(points=check_points(data, what), kind="points")

    # VTK is loaded only for datasets: array inputs never need it
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
            corners = box_corners(b[:, 0], b[:, 1])
            check_points(corners, what)
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
            points=check_points(pts, what),
            kind="volume",
            spacing=spacing,
            threshold=thr,
            part=part,
            boundary=boundary,
        )

    pts = check_points(np.asarray(ds.points, dtype=np.float64), what)
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


def point_spacing(points: np.ndarray) -> float:
    """A generous typical neighbour distance of a point set.

    Parameters
    ----------
    points : (N, 3) float array
        At least two points; large sets are subsampled.

    Returns
    -------
    float
        The 90th percentile of the nearest-neighbour distances (world units).
    """
    p = points if len(points) <= 50_000 else points[:: len(points) // 50_000 + 1]
    d, _ = kd_tree(p).query(p, k=2)
    return float(np.percentile(d[:, 1], 90))
