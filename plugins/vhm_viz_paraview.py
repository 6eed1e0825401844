"""ParaView plugin: the vhm_viz harmonic deformation as a filter (Filters > vhm_viz).

Load it with Tools > Manage Plugins > Load New (ParaView 5.10+, whose Python can import the
installed ``vhm_viz`` package, e.g. ``pvpython -m pip install vhm_viz`` or PYTHONPATH).
Modelled on meshio's ParaView plugin: the filter is a thin wrapper that delegates all the
work to :class:`vhm_viz.filters.HarmonicDeformationFilter`.

Inputs: the data to deform (any dataset) and, optionally, the cage (polydata). Properties:
the scene file (JSON, see ``vhm_viz.scene``), the outside-the-cage policy, the optional
output arrays and, for image data, the volume tolerance (the lattice of
``vhm_viz.core.volume``).
"""

from paraview.util.vtkAlgorithm import (
    VTKPythonAlgorithmBase,
    smdomain,
    smhint,
    smproperty,
    smproxy,
)
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkDataSet, vtkPolyData

from vhm_viz.filters import HarmonicDeformationFilter


@smproxy.filter(name="VHMHarmonicDeformation", label="VHM Harmonic Deformation")
@smhint.xml('<ShowInMenu category="vhm_viz" />')
@smproperty.input(name="Cage", port_index=1)
@smdomain.datatype(dataTypes=["vtkPolyData"], composite_data_supported=False)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkDataSet"], composite_data_supported=False)
class VHMHarmonicDeformation(VTKPythonAlgorithmBase):
    def __init__(self):
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=2, nOutputPorts=1, outputType="vtkDataSet"
        )
        self._scene_file = ""
        self._outside = "error"
        self._arrays = [False, False, False]
        self._tolerance = 0.05
        self._inner = HarmonicDeformationFilter()

    def FillInputPortInformation(self, port, info):
        if port == 1:
            info.Set(self.INPUT_REQUIRED_DATA_TYPE(), "vtkPolyData")
            info.Set(self.INPUT_IS_OPTIONAL(), 1)
        else:
            info.Set(self.INPUT_REQUIRED_DATA_TYPE(), "vtkDataSet")
        return 1

    @smproperty.stringvector(name="SceneFile", number_of_elements=1)
    @smdomain.filelist()
    @smhint.filechooser(extensions="json", file_description="vhm_viz scene files")
    def SetSceneFile(self, name):
        if name != self._scene_file:
            self._scene_file = name
            self.Modified()

    @smproperty.xml(
        '<IntVectorProperty name="PassThroughOutside" command="SetPassThroughOutside" '
        'number_of_elements="1" default_values="0"><BooleanDomain name="bool"/>'
        "<Documentation>Leave points outside the cage in place (flagged vhm_outside) "
        "instead of failing.</Documentation></IntVectorProperty>"
    )
    def SetPassThroughOutside(self, value):
        self._outside = "passthrough" if value else "error"
        self.Modified()

    @smproperty.xml(
        '<IntVectorProperty name="OutputArrays" command="SetOutputArrays" '
        'number_of_elements="3" default_values="0 0 0">'
        "<Documentation>Add displacement, jacobian_determinant, condition_number."
        "</Documentation></IntVectorProperty>"
    )
    def SetOutputArrays(self, displacement, determinant, condition):
        self._arrays = [bool(displacement), bool(determinant), bool(condition)]
        self.Modified()

    @smproperty.xml(
        '<DoubleVectorProperty name="VolumeTolerance" command="SetVolumeTolerance" '
        'number_of_elements="1" default_values="0.05"><DoubleRangeDomain name="range" '
        'min="0.001"/><Documentation>Image data: largest position error of a warped voxel, '
        "in voxels (default 0.05).</Documentation></DoubleVectorProperty>"
    )
    def SetVolumeTolerance(self, value):
        if float(value) != self._tolerance:
            self._tolerance = float(value)
            self.Modified()

    # the same output-type rules as the filter it wraps (vtkWarpVector's)
    RequestDataObject = HarmonicDeformationFilter.RequestDataObject

    def RequestData(self, request, in_info, out_info):
        inp = vtkDataSet.GetData(in_info[0], 0)
        cage = vtkPolyData.GetData(in_info[1], 0) if self.GetNumberOfInputConnections(1) else None
        if not self._scene_file:
            raise RuntimeError("VHM Harmonic Deformation: set the SceneFile property")
        inner = self._inner
        if inner.GetScene() is None or getattr(self, "_loaded", None) != self._scene_file:
            inner.SetScene(self._scene_file)
            self._loaded = self._scene_file
        inner.SetInputData(inp)
        if cage is not None:
            inner.SetCageData(cage)
        inner.SetOutsidePolicy(self._outside)
        inner.SetTolerance(self._tolerance)
        inner.SetComputeDisplacement(self._arrays[0])
        inner.SetComputeJacobianDeterminant(self._arrays[1])
        inner.SetComputeConditionNumber(self._arrays[2])
        from vhm_viz.filters import update

        result = update(inner)
        vtkDataObject.GetData(out_info, 0).ShallowCopy(result)
        return 1
