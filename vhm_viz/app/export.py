"""Export of the explorer's deformed data, as ``vhm-viz deform`` writes it.

The display is deformed through a float32 binding (fast to drag); the export evaluates the
harmonic map in float64, so it equals ``vhm-viz deform`` of the saved scene to rounding.
A volume is resampled on its grid for image formats and warped (a structured grid) for
the others, the command line's choice (:func:`vhm_viz.io.is_image_format`).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from vhm_viz.core.errors import FoldWarning
from vhm_viz.folds import output_folds
from vhm_viz.io import is_image_format, refuse_inputs, write_dataset

__all__ = [
    "export_path",
    "write_deformed",
    "write_deformed_volume",
]


def export_path(path, source: dict, input_files) -> Path:
    """The file to write: ``path``, with the input's suffix (``.vtp`` without one) if it has none.

    Raises
    ------
    ValueError
        The path is one of ``input_files`` (data, cage or anchors read since loading).
    """
    path = Path(path)
    if not path.suffix:
        src = source.get("path")
        path = path.with_suffix(Path(src).suffix if src else ".vtp")
    refuse_inputs(path, list(input_files))
    return path


def write_deformed(
    path: Path, display, rest_points: np.ndarray, harmonic_map=None, inputs=()
) -> list:
    """Write the display dataset, its points mapped by ``harmonic_map`` in float64.

    Returns the line that says how the deformation folds the data, when it does
    (:func:`vhm_viz.folds.output_folds`, what ``vhm-viz deform`` refuses without
    ``--allow-folds``), in a list; the file is written all the same.

    Parameters
    ----------
    path : Path
    display : pyvista.DataSet
        The shown dataset (its point arrays are written; names starting with ``_`` are the
        display's helpers and are dropped).
    rest_points : (P, 3) ndarray
        The display's rest positions.
    harmonic_map : HarmonicMap, optional
        The solved map; without one the display's points are written as they are.
    inputs : iterable of path-like
        The files the session read: no file written (the arrays beside an image output
        included) may be one of them.
    """
    data = display.copy(deep=True)
    folds = None
    if harmonic_map is not None:
        data.points = harmonic_map.map(rest_points, outside="passthrough")
        rest = display.copy(deep=True)
        rest.points = rest_points
        folds = output_folds(rest, data, harmonic_map)
    for name in [n for n in data.point_data.keys() if n.startswith("_")]:
        del data.point_data[name]
    try:
        write_dataset(path, data, inputs=inputs)
    except (ValueError, TypeError) as exc:  # a suffix VTK cannot write this type to
        raise ValueError(f"cannot write {path.name}: {exc}") from exc
    return [] if folds is None else [folds]


def write_deformed_volume(path: Path, volume, harmonic_map, inputs=()) -> list:
    """Write a deformed volume: resampled or warped as :func:`~vhm_viz.io.is_image_format` says.

    ``inputs`` and what it returns: as for :func:`write_deformed` (a resample's voxels in
    folds, a warp's inverted voxel cells).
    """
    import pyvista as pv

    from vhm_viz.filters import HarmonicDeformationFilter, HarmonicResampleFilter, update

    resample = is_image_format(path)
    flt = HarmonicResampleFilter() if resample else HarmonicDeformationFilter()
    flt.SetInputData(volume)
    flt.SetHarmonicMap(harmonic_map)
    flt.SetOutsidePolicy("passthrough")
    with warnings.catch_warnings():  # the fold line below says it
        warnings.simplefilter("ignore", FoldWarning)
        data = pv.wrap(update(flt))
    folds = output_folds(volume, data, harmonic_map, engine=flt.volume_engine,
                         resampled=flt.fold_voxels if resample else None)  # fmt: skip
    write_dataset(path, data, inputs=inputs)
    return [] if folds is None else [folds]
