"""Pieces of a volume's work: where the leaves reach, and engines for output pieces.

Each leaf of the lattice maps into a box of the output grid (its Bezier control points
bound its image). From those boxes come the grid that covers the deformed volume
(:func:`output_grid`), the output voxels where a leaf may hold pre-images, the input
voxels that resampling an output piece reads, and the per-plane sums by which MPI ranks
cut the work (:mod:`vhm_viz.core.partition`). :class:`VolumePieces` holds these queries of
:class:`~vhm_viz.core.volume.VolumeDeformation`, with the engines that resample one
piece of the output from the leaves joined from several windows (MPI ranks).
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.lattice import HermiteLattice, join_parts
from vhm_viz.core.partition import pull_back_pairs, pull_back_spans, window_of
from vhm_viz.core.volume_kernels import box_of

__all__ = ["VolumePieces", "output_grid"]

#: Image bounds this close to a voxel (in voxels) are taken to lie on it: the rounding of
#: the control points must not add a plane of voxels.
_ON_VOXEL = 1e-6
#: The most voxels along one axis of an output grid: image extents (VTK's) are 32-bit
#: integers, and a longer axis would overflow the grid's voxel count.
_MAX_AXIS = 2**31 - 1


class VolumePieces:
    """What :class:`~vhm_viz.core.volume.VolumeDeformation` answers about pieces of its work.

    A base class of the engine, which provides ``geometry`` (the input grid),
    ``map``, ``tolerance``, ``outside``, ``root``, ``memory_budget``, ``exchange``,
    ``window``, ``build()``, ``lattice``, ``_lattice``, ``piece``, ``_memo`` (answers
    kept per output grid, dropped with the lattice), ``_any_outside`` and ``_whole(what,
    geometry, box)`` (refuses a query that needs the whole lattice).
    """

    def output_geometry(self, spacing=None) -> ImageGeometry:
        """The grid that covers the whole deformed volume.

        It has the input's direction; its box contains the images of all lattice cells
        with voxels inside the cage (bounded by their Bezier control points, which
        contain them) -- and, with the ``"passthrough"`` policy, the input's own box when
        voxels stay in place. With the input spacing (default) its voxels are aligned with
        the input's, so an identity map reproduces the input grid.

        Parameters
        ----------
        spacing : (3,) array_like, optional
            Output voxel size (world units); default the input spacing.
        """
        key = ("output_geometry", None if spacing is None else
               tuple(np.asarray(spacing, dtype=np.float64).ravel().tolist()))  # fmt: skip
        if key not in self._memo:
            self._memo[key] = self._output_geometry(spacing)
        return self._memo[key]

    def _output_geometry(self, spacing) -> ImageGeometry:
        self._whole("output_geometry")
        lo, hi, outside = self.image_bounds()
        return output_grid(self.geometry, lo, hi, spacing=spacing,
                           keep_input=self.outside == "passthrough" and outside)  # fmt: skip

    @classmethod
    def for_piece(
        cls, harmonic_map, geometry: ImageGeometry, lattice: HermiteLattice,
        output_geometry: ImageGeometry, piece, *, any_outside: bool, tolerance: float,
        outside: str, memory_budget: int | None = None, exchange=None,
    ) -> VolumePieces:  # fmt: skip
        """An engine that resamples one piece of an output grid with a partial lattice.

        ``lattice`` must hold every leaf whose image can reach the ``piece`` (a box of
        ``output_geometry``): :func:`~vhm_viz.core.lattice.join_parts` of the MPI ranks'
        windows. Resampling the piece (or boxes within it) then gives the whole lattice's
        result. ``any_outside``: whether the whole volume has voxels outside the cage
        (the partial lattice's masks cannot tell).
        """
        engine = cls(harmonic_map, geometry, tolerance=tolerance, outside=outside,
                     memory_budget=memory_budget, root=lattice.root, exchange=exchange)  # fmt: skip
        engine._lattice = lattice
        engine.piece = (output_geometry, box_of(output_geometry, piece))
        engine._any_outside = bool(any_outside)
        engine._memo[("output_geometry", None)] = output_geometry
        return engine

    def piece_engine(self, lattice: HermiteLattice, output_geometry: ImageGeometry, piece, *,
                     any_outside: bool) -> VolumePieces:  # fmt: skip
        """:meth:`for_piece` with this engine's map, grid, tolerance and settings.

        For an MPI rank whose window engine this is: its piece's engine then resamples
        with the same tolerance, outside policy, memory budget and exchange.
        """
        return self.for_piece(
            self.map, self.geometry, lattice, output_geometry, piece, any_outside=any_outside,
            tolerance=self.tolerance, outside=self.outside, memory_budget=self.memory_budget,
            exchange=self.exchange,
        )  # fmt: skip

    def join_parts(self, parts, stats=None) -> HermiteLattice:
        """:func:`~vhm_viz.core.lattice.join_parts` of parts of lattices like this one's.

        The parts (:meth:`HermiteLattice.part`) of the MPI ranks' window lattices of this
        map and grid, joined with this engine's tolerance and root cell size.
        """
        return join_parts(parts, self.map, self.geometry, tolerance=self.tolerance,
                          root=self.root, stats=stats)  # fmt: skip

    def grid_over(self, lo, hi, *, spacing=None, keep_input: bool = False) -> ImageGeometry:
        """:func:`output_grid` over image bounds, on this engine's input grid.

        For MPI ranks, whose combined :meth:`image_bounds` (the smallest ``lo``, the
        largest ``hi``) bound the whole volume's image.
        """
        return output_grid(self.geometry, lo, hi, spacing=spacing, keep_input=keep_input)

    def image_bounds(self):
        """Where this engine's leaves map to, and whether its voxels all lie inside the cage.

        For :func:`output_grid`; MPI ranks combine their windows' bounds (the smallest
        ``lo``, the largest ``hi``, any outside) into the whole volume's.

        Returns
        -------
        lo, hi : (3,) float64
            Bounds of the leaves' images (Bezier control point boxes) in continuous input
            indices; ``+inf`` and ``-inf`` without leaves.
        outside : bool
            A voxel (of the window) is outside the cage.
        """
        lat = self.build()
        geo = self.geometry
        lo, hi = lat.image_boxes(geo)  # (refuses a lattice for the voxels only)
        box = box_of(geo, None) if self.window is None else self.window
        outside = bool((box[1::2] >= box[0::2]).all() and not lat.inside(box).all())
        return lo.min(axis=0, initial=np.inf), hi.max(axis=0, initial=-np.inf), outside

    def candidate_boxes(self, geometry: ImageGeometry):
        """Per leaf, the output voxels where it may hold pre-images (kept per output grid).

        :meth:`HermiteLattice.candidate_boxes`, a pass over every leaf's Bezier control
        points, which resampling, its input window and the MPI ranks' tables all ask for.
        Dropped with the lattice.

        Returns
        -------
        lo, hi : (L, 3) int64
            Inclusive voxel boxes (read-only).
        """
        key = ("candidate_boxes", geometry.key())
        if key not in self._memo:
            lo, hi = self.lattice.candidate_boxes(geometry)
            lo.flags.writeable = hi.flags.writeable = False
            self._memo[key] = (lo, hi)
        return self._memo[key]

    def reach_table(self, geometry: ImageGeometry, leaves=None) -> np.ndarray:
        """Per root cell with leaves: where its leaves' pre-images may be, and their voxels.

        Rows ``(out_lo, out_hi, in_lo, in_hi)`` (each 3 int64, inclusive): the output voxels
        of ``geometry`` its leaves' images can reach (:meth:`HermiteLattice.candidate_boxes`)
        and the input voxels its leaves span. MPI ranks share their windows' tables to find
        each output piece's input window without the whole lattice (:func:`window_of`).
        ``leaves``: only these (sorted) leaves' root cells (default all).
        """
        lat = self.build()
        leaves = np.arange(len(lat.leaf_size)) if leaves is None else np.asarray(leaves)
        if not len(leaves):
            return np.zeros((0, 12), dtype=np.int64)
        lo, hi = self._boxes_of(geometry, leaves)
        # the leaves come grouped by root cell (in their order); reduced column group by
        # column group, without a table of every leaf's (L, 12)
        rkey = lat.root_keys(leaves)
        starts = np.concatenate([[0], np.nonzero(np.diff(rkey))[0] + 1])
        o = lat.leaf_origin[leaves]
        return np.column_stack([
            np.minimum.reduceat(lo, starts), np.maximum.reduceat(hi, starts),
            np.minimum.reduceat(o, starts),
            np.maximum.reduceat(o + lat.leaf_size[leaves, None], starts),
        ])  # fmt: skip

    def _boxes_of(self, geometry: ImageGeometry, leaves=None):
        """:meth:`candidate_boxes` of ``leaves`` only (default all)."""
        lo, hi = self.candidate_boxes(geometry)
        if leaves is None:
            return lo, hi
        leaves = np.asarray(leaves)
        return lo[leaves], hi[leaves]

    def pull_back_pairs(self, geometry: ImageGeometry, leaves=None) -> np.ndarray:
        """Per k-plane of an output grid: its (voxel, candidate leaf) pairs.

        Pulling a voxel back tries every leaf whose candidate box holds it (Newton's
        method on the leaf's polynomial, :meth:`HermiteLattice.pull_back`): most of the
        work of resampling a plane. MPI ranks add up the pairs of their own leaves (each
        leaf counted once) to cut the output into shares of work
        (:func:`pull_back_shares`).

        Parameters
        ----------
        geometry : ImageGeometry
            The output grid.
        leaves : (L,) int array_like, optional
            Only these leaves (default all).

        Returns
        -------
        (nz,) float64
        """
        return pull_back_pairs(*self._boxes_of(geometry, leaves), geometry)

    def pull_back_spans(self, geometry: ImageGeometry, leaves=None):
        """Per k-plane of an output grid: the leaves whose candidate boxes start and end there.

        The leaves that resampling a run of planes ``a..b`` needs (whose candidate boxes
        reach it) are those started by plane ``b`` less those ended before ``a``: how
        :func:`pull_back_shares` weighs the MPI ranks' memory. Leaves whose boxes miss the
        grid are not counted; boxes are clipped to it. Like :meth:`pull_back_pairs` (and
        with its parameters), ranks add up the counts of their own leaves.

        Returns
        -------
        starts, ends : (nz,) float64
        """
        return pull_back_spans(*self._boxes_of(geometry, leaves), geometry)

    def input_window(self, geometry: ImageGeometry, box=None, interpolation: str = "linear"):
        """The input voxels that resampling the output ``box`` of ``geometry`` reads.

        The leaves whose images can reach the box (their Bezier control points' boxes, as
        :meth:`resample` scatters them), each widened by how far outside it a pre-image
        may lie and by the interpolation stencil; with the ``"passthrough"`` policy also
        the box's own position in the input grid (voxels outside the cage stay in place).
        A piece of the output thus needs only its window of the input (an UPDATE_EXTENT).

        Returns
        -------
        (6,) int64 or None
            ``(i0, i1, j0, j1, k0, k1)`` inclusive, or None when nothing is read.
        """
        b = box_of(geometry, box)
        key = ("input_window", geometry.key(), tuple(b.tolist()), interpolation)
        if key not in self._memo:
            self._memo[key] = self._input_window(geometry, b, interpolation)
        window = self._memo[key]
        return None if window is None else window.copy()

    def _input_window(self, geometry: ImageGeometry, b, interpolation: str):
        self._whole("input_window", geometry, b)
        lat = self.lattice
        lo, hi = self.candidate_boxes(geometry)
        # the table rows of the leaves that reach the box only (window_of reads no other):
        # every leaf's, (L, 12) int64, would be held at the start of each piece an MPI
        # rank resamples, the last one while its output piece is full
        hit = np.flatnonzero(np.all((lo <= b[1::2]) & (hi >= b[0::2]), axis=1))
        o = lat.leaf_origin[hit]
        table = np.column_stack([lo[hit], hi[hit], o, o + lat.leaf_size[hit, None]])
        return window_of(
            table, b, self.geometry, geometry, interpolation=interpolation,
            margin=lat.margins().max(initial=0.0),
            in_place=self.outside == "passthrough" and self._has_outside(),
        )  # fmt: skip

    def _has_outside(self) -> bool:
        """Whether the volume has voxels outside the cage."""
        if self._any_outside is not None:
            return self._any_outside
        return not self.lattice.inside(box_of(self.geometry, None)).all()


def output_grid(geometry: ImageGeometry, lo, hi, *, spacing=None,
                keep_input: bool = False) -> ImageGeometry:  # fmt: skip
    """The output grid over deformed voxels whose images lie within ``lo..hi``.

    Its extent is the bounds', rounded out to whole voxels. The tolerance does not widen
    it: pre-images are found on the lattice's polynomials, whose images the bounds
    contain, so voxels beyond them would hold the fill value (or, within half a voxel,
    the input's border).

    Parameters
    ----------
    geometry : ImageGeometry
        The input grid.
    lo, hi : (3,) array_like
        Bounds of the images in continuous input indices (:meth:`VolumeDeformation.image_bounds`).
    spacing : (3,) array_like, optional
        Output voxel size; default the input spacing (voxels aligned with the input's).
    keep_input : bool
        Also cover the input's own box (voxels left in place).
    """
    geo = geometry
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError("no voxel of the volume is inside the cage")
    if keep_input:
        lo = np.minimum(lo, 0.0)
        hi = np.maximum(hi, np.asarray(geo.dimensions) - 1.0)
    if spacing is None:
        # bounds within rounding of a voxel are on it: the identity's grid is the input's
        lo, hi = np.floor(lo + _ON_VOXEL), np.ceil(hi - _ON_VOXEL)
        dims = _axis_voxels(hi - lo + 1)
        return ImageGeometry(geo.points(lo[None])[0], geo.spacing, dims, geo.direction)
    sp = np.asarray(spacing, dtype=np.float64).reshape(3)
    if not (np.isfinite(sp).all() and (sp > 0).all()):
        raise ValueError(f"spacing must be three positive numbers; got {spacing}")
    extent = (hi - lo) * geo.spacing
    dims = _axis_voxels(np.floor(extent / sp + 1e-9) + 1)
    # centre the output voxels on the deformed volume's box
    start = lo * geo.spacing + 0.5 * (extent - (dims - 1) * sp)
    return ImageGeometry(geo.origin + geo.direction @ start, sp, dims, geo.direction)


def _axis_voxels(counts) -> np.ndarray:
    """Voxels along each axis of an output grid (int64), refused past :data:`_MAX_AXIS`."""
    if (counts > _MAX_AXIS).any():
        shown = "x".join(f"{c:.3g}" for c in counts)
        raise ValueError(
            f"an output grid of {shown} voxels is longer than {_MAX_AXIS} voxels along an "
            "axis; give a coarser spacing"
        )
    return counts.astype(np.int64)
