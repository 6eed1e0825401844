"""VTK filters: harmonic deformation of any dataset, volume resampling, Jacobian analysis.

All three are ``VTKPythonAlgorithmBase`` subclasses with the data on input port 0 and an
optional cage (``vtkPolyData``) on input port 1; the deformation is set on the filter
(``SetDeformer``, ``SetScene`` or ``SetHarmonicMap``). VTK only logs exceptions raised
while a filter executes; :func:`update` updates a filter and re-raises them.

* :class:`HarmonicDeformationFilter` -- moves the points (output types as ``vtkWarpVector``).
* :class:`HarmonicResampleFilter` -- a deformed volume back on a regular grid (pull-back).
* :class:`JacobianAnalysisFilter` -- determinant, condition number, rotation, foldovers.
"""

from vhm_viz.filters._common import update
from vhm_viz.filters.analysis import ANALYSIS_ARRAYS, JacobianAnalysisFilter
from vhm_viz.filters.deformation import HarmonicDeformationFilter, output_type_for
from vhm_viz.filters.resample import HarmonicResampleFilter

__all__ = [
    "HarmonicDeformationFilter",
    "HarmonicResampleFilter",
    "JacobianAnalysisFilter",
    "ANALYSIS_ARRAYS",
    "output_type_for",
    "update",
]
