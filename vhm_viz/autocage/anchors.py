"""Automatic anchors: :func:`auto_anchors` places rigidity samples that cover the shape.

The paper puts its anchors on the medial axis (curve-like parts, Figures 5-6) or medial
surface (plate-like parts, Figure 14). Here the input's interior is voxelised and its
Euclidean distance transform computed; the voxels on the ridge of that distance (no
neighbour deeper by half the step to it: centres of near-maximal balls) are the medial
skeleton. Anchors must also *cover* the shape -- every input point near an anchor -- since
the rigidity term only acts where anchors are:

1. every cage shell, then every connected part of the shape (largest first, at most half
   the anchors when parts are many) gets an anchor at its deepest skeleton voxel;
2. farthest-point sampling adds the others, either over the skeleton (the medial
   placement) or over the shape's points (the point farthest from all anchors gets the
   next one, on the skeleton where the skeleton comes nearer to it than any anchor --
   limbs --, else halfway from it towards the skeleton -- fat parts);
3. Lloyd rounds move each anchor towards the centre of the smallest ball around the points
   it covers, within its part, keeping the best configuration seen; then the least useful
   anchor moves next to the worst-covered point while that improves the coverage;
4. the medial placement is kept when it covers every point within ``_COVERAGE_GOAL`` (15%)
   of the diagonal, or when neither does and it is within ``_MEDIAL_SLACK`` of the other.

Candidates are voxels at least a voxel from the surface; thin limbs without such voxels
and specks of volumes use their own voxels, checked to lie inside a closed input surface
exactly (winding number). Every anchor lies inside the shape and the cage.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
from scipy import ndimage

from vhm_viz import io
from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.samples import collect_samples, point_spacing
from vhm_viz.core.basis import domain_columns, inside_cage, winding_number
from vhm_viz.core.cage import Cage
from vhm_viz.core.errors import OutsideCageError, describe_indices
from vhm_viz.core.limits import check_integer_at_least, check_setting
from vhm_viz.core.scipy_extensions import kd_tree

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = ["auto_anchors", "AnchorReport"]

#: every point within this fraction of the bounding-box diagonal of an anchor: the
#: coverage the automatic anchors aim at. They stay on the skeleton when that meets it,
#: or when neither placement does and the skeleton's coverage is within
#: ``_MEDIAL_SLACK`` times the other's.
_COVERAGE_GOAL = 0.15
_MEDIAL_SLACK = 1.2

#: A volume's whole box as the shape (no threshold): the anchor grid's voxels along its
#: longest side (a box's skeleton needs no finer grid), the lattice points the placement
#: covers and the lattice points the report measures, along that side.
_BOX_RESOLUTION = 48
_BOX_TARGETS_PER_SIDE = 16
_BOX_REPORT_PER_SIDE = 32


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
    coverage : float
        Largest distance from an input point to its nearest anchor (world units); for a
        volume without a threshold, from a point of a lattice filling its box.
    coverage_relative : float
        ``coverage`` over the input's bounding-box diagonal.
    n_parts : int
        Connected parts of the interior (within the cage's shells) that can hold anchors.
    parts_without_anchor : int
        Parts left without an anchor (only when there are more parts than anchors).
    n_candidates : int
        Medial (skeleton) voxels.
    voxel_size : float
    seconds : float
    """

    count: int
    min_pairwise_distance: float
    min_depth: float
    coverage: float
    coverage_relative: float
    n_parts: int
    parts_without_anchor: int
    n_candidates: int
    voxel_size: float
    seconds: float

    def __str__(self) -> str:
        return (
            f"{self.count} anchors from {self.n_candidates} medial voxels in {self.n_parts} "
            f"part(s); every point within {self.coverage:.4g} "
            f"({100 * self.coverage_relative:.1f}% of the diagonal) of an anchor; min "
            f"pairwise distance {self.min_pairwise_distance:.4g}, min depth "
            f"{self.min_depth:.4g}; {self.seconds:.2f} s"
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


#: the length of each of ``_OFFSETS``: the step to that neighbour, in voxels
_STEPS = np.linalg.norm(_OFFSETS, axis=1)


def _medial(depth: np.ndarray, interior: np.ndarray, voxels: np.ndarray) -> np.ndarray:
    """Whether each voxel is on the skeleton (interior, no neighbour much deeper).

    A neighbour deeper by half the step to it or more takes a voxel off the skeleton;
    outside the grid counts as depth 0.

    Parameters
    ----------
    depth : (nx, ny, nz) float array
        Distance of each voxel to the outside, in voxels.
    interior : (nx, ny, nz) bool array
    voxels : (k, 3) int array
        The voxels asked about (indices into the grid).

    Returns
    -------
    (k,) bool
    """
    return _medial_kernel(
        np.ascontiguousarray(depth, dtype=np.float64),
        np.ascontiguousarray(interior, dtype=np.bool_),
        np.ascontiguousarray(voxels, dtype=np.int64),
        _OFFSETS.astype(np.int64),
        _STEPS,
    )


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _medial_kernel(depth, interior, voxels, offsets, steps):  # pragma: no cover - compiled
    """:func:`_medial` at each voxel: the largest rise ``(neighbour - depth) / step``."""
    nx, ny, nz = depth.shape
    out = np.zeros(voxels.shape[0], dtype=np.bool_)
    for k in range(voxels.shape[0]):
        i, j, m = voxels[k, 0], voxels[k, 1], voxels[k, 2]
        if not interior[i, j, m]:
            continue
        here = depth[i, j, m]
        rise = -np.inf
        for o in range(offsets.shape[0]):
            a, b, c = i + offsets[o, 0], j + offsets[o, 1], m + offsets[o, 2]
            there = 0.0
            if 0 <= a < nx and 0 <= b < ny and 0 <= c < nz:
                there = depth[a, b, c]
            r = (there - here) / steps[o]
            if r > rise:
                rise = r
        out[k] = rise < 0.5
    return out


def _as_cage(cage):
    """The cage argument of :func:`auto_anchors` as a :class:`vhm_viz.Cage`."""
    if isinstance(cage, Cage):
        return cage
    if isinstance(cage, (str, os.PathLike)):
        return io.read_cage(cage)
    if isinstance(cage, tuple) and len(cage) == 2:
        return Cage(*cage)
    if hasattr(cage, "GetPoints"):
        return io.cage_from_dataset(cage)
    raise ValueError(f"automatic anchors: cannot use {type(cage).__name__} as a cage")


def _shape_voxels(samples, grid):
    """(inside, surface) voxel masks of the shape on ``grid``."""
    pts = samples.points
    if samples.kind == "volume-box":
        inside = np.zeros(grid.shape, dtype=bool)
        i0, i1 = grid.voxel_of(pts.min(axis=0)[None])[0], grid.voxel_of(pts.max(axis=0)[None])[0]
        inside[i0[0] : i1[0] + 1, i0[1] : i1[1] + 1, i0[2] : i1[2] + 1] = True
        return inside, inside & ~ndimage.binary_erosion(inside)
    surface = samples.voxelise(grid, closing=1.0 if samples.kind == "volume" else 2.0)
    if samples.kind == "volume":
        # the region itself is the shape (cavities below the threshold stay out)
        return surface, surface & ~ndimage.binary_erosion(surface)
    inside = vx.fill_inside(surface)
    return inside, surface


def _box_points(lo: np.ndarray, hi: np.ndarray, per_side: int) -> np.ndarray:
    """A lattice filling the box ``lo``-``hi``, its faces and corners included.

    ``per_side`` points along the box's longest side; along the others as many as keep
    the step at most that one's (at least 2). Returns (N, 3) float64.
    """
    step = float(np.max(hi - lo)) / (per_side - 1)
    axes = [
        np.linspace(a, b, max(2, int(np.ceil((b - a) / step * (1 - 1e-9))) + 1))
        for a, b in zip(lo, hi, strict=True)
    ]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _shell_of(cage, points: np.ndarray) -> np.ndarray:
    """Index of the cage shell (domain) holding each point; -1 outside the cage."""
    V, F = np.asarray(cage.vertices), np.asarray(cage.faces)
    out = np.full(len(points), -1, dtype=np.int64)
    n = len(V)
    for k, cols in enumerate(domain_columns(V, F)):
        faces = F[cols[cols >= n] - n]
        out[inside_cage(winding_number(points, V, faces)) & (out < 0)] = k
    return out


def _targets(points: np.ndarray, h: float, limit: int = 50_000) -> np.ndarray:
    """What the anchors must cover: one input point per cell of a grid.

    Cells of size ``h`` or, for large inputs, coarser so that about ``limit`` remain
    (the coverage is then exact up to a cell diagonal; the report measures every point).
    """
    cell = float(h)
    for _ in range(8):
        key = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
        _, first = np.unique(key, axis=0, return_index=True)
        if len(first) <= limit:
            break
        cell *= (len(first) / limit) ** (1.0 / 3.0) * 1.05
    return points[np.sort(first)]


def _ball_centre(points: np.ndarray, rounds: int = 30) -> np.ndarray:
    """Approximate centre of the smallest ball around ``points`` (Badoiu-Clarkson)."""
    return np.array(_ball_centre_kernel(np.ascontiguousarray(points, dtype=np.float64), rounds))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _ball_centre_kernel(points, rounds):  # pragma: no cover - compiled
    """:func:`_ball_centre`'s ``(x, y, z)``.

    From the mean, a step ``1 / (i + 1)`` of the way to the point farthest from the centre
    (the first of equals), ``rounds`` times: numpy's ``mean(axis=0)``, squared distances
    and ``argmax``, operation for operation.
    """
    n = points.shape[0]
    cx, cy, cz = 0.0, 0.0, 0.0
    for k in range(n):  # numpy's axis-0 sum: row after row
        cx += points[k, 0]
        cy += points[k, 1]
        cz += points[k, 2]
    cx, cy, cz = cx / n, cy / n, cz / n
    for i in range(1, rounds + 1):
        best, far = -np.inf, 0
        for k in range(n):
            dx, dy, dz = points[k, 0] - cx, points[k, 1] - cy, points[k, 2] - cz
            d = dx * dx + dy * dy + dz * dz
            if d > best:
                best, far = d, k
        cx = cx + (points[far, 0] - cx) / (i + 1)
        cy = cy + (points[far, 1] - cy) / (i + 1)
        cz = cz + (points[far, 2] - cz) / (i + 1)
    return cx, cy, cz


class _Trees:
    """KD-trees of the candidates' centres, each built once per set of candidates.

    The placement asks for the same sets again and again (all candidates, a part's, its
    skeleton's, the allowed ones of a part: often all of them), and building a tree over
    a volume's hundreds of thousands of candidates costs more than the queries.
    """

    def __init__(self, centres: np.ndarray):
        self.centres = centres
        self._built: dict = {}

    def of(self, index=None) -> cKDTree:
        """The tree of ``centres[index]`` (ascending candidate indices; None: all)."""
        every = index is None or len(index) == len(self.centres)  # ascending: all of them
        key = "all" if every else np.asarray(index, dtype=np.int64).tobytes()
        if key not in self._built:
            self._built[key] = kd_tree(
                self.centres if every else self.centres[index],
                balanced_tree=False,
                compact_nodes=False,
            )
        return self._built[key]


def _farthest_point_anchors(trees, skeleton, part, targets, seeds, count, on_skeleton):
    """Farthest-point sampling, over the skeleton or over the shape's points.

    ``on_skeleton``: the skeleton voxel farthest from all anchors gets the next one (the
    paper's medial anchors). Otherwise the target (shape point) farthest from all anchors
    gets it, in the part of the candidate nearest to the target: on that part's skeleton
    when that is nearer to the target than every anchor (a limb), else halfway from the
    target towards the skeleton (a fat part, whose skeleton is far from its surface).
    Returns candidate indices, ``seeds`` first. ``trees``: the candidates' :class:`_Trees`.
    """
    centres = trees.centres
    chosen = list(seeds)
    tree_all = trees.of()
    by_part = {}

    def part_trees(k):
        if k not in by_part:
            members = np.flatnonzero(part == k)
            sk = members[skeleton[members]]
            by_part[k] = (members, trees.of(members), sk, trees.of(sk) if len(sk) else None)
        return by_part[k]

    if on_skeleton:
        # plain farthest-point sampling over the skeleton (and over the candidates of
        # parts that have none)
        has_skeleton = np.zeros(int(part.max()) + 1, dtype=bool)
        has_skeleton[part[skeleton]] = True
        pool = np.flatnonzero(skeleton | ~has_skeleton[part])
        gap = np.full(len(pool), np.inf)
        for c in chosen:
            gap = np.minimum(gap, np.linalg.norm(centres[pool] - centres[c], axis=1))
        while len(chosen) < count:
            c = int(pool[np.argmax(gap)])
            chosen.append(c)
            gap = np.minimum(gap, np.linalg.norm(centres[pool] - centres[c], axis=1))
        return np.array(chosen[:count], dtype=np.int64)
    dist = np.full(len(targets), np.inf)
    for c in chosen:
        dist = np.minimum(dist, np.linalg.norm(targets - centres[c], axis=1))
    taken = np.zeros(len(centres), dtype=bool)
    taken[chosen] = True
    # every candidate's distance to the nearest anchor, kept from the first taken pick
    # on (fat shapes take nearly every pick): one pass per anchor, not a tree per pick
    gap = None
    while len(chosen) < count:
        i = int(np.argmax(dist))
        p, r = targets[i], float(dist[i])
        c = int(tree_all.query(p)[1])
        members, tree, sk, tree_sk = part_trees(int(part[c]))
        pool = members
        if tree_sk is not None:
            ds, js = tree_sk.query(p)
            if ds < r:  # the skeleton is nearer than any anchor: use it
                c, pool = int(sk[js]), sk
            else:  # a fat part: halfway from the point towards its skeleton
                q = p + min(0.5 * r, ds) * (centres[sk[js]] - p) / max(ds, 1e-300)
                c = int(members[tree.query(q)[1]])
        if taken[c]:  # taken: the free candidate of the pool farthest from the anchors
            # (a pool all taken -- a skeleton of a voxel or two -- widens to the part,
            # then to every candidate: anchors never coincide)
            if gap is None:
                gap = kd_tree(centres[chosen]).query(centres)[0]
            for wider in (pool, members, None):
                free = np.flatnonzero(~taken) if wider is None else wider[~taken[wider]]
                if len(free):
                    break
            c = int(free[np.argmax(gap[free])])
        chosen.append(c)
        taken[c] = True
        if gap is not None:
            _nearer(gap, centres, c)
        dist = np.minimum(dist, np.linalg.norm(targets - centres[c], axis=1))
    return np.array(chosen[:count], dtype=np.int64)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _nearer(gap, centres, c):  # pragma: no cover - compiled
    """``gap = min(gap, |centres - centres[c]|)`` in place, in one pass."""
    x, y, z = centres[c, 0], centres[c, 1], centres[c, 2]
    for k in range(centres.shape[0]):
        dx, dy, dz = centres[k, 0] - x, centres[k, 1] - y, centres[k, 2] - z
        d = np.sqrt(dx * dx + dy * dy + dz * dz)
        if d < gap[k]:
            gap[k] = d


def _closest_pair(points: np.ndarray) -> float:
    """Smallest distance between two of the points (``inf`` for fewer than two)."""
    if len(points) < 2:
        return float("inf")
    return float(kd_tree(points).query(points, k=2)[0][:, 1].min())


def _minimax_rounds(trees, allowed, part, targets, chosen, rounds: int = 40):
    """Lloyd iterations towards the centres of the balls around what each anchor covers.

    Every round moves each anchor to (the ``allowed`` candidate of its part nearest to)
    the centre of the smallest ball around the targets it is nearest to; the
    configuration with the smallest largest distance seen is returned (rounds may go up
    as well as down, which lets anchors slide past each other).
    """
    centres = trees.centres
    of_part = {}
    for k in np.unique(part[chosen]):
        idx = np.flatnonzero((part == k) & allowed)
        if len(idx) == 0:
            idx = np.flatnonzero(part == k)
        of_part[int(k)] = (idx, trees.of(idx))
    d, lab = kd_tree(centres[chosen]).query(targets)
    best, best_chosen = float(d.max()), chosen.copy()
    # anchors may not crowd closer than half the closest pair farthest-point sampling left
    spread = 0.5 * _closest_pair(centres[chosen])
    for _ in range(rounds):
        moved = chosen.copy()
        # the targets each anchor covers, in their order: one stable sort, not a scan each
        by_anchor = np.argsort(lab, kind="stable")
        ends = np.searchsorted(lab[by_anchor], np.arange(len(chosen) + 1))
        for a in range(len(chosen)):
            if ends[a + 1] > ends[a]:
                mine = targets[by_anchor[ends[a] : ends[a + 1]]]
                idx, tree = of_part[int(part[chosen[a]])]
                moved[a] = idx[tree.query(_ball_centre(mine))[1]]
        _undo_crowding(centres, chosen, moved, spread)
        if _closest_pair(centres[moved]) < spread:
            break
        if np.array_equal(moved, chosen):
            break
        chosen = moved
        d, lab = kd_tree(centres[chosen]).query(targets)
        if d.max() < best:
            best, best_chosen = float(d.max()), chosen.copy()
    return best_chosen, best


def _undo_crowding(centres, chosen, moved, spread: float) -> None:
    """Undo, anchor after anchor, each move that crowds another anchor, in place.

    Anchor ``a`` goes back to ``chosen[a]`` when ``moved[a]`` lies nearer than ``spread``
    to another anchor where that one is now: moved, or already sent back. The neighbours
    within ``spread`` come from one tree of both positions of every anchor.
    """
    n = len(moved)
    if n < 2 or not spread > 0:  # no distance is below zero
        return
    tree = kd_tree(np.concatenate([centres[moved], centres[chosen]]))
    near = tree.query_ball_point(centres[moved], r=spread * (1 + 1e-9))  # then exactly
    back = np.zeros(n, dtype=bool)
    for a in range(n):
        here = centres[moved[a]]
        for j in near[a]:
            b, at_rest = (j, False) if j < n else (j - n, True)
            # b is where it is now: moved unless sent back (only anchors before a are)
            if b == a or at_rest != (b < a and back[b]):
                continue
            d = centres[chosen[b] if at_rest else moved[b]] - here
            if np.sqrt(d @ d) < spread:
                back[a] = True
                moved[a] = chosen[a]
                break


def _relocated(trees, allowed, part, targets, chosen, cover, tries: int = 6):
    """Move the least useful anchor next to the worst-covered point, while that helps.

    The anchor with the smallest covered ball (not the only one of its part) goes to the
    ``allowed`` candidate nearest to the target farthest from all anchors, then Lloyd
    rounds settle the rest; the move is kept when the coverage improves.
    """
    centres, tree = trees.centres, trees.of()
    for _ in range(tries):
        d, lab = kd_tree(centres[chosen]).query(targets)
        radius = np.zeros(len(chosen))
        np.maximum.at(radius, lab, d)
        alone = np.bincount(part[chosen])[part[chosen]] == 1  # its part's only anchor
        radius[alone] = np.inf
        a = int(np.argmin(radius))
        if not np.isfinite(radius[a]):
            break
        k = min(16, len(centres))
        near = np.atleast_1d(tree.query(targets[int(np.argmax(d))], k=k)[1])
        taken = set(chosen.tolist())
        near = [c for c in near if allowed[c] and c not in taken]
        if not near:
            break
        trial = chosen.copy()
        trial[a] = near[0]
        trial, trial_cover = _minimax_rounds(trees, allowed, part, targets, trial, rounds=15)
        if trial_cover >= cover:
            break
        chosen, cover = trial, trial_cover
    return chosen, cover


def _check_enclosed(samples, cage, points: np.ndarray) -> None:
    """Refuse a cage that does not enclose the shape, as deforming the data would.

    The shape's points (``points``): a surface's vertices, a cloud's or tet mesh's
    points, a volume's voxels above its threshold, or without a threshold a lattice
    filling the volume's box (the shape is then the whole box). Inside is
    :meth:`vhm_viz.Cage.contains`, the test ``deform`` and ``analyze`` use. Anchors
    placed in the part of the shape a cage holds would not be the anchors of the shape,
    and a cage holding almost none of it leaves only the same few voxels to hold them.

    Raises
    ------
    OutsideCageError
        Points outside the cage, counted (and for surfaces, clouds and tet meshes, listed
        by their index in the input).
    """
    outside = np.flatnonzero(~cage.contains(points))
    if not len(outside):
        return
    n, total = len(outside), len(points)
    if samples.kind == "volume-box":
        what = (
            f"{n} of {total} points of a lattice filling the volume's box are outside the "
            "cage (without a threshold the shape is the whole box): give a cage that "
            "encloses the box, or a threshold whose region the cage encloses"
        )
    elif samples.kind == "volume":
        what = (
            f"{n} of {total} voxels above the threshold {samples.threshold:.6g} are "
            "outside the cage: give a cage that encloses them, or a higher threshold"
        )
    else:
        used = np.unique(samples.tri_faces) if samples.kind == "surface" else ()
        if len(used) == total:  # a surface's points are the vertices its faces use
            outside = used[outside]
        what = (
            f"{n} of {total} points of the data are outside the cage (indices "
            f"{describe_indices(outside)}): give a cage that encloses the data"
        )
    raise OutsideCageError(f"automatic anchors: {what}", outside)


def _inside_shape(samples, points: np.ndarray) -> np.ndarray:
    """Exact check that points lie inside the input's surface (surfaces, tet meshes)."""
    if samples.tri_faces is None or not len(samples.tri_faces) or not len(points):
        return np.ones(len(points), dtype=bool)
    # inconsistently oriented inputs give -1 inside: only the magnitude is trusted
    return np.abs(winding_number(points, samples.tri_vertices, samples.tri_faces)) > 0.5


def auto_anchors(
    data,
    cage,
    count: int,
    *,
    resolution: int | None = None,
    threshold=None,
    scalars: str | None = None,
    outside: str = "error",
    return_report: bool = False,
):
    """Place ``count`` anchors that cover ``data``, on its skeleton where it is thin.

    Parameters
    ----------
    data : PolyData, UnstructuredGrid, ImageData, (N, 3) array, (vertices, faces) or path
        The shape (as for :func:`vhm_viz.auto_cage`).
    cage : Cage, (vertices, faces), PolyData or path
        Anchors must lie inside it. It must enclose the shape: every point of a surface,
        cloud or tet mesh, every voxel above a volume's threshold, or without a threshold
        the volume's whole box.
    count : int
        Number of anchors ``d``, in ``anchor_count``'s range (1 to 10,000:
        :mod:`vhm_viz.core.limits`); exactly this many are returned.
    resolution : int, optional
        Voxels along the longest side of the shape (default 96; volumes: one per image
        sample, at most 96; a volume without a threshold, whose shape is its whole box:
        48).
    threshold, scalars
        Volumes: as for :func:`vhm_viz.auto_cage`.
    outside : {"error", "ignore"}
        Points of the shape outside the cage: refused (:class:`OutsideCageError`), or
        left to the caller, the anchors covering the part of the shape the cage holds
        (a scene's solve: its map checks the data against the cage, as ``deform
        --outside`` says).
    return_report : bool
        Also return an :class:`AnchorReport` (coverage, parts, depth).

    Returns
    -------
    anchors : (count, 3) float64
        Inside the shape and the cage, no two the same. Every cage shell holding part of
        the shape gets one, and every connected part when there are at most
        ``count // 2`` of them (else the largest, up to half the anchors; the report
        counts the others).
    report : AnchorReport, only with ``return_report``

    Raises
    ------
    OutsideCageError
        Points of the shape outside the cage, counted.
    SettingError
        ``count`` out of its range, or ``resolution`` not an integer of at least 4.
    ValueError
        Degenerate input, a shape too thin for the voxel grid (raise ``resolution``), or
        fewer interior voxels than ``count``.
    """
    t0 = time.perf_counter()
    count = check_setting("anchor_count", count, "count")
    if resolution is not None:
        resolution = check_integer_at_least("resolution", resolution, 4)
    samples = collect_samples(data, threshold=threshold, scalars=scalars, what="auto_anchors")
    cage = _as_cage(cage)
    pts, box_targets = samples.points, None
    if samples.kind == "volume-box":
        # the whole box is the shape: the anchors cover its inside, not only its corners
        # (a coarser lattice of it for the placement); its skeleton needs no fine grid
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pts = _box_points(lo, hi, _BOX_REPORT_PER_SIDE)
        box_targets = _box_points(lo, hi, _BOX_TARGETS_PER_SIDE)
        resolution = _BOX_RESOLUTION if resolution is None else resolution
    if outside == "error":
        _check_enclosed(samples, cage, pts)
    elif outside != "ignore":
        raise ValueError(f"automatic anchors: outside must be 'error' or 'ignore'; got {outside!r}")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ext = float(np.max(hi - lo))
    if resolution is None and samples.kind == "volume" and samples.spacing:
        # one voxel per image sample: the region needs no closing
        resolution = int(np.clip(np.ceil(ext / samples.spacing), 4, 96))
    r = 96 if resolution is None else resolution
    if samples.kind == "points" and samples.spacing is None:
        samples.spacing = point_spacing(pts)
    grid = vx.make_grid(lo, hi, r, 2)
    inside, surface = _shape_voxels(samples, grid)
    depth = ndimage.distance_transform_edt(inside)  # voxels to the nearest outside centre
    # candidates: voxels at least a voxel away from every surface sample ("interior");
    # where the shape is too thin to have any (a limb one or two voxels thick, a few
    # voxels from any interior one) the voxels that hold no surface sample; in a speck
    # (a voxel or two of a volume) its voxels. So thin limbs and small parts can hold
    # anchors too.
    pieces, n_pieces = ndimage.label(inside, structure=np.ones((3, 3, 3), dtype=bool))
    interior = inside & ~vx.cube_dilate(surface, 1)
    loose = inside & ~surface
    held = np.zeros(n_pieces + 1, dtype=bool)
    held[np.unique(pieces[loose])] = True
    cand_mask = interior | (loose & ~vx.cube_dilate(interior, 2)) | (inside & ~held[pieces])
    cand = np.argwhere(cand_mask)
    if len(cand) == 0:
        raise ValueError(
            f"automatic anchors: the shape is too thin for a {r}-voxel grid (no interior voxel); "
            "raise resolution"
        )
    centres = grid.centers(cand)
    if samples.kind == "volume":
        # a voxel of the anchor grid can straddle the region's rim (anisotropic images):
        # the anchor goes to the nearest voxel above the threshold, in the region for sure
        nearest = kd_tree(pts).query(centres)[1]
        _, first = np.unique(nearest, return_index=True)
        cand, centres = cand[np.sort(first)], pts[nearest[np.sort(first)]]
    shell = _shell_of(cage, centres)
    keep = shell >= 0
    # a voxel off the interior can lie outside a closed input surface (in a narrow gap
    # the voxelisation closed): those are checked exactly (winding number)
    doubtful = keep & ~interior[cand[:, 0], cand[:, 1], cand[:, 2]]
    keep[doubtful] = _inside_shape(samples, centres[doubtful])
    cand, centres, shell = cand[keep], centres[keep], shell[keep]
    if len(cand) < count:
        raise ValueError(
            f"automatic anchors: only {len(cand)} interior voxels inside the cage for {count} "
            "anchors; raise resolution or lower count"
        )
    dep = depth[cand[:, 0], cand[:, 1], cand[:, 2]]
    skeleton = _medial(depth, inside, cand)
    # parts: connected pieces of the shape, split by cage shell
    comp = pieces[cand[:, 0], cand[:, 1], cand[:, 2]]
    # numbered as the (piece, shell) pairs sort: one integer key per pair, in that order
    _, part = np.unique(comp * (int(shell.max()) + 1) + shell, return_inverse=True)
    part = part.ravel()
    sizes = np.bincount(part)
    # seeds: every cage shell holding candidates (a constrained shell needs an anchor),
    # then every part, largest first -- all of them when they take at most half the
    # anchors, else as many as that (the rest go where the coverage needs them)
    shell_of_part = np.zeros(len(sizes), dtype=np.int64)
    shell_of_part[part] = shell
    order = np.argsort(-sizes, kind="stable")
    first_of_shell = [int(order[shell_of_part[order] == k][0]) for k in np.unique(shell)]
    rest = [int(k) for k in order if int(k) not in first_of_shell]
    budget = count if len(sizes) <= count // 2 else max(count // 2, len(first_of_shell))
    seed_parts = (first_of_shell + rest)[: min(budget, count)]
    seeds = []
    for k in seed_parts:
        members = np.flatnonzero(part == k)
        pref = members[skeleton[members]] if skeleton[members].any() else members
        seeds.append(int(pref[np.argmax(dep[pref])]))
    targets = _targets(pts, grid.h) if box_targets is None else box_targets
    # on the skeleton (the paper's medial anchors) unless leaving it covers the shape
    # clearly better, or the skeleton alone misses the coverage goal (fat parts, whose
    # skeleton lies far from much of their surface)
    placed = []
    trees = _Trees(centres)
    for on_skeleton in (True, False):
        chosen = _farthest_point_anchors(trees, skeleton, part, targets, seeds, count, on_skeleton)
        allowed = skeleton if on_skeleton else np.ones(len(centres), dtype=bool)
        chosen, cover = _minimax_rounds(trees, allowed, part, targets, chosen)
        placed.append(_relocated(trees, allowed, part, targets, chosen, cover))
    (medial, medial_cover), (mixed, mixed_cover) = placed
    diag = float(np.linalg.norm(hi - lo))
    goal = _COVERAGE_GOAL * diag
    if len(np.unique(medial)) < count:
        on_medial = False  # a skeleton of fewer voxels than anchors: some would coincide
    elif medial_cover <= goal or mixed_cover > goal:
        on_medial = medial_cover <= max(goal, _MEDIAL_SLACK * mixed_cover)
    else:
        on_medial = False
    chosen = medial if on_medial else mixed
    if len(np.unique(chosen)) < count:  # pragma: no cover - guarded by construction
        raise RuntimeError(
            f"automatic anchors: internal error, {len(np.unique(chosen))} distinct positions for "
            f"{count} anchors"
        )
    anchors = centres[chosen]
    dist, _ = kd_tree(anchors).query(pts)
    min_pair = _closest_pair(anchors)
    report = AnchorReport(
        count=count,
        min_pairwise_distance=min_pair,
        min_depth=float(dep[chosen].min() * grid.h),
        coverage=float(dist.max()),
        coverage_relative=float(dist.max()) / diag,
        n_parts=int(len(sizes)),
        parts_without_anchor=int(len(sizes) - len(np.unique(part[chosen]))),
        n_candidates=int(skeleton.sum()),
        voxel_size=float(grid.h),
        seconds=time.perf_counter() - t0,
    )
    return (anchors, report) if return_report else anchors
