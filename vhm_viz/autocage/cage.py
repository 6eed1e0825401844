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
    shell), then falls back to ``"voxel"``. (:mod:`~vhm_viz.autocage.offset_surface`,
    :mod:`~vhm_viz.autocage.offset_cage`, :mod:`~vhm_viz.autocage.clearance`.)

``"voxel"`` (the paper's Section 4 cage: uniform decomposition of space with coplanar
faces merged)
    The union of the voxels within the clearance of the input, made well composed, its
    boundary squares merged into maximal coplanar polygons and triangulated. Valid by
    construction; coarser (the voxel size is the largest one that fits ``max_faces``);
    parts closer than about twice the clearance share a shell.
    (:mod:`~vhm_viz.autocage.voxel_cage`.)

Inputs become points in :mod:`~vhm_viz.autocage.samples` (volumes thresholded by
:mod:`~vhm_viz.autocage.threshold`); this module is the driver that picks the method,
checks the enclosure of every input point and reports.

The report (:class:`AutoCageReport`) gives the clearance used, the smallest gap kept open
between shells and the largest gap bridged inside one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.clearance import push_out, reaching_signed_distances
from vhm_viz.autocage.mesh import BOX_TRIANGLES, box_corners, make_cage, orient_outward
from vhm_viz.autocage.offset_cage import default_voxel_size, offset_cage
from vhm_viz.autocage.parts import shape_samples
from vhm_viz.autocage.samples import InputSamples, collect_samples, point_spacing
from vhm_viz.autocage.threshold import resolve_threshold, volume_values
from vhm_viz.autocage.voxel_cage import voxel_cage
from vhm_viz.core.basis import winding_number
from vhm_viz.core.cage import MIN_FACE_ANGLE
from vhm_viz.core.errors import SettingError
from vhm_viz.core.limits import check_integer_at_least

#: the largest clearance, in bounding-box diagonals of the input
_MAX_OFFSET = 1.0

__all__ = [
    "auto_cage",
    "AutoCageReport",
    "InputSamples",
    "collect_samples",
    "volume_values",
    "resolve_threshold",
]


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
        The clearance the cage was built for (the requested ``offset``, or two or four
        times it when smaller ones failed); parts farther apart than it get separate
        shells.
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
    thin_faces : int
        Faces whose smallest angle is below :data:`~vhm_viz.core.cage.MIN_FACE_ANGLE`
        (``Cage.thin_faces``): kept, since no repair removes them without moving the cage
        into the shape, but a solve on them may stop converging or go wrong.
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
    thin_faces: int = 0

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
            + (
                f"; {self.thin_faces} faces thinner than {MIN_FACE_ANGLE:g} degrees (a solve "
                "on them may stop converging or go wrong)"
                if self.thin_faces
                else ""
            )
            + f"; {self.seconds:.2f} s"
        )


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
        the input's bounding-box diagonal, at most the diagonal). The ``"offset"`` method
        keeps at least half of it (where simplification cut in, the cage is pushed back
        out to that), and between separate parts at most a third of their gap; the
        ``"voxel"`` method all of it. Separate parts farther apart than the offset used
        (``offset_used`` in the report) get separate shells and the space between them
        stays outside; closer ones may share a shell.
    max_faces : int
        Largest number of triangles (default 500, the paper's range is 200-500).
    resolution : int, optional
        Voxels along the longest bounding-box side. ``"offset"``: the grid the offset
        surface is extracted on (default ``1.5 * side / offset`` within 32-112, and
        coarser where the clearance on either side would take the grid past 115 voxels).
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
    SettingError
        An offset that is not positive or is larger than the input's bounding-box
        diagonal; ``threshold`` or ``scalars`` for an input that is not a volume;
        ``max_faces`` not an integer of at least 12, ``resolution`` not one of at least 1.
    ValueError
        Degenerate input (empty, NaN/inf, a single point, coplanar or collinear points)
        or an unknown method.
    """
    t0 = time.perf_counter()
    if method not in ("auto", "offset", "voxel"):
        raise ValueError(f"automatic cage: unknown method {method!r} (auto, offset, voxel)")
    max_faces = check_integer_at_least("max_faces", max_faces, 12, " (a box needs 12 triangles)")
    if resolution is not None:
        resolution = check_integer_at_least("resolution", resolution, 1)
    samples = collect_samples(data, threshold=threshold, scalars=scalars)
    if samples.kind == "points" and samples.spacing is None:
        samples.spacing = point_spacing(samples.points)
    pts = samples.points
    lo = pts.min(axis=0)
    hi = pts.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if offset is None:
        offset = 0.01 * diag
    offset = float(offset)
    if not (np.isfinite(offset) and 0 < offset <= _MAX_OFFSET * diag):
        # farther out the cage follows nothing of the shape, and its grid (which spans
        # the clearance) only grows
        raise SettingError(
            "offset",
            f"must be positive and at most the data's bounding-box diagonal, {diag:.4g} "
            f"(world units); got {offset:.4g}",
        )
    notes: list[str] = []
    used = "voxel" if samples.kind == "volume-box" else method
    cage = None
    offset_used, bridged, kept, n_parts = offset, float("nan"), float("nan"), 1
    sd = np.empty(0)
    if used in ("auto", "offset"):
        found = _offset_with_retries(samples, lo, hi, offset, max_faces, resolution, method, notes)
        if found is None:
            used = "voxel"
        else:
            (grid, V, F, ncomp, cage, groups, sd), offset_used, n_parts = found
            used = "offset"
            bridged, kept = groups.bridged, groups.kept
    if samples.kind == "volume-box":
        # the bounding box grown by the offset: 8 vertices, 12 triangles
        V = box_corners(lo - offset, hi + offset)
        F, ncomp = orient_outward(V, BOX_TRIANGLES)
        grid = vx.make_grid(lo, hi, 1, 0)
        cage = make_cage(V, F)
        used = "box"
    if used == "voxel":
        grid, V, F = voxel_cage(samples, lo, hi, offset, max_faces, resolution, notes)
        F, ncomp = orient_outward(V, F)
        cage = make_cage(V, F, check_self_intersection=False)  # embedded by construction
    # independent of how the cage was built: the distance from the boundary points (the
    # closest to the cage) and the winding number of every point, on the cage returned
    V, F = np.asarray(cage.vertices), np.asarray(cage.faces)
    for _ in range(3):
        if not cage.repairs or winding_number(pts, V, F).min() > 0.5:
            break
        # sliver repair (edge collapses) cut into the shape: push those faces back out
        notes.append(f"sliver repair moved the cage ({len(cage.repairs)} steps); pushed out")
        V, _sd = push_out(V, F, pts, 0.5 * offset_used, 2.0 * offset_used)
        cage = make_cage(V, F)
        V, F = np.asarray(cage.vertices), np.asarray(cage.faces)
    if cage.repairs or used != "offset" or not np.isfinite(sd).any():
        sd, _ = reaching_signed_distances(V, F, pts[samples.on_boundary()], 2.0 * offset_used)
    clearance = float(-sd[np.isfinite(sd)].max())
    wmin = float(winding_number(pts, V, F).min())
    enclosed = bool(clearance > 0 and wmin > 0.5)
    if not enclosed:  # pragma: no cover - guarded by construction
        raise RuntimeError(
            f"automatic cage: internal error, the cage does not enclose the input "
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
        thin_faces=len(cage.thin_faces),
    )
    return (cage, report) if return_report else cage


def _offset_with_retries(samples, lo, hi, offset, max_faces, resolution, method, notes):
    """The "offset" cage at the first offset that gives one; None: fall back to voxels.

    When the cage cannot be made at the requested offset (too many separate parts for the
    faces, gaps the faces cannot keep open), ``method="auto"`` retries at two and four
    times the offset -- parts closer than it then share a shell -- before the caller
    falls back to the voxel cage; ``method="offset"`` raises instead.

    Returns
    -------
    (built, offset_used, n_parts) or None
        ``built`` is what :func:`vhm_viz.autocage.offset_cage.offset_cage` returned at
        ``offset_used``; ``n_parts`` counts the separate parts of the input.
    """
    tries = (offset, 2.0 * offset, 4.0 * offset) if method == "auto" else (offset,)
    ext = float((hi - lo).max())
    h0 = ext / resolution if resolution else default_voxel_size(ext, offset)
    shape = shape_samples(samples, 0.5 * h0)
    for k, off in enumerate(tries):
        try:
            built = offset_cage(
                samples, shape, lo, hi, off, max_faces, resolution, notes, 3.0 * tries[-1]
            )
        except (RuntimeError, ValueError) as exc:
            if method == "offset":
                raise RuntimeError(f"automatic cage: offset method failed: {exc}") from exc
            notes.append(f"offset method failed at offset {off:.4g} ({exc})")
            continue
        if k:
            notes.append(f"used offset {off:.4g} ({off / offset:g} times the requested one)")
        return built, off, shape.n_parts
    notes.append("using the voxel cage")
    return None
