"""The one validator of point arrays: ``(N, 3)`` finite coordinates.

Every public entry of the core that takes points (basis evaluation, bindings, the
deformer's anchors and constraints, the metrics) checks them here, so a caller gets the
same error, with the same wording, wherever a bad array enters.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.errors import describe_indices

__all__ = ["as_points"]


def as_points(points, name: str = "points", *, allow_empty: bool = True) -> np.ndarray:
    """Validate an array of 3D points.

    Parameters
    ----------
    points : (N, 3) or (3,) array_like
        Coordinates (any length unit). A single point ``(3,)`` becomes one row; an empty
        array (any shape of size 0) becomes ``(0, 3)``.
    name : str
        What the points are, for the error messages.
    allow_empty : bool
        False to refuse an array without points.

    Returns
    -------
    (N, 3) float64
        C-contiguous (a copy only where ``points`` was not already such an array).

    Raises
    ------
    ValueError
        When the shape is not ``(N, 3)``, when ``N`` is 0 and ``allow_empty`` is False,
        or when a coordinate is NaN or infinite (the offending rows are listed).
    """
    p = np.ascontiguousarray(points, dtype=np.float64)
    if p.ndim == 1 and p.shape[0] == 3:
        p = p.reshape(1, 3)
    if p.size == 0:
        p = p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3); got {np.shape(points)}")
    if not allow_empty and len(p) == 0:
        raise ValueError(f"{name} is empty")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise ValueError(
            f"{name} has non-finite coordinates at indices {describe_indices(np.nonzero(bad)[0])}"
        )
    return p
