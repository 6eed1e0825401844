"""Folds in a deformed output: how many, where, and the line that says so.

A resample marks the output voxels that have several pre-images (``vhm_foldover``,
:class:`~vhm_viz.core.volume.Resampled`). :func:`fold_voxels` summarises such a mask
(their count and the box of their output positions), :func:`merge_fold_voxels` joins the
summaries of pieces, and :func:`fold_voxels_text` is the one wording of them: in the
command line's fold check (:func:`vhm_viz.folds.fold_warning`), the resample
filter's warning (ParaView's output window) and the explorer's export.

A warp's inverted cells are summarised alike: :func:`inverted_cells` (their count, the
worst determinant and where, the box of their rest centres), :func:`merge_inverted_cells`
and :func:`inverted_cells_text`, in the command line's check and the deformation
filter's warning.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.image import ImageGeometry

__all__ = [
    "FOLD_SCAN_VOXELS",
    "FOLDS",
    "fold_voxels",
    "fold_voxels_text",
    "inverted_cells",
    "inverted_cells_text",
    "merge_fold_voxels",
    "merge_inverted_cells",
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


def inverted_cells(determinants, centres, cells: int, straddling: int = 0) -> dict:
    """The inverted cells of a deformed mesh or image: their count, worst and box.

    Parameters
    ----------
    determinants : (K,) array_like
        The inverted cells' determinants (``<= 0``, relative to the rest cell's).
    centres : (K, 3) array_like
        Their rest centres (world units).
    cells : int
        The cells measured (with finite corners), inverted or not.
    straddling : int
        Of the K, those with points outside the cage, left in place (the "passthrough"
        outside policy): such a cell spans the map and the identity, and may be inverted
        where the map itself does not fold.

    Returns
    -------
    dict
        ``count`` (K), ``cells``, ``straddling``, ``worst`` (the smallest determinant;
        ``inf`` when K is 0), ``at`` (3,) its cell's centre, and ``lo``, ``hi`` (3,) the
        box of the centres (``inf`` and ``-inf`` when K is 0).
    """
    det = np.asarray(determinants, dtype=np.float64).reshape(-1)
    at = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    out = {"count": int(det.size), "cells": int(cells), "straddling": int(straddling),
           "worst": np.inf, "at": np.full(3, np.nan), "lo": np.full(3, np.inf),
           "hi": np.full(3, -np.inf)}  # fmt: skip
    if det.size:
        k = int(np.argmin(det))
        out["worst"], out["at"] = float(det[k]), at[k].copy()
        # column by column: numpy's axis-0 reduction of (K, 3) is slow
        out["lo"] = np.array([at[:, c].min() for c in range(3)])
        out["hi"] = np.array([at[:, c].max() for c in range(3)])
    return out


def merge_inverted_cells(parts) -> dict:
    """One :func:`inverted_cells` summary of several disjoint pieces' summaries."""
    parts = list(parts)
    out = inverted_cells([], np.zeros((0, 3)), sum(int(p["cells"]) for p in parts))
    out["count"] = sum(int(p["count"]) for p in parts)
    out["straddling"] = sum(int(p.get("straddling", 0)) for p in parts)
    for p in parts:
        if p["count"] and p["worst"] < out["worst"]:
            out["worst"], out["at"] = float(p["worst"]), np.asarray(p["at"], dtype=np.float64)
        out["lo"] = np.minimum(out["lo"], p["lo"])
        out["hi"] = np.maximum(out["hi"], p["hi"])
    return out


def inverted_cells_text(cells: dict) -> str | None:
    """The line of an :func:`inverted_cells` summary; None when no cell is inverted.

    ``K of N cells inverted (cell det <= 0; worst D at (x, y, z), within
    (x, y, z)-(x, y, z))``, positions being rest positions; then how many of them straddle
    the cage, if any.
    """
    if not cells["count"]:
        return None
    where = f"worst {cells['worst']:.3g} at {position_text(cells['at'])}"
    if cells["count"] > 1:
        where += f", within {position_text(cells['lo'])}-{position_text(cells['hi'])}"
    text = f"{cells['count']} of {cells['cells']} cells inverted (cell det <= 0; {where})"
    straddling = int(cells.get("straddling", 0))
    if straddling:
        which = "all" if straddling == cells["count"] else straddling
        text += (
            f", {which} of them straddling the cage (their points outside it left in place, "
            "not mapped)"
        )
    return text
