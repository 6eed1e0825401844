"""VTK filters: harmonic deformation of any dataset, volume resampling, Jacobian analysis.

All three are ``VTKPythonAlgorithmBase`` subclasses with the data on input port 0 and an
optional cage (``vtkPolyData``) on input port 1; the deformation is set on the filter
(``SetDeformer``, ``SetScene`` or ``SetHarmonicMap``). VTK only logs exceptions raised
while a filter executes; :func:`update` updates a filter and re-raises them.

* :class:`HarmonicDeformationFilter` -- moves the points (output types as ``vtkWarpVector``).
* :class:`HarmonicResampleFilter` -- a deformed volume back on a regular grid (pull-back).
* :class:`JacobianAnalysisFilter` -- determinant, condition number, rotation, foldovers,
  and the quality of the deformed cells.

:func:`region_of` turns a dataset into the region :func:`vhm_viz.certify_injectivity`
certifies, and :func:`cell_quality` measures the cells of a deformed dataset.
"""

from vhm_viz.filters._vtk import update
from vhm_viz.filters.analysis import ANALYSIS_ARRAYS, JacobianAnalysisFilter
from vhm_viz.filters.cells import CELL_ARRAYS, cell_quality, region_of
from vhm_viz.filters.deformation import HarmonicDeformationFilter, output_type_for
from vhm_viz.filters.resample import HarmonicResampleFilter

__all__ = [
    "HarmonicDeformationFilter",
    "HarmonicResampleFilter",
    "JacobianAnalysisFilter",
    "ANALYSIS_ARRAYS",
    "CELL_ARRAYS",
    "cell_quality",
    "region_of",
    "output_type_for",
    "update",
]
