"""A resampled volume's voxels in folds: how many, where, and the line that says so.

A resample marks the output voxels that have several pre-images (``vhm_foldover``,
:class:`~vhm_viz.core.volume.Resampled`). :func:`fold_voxels` summarises such a mask
(their count and the box of their output positions), :func:`merge_fold_voxels` joins the
summaries of pieces, and :func:`fold_voxels_text` is the one wording of them: in the
command line's fold check (:func:`vhm_viz.folds.fold_warning`), the resample
filter's warning (ParaView's output window) and the explorer's export.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.image import ImageGeometry

__all__ = [
    "FOLD_SCAN_VOXELS",
    "FOLDS",
    "fold_voxels",
    "fold_voxels_text",
    "merge_fold_voxels",
    "position_text",
]

#: The start of every line that says a deformation folds the data.
FOLDS = "the deformation folds the data: "
#: Voxels of a fold mask scanned at a time for the positions of those in folds: a large
#: fold needs no array of all its positions.
FOLD_SCAN_VOXELS = 1 << 22


def position_text(p) -> str:
    """``(x, y, z)`` to 4 digits."""
    return "(" + ", ".join(f"{c:.4g}" for c in p) + ")"


def fold_voxels(foldover, geometry: ImageGeometry | None) -> dict:
    """The voxels of a grid that a fold mask marks: their count and the box they span.

    Parameters
    ----------
    foldover : (P,) array_like
        Nonzero at the voxels in folds, in VTK's point order (i fastest).
    geometry : ImageGeometry or None
        The mask's grid (None: an empty piece, with an empty mask).

    Returns
    -------
    dict
        ``count`` (voxels in folds), ``voxels`` (all of the mask's), and ``lo``, ``hi``
        (3,) float64, the box of the output positions of those in folds (``inf`` and
        ``-inf`` when there are none).
    """
    mask = np.asarray(foldover).reshape(-1)
    count, lo, hi = 0, np.full(3, np.inf), np.full(3, -np.inf)
    dims = None if geometry is None else tuple(geometry.dimensions)
    for start in range(0, mask.size, FOLD_SCAN_VOXELS):
        index = np.flatnonzero(mask[start : start + FOLD_SCAN_VOXELS]) + start
        if index.size:
            count += index.size
            at = geometry.points(np.column_stack(np.unravel_index(index, dims, order="F")))
            # column by column: numpy's axis-0 reduction of (K, 3) is slow
            lo = np.minimum(lo, [at[:, c].min() for c in range(3)])
            hi = np.maximum(hi, [at[:, c].max() for c in range(3)])
    return {"count": int(count), "voxels": int(mask.size), "lo": lo, "hi": hi}


def merge_fold_voxels(parts) -> dict:
    """One :func:`fold_voxels` summary of several disjoint pieces' summaries."""
    parts = list(parts)
    return {
        "count": sum(int(p["count"]) for p in parts),
        "voxels": sum(int(p["voxels"]) for p in parts),
        "lo": np.min([p["lo"] for p in parts], axis=0) if parts else np.full(3, np.inf),
        "hi": np.max([p["hi"] for p in parts], axis=0) if parts else np.full(3, -np.inf),
    }


def fold_voxels_text(voxels: dict) -> str | None:
    """The line of a :func:`fold_voxels` summary; None when no voxel is in a fold.

    ``K of N output voxels in folds (several pre-images; output positions within
    (x, y, z)-(x, y, z))``.
    """
    if not voxels["count"]:
        return None
    lo, hi = voxels["lo"], voxels["hi"]
    where = f"output position {position_text(lo)}"
    if not np.array_equal(lo, hi):
        where = f"output positions within {position_text(lo)}-{position_text(hi)}"
    return (
        f"{voxels['count']} of {voxels['voxels']} output voxels in folds "
        f"(several pre-images; {where})"
    )
