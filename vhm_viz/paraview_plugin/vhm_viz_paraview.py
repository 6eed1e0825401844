"""ParaView plugin: vhm_viz's harmonic deformation, Jacobian analysis and resampling.

This folder ships inside the wheel; ``vhm-viz paraview`` prints its path and the lines that
set up ParaView's Python (from a checkout: ``eval "$(bash plugins/paraview-env.sh)"``, whose
``plugins/vhm_viz_paraview.py`` runs this file). ParaView then loads the plugin from
``PV_PLUGIN_PATH`` (or load it with Tools > Manage Plugins). The filters appear under
Filters > vhm_viz and in ``paraview.simple`` as ``VHMHarmonicDeformation``,
``VHMJacobianAnalysis`` and ``VHMResampleToImage``.

Modelled on meshio's ParaView plugin, this file only declares proxies and properties: each
filter *is* the corresponding :mod:`vhm_viz.filters` algorithm (same pipeline contract:
the whole cage is requested on every rank, pieces and extents are honoured), with
:meth:`SetParallelReporting` on, so that under ``mpiexec`` the ranks agree on errors, every
error is one line in ParaView's output window, and a failed update leaves no stale output.
"""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from vhm_viz.filters import (
    HarmonicDeformationFilter,
    HarmonicResampleFilter,
    JacobianAnalysisFilter,
)
from vhm_viz.filters._common import DeformationSource

_SCENE_HELP = (
    "A vhm_viz scene (JSON): cage, anchors, constraints, mode, solver settings. Write one "
    "with the vhm_viz explorer, vhm_viz.scene.Scene.save or by hand (see the README). The "
    "file is read again when it changes."
)
_CAGE_HELP = (
    "Optional: the cage as a closed triangle surface. When connected it replaces the "
    "scene's cage (the deformer is rebuilt on it). Every rank receives all of it."
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

    @smproperty.intvector(name="AllowUnconverged", default_values=0, number_of_elements=1)
    @smdomain.xml(
        '<BooleanDomain name="bool"/>'
        "<Documentation>Deform even when the scene's solve stops at solver.max_iterations "
        "before its tolerance (a warning says how far it stopped). Off: such an update "
        "fails with that message and leaves no output.</Documentation>"
    )
    def SetAllowUnconvergedFlag(self, value):
        self.SetAllowUnconverged(bool(int(value)))

    cls.SetSceneFile = SetSceneFile
    cls.SetOutsidePolicyIndex = SetOutsidePolicyIndex
    cls.SetAllowUnconvergedFlag = SetAllowUnconvergedFlag
    return cls


class _ParaViewReporting:
    """Errors as one line in ParaView's output window, agreed across MPI ranks."""

    label = ""

    def __init__(self):
        super().__init__()
        self.SetParallelReporting(True)

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
        "vtkValidPointMask).</Documentation>"
    )
    def SetFillValueProperty(self, value):
        self.SetFillValue(float(value))
