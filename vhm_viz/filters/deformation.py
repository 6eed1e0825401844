"""``HarmonicDeformationFilter``: deform any vtkDataSet with a variational harmonic map."""

from __future__ import annotations

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonCore import VTK_UNSIGNED_CHAR, vtkPoints
from vtkmodules.vtkCommonDataModel import (
    vtkCellArray,
    vtkDataObject,
    vtkDataSet,
    vtkPolyData,
    vtkStructuredGrid,
    vtkUnstructuredGrid,
)
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from vhm_viz.core.binding import cofactor_normals
from vhm_viz.core.errors import FoldWarning
from vhm_viz.core.fold_voxels import (
    FOLDS,
    inverted_cells,
    inverted_cells_text,
    merge_inverted_cells,
)
from vhm_viz.core.metrics import condition_number, jacobian_determinant
from vhm_viz.filters import mpi
from vhm_viz.filters._common import DeformationSource
from vhm_viz.filters._vtk import (
    add_lattice_counts,
    image_geometry,
    numpy_points,
    own_extent,
    requested_extent,
    set_field_counts,
)
from vhm_viz.filters.cells import (
    add_cell_arrays,
    cell_centres,
    cell_quality,
    cells_touching,
    own_cells,
)
from vhm_viz.io import cell_types

__all__ = ["HarmonicDeformationFilter", "output_type_for"]

_SDDP = vtkStreamingDemandDrivenPipeline

#: Output class per input class (as vtkWarpVector).
_OUTPUT_TYPES = {
    "vtkPolyData": "vtkPolyData",
    "vtkUnstructuredGrid": "vtkUnstructuredGrid",
    "vtkStructuredGrid": "vtkStructuredGrid",
    "vtkImageData": "vtkStructuredGrid",
    "vtkStructuredPoints": "vtkStructuredGrid",
    "vtkUniformGrid": "vtkStructuredGrid",
    "vtkRectilinearGrid": "vtkStructuredGrid",
}


def output_type_for(input_class: str) -> str:
    """VTK class name of the filter's output for an input of class ``input_class``.

    PolyData, UnstructuredGrid and StructuredGrid keep their type; ImageData and
    RectilinearGrid become StructuredGrid (their points move off the lattice). Other point
    sets keep their type.
    """
    return _OUTPUT_TYPES.get(input_class, input_class)


def _new_output(inp):
    name = output_type_for(inp.GetClassName())
    if name == "vtkStructuredGrid":
        return vtkStructuredGrid()
    if name == "vtkPolyData":
        return vtkPolyData()
    if name == "vtkUnstructuredGrid":
        return vtkUnstructuredGrid()
    if inp.IsA("vtkPointSet"):
        return inp.NewInstance()
    raise TypeError(f"HarmonicDeformationFilter cannot deform a {inp.GetClassName()}")


def _as_point_set(inp):
    """Image and rectilinear data as a structured grid (VTK's own converters)."""
    # here: importing VTK's filter modules is slow, a resample never comes here
    from vtkmodules.vtkFiltersGeneral import vtkImageDataToPointSet, vtkRectilinearGridToPointSet

    if inp.IsA("vtkImageData"):
        conv = vtkImageDataToPointSet()
    elif inp.IsA("vtkRectilinearGrid"):
        conv = vtkRectilinearGridToPointSet()
    else:
        return inp
    conv.SetInputData(inp)
    conv.Update()
    return conv.GetOutput()


def _set_array(
    data, name: str, values: np.ndarray, *, normals: bool = False, copy: bool = True
) -> None:
    # copy=False: ``values`` is this array's own (VTK keeps a reference to it)
    arr = ns.numpy_to_vtk(np.ascontiguousarray(values), deep=1 if copy else 0)
    arr.SetName(name)
    data.RemoveArray(name)
    data.AddArray(arr)
    if normals:
        data.SetNormals(arr)


def _normals_array(data):
    arr = data.GetNormals()
    if arr is None:
        arr = data.GetArray("Normals")
    if arr is None or arr.GetNumberOfComponents() != 3:
        return None
    return arr


class HarmonicDeformationFilter(DeformationSource):
    """Deform any ``vtkDataSet`` through a variational harmonic map (paper eq. 8).

    Input port 0 takes the data (surface, point cloud, tet mesh, structured or image data,
    ``vtkRectilinearGrid``); input port 1 optionally the cage (``vtkPolyData``; see
    :mod:`vhm_viz.filters._common` for how it combines with the deformation set on the
    filter). The deformation is set with :meth:`SetDeformer`, :meth:`SetScene` or
    :meth:`SetHarmonicMap`.

    Output types follow ``vtkWarpVector``: PolyData -> PolyData, UnstructuredGrid ->
    UnstructuredGrid, StructuredGrid -> StructuredGrid, ImageData and RectilinearGrid ->
    StructuredGrid. Point and cell data pass through, except normals: point normals are
    deformed through the Jacobian, ``n' = cof(J) n`` normalised (paper eq. 6), and cell
    normals likewise with the Jacobian at the rest cell centre. Optional point arrays:
    ``displacement`` (vectors), ``jacobian_determinant``, ``condition_number``; optional
    cell arrays (:meth:`SetComputeCellQuality`, datasets with 3D cells): the quality of the
    deformed cells, as :class:`~vhm_viz.filters.JacobianAnalysisFilter` writes it. With the
    ``"passthrough"`` outside policy, the ``uint8`` point array ``vhm_outside`` flags the
    points left in place; :attr:`outside_count` counts them (also stored as the field
    array ``vhm_outside_count``). With :meth:`SetCheckFolds` the deformed cells are
    measured and inverted ones said in a :class:`~vhm_viz.core.errors.FoldWarning` (in
    ParaView, in its output window), counted in :attr:`fold_cells`.

    The binding (``F = D_points B``, the expensive part) is cached: it is rebuilt only when
    the input geometry, the cage, the deformer (anchors) or the constraint layout change,
    not when only the targets move (:meth:`UpdateTargets`). :attr:`bind_count` counts the
    rebuilds. ``ProgressEvent`` is fired while binding and evaluating; ``AbortExecute``
    stops the work between chunks.

    Examples
    --------
    >>> f = HarmonicDeformationFilter()  # doctest: +SKIP
    >>> f.SetInputData(mesh); f.SetDeformer(deformer)  # doctest: +SKIP
    >>> deformed = vhm_viz.filters.update(f)  # doctest: +SKIP
    """

    def __init__(self):
        super().__init__(input_type="vtkDataSet", output_type="vtkDataSet")
        self._displacement = False
        self._determinant = False
        self._condition = False
        self._cell_quality = False
        self._deform_normals = True
        self._check_folds = False
        #: :func:`vhm_viz.core.metrics.cell_summary` of the last update (with
        #: :meth:`SetComputeCellQuality` and 3D cells), else None.
        self.cell_summary: dict | None = None
        #: :func:`vhm_viz.core.fold_voxels.inverted_cells` of the last update's output
        #: (with :meth:`SetCheckFolds`; under MPI the whole output's), else None.
        self.fold_cells: dict | None = None
        self._piece_folds: dict | None = None  # this rank's piece's, before they agree

    # ------------------------------------------------------------------ options
    def SetComputeDisplacement(self, value: bool) -> None:
        """Add the point vectors ``displacement = f(p) - p``."""
        self._set_option("_displacement", bool(value))

    def SetComputeJacobianDeterminant(self, value: bool) -> None:
        """Add the point array ``jacobian_determinant`` (``det J``, local volume ratio)."""
        self._set_option("_determinant", bool(value))

    def SetComputeConditionNumber(self, value: bool) -> None:
        """Add the point array ``condition_number`` (``s_max / s_min`` of ``J``)."""
        self._set_option("_condition", bool(value))

    def SetComputeCellQuality(self, value: bool) -> None:
        """Add the cell quality arrays (datasets with 3D cells; see the class notes)."""
        self._set_option("_cell_quality", bool(value))

    def SetDeformNormals(self, value: bool) -> None:
        """Deform point/cell normals through the Jacobian (default True)."""
        self._set_option("_deform_normals", bool(value))

    def SetCheckFolds(self, value: bool) -> None:
        """Measure the deformed cells and say how many are inverted, and where (default off).

        A warped image's voxels by their hexahedra's corner Jacobians, where the volume
        engine's lattice does not prove them unfolded
        (:func:`vhm_viz.folds.inverted_voxel_cells`); other 3D cells by the tetrahedra
        they split into (:func:`~vhm_viz.filters.cell_quality`). Surfaces and point clouds
        have no cells to measure. ``vhm-viz deform`` makes its own check (with the
        continuous map's ``det J`` besides); the ParaView plugin turns this one on.
        """
        self._set_option("_check_folds", bool(value))

    # ------------------------------------------------------------------ pipeline
    def RequestDataObject(self, request, in_info, out_info):
        """Create the output type matching the input (vtkWarpVector's rules)."""
        inp = vtkDataObject.GetData(in_info[0], 0)
        if inp is None:
            return 0
        out = vtkDataObject.GetData(out_info, 0)
        wanted = output_type_for(inp.GetClassName())
        if out is None or out.GetClassName() != wanted:
            try:
                out = _new_output(inp)
            except TypeError as exc:
                self.last_error = exc
                return 0
            out_info.GetInformationObject(0).Set(vtkDataObject.DATA_OBJECT(), out)
        return 1

    # ------------------------------------------------------------------ the work
    def _piece_input(self, inp, in_info, out_info):
        """Structured input delivered whole while a piece is wanted: crop to the piece.

        Sources that stream (readers, ``vtkRTAnalyticSource``) deliver the requested
        extent; a ``vtkTrivialProducer`` delivers the whole data set, which is cropped here
        to the output's update extent (or, without one, to the piece that
        ``vtkExtentTranslator`` assigns in block mode), its ghost layers marked
        (``vtkGhostType``) as a streaming source's executive marks them.
        """
        if inp.GetExtentType() != 1:
            return inp
        whole = in_info[0].GetInformationObject(0).Get(_SDDP.WHOLE_EXTENT())
        have = tuple(inp.GetExtent())
        want = requested_extent(out_info.GetInformationObject(0), whole)
        if want is None or tuple(want) == have:
            return inp
        inside = all(have[2 * a] <= want[2 * a] and want[2 * a + 1] <= have[2 * a + 1]
                     for a in range(3))  # fmt: skip
        if not inside or any(want[2 * a] > want[2 * a + 1] for a in range(3)):
            return inp
        sub = inp.NewInstance()
        sub.ShallowCopy(inp)
        sub.Crop(want)
        own = own_extent(out_info.GetInformationObject(0), whole)
        if own is not None:
            sub.GenerateGhostArray(list(own))
        return sub

    def _execute(self, in_info, out_info):
        inp = vtkDataSet.GetData(in_info[0], 0)
        out = vtkDataObject.GetData(out_info, 0)
        inp = self._piece_input(inp, in_info, out_info)
        if inp.IsA("vtkImageData"):
            return self._execute_image(inp, in_info, out)
        hm, dfm = self._resolve(in_info, inp)
        self.UpdateProgress(0.05)
        src = _as_point_set(inp)
        out.ShallowCopy(src)
        points = numpy_points(src)
        ev = self._bind(hm, dfm, inp, points, 0.05, 0.6)
        deformed = ev.deform()
        self.UpdateProgress(0.65)

        pts = vtkPoints()
        pts.SetData(ns.numpy_to_vtk(np.ascontiguousarray(deformed), deep=1))
        out.SetPoints(pts)
        _boxes_as_hexahedra(out)
        pd, cd = out.GetPointData(), out.GetCellData()
        pnormals = _normals_array(src.GetPointData()) if self._deform_normals else None
        cnormals = _normals_array(src.GetCellData()) if self._deform_normals else None
        need_j = self._determinant or self._condition or pnormals is not None
        if need_j and len(points):
            jac = ev.jacobians(progress=self._progress(0.65, 0.95), abort=self._aborted)
            if pnormals is not None:
                n = ns.vtk_to_numpy(pnormals).reshape(-1, 3)
                _set_array(
                    pd, pnormals.GetName() or "Normals", cofactor_normals(jac, n), normals=True
                )
            if self._determinant:
                _set_array(pd, "jacobian_determinant", jacobian_determinant(jac))
            if self._condition:
                _set_array(pd, "condition_number", condition_number(jac))
        if cnormals is not None and src.GetNumberOfCells():
            centres = _cell_centres(src)
            jc = hm.evaluate(centres, order=1, outside="passthrough")[1]
            n = ns.vtk_to_numpy(cnormals).reshape(-1, 3)
            _set_array(cd, cnormals.GetName() or "Normals", cofactor_normals(jc, n), normals=True)
        self.cell_summary = quality = None
        if self._cell_quality and len(points):
            quality = cell_quality(src, deformed)
            if quality is not None:
                add_cell_arrays(out, quality)
                self.cell_summary = quality["summary"]
        if self._check_folds and len(points):
            if quality is None:
                quality = cell_quality(src, deformed, condition=False)
            if quality is not None:
                self._piece_folds = _mesh_folds(src, quality["determinant"], self._left(ev.outside))
        if self._displacement:
            _set_array(pd, "displacement", deformed - points)
        self._finish(out, ev.outside)
        return 1

    def _finish(self, out, outside: np.ndarray) -> None:
        """The outside flags (``vhm_outside``) and count (field ``vhm_outside_count``).

        Serially, also the fold warning of this output (under MPI, once the ranks agree).
        """
        if self._check_folds and not self._mpi():
            self._say_folds(self._piece_folds)
        if self._outside != "error":
            # uint8 flags are handed over (the image path makes them for this); others
            # are converted into a new array, which is handed over
            flags = np.asarray(outside).astype(np.uint8, copy=False)
            _set_array(out.GetPointData(), "vhm_outside", flags, copy=False)
        set_field_counts(out, "vhm_outside_count", [self.outside_count])
        self.UpdateProgress(1.0)

    def _left(self, outside) -> np.ndarray | None:
        """The flags of points left in place outside the cage (passthrough), else None."""
        if self._outside != "passthrough" or not np.any(outside):
            return None
        return np.asarray(outside)

    def _forget_output(self) -> None:
        super()._forget_output()
        self.fold_cells = None
        self._piece_folds = inverted_cells([], np.zeros((0, 3)), 0)

    def _agree_on_output(self, out_info) -> None:
        """Under MPI: the fold warning of the whole output, said once (collective)."""
        if self._check_folds:
            rows = mpi.gather_rows_of(lambda: _folds_row(self._piece_folds)[None, :], 13)
            self._say_folds(merge_inverted_cells(_folds_of_row(row) for row in rows))

    def _say_folds(self, folds: dict) -> None:
        """Keep the output's inverted cells; say them if there are any."""
        self.fold_cells = folds
        text = inverted_cells_text(folds)
        if text is not None:
            line = f"{FOLDS}{text} (rest positions)"
            self._output_warnings = [line]
            self._say_warning(line, FoldWarning)

    def _execute_image(self, inp, in_info, out):
        """Images: the volume engine's lattice, streamed in slabs, instead of a binding.

        Only this piece's root cells of the lattice are built (aligned with the whole
        grid, so a piece's voxels get the same positions as in the whole volume, to
        rounding): two ranks each build about half of it.
        """
        hm, _ = self._resolve(in_info, inp)
        self.cell_summary = None
        whole = in_info[0].GetInformationObject(0).Get(_SDDP.WHOLE_EXTENT())
        whole = inp.GetExtent() if whole is None else whole
        ext = inp.GetExtent()
        box = [ext[a] - whole[a - a % 2] for a in range(6)]
        geo = image_geometry(inp, whole)
        if any(box[2 * a + 1] < box[2 * a] for a in range(3)):
            # an empty piece (more ranks than planes): nothing to warp, but under MPI the
            # rank still evaluates its share of the others' lattice points
            if self._lattice_exchange() is not None:
                self._volume(hm, geo, self._outside, window=box, pre_images=False).build()
            out.SetExtent(ext)
            if self._check_folds and not self._mpi():
                self._say_folds(self._piece_folds)
            return 1
        # the voxels only are warped: a lattice without pre-images (faster, smaller)
        vol = self._volume(hm, geo, self._outside, window=box, pre_images=False)
        progress, abort = self._progress(0.0, 0.8), self._aborted
        points = vol.warp(box, progress=progress, abort=abort)
        inside = vol.lattice.inside(box).ravel()
        self.outside_count = int(inside.size - np.count_nonzero(inside))
        out.SetExtent(ext)
        pts = vtkPoints()
        pts.SetData(ns.numpy_to_vtk(points, deep=0))  # keeps a reference, no copy
        out.SetPoints(pts)
        out.GetPointData().ShallowCopy(inp.GetPointData())
        out.GetCellData().ShallowCopy(inp.GetCellData())
        pd = out.GetPointData()
        pnormals = _normals_array(inp.GetPointData()) if self._deform_normals else None
        if self._determinant or self._condition or pnormals is not None:
            n = len(points)
            det = np.empty(n) if self._determinant else None
            cond = np.empty(n) if self._condition else None
            normals = np.empty((n, 3)) if pnormals is not None else None
            rest = ns.vtk_to_numpy(pnormals).reshape(-1, 3) if pnormals is not None else None
            slabs = vol.jacobian_slabs(box, progress=self._progress(0.8, 0.95), abort=abort)
            for rows, jac in slabs:
                if det is not None:
                    det[rows] = jacobian_determinant(jac)
                if cond is not None:
                    cond[rows] = condition_number(jac)
                if normals is not None:
                    normals[rows] = cofactor_normals(jac, rest[rows])
            if det is not None:
                _set_array(pd, "jacobian_determinant", det)
            if cond is not None:
                _set_array(pd, "condition_number", cond)
            if normals is not None:
                _set_array(pd, pnormals.GetName() or "Normals", normals, normals=True)
        if self._displacement:
            _set_array(pd, "displacement", points - vol.geometry.sub(box).points())
        if self._cell_quality:  # the voxels as warped (six tets each)
            quality = cell_quality(inp, points)
            if quality is not None:
                add_cell_arrays(out, quality)
                self.cell_summary = quality["summary"]
        if self._check_folds:
            progress = self._progress(0.95, 1.0)
            left = self._left(np.logical_not(inside))
            self._piece_folds = _image_folds(inp, points, vol, box, progress, left)
        add_lattice_counts(out, vol)
        # one array for the flags, not three (each a byte per voxel)
        self._finish(out, np.logical_not(inside, out=np.empty(inside.size, np.uint8)))
        return 1


def _image_folds(piece, points, vol, box, progress, outside=None) -> dict:
    """:func:`inverted_cells` of a warped piece ``box`` of an image (``vol``'s geometry).

    :func:`vhm_viz.folds.warped_voxel_folds`, sparing the cells the lattice proves
    unfolded as the command line's check does (:func:`vhm_viz.folds.proof_sized`). Only
    the ``piece``'s own cells count: a piece requested with ghost levels has layers of
    its neighbours' cells, which they count. ``outside``: (N,) flags of the points left in
    place outside the cage, whose inverted cells straddle it.
    """
    from vhm_viz.folds import proof_sized, warped_voxel_folds

    own = own_cells(piece)
    geometry = vol.geometry.sub(box)
    unproven = vol.unproven_cells(box) if proof_sized(geometry.dimensions) else None
    cells = warped_voxel_folds(geometry, points, progress, None, unproven)
    if cells is None:
        return inverted_cells([], np.zeros((0, 3)), 0)
    bad, det = cells["inverted"], cells["inverted_determinant"]
    measured = cells["summary"]["cells"]
    if not own.all():
        bad, det = bad[own[bad]], det[own[bad]]
        measured -= int(np.count_nonzero(_finite_cells(points, geometry.dimensions) & ~own))
    return inverted_cells(det, cells["centres"](bad), measured, _straddling(piece, bad, outside))


def _finite_cells(points, dims) -> np.ndarray:
    """Which voxel cells of a (``dims``) grid of ``points`` have finite corners: (C,) bool."""
    finite = np.isfinite(points).all(axis=1).reshape(dims[::-1])
    out = finite[:-1, :-1, :-1].copy()
    for c, b, a in np.ndindex(2, 2, 2):
        out &= finite[c : c + dims[2] - 1, b : b + dims[1] - 1, a : a + dims[0] - 1]
    return out.reshape(-1)


def _mesh_folds(rest, determinant, outside=None) -> dict:
    """:func:`inverted_cells` of a deformed mesh's own cells (not its ghost cells).

    ``outside``: (N,) flags of the points left in place outside the cage, if any.
    """
    det = np.asarray(determinant)
    own = own_cells(rest)
    bad = np.flatnonzero((det <= 0) & own)
    measured = int(np.count_nonzero(np.isfinite(det) & own))
    straddling = _straddling(rest, bad, outside)
    return inverted_cells(det[bad], cell_centres(rest, bad), measured, straddling)


def _straddling(data, cells, outside) -> int:
    """How many of ``data``'s ``cells`` have a point flagged in ``outside`` (or None)."""
    if outside is None:
        return 0
    return int(np.count_nonzero(cells_touching(data, cells, outside)))


def _folds_row(folds) -> np.ndarray:
    """An :func:`inverted_cells` summary as 13 numbers, to gather over MPI ranks."""
    head = [folds["count"], folds["cells"], folds["worst"]]
    tail = [folds["straddling"]]
    return np.concatenate([head, folds["at"], folds["lo"], folds["hi"], tail]).astype(np.float64)


def _folds_of_row(row) -> dict:
    """The summary of a :func:`_folds_row`."""
    return {"count": int(row[0]), "cells": int(row[1]), "worst": float(row[2]),
            "at": row[3:6], "lo": row[6:9], "hi": row[9:12],
            "straddling": int(row[12])}  # fmt: skip


#: VTK's axis-aligned cells and the general cells that take them over once moved, with
#: the corner order of the general cell (a voxel's and pixel's corners run in lattice
#: order, a hexahedron's and quad's around each face).
_BOX_CELLS = {11: (12, np.array([0, 1, 3, 2, 4, 5, 7, 6])), 8: (9, np.array([0, 1, 3, 2]))}


def _boxes_as_hexahedra(out) -> None:
    """Voxel and pixel cells of an unstructured grid become hexahedra and quads.

    A voxel (pixel) cell stands for an axis-aligned box (rectangle): VTK takes its
    volume, contains-tests and interpolation from that box, which its deformed points no
    longer are. The cell arrays are shared with the input: new ones replace them.
    """
    if not out.IsA("vtkUnstructuredGrid") or not out.GetNumberOfCells():
        return
    types = cell_types(out)
    if not np.isin(types, list(_BOX_CELLS)).any():
        return
    cells = out.GetCells()
    conn = ns.vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64)  # a copy
    offsets = ns.vtk_to_numpy(cells.GetOffsetsArray()).astype(np.int64)
    types = types.astype(np.uint8)  # a copy
    for box, (general, order) in _BOX_CELLS.items():
        which = np.flatnonzero(types == box)
        if which.size:
            ids = offsets[which][:, None] + np.arange(len(order))
            conn[ids] = conn[ids[:, order]]
            types[which] = general
    new = vtkCellArray()
    new.SetData(
        ns.numpy_to_vtkIdTypeArray(offsets, deep=1), ns.numpy_to_vtkIdTypeArray(conn, deep=1)
    )
    out.SetCells(ns.numpy_to_vtk(types, deep=1, array_type=VTK_UNSIGNED_CHAR), new)


def _cell_centres(ds) -> np.ndarray:
    from vtkmodules.vtkFiltersCore import vtkCellCenters  # here: importing it is slow

    cc = vtkCellCenters()
    cc.SetInputData(ds)
    cc.VertexCellsOff()
    cc.CopyArraysOff()
    cc.Update()
    return numpy_points(cc.GetOutput())
