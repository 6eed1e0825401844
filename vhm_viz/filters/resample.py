"""``HarmonicResampleFilter``: a deformed volume resampled back onto a regular grid."""

from __future__ import annotations

import math

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from vhm_viz.core.inverse import ImageGeometry, forward_lattice, pull_back, trilinear
from vhm_viz.filters._common import DeformationSource

__all__ = ["HarmonicResampleFilter", "image_geometry"]

_SDDP = vtkStreamingDemandDrivenPipeline
_MODES = ("deformed", "input")


def image_geometry(img, extent=None) -> ImageGeometry:
    """:class:`ImageGeometry` of a ``vtkImageData`` (or of one of its sub-extents)."""
    ext = img.GetExtent() if extent is None else extent
    origin = np.asarray(img.GetOrigin(), dtype=np.float64)
    spacing = np.asarray(img.GetSpacing(), dtype=np.float64)
    m = img.GetDirectionMatrix()
    direction = np.array([[m.GetElement(i, j) for j in range(3)] for i in range(3)])
    start = np.array(ext[0::2], dtype=np.float64)
    dims = [ext[2 * a + 1] - ext[2 * a] + 1 for a in range(3)]
    return ImageGeometry(origin + direction @ (start * spacing), spacing, dims, direction)


class HarmonicResampleFilter(DeformationSource):
    """Resample a deformed volume onto a regular grid by pulling voxels back (vtkImageData).

    Each output voxel centre ``y`` is mapped back to its pre-image ``x`` (``f(x) = y``)
    by Newton iterations with the closed-form Jacobian, started from a forward-deformed
    lattice of the input grid; every point array of the input is then sampled at ``x``
    by trilinear interpolation (integer arrays are rounded back to their type). See
    :mod:`vhm_viz.core.inverse`.

    **Fill value.** Voxels without a pre-image -- it would lie outside the cage or
    outside the input volume (extended by half a voxel, where the nearest boundary values
    are used, as ``vtkImageReslice``'s border does), or Newton did not converge -- get
    :meth:`SetFillValue` (default 0, the background of CT/MR data) in every array, and 0
    in the ``uint8`` array ``vtkValidPointMask`` (1 elsewhere), as ``vtkProbeFilter``
    does. Cell data is not resampled.

    **Output grid.** ``"deformed"`` (default): the input spacing, over the bounding box of
    the deformed volume (the part inside the cage); ``"input"``: the input grid itself;
    or set explicitly with :meth:`SetOutputGeometry`. The output honours requested
    sub-extents (pieces); the whole input volume and the whole cage are requested in
    every piece, since a pre-image can be anywhere.

    Input port 0: ``vtkImageData``; port 1: optional cage. The deformation is set as for
    :class:`~vhm_viz.filters.HarmonicDeformationFilter`.
    """

    def __init__(self):
        super().__init__(input_type="vtkImageData", output_type="vtkImageData")
        self._fill = 0.0
        self._mode = "deformed"
        self._explicit = None
        self._tolerance = 1e-3
        self._max_iterations = 30
        self._lattice = None
        self._geometry = None
        #: Newton statistics of the last execution: voxels, valid voxels.
        self.stats: dict = {}

    # ------------------------------------------------------------------ options
    def SetFillValue(self, value: float) -> None:
        """Value of the voxels without a pre-image (default 0)."""
        self._fill = float(value)
        self.Modified()

    def GetFillValue(self) -> float:
        """The fill value."""
        return self._fill

    def SetOutputMode(self, mode: str) -> None:
        """``"deformed"`` (bounding box of the deformed volume) or ``"input"`` (input grid)."""
        if mode not in _MODES:
            raise ValueError(f"output mode must be one of {_MODES}; got {mode!r}")
        self._mode = mode
        self._explicit = None
        self.Modified()

    def SetOutputGeometry(self, origin, spacing, dimensions) -> None:
        """An explicit output grid (axis-aligned)."""
        dims = tuple(int(d) for d in dimensions)
        if len(dims) != 3 or min(dims) < 1:
            raise ValueError(f"dimensions must be three positive integers; got {dimensions}")
        sp = np.asarray(spacing, dtype=np.float64).reshape(3)
        if not (sp > 0).all():
            raise ValueError(f"spacing must be positive; got {spacing}")
        self._explicit = ImageGeometry(origin, sp, dims)
        self.Modified()

    def SetTolerance(self, value: float) -> None:
        """Newton tolerance on ``|f(x) - y|`` as a fraction of the smallest input spacing."""
        self._tolerance = float(value)
        self.Modified()

    def SetMaxIterations(self, value: int) -> None:
        """Newton iteration cap (default 30)."""
        self._max_iterations = int(value)
        self.Modified()

    # ------------------------------------------------------------------ pipeline
    def RequestInformation(self, request, in_info, out_info):
        """Compute the output grid (needs the map: built or solved here if necessary)."""
        return self._guard(self._information, in_info, out_info)

    def _information(self, in_info, out_info):
        info0 = in_info[0].GetInformationObject(0)
        img = vtkImageData.GetData(in_info[0], 0)
        whole = info0.Get(_SDDP.WHOLE_EXTENT())
        if img is None or whole is None:
            raise ValueError("HarmonicResampleFilter needs vtkImageData on input port 0")
        src = image_geometry(img, whole)
        hm, _ = self._resolve(in_info, img)
        self._lattice = forward_lattice(hm, src)
        if self._explicit is not None:
            geo = self._explicit
        elif self._mode == "input":
            geo = ImageGeometry(src.origin, src.spacing, src.dimensions, src.direction)
        else:
            deformed = self._lattice[1]
            if len(deformed) == 0:
                raise ValueError("no input voxel lies inside the cage")
            lo, hi = deformed.min(0), deformed.max(0)
            sp = src.spacing
            dims = [max(1, math.floor((hi[a] - lo[a]) / sp[a] + 1e-9) + 1) for a in range(3)]
            geo = ImageGeometry(lo, sp, dims)
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
        """The whole input volume and the whole cage, whatever the output piece."""
        info0 = in_info[0].GetInformationObject(0)
        whole = info0.Get(_SDDP.WHOLE_EXTENT())
        if whole is not None:
            info0.Set(_SDDP.UPDATE_EXTENT(), *whole)
        self._request_whole_cage(in_info)
        return 1

    def _execute(self, in_info, out_info):
        img = vtkImageData.GetData(in_info[0], 0)
        out = vtkImageData.GetData(out_info, 0)
        info = out_info.GetInformationObject(0)
        hm, _ = self._resolve(in_info, img)
        src = image_geometry(img)
        geo = self._geometry
        ext = info.Get(_SDDP.UPDATE_EXTENT())
        if ext is None:
            ext = info.Get(_SDDP.WHOLE_EXTENT())
        out.SetExtent(ext)
        out.SetOrigin(*geo.origin)
        out.SetSpacing(*geo.spacing)
        out.SetDirectionMatrix(*geo.direction.ravel())
        sub = image_geometry(out, ext)
        y = sub.points()
        tol = self._tolerance * float(np.min(src.spacing))
        x, valid = pull_back(
            hm,
            src,
            y,
            tolerance=tol,
            max_iterations=self._max_iterations,
            progress=self._progress(0.05, 0.9),
            abort=self._aborted,
            lattice=self._lattice,
        )
        self.stats = {"voxels": len(y), "valid": int(valid.sum())}
        pd_in, pd_out = img.GetPointData(), out.GetPointData()
        xs = x[valid]
        scalars_name = pd_in.GetScalars().GetName() if pd_in.GetScalars() is not None else None
        for a in range(pd_in.GetNumberOfArrays()):
            arr = pd_in.GetArray(a)
            if arr is None or arr.GetName() == "vtkValidPointMask":
                continue
            vals = ns.vtk_to_numpy(arr)
            comps = arr.GetNumberOfComponents()
            res = np.full((len(y), comps) if comps > 1 else len(y), self._fill, dtype=np.float64)
            if xs.size:
                res[valid] = trilinear(vals, src, xs, self._fill)
            if np.issubdtype(vals.dtype, np.integer):
                info_t = np.iinfo(vals.dtype)
                res = np.clip(np.rint(res), info_t.min, info_t.max)
            res = res.astype(vals.dtype)
            new = ns.numpy_to_vtk(np.ascontiguousarray(res), deep=1, array_type=arr.GetDataType())
            new.SetName(arr.GetName())
            pd_out.AddArray(new)
            if arr.GetName() == scalars_name:
                pd_out.SetActiveScalars(arr.GetName())
        mask = ns.numpy_to_vtk(valid.astype(np.uint8), deep=1)
        mask.SetName("vtkValidPointMask")
        pd_out.AddArray(mask)
        self.UpdateProgress(1.0)
        return 1
