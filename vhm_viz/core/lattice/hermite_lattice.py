"""The :class:`HermiteLattice` object: leaves, node data, and what it answers."""

from __future__ import annotations

import numba
import numpy as np

from vhm_viz.core.image import BORDER, ImageGeometry
from vhm_viz.core.lattice.cage_edges import bin_edges, points_near_binned_edges
from vhm_viz.core.lattice.cell_formulas import MARGIN
from vhm_viz.core.lattice.fold_proof import unproven_boxes
from vhm_viz.core.lattice.hermite import (
    eval_points,
    leaf_jacobians,
    leaf_owning,
    leaf_voxels,
)
from vhm_viz.core.lattice.pullback import (
    candidate_rows,
    cut_blocks,
    output_boxes,
    pull_back_rows,
)
from vhm_viz.core.memory import release_free_memory, take_in_place
from vhm_viz.core.row_threads import run_rows
from vhm_viz.core.work_items import worker_count


class HermiteLattice:
    """The adaptive Hermite lattice of a harmonic map over an image grid.

    Built by :func:`build_lattice`. Positions ``u`` are continuous voxel indices of the
    input grid (``geometry``); values are world positions.

    Attributes
    ----------
    geometry : ImageGeometry
        The input grid.
    tolerance : float
        Largest position error aimed at (voxels of the input spacing).
    data : (Q, 8, 3) float64
        Node data rows: ``f, f_u, f_v, f_w, f_uv, f_uw, f_vw, f_uvw``.
    leaf_origin : (L, 3) int64
        Lowest corner of each leaf cell (voxel indices).
    leaf_size : (L,) int64
        Cell size (voxels, a power of two).
    leaf_rows : (L, 8) int64
        Data rows of the corners (corner ``a + 2 b + 4 c`` at ``origin + (a, b, c) size``).
    leaf_cut : (L,) bool
        The cage passes through the cell (voxels outside it, or next to its surface);
        without pre-images only voxels outside it count (the surface is not marked).
    mask : (Nz, Ny, Nx) bool or None
        Inside the cage, for every lattice point (the volume's voxels and the lattice's
        overhang beyond them); a window's lattice fills only its root cells' rows. None
        in a joined lattice (:func:`join_parts`), which resamples only: its pull-back
        reads :meth:`cut_flags`.
    near : (Nz, Ny, Nx) bool or None
        Lattice points next to the cage surface (:func:`~vhm_viz.core.image.surface_mask`):
        pre-images in grid cubes touching them are checked with the winding number. Filled
        as ``mask`` is; None in a lattice without pre-images, which never reads it.
    edge_a, edge_b : (E, 3) float64
        End points of the cage's edges, in voxel indices (:meth:`near_cage_edges`).
    pre_images : bool
        False: a lattice for the voxels only (see :func:`build_lattice`).
    stats : dict
        ``evaluations`` (exact map evaluations), ``leaves``, ``leaves_per_size``,
        ``data_rows``, ``seconds``.
    """

    def __init__(self, **arrays):
        self.__dict__.update(arrays)
        self.end = self.n_root * self.root  # index of the lattice's far corner per axis
        self._margins = None
        self._edge_bins = None
        self._cut_flags = None

    def cut_flags(self, lat_geo=None, vertices=None, faces=None):
        """The inside and surface flags the pull-back reads: :func:`cut_blocks` (kept).

        From the masks; a lattice without them (joined) is given them by
        :func:`join_parts`, which passes the cage.
        """
        if self._cut_flags is None:
            if self.mask is None and lat_geo is None:
                raise ValueError("this lattice has no masks: its cut flags need the cage")
            self._cut_flags = cut_blocks(self, lat_geo, vertices, faces)
        return self._cut_flags

    def _need_pre_images(self, what: str) -> None:
        if not self.pre_images:
            raise ValueError(
                f"{what} needs the polynomial between voxels: this lattice was built for "
                "the voxels only (pre_images=False)"
            )

    @property
    def nbytes(self) -> int:
        """Memory held by the lattice's arrays (bytes)."""
        return int(
            sum(v.nbytes for v in self.__dict__.values() if isinstance(v, np.ndarray))
        )

    @property
    def last(self) -> np.ndarray:
        """Largest voxel index per axis of the input grid."""
        return np.asarray(self.geometry.dimensions, dtype=np.int64) - 1

    def inside(self, box) -> np.ndarray:
        """Inside mask (nz, ny, nx) of the voxels of ``box = (i0, i1, j0, j1, k0, k1)``."""
        i0, i1, j0, j1, k0, k1 = box
        return self.mask[k0 : k1 + 1, j0 : j1 + 1, i0 : i1 + 1]

    def leaves_in(self, box) -> np.ndarray:
        """Leaves owning a voxel of ``box`` (inclusive voxel ranges)."""
        o, h = self.leaf_origin, self.leaf_size
        lo = np.asarray(box[0::2])
        hi = np.asarray(box[1::2])
        ok = np.all((o <= hi) & (o + h[:, None] >= lo), axis=1)
        return np.ascontiguousarray(np.nonzero(ok)[0])

    def warp(self, box, out) -> None:
        """Interpolated world positions of the inside voxels of ``box``.

        Parameters
        ----------
        box : (i0, i1, j0, j1, k0, k1)
            Inclusive voxel ranges.
        out : (P, 3) float64
            The box's voxels, i fastest; rows of inside voxels are written.
        """
        b = np.asarray(box, dtype=np.int64)
        leaf_voxels(
            self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, self.leaves_in(b),
            self.end, b, self.mask, out, worker_count(),
        )  # fmt: skip

    def jacobians(self, box, out) -> None:
        """World Jacobians ``J[p, i, j] = d f_i / d x_j`` of the inside voxels of ``box``."""
        b = np.asarray(box, dtype=np.int64)
        leaf_jacobians(
            self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, self.leaves_in(b),
            self.end, b, self.mask, self.geometry.world_to_index, out, worker_count(),
        )  # fmt: skip

    def unproven_cells(self, box, rest_sign: float) -> np.ndarray:
        """Boxes of the voxel cells of ``box`` whose warp the leaves do not prove unfolded.

        :mod:`~vhm_viz.core.lattice.fold_proof`: the other cells of the warped voxels
        (:meth:`warp`) have corner Jacobian determinants of the sign of the rest voxel's.

        Parameters
        ----------
        box : (i0, i1, j0, j1, k0, k1)
            Inclusive voxel ranges; its cells are those with their lowest corner at
            ``i0 .. i1 - 1`` and so on.
        rest_sign : float
            The sign of the rest voxel's determinant (negative for a left-handed frame).

        Returns
        -------
        (K, 6) int64
            Disjoint inclusive cell ranges, relative to the box's first cell.
        """
        b = np.asarray(box, dtype=np.int64)
        first, last = b[0::2], b[1::2] - 1
        if (last < first).any() or not len(self.leaf_size):
            return np.zeros((0, 6), dtype=np.int64)
        parts = []

        def roots(start, stop):
            parts.append((start, unproven_boxes(
                start, stop, self.data, self.leaf_rows, self.leaf_origin, self.leaf_size,
                self.leaf_cut, float(rest_sign), self.root_start, self.root_count,
                self.n_root, self.root, self.last, first, last,
            )))  # fmt: skip

        run_rows(roots, len(self.root_start), grain=64)
        parts.sort(key=lambda part: part[0])
        return np.concatenate([np.zeros((0, 6), np.int64)] + [b for _, b in parts])

    @staticmethod
    def load_proof_kernel() -> None:
        """Load :meth:`unproven_cells`' compiled kernel now, for the arrays a lattice holds.

        Over an empty range of root cells, so that nothing is computed: a check's warm-up
        (:func:`vhm_viz.folds.load_check_kernels`) before a lattice exists.
        """
        none = np.zeros(0, dtype=np.int64)
        axes = np.ones(3, dtype=np.int64)
        box = np.zeros(6, dtype=np.int64)
        unproven_boxes(
            0, 0, np.zeros((0, 8, 3)), np.zeros((0, 8), np.int64), np.zeros((0, 3), np.int64),
            none, np.zeros(0, dtype=bool), 1.0, none, none, axes, 1, axes, box[0::2],
            box[1::2] - 1,
        )  # fmt: skip

    def evaluate(self, u, *, gradient: bool = False):
        """The interpolated map at continuous voxel indices.

        Parameters
        ----------
        u : (P, 3) array_like
            Voxel indices (points beyond the lattice are clamped onto it).
        gradient : bool
            Also return ``df/du`` (P, 3, 3).

        Returns
        -------
        f : (P, 3)
        fu : (P, 3, 3), only with ``gradient``

        Raises
        ------
        ValueError
            For points in cells with no voxel inside the cage (no data there).
        """
        self._need_pre_images("evaluate")
        u = np.ascontiguousarray(np.atleast_2d(u), dtype=np.float64)
        leaf = self.locate(u)
        if (leaf < 0).any():
            raise ValueError("points in cells without a voxel inside the cage")
        f = np.empty((len(u), 3))
        g = np.empty((len(u), 3, 3))
        if len(u):
            eval_points(self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, leaf, u, f, g)
        return (f, g) if gradient else f

    def near_cage_edges(self, u, radius: float) -> np.ndarray:
        """Whether each point lies within ``radius`` voxels of a cage edge.

        Parameters
        ----------
        u : (P, 3) array_like
            Continuous voxel indices.
        radius : float
            Euclidean distance in voxel index units.

        Returns
        -------
        (P,) bool
        """
        u = np.ascontiguousarray(np.atleast_2d(u), dtype=np.float64)
        if self._edge_bins is None or self._edge_bins[0] < radius:
            self._edge_bins = (radius, *bin_edges(self.edge_a, self.edge_b, radius))
        _, lo, shape, start, ids = self._edge_bins
        out = np.zeros(len(u), dtype=np.bool_)
        if len(u) and len(self.edge_a):
            points_near_binned_edges(
                u, self.edge_a, self.edge_b, radius, lo, shape, start, ids, out
            )
        return out

    def locate(self, u) -> np.ndarray:
        """Index of the leaf owning each point (``-1`` in cells without inside voxels)."""
        u = np.ascontiguousarray(np.atleast_2d(u), dtype=np.float64)
        out = np.empty(len(u), dtype=np.int64)
        locate_leaves(
            self.leaf_origin, self.leaf_size, self.root_start, self.root_count, self.n_root,
            self.root, u, out,
        )  # fmt: skip
        return out

    def image_boxes(self, geometry: ImageGeometry, margin=0.0, border: float = 0.0):
        """Per leaf, the box of ``geometry``'s continuous indices its image can reach.

        From the Bezier control points of each leaf's polynomial, which contain its image,
        restricted to the volume (extended by ``border`` voxels); ``margin`` (voxels,
        scalar or per leaf) grows each cell before mapping (to first order).

        Returns
        -------
        lo, hi : (L, 3) float64
        """
        self._need_pre_images("image_boxes")
        n = len(self.leaf_size)
        lo, hi = np.empty((n, 3)), np.empty((n, 3))
        if n:
            output_boxes(
                self.data, self.leaf_rows, self.leaf_origin, self.leaf_size,
                np.full(3, -border), self.last + border, geometry.origin,
                np.ascontiguousarray(geometry.world_to_index),
                np.broadcast_to(np.asarray(margin, dtype=np.float64), (n,)).copy(), lo, hi,
            )  # fmt: skip
        return lo, hi

    def margins(self) -> np.ndarray:
        """How far (voxels) outside each leaf its pre-images may lie.

        :data:`MARGIN` (mismatch between cells of different sizes), plus the half-voxel
        border for leaves on the volume's boundary.
        """
        if self._margins is None:
            o, h = self.leaf_origin, self.leaf_size[:, None]
            boundary = ((o <= 0) | (o + h >= self.last)).any(axis=1)
            self._margins = MARGIN + BORDER * boundary
        return self._margins

    def candidate_boxes(self, geometry: ImageGeometry):
        """Per leaf, the output voxels (inclusive int64 boxes) where it may hold pre-images."""
        lo, hi = self.image_boxes(geometry, self.margins(), BORDER)
        return np.floor(lo).astype(np.int64), np.ceil(hi).astype(np.int64)

    def pull_back(self, geometry: ImageGeometry, box, boxes, u, state, fold, quality,
                  near_edge=None, tests=None, device: str = "cpu") -> None:  # fmt: skip
        """Pre-images (input voxel indices) of the voxels of an output box.

        Parameters
        ----------
        geometry : ImageGeometry
            The output grid.
        box : (i0, i1, j0, j1, k0, k1)
            Inclusive output voxel ranges.
        boxes : (lo, hi) int64 arrays
            :meth:`image_boxes` rounded outward to output voxels.
        u : (P, 3) float64
            Pre-images of the box's voxels (i fastest), where ``state > 0``.
        state, fold : (P,) uint8
            See :func:`pull_back_rows` (every voxel's is written).
        quality : (P,) float64
        near_edge : (L,) bool, optional
            Leaves whose pre-images get :data:`~vhm_viz.core.lattice.pullback.NEAR_EDGE`
            in ``state`` (default: every leaf).
        tests : (L, S, 3, 5) float64, optional
            :func:`~vhm_viz.core.lattice.pullback.subcell_tests` on this output grid:
            fewer Newton solves that end outside their leaf (default: the leaves' own;
            the CPU's only).
        device : {"cpu", "cuda"}
            Where the Newton solves run (``"cuda"``:
            :func:`~vhm_viz.core.lattice.cuda_pullback.pull_back_on_gpu`).
        """
        self._need_pre_images("pull_back")
        if near_edge is None:
            near_edge = np.ones(len(self.leaf_size), dtype=np.bool_)
        b = np.asarray(box, dtype=np.int64)
        lo, hi = boxes
        leaves = np.nonzero(
            np.all((lo <= b[1::2]) & (hi >= b[0::2]), axis=1)
        )[0].astype(np.int64)
        n_rows = (b[3] - b[2] + 1) * (b[5] - b[4] + 1)
        start = np.zeros(n_rows + 1, dtype=np.int64)
        empty = np.zeros(0, dtype=np.int64)
        candidate_rows(leaves, lo, hi, b, start, empty, empty, empty)
        start = np.cumsum(start)
        total = int(start[-1])
        row_leaf = np.empty(total, dtype=np.int64)
        row_i0 = np.empty(total, dtype=np.int64)
        row_i1 = np.empty(total, dtype=np.int64)
        if total:
            candidate_rows(leaves, lo, hi, b, start, row_leaf, row_i0, row_i1)
        if device == "cuda":
            from vhm_viz.core.lattice.cuda_pullback import pull_back_on_gpu

            pull_back_on_gpu(self, geometry, b, start, row_leaf, row_i0, row_i1, near_edge,
                             u, state, fold, quality)  # fmt: skip
            return
        if tests is None:
            tests = np.zeros((0, 1, 3, 5))
        pull_back_rows(
            self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, self.leaf_cut, near_edge,
            self.centre_f, self.centre_ginv, self.rho, self.margins(), tests, *self.cut_flags(),
            self.last,
            geometry.origin, geometry.index_to_world, b, start, row_leaf, row_i0, row_i1,
            u, state, fold, quality, worker_count(),
        )  # fmt: skip

    def release_masks(self) -> None:
        """Free the masks, which no part carries: afterwards only :meth:`part` may be used.

        For a window's lattice about to hand out its leaves, so that the masks are not
        held while it packs the other ranks' parts.
        """
        self.mask = self.near = None
        self._cut_flags = None
        release_free_memory()

    def root_keys(self, leaves=None) -> np.ndarray:
        """Root cell of each leaf (or of ``leaves``), as one int64 key (i fastest)."""
        o = self.leaf_origin if leaves is None else self.leaf_origin[leaves]
        return root_keys_of(o, self.root, self.n_root)

    def part(self, leaves, *, release: bool = False, copy: bool = True) -> dict:
        """Some leaves with the data they read, as plain arrays (:data:`PART_FIELDS`).

        For lattices built in windows (MPI ranks) whose leaves are regrouped by
        :func:`join_parts`: each leaf carries its place in the whole lattice's order (its
        root cell, and its rank among that root cell's leaves, which a window's build
        keeps), so that the joined lattice visits them as the whole lattice would.

        ``release``: make the part out of this lattice's own arrays (their rows moved
        in place and the arrays shrunk, :func:`take_in_place`), so that the lattice and the
        part are not held together (the last part taken from a lattice about to be
        dropped); the lattice cannot be used afterwards. Copying would hold each field
        twice.

        ``copy`` False: the fields taken from the lattice's arrays are ``(array, index)``
        pairs (the part's rows are ``array[index]``), for a caller that copies them
        straight into a buffer (:func:`~vhm_viz.filters.mpi.send_parts`), so that
        a copy of the part and its packed buffer are not held together.
        """
        self._need_pre_images("part")
        leaves = np.asarray(leaves, dtype=np.int64).ravel()
        # the data rows the leaves read, renumbered in their order: by marks over the
        # data rows, not np.unique (whose sort of every corner's row would hold five
        # copies of them at once)
        rows = self.leaf_rows[leaves]
        read = np.zeros(len(self.data), dtype=bool)
        read[rows] = True
        used = np.flatnonzero(read)
        del read
        renumber = np.zeros(len(self.data), dtype=np.int64)
        renumber[used] = np.arange(len(used))
        rows = renumber[rows]
        del renumber
        rkey = self.root_keys(leaves)
        out = {"order": np.column_stack([rkey, leaves - self.root_start[rkey]]),
               "rows": rows}  # fmt: skip
        if release:  # what no part needs goes first
            self.leaf_rows = self.root_start = self.root_count = None
            self._margins = self._edge_bins = None
            self.release_masks()
        for name, attr in (("origin", "leaf_origin"), ("size", "leaf_size"),
                           ("cut", "leaf_cut"), ("centre_f", "centre_f"),
                           ("centre_ginv", "centre_ginv"), ("rho", "rho"),
                           ("data", "data")):  # fmt: skip
            index = used if name == "data" else leaves
            if release:
                out[name] = take_in_place(self.__dict__, attr, index)
                release_free_memory()  # (a shrunk heap block's tail)
            elif not copy:
                out[name] = (getattr(self, attr), index)
            else:
                out[name] = getattr(self, attr)[index]
        return out

    def __repr__(self) -> str:
        return (
            f"HermiteLattice(leaves={self.stats['leaves']}, "
            f"evaluations={self.stats.get('evaluations')}, {self.nbytes / 1e6:.1f} MB)"
        )


def root_keys_of(origin, root, n_root) -> np.ndarray:
    """Root cell of leaves at ``origin`` (voxels), as one int64 key (i fastest)."""
    rid = origin // root
    return rid[:, 0] + n_root[0] * (rid[:, 1] + n_root[1] * rid[:, 2])


def root_index(rkey, n_root):
    """``(start, count)`` per root cell of leaves sorted by root key (:func:`locate_leaves`)."""
    count = np.bincount(rkey, minlength=int(np.prod(n_root))).astype(np.int64)
    return np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64), count


def leaf_stats(size, data_rows: int) -> dict:
    """A lattice's leaf counts (``stats``): leaves, leaves per size, data rows."""
    sizes, per_size = np.unique(size, return_counts=True)
    return {
        "leaves": int(len(size)),
        "leaves_per_size": {int(s): int(c) for s, c in zip(sizes, per_size, strict=True)},
        "data_rows": int(data_rows),
    }


@numba.njit(parallel=True, cache=True)
def locate_leaves(origin, size, root_start, root_count, n_root, root, u, out):  # pragma: no cover
    """Leaf owning each point: half-open boxes ``[o, o + h)``, closed at the lattice's end.

    Points beyond the lattice are clamped onto it; points in pruned cells get -1.
    """
    for p in numba.prange(u.shape[0]):
        out[p] = leaf_owning(u[p, 0], u[p, 1], u[p, 2], origin, size, root_start, root_count,
                             n_root, root)  # fmt: skip
