"""The one colour convention of vhm_viz: how det J and cond J are coloured and binned.

Every view that shows a Jacobian measure (the explorer's slices and volumes, the paper's
Figure 4 and 12 renderings in :mod:`vhm_viz.plotting`, the ParaView plugin's presets)
takes its colour map, colour range and histogram bins from here, so that one colour means
one value everywhere.

- **det J** is a ratio of volumes: 2 (doubled) and 1/2 (halved) are equally far from 1.
  It is shown with a diverging map (coolwarm: blue shrinks, white keeps, red grows) on a
  **log scale centred on 1** with a range symmetric in ``log det``: ``(1/r, r)``. A value
  ``det J <= 0`` (a fold) has no logarithm; it takes the ``FOLD_COLOUR`` (the map's
  below-range colour), so folds are never mistaken for mere compression.
- **cond J** (``sigma_max / sigma_min >= 1``) is one-sided: a sequential map (viridis)
  from 1 upwards.
- **Histograms** show every value: values beyond the drawn range are counted in overflow
  (and underflow) bins reported with their counts, never cut silently.

Numbers only (no VTK, PyVista, Qt or matplotlib), so the ParaView plugin can use it too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "DET_CMAP",
    "COND_CMAP",
    "FOLD_COLOUR",
    "PARAVIEW_PRESETS",
    "MEASURES",
    "det_range",
    "cond_range",
    "measure_style",
    "Histogram",
    "histogram",
]

#: matplotlib / PyVista name of the diverging map of det J (Moreland's cool-to-warm).
DET_CMAP = "coolwarm"
#: matplotlib / PyVista name of the sequential map of cond J.
COND_CMAP = "viridis"
#: RGB (0..1) of det J <= 0 (folded): black, outside the blue-white-red ramp.
FOLD_COLOUR = (0.0, 0.0, 0.0)
#: The same maps under ParaView's preset names.
PARAVIEW_PRESETS = {"determinant": "Cool to Warm", "condition_number": "Viridis (matplotlib)"}

# The narrowest ranges shown: a map within 1 +- a few percent of rigid still gets a
# readable bar instead of noise stretched over the whole ramp.
_MIN_DET_RATIO = 2.0
_MIN_COND_TOP = 2.0


def _finite(values) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64).ravel()
    return v[np.isfinite(v)]


def det_range(det, *, percentile: float = 99.0, min_ratio: float = _MIN_DET_RATIO):
    """Colour range of det J: symmetric in ``log det`` around 1.

    Parameters
    ----------
    det : array_like, any shape
        Determinants (dimensionless volume ratios); non-finite values are ignored and
        values ``<= 0`` (folds) do not widen the range: they take ``FOLD_COLOUR``.
    percentile : float
        Percentile of ``|log det|`` over the positive values that sets the range, so one
        extreme value does not wash out the rest (the histogram still counts it).
    min_ratio : float
        The range is at least ``(1/min_ratio, min_ratio)``.

    Returns
    -------
    (float, float)
        ``(1/r, r)`` with ``r >= min_ratio``; draw it on a log scale.
    """
    v = _finite(det)
    v = v[v > 0]
    r = float(min_ratio)
    if v.size:
        spread = float(np.percentile(np.abs(np.log(v)), percentile))
        r = max(r, float(np.exp(spread)))
    return (1.0 / r, r)


def cond_range(cond, *, percentile: float = 99.0, min_top: float = _MIN_COND_TOP):
    """Colour range of cond J: ``(1, max(min_top, percentile of the finite values))``.

    Parameters
    ----------
    cond : array_like, any shape
        Condition numbers (``>= 1``; infinite for a singular J, ignored here).

    Returns
    -------
    (float, float)
    """
    v = _finite(cond)
    top = float(np.percentile(v, percentile)) if v.size else min_top
    return (1.0, max(float(min_top), top))


#: Per measure: its other names, colour map, range of the values, log scale, colour of
#: the folds below the range, and title.
_MEASURE_STYLES = {
    "determinant": (("jacobian_determinant", "det"), DET_CMAP, det_range, True, FOLD_COLOUR,
                    "det J (log scale; black: det J <= 0)"),
    "condition_number": (("cond", "cond J"), COND_CMAP, cond_range, False, None, "cond J"),
}  # fmt: skip

#: The Jacobian measures a view can be coloured by, in menu order.
MEASURES = tuple(_MEASURE_STYLES)


def measure_style(measure: str, values) -> dict:
    """Colour map, range and scale of one measure, for any renderer.

    Parameters
    ----------
    measure : {"determinant", "condition_number"}
    values : array_like
        The values to be shown (sets the range).

    Returns
    -------
    dict
        ``cmap`` (matplotlib/PyVista name), ``clim`` (lo, hi), ``log_scale`` (bool),
        ``below_color`` (RGB of values under ``clim[0]`` that are folds, or None),
        ``title`` and ``paraview_preset``.
    """
    for name, (aliases, cmap, clim, log_scale, below, title) in _MEASURE_STYLES.items():
        if measure == name or measure in aliases:
            return {"cmap": cmap, "clim": clim(values), "log_scale": log_scale,
                    "below_color": below, "title": title,
                    "paraview_preset": PARAVIEW_PRESETS[name]}  # fmt: skip
    raise ValueError(f"unknown measure {measure!r} ({', '.join(MEASURES)})")


@dataclass(frozen=True)
class Histogram:
    """Counts of values in bins, with every value accounted for.

    Attributes
    ----------
    counts : (bins,) int64
        Values in ``[edges[k], edges[k+1])`` (the last bin is closed).
    edges : (bins + 1,) float64
    below, above : int
        Finite values under ``edges[0]`` / over ``edges[-1]`` (underflow / overflow bins).
    nonfinite : int
        NaN and infinite values (an infinite cond J is a singular J).
    """

    counts: np.ndarray
    edges: np.ndarray
    below: int
    above: int
    nonfinite: int

    @property
    def total(self) -> int:
        """Every value given, in some bin."""
        return int(self.counts.sum()) + self.below + self.above + self.nonfinite


def histogram(values, value_range=None, bins: int = 40, *, log: bool = False) -> Histogram:
    """Histogram that never drops a value silently.

    Parameters
    ----------
    values : array_like, any shape
    value_range : (float, float), optional
        Drawn range; default the finite values' min and max (then nothing overflows).
    bins : int
    log : bool
        Bins equal in ``log`` (for det J, with positive ``value_range``); values ``<= 0``
        land in ``below``.

    Returns
    -------
    Histogram
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    fin = np.isfinite(v)
    nonfinite = int(v.size - fin.sum())
    v = v[fin]
    if value_range is None:
        if v.size == 0:
            value_range = (1.0, 2.0)
        else:
            pos = v[v > 0] if log else v
            lo = float(pos.min()) if pos.size else 1.0
            hi = float(pos.max()) if pos.size else 2.0
            value_range = (lo, hi)
    lo, hi = (float(x) for x in value_range)
    if hi <= lo:
        pad = 0.5 * max(abs(lo), 1.0) if not log else 0.0
        lo, hi = (lo / 2, hi * 2) if log else (lo - pad, hi + pad)
    if log:
        if lo <= 0:
            raise ValueError(f"a log histogram needs a positive range, got ({lo}, {hi})")
        edges = np.geomspace(lo, hi, bins + 1)
    else:
        edges = np.linspace(lo, hi, bins + 1)
    below = int(np.count_nonzero(v < lo))
    above = int(np.count_nonzero(v > hi))
    inside = v[(v >= lo) & (v <= hi)]
    counts, _ = np.histogram(inside, bins=edges)
    return Histogram(counts.astype(np.int64), edges, below, above, nonfinite)
