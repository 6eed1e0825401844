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

The engine's parts live beside it: the lattice (:mod:`vhm_viz.core.lattice`), the
per-voxel kernels (:mod:`vhm_viz.core.volume_kernels`), where the leaves reach and the
engines of output pieces (:mod:`vhm_viz.core.volume_pieces`), the pre-images
found besides the lattice's (:mod:`vhm_viz.core.preimages`) and the cutting of the work
into MPI ranks' shares (:mod:`vhm_viz.core.partition`); their public names are importable
from here too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vhm_viz.core.basis import DEFAULT_MEMORY_BUDGET
from vhm_viz.core.binding import check_outside_policy
from vhm_viz.core.devices import require_device
from vhm_viz.core.displacement import (
    FIELD_KINDS,
    DisplacementField,
    check_field_kind,
    subtract_grid_points,
)
from vhm_viz.core.errors import AbortedError, OutsideCageError, describe_indices
from vhm_viz.core.image import (
    INTERPOLATIONS,
    ImageGeometry,
    check_fill_value,
    check_interpolation,
)
from vhm_viz.core.lattice import (
    DEFAULT_ROOT,
    DEFAULT_TOLERANCE,
    MAX_TOLERANCE,
    HermiteLattice,
    build_lattice,
    check_tolerance,
)
from vhm_viz.core.lattice.pullback import subcell_tests
from vhm_viz.core.memory import PULL_BACK_SLAB_BYTES, SLAB_VOXEL_BYTES, release_free_memory
from vhm_viz.core.partition import (
    equal_cuts,
    lattice_build_work,
    layer_shares,
    pull_back_shares,
    window_of,
)
from vhm_viz.core.preimages import (
    exact_preimages,
    leaves_near_edges,
    pass_through,
    settle_preimages,
)
from vhm_viz.core.volume_kernels import (
    box_ijk,
    box_of,
    check_out_arrays,
    fast_jacobian_measures,
    fill_outside,
    finish_slab,
    scaled_progress,
    slabs_of,
)
from vhm_viz.core.volume_pieces import VolumePieces, output_grid

__all__ = [
    "VolumeDeformation",
    "Resampled",
    "DisplacementField",
    "FIELD_KINDS",
    "output_grid",
    "layer_shares",
    "equal_cuts",
    "pull_back_shares",
    "lattice_build_work",
    "window_of",
    "exact_preimages",
    "fast_jacobian_measures",
    "DEFAULT_TOLERANCE",
    "MAX_TOLERANCE",
    "check_tolerance",
    "EXACT_VOXELS",
    "INTERPOLATIONS",
]

#: Volumes of at most this many voxels are evaluated exactly at every voxel (a lattice of
#: single-voxel cells): a lattice would not save evaluations there.
EXACT_VOXELS = 32768
_RESAMPLE_BYTES = SLAB_VOXEL_BYTES["resample"]
_WARP_BYTES = SLAB_VOXEL_BYTES["warp"]


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
    displacement : (P, 3) float64 or None
        The pull-back displacement ``f^-1(y) - y`` of each voxel (world units; 0 where
        ``valid`` is 0), when asked for (see :mod:`vhm_viz.core.displacement`).
    """

    geometry: ImageGeometry
    arrays: dict
    valid: np.ndarray
    foldover: np.ndarray
    counts: dict = field(default_factory=dict)
    displacement: np.ndarray | None = None


def _check_abort(abort) -> None:
    if abort is not None and abort():
        raise AbortedError("aborted")


class VolumeDeformation(VolumePieces):
    """A harmonic map applied to the voxels of an image grid.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    geometry : ImageGeometry
        The input volume's grid.
    tolerance : float
        Largest position error of a mapped voxel, in voxels of the input spacing
        (default :data:`DEFAULT_TOLERANCE`); also bounds the pre-image error of a
        resampled voxel where the map is not strongly compressive.
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
    device : {"cpu", "cuda"}
        Where the lattice's exact evaluations of the map and its Jacobians, and the
        pull-back's Newton solves, run: the CPU (default) or an NVIDIA GPU
        (:mod:`vhm_viz.core.cuda_map`, :mod:`vhm_viz.core.lattice.cuda_pullback`; the same
        values to rounding, pre-images within the tolerance).
        :class:`~vhm_viz.core.errors.DeviceUnavailableError` without a GPU. The lattice's
        refinement, its per-voxel polynomials, the candidate lists and the sampling run on
        the CPU either way.

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
        device: str = "cpu",
    ):
        self.device = require_device(device)
        same = getattr(harmonic_map, "device", "cpu") == self.device
        self.map = harmonic_map if same else harmonic_map.on(self.device)
        self.exchange = exchange
        self.geometry = geometry
        self.tolerance = check_tolerance(tolerance)
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
            self.window = None if window is None else box_of(geometry, window)
        if self.window is not None and self.window.tolist() == box_of(geometry, None).tolist():
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
            exchange=self.exchange, pre_images=self.pre_images, device=self.device,
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
        b = box_of(self.geometry, box)
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
        if inside.all():  # (the usual case, without a pass that makes indices)
            return np.zeros(0, dtype=np.int64)
        if b.tolist() == box_of(self.geometry, None).tolist():
            return np.nonzero(~inside.ravel())[0]
        nx, ny, _ = self.geometry.dimensions
        ijk = box_ijk(b)[~inside.ravel()]
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
            # a piece's count is of the piece's voxels: an MPI rank says its own piece's
            b = self._in_window(self.window if box is None else box)
            n = int(np.prod(b[1::2] - b[0::2] + 1))
            of = f"{n} voxels"
            if n != self.geometry.n_points:
                of = f"the {n} voxels of the piece {b.tolist()} ({self.geometry.n_points} in all)"
            raise OutsideCageError(
                f"{bad.size} of {of} are outside the cage (indices {describe_indices(bad)}); "
                "use the 'passthrough' outside policy to leave them in place or 'nan' to drop "
                "them",
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
        lat = self.build(progress=scaled_progress(progress, 0.0, 0.6), abort=abort)
        self._refuse_outside(b)
        n = int(np.prod(b[1::2] - b[0::2] + 1))
        if out is None:
            out = np.empty((n, 3))
        elif out.shape != (n, 3) or out.dtype != np.float64:
            raise ValueError(f"out must be a float64 array of shape ({n}, 3)")
        self._start_slabs()
        slabs = list(slabs_of(b, _WARP_BYTES, self.memory_budget))
        plane = int((b[1] - b[0] + 1) * (b[3] - b[2] + 1))
        for s, slab in enumerate(slabs):
            _check_abort(abort)
            lo = (slab[4] - b[4]) * plane
            view = out[lo : lo + (slab[5] - slab[4] + 1) * plane]
            self._count_slab(len(view))
            inside = lat.inside(slab)
            if not inside.all():  # nothing to fill: no call (nor its compile on a first run)
                fill_outside(
                    self.geometry.origin, self.geometry.index_to_world, slab, inside,
                    self.outside == "nan", view,
                )  # fmt: skip
            lat.warp(slab, view)
            if progress is not None:
                progress(0.6 + 0.4 * (s + 1) / len(slabs), "warp")
        return out

    def unproven_cells(self, box=None) -> np.ndarray:
        """The voxel cells of a box whose warp (:meth:`warp`) is not proven unfolded.

        Every other cell of the warped voxels has corner Jacobian determinants of the
        rest voxel's sign: the lattice's polynomials prove it
        (:mod:`~vhm_viz.core.lattice.fold_proof`). A fold check measures these alone
        (:func:`~vhm_viz.core.cell_kernels.inverted_hexahedra`'s ``boxes``).

        Parameters
        ----------
        box : (i0, i1, j0, j1, k0, k1), optional
            Inclusive voxel ranges (default: the window); its cells have their lowest
            corner at ``i0 .. i1 - 1`` and so on.

        Returns
        -------
        (K, 6) int64
            Disjoint inclusive cell ranges ``i0, i1, j0, j1, k0, k1``, relative to the
            box's first cell.
        """
        b = self._in_window(self.window if box is None else box)
        sign = float(np.sign(np.linalg.det(self.geometry.index_to_world)))
        return self.lattice.unproven_cells(b, sign)

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
        lat = self.build(progress=scaled_progress(progress, 0.0, 0.6), abort=abort)
        self._refuse_outside(b)
        self._start_slabs()
        slabs = list(slabs_of(b, 72, self.memory_budget))
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

        Computed slab by slab by :func:`~vhm_viz.core.volume_kernels.fast_jacobian_measures`.

        Returns
        -------
        dict
            ``determinant``, ``condition_number``, ``rotation_angle`` (radians) as (P,)
            float64 and ``foldover`` (P,) bool (``det J <= 0``).
        """
        b = self._in_window(self.window if box is None else box)
        n = int(np.prod(b[1::2] - b[0::2] + 1))
        det, cond, angle = np.empty(n), np.empty(n), np.empty(n)
        for rows, jac in self.jacobian_slabs(b, progress, abort):
            fast_jacobian_measures(jac, out=(det[rows], cond[rows], angle[rows]))
        return {
            "determinant": det,
            "condition_number": cond,
            "rotation_angle": angle,
            "foldover": det <= 0,
        }

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
        displacement: bool = False,
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
            Value of voxels without a pre-image; every array's dtype must hold it exactly
            (:func:`~vhm_viz.core.image.check_fill_value`: a ValueError before any work).
        input_box : (i0, i1, j0, j1, k0, k1), optional
            ``arrays`` hold only this box of the input grid (default: all of it); it must
            contain :meth:`input_window` of the output box, the voxels the pre-images
            reach. The result is the same as with the whole input.
        out : Resampled, optional
            Write into these arrays instead of new ones: an array of each name with the
            input's dtype and components, ``valid`` and ``foldover``, each a (C-contiguous)
            row per voxel of the box -- say, views of the rows of a larger box that this
            box's voxels occupy (an MPI rank's output piece, resampled in parts).
            With ``displacement``, also its ``displacement``.
        displacement : bool
            Also the pull-back displacement of each voxel, from the same pre-images
            (:attr:`Resampled.displacement`).
        progress, abort : callables, optional

        Returns
        -------
        Resampled
            Arrays keep their dtype: integer arrays interpolated linearly or cubically are
            rounded and clipped to their type's range. With ``out``: ``out``, its arrays
            filled and its counts set.
        """
        check_interpolation(interpolation)
        fill_value = check_fill_value(
            fill_value, {name: np.asarray(v).dtype for name, v in arrays.items()}
        )
        src = self.geometry
        ib = box_of(src, input_box)
        nx, ny, nz = (int(n) for n in ib[1::2] - ib[0::2] + 1)
        volumes = {}
        for name, values in arrays.items():
            v = np.asarray(values)
            if v.shape[0] != nx * ny * nz:
                raise ValueError(
                    f"array {name!r} has {v.shape[0]} values for {nx * ny * nz} voxels"
                )
            volumes[name] = v.reshape(nz, ny, nx, -1)
        self.build(progress=scaled_progress(progress, 0.0, 0.5), abort=abort)
        out_geo = self.output_geometry() if geometry is None else geometry
        b = box_of(out_geo, box)
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
            check_out_arrays(result, valid, foldover, shapes, n)
        vectors = None
        if displacement:
            vectors = np.empty((n, 3)) if out is None else out.displacement
            if vectors is None or vectors.shape != (n, 3) or vectors.dtype != np.float64 \
                    or not vectors.flags.c_contiguous:  # fmt: skip
                raise ValueError(f"out.displacement must be a contiguous float64 ({n}, 3) array")
        width = int(b[1] - b[0] + 1)
        plane = width * int(b[3] - b[2] + 1)
        tally = np.zeros(3, dtype=np.int64)  # valid, identity, foldover
        row_counts = None  # per output row of a slab (finish_slab's scratch)
        for rows, u, state, fold in self._pull_back_slabs(out_geo, b, progress, abort):
            if vectors is not None:
                slab = b.copy()
                slab[4], slab[5] = b[4] + rows.start // plane, b[4] + rows.stop // plane - 1
                self._pull_back_displacements(vectors[rows], u, state, out_geo, slab)
            if row_counts is None:  # the first slab is the largest
                row_counts = np.empty((len(state) // width, 3), dtype=np.int64)
            # (the volumes hold the input box: their indices are shifted as they are read)
            samples = [(result[name][rows], vol) for name, vol in volumes.items()]
            tally += finish_slab(state, fold, u, valid[rows], foldover[rows], samples,
                                 interpolation, fill_value, width, row_counts,
                                 ib[0::2])  # fmt: skip
            del u, state, fold, samples  # before the next slab's arrays are made
        counts = {
            "voxels": n,
            "valid": int(tally[0]),
            "identity": int(tally[1]),
            "foldover": int(tally[2]),
        }
        if out is not None:
            out.geometry, out.counts = out_geo.sub(b), counts
            return out
        return Resampled(out_geo.sub(b), result, valid, foldover, counts, vectors)

    def _pull_back_displacements(self, vectors, u, state, out_geo, slab) -> None:
        """``f^-1(y) - y`` of a slab's output voxels (world), 0 where none, into ``vectors``."""
        np.matmul(u, self.geometry.index_to_world.T, out=vectors)
        vectors += self.geometry.origin
        subtract_grid_points(vectors, out_geo, slab)
        vectors[state == 0] = 0.0

    def displacement_field(
        self,
        geometry: ImageGeometry | None = None,
        *,
        kind: str = "pullback",
        box=None,
        progress=None,
        abort=None,
    ) -> DisplacementField:
        """The deformation as a displacement field (see :mod:`vhm_viz.core.displacement`).

        Parameters
        ----------
        geometry : ImageGeometry, optional
            ``"pullback"``: the output grid (default :meth:`output_geometry`).
            ``"forward"``: must be the input grid, or None.
        kind : {"pullback", "forward"}
            ``"pullback"``: ``u(y) = f^-1(y) - y`` on the output grid, from the pre-images
            :meth:`resample` finds (applied by ITK's ``DisplacementFieldTransform`` it
            reproduces the resample); no pre-image gives 0 and ``valid`` 0, several
            ``foldover`` 1 (the mask of the resample). ``"forward"``: ``u(x) = f(x) - x``
            on the input grid (:meth:`warp`); ``foldover`` 1 where ``det J <= 0``
            (:meth:`jacobian_slabs`); voxels outside the cage follow the outside policy
            (``"passthrough"``: 0, ``"nan"``: 0 and ``valid`` 0).
        box : (i0, i1, j0, j1, k0, k1), optional
            Only these voxels of the grid (default all).
        progress, abort : callables, optional

        Returns
        -------
        DisplacementField
            Vectors in world units and frame (LPS for scans), one row per voxel of the
            box. Work goes slab by slab: the memory is the field plus one slab's arrays.
        """
        if check_field_kind(kind) == "pullback":
            res = self.resample({}, geometry, box=box, displacement=True,
                                progress=progress, abort=abort)  # fmt: skip
            return DisplacementField(res.geometry, res.displacement, res.valid, res.foldover)
        if geometry is not None and not geometry.same_as(self.geometry):
            raise ValueError(
                "a forward displacement field lives on the input grid: give no geometry"
            )
        b = self._in_window(self.window if box is None else box)
        vectors = self.warp(b, progress=scaled_progress(progress, 0.0, 0.7), abort=abort)
        subtract_grid_points(vectors, self.geometry, b)
        det = np.empty(len(vectors))
        for rows, jac in self.jacobian_slabs(b, scaled_progress(progress, 0.7, 1.0), abort):
            with np.errstate(invalid="ignore"):  # NaN Jacobians: voxels without an image
                det[rows] = np.linalg.det(jac)
        return DisplacementField.forward(self.geometry.sub(b), vectors, det, copy=False)

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
        b = box_of(geometry, b)
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
        lat = self.build(progress=scaled_progress(progress, 0.0, 0.5), abort=abort)
        self._refuse_outside()
        boxes = self.candidate_boxes(out_geo)
        near_edge = leaves_near_edges(lat)
        tests = subcell_tests(lat, out_geo) if self.device == "cpu" else None
        self._start_slabs()
        budget = DEFAULT_MEMORY_BUDGET if self.memory_budget is None else self.memory_budget
        slabs = list(slabs_of(b, _RESAMPLE_BYTES, min(budget, PULL_BACK_SLAB_BYTES)))
        plane = int((b[1] - b[0] + 1) * (b[3] - b[2] + 1))
        # one set of slab arrays, reused by every slab (the pull-back writes each voxel's):
        # new arrays per slab would each be paged in again, one thread zeroing them
        largest = max((int(slab[5] - slab[4] + 1) for slab in slabs), default=0) * plane
        buffers = (np.empty((largest, 3)), np.empty(largest, dtype=np.uint8),
                   np.empty(largest, dtype=np.uint8), np.empty(largest))  # fmt: skip
        for s, slab in enumerate(slabs):
            _check_abort(abort)
            m = int((slab[5] - slab[4] + 1) * plane)
            self._count_slab(m)
            u, state, fold, quality = (a[:m] for a in buffers)
            lat.pull_back(out_geo, slab, boxes, u, state, fold, quality, near_edge, tests,
                          self.device)  # fmt: skip
            settle_preimages(self.map, lat, self.geometry, out_geo, slab, u, state)
            if self.outside == "passthrough":
                pass_through(self.map, self.geometry, out_geo, slab, u, state)
            lo = int((slab[4] - b[4]) * plane)
            yield slice(lo, lo + m), u, state, fold
            del u, state, fold, quality
            if progress is not None:
                progress(0.5 + 0.5 * (s + 1) / len(slabs), "resample")
        del buffers
        # the slabs' transients (index lists, sampling buffers) leave free pages inside
        # the heap: back to the system
        release_free_memory()

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
