"""Volumes under a harmonic map: forward warp, pull-back resampling, Jacobian analysis.

The one volume engine of vhm_viz; the command line, the PyVista accessor, the VTK and
ParaView filters and the explorer all call :class:`VolumeDeformation`. It maps a volume
through the adaptive Hermite lattice of :mod:`vhm_viz.core.lattice` (exact values and
Jacobians at its nodes, tricubic Hermite in between, refined until test points agree with
the exact map to a fraction of the tolerance), so a 256^3 scan needs a few hundred
thousand exact evaluations instead of 16.8 million. Work goes slab by slab (sized by a
memory budget, with progress and abort between slabs): the peak memory is the input and
output arrays plus the lattice and one slab's working arrays.

* **Forward warp** (:meth:`VolumeDeformation.warp`): every voxel's deformed position.
* **Resample** (:meth:`VolumeDeformation.resample`): the deformed volume on a regular
  grid. Each output voxel ``y`` is pulled back to ``x`` with ``f(x) = y``: the lattice's
  leaves are scattered into the output grid by the boxes of their images, and Newton's
  method runs on each candidate leaf's polynomial; pre-images within 1.5 voxels of a cage
  edge, where the map has a logarithmic singularity, are then polished by Newton's method
  on the exact map. Where several pre-images exist (a fold) the voxel is flagged. The
  input is then sampled at ``x`` (nearest, trilinear or cubic). As with
  ``vtkImageReslice``'s default border the input extends half a voxel beyond its outer
  grid points (with the boundary values): each voxel stands for a full cube.
* **Analysis** (:meth:`VolumeDeformation.jacobians`): ``df/dx`` of every voxel from the
  lattice's polynomials.

Voxels outside the cage follow the outside policy (:data:`~vhm_viz.core.binding.OUTSIDE_POLICIES`):
``"error"`` refuses the volume (naming them), ``"passthrough"`` leaves them where they are
(identity), ``"nan"`` gives them no image (NaN positions; no data in a resampled volume).
Output voxels without a pre-image get the fill value and 0 in ``vtkValidPointMask``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from vhm_viz.core.basis import DEFAULT_MEMORY_BUDGET, evaluate_map, inside_cage, winding_number
from vhm_viz.core.binding import check_outside_policy
from vhm_viz.core.errors import AbortedError, OutsideCageError, describe_indices
from vhm_viz.core.image import BORDER, INTERPOLATIONS, ImageGeometry, inside_mask, sample
from vhm_viz.core.lattice import DEFAULT_ROOT, HermiteLattice, build_lattice
from vhm_viz.core.memory import release_free_memory

__all__ = [
    "VolumeDeformation",
    "Resampled",
    "output_grid",
    "layer_shares",
    "equal_cuts",
    "pull_back_shares",
    "lattice_build_work",
    "window_of",
    "exact_preimages",
    "DEFAULT_TOLERANCE",
    "EXACT_VOXELS",
    "INTERPOLATIONS",
]

#: Default largest position error, in voxels of the input spacing.
DEFAULT_TOLERANCE = 0.05
#: Volumes of at most this many voxels are evaluated exactly at every voxel (a lattice of
#: single-voxel cells): a lattice would not save evaluations there.
EXACT_VOXELS = 32768
# Working bytes per output voxel of a resampling slab (pre-image, state, fold, quality,
# outside flag, one sampled float64 component), and per voxel of a warp slab.
_RESAMPLE_BYTES = 56
# A pull-back slab's working arrays stay within this whatever the memory budget: on the
# embryo (20 million output voxels, one thread) 16 MB slabs resampled in 7.3 s, 64 MB
# ones in 7.6 s and 8 MB ones in 7.8 s; each process (each MPI rank) holds 48 MB less.
_PULL_BACK_SLAB_BYTES = 16 * 2**20
_WARP_BYTES = 16
# The work of resampling a voxel beyond its leaf tests (its arrays, sampling,
# pass-through), in leaf tests: 23 ns per voxel of an output slab that no leaf reaches
# against 0.13 us per (voxel, candidate leaf) pair (the embryo's output, one thread).
_PULL_BACK_VOXEL_WORK = 0.2
# The work of a lattice build per exact evaluation and basis function of the map (cage
# vertex or face), the build's bookkeeping included, in leaf tests: the embryo's build
# took 8.1 s per MPI rank of 2 for 790,199 evaluations of 754 functions (20 us each,
# one thread) against 0.13 us per (voxel, candidate leaf) pair.
_EVALUATION_WORK_PER_BASIS = 0.2
# Pre-images closer than this (voxels) to a cage edge are polished by Newton's method on
# the exact map: there the map has a logarithmic singularity that no cubic between voxels
# follows, and a position error e moves a pre-image by e / s_min (s_min: the Jacobian's
# smallest singular value in voxels). CT head, 500-face automatic cage, 208,841 random
# output voxels: without polishing 5 pre-images were off by 0.05-0.067 voxel, all within
# 1.5 voxels of an edge (one at s_min = 0.17, the others within 0.75 voxel); with 1.5 the
# largest error is 0.033 (at s_min = 0.12, 4.7 voxels from the cage). On the 256^3 embryo
# this polishes 63,433 pre-images in about 2 s.
_EXACT_NEAR_EDGE = 1.5
# Newton on the exact map starts from the lattice's pre-image, a few hundredths of a voxel
# off: two or three steps converge; more means it left for another branch.
_EXACT_ITERATIONS = 6


@dataclass
class Resampled:
    """A resampled volume: the arrays on the output grid and what happened to its voxels.

    Attributes
    ----------
    geometry : ImageGeometry
        The output grid (or the requested box of it).
    arrays : dict of str -> ndarray
        Each input array on the output voxels (VTK order), same dtype as the input.
    valid : (P,) uint8
        1 where the voxel has a pre-image (``vtkValidPointMask``).
    foldover : (P,) uint8
        1 where it has several pre-images more than a voxel apart (``vhm_foldover``).
    counts : dict
        ``voxels``, ``valid``, ``identity`` (outside voxels left in place),
        ``foldover``.
    """

    geometry: ImageGeometry
    arrays: dict
    valid: np.ndarray
    foldover: np.ndarray
    counts: dict = field(default_factory=dict)


def _check_abort(abort) -> None:
    if abort is not None and abort():
        raise AbortedError("aborted")


def _box_of(geometry: ImageGeometry, box) -> np.ndarray:
    """A voxel box ``(i0, i1, j0, j1, k0, k1)`` (default: the whole grid), validated."""
    dims = geometry.dimensions
    if box is None:
        return np.array([0, dims[0] - 1, 0, dims[1] - 1, 0, dims[2] - 1], dtype=np.int64)
    b = np.asarray(box, dtype=np.int64).reshape(6)
    if (b[0::2] < 0).any() or (b[1::2] >= np.asarray(dims)).any() or (b[1::2] < b[0::2]).any():
        raise ValueError(f"box {b.tolist()} is not inside the grid of dimensions {dims}")
    return b


def _check_out(arrays: dict, valid, foldover, shapes: dict, n: int) -> None:
    """Refuse ``out`` arrays of :meth:`VolumeDeformation.resample` that do not fit."""
    want = dict(shapes)
    want["valid"] = ((n,), np.dtype(np.uint8))
    want["foldover"] = ((n,), np.dtype(np.uint8))
    got = dict(arrays)
    got["valid"], got["foldover"] = valid, foldover
    if set(got) != set(want):
        raise ValueError(f"out holds the arrays {sorted(got)}, not {sorted(want)}")
    for name, (shape, dtype) in want.items():
        a = got[name]
        if a.shape != shape or a.dtype != dtype or not a.flags.c_contiguous:
            raise ValueError(
                f"out array {name!r} is {a.dtype}{list(a.shape)}; the box needs a "
                f"contiguous {np.dtype(dtype)}{list(shape)}"
            )


def _slabs(box: np.ndarray, bytes_per_voxel: int, memory_budget: int | None):
    """Split a box into slabs of whole k-planes whose working arrays fit the budget."""
    budget = DEFAULT_MEMORY_BUDGET if memory_budget is None else int(memory_budget)
    plane = int((box[1] - box[0] + 1) * (box[3] - box[2] + 1))
    planes = max(1, budget // max(plane * bytes_per_voxel, 1))
    for k0 in range(int(box[4]), int(box[5]) + 1, planes):
        slab = box.copy()
        slab[4], slab[5] = k0, min(int(box[5]), k0 + planes - 1)
        yield slab


def _box_ijk(box) -> np.ndarray:
    """(P, 3) voxel indices of a box, i fastest."""
    k, j, i = np.meshgrid(
        np.arange(box[4], box[5] + 1),
        np.arange(box[2], box[3] + 1),
        np.arange(box[0], box[1] + 1),
        indexing="ij",
    )
    return np.column_stack([i.ravel(), j.ravel(), k.ravel()])


class VolumeDeformation:
    """A harmonic map applied to the voxels of an image grid.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    geometry : ImageGeometry
        The input volume's grid.
    tolerance : float
        Largest position error of a mapped voxel, in voxels of the input spacing
        (default 0.05); also bounds the pre-image error of a resampled voxel where the
        map is not strongly compressive.
    outside : {"error", "passthrough", "nan"}
        Voxels outside the cage (see the module documentation).
    memory_budget : int, optional
        Bytes of working memory per slab and per evaluation chunk (default
        :data:`~vhm_viz.core.basis.DEFAULT_MEMORY_BUDGET`).
    root : int, optional
        Root cell size of the lattice (voxels, a power of two; default
        :data:`~vhm_viz.core.lattice.DEFAULT_ROOT`, or 1 -- every voxel exact -- for
        volumes of at most :data:`EXACT_VOXELS` voxels).
    window : (i0, i1, j0, j1, k0, k1), optional
        Only this box of voxels will be warped or analysed (a piece of the volume: an MPI
        rank's, a streamed piece): the lattice is built over the root cells that own its
        voxels only, aligned with the whole grid, so those voxels get the same values as
        with the whole lattice (to rounding). Resampling and :meth:`output_geometry` need
        the whole lattice (pre-images may lie anywhere): they refuse a window; MPI ranks
        resample pieces with lattices joined from the windows' leaves
        (:meth:`for_piece`). With an ``exchange`` the window may be empty (an MPI rank's
        empty piece): :meth:`build` then only takes its share of the other builders'
        evaluations.
    exchange : callable, optional
        How the lattice's exact evaluations are shared with other builders (MPI ranks
        that build their windows, or the whole lattice, together): see
        :func:`~vhm_viz.core.lattice.build_lattice`. The values do not depend on it.
    pre_images : bool
        False: this engine only warps and analyses voxels, so its lattice skips what only
        pre-images need (faster and smaller: see
        :func:`~vhm_viz.core.lattice.build_lattice`); the voxels' values are the same.
        Resampling and :meth:`output_geometry` refuse it. Default: True without a
        window, False with one (a window's engine only warps and analyses, unless its
        leaves are to be joined for resampling: :meth:`for_piece`).

    Notes
    -----
    The lattice is built on first use (:attr:`lattice`) and kept: warping, resampling
    onto several grids and analysing the same volume build it once.
    """

    def __init__(
        self,
        harmonic_map,
        geometry: ImageGeometry,
        *,
        tolerance: float = DEFAULT_TOLERANCE,
        outside: str = "error",
        memory_budget: int | None = None,
        root: int | None = None,
        window=None,
        exchange=None,
        pre_images: bool | None = None,
    ):
        self.map = harmonic_map
        self.exchange = exchange
        self.geometry = geometry
        self.tolerance = float(tolerance)
        if not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"tolerance must be a positive number of voxels; got {tolerance}")
        self.outside = check_outside_policy(outside)
        if memory_budget is not None and not int(memory_budget) > 0:
            raise ValueError(f"memory_budget must be a positive byte count; got {memory_budget}")
        self.memory_budget = None if memory_budget is None else int(memory_budget)
        if root is None:
            root = 1 if geometry.n_points <= EXACT_VOXELS else DEFAULT_ROOT
        self.root = int(root)
        w = None if window is None else np.asarray(window, dtype=np.int64).reshape(6)
        if w is not None and exchange is not None and (w[1::2] < w[0::2]).any():
            # an MPI rank's empty piece: its build makes no cell but shares the others'
            # evaluations (see build_lattice)
            self.window = w
        else:
            self.window = None if window is None else _box_of(geometry, window)
        if self.window is not None and self.window.tolist() == _box_of(geometry, None).tolist():
            self.window = None
        # a window's engine refuses resampling: by default it skips what only that needs
        self.pre_images = self.window is None if pre_images is None else bool(pre_images)
        #: ``(output geometry, box)`` of a piece engine (:meth:`for_piece`), else None.
        self.piece = None
        # whether the whole volume has voxels outside the cage, where the lattice cannot
        # tell (a piece engine's lattice holds the masks of its own rows only)
        self._any_outside: bool | None = None
        self._lattice: HermiteLattice | None = None
        # output grids and input windows, each a pass over every leaf: a pipeline asks
        # for them again in each information and update-extent pass
        self._memo: dict = {}
        #: Slabs processed by the last warp/resample/jacobians call (for tests of the
        #: memory bound) and the largest slab's voxel count.
        self.slab_count = 0
        self.largest_slab = 0

    # ------------------------------------------------------------------ the lattice
    @property
    def lattice(self) -> HermiteLattice:
        """The lattice (built on first access, without progress reports)."""
        return self.build()

    def build(self, progress=None, abort=None) -> HermiteLattice:
        """Build the lattice now (once), reporting ``progress(fraction, "lattice")``."""
        if self._lattice is None:
            self._lattice = build_lattice(
                self.map,
                self.geometry,
                tolerance=self.tolerance,
                root=self.root,
                memory_budget=self.memory_budget,
                progress=progress,
                abort=abort,
                window=None if self.window is None else self.window.tolist(),
                exchange=self.exchange,
                pre_images=self.pre_images,
            )
        return self._lattice

    def drop_lattice(self) -> None:
        """Free the lattice (it is built again when next needed)."""
        self._lattice = None
        self._memo.clear()

    def with_outside(self, outside: str) -> VolumeDeformation:
        """The same engine with another outside policy, sharing the lattice once built.

        The lattice covers the voxels inside the cage whatever the policy; only what
        happens to the others changes.
        """
        other = VolumeDeformation(
            self.map, self.geometry, tolerance=self.tolerance, outside=outside,
            memory_budget=self.memory_budget, root=self.root,
            window=None if self.window is None else self.window.tolist(),
            exchange=self.exchange, pre_images=self.pre_images,
        )  # fmt: skip
        other._lattice = self._lattice
        return other

    def _in_window(self, box) -> np.ndarray:
        """``box`` validated, and inside the window this engine was built for."""
        if self.piece is not None:
            raise ValueError(
                "this volume engine holds the leaves that reach one output piece only "
                f"({self.piece[1].tolist()}): it resamples that piece, nothing else"
            )
        b = _box_of(self.geometry, box)
        w = self.window
        if w is not None and ((b[0::2] < w[0::2]).any() or (b[1::2] > w[1::2]).any()):
            raise ValueError(
                f"box {b.tolist()} is not inside the window {w.tolist()} this volume engine "
                "was built for"
            )
        return b

    def _whole(self, what: str, geometry: ImageGeometry | None = None, box=None) -> None:
        if self.piece is not None:
            geo, piece = self.piece
            inside = (
                geometry is not None
                and box is not None
                and geometry.key() == geo.key()
                and (np.asarray(box)[0::2] >= piece[0::2]).all()
                and (np.asarray(box)[1::2] <= piece[1::2]).all()
            )
            if not inside:
                raise ValueError(
                    f"{what} needs the whole lattice: this volume engine holds the leaves "
                    f"that reach the output piece {piece.tolist()} only"
                )
            return
        if self.window is not None:
            raise ValueError(
                f"{what} needs the whole lattice: this volume engine was built for the window "
                f"{self.window.tolist()} only"
            )
        if not self.pre_images:
            raise ValueError(
                f"{what} needs pre-images: this volume engine was built for warping and "
                "analysing voxels only (pre_images=False)"
            )

    def outside_voxels(self, box=None) -> np.ndarray:
        """Indices (VTK order, of the whole grid) of the voxels outside the cage."""
        b = self._in_window(self.window if box is None else box)
        inside = self.lattice.inside(b)
        if b.tolist() == _box_of(self.geometry, None).tolist():
            return np.nonzero(~inside.ravel())[0]
        nx, ny, _ = self.geometry.dimensions
        ijk = _box_ijk(b)[~inside.ravel()]
        return ijk[:, 0] + nx * (ijk[:, 1] + ny * ijk[:, 2])

    def _refuse_outside(self, box=None) -> None:
        if self.outside != "error":
            return
        if self._any_outside is not None:  # a piece engine: agreed for the whole volume
            if self._any_outside:
                raise OutsideCageError(
                    "voxels of the volume are outside the cage; use the 'passthrough' "
                    "outside policy to leave them in place or 'nan' to drop them",
                    np.zeros(0, dtype=np.int64),
                )
            return
        bad = self.outside_voxels(box)
        if bad.size:
            raise OutsideCageError(
                f"{bad.size} of {self.geometry.n_points} voxels are outside the cage (indices "
                f"{describe_indices(bad)}); use the 'passthrough' outside policy to leave them "
                "in place or 'nan' to drop them",
                bad,
            )

    # ------------------------------------------------------------------ forward warp
    def warp(self, box=None, out=None, progress=None, abort=None) -> np.ndarray:
        """Deformed world positions of the voxels of a box.

        Parameters
        ----------
        box : (i0, i1, j0, j1, k0, k1), optional
            Inclusive voxel ranges (default: the whole grid).
        out : (P, 3) float64 ndarray, optional
            Written in place (VTK order within the box) and returned.
        progress : callable(fraction, message), optional
        abort : callable() -> bool, optional

        Returns
        -------
        (P, 3) float64
            Inside voxels: the map (within the tolerance); outside voxels: their own
            position (``"passthrough"``) or NaN (``"nan"``).

        Raises
        ------
        OutsideCageError
            With the ``"error"`` policy when a voxel of the box is outside the cage.
        """
        b = self._in_window(self.window if box is None else box)
        lat = self.build(progress=_scaled(progress, 0.0, 0.6), abort=abort)
        self._refuse_outside(b)
        n = int(np.prod(b[1::2] - b[0::2] + 1))
        if out is None:
            out = np.empty((n, 3))
        elif out.shape != (n, 3) or out.dtype != np.float64:
            raise ValueError(f"out must be a float64 array of shape ({n}, 3)")
        self._start_slabs()
        slabs = list(_slabs(b, _WARP_BYTES, self.memory_budget))
        plane = int((b[1] - b[0] + 1) * (b[3] - b[2] + 1))
        for s, slab in enumerate(slabs):
            _check_abort(abort)
            lo = (slab[4] - b[4]) * plane
            view = out[lo : lo + (slab[5] - slab[4] + 1) * plane]
            self._count_slab(len(view))
            _fill_outside(
                self.geometry.origin, self.geometry.index_to_world, slab, lat.inside(slab),
                self.outside == "nan", view,
            )  # fmt: skip
            lat.warp(slab, view)
            if progress is not None:
                progress(0.6 + 0.4 * (s + 1) / len(slabs), "warp")
        return out

    def jacobian_slabs(self, box=None, progress=None, abort=None):
        """World Jacobians of the voxels of a box, slab by slab (bounded memory).

        From the derivatives of the lattice's polynomials; outside voxels get ``I``
        (``"passthrough"``) or NaN (``"nan"``).

        Yields
        ------
        rows : slice
            The slab's voxels among the box's (VTK order).
        J : (P, 3, 3) float64
            ``J[p, i, j] = d f_i / d x_j``.
        """
        b = self._in_window(self.window if box is None else box)
        lat = self.build(progress=_scaled(progress, 0.0, 0.6), abort=abort)
        self._refuse_outside(b)
        self._start_slabs()
        slabs = list(_slabs(b, 72, self.memory_budget))
        plane = int((b[1] - b[0] + 1) * (b[3] - b[2] + 1))
        for s, slab in enumerate(slabs):
            _check_abort(abort)
            lo = int((slab[4] - b[4]) * plane)
            m = int((slab[5] - slab[4] + 1) * plane)
            self._count_slab(m)
            jac = np.empty((m, 3, 3))
            jac[~lat.inside(slab).ravel()] = np.eye(3) if self.outside != "nan" else np.nan
            lat.jacobians(slab, jac)
            yield slice(lo, lo + m), jac
            if progress is not None:
                progress(0.6 + 0.4 * (s + 1) / len(slabs), "jacobians")

    def jacobians(self, box=None, progress=None, abort=None) -> np.ndarray:
        """World Jacobians ``J[p, i, j] = d f_i / d x_j`` of the voxels of a box, (P, 3, 3).

        See :meth:`jacobian_slabs` (which keeps only one slab's Jacobians in memory).
        """
        b = self._in_window(self.window if box is None else box)
        out = np.empty((int(np.prod(b[1::2] - b[0::2] + 1)), 3, 3))
        for rows, jac in self.jacobian_slabs(b, progress, abort):
            out[rows] = jac
        return out

    def jacobian_measures(self, box=None, progress=None, abort=None) -> dict:
        """:func:`~vhm_viz.core.metrics.jacobian_measures` of every voxel of a box.

        Returns
        -------
        dict
            ``determinant``, ``condition_number``, ``rotation_angle`` (radians) as (P,)
            float64 and ``foldover`` (P,) bool (``det J <= 0``).
        """
        from vhm_viz.core.metrics import jacobian_measures

        b = self._in_window(self.window if box is None else box)
        n = int(np.prod(b[1::2] - b[0::2] + 1))
        det, cond, angle = np.empty(n), np.empty(n), np.empty(n)
        for rows, jac in self.jacobian_slabs(b, progress, abort):
            hard = np.zeros(len(jac), dtype=np.bool_)
            _measures(jac, det[rows], cond[rows], angle[rows], hard)
            if hard.any():  # folded or degenerate: the SVD's definitions
                m = jacobian_measures(jac[hard])
                for name, dst in (("determinant", det), ("condition_number", cond),
                                  ("rotation_angle", angle)):  # fmt: skip
                    dst[rows][hard] = m[name]
        return {
            "determinant": det,
            "condition_number": cond,
            "rotation_angle": angle,
            "foldover": det <= 0,
        }

    # ------------------------------------------------------------------ output grid
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
        return output_grid(self.geometry, lo, hi, tolerance=self.tolerance, spacing=spacing,
                           keep_input=self.outside == "passthrough" and outside)  # fmt: skip

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
        box = _box_of(geo, None) if self.window is None else self.window
        outside = bool((box[1::2] >= box[0::2]).all() and not lat.inside(box).all())
        return lo.min(axis=0, initial=np.inf), hi.max(axis=0, initial=-np.inf), outside

    def candidate_boxes(self, geometry: ImageGeometry):
        """Per leaf, the output voxels where it may hold pre-images (kept per output grid).

        :meth:`HermiteLattice.candidate_boxes`, a pass over every leaf's Bezier control
        points (0.2 s on the embryo's 249k leaves): resampling, its input window and the
        MPI ranks' tables all ask for it. Dropped with the lattice.

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
        lo, hi = self._boxes_of(geometry, leaves)
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

    def pull_back_spans(self, geometry: ImageGeometry, leaves=None):
        """Per k-plane of an output grid: the leaves whose candidate boxes start and end there.

        The leaves that resampling a run of planes ``a..b`` needs (whose candidate boxes
        reach it) are those started by plane ``b`` less those ended before ``a``: how
        :func:`pull_back_shares` weighs the MPI ranks' memory. Leaves whose boxes miss the
        grid are not counted; boxes are clipped to it. Like :meth:`pull_back_pairs`, ranks
        add up the counts of their own leaves.

        Parameters
        ----------
        geometry : ImageGeometry
            The output grid.
        leaves : (L,) int array_like, optional
            Only these leaves (default all).

        Returns
        -------
        starts, ends : (nz,) float64
        """
        lo, hi = self._boxes_of(geometry, leaves)
        dims = np.asarray(geometry.dimensions, dtype=np.int64)
        reach = np.all((lo <= dims - 1) & (hi >= 0) & (lo <= hi), axis=1)
        nz = int(dims[2])
        k_lo = np.clip(lo[reach, 2], 0, nz - 1)
        k_hi = np.clip(hi[reach, 2], 0, nz - 1)
        return (np.bincount(k_lo, minlength=nz).astype(np.float64),
                np.bincount(k_hi, minlength=nz).astype(np.float64))  # fmt: skip

    @classmethod
    def for_piece(
        cls, harmonic_map, geometry: ImageGeometry, lattice: HermiteLattice,
        output_geometry: ImageGeometry, piece, *, any_outside: bool, tolerance: float,
        outside: str, memory_budget: int | None = None, exchange=None,
    ) -> VolumeDeformation:  # fmt: skip
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
        engine.piece = (output_geometry, _box_of(output_geometry, piece))
        engine._any_outside = bool(any_outside)
        engine._memo[("output_geometry", None)] = output_geometry
        return engine

    # ------------------------------------------------------------------ resampling
    def resample(
        self,
        arrays: dict,
        geometry: ImageGeometry | None = None,
        *,
        box=None,
        interpolation: str = "linear",
        fill_value: float = 0.0,
        input_box=None,
        out: Resampled | None = None,
        progress=None,
        abort=None,
    ) -> Resampled:
        """The deformed volume on a regular grid (pull-back; see the module documentation).

        Parameters
        ----------
        arrays : dict of str -> ndarray
            Input point arrays, (N,) or (N, c), VTK order, any numeric dtype.
        geometry : ImageGeometry, optional
            Output grid (default :meth:`output_geometry`).
        box : (i0, i1, j0, j1, k0, k1), optional
            Only these output voxels (a piece); default all.
        interpolation : {"linear", "nearest", "cubic"}
            Sampling of the input at the pre-images: trilinear; nearest voxel (values
            copied exactly, for label maps); Catmull-Rom cubic convolution.
        fill_value : float
            Value of voxels without a pre-image (cast to each array's dtype).
        input_box : (i0, i1, j0, j1, k0, k1), optional
            ``arrays`` hold only this box of the input grid (default: all of it); it must
            contain :meth:`input_window` of the output box, the voxels the pre-images
            reach. The result is the same as with the whole input.
        out : Resampled, optional
            Write into these arrays instead of new ones: an array of each name with the
            input's dtype and components, ``valid`` and ``foldover``, each a (C-contiguous)
            row per voxel of the box -- say, views of the rows of a larger box that this
            box's voxels occupy (an MPI rank's output piece, resampled in parts).
        progress, abort : callables, optional

        Returns
        -------
        Resampled
            Arrays keep their dtype: integer arrays interpolated linearly or cubically are
            rounded and clipped to their type's range. With ``out``: ``out``, its arrays
            filled and its counts set.
        """
        if interpolation not in INTERPOLATIONS:
            raise ValueError(
                f"interpolation must be one of {INTERPOLATIONS}; got {interpolation!r}"
            )
        src = self.geometry
        ib = _box_of(src, input_box)
        nx, ny, nz = (int(n) for n in ib[1::2] - ib[0::2] + 1)
        volumes = {}
        for name, values in arrays.items():
            v = np.asarray(values)
            if v.shape[0] != nx * ny * nz:
                raise ValueError(
                    f"array {name!r} has {v.shape[0]} values for {nx * ny * nz} voxels"
                )
            volumes[name] = v.reshape(nz, ny, nx, -1)
        self.build(progress=_scaled(progress, 0.0, 0.5), abort=abort)
        out_geo = self.output_geometry() if geometry is None else geometry
        b = _box_of(out_geo, box)
        if input_box is not None:
            need = self.input_window(out_geo, b, interpolation)
            short = need is not None and (
                (need[0::2] < ib[0::2]).any() or (need[1::2] > ib[1::2]).any()
            )
            if short:
                raise ValueError(
                    f"input_box {ib.tolist()} does not hold the input voxels {need.tolist()} "
                    "that the pre-images of this output box reach"
                )
        n = int(np.prod(b[1::2] - b[0::2] + 1))
        shapes = {name: ((n,) + v.shape[3:] if v.shape[3] > 1 else (n,), v.dtype)
                  for name, v in volumes.items()}  # fmt: skip
        if out is None:
            result = {name: np.empty(shape, dtype=dt) for name, (shape, dt) in shapes.items()}
            valid = np.zeros(n, dtype=np.uint8)
            foldover = np.zeros(n, dtype=np.uint8)
        else:
            result, valid, foldover = out.arrays, out.valid, out.foldover
            _check_out(result, valid, foldover, shapes, n)
        identity = 0
        for rows, u, state, fold in self._pull_back_slabs(out_geo, b, progress, abort):
            identity += int(np.count_nonzero(state == 3))
            ok = np.flatnonzero(state).astype(np.int64, copy=False)
            valid[rows] = state > 0
            foldover[rows] = fold
            if input_box is not None:  # indices of the box's arrays (in place: no copies
                u -= ib[0::2]  # of a slab; rows without a pre-image are not read)
            for name, vol in volumes.items():
                _sample_into(result[name][rows], vol, u, ok, interpolation, fill_value)
            del u, state, fold, ok  # before the next slab's arrays are made
        counts = {
            "voxels": n,
            "valid": int(valid.sum()),
            "identity": int(identity),
            "foldover": int(foldover.sum()),
        }
        if out is not None:
            out.geometry, out.counts = out_geo.sub(b), counts
            return out
        return Resampled(out_geo.sub(b), result, valid, foldover, counts)

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
        b = _box_of(geometry, box)
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
        # every leaf's, (L, 12) int64, was 14 MB at the start of each piece an MPI rank
        # of the embryo resamples, the last one while its output piece is full
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
        return not self.lattice.inside(_box_of(self.geometry, None)).all()

    def slice(
        self,
        arrays: dict,
        axis: int = 2,
        index: int | None = None,
        geometry: ImageGeometry | None = None,
        *,
        interpolation: str = "linear",
        fill_value: float = 0.0,
    ) -> Resampled:
        """One plane of the resampled volume (for viewers: only that plane is pulled back).

        Parameters
        ----------
        arrays : dict of str -> ndarray
            Input point arrays, as for :meth:`resample`.
        axis : {0, 1, 2}
            The plane's normal axis of the output grid (2: a k-plane).
        index : int, optional
            The plane (default: the middle one).
        geometry : ImageGeometry, optional
            Output grid (default :meth:`output_geometry`).
        interpolation, fill_value
            As for :meth:`resample`.

        Returns
        -------
        Resampled
            Its ``geometry`` is the one-voxel-thick plane.
        """
        out = self.output_geometry() if geometry is None else geometry
        dims = out.dimensions
        index = dims[axis] // 2 if index is None else int(index)
        if not 0 <= index < dims[axis]:
            raise ValueError(f"plane {index} is outside 0..{dims[axis] - 1} along axis {axis}")
        box = [0, dims[0] - 1, 0, dims[1] - 1, 0, dims[2] - 1]
        box[2 * axis] = box[2 * axis + 1] = index
        return self.resample(
            arrays, out, box=box, interpolation=interpolation, fill_value=fill_value
        )

    def preimages(self, geometry: ImageGeometry, voxels, progress=None, abort=None):
        """Pre-images (input voxel indices) of some output voxels, as resampling finds them.

        Parameters
        ----------
        geometry : ImageGeometry
            The output grid.
        voxels : (P, 3) int array_like
            Output voxel indices.

        Returns
        -------
        u : (P, 3) float64
            Continuous input indices (NaN where there is none).
        kind : (P,) uint8
            0 none, 1 found inside the cage, 3 left in place outside it (passthrough).
        fold : (P,) uint8
            1 where another pre-image lies more than a voxel away.
        """
        ijk = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
        u = np.full((len(ijk), 3), np.nan)
        kind = np.zeros(len(ijk), dtype=np.uint8)
        fold_out = np.zeros(len(ijk), dtype=np.uint8)
        if not len(ijk):
            return u, kind, fold_out
        b = np.empty(6, dtype=np.int64)
        b[0::2], b[1::2] = ijk.min(0), ijk.max(0)
        b = _box_of(geometry, b)
        nx, ny = b[1] - b[0] + 1, b[3] - b[2] + 1
        flat = (ijk[:, 0] - b[0]) + nx * ((ijk[:, 1] - b[2]) + ny * (ijk[:, 2] - b[4]))
        order = np.argsort(flat)
        for rows, us, state, fold in self._pull_back_slabs(geometry, b, progress, abort):
            lo, hi = np.searchsorted(flat[order], [rows.start, rows.stop])
            pick = order[lo:hi]
            local = flat[pick] - rows.start
            found = state[local] > 0
            u[pick[found]] = us[local[found]]
            kind[pick] = state[local]
            fold_out[pick] = fold[local]
            del us, state, fold  # before the next slab's arrays are made
        return u, kind, fold_out

    def _pull_back_slabs(self, out_geo, b, progress, abort):
        """Pre-images of an output box, slab by slab (see :meth:`resample`).

        Yields
        ------
        rows : slice
            The slab's voxels among the box's.
        u : (P, 3) float64
            Pre-images (input voxel indices) where ``state > 0``.
        state : (P,) uint8
            0 none, 1 inside the cage, 3 left in place (passthrough).
        fold : (P,) uint8
        """
        self._whole("resampling", out_geo, b)
        lat = self.build(progress=_scaled(progress, 0.0, 0.5), abort=abort)
        self._refuse_outside()
        boxes = self.candidate_boxes(out_geo)
        self._start_slabs()
        budget = DEFAULT_MEMORY_BUDGET if self.memory_budget is None else self.memory_budget
        slabs = list(_slabs(b, _RESAMPLE_BYTES, min(budget, _PULL_BACK_SLAB_BYTES)))
        plane = int((b[1] - b[0] + 1) * (b[3] - b[2] + 1))
        for s, slab in enumerate(slabs):
            _check_abort(abort)
            m = int((slab[5] - slab[4] + 1) * plane)
            self._count_slab(m)
            u = np.zeros((m, 3))
            state = np.zeros(m, dtype=np.uint8)
            fold = np.zeros(m, dtype=np.uint8)
            lat.pull_back(out_geo, slab, boxes, u, state, fold, np.zeros(m))
            self._confirm_tentative(u, state)
            self._polish_next_to_edges(out_geo, slab, u, state)
            self._pass_through(out_geo, slab, u, state)
            lo = int((slab[4] - b[4]) * plane)
            yield slice(lo, lo + m), u, state, fold
            del u, state, fold  # one slab's arrays at a time
            # and their heap pages handed back: glibc serves them from the heap (below its
            # dynamic mmap threshold), and the holes they leave stay resident while the
            # next slabs' arrays, of other sizes, land elsewhere. The embryo's serial
            # resample peaked 15-17 MB higher without (331-333 MB, now 316), the same time.
            release_free_memory()
            if progress is not None:
                progress(0.5 + 0.5 * (s + 1) / len(slabs), "resample")

    def _confirm_tentative(self, u, state) -> None:
        """Pre-images next to the cage: keep those the winding number puts inside."""
        t = np.nonzero(state == 2)[0]
        if t.size:
            cage = self.map.cage
            ins = inside_cage(winding_number(self.geometry.points(u[t]), cage.vertices, cage.faces))
            state[t] = np.where(ins, 1, 0)

    def _polish_next_to_edges(self, out_geo, slab, u, state) -> int:
        """Pre-images next to a cage edge: Newton's method on the exact map from there.

        Kept where it converges within a voxel of the lattice's pre-image (the same
        branch of a fold); elsewhere the lattice's pre-image stays. Returns how many were
        replaced.
        """
        rows = np.nonzero(state == 1)[0]
        if not rows.size:
            return 0
        rows = rows[self.lattice.near_cage_edges(u[rows], _EXACT_NEAR_EDGE)]
        if not rows.size:
            return 0
        nx, ny = slab[1] - slab[0] + 1, slab[3] - slab[2] + 1
        ijk = np.column_stack([rows % nx, (rows // nx) % ny, rows // (nx * ny)]) + slab[0::2]
        geo = self.geometry
        x, ok = exact_preimages(
            self.map, out_geo.points(ijk.astype(np.float64)), geo.points(u[rows]),
            tolerance=1e-4 * float(np.min(geo.spacing)), max_iterations=_EXACT_ITERATIONS,
        )  # fmt: skip
        rows, exact = rows[ok], geo.continuous_index(x[ok])
        same = np.linalg.norm(exact - u[rows], axis=1) <= 1.0
        u[rows[same]] = exact[same]
        return int(same.sum())

    def _pass_through(self, out_geo, slab, u, state) -> int:
        """Outside voxels left in place: output voxels outside the cage with no pre-image."""
        if self.outside != "passthrough":
            return 0
        empty = state == 0
        if not empty.any():
            return 0
        cage = self.map.cage
        rows = (slab[2], slab[3] + 1, slab[4], slab[5] + 1)
        mask = inside_mask(out_geo, cage.vertices, cage.faces, rows=rows)
        src = self.geometry
        # output index -> input index: x = W_in (o_out + M_out i - o_in)
        to_src = src.world_to_index @ out_geo.index_to_world
        shift = src.world_to_index @ (out_geo.origin - src.origin)
        last = np.asarray(src.dimensions, dtype=np.float64) - 1.0
        return int(
            _identity_preimages(
                to_src, shift, slab, mask[:, :, slab[0] : slab[1] + 1], last, u, state
            )
        )

    # ------------------------------------------------------------------ bookkeeping
    def _start_slabs(self) -> None:
        self.slab_count = 0
        self.largest_slab = 0

    def _count_slab(self, voxels: int) -> None:
        self.slab_count += 1
        self.largest_slab = max(self.largest_slab, int(voxels))

    def __repr__(self) -> str:
        return (
            f"VolumeDeformation(dimensions={self.geometry.dimensions}, "
            f"tolerance={self.tolerance}, outside={self.outside!r})"
        )


def output_grid(geometry: ImageGeometry, lo, hi, *, tolerance: float, spacing=None,
                keep_input: bool = False) -> ImageGeometry:  # fmt: skip
    """The output grid over deformed voxels whose images lie within ``lo..hi``.

    Parameters
    ----------
    geometry : ImageGeometry
        The input grid.
    lo, hi : (3,) array_like
        Bounds of the images in continuous input indices (:meth:`VolumeDeformation.image_bounds`).
    tolerance : float
        Added on every side (voxels).
    spacing : (3,) array_like, optional
        Output voxel size; default the input spacing (voxels aligned with the input's).
    keep_input : bool
        Also cover the input's own box (voxels left in place).
    """
    geo = geometry
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError("no voxel of the volume is inside the cage")
    lo = lo - tolerance
    hi = hi + tolerance
    if keep_input:
        lo = np.minimum(lo, 0.0)
        hi = np.maximum(hi, np.asarray(geo.dimensions) - 1.0)
    if spacing is None:
        lo, hi = np.floor(lo), np.ceil(hi)
        dims = (hi - lo).astype(np.int64) + 1
        return ImageGeometry(geo.points(lo[None])[0], geo.spacing, dims, geo.direction)
    sp = np.asarray(spacing, dtype=np.float64).reshape(3)
    if not (np.isfinite(sp).all() and (sp > 0).all()):
        raise ValueError(f"spacing must be three positive numbers; got {spacing}")
    extent = (hi - lo) * geo.spacing
    dims = np.floor(extent / sp + 1e-9).astype(np.int64) + 1
    # centre the output voxels on the deformed volume's box
    start = lo * geo.spacing + 0.5 * (extent - (dims - 1) * sp)
    return ImageGeometry(geo.origin + geo.direction @ start, sp, dims, geo.direction)


def layer_shares(geometry: ImageGeometry, cage, root: int, parts: int) -> np.ndarray:
    """Split the root k-layers of a lattice into ``parts`` runs of about equal work.

    The work of a root layer is taken to be its voxels inside the cage, counted on a grid
    of every ``root / 4``-th voxel: the lattice refines only cells with voxels inside.
    A proxy, not a count of leaves: on the 256^3 embryo the lower half of the layers
    holds 62% of these voxels and 63% of the leaves, and cutting by them gives 135k and
    114k own leaves (equal halves of the layers: 156k and 93k). Deterministic: every MPI
    rank computes the same cuts.

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
    voxel: an MPI rank's time. On the 256^3 embryo bent as in ``bench_volume.py`` the
    output's lower half holds 71% of the pairs: ParaView's halves of the output keep one
    MPI rank busy for twice as long as the other. A part's share of the work counts its
    even share of ``shared_work`` too: the work every part does alike, whatever the cuts
    (the ranks' lattice build, :func:`lattice_build_work`), so that the cuts weigh a
    plane by its part of a rank's whole update.

    The leaves that a run of planes needs (those whose candidate boxes reach it:
    ``spans``) are most of an MPI rank's memory while it pulls back. They are not spread
    as the work is: on the embryo, equal shares of the work need 111k and 146k of the
    249k leaves. With ``spans`` the cuts make the largest of every part's two shares --
    of the work, of the leaves -- as small as it can be. Without ``shared_work`` that
    was, on the embryo, 54% of the pull-back's work for one rank and 54% of the leaves
    (134k; the other 123k) for the other. With the build counted (twice the pull-back's
    work there), 52% of the update's work (55% of the pull-back's) for one, 52% of the
    leaves (129k; the other 128k) for the other: the second rank peaked at 194-201 MB
    against 198-203 MB, and the update took no longer. Without ``spans``, equal shares of the work.

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


@numba.njit(parallel=True, cache=True)
def _measures(jac, det, cond, angle, hard):  # pragma: no cover - compiled
    """Det J, s_max / s_min and the polar rotation's angle of 3x3 matrices, fast.

    The singular values come from the eigenvalues of ``J^T J`` in closed form
    (trigonometric solution of the characteristic cubic, Smith 1961); the rotation from
    Higham's scaled Newton iteration ``X <- (g X + X^-T / g) / 2`` (Higham 1986), a few
    3x3 inverses. Matrices with ``det J <= 0`` or that do not converge are flagged in
    ``hard`` (the caller takes the SVD's values there). NaN matrices give NaN.
    """
    for p in numba.prange(jac.shape[0]):
        a0, a1, a2 = jac[p, 0, 0], jac[p, 0, 1], jac[p, 0, 2]
        a3, a4, a5 = jac[p, 1, 0], jac[p, 1, 1], jac[p, 1, 2]
        a6, a7, a8 = jac[p, 2, 0], jac[p, 2, 1], jac[p, 2, 2]
        d = a0 * (a4 * a8 - a5 * a7) - a1 * (a3 * a8 - a5 * a6) + a2 * (a3 * a7 - a4 * a6)
        det[p] = d
        if not d > 0.0:
            hard[p] = np.isfinite(d)
            cond[p] = np.nan
            angle[p] = np.nan
            continue
        # eigenvalues of the symmetric S = J^T J
        s00 = a0 * a0 + a3 * a3 + a6 * a6
        s11 = a1 * a1 + a4 * a4 + a7 * a7
        s22 = a2 * a2 + a5 * a5 + a8 * a8
        s01 = a0 * a1 + a3 * a4 + a6 * a7
        s02 = a0 * a2 + a3 * a5 + a6 * a8
        s12 = a1 * a2 + a4 * a5 + a7 * a8
        q = (s00 + s11 + s22) / 3.0
        off = s01 * s01 + s02 * s02 + s12 * s12
        r = math.sqrt(((s00 - q) ** 2 + (s11 - q) ** 2 + (s22 - q) ** 2 + 2.0 * off) / 6.0)
        if r <= 1e-300:
            lmax = lmin = q
        else:
            b00, b11, b22 = (s00 - q) / r, (s11 - q) / r, (s22 - q) / r
            b01, b02, b12 = s01 / r, s02 / r, s12 / r
            half = 0.5 * (
                b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02)
                + b02 * (b01 * b12 - b11 * b02)
            )  # fmt: skip
            phi = math.acos(min(1.0, max(-1.0, half))) / 3.0
            lmax = q + 2.0 * r * math.cos(phi)
            lmin = q + 2.0 * r * math.cos(phi + 2.0 * math.pi / 3.0)
        if not lmin > 1e-12 * lmax:  # nearly singular: the cubic loses s_min
            hard[p] = True
            continue
        cond[p] = math.sqrt(lmax / lmin)
        # polar rotation: X <- (g X + X^-T / g) / 2, X^-T = cofactor(X) / det(X)
        x0, x1, x2, x3, x4, x5, x6, x7, x8 = a0, a1, a2, a3, a4, a5, a6, a7, a8
        dx = d
        ok = False
        for _ in range(30):
            c0, c1, c2 = x4 * x8 - x5 * x7, x5 * x6 - x3 * x8, x3 * x7 - x4 * x6
            c3, c4, c5 = x2 * x7 - x1 * x8, x0 * x8 - x2 * x6, x1 * x6 - x0 * x7
            c6, c7, c8 = x1 * x5 - x2 * x4, x2 * x3 - x0 * x5, x0 * x4 - x1 * x3
            nx = x0 * x0 + x1 * x1 + x2 * x2 + x3 * x3 + x4 * x4 + x5 * x5
            nx += x6 * x6 + x7 * x7 + x8 * x8
            nc = c0 * c0 + c1 * c1 + c2 * c2 + c3 * c3 + c4 * c4 + c5 * c5
            nc += c6 * c6 + c7 * c7 + c8 * c8
            g = math.sqrt(math.sqrt(nc / (dx * dx * nx)))
            h = 0.5 / (g * dx)
            y0, y1, y2 = 0.5 * g * x0 + h * c0, 0.5 * g * x1 + h * c1, 0.5 * g * x2 + h * c2
            y3, y4, y5 = 0.5 * g * x3 + h * c3, 0.5 * g * x4 + h * c4, 0.5 * g * x5 + h * c5
            y6, y7, y8 = 0.5 * g * x6 + h * c6, 0.5 * g * x7 + h * c7, 0.5 * g * x8 + h * c8
            change = (y0 - x0) ** 2 + (y4 - x4) ** 2 + (y8 - x8) ** 2 + (y1 - x1) ** 2
            change += (y2 - x2) ** 2 + (y3 - x3) ** 2 + (y5 - x5) ** 2 + (y6 - x6) ** 2
            change += (y7 - x7) ** 2
            x0, x1, x2, x3, x4, x5, x6, x7, x8 = y0, y1, y2, y3, y4, y5, y6, y7, y8
            dx = x0 * (x4 * x8 - x5 * x7) - x1 * (x3 * x8 - x5 * x6) + x2 * (x3 * x7 - x4 * x6)
            if change < 1e-24:
                ok = True
                break
        if not ok:
            hard[p] = True
            continue
        angle[p] = math.acos(min(1.0, max(-1.0, 0.5 * (x0 + x4 + x8 - 1.0))))


@numba.njit(parallel=True, cache=True)
def _fill_outside(origin, to_world, box, inside, nan, out):  # pragma: no cover - compiled
    """Outside voxels of a box: their own position, or NaN."""
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    for kk in numba.prange(box[5] - box[4] + 1):
        k = box[4] + kk
        for jj in range(ny):
            j = box[2] + jj
            for ii in range(nx):
                if inside[kk, jj, ii]:
                    continue
                p = (kk * ny + jj) * nx + ii
                i = box[0] + ii
                for a in range(3):
                    out[p, a] = (
                        np.nan
                        if nan
                        else origin[a] + to_world[a, 0] * i + to_world[a, 1] * j
                        + to_world[a, 2] * k
                    )  # fmt: skip


@numba.njit(parallel=True, cache=True)
def _identity_preimages(to_src, shift, box, inside, last, u, state):  # pragma: no cover
    """Identity pre-images of the output voxels left without one (``state`` 3).

    Only voxels outside the cage (``inside`` False) whose position lies within the input's
    half-voxel border: there the outside voxels stayed in place.
    """
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    nk = box[5] - box[4] + 1
    count = np.zeros(nk, dtype=np.int64)
    for kk in numba.prange(nk):
        k = box[4] + kk
        for jj in range(ny):
            j = box[2] + jj
            for ii in range(nx):
                p = (kk * ny + jj) * nx + ii
                if state[p] != 0 or inside[kk, jj, ii]:
                    continue
                i = box[0] + ii
                ok = True
                x = np.empty(3)
                for a in range(3):
                    x[a] = shift[a] + to_src[a, 0] * i + to_src[a, 1] * j + to_src[a, 2] * k
                    if x[a] < -BORDER or x[a] > last[a] + BORDER:
                        ok = False
                if ok:
                    for a in range(3):
                        u[p, a] = x[a]
                    state[p] = 3
                    count[kk] += 1
    return count.sum()


def _scaled(progress, lo: float, hi: float):
    if progress is None:
        return None

    def cb(fraction, message=""):
        progress(lo + (hi - lo) * float(fraction), message)

    return cb


def _sample_into(out, volume, u, rows, kind: str, fill_value: float) -> None:
    """Sample ``volume`` at ``u[rows]`` into ``out`` (its dtype), fill elsewhere."""
    dtype = volume.dtype
    comps = volume.shape[3]
    integer = np.issubdtype(dtype, np.integer)
    fill = fill_value
    lo = hi = 0.0
    if integer:
        info = np.iinfo(dtype)
        fill = np.clip(np.rint(fill_value), info.min, info.max)
        lo, hi = float(info.min), float(info.max)
    flat = out.reshape(len(out), comps)
    flat[...] = np.asarray(fill).astype(dtype)
    if not rows.size:
        return
    # one buffer row per slab voxel (the kernels write the rows asked for in place); the
    # rows are stored with no temporaries (a slab is a million voxels)
    buf = np.empty((len(u), comps), dtype=dtype if kind == "nearest" else np.float64)
    sample(volume, u, rows, kind, buf)
    _store_rows(buf, rows, integer and kind != "nearest", lo, hi, flat)


@numba.njit(cache=True)
def _store_rows(buf, rows, round_clip, lo, hi, out):  # pragma: no cover - compiled
    """``out[rows] = buf[rows]``, rounded and clipped to ``[lo, hi]`` if ``round_clip``."""
    if round_clip:
        for r in rows:
            for c in range(buf.shape[1]):
                out[r, c] = min(max(np.rint(buf[r, c]), lo), hi)
    else:  # (no float in between: 64-bit labels are copied exactly)
        for r in rows:
            for c in range(buf.shape[1]):
                out[r, c] = buf[r, c]


def exact_preimages(harmonic_map, targets, starts, *, tolerance: float, max_iterations: int = 30):
    """Solve ``f(x) = y`` by Newton's method on the exact (closed-form) map.

    The reference inverse (slow: one closed-form evaluation per point and iteration);
    the volume engine inverts the lattice's polynomials instead.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    targets : (N, 3) array_like
        The points ``y`` (world).
    starts : (N, 3) array_like
        Initial guesses inside the cage.
    tolerance : float
        Stop when ``|f(x) - y| <= tolerance`` (world units).
    max_iterations : int

    Returns
    -------
    x : (N, 3) float64
        Pre-images (NaN where none was found).
    ok : (N,) bool
        Converged inside the cage.
    """
    y = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    x = np.array(starts, dtype=np.float64).reshape(-1, 3)
    cage = harmonic_map.cage
    V = np.ascontiguousarray(cage.vertices, dtype=np.float64)
    F = np.ascontiguousarray(cage.faces, dtype=np.int64)
    z = np.asarray(harmonic_map.coefficients)
    ok = np.zeros(len(y), bool)
    active = np.arange(len(y))
    for it in range(max_iterations + 1):
        if not active.size:
            break
        # the fused kernel: values and Jacobians without the (N, n + m) basis arrays
        # (HarmonicMap.evaluate's chunks of them were 24 MB of a resample's peak)
        f, jac, wind = evaluate_map(x[active], V, F, z, order=1)
        out = ~inside_cage(wind)
        f[out], jac[out] = np.nan, np.nan
        r = f - y[active]
        norm = np.linalg.norm(r, axis=1)
        conv = norm <= tolerance
        ok[active[conv]] = True
        keep = ~conv & np.isfinite(norm)
        active = active[keep]
        if it == max_iterations or not active.size:
            break
        jk, rk = jac[keep], r[keep]
        good = np.abs(np.linalg.det(jk)) > 1e-14
        step = np.full_like(rk, np.nan)
        step[good] = np.linalg.solve(jk[good], rk[good][..., None])[..., 0]
        x[active] -= step
        active = active[np.isfinite(step).all(axis=1)]
    x[~ok] = np.nan
    return x, ok
