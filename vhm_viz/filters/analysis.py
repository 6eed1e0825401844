"""``JacobianAnalysisFilter``: per-point quality of a deformation, from the closed form."""

from __future__ import annotations

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkDataSet
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

from vhm_viz.core.metrics import jacobian_measures
from vhm_viz.filters import mpi
from vhm_viz.filters._common import DeformationSource
from vhm_viz.filters._vtk import image_geometry, numpy_points
from vhm_viz.filters.cells import add_cell_arrays, cell_quality, own_cell_counts, set_cell_counts

__all__ = ["JacobianAnalysisFilter", "ANALYSIS_ARRAYS"]

#: Point arrays added by :class:`JacobianAnalysisFilter`.
ANALYSIS_ARRAYS = ("jacobian_determinant", "condition_number", "rotation_angle", "foldover")


def _add(data, name, values):
    arr = ns.numpy_to_vtk(np.ascontiguousarray(values), deep=1)
    arr.SetName(name)
    data.RemoveArray(name)
    data.AddArray(arr)


class JacobianAnalysisFilter(DeformationSource):
    """Add Jacobian quality arrays to any dataset, at its (rest) points.

    The Jacobian ``J = df/dx`` of the map is evaluated in closed form at the input points
    (no finite differences); the output is the input (same type, same points) with the
    point arrays

    * ``jacobian_determinant`` -- ``det J`` (local volume ratio, 1 for no change);
    * ``condition_number`` -- ``s_max / s_min`` (1 for a similarity);
    * ``rotation_angle`` -- angle of the rotation of the polar decomposition, in degrees;
    * ``foldover`` -- ``uint8``, 1 where ``det J <= 0``;

    plus ``vhm_outside`` with the ``"passthrough"`` outside policy (those points get
    ``J = I``). The values equal :func:`vhm_viz.metrics.jacobian_measures` of
    ``HarmonicMap.jacobian`` at the same points. The deformation and the cage (port 1)
    are set as for :class:`~vhm_viz.filters.HarmonicDeformationFilter`.

    Datasets with 3D cells (tet meshes, any cells VTK splits into tets, volumes) also get
    the quality of the cells the deformation returns, from the deformed vertex positions
    (:func:`vhm_viz.core.metrics.cell_measures`): the cell arrays
    ``cell_jacobian_determinant`` (volume ratio of the cell's linear tets, the smallest
    over them), ``cell_condition_number`` (the largest), ``cell_inverted`` (``uint8``, 1
    where the determinant is ``<= 0``) and ``cell_rest_inverted`` (``uint8``, cells stored
    inverted at rest: not blamed on the deformation), with the counts in the field arrays
    ``vhm_cells_inverted`` and ``vhm_cells_rest_inverted``. :attr:`cell_summary` holds all
    the counts of the last update (None without 3D cells).

    Images of more than :data:`~vhm_viz.core.volume.EXACT_VOXELS` voxels take their
    Jacobians from the volume engine's lattice (:mod:`vhm_viz.core.volume`, tolerance
    :meth:`SetTolerance`), slab by slab, instead of an exact evaluation per voxel.
    """

    def __init__(self):
        super().__init__(input_type="vtkDataSet", output_type="vtkDataSet")
        #: :func:`vhm_viz.core.metrics.cell_summary` of the last update, or None.
        self.cell_summary: dict | None = None

    def RequestDataObject(self, request, in_info, out_info):
        """The output has the input's type."""
        inp = vtkDataObject.GetData(in_info[0], 0)
        if inp is None:
            return 0
        out = vtkDataObject.GetData(out_info, 0)
        if out is None or out.GetClassName() != inp.GetClassName():
            out_info.GetInformationObject(0).Set(vtkDataObject.DATA_OBJECT(), inp.NewInstance())
        return 1

    def _agree_on_output(self, out_info) -> None:
        """Under MPI, the cell counts' field arrays of the whole output.

        ``vhm_cells_inverted`` and ``vhm_cells_rest_inverted``: every rank's own cells
        (not its ghost cells, another rank's) summed.
        """
        out = vtkDataObject.GetData(out_info, 0)
        rows = mpi.gather_rows_of(lambda: own_cell_counts(out)[None, :], 3)
        if rows[:, 2].any():  # some rank has 3D cells: each says the whole output's counts
            set_cell_counts(out, int(rows[:, 0].sum()), int(rows[:, 1].sum()))

    def _execute(self, in_info, out_info):
        inp = vtkDataSet.GetData(in_info[0], 0)
        out = vtkDataObject.GetData(out_info, 0)
        hm, dfm = self._resolve(in_info, inp)
        out.ShallowCopy(inp)
        if inp.IsA("vtkImageData"):
            return self._execute_image(in_info, inp, hm, out)
        pts = numpy_points(inp)
        ev = self._bind(hm, dfm, inp, pts, 0.0, 0.5)
        jac = ev.jacobians(progress=self._progress(0.5, 0.9), abort=self._aborted)
        pd = out.GetPointData()
        if len(pts):
            m = jacobian_measures(jac)
            _add(pd, "jacobian_determinant", m["determinant"])
            _add(pd, "condition_number", m["condition_number"])
            _add(pd, "rotation_angle", np.degrees(m["rotation_angle"]))
            _add(pd, "foldover", (m["determinant"] <= 0).astype(np.uint8))
        if self._outside != "error":
            _add(pd, "vhm_outside", ev.outside.astype(np.uint8))
        self.cell_summary = None
        if len(pts):
            quality = cell_quality(inp, ev.deform())
            if quality is not None:
                add_cell_arrays(out, quality)
                self.cell_summary = quality["summary"]
        self.UpdateProgress(1.0)
        return 1

    def _execute_image(self, in_info, inp, hm, out):
        """Images: the measures of the lattice's Jacobians (this piece's part of it)."""
        info = in_info[0].GetInformationObject(0)
        whole = info.Get(vtkStreamingDemandDrivenPipeline.WHOLE_EXTENT())
        whole = inp.GetExtent() if whole is None else whole
        ext = inp.GetExtent()
        box = [ext[a] - whole[a - a % 2] for a in range(6)]
        geo = image_geometry(inp, whole)
        # Jacobians at the voxels only: a lattice without pre-images (faster, smaller)
        vol = self._volume(hm, geo, self._outside, window=box, pre_images=False)
        m = vol.jacobian_measures(box, progress=self._progress(0.0, 0.95), abort=self._aborted)
        pd = out.GetPointData()
        _add(pd, "jacobian_determinant", m["determinant"])
        _add(pd, "condition_number", m["condition_number"])
        _add(pd, "rotation_angle", np.degrees(m["rotation_angle"]))
        _add(pd, "foldover", m["foldover"].astype(np.uint8))
        if self._outside != "error":
            _add(pd, "vhm_outside", (~vol.lattice.inside(box)).ravel().astype(np.uint8))
        # the voxels as the deformation returns them (six tets each), from the same lattice
        quality = cell_quality(inp, vol.warp(box, abort=self._aborted))
        self.cell_summary = None
        if quality is not None:
            add_cell_arrays(out, quality)
            self.cell_summary = quality["summary"]
        self.UpdateProgress(1.0)
        return 1
