"""``HarmonicResampleFilter``: a deformed volume resampled back onto a regular grid."""

from __future__ import annotations

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonDataModel import vtkImageData, vtkPolyData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from vhm_viz.core.displacement import DisplacementField
from vhm_viz.core.errors import FoldWarning
from vhm_viz.core.fold_voxels import FOLDS, fold_voxels, fold_voxels_text, merge_fold_voxels
from vhm_viz.core.image import ImageGeometry, check_interpolation
from vhm_viz.core.lattice import PART_FIELDS, join_parts
from vhm_viz.core.memory import release_free_memory
from vhm_viz.core.volume import (
    Resampled,
    VolumeDeformation,
    lattice_build_work,
    layer_shares,
    output_grid,
    pull_back_shares,
    window_of,
)
from vhm_viz.filters import mpi
from vhm_viz.filters._common import DeformationSource
from vhm_viz.filters._vtk import (
    add_lattice_counts,
    image_geometry,
    information_geometry,
    requested_extent,
    set_field_counts,
)

__all__ = [
    "HarmonicResampleFilter",
    "image_geometry",
    "FIELD_ARRAY",
    "displacement_field_of",
    "resampled_arrays",
]

_SDDP = vtkStreamingDemandDrivenPipeline
_MODES = ("deformed", "input")
# Voxels beyond a rank's own root layers that its window holds: a single-voxel cell's
# twists difference the node one voxel across (its own cells then come out as the whole
# lattice's, bit for bit; with no voxel beyond, pre-images near a window's edge would
# differ from a serial run's). One would do; two keep a margin, and far fewer leaves than
# a whole root layer.
_HALO = 2
#: The point array of a displacement field's vectors in a VTK image
#: (:meth:`HarmonicResampleFilter.SetComputeDisplacementField`,
#: ``mesh.vhm.displacement_field``).
FIELD_ARRAY = "vhm_displacement_field"
#: Point arrays the filter adds (never resampled from an input that already has them).
_OWN_ARRAYS = ("vtkValidPointMask", "vhm_foldover", FIELD_ARRAY)


class HarmonicResampleFilter(DeformationSource):
    """Resample a deformed volume onto a regular grid by pulling voxels back (vtkImageData).

    The volume engine (:mod:`vhm_viz.core.volume`) maps the input through an adaptive
    lattice of exact map values and Jacobians (tricubic Hermite in between, within
    :meth:`SetTolerance` voxels of the exact map); each output voxel is pulled back to its
    pre-image by Newton's method on the lattice's polynomials, and every point array of
    the input is sampled there (:meth:`SetInterpolation`; integer arrays keep their type).

    **Fill value.** Voxels without a pre-image -- outside the deformed volume, whose
    input extends half a voxel beyond its outer grid points as with ``vtkImageReslice``'s
    border -- get :meth:`SetFillValue` (default 0) in every array and 0 in the ``uint8``
    array ``vtkValidPointMask`` (1 elsewhere), as ``vtkProbeFilter`` does. Every array's
    type must hold the fill value exactly (:func:`~vhm_viz.core.image.check_fill_value`):
    an update with one it cannot hold fails, naming the type's values. Where several
    pre-images exist (a fold) the ``uint8`` array ``vhm_foldover`` is 1; the field arrays
    ``vhm_foldover_count`` and ``vhm_valid_count`` count them (under MPI, in the whole
    output: the same on every rank). An output with voxels in
    folds is made as asked, and said: how many and the box of their positions
    (:attr:`fold_voxels`), one line in :attr:`warnings`, given as a
    :class:`~vhm_viz.core.errors.FoldWarning` (in ParaView, in its output window).
    Cell data is not resampled.

    **Displacement field** (opt-in, :meth:`SetComputeDisplacementField`): the point array
    ``vhm_displacement_field``, 3 float64 components, the pull-back ``f^-1(y) - y`` of
    each output voxel in world units and frame (0 where ``vtkValidPointMask`` is 0), from
    the same pre-images as the resampled arrays: ITK's ``DisplacementFieldTransform`` of
    it reproduces the output (see :mod:`vhm_viz.core.displacement`,
    :func:`vhm_viz.io.fields.write_displacement_field`).

    **Outside the cage** voxels follow the outside policy (:meth:`SetOutsidePolicy`):
    ``"error"`` (default) refuses a volume with voxels outside the cage, ``"passthrough"``
    leaves them in place (output voxels outside the cage take the input there), ``"nan"``
    drops them.

    **Output grid.** ``"deformed"`` (default): the input's spacing (or
    :meth:`SetOutputSpacing`) and direction, over the box that holds the whole deformed
    volume (bounded from the lattice's control points, so nothing is clipped);
    ``"input"``: the input grid itself; or :meth:`SetReferenceImage` (another image's
    grid) or :meth:`SetOutputGeometry`. The output honours requested sub-extents (pieces):
    a piece pulls back its own voxels only, and requests from its input only the window
    its pre-images reach (:meth:`VolumeDeformation.input_window
    <vhm_viz.core.volume.VolumeDeformation.input_window>`: the leaves whose images can
    reach the piece, widened by the interpolation stencil), plus the whole cage. The
    lattice is built whole (from the input's grid, before any voxel is read) and shared
    by the pieces of an update.

    **MPI ranks** (ParaView) share the lattice instead of each building it whole. Each
    rank builds the root cells of its share of the input's k-layers (shares of the
    voxels inside the cage: :func:`~vhm_viz.core.volume.layer_shares`) and the cells
    holding the two voxels beyond them on each side (the single-voxel cells' twists read
    neighbours there, so its own root cells come out as in the whole lattice, bit for
    bit); the ranks agree on the output grid from their leaves' bounds, and on a cut of
    the output's k-planes into shares of the pull-back work and of the leaves it needs
    (:func:`~vhm_viz.core.volume.pull_back_shares`: the pieces ParaView asks for need not
    hold equal work: one half of a scan may hold most of it). Each rank pulls back the
    voxels of its planes, whichever rank's piece they belong to, and sends them there; it
    reads the input window those planes may need, from every rank's table of where its
    root cells map to. At the update each rank sends to every other the leaves whose
    images reach that rank's planes, and pulls back with the leaves it gathered
    (:func:`~vhm_viz.core.lattice.join_parts`): the serial result, bit for bit, with about
    a rank's share of the lattice in memory.
    The field array ``vhm_pulled_back_voxels`` counts the voxels a rank pulled back.

    Input port 0: ``vtkImageData``; port 1: optional cage. The deformation is set as for
    :class:`~vhm_viz.filters.HarmonicDeformationFilter`.
    """

    def __init__(self):
        super().__init__(input_type="vtkImageData", output_type="vtkImageData")
        self._fill = 0.0
        self._mode = "deformed"
        self._explicit: ImageGeometry | None = None
        self._spacing = None
        self._interpolation = "linear"
        self._field = False
        self._geometry: ImageGeometry | None = None
        self._information_error: BaseException | None = None
        # MPI ranks: what the ranks agreed on in the information pass, and the engine of
        # this rank's output piece
        self._shared = None
        self._piece_engine = None
        self._piece_key = None
        #: Counts of the last execution: voxels, valid, identity, foldover.
        self.stats: dict = {}
        #: The output's voxels in folds of the last execution (under MPI, of the whole
        #: output): :func:`~vhm_viz.core.fold_voxels.fold_voxels`, or None.
        self.fold_voxels: dict | None = None

    # ------------------------------------------------------------------ options
    def SetFillValue(self, value: float) -> None:
        """Value of the voxels without a pre-image (default 0).

        Every array's type must hold it exactly (an integer in its range for integer
        arrays); an update with one it cannot hold fails.
        """
        self._set_option("_fill", float(value))

    def GetFillValue(self) -> float:
        """The fill value."""
        return self._fill

    def SetInterpolation(self, kind: str) -> None:
        """``"linear"`` (trilinear, default), ``"nearest"`` (label maps) or ``"cubic"``."""
        self._set_option("_interpolation", check_interpolation(kind))

    def GetInterpolation(self) -> str:
        """The interpolation kind."""
        return self._interpolation

    def SetComputeDisplacementField(self, value: bool) -> None:
        """Add the pull-back displacement of each output voxel (``vhm_displacement_field``)."""
        self._set_option("_field", bool(value))

    def GetComputeDisplacementField(self) -> bool:
        """Whether the output holds ``vhm_displacement_field``."""
        return self._field

    def SetOutputMode(self, mode: str) -> None:
        """``"deformed"`` (the whole deformed volume) or ``"input"`` (the input grid)."""
        if mode not in _MODES:
            raise ValueError(f"output mode must be one of {_MODES}; got {mode!r}")
        self._mode = mode
        self._explicit = None
        self.Modified()

    def SetOutputSpacing(self, spacing) -> None:
        """Voxel size of the ``"deformed"`` output grid (default: the input spacing).

        With another output grid (:meth:`SetReferenceImage`, :meth:`SetOutputGeometry`,
        output mode ``"input"``) an update fails: that grid has its own spacing.
        """
        if spacing is not None:
            spacing = tuple(float(v) for v in np.asarray(spacing, dtype=np.float64).reshape(3))
            if not all(np.isfinite(v) and v > 0 for v in spacing):
                raise ValueError(f"spacing must be three positive numbers; got {spacing}")
        self._spacing = spacing
        self.Modified()

    def SetOutputGeometry(self, origin, spacing, dimensions, direction=None) -> None:
        """An explicit output grid."""
        self._explicit = ImageGeometry(origin, spacing, dimensions, direction)
        self.Modified()

    def SetReferenceImage(self, image) -> None:
        """Resample onto the grid (origin, spacing, dimensions, direction) of ``image``."""
        self._explicit = image_geometry(image)
        self.Modified()

    # ------------------------------------------------------------------ pipeline
    def RequestInformation(self, request, in_info, out_info):
        """Compute the output grid (needs the map: built or solved here if necessary).

        With :meth:`SetParallelReporting` (ParaView) a failure here is reported by the
        update's ``RequestData``, once and agreed by the ranks: this pass then succeeds
        without an output grid, rather than adding VTK's executive error (and running
        ``RequestData`` without a grid) to the one line.
        """
        self._geometry = None
        ok = self._guard(self._information, in_info, out_info)
        self._information_error = self.last_error
        return 1 if self._parallel_reporting else ok

    def _engine(self, in_info, img):
        geo = information_geometry(in_info[0].GetInformationObject(0))
        if img is None or geo is None:
            raise ValueError("HarmonicResampleFilter needs vtkImageData on input port 0")
        self._cage_now(in_info)
        hm, _ = self._resolve(in_info, img)
        return self._volume(hm, geo, self._outside)

    def _cage_now(self, in_info) -> None:
        """Bring the port-1 cage up to date.

        The map is needed in the information pass, before the pipeline has run the cage's
        producer.
        """
        if self.GetNumberOfInputConnections(1):
            pd = vtkPolyData.GetData(in_info[1])
            if pd is None or pd.GetNumberOfPoints() == 0:
                self.GetInputAlgorithm(1, 0).UpdatePiece(0, 1, 0)

    def _information(self, in_info, out_info):
        if self._spacing is not None and (self._explicit is not None or self._mode == "input"):
            given = "the reference grid" if self._explicit is not None else "the input grid"
            raise ValueError(
                "an output spacing applies to the grid that holds the deformed volume "
                f"(output mode 'deformed'); {given} has its own spacing"
            )
        img = vtkImageData.GetData(in_info[0], 0)
        if self._mpi():
            geo = self._share_lattice(in_info, img)
            return self._set_output_information(geo, out_info)
        vol = self._engine(in_info, img)
        if self._explicit is not None:
            geo = self._explicit
        elif self._mode == "input":
            geo = vol.geometry
        else:
            vol.build(progress=self._progress(0.0, 0.5), abort=self._aborted)
            geo = vol.output_geometry(self._spacing)
        return self._set_output_information(geo, out_info)

    def _set_output_information(self, geo, out_info):
        self._geometry = geo
        out = out_info.GetInformationObject(0)
        nx, ny, nz = geo.dimensions
        out.Set(_SDDP.WHOLE_EXTENT(), 0, nx - 1, 0, ny - 1, 0, nz - 1)
        out.Set(vtkImageData.ORIGIN(), *geo.origin)
        out.Set(vtkImageData.SPACING(), *geo.spacing)
        out.Set(vtkImageData.DIRECTION(), tuple(geo.direction.ravel()), 9)
        out.Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
        return 1

    def RequestUpdateExtent(self, request, in_info, out_info):
        """The input window the output piece's pre-images reach, and the whole cage."""
        self._request_whole_cage(in_info)
        return self._guard(self._request_window, in_info, out_info)

    def _request_window(self, in_info, out_info):
        info0 = in_info[0].GetInformationObject(0)
        whole = info0.Get(_SDDP.WHOLE_EXTENT())
        if whole is None:
            return 1
        out = out_info.GetInformationObject(0)
        ext = requested_extent(out)
        window = None
        if self._mpi():
            # the planes this rank pulls back (for whichever rank's piece holds them), not
            # its own piece; nothing if the information pass failed (RequestData says so)
            shared = self._shared
            box = None if shared is None else _work_box(shared, mpi.rank())
            if box is not None:
                window = window_of(
                    shared["table"], box, shared["input"], self._geometry,
                    interpolation=self._interpolation, margin=shared["margin"],
                    in_place=self._outside == "passthrough" and shared["any_outside"],
                )  # fmt: skip
        elif self._geometry is not None and ext is not None and ext[0] <= ext[1]:
            vol = self._engine(in_info, vtkImageData.GetData(in_info[0], 0))
            window = vol.input_window(self._geometry, ext, self._interpolation)
        if window is None:  # nothing to read: one voxel (an empty extent confuses readers)
            window = [0, 0, 0, 0, 0, 0]
        start = whole[0::2]
        info0.Set(_SDDP.UPDATE_EXTENT(), *[int(window[a]) + start[a // 2] for a in range(6)])
        # the window is the request: not the output's piece number, which a reader would
        # turn into its own extent
        info0.Set(_SDDP.UPDATE_PIECE_NUMBER(), 0)
        info0.Set(_SDDP.UPDATE_NUMBER_OF_PIECES(), 1)
        return 1

    def _forget_output(self) -> None:
        super()._forget_output()
        self.fold_voxels = None

    def _execute(self, in_info, out_info):
        if self._geometry is None:  # the information pass failed: its error is the reason
            raise self._information_error or RuntimeError("no output grid: no information pass")
        img = vtkImageData.GetData(in_info[0], 0)
        out = vtkImageData.GetData(out_info, 0)
        info = out_info.GetInformationObject(0)
        geo = self._geometry
        ext = info.Get(_SDDP.UPDATE_EXTENT())
        if ext is None:
            ext = info.Get(_SDDP.WHOLE_EXTENT())
        out.SetExtent(ext)
        out.SetOrigin(*geo.origin)
        out.SetSpacing(*geo.spacing)
        out.SetDirectionMatrix(*geo.direction.ravel())
        whole = in_info[0].GetInformationObject(0).Get(_SDDP.WHOLE_EXTENT())
        have = img.GetExtent()
        input_box = [have[a] - whole[a - a % 2] for a in range(6)]
        pd_in, pd_out = img.GetPointData(), out.GetPointData()
        scalars = pd_in.GetScalars().GetName() if pd_in.GetScalars() is not None else None
        arrays, types = {}, {}
        for name, arr in resampled_arrays(img).items():
            arrays[name] = ns.vtk_to_numpy(arr)
            types[name] = arr.GetDataType()
        options = dict(interpolation=self._interpolation, fill_value=self._fill,
                       input_box=input_box, displacement=self._field,
                       abort=self._aborted)  # fmt: skip
        if self._mpi():
            vol, res, pulled = self._resample_shared(in_info, img, ext, arrays, options)
        else:
            vol = self._engine(in_info, img)
            res = vol.resample(arrays, geo, box=ext, progress=self._progress(0.0, 0.98),
                               **options)  # fmt: skip
            pulled = res.counts["voxels"]
        self.stats = {**res.counts, "pulled_back": int(pulled)}
        counts = {**self._report_folds(res, ext), "pulled_back": int(pulled)}
        add_lattice_counts(out, vol)
        for name, values in res.arrays.items():
            new = ns.numpy_to_vtk(values, deep=0, array_type=types[name])
            new.SetName(name)
            pd_out.AddArray(new)
            if name == scalars:
                pd_out.SetActiveScalars(name)
        own = [("vtkValidPointMask", res.valid), ("vhm_foldover", res.foldover)]
        if self._field:
            own.append((FIELD_ARRAY, res.displacement))
        for name, values in own:
            new = ns.numpy_to_vtk(values, deep=0)
            new.SetName(name)
            pd_out.AddArray(new)
        for name, key in (("valid_count", "valid"), ("foldover_count", "foldover"),
                          ("pulled_back_voxels", "pulled_back")):  # fmt: skip
            set_field_counts(out, f"vhm_{name}", [counts[key]])
        self.UpdateProgress(1.0)
        return 1

    def _report_folds(self, res: Resampled, ext) -> dict:
        """Count and place the output's voxels in folds; say so if there are any.

        Under MPI, of the whole output (collective), agreed by every rank: each voxel is
        counted by the first rank whose piece holds it (neighbouring pieces share a plane).
        Returns the counts of the field arrays: ``valid`` and ``foldover`` voxels of the
        output (under MPI the whole output's; else this update's piece's).
        """
        if not self._mpi():
            folds = fold_voxels(res.foldover, res.geometry)
            valid = res.counts["valid"]
        else:
            ext = np.asarray(ext, dtype=np.int64)
            pieces = mpi.gather_rows_of(lambda: ext[None, :].astype(np.float64), 6)

            def mine():  # (an error here stops every rank at the gather, not a hang)
                before = pieces[: mpi.rank()].astype(np.int64)
                part = fold_voxels(_unshared(res.foldover, ext, before), res.geometry)
                valid = np.count_nonzero(_unshared(res.valid, ext, before))
                return np.concatenate([[part["count"], valid], part["lo"], part["hi"]])[None, :]

            rows = mpi.gather_rows_of(mine, 8)
            folds = merge_fold_voxels(
                {"count": r[0], "voxels": 0, "lo": r[2:5], "hi": r[5:8]} for r in rows
            )
            folds["voxels"] = self._geometry.n_points
            valid = int(rows[:, 1].sum())
        self.fold_voxels = folds
        text = fold_voxels_text(folds)
        if text is not None:
            self._output_warnings = [FOLDS + text]
            self._say_warning(FOLDS + text, FoldWarning)
        return {"valid": int(valid), "foldover": folds["count"]}

    # ------------------------------------------------------------------ MPI ranks
    def _share_lattice(self, in_info, img) -> ImageGeometry:
        """The information pass under MPI: build this rank's window, agree on the output.

        Collective (the build and two gathers); returns the output grid.
        """
        geo_in = information_geometry(in_info[0].GetInformationObject(0))
        if img is None or geo_in is None:
            raise ValueError("HarmonicResampleFilter needs vtkImageData on input port 0")
        self._cage_now(in_info)
        hm, _ = self._resolve(in_info, img)
        vol, own = self._window_engine(hm, geo_in)
        key = (self._volumes.key, self._outside, self._mode, self._spacing,
               None if self._explicit is None else self._explicit.key())  # fmt: skip
        if self._shared is not None and self._shared["key"] == key:
            return self._shared["geometry"]

        def bounds():
            lo, hi, outside = vol.image_bounds()
            margin = float(vol.lattice.margins()[own(vol.lattice)].max(initial=0.0))
            return np.concatenate([lo, hi, [float(outside), margin]])

        vol.build(progress=self._progress(0.0, 0.5), abort=self._aborted)
        rows = mpi.gather_rows_of(bounds, 8)
        lo, hi = rows[:, 0:3].min(axis=0), rows[:, 3:6].max(axis=0)
        # (with the "error" policy each piece refuses outside voxels when resampled)
        any_outside = bool(rows[:, 6].max() > 0)
        if self._explicit is not None:
            geo = self._explicit
        elif self._mode == "input":
            geo = geo_in
        else:
            keep = self._outside == "passthrough" and any_outside
            geo = output_grid(geo_in, lo, hi, spacing=self._spacing, keep_input=keep)
        table = mpi.gather_rows_of(lambda: vol.reach_table(geo, own(vol.lattice)), 12)
        table = table.astype(np.int64)
        # which output planes each rank pulls back: shares of the work and of the leaves,
        # whichever pieces the pipeline asks for (they need not hold equal work)
        nz = int(geo.dimensions[2])

        def counts():
            mine = own(vol.lattice)
            return np.concatenate([vol.pull_back_pairs(geo, mine),
                                   *vol.pull_back_spans(geo, mine),
                                   [vol.lattice.stats["evaluations"]]])[None, :]  # fmt: skip

        summed = mpi.gather_rows_of(counts, 3 * nz + 1).sum(axis=0)
        pairs, *spans = summed[:-1].reshape(3, nz)
        # each rank's even share of the build counts in its time: the cuts lean on the
        # leaves, most of its memory (the build may be more work than the pull-back).
        # The ranks' counts include the halo points each needed from the others: a few
        # percent over the distinct evaluations, the work the constant prices
        # (LatticeExchange.distinct would add up the builds again if a rank rebuilt)
        build = lattice_build_work(summed[-1], len(hm.cage.vertices) + len(hm.cage.faces))
        cuts = pull_back_shares(pairs, geo, mpi.process_count(), spans, build)
        self._shared = {"key": key, "geometry": geo, "input": geo_in, "table": table,
                        "any_outside": any_outside, "margin": float(rows[:, 7].max()),
                        "cuts": cuts}  # fmt: skip
        self._piece_engine = self._piece_key = None
        return geo

    def _window_engine(self, hm, geo_in):
        """The engine of this rank's window, and which of its leaves are its own (not the halo)."""
        root = VolumeDeformation(hm, geo_in).root
        last_k = geo_in.dimensions[2] - 1
        # this rank's root k-layers: a share of the work, not of the layers (the cage
        # holds more of the volume in some layers than in others)
        cuts = layer_shares(geo_in, hm.cage, root, mpi.process_count())
        me = mpi.rank()
        first, final = int(cuts[me]), int(cuts[me + 1]) - 1
        nx, ny, _ = geo_in.dimensions
        if final < first:  # more ranks than layers: no cells, a share of the evaluations
            window = [0, -1, 0, -1, 0, -1]
        else:
            # its voxels and _HALO more on each side: the single-voxel cells' twists read
            # the neighbours there (the root cells around are built, but refined only
            # where they hold a voxel of the window)
            window = [0, nx - 1, 0, ny - 1, max(first * root - _HALO, 0),
                      min((final + 1) * root - 1 + _HALO, last_k)]  # fmt: skip
        vol = self._volume(hm, geo_in, self._outside, window=window, pre_images=True)

        def own(lattice):
            per_layer = int(lattice.n_root[0] * lattice.n_root[1])
            layer = lattice.root_keys() // per_layer
            return np.nonzero((layer >= first) & (layer <= final))[0]

        return vol, own

    def _piece(self, in_info, img, ext):
        """The engine that pulls back this rank's planes, and each rank's box of them.

        Collective: the ranks gather their pieces; unless every rank still has its
        engine, each rank (re)builds its window if need be and sends every other rank
        the leaves of its own root cells whose images reach that rank's boxes. Returns
        ``(engine or None, boxes)``: ``boxes[q]``, the part of rank ``q``'s piece among
        this rank's planes (None if empty).
        """
        shared = self._shared
        ext = np.asarray(ext, dtype=np.int64)
        piece_key = None if shared is None else (shared["key"], tuple(ext.tolist()))
        have = self._piece_engine is not None and self._piece_key == piece_key
        if mpi.all_ranks(have):
            return self._piece_engine
        self._piece_engine = self._piece_key = None
        found = {}

        def window_engine():
            if shared is None:
                raise RuntimeError("the information pass did not run on this rank")
            hm, _ = self._resolve(in_info, img)
            found["vol"], found["own"] = self._window_engine(hm, shared["input"])
            return ext

        pieces = mpi.gather_rows_of(window_engine, 6).astype(np.int64)
        vol, own = found["vol"], found["own"]
        n = len(pieces)
        # boxes[r][q]: what rank r pulls back for rank q
        boxes = [[_meet(_work_box(shared, r), pieces[q]) for q in range(n)] for r in range(n)]

        def leaves_for_each_rank():
            lat = vol.lattice  # (built again if an earlier piece dropped it)
            leaves = own(lat)
            lo, hi = vol.candidate_boxes(shared["geometry"])
            lo, hi = lo[leaves], hi[leaves]
            found["leaves"] = []
            for r in range(n):
                hit = np.zeros(len(leaves), dtype=bool)
                for b in boxes[r]:
                    if b is not None:
                        hit |= np.all((lo <= b[1::2]) & (hi >= b[0::2]), axis=1)
                found["leaves"].append(leaves[hit])
            return np.zeros((0, 1))

        mpi.gather_rows_of(leaves_for_each_rank, 1)
        stats = dict(vol.lattice.stats)
        leaves = found.pop("leaves")

        me = mpi.rank()
        # the window's lattice now only hands out its leaves: the engine lets go of it
        # (it is built again if ever needed) and its masks go before any part is made
        lat = vol.lattice
        vol.drop_lattice()
        lat.release_masks()

        def part_for(q):
            if q != me:  # its rows copied straight into the send buffer
                return lat.part(leaves[q], copy=False)
            # the last part (send_parts makes this rank's own after packing the others',
            # before receiving any): taken out of the lattice's own arrays, this rank's
            # boxes then need only their own
            return lat.part(leaves[q], release=True)

        got = mpi.send_parts(part_for, PART_FIELDS)
        lat = None  # (what the own part left of it)
        release_free_memory()
        joined = join_parts(got, vol.map, vol.geometry, tolerance=self._tolerance,
                            root=vol.root, stats=stats)  # fmt: skip
        del got
        release_free_memory()
        mine = [b for b in boxes[me] if b is not None]
        engine = None
        if mine:
            hull = np.empty(6, dtype=np.int64)
            hull[0::2] = np.min([b[0::2] for b in mine], axis=0)
            hull[1::2] = np.max([b[1::2] for b in mine], axis=0)
            engine = VolumeDeformation.for_piece(
                vol.map, vol.geometry, joined, shared["geometry"], hull,
                any_outside=shared["any_outside"], tolerance=self._tolerance,
                outside=self._outside, memory_budget=vol.memory_budget,
                exchange=vol.exchange,
            )  # fmt: skip
        self._piece_engine = (engine if engine is not None else vol, boxes)
        self._piece_key = piece_key
        return self._piece_engine

    def _resample_shared(self, in_info, img, ext, arrays: dict, options: dict):
        """The output piece of this rank under MPI, pulled back by the ranks in shares of work.

        Each rank pulls back its planes (:func:`~vhm_viz.core.volume.pull_back_shares`):
        first those of the other ranks' pieces, which it sends them, then those of its
        own piece, straight into the output arrays. A rank pulls back planes of another's
        piece where the cuts hand it that piece's denser planes: their slabs, the
        largest, come before its own piece is filled, which lowers the rank's peak.
        Collective. Returns
        ``(engine, result, voxels this rank pulled back)``.
        """
        vol, boxes = self._piece(in_info, img, ext)
        geo = self._geometry
        me, n = mpi.rank(), len(boxes)
        ext = np.asarray(ext, dtype=np.int64)
        empty = bool((ext[1::2] < ext[0::2]).any())
        voxels = 0 if empty else _voxels(ext)
        comps = {name: a.shape[1:] if a.ndim > 1 else () for name, a in arrays.items()}
        piece = Resampled(
            None if empty else geo.sub(ext),
            {name: np.empty((voxels,) + comps[name], dtype=a.dtype) for name, a in arrays.items()},
            np.zeros(voxels, dtype=np.uint8),
            np.zeros(voxels, dtype=np.uint8),
            displacement=np.empty((voxels, 3)) if self._field else None,
        )  # fmt: skip
        fields = {"counts": ((4,), np.int64), "valid": ((), np.uint8),
                  "foldover": ((), np.uint8)}  # fmt: skip
        if self._field:
            fields["displacement"] = ((3,), np.float64)
        fields.update({"array " + name: (comps[name], a.dtype) for name, a in arrays.items()})
        keys = ("voxels", "valid", "identity", "foldover")
        counts = np.zeros(4, dtype=np.int64)
        outgoing = [None] * n
        order = [q for q in range(n) if q != me] + [me]
        total = sum(_voxels(b) for b in boxes[me] if b is not None) or 1
        done = 0

        def pull_back():
            nonlocal done
            for q in order:
                b = boxes[me][q]
                if b is None:
                    continue
                progress = self._progress(0.95 * done / total, 0.95 * (done + _voxels(b)) / total)
                if q == me:
                    res = vol.resample(arrays, geo, box=b, out=_rows_of(piece, ext, b),
                                       progress=progress, **options)  # fmt: skip
                    counts[:] += [res.counts[k] for k in keys]
                else:
                    res = vol.resample(arrays, geo, box=b, progress=progress, **options)
                    part = {"array " + name: v for name, v in res.arrays.items()}
                    part.update(valid=res.valid, foldover=res.foldover,
                                counts=np.array([[res.counts[k] for k in keys]]))  # fmt: skip
                    if self._field:
                        part["displacement"] = res.displacement
                    outgoing[q] = part
                done += _voxels(b)
            return np.zeros((0, 1))

        # every rank pulls back before any sends: an error on one stops them all here
        mpi.gather_rows_of(pull_back, 1)
        nothing = {name: np.zeros((0,) + shape, dtype=dtype)
                   for name, (shape, dtype) in fields.items()}  # fmt: skip

        def part_for(q):
            part, outgoing[q] = outgoing[q], None
            return nothing if part is None else part

        for r, part in enumerate(mpi.send_parts(part_for, fields)):
            if r == me or boxes[r][me] is None:
                continue
            rows = _rows_of(piece, ext, boxes[r][me])
            for name in arrays:
                rows.arrays[name][...] = part["array " + name]
            rows.valid[...] = part["valid"]
            rows.foldover[...] = part["foldover"]
            if self._field:
                rows.displacement[...] = part["displacement"]
            counts += part["counts"][0]
        piece.counts = {k: int(c) for k, c in zip(keys, counts, strict=True)}
        return vol, piece, done


def resampled_arrays(image) -> dict:
    """The point arrays of an image that :class:`HarmonicResampleFilter` resamples.

    Every point array but the filter's own (:data:`_OWN_ARRAYS`: an earlier output's
    masks are made again, not resampled), by name (``vtkDataArray``).
    """
    pd = image.GetPointData()
    arrays = {}
    for a in range(pd.GetNumberOfArrays()):
        arr = pd.GetArray(a)
        if arr is not None and arr.GetName() not in _OWN_ARRAYS:
            arrays[arr.GetName()] = arr
    return arrays


def displacement_field_of(image, kind: str = "pullback") -> DisplacementField:
    """The displacement field a VTK image's point arrays hold.

    Parameters
    ----------
    image : vtkImageData or pyvista.ImageData
        With the point arrays :data:`FIELD_ARRAY` (3 components), ``vtkValidPointMask``
        and ``vhm_foldover``: the output of :class:`HarmonicResampleFilter` with
        :meth:`~HarmonicResampleFilter.SetComputeDisplacementField`, or of
        ``mesh.vhm.displacement_field``.
    kind : {"pullback", "forward"}
        What the vectors are.

    Returns
    -------
    DisplacementField
    """
    pd = image.GetPointData()
    arrays = {}
    for name in (FIELD_ARRAY, "vtkValidPointMask", "vhm_foldover"):
        arr = pd.GetArray(name)
        if arr is None:
            raise ValueError(f"the image has no point array {name!r}: not a displacement field")
        arrays[name] = ns.vtk_to_numpy(arr)
    return DisplacementField(
        image_geometry(image),
        np.asarray(arrays[FIELD_ARRAY], dtype=np.float64).reshape(-1, 3),
        np.asarray(arrays["vtkValidPointMask"], dtype=np.uint8),
        np.asarray(arrays["vhm_foldover"], dtype=np.uint8),
        kind,
    )


def _work_box(shared: dict, r: int):
    """The output planes that rank ``r`` pulls back (a box of the whole grid), or None."""
    k0, k1 = int(shared["cuts"][r]), int(shared["cuts"][r + 1]) - 1
    if k1 < k0:
        return None
    nx, ny, _ = shared["geometry"].dimensions
    return np.array([0, nx - 1, 0, ny - 1, k0, k1], dtype=np.int64)


def _meet(a, b):
    """The intersection of two voxel boxes, or None if empty (or either is None)."""
    if a is None or b is None:
        return None
    out = np.empty(6, dtype=np.int64)
    out[0::2] = np.maximum(a[0::2], b[0::2])
    out[1::2] = np.minimum(a[1::2], b[1::2])
    return None if (out[1::2] < out[0::2]).any() else out


def _unshared(mask: np.ndarray, ext, others) -> np.ndarray:
    """``mask`` of the piece ``ext`` without the voxels that the pieces ``others`` hold too."""
    shared = [m for m in (_meet(ext, o) for o in others) if m is not None]
    if not shared:
        return mask
    ext = np.asarray(ext)
    nx, ny, nz = (int(ext[2 * a + 1] - ext[2 * a] + 1) for a in range(3))
    kept = np.array(mask, dtype=np.uint8).reshape(nz, ny, nx)
    for m in shared:
        lo, hi = m[0::2] - ext[0::2], m[1::2] - ext[0::2] + 1
        kept[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]] = 0
    return kept.reshape(-1)


def _voxels(box) -> int:
    return int(np.prod(np.asarray(box)[1::2] - np.asarray(box)[0::2] + 1))


def _rows_of(piece: Resampled, ext, box) -> Resampled:
    """Views of a piece's arrays at the voxels of ``box``: whole rows of its k-planes.

    ``box`` spans the piece's i and j ranges (a run of its planes), so its voxels are
    consecutive in the piece's arrays.
    """
    ext, box = np.asarray(ext), np.asarray(box)
    assert (box[:4] == ext[:4]).all(), "a share of a piece is a run of its whole planes"
    plane = int((ext[1] - ext[0] + 1) * (ext[3] - ext[2] + 1))
    rows = slice(int(box[4] - ext[4]) * plane, int(box[5] - ext[4] + 1) * plane)
    field = None if piece.displacement is None else piece.displacement[rows]
    return Resampled(None, {name: a[rows] for name, a in piece.arrays.items()},
                     piece.valid[rows], piece.foldover[rows], displacement=field)  # fmt: skip
