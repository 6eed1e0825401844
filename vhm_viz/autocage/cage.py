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
    """

    points: np.ndarray
    tri_vertices: np.ndarray | None = None
    tri_faces: np.ndarray | None = None
    kind: str = "points"
    spacing: float | None = None


def _otsu(values: np.ndarray) -> float:
    v = np.asarray(values, dtype=np.float64).ravel()
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
        pts = np.asarray(ds.points, dtype=np.float64)
        _check_points(pts, what)
        if threshold is None:
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            corners = np.array(
                [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
            )
            return InputSamples(points=corners, kind="volume-box")
        name = scalars or ds.active_scalars_name or (ds.array_names[0] if ds.array_names else None)
        if name is None:
            raise ValueError(f"{what}: the volume has no scalars to threshold")
        vals = np.asarray(ds.get_array(name))
        if vals.ndim > 1:
            vals = np.linalg.norm(vals, axis=1)
        if len(vals) == ds.n_cells and len(vals) != ds.n_points:
            pts = np.asarray(ds.cell_centers().points)
        thr = (
            _otsu(vals)
            if (isinstance(threshold, str) and threshold.lower() == "otsu")
            else float(threshold)
        )
        sel = vals > thr
        if not sel.any():
            raise ValueError(f"{what}: no voxel of '{name}' is above the threshold {thr:g}")
        sp = np.asarray(
            getattr(ds, "spacing", None)
            or np.ptp(pts, axis=0) / np.maximum(np.asarray(ds.dimensions) - 1, 1)
        )
        return InputSamples(
            points=_check_points(pts[sel], what), kind="volume", spacing=float(np.max(sp))
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
        Connected components of the cage.
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
    seconds: float = 0.0
    notes: list = field(default_factory=list)

    def __str__(self) -> str:
        return (
            f"{self.method} cage: {self.n_faces} faces, {self.n_vertices} vertices, "
            f"{self.n_components} component(s); clearance {self.clearance:.4g} "
            f"({100 * self.clearance_relative:.2f}% of the diagonal), min winding number "
            f"{self.min_winding_number:.6f} over {self.n_points} points; {self.seconds:.2f} s"
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


def _offset_surface(samples: InputSamples, lo, hi, offset, resolution):
    """Triangle mesh of the surface at distance ``offset`` outside the input."""
    import pyvista as pv

    ext = float((hi - lo).max())
    if resolution is None:
        resolution = int(np.clip(np.ceil(1.5 * ext / offset), 32, 112))
    h = ext / resolution
    pad = int(np.ceil(offset / h)) + 4
    grid = vx.make_grid(lo, hi, resolution, pad)
    pts = [samples.points]
    if samples.tri_faces is not None and len(samples.tri_faces):
        pts.append(vx.sample_triangles(samples.tri_vertices, samples.tri_faces, 0.5 * h))
    allpts = np.concatenate(pts)
    occ = vx.splat(grid, allpts)
    if samples.spacing is not None:
        occ = vx.close_shell(occ, int(np.ceil(2 * samples.spacing / h)) - 1)
    inside = ndimage.binary_fill_holes(vx.grow(occ, 1.0))
    inside = ndimage.binary_erosion(inside, structure=np.ones((3, 3, 3), bool)) | occ
    # distance (voxel units) from every voxel centre to the nearest inside voxel centre
    edt = ndimage.distance_transform_edt(~inside)
    field_ = edt * h
    band = (~inside) & (field_ < offset + 3 * h)
    idx = np.argwhere(band)
    if len(idx):
        d, _ = cKDTree(allpts).query(grid.centers(idx), k=1, workers=-1)
        field_[band] = d
    field_[inside] = 0.0
    img = pv.ImageData(dimensions=grid.shape, spacing=(h, h, h), origin=grid.origin + 0.5 * h)
    img.point_data["d"] = field_.ravel(order="F")
    iso = img.contour([offset], scalars="d", method="flying_edges")
    iso = iso.clean().triangulate()
    return grid, iso


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
    """Move cage vertices outward until every point is ``min_clear`` inside.

    Each point closer than ``min_clear`` (or outside) pushes the three vertices of its
    nearest face along their normals, far enough to move that face's plane by the
    missing distance (plus 20%), but at most ``min_clear`` per round: small steps with
    normals recomputed in between do not fold concave regions onto themselves (larger
    steps made the CT head's cage self-intersect). Returns the new vertices and the
    signed distances (``inf`` beyond ``radius``).
    """
    V = V.copy()
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
        deficit = 1.2 * (min_clear + sd[viol]) + 1e-3 * min_clear
        need = np.zeros(len(V))
        fv = face[viol]
        for k in range(3):
            vk = F[fv, k]
            cos = np.einsum("ij,ij->i", vn[vk], fn[fv])
            np.maximum.at(need, vk, deficit / np.maximum(cos, 0.25))
        V = V + vn * np.minimum(need, min_clear)[:, None]
    sd, _ = _near_sd(V, F, points, radius)
    return V, sd


def _offset_cage(samples, lo, hi, offset, max_faces, resolution, min_clear, notes):
    """(grid, vertices, faces, signed distances, components, Cage) of the offset method.

    VTK's quadric decimation takes the offset surface down to a few times ``max_faces``
    (fast, still manifold there), :func:`vhm_viz.autocage.simplify.simplify` finishes with
    link-condition-checked collapses, then the cage is pushed out where needed.
    """
    grid, iso = _offset_surface(samples, lo, hi, offset, resolution)
    if iso.n_cells == 0:
        raise RuntimeError("empty offset surface")
    V = np.asarray(iso.points, dtype=np.float64)
    F, _ = _orient_outward(V, _faces_of(iso))
    radius = 2.0 * offset
    target = max_faces
    for factor in (4, 8, 16):
        coarse = factor * max_faces
        if len(F) > coarse:
            dec = _polydata(V, F).decimate(1.0 - coarse / len(F))
            V1, F1 = _compact(np.asarray(dec.points, dtype=np.float64), _faces_of(dec))
            F1, _ = _orient_outward(V1, F1)
        else:
            V1, F1 = V, F
        probs = edge_problems(F1)
        if any(probs.values()):
            notes.append(f"quadric decimation to {coarse} faces not manifold ({probs})")
            continue
        break
    else:
        raise RuntimeError("quadric decimation keeps producing non-manifold surfaces")
    # simplification is cheap (compiled), so several variants are tried before the caller
    # falls back to a larger offset: fewer faces, then a stricter normal-turn limit
    # (flatter, less folded surfaces push out more cleanly)
    attempts = ((1.0, 0.2), (0.9, 0.2), (1.0, 0.5), (0.8, 0.5))
    for frac, turn in attempts:
        V2, F2 = simplify(V1, F1, int(target * frac), outside=True, max_normal_turn=turn)
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
        V3, sd = _push_out(V2, F2, samples.points, min_clear, radius)
        if (np.isfinite(sd) & (sd > -min_clear * 0.999)).any():
            notes.append(
                f"push-out did not restore the clearance ({len(F2)} faces, normal turn "
                f"{turn}); retrying"
            )
            continue
        try:
            cage = _make_cage(V3, F2)
        except CageError as exc:
            notes.append(f"offset cage rejected ({exc}); retrying")
            continue
        return grid, V3, F2, sd, ncomp, cage
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
    if used in ("auto", "offset"):
        # thin tubes (fingers) sometimes cannot be simplified at the requested offset:
        # "auto" retries at twice the offset before falling back to the voxel cage
        tries = (offset, 2.0 * offset) if method == "auto" else (offset,)
        for k, off in enumerate(tries):
            try:
                grid, V, F, sd, ncomp, cage = _offset_cage(
                    samples, lo, hi, off, max_faces, resolution, 0.5 * off, notes
                )
                used = "offset"
                radius_used = 2.0 * off
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
            # thin faces are not refused or repaired here: a repair may not move the surface
            # inward and the simplified cages have many; Cage.thin_faces reports them
            min_angle=0.0,
        )
