"""The ``"offset"`` cage: offset surfaces simplified to the face budget, pushed out, checked.

Every group of parts gets an offset surface (:mod:`vhm_viz.autocage.offset_surface`).
VTK's quadric decimation and the compiled simplifier (:mod:`vhm_viz.autocage.simplify`,
which refuses collapses that make faces touch or swallow a shell) take the shells to
``max_faces``; faces thinner than :data:`SLIVER_TARGET_ANGLE` are flipped or collapsed
away (:func:`vhm_viz.core.slivers.reduce_slivers`); where that cut into the clearance,
vertices are pushed outward (:mod:`vhm_viz.autocage.clearance`) until every boundary
sample is half its local clearance inside. A cage that closes a gap between groups, or
cannot be made valid, raises RuntimeError so that :func:`vhm_viz.auto_cage` can retry at
a larger offset.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.clearance import push_out
from vhm_viz.autocage.mesh import compact, faces_of, make_cage, orient_outward, polydata
from vhm_viz.autocage.meshcheck import edge_problems
from vhm_viz.autocage.offset_surface import (
    gap_midpoints,
    make_groups,
    nested_groups,
    offset_surfaces,
)
from vhm_viz.autocage.parts import merge_groups
from vhm_viz.autocage.simplify import simplify
from vhm_viz.core.basis import winding_number
from vhm_viz.core.cage import self_intersections
from vhm_viz.core.errors import CageError
from vhm_viz.core.slivers import MIN_FACE_ANGLE, face_angles, reduce_slivers

__all__ = ["offset_cage", "default_resolution", "default_voxel_size"]


#: more self-intersecting face pairs than this in the simplified offset surface (before
#: the push-out) means the offset is too small for the shape's gaps: skip the retries
_MAX_CROSSINGS = 12

#: smallest angle (degrees) the simplified cage's faces are brought to where an edge flip
#: or collapse can: twice the solve's minimum (:data:`vhm_viz.core.slivers.MIN_FACE_ANGLE`),
#: so that the push-out's moves leave them above it. Quadric simplification spends faces
#: on curved strips (the rounded edges of an offset box), whose triangles are needles
SLIVER_TARGET_ANGLE = 2.0 * MIN_FACE_ANGLE
#: how far (a fraction of the offset) removing them may move the surface inward: no
#: closer to the data than the half offset the push-out then guarantees
SLIVER_INWARD = 0.5

#: a shell needs about this many faces: more separate groups than max_faces / this at the
#: requested offset make the offset method retry with a larger one (fewer groups)
_FACES_PER_SHELL = 24


def default_resolution(extent: float, offset: float) -> int:
    """Voxels along the longest side of the extraction grid: ``1.5 * extent / offset``.

    Parameters
    ----------
    extent : float
        Longest side of the input's bounding box (world units).
    offset : float
        Clearance (world units).

    Returns
    -------
    int
        Within 32-112.
    """
    return int(np.clip(np.ceil(1.5 * extent / offset), 32, 112))


#: the default extraction grid's voxels across the input and its clearance on both
#: sides: the largest :func:`default_resolution` plus 1.5 voxels of clearance each side
_MAX_SPAN = 115


def default_voxel_size(extent: float, offset: float) -> float:
    """Voxel size of the default extraction grid (world units).

    ``extent / default_resolution(extent, offset)``, coarser where the grid across the
    input and the clearance on both sides (which the offset surface's grid spans) would
    exceed :data:`_MAX_SPAN` voxels: offsets larger than about the input's extent,
    whose grid would otherwise grow with the offset.
    """
    return max(extent / default_resolution(extent, offset), (extent + 2.0 * offset) / _MAX_SPAN)


def _decimated(V, F, target: int, notes: list):
    """The offset surfaces taken down to a few times ``target`` faces.

    VTK's quadric decimation (fast) when its result is a closed 2-manifold, else the
    compiled simplifier.
    """
    F, _ = orient_outward(V, F)
    for factor in (4, 8, 16):
        coarse = factor * target
        if len(F) > coarse:
            dec = polydata(V, F).decimate(1.0 - coarse / len(F))
            V1, F1 = compact(np.asarray(dec.points, dtype=np.float64), faces_of(dec))
            F1, _ = orient_outward(V1, F1)
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


def offset_cage(samples, shape, lo, hi, offset, max_faces, resolution, notes, reach=None):
    """The cage of the "offset" method at one offset.

    Parts closer than ``offset`` (and nested parts) are grouped; every group gets its own
    offset surface, at the clearance ``offset`` narrowed to a third of the gap near other
    groups. VTK's quadric decimation takes the surfaces down to a few times ``max_faces``
    (fast, still manifold there), :func:`vhm_viz.autocage.simplify.simplify` finishes
    with link-condition-checked collapses, then the cage is pushed out where needed (every
    boundary sample at least half its local clearance inside) and checked to leave the
    space between groups outside.

    Parameters
    ----------
    samples : InputSamples
    shape : ShapeSamples
        The input's boundary samples with their parts.
    lo, hi : (3,) float arrays
        The input's bounding box (world units).
    offset : float
        Clearance (world units).
    max_faces : int
        Face budget.
    resolution : int or None
        Voxels along the longest side (default: :func:`default_voxel_size`'s voxels).
    notes : list of str
        Variants retried and why are appended.
    reach : float, optional
        How far to look for pairs of parts (the same for every retry).

    Returns
    -------
    grid : Grid
        The extraction grid.
    V : (n, 3) float64
    F : (m, 3) int64
        The cage's arrays, outward oriented.
    n_components : int
        Its shells.
    cage : Cage
        The validated cage.
    groups : PartGroups
    sd : (n_input,) float64
        Signed distances of the input's boundary points (``inf`` beyond twice the offset).

    Raises
    ------
    RuntimeError
        No valid cage at this offset (a larger one may give one).
    """
    ext = float((hi - lo).max())
    if resolution is None:
        h = default_voxel_size(ext, offset)
        resolution = max(1, round(ext / h))  # the voxels along the side, for the report
    else:
        h = ext / int(resolution)
    max_groups = max(1, max_faces // _FACES_PER_SHELL)
    groups = make_groups(shape, offset, h, samples.spacing, max_groups, reach=reach)
    # point sets: a voxel centre is in the shape when within a sample's voxel (volumes)
    # or a typical neighbour distance (clouds) of a sample
    solid_radius = None
    if samples.tri_faces is None and samples.spacing:
        solid_radius = (0.5 * np.sqrt(3.0) if samples.kind == "volume" else 1.0) * samples.spacing
    while True:
        meshes, solids = offset_surfaces(shape, groups, offset, solid_radius)
        # an offset surface that closes over a pocket holding another group would nest
        # that group's shell inside it: such groups share a shell
        nested = nested_groups(solids, shape.points, groups.label) if groups.count > 1 else []
        if not nested:
            break
        groups.label, groups.count = merge_groups(groups.label, nested)
        groups = make_groups(shape, offset, h, samples.spacing, max_groups, merged=groups)
    V = np.concatenate([np.asarray(m.points, dtype=np.float64) for m in meshes])
    first = np.cumsum([0] + [m.n_points for m in meshes])[:-1]
    F = np.concatenate([faces_of(m) + o for m, o in zip(meshes, first, strict=True)])
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
    mids = gap_midpoints(shape, groups)
    # simplification is cheap (compiled), so several variants are tried before the caller
    # falls back to a larger offset: fewer faces, then a stricter normal-turn limit
    # (flatter, less folded surfaces push out more cleanly)
    attempts = ((1.0, 0.2), (0.9, 0.2), (1.0, 0.5), (0.8, 0.5))
    for frac, turn in attempts:
        V2, F2 = _simplified(V1, F1, int(max_faces * frac), turn)
        if len(F2) > max_faces:
            notes.append(f"simplification stopped at {len(F2)} faces (> {max_faces}); retrying")
            continue
        F2, ncomp = orient_outward(V2, F2)
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
        if ncomp < groups.count:
            notes.append(f"{ncomp} shells for {groups.count} part groups; retrying")
            continue
        # the thin faces flipped or collapsed away, when that still gives a valid cage;
        # else the simplified surface as it is
        for Vc, Fc in (*_without_slivers(V2, F2, ncomp, SLIVER_INWARD * offset), (V2, F2)):
            last = Fc is F2
            V3, sd = push_out(Vc, Fc, check_points, min_clear, radius)
            short = np.isfinite(sd) & (sd > -min_clear * 0.999)
            if short.any():
                if not last:
                    continue
                if (min_clear[short] < 0.5 * offset).any():
                    # near a gap the faces are too coarse to keep it open: another variant
                    # of the same face count will not do better, a larger offset does
                    raise RuntimeError("the faces cannot keep the gaps between parts open")
                notes.append(
                    f"push-out did not restore the clearance ({len(Fc)} faces, normal turn "
                    f"{turn}); retrying"
                )
                continue
            if len(mids) and (winding_number(mids, V3, Fc) > 0.5).any():
                if not last:
                    continue
                raise RuntimeError("the cage closes a gap between parts")
            try:
                cage = make_cage(V3, Fc)
            except CageError as exc:
                if last:
                    notes.append(f"offset cage rejected ({exc}); retrying")
                continue
            grid = vx.Grid(lo, h, (int(resolution),) * 3)
            return grid, V3, Fc, ncomp, cage, groups, sd[: shape.n_input]
    raise RuntimeError("could not simplify the offset surface into a valid cage")


def _without_slivers(V, F, ncomp: int, inward: float) -> list:
    """``[(V', F')]``: the cage with its thin faces flipped or collapsed away; [] if none.

    Faces with an angle below :data:`SLIVER_TARGET_ANGLE` are worked on, worst first
    (:func:`vhm_viz.core.slivers.reduce_slivers`). Steps that move the surface inward are
    allowed up to ``inward`` (world units): the push-out that follows restores the
    clearance, and the caller validates the result as any other. Dropped when a shell
    was lost.
    """
    if face_angles(V, F).min() >= SLIVER_TARGET_ANGLE:
        return []
    V1, F1, _ = reduce_slivers(V, F, SLIVER_TARGET_ANGLE, inward=inward)
    F1, n1 = orient_outward(V1, F1)
    if n1 != ncomp or len(F1) < 4:
        return []
    return [(V1, F1)]
