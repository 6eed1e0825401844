"""Anchor points from rigidity lines (paper Section 2.2, "The discrete energy").

The rigidity energy is sampled at ``d`` anchor points placed on rigidity lines (a skeleton
or medial-axis polyline). :func:`anchors_from_polylines` spreads them evenly by arc length.
"""

from __future__ import annotations

import numpy as np

__all__ = ["anchors_from_polylines"]


def anchors_from_polylines(points, edges, count: int) -> np.ndarray:
    """Sample ``count`` anchor points evenly along a set of polylines.

    The polylines are given as a graph (points and segments), e.g. the rigidity lines read by
    :func:`vhm_viz.read_polylines` or a skeleton read by :func:`vhm_viz.read_tgf`. Samples are
    spaced evenly by arc length over the *total* length of all segments, at the midpoints of
    ``count`` equal arc-length intervals, so every line receives a number of anchors
    proportional to its length (the paper's ``d / l`` per line for equally long lines) and no
    anchor sits on a joint shared by several segments. Exact duplicates are never produced.

    Parameters
    ----------
    points : (P, 3) array_like of float
        Polyline vertices.
    edges : (E, 2) array_like of int
        Segments between vertices. Zero-length segments are ignored.
    count : int
        Number of anchors ``d`` (>= 1).

    Returns
    -------
    (count, 3) float64
        Anchor positions, ordered along the segments as given.

    Raises
    ------
    ValueError
        Wrong shapes, non-finite points, indices out of range, ``count < 1``, or polylines of
        zero total length.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (P, 3); got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError("points contain non-finite coordinates")
    e = np.asarray(edges)
    if e.ndim != 2 or e.shape[1] != 2:
        raise ValueError(f"edges must have shape (E, 2); got {e.shape}")
    e = e.astype(np.int64)
    if e.size and (e.min() < 0 or e.max() >= len(p)):
        raise ValueError(f"edge indices must lie in [0, {len(p)})")
    count = int(count)
    if count < 1:
        raise ValueError(f"count must be >= 1; got {count}")
    a, b = p[e[:, 0]], p[e[:, 1]]
    length = np.linalg.norm(b - a, axis=1)
    keep = length > 0
    a, b, length = a[keep], b[keep], length[keep]
    total = float(length.sum())
    if total <= 0:
        raise ValueError("the polylines have zero total length")
    cum = np.concatenate([[0.0], np.cumsum(length)])
    s = (np.arange(count) + 0.5) * (total / count)
    seg = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(length) - 1)
    t = np.clip((s - cum[seg]) / length[seg], 0.0, 1.0)
    return a[seg] + t[:, None] * (b[seg] - a[seg])
