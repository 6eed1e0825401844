"""Automatic anchors: :func:`auto_anchors` places rigidity samples on the medial structure.

The paper puts its anchors on the medial axis (curve-like parts, Figures 5-6) or medial
surface (plate-like parts, Figure 14). Here the input's interior is voxelised, its
Euclidean distance transform computed, and the voxels on the ridge of that distance (no
neighbour farther from the surface by more than half the step to it: centres of
near-maximal balls) are the medial candidates. Anchors are picked from them by farthest
point sampling started at the thickest point, so they are spread over every part, and
each is checked to lie strictly inside the shape and the cage.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.cage import collect_samples

__all__ = ["auto_anchors", "AnchorReport"]


@dataclass
class AnchorReport:
    """What :func:`auto_anchors` placed.

    Attributes
    ----------
    count : int
    min_pairwise_distance : float
        Smallest distance between two anchors (world units).
    min_depth : float
        Smallest estimated distance from an anchor to the shape's surface.
    n_candidates : int
        Medial voxels the anchors were sampled from.
    voxel_size : float
    seconds : float
    """

    count: int
    min_pairwise_distance: float
    min_depth: float
    n_candidates: int
    voxel_size: float
    seconds: float

    def __str__(self) -> str:
        return (
            f"{self.count} anchors from {self.n_candidates} medial voxels; min pairwise "
            f"distance {self.min_pairwise_distance:.4g}, min depth {self.min_depth:.4g}; "
            f"{self.seconds:.2f} s"
        )


_OFFSETS = np.array(
    [
        (i, j, k)
        for i in (-1, 0, 1)
        for j in (-1, 0, 1)
        for k in (-1, 0, 1)
        if (i, j, k) != (0, 0, 0)
    ]
)


def _medial(depth: np.ndarray, interior: np.ndarray) -> np.ndarray:
    """Interior voxels where no neighbour is deeper by half the step or more."""
    pad = np.pad(depth, 1)
    n = np.array(depth.shape)
    rise = np.full(depth.shape, -np.inf)
    for off in _OFFSETS:
        sl = tuple(slice(1 + o, 1 + o + s) for o, s in zip(off, n, strict=True))
        rise = np.maximum(rise, (pad[sl] - depth) / np.linalg.norm(off))
    return interior & (rise < 0.5)


def _as_cage(cage):
    from vhm_viz import io
    from vhm_viz.core.cage import Cage

    if isinstance(cage, Cage):
        return cage
    if isinstance(cage, (str, os.PathLike)):
        return io.read_cage(cage)
    if isinstance(cage, tuple) and len(cage) == 2:
        return Cage(*cage)
    if hasattr(cage, "GetPoints"):
        return io.cage_from_dataset(cage)
    raise ValueError(f"auto_anchors: cannot use {type(cage).__name__} as a cage")


def auto_anchors(
    data,
    cage,
    count: int,
    *,
    resolution: int | None = None,
    threshold=None,
    scalars: str | None = None,
    return_report: bool = False,
):
    """Place ``count`` anchors on the medial axis/surface of ``data``, inside ``cage``.

    Parameters
    ----------
    data : PolyData, UnstructuredGrid, ImageData, (N, 3) array, (vertices, faces) or path
        The shape (as for :func:`vhm_viz.auto_cage`).
    cage : Cage, (vertices, faces), PolyData or path
        Anchors must lie inside it.
    count : int
        Number of anchors ``d`` (>= 1).
    resolution : int, optional
        Voxels along the longest side of the shape (default 96).
    threshold, scalars
        Volumes: as for :func:`vhm_viz.auto_cage`.
    return_report : bool
        Also return an :class:`AnchorReport`.

    Returns
    -------
    anchors : (count, 3) float64
        Strictly inside the shape and the cage, farthest-point spread.
    report : AnchorReport, only with ``return_report``

    Raises
    ------
    ValueError
        Degenerate input, ``count < 1``, or a shape too thin for the voxel grid (raise
        ``resolution``), or fewer interior candidates than ``count``.
    """
    t0 = time.perf_counter()
    count = int(count)
    if count < 1:
        raise ValueError(f"auto_anchors: count must be >= 1, got {count}")
    samples = collect_samples(data, threshold=threshold, scalars=scalars, what="auto_anchors")
    cage = _as_cage(cage)
    pts = samples.points
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ext = float(np.max(hi - lo))
    if resolution is None and samples.kind == "volume" and samples.spacing:
        # one voxel per image sample: the region needs no closing
        resolution = int(np.clip(np.ceil(ext / samples.spacing), 4, 96))
    r = int(resolution or 96)
    if r < 4:
        raise ValueError(f"auto_anchors: resolution must be >= 4, got {r}")
    grid = vx.make_grid(lo, hi, r, 2)
    h = grid.h
    if samples.kind == "volume-box":
        inside = np.zeros(grid.shape, dtype=bool)
        i0, i1 = grid.voxel_of(lo[None])[0], grid.voxel_of(hi[None])[0]
        inside[i0[0] : i1[0] + 1, i0[1] : i1[1] + 1, i0[2] : i1[2] + 1] = True
        surface = inside & ~ndimage.binary_erosion(inside)
    else:
        allp = [pts]
        if samples.tri_faces is not None and len(samples.tri_faces):
            allp.append(vx.sample_triangles(samples.tri_vertices, samples.tri_faces, 0.5 * h))
        surface = vx.splat(grid, np.concatenate(allp))
        if samples.kind in ("points",) and samples.spacing is None:
            from vhm_viz.autocage.cage import _point_spacing

            samples.spacing = _point_spacing(pts)
        if samples.spacing is not None:
            factor = 1 if samples.kind == "volume" else 2
            surface = vx.close_shell(surface, int(np.ceil(factor * samples.spacing / h)) - 1)
        if samples.kind == "volume":
            # the region itself is the shape (cavities below the threshold stay out)
            inside = surface
            surface = inside & ~ndimage.binary_erosion(inside)
        else:
            inside = ndimage.binary_fill_holes(vx.grow(surface, 1.0))
            inside = ndimage.binary_erosion(inside, structure=np.ones((3, 3, 3), bool)) | surface
    # interior: voxels that are not next to a surface sample
    interior = inside & ~vx._cube_dilate(surface, 1)
    if not interior.any():
        raise ValueError(
            f"auto_anchors: the shape is too thin for a {r}-voxel grid (no interior voxel); "
            "raise resolution"
        )
    depth = ndimage.distance_transform_edt(interior)  # voxels to the nearest non-interior
    medial = _medial(depth, interior) & (depth >= 1.0)
    cand = np.argwhere(medial)
    centres = grid.centers(cand)
    ok = cage.contains(centres)
    cand, centres = cand[ok], centres[ok]
    if len(cand) < count:
        extra = np.argwhere(interior)
        extra_c = grid.centers(extra)
        okx = cage.contains(extra_c)
        cand = np.concatenate([cand, extra[okx]])
        centres = np.concatenate([centres, extra_c[okx]])
        _, uniq = np.unique(cand, axis=0, return_index=True)
        cand, centres = cand[np.sort(uniq)], centres[np.sort(uniq)]
    if len(cand) < count:
        raise ValueError(
            f"auto_anchors: only {len(cand)} interior voxels inside the cage for {count} "
            "anchors; raise resolution or lower count"
        )
    dep = depth[cand[:, 0], cand[:, 1], cand[:, 2]]
    chosen = [int(np.argmax(dep))]
    mind = np.linalg.norm(centres - centres[chosen[0]], axis=1)
    for _ in range(count - 1):
        nxt = int(np.argmax(mind))
        chosen.append(nxt)
        mind = np.minimum(mind, np.linalg.norm(centres - centres[nxt], axis=1))
    anchors = centres[chosen]
    # strictly inside the shape: for closed surfaces, check the winding number
    if samples.tri_faces is not None and len(samples.tri_faces) and samples.kind == "surface":
        from vhm_viz.core.basis import winding_number

        w = winding_number(anchors, samples.tri_vertices, samples.tri_faces)
        bad = np.flatnonzero(w < 0.5)
        if len(bad):  # pragma: no cover - open or inconsistent input surfaces
            raise ValueError(
                f"auto_anchors: anchors {bad.tolist()} fall outside the input surface "
                "(is it closed and consistently oriented?)"
            )
    if len(anchors) > 1:
        diff = anchors[:, None, :] - anchors[None, :, :]
        dist = np.linalg.norm(diff, axis=2)
        dist[np.diag_indices(len(anchors))] = np.inf
        min_pair = float(dist.min())
    else:
        min_pair = float("inf")
    report = AnchorReport(
        count=count,
        min_pairwise_distance=min_pair,
        min_depth=float(dep[chosen].min() * h),
        n_candidates=int(medial.sum()),
        voxel_size=float(h),
        seconds=time.perf_counter() - t0,
    )
    return (anchors, report) if return_report else anchors
