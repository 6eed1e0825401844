"""Cutting a volume's work into shares for MPI ranks: root layers, output planes, windows.

Deterministic functions of plain sums: every rank computes the same cuts from the same
numbers. The lattice's root k-layers are cut by the voxels inside the cage
(:func:`layer_shares`); an output grid's k-planes by the work and the leaves of pulling
them back (:func:`pull_back_shares`); :func:`window_of` finds the input voxels that
resampling an output box reads, from tables the ranks share.
"""

from __future__ import annotations

import math

import numpy as np

from vhm_viz.core.image import ImageGeometry, inside_mask

__all__ = [
    "layer_shares",
    "equal_cuts",
    "lattice_build_work",
    "pull_back_shares",
    "pull_back_pairs",
    "pull_back_spans",
    "window_of",
]

# The work of resampling a voxel beyond its leaf tests (its arrays, sampling,
# pass-through), in leaf tests: a voxel of an output slab that no leaf reaches costs
# about a fifth of a (voxel, candidate leaf) pair.
_PULL_BACK_VOXEL_WORK = 0.2
# The work of a lattice build per exact evaluation and basis function of the map (cage
# vertex or face), the build's bookkeeping included, in leaf tests: about a fifth of a
# (voxel, candidate leaf) pair per function.
_EVALUATION_WORK_PER_BASIS = 0.2


def layer_shares(geometry: ImageGeometry, cage, root: int, parts: int) -> np.ndarray:
    """Split the root k-layers of a lattice into ``parts`` runs of about equal work.

    The work of a root layer is taken to be its voxels inside the cage, counted on a grid
    of every ``root / 4``-th voxel: the lattice refines only cells with voxels inside.
    A proxy, not a count of leaves, but one that follows the leaves far more closely
    than equal numbers of layers do (a cage holds more of the volume in some layers than
    in others). Deterministic: every MPI rank computes the same cuts.

    Parameters
    ----------
    geometry : ImageGeometry
        The input grid.
    cage : Cage
        Its ``vertices`` and ``faces`` (world).
    root : int
        Root cell size (voxels).
    parts : int

    Returns
    -------
    (parts + 1,) int64
        Layer cuts: part ``r`` holds the layers ``cuts[r] <= layer < cuts[r + 1]``. Equal
        numbers of layers when no voxel is inside.
    """
    last_k = int(geometry.dimensions[2]) - 1
    n_layers = max(1, -(-last_k // root))
    step = max(1, root // 4)
    dims = [-(-int(n) // step) for n in geometry.dimensions]
    coarse = ImageGeometry(geometry.origin, np.asarray(geometry.spacing) * step, dims,
                           geometry.direction)  # fmt: skip
    inside = inside_mask(coarse, cage.vertices, cage.faces).sum(axis=(1, 2))
    # a root cell owns the voxels [o, o + root); the lattice's far end, the last cell
    layer = np.minimum(np.arange(len(inside)) * step // root, n_layers - 1)
    weight = np.bincount(layer, weights=inside, minlength=n_layers).astype(np.float64)
    return equal_cuts(weight, parts)


def equal_cuts(weight, parts: int) -> np.ndarray:
    """Split a run of items into ``parts`` contiguous runs of about equal total weight.

    Each cut falls at the item boundary nearest its target (``r / parts`` of the total),
    so a part may be empty when one item outweighs a share. Deterministic: every MPI rank
    computes the same cuts from the same weights.

    Parameters
    ----------
    weight : (n,) array_like
        Non-negative weights (work per item). All zero: equal numbers of items.
    parts : int

    Returns
    -------
    (parts + 1,) int64
        Cuts: part ``r`` holds the items ``cuts[r] <= i < cuts[r + 1]``.
    """
    weight = np.asarray(weight, dtype=np.float64).ravel()
    n = len(weight)
    if not weight.sum() > 0:
        weight = np.ones(n)
    total = np.concatenate([[0.0], np.cumsum(weight)])
    cuts = [0]
    for r in range(1, parts):
        target = total[-1] * r / parts
        at = int(np.searchsorted(total, target))
        if at > 0 and target - total[at - 1] < total[min(at, n)] - target:
            at -= 1  # the nearer of the two item boundaries around the target
        cuts.append(min(max(at, cuts[-1]), n))
    cuts.append(n)
    return np.asarray(cuts, dtype=np.int64)


def lattice_build_work(evaluations: int, basis_functions: int) -> float:
    """The work of a lattice build of ``evaluations`` exact evaluations, in leaf tests.

    In the units of :func:`pull_back_shares` (a (voxel, candidate leaf) pair of a
    pull-back), for a map of ``basis_functions`` functions (cage vertices plus faces).
    """
    return float(evaluations) * float(basis_functions) * _EVALUATION_WORK_PER_BASIS


def pull_back_shares(pairs, geometry: ImageGeometry, parts: int, spans=None,
                     shared_work: float = 0.0) -> np.ndarray:  # fmt: skip
    """Cut the k-planes of an output grid into ``parts`` runs: shares of work and of leaves.

    A plane's work is its (voxel, candidate leaf) pairs
    (:meth:`VolumeDeformation.pull_back_pairs`) plus :data:`_PULL_BACK_VOXEL_WORK` per
    voxel: an MPI rank's time. The pairs are not spread evenly over the planes (a bent
    volume's denser half can hold most of them), so equal numbers of planes would keep
    one rank busy far longer than another. A part's share of the work counts its even
    share of ``shared_work`` too: the work every part does alike, whatever the cuts (the
    ranks' lattice build, :func:`lattice_build_work`), so that the cuts weigh a plane by
    its part of a rank's whole update.

    The leaves that a run of planes needs (those whose candidate boxes reach it:
    ``spans``) are most of an MPI rank's memory while it pulls back. They are not spread
    as the work is, so with ``spans`` the cuts make the largest of every part's two
    shares -- of the work, of the leaves -- as small as it can be: no rank takes much
    more than its share of either. Without ``spans``, equal shares of the work.

    Parameters
    ----------
    pairs : (nz,) array_like
        Pairs per k-plane of the whole lattice.
    geometry : ImageGeometry
        The output grid.
    parts : int
    spans : ((nz,), (nz,)) array_like, optional
        Per k-plane, the leaves whose candidate boxes start there and those that end
        there (:meth:`VolumeDeformation.pull_back_spans`).
    shared_work : float
        Work shared evenly by the parts besides their planes, in leaf tests (>= 0).

    Returns
    -------
    (parts + 1,) int64
        Plane cuts: part ``r`` pulls back the planes ``cuts[r] <= k < cuts[r + 1]``.
        Deterministic: every MPI rank computes the same cuts from the same sums.
    """
    nx, ny, nz = (int(n) for n in geometry.dimensions)
    work = np.asarray(pairs, dtype=np.float64) + _PULL_BACK_VOXEL_WORK * float(nx * ny)
    if spans is None or parts <= 1:
        return equal_cuts(work, parts)
    starts, ends = (np.asarray(a, dtype=np.float64).reshape(nz) for a in spans)
    done_work = np.concatenate([[0.0], np.cumsum(work)])
    started = np.cumsum(starts)  # leaves reaching a plane <= k
    ended = np.concatenate([[0.0], np.cumsum(ends)])  # leaves ending below plane k
    shared = max(float(shared_work), 0.0)
    total_work, total_leaves = done_work[-1] + shared, max(started[-1], 1.0)

    def share(a, b):  # the larger of planes a..b-1's shares
        return max((shared / parts + done_work[b] - done_work[a]) / total_work,
                   (started[b - 1] - ended[a]) / total_leaves)  # fmt: skip

    def greedy(limit):  # the longest runs within the limit, or None if more than parts
        cuts = [0]
        while cuts[-1] < nz:
            a, b = cuts[-1], cuts[-1] + 1  # (a plane over the limit makes a run alone)
            while b < nz and share(a, b + 1) <= limit:
                b += 1
            cuts.append(b)
            if len(cuts) > parts + 1:
                return None
        return cuts + [nz] * (parts + 1 - len(cuts))

    # bisection on the largest share: greedy runs fit within a limit iff it can be met
    lo, hi = 0.0, 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if greedy(mid) is None:
            lo = mid
        else:
            hi = mid
    return np.asarray(greedy(hi), dtype=np.int64)


def window_of(table, box, geometry: ImageGeometry, output: ImageGeometry, *,
              interpolation: str = "linear", margin: float, in_place: bool):  # fmt: skip
    """The input voxels that resampling the output ``box`` reads (see ``input_window``).

    Parameters
    ----------
    table : (R, 12) int array_like
        Rows ``(out_lo, out_hi, in_lo, in_hi)``: the output voxels a group of leaves (one
        leaf, or a root cell's: :meth:`VolumeDeformation.reach_table`) can reach, and the
        input voxels it spans.
    box : (6,) int
        The output box ``(i0, i1, j0, j1, k0, k1)``.
    geometry, output : ImageGeometry
        The input and output grids.
    interpolation : str
        Its stencil widens the window (one voxel, two for cubic).
    margin : float
        How far (voxels) outside its leaf a pre-image may lie (the largest of the leaves').
    in_place : bool
        Voxels outside the cage stay in place: the box's own position in the input is read.

    Returns
    -------
    (6,) int64 or None
        ``(i0, i1, j0, j1, k0, k1)`` inclusive, or None when nothing is read.
    """
    b = np.asarray(box, dtype=np.int64)
    t = np.asarray(table, dtype=np.int64).reshape(-1, 12)
    hit = np.all((t[:, 0:3] <= b[1::2]) & (t[:, 3:6] >= b[0::2]), axis=1)
    # pre-images lie within the leaf grown by its margin; the stencil reaches one voxel
    # beyond the cell holding them (linear), two for cubic
    stencil = 2 if interpolation == "cubic" else 1
    reach = stencil + int(math.ceil(margin))
    last = np.asarray(geometry.dimensions, dtype=np.int64) - 1
    parts_lo, parts_hi = [], []
    if hit.any():
        parts_lo.append(t[hit, 6:9].min(axis=0) - reach)
        parts_hi.append(t[hit, 9:12].max(axis=0) + reach)
    if in_place:
        corners = np.array([[b[0 + a], b[2 + c], b[4 + d]] for a in (0, 1)
                            for c in (0, 1) for d in (0, 1)], dtype=np.float64)  # fmt: skip
        u = geometry.continuous_index(output.points(corners))
        parts_lo.append(np.floor(u.min(axis=0)).astype(np.int64) - reach)
        parts_hi.append(np.ceil(u.max(axis=0)).astype(np.int64) + reach)
    if not parts_lo:
        return None
    w_lo = np.maximum(np.min(parts_lo, axis=0), 0)
    w_hi = np.minimum(np.max(parts_hi, axis=0), last)
    if (w_hi < w_lo).any():
        return None
    out = np.empty(6, dtype=np.int64)
    out[0::2], out[1::2] = w_lo, w_hi
    return out


def pull_back_pairs(lo, hi, geometry: ImageGeometry) -> np.ndarray:
    """Per k-plane of an output grid: the (voxel, candidate leaf) pairs of some leaves.

    Pulling a voxel back tries every leaf whose candidate box holds it (Newton's method
    on the leaf's polynomial): most of the work of resampling a plane.

    Parameters
    ----------
    lo, hi : (L, 3) int array_like
        The leaves' candidate boxes of output voxels (inclusive).
    geometry : ImageGeometry
        The output grid.

    Returns
    -------
    (nz,) float64
    """
    dims = np.asarray(geometry.dimensions, dtype=np.int64)
    lo, hi = np.maximum(lo, 0), np.minimum(hi, dims - 1)
    size = np.clip(hi - lo + 1, 0, None)
    area = (size[:, 0] * size[:, 1]).astype(np.float64)
    area[size[:, 2] == 0] = 0.0
    # each leaf adds its area to the planes k_lo..k_hi: a difference array
    change = np.zeros(int(dims[2]) + 1)
    np.add.at(change, np.minimum(lo[:, 2], dims[2]), area)
    np.add.at(change, np.minimum(hi[:, 2] + 1, dims[2]), -area)
    return np.cumsum(change[:-1])


def pull_back_spans(lo, hi, geometry: ImageGeometry):
    """Per k-plane of an output grid: the leaves whose candidate boxes start and end there.

    The leaves that resampling a run of planes ``a..b`` needs (whose candidate boxes
    reach it) are those started by plane ``b`` less those ended before ``a``. Leaves whose
    boxes miss the grid are not counted; boxes are clipped to it. ``lo``, ``hi`` and
    ``geometry`` as for :func:`pull_back_pairs`.

    Returns
    -------
    starts, ends : (nz,) float64
    """
    dims = np.asarray(geometry.dimensions, dtype=np.int64)
    reach = np.all((lo <= dims - 1) & (hi >= 0) & (lo <= hi), axis=1)
    nz = int(dims[2])
    k_lo = np.clip(lo[reach, 2], 0, nz - 1)
    k_hi = np.clip(hi[reach, 2], 0, nz - 1)
    return (np.bincount(k_lo, minlength=nz).astype(np.float64),
            np.bincount(k_hi, minlength=nz).astype(np.float64))  # fmt: skip
