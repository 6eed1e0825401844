"""Thresholding a volume: the scalar it is thresholded on and the threshold as a number.

The region of a volume that :func:`vhm_viz.auto_cage` and :func:`vhm_viz.auto_anchors`
enclose is the set of samples whose value is strictly above the threshold; ``"otsu"``
picks Otsu's threshold (:func:`otsu_threshold`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["otsu_threshold", "resolve_threshold", "volume_values"]

#: histogram bins Otsu's threshold is chosen from
OTSU_BINS = 256


def otsu_threshold(values: np.ndarray) -> float:
    """Otsu's threshold: the split of a histogram that maximises the between-class variance.

    The finite ``values`` are binned into :data:`OTSU_BINS` equal bins; for every split
    after bin ``k`` the two classes (bins ``0..k`` and the rest, each bin at its centre)
    have weights ``w0``, ``w1`` (sample counts) and means ``mu0``, ``mu1``, and the split
    maximising ``w0 * w1 * (mu0 - mu1) ** 2`` is chosen (Otsu 1979).

    Parameters
    ----------
    values : array_like
        Samples of any shape (flattened); NaN and infinite values are ignored.

    Returns
    -------
    float
        The upper edge of the last bin of the lower class, in the units of ``values``: the
        upper class is ``values > threshold``, up to values on that edge.
    """
    v = np.asarray(values).ravel()
    if v.dtype.kind == "f":
        v = v[np.isfinite(v)]
    hist, edges = np.histogram(v, bins=OTSU_BINS)
    centers = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * centers)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    between = w0 * w1 * (mu0 - mu1) ** 2
    return float(edges[1:][np.argmax(between)])


def volume_values(ds, scalars: str | None = None, what: str = "volume"):
    """The scalar a volume is thresholded on, per point (or per cell), and its name.

    Parameters
    ----------
    ds : pyvista.ImageData, RectilinearGrid or StructuredGrid
    scalars : str, optional
        Array name (default: the active scalars, else the first array).
    what : str
        Prefix for error messages.

    Returns
    -------
    values : (n,) ndarray
        The array (vectors: their length).
    name : str
    """
    name = scalars or ds.active_scalars_name or (ds.array_names[0] if ds.array_names else None)
    if name is None:
        raise ValueError(f"{what}: the volume has no scalars to threshold")
    vals = np.asarray(ds.get_array(name))
    if vals.ndim > 1:
        vals = np.linalg.norm(vals, axis=1)
    return vals, name


def resolve_threshold(values: np.ndarray, threshold) -> float:
    """A threshold as a number: ``"otsu"`` becomes :func:`otsu_threshold` of ``values``.

    The region of a volume is the voxels whose value is strictly above it.

    Parameters
    ----------
    values : array_like
        The volume's scalar (see :func:`volume_values`).
    threshold : float or "otsu"

    Returns
    -------
    float
        In the units of ``values``.

    Raises
    ------
    ValueError
        A string other than ``"otsu"`` (any case).
    """
    if isinstance(threshold, str):
        if threshold.lower() != "otsu":
            raise ValueError(f"threshold must be a number or 'otsu', got {threshold!r}")
        return otsu_threshold(values)
    return float(threshold)
