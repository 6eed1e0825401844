"""ParaView plugin: vhm_viz's harmonic deformation, Jacobian analysis and resampling.

This folder ships inside the wheel; ``vhm-viz paraview`` prints its path and the lines that
set up ParaView's Python (from a checkout: ``eval "$(bash plugins/paraview-env.sh)"``, whose
``plugins/vhm_viz_paraview.py`` runs this file). ParaView then loads the plugin from
``PV_PLUGIN_PATH`` (or load it with Tools > Manage Plugins). The filters appear under
Filters > vhm_viz and in ``paraview.simple`` as ``VHMHarmonicDeformation``,
``VHMJacobianAnalysis`` and ``VHMResampleToImage``. The reader "VHM Medical Image Reader"
(``VHMMedicalImageReader``) opens NIfTI, MetaImage, NRRD/NHDR and DICOM series in the
frame :func:`vhm_viz.read_dataset` gives them: ITK's physical (LPS) world, with origin,
spacing and direction as SimpleITK reads them, so a scene made in Python, in the explorer
or in 3D Slicer fits the image in ParaView.

Modelled on meshio's ParaView plugin, this file only declares proxies and properties: each
filter *is* the corresponding :mod:`vhm_viz.filters` algorithm (same pipeline contract:
the whole cage is requested on every rank, pieces and extents are honoured), with
:meth:`SetParallelReporting` on, so that under ``mpiexec`` the ranks agree on errors, every
error is one line in ParaView's output window, and a failed update leaves no stale output.
"""

import os

from paraview.util.vtkAlgorithm import (
    VTKPythonAlgorithmBase,
    smdomain,
    smhint,
    smproperty,
    smproxy,
)
from vtkmodules.vtkCommonCore import vtkOutputWindow

from vhm_viz.filters import (
    HarmonicDeformationFilter,
    HarmonicResampleFilter,
    JacobianAnalysisFilter,
    mpi,
)
from vhm_viz.filters._common import DeformationSource
from vhm_viz.io.dicom import read_series
from vhm_viz.io.errors import first_line
from vhm_viz.io.itk_images import sitk_message

_SCENE_HELP = (
    "A vhm_viz scene (JSON): cage, anchors, constraints, mode, solver settings. Write one "
    "with the vhm_viz explorer, vhm_viz.scene.Scene.save or by hand (see the README). The "
    "file is read again when it changes."
)
_CAGE_HELP = (
    "Optional: the cage as a closed triangle surface. When connected it replaces the "
    "scene's cage (the deformer is rebuilt on it). Every rank receives all of it."
)
_UNCONVERGED_HELP = (
    "Deform even when the scene's solve stops at solver.max_iterations before its "
    "tolerance (a warning says how far it stopped). Off: such an update fails with that "
    "message and leaves no output."
)
_FIELD_HELP = (
    "Add the point array vhm_displacement_field: each output voxel's pull-back "
    "displacement f^-1(y) - y in LPS millimetres, what ITK, ANTs and Slicer apply as a "
    "displacement field."
)
_OUTSIDE_XML = (
    '<IntVectorProperty name="OutsidePolicy" command="SetOutsidePolicyIndex" '
    'number_of_elements="1" default_values="0">'
    '<EnumerationDomain name="enum">'
    '<Entry value="0" text="Error"/><Entry value="1" text="Pass through"/>'
    '<Entry value="2" text="NaN"/></EnumerationDomain>'
    "<Documentation>Points outside the cage: fail naming them (Error), leave them in place "
    "(Pass through) or make them NaN; the last two flag them in the point array "
    "vhm_outside.</Documentation></IntVectorProperty>"
)
_OUTSIDE = ("error", "passthrough", "nan")
_FOLDS_HELP = (
    "Measure the deformed cells (a volume's voxels, a mesh's 3D cells) and say in the output "
    "messages how many are inverted and where (rest positions)."
)
_OPTIONAL_ARRAYS = ("displacement", "jacobian_determinant", "condition_number")


def _filter(name, label, data_type):
    """The proxy declaration: menu entry, Input (of ``data_type``) and optional Cage ports."""

    def declare(cls):
        for decorate in reversed(
            [
                smproxy.filter(name=name, label=label),
                smhint.xml('<ShowInMenu category="vhm_viz" />'),
                smproperty.input(name="Cage", port_index=1),
                smdomain.datatype(dataTypes=["vtkPolyData"], composite_data_supported=False),
                smdomain.xml(f"<Documentation>{_CAGE_HELP}</Documentation>"),
                smproperty.input(name="Input", port_index=0),
                smdomain.datatype(dataTypes=[data_type], composite_data_supported=False),
            ]
        ):
            cls = decorate(cls)
        return cls

    return declare


def _checkbox(name, documentation, default=0):
    """A ParaView checkbox property (off unless ``default``) with its tooltip, for a setter."""

    def declare(setter):
        setter = smdomain.xml(
            f'<BooleanDomain name="bool"/><Documentation>{documentation}</Documentation>'
        )(setter)
        return smproperty.intvector(name=name, default_values=default, number_of_elements=1)(setter)

    return declare


def _scene_and_outside(cls):
    """SceneFile, OutsidePolicy and AllowUnconverged properties on ``cls`` itself
    (ParaView reads only a class's own attributes, so a shared base class cannot carry
    them)."""

    @smproperty.stringvector(name="SceneFile", default_values="", number_of_elements=1)
    @smdomain.filelist()
    @smhint.filechooser(extensions="json", file_description="vhm_viz scene files")
    @smdomain.xml(f"<Documentation>{_SCENE_HELP}</Documentation>")
    def SetSceneFile(self, name):
        DeformationSource.SetSceneFile(self, name)

    @smproperty.xml(_OUTSIDE_XML)
    def SetOutsidePolicyIndex(self, index):
        self.SetOutsidePolicy(_OUTSIDE[int(index)])

    @_checkbox("AllowUnconverged", _UNCONVERGED_HELP)
    def SetAllowUnconvergedFlag(self, value):
        self.SetAllowUnconverged(bool(int(value)))

    cls.SetSceneFile = SetSceneFile
    cls.SetOutsidePolicyIndex = SetOutsidePolicyIndex
    cls.SetAllowUnconvergedFlag = SetAllowUnconvergedFlag
    return cls


def _pass_direction(algorithm, in_info) -> None:
    """Give port 0's information the image direction ParaView's post-filter left out.

    ParaView 5.11 (VTK 9.2) puts a ``vtkPVPostFilter`` after every source; its information
    pass copies an image's extent, origin and spacing but not its direction, which the
    filters need before any data is read (an oblique or radiological scan would be placed
    with the identity). The direction is taken from the source's own output information,
    through post-filters only.
    """
    from vtkmodules.vtkCommonDataModel import vtkDataObject

    key = vtkDataObject.DIRECTION()
    info = (
        in_info[0].GetInformationObject(0) if in_info[0].GetNumberOfInformationObjects() else None
    )
    if info is None or info.Has(key) or algorithm.GetNumberOfInputConnections(0) == 0:
        return
    producer = algorithm.GetInputAlgorithm(0, 0)
    while producer is not None and producer.IsA("vtkPVPostFilter"):
        if producer.GetNumberOfInputConnections(0) == 0:
            return
        upstream = producer.GetInputInformation(0, 0)
        if upstream.Has(key):
            info.Set(key, upstream.Get(key), 9)
            return
        producer = producer.GetInputAlgorithm(0, 0)


class _ParaViewReporting:
    """Errors as one line in ParaView's output window, agreed across MPI ranks."""

    label = ""

    def __init__(self):
        super().__init__()
        self.SetParallelReporting(True)

    def RequestInformation(self, request, in_info, out_info):
        """The filter's information pass, with the input image's direction restored."""
        _pass_direction(self, in_info)
        return super().RequestInformation(request, in_info, out_info)

    def _label(self):
        return self.label


@_filter("VHMHarmonicDeformation", "VHM Harmonic Deformation", "vtkDataSet")
@_scene_and_outside
class VHMHarmonicDeformation(_ParaViewReporting, HarmonicDeformationFilter):
    """Deform any dataset with a scene's variational harmonic map (vtkWarpVector's types)."""

    label = "VHM Harmonic Deformation"

    def __init__(self):
        super().__init__()
        from vtkmodules.vtkCommonCore import vtkDataArraySelection

        # a checklist in ParaView's panel: the optional point arrays, all off by default
        self._arrays = vtkDataArraySelection()
        for name in _OPTIONAL_ARRAYS:
            self._arrays.AddArray(name, False)
        self._arrays.AddObserver("ModifiedEvent", lambda *_: self._apply_array_selection())
        self.SetCheckFolds(True)  # the CheckFolds checkbox's default

    def _apply_array_selection(self):
        on = self._arrays.ArrayIsEnabled
        self.SetComputeDisplacement(bool(on("displacement")))
        self.SetComputeJacobianDeterminant(bool(on("jacobian_determinant")))
        self.SetComputeConditionNumber(bool(on("condition_number")))

    @smproperty.dataarrayselection(name="OutputArrays")
    @smdomain.xml(
        "<Documentation>Extra point arrays: displacement (vectors f(p) - p), "
        "jacobian_determinant (local volume ratio det J), condition_number "
        "(s_max / s_min of J).</Documentation>"
    )
    def GetOutputArrays(self):
        return self._arrays

    @smproperty.doublevector(name="VolumeTolerance", default_values=0.05)
    @smdomain.doublerange(min=0.001, max=1.0)
    @smdomain.xml(
        "<Documentation>Image data: largest position error of a warped voxel, in voxels of "
        "the input spacing (the volume engine's adaptive lattice).</Documentation>"
    )
    def SetVolumeTolerance(self, value):
        self.SetTolerance(float(value))

    @_checkbox("CheckFolds", _FOLDS_HELP, default=1)
    def SetCheckFoldsFlag(self, value):
        self.SetCheckFolds(bool(int(value)))


@_filter("VHMJacobianAnalysis", "VHM Jacobian Analysis", "vtkDataSet")
@_scene_and_outside
class VHMJacobianAnalysis(_ParaViewReporting, JacobianAnalysisFilter):
    """det J, cond J, rotation angle and foldovers of a scene's map on the rest data."""

    label = "VHM Jacobian Analysis"


@_filter("VHMResampleToImage", "VHM Resample To Image", "vtkImageData")
@_scene_and_outside
class VHMResampleToImage(_ParaViewReporting, HarmonicResampleFilter):
    """The deformed volume resampled on a regular grid (pull-back through the inverse map)."""

    label = "VHM Resample To Image"

    @smproperty.doublevector(name="Tolerance", default_values=0.05)
    @smdomain.doublerange(min=1e-6, max=1.0)
    @smdomain.xml(
        "<Documentation>Largest allowed position error of a pulled-back voxel, in voxels of "
        "the input spacing.</Documentation>"
    )
    def SetToleranceVoxels(self, value):
        self.SetTolerance(float(value))

    @smproperty.doublevector(name="FillValue", default_values=0.0)
    @smdomain.xml(
        "<Documentation>Value of output voxels without a pre-image (they also get 0 in "
        "vtkValidPointMask); every array's type must hold it exactly (an integer in its "
        "range for integer data).</Documentation>"
    )
    def SetFillValueProperty(self, value):
        self.SetFillValue(float(value))

    @_checkbox("DisplacementField", _FIELD_HELP)
    def SetDisplacementFieldFlag(self, value):
        self.SetComputeDisplacementField(bool(int(value)))


# the point array is named as VTK's own reader of the format names it
_SCAN_ARRAYS = {".nii": "NIFTI", ".nii.gz": "NIFTI", ".mha": "MetaImage", ".mhd": "MetaImage",
                ".nrrd": "NRRDImage", ".nhdr": "NRRDImage", ".dcm": "DICOMImage"}  # fmt: skip
_SCAN_EXTENSIONS = "nii nii.gz mha mhd nrrd nhdr dcm"


def _scan_suffix(path):
    name = os.path.basename(path).lower()
    return ".nii.gz" if name.endswith(".nii.gz") else os.path.splitext(name)[1]


def read_scan(path):
    """A scan as a ``vtkImageData`` in ITK's physical (LPS) frame, read by SimpleITK.

    Parameters
    ----------
    path : str
        A NIfTI, MetaImage or NRRD/NHDR file, a DICOM folder, or one DICOM file (its
        folder's series that holds the file is read).

    Returns
    -------
    vtkImageData
        Origin, spacing and direction as SimpleITK reads them; one point array, with the
        image's components.
    """
    import SimpleITK as sitk
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData

    if not os.path.exists(path):
        raise FileNotFoundError(f"{path}: no such file or folder")
    try:
        if os.path.isdir(path) or _scan_suffix(path) == ".dcm":
            image = read_series(path)  # the series vhm_viz.read_dataset chooses
            name = "DICOMImage"
        else:
            image = sitk.ReadImage(path)
            name = _SCAN_ARRAYS.get(_scan_suffix(path), "ImageFile")
    except RuntimeError as exc:  # SimpleITK's: its first line names its own source file
        raise ValueError(f"{path}: {sitk_message(exc)}") from None
    if image.GetDimension() != 3:
        raise ValueError(f"{path}: a {image.GetDimension()}D image; this reader reads 3D scans")
    values = sitk.GetArrayFromImage(image)  # (z, y, x[, c]): x varies fastest
    comps = image.GetNumberOfComponentsPerPixel()
    array = numpy_to_vtk(values.reshape(-1, comps) if comps > 1 else values.ravel(), deep=1)
    array.SetName(name)
    out = vtkImageData()
    out.SetDimensions(*image.GetSize())
    out.SetOrigin(*image.GetOrigin())
    out.SetSpacing(*image.GetSpacing())
    out.SetDirectionMatrix(*image.GetDirection())
    out.GetPointData().SetScalars(array)
    return out


@smproxy.reader(
    name="VHMMedicalImageReader",
    label="VHM Medical Image Reader",
    extensions=_SCAN_EXTENSIONS,
    file_description="Medical images in ITK's LPS frame (vhm_viz)",
)
class VHMMedicalImageReader(VTKPythonAlgorithmBase):
    """NIfTI, MetaImage, NRRD/NHDR and DICOM scans, placed as ``vhm_viz.read_dataset`` places
    them (:func:`read_scan`)."""

    def __init__(self):
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=0, nOutputPorts=1, outputType="vtkImageData"
        )
        self._path = None
        self._image = None

    @smproperty.stringvector(name="FileName")
    @smdomain.filelist()
    @smhint.filechooser(extensions=_SCAN_EXTENSIONS, file_description="Medical images")
    def SetFileName(self, name):
        """The scan (a file, or a DICOM file whose series is read)."""
        if name != self._path:
            self._path, self._image = name, None
            self.Modified()

    def _scan(self):
        if self._image is None:
            if not self._path:
                raise ValueError("no file name set")
            self._image = read_scan(self._path)
        return self._image

    def RequestInformation(self, request, in_info, out_info):
        """Whole extent, origin, spacing and direction of the scan."""
        from vtkmodules.vtkCommonDataModel import vtkDataObject
        from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm
        from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

        info = out_info.GetInformationObject(0)
        try:
            image = self._scan()
        except Exception as exc:  # noqa: BLE001 - SimpleITK raises RuntimeError and more
            # one line in the output messages (once under MPI: every rank fails alike) and
            # an empty image: no traceback, no executive errors after it
            self._image = None
            if mpi.rank() == 0:
                vtkOutputWindow.GetInstance().DisplayErrorText(
                    f"VHM Medical Image Reader: {first_line(exc)}\n"
                )
            info.Set(sddp.WHOLE_EXTENT(), 0, -1, 0, -1, 0, -1)
            return 1
        info.Set(sddp.WHOLE_EXTENT(), *image.GetExtent())
        info.Set(vtkDataObject.ORIGIN(), *image.GetOrigin())
        info.Set(vtkDataObject.SPACING(), *image.GetSpacing())
        direction = image.GetDirectionMatrix()
        info.Set(
            vtkDataObject.DIRECTION(),
            tuple(direction.GetElement(i, j) for i in range(3) for j in range(3)),
            9,
        )
        info.Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
        return 1

    def RequestData(self, request, in_info, out_info):
        """The scan, cropped to the requested extent."""
        from vtkmodules.vtkCommonDataModel import vtkImageData
        from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

        out = vtkImageData.GetData(out_info, 0)
        if self._image is None:  # the information pass said why
            out.Initialize()
            return 1
        out.ShallowCopy(self._image)
        extent = out_info.GetInformationObject(0).Get(sddp.UPDATE_EXTENT())
        if extent is not None:
            out.Crop(extent)
        return 1
