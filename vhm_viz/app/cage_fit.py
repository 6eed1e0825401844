"""Whether a cage fits the explorer's data: every point inside, or a volume's region.

A volume's cage may enclose only the region above a threshold, as
``auto_cage(..., threshold=...)`` and ``vhm-viz cage --threshold`` build it; voxels outside
stay put.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from vhm_viz.autocage.cage import resolve_threshold, volume_values
from vhm_viz.core.errors import CageError, describe_indices

__all__ = ["point_values", "region_threshold"]


def point_values(volume, rest, n_points: int):
    """(P,) scalar values of a volume's points; None for data that is not a volume.

    Parameters
    ----------
    volume : VolumeView or None
        The explorer's loaded volume.
    rest : pyvista.DataSet
        The loaded data (a structured grid of values also counts).
    n_points : int
        Points of the displayed data (the values must match them).
    """
    if volume is not None:
        return volume.values
    if not isinstance(rest, pv.StructuredGrid | pv.ImageData | pv.RectilinearGrid):
        return None
    try:
        values, _ = volume_values(rest)
    except ValueError:
        return None
    return values if len(values) == n_points else None


def region_threshold(values, inside: np.ndarray, threshold):
    """The threshold whose region a cage that leaves points out encloses.

    Parameters
    ----------
    values : (P,) ndarray or None
        The points' scalar values (:func:`point_values`); None when the data is no volume.
    inside : (P,) bool ndarray
        Which points the cage encloses (not all).
    threshold : float, str or None
        The user's threshold (a number or ``"otsu"``): every point above it must be inside.
        None: the region above the largest value left out, if it is not empty.

    Returns
    -------
    threshold : float, str or None
        The given threshold, or the one found.
    note : str or None
        What the user should know when a threshold was found.

    Raises
    ------
    CageError
        Points of the data (or of the region) outside the cage, with count and indices;
        also a cage that encloses no region above a threshold.
    """
    bad = np.nonzero(~inside)[0]
    if values is None:
        raise CageError(
            f"the cage does not enclose the shape: {bad.size} of {len(inside)} points "
            f"are outside (indices {describe_indices(bad)})"
        )
    if threshold is not None:
        thr = resolve_threshold(values, threshold)
        missed = np.nonzero(~inside & (values > thr))[0]
        if missed.size:
            raise CageError(
                f"the cage does not enclose the region above {thr:.6g}: {missed.size} of "
                f"{int((values > thr).sum())} voxels are outside (indices "
                f"{describe_indices(missed)})"
            )
        return threshold, None
    thr = float(values[~inside].max())
    region = int((values > thr).sum())
    if region == 0:
        raise CageError(
            f"the cage does not enclose the volume: {bad.size} of {len(inside)} voxels are "
            "outside, among them the largest values"
        )
    note = (
        f"the cage encloses the {region} voxels above {thr:.6g} (threshold set to it); "
        f"the {bad.size} voxels outside stay put"
    )
    return thr, note
