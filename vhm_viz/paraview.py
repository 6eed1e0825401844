"""ParaView display of the Jacobian measures in vhm_viz's one colour convention.

A thin adapter over :mod:`vhm_viz.colours` for ``pvpython``, ``pvbatch`` and the GUI's
Python shell (it imports ``paraview.simple`` when called, so importing this module needs no
ParaView): det J with ParaView's "Cool to Warm" on a log scale centred on 1 with the
symmetric range of :func:`vhm_viz.colours.det_range`, folds (``det J <= 0``) in the
below-range colour; cond J with "Viridis (matplotlib)" from 1. The same as the explorer and
the figures of :mod:`vhm_viz.plotting`.

Example, after ``eval "$(bash plugins/paraview-env.sh)"``::

    import paraview.simple as pvs
    from vhm_viz.paraview import color_by_measure
    bent = pvs.VHMJacobianAnalysis(Input=..., Cage=...)
    color_by_measure(bent, "jacobian_determinant")
"""

from __future__ import annotations

import numpy as np

from vhm_viz import colours

__all__ = ["color_by_measure"]

_MEASURES = {
    "jacobian_determinant": "determinant",
    "cell_jacobian_determinant": "determinant",
    "condition_number": "condition_number",
    "cell_condition_number": "condition_number",
}


def color_by_measure(source, array: str = "jacobian_determinant", view=None):
    """Show ``source`` coloured by a Jacobian measure array, in the one convention.

    Parameters
    ----------
    source : paraview proxy
        A pipeline source with the array (e.g. VHM Jacobian Analysis or VHM Harmonic
        Deformation with the array among its OutputArrays).
    array : str
        ``jacobian_determinant``, ``condition_number`` (point arrays) or their ``cell_``
        versions (cell arrays of tet meshes).
    view : paraview view proxy, optional
        Default: the active render view.

    Returns
    -------
    display, lookup table
        The representation and the array's colour transfer function.
    """
    import paraview.simple as pvs
    from paraview import servermanager

    if array not in _MEASURES:
        raise ValueError(f"unknown measure array {array!r} ({', '.join(_MEASURES)})")
    association = "CELLS" if array.startswith("cell_") else "POINTS"
    pvs.UpdatePipeline(proxy=source)
    # the values that set the colour range (percentiles): the whole dataset in pvpython and
    # the GUI; under ``mpiexec pvbatch`` what Fetch gathers (it can be rank 0's piece)
    values = servermanager.Fetch(source)
    values = _array_values(values, array, association)
    style = colours.measure_style(_MEASURES[array], values)
    view = view or pvs.GetActiveViewOrCreate("RenderView")
    display = pvs.Show(source, view)
    pvs.ColorBy(display, (association, array))
    lut = pvs.GetColorTransferFunction(array)
    lut.ApplyPreset(style["paraview_preset"], True)
    lo, hi = style["clim"]
    lut.AutomaticRescaleRangeMode = "Never"
    lut.RescaleTransferFunction(lo, hi)
    if style["log_scale"]:
        lut.MapControlPointsToLogSpace()
        lut.UseLogScale = 1
    if style["below_color"] is not None:
        lut.UseBelowRangeColor = 1
        lut.BelowRangeColor = list(style["below_color"])
    display.SetScalarBarVisibility(view, True)
    bar = pvs.GetScalarBar(lut, view)
    bar.Title = style["title"]
    bar.ComponentTitle = ""
    return display, lut


def _array_values(data, name, association):
    """The array's values from a fetched dataset (composite: every block)."""
    from vtkmodules.numpy_interface import dataset_adapter as dsa

    wrapped = dsa.WrapDataObject(data)
    fields = wrapped.CellData if association == "CELLS" else wrapped.PointData
    arr = fields[name]
    if arr is None or isinstance(arr, dsa.VTKNoneArray):
        raise ValueError(f"the source has no {association.lower()[:-1]} array {name!r}")
    if isinstance(arr, dsa.VTKCompositeDataArray):
        parts = [np.asarray(a).ravel() for a in arr.Arrays if not isinstance(a, dsa.VTKNoneArray)]
        return np.concatenate(parts) if parts else np.zeros(0)
    return np.asarray(arr).ravel()
