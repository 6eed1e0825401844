"""Anchor files: the JSON that ``vhm-viz anchors`` writes, a bare list, or Slicer markups."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError, check_file_size, first_line, require_file
from vhm_viz.io.markups import is_markups_path, read_markups, write_markups
from vhm_viz.io.text import JSONTextError, json_text, parse_json, write_text

__all__ = ["read_anchors", "write_anchors"]


def read_anchors(path) -> np.ndarray:
    """Anchor points from a JSON file: what ``vhm-viz anchors`` writes, a list, or markups.

    Parameters
    ----------
    path : str or os.PathLike
        ``{"anchors": [[x, y, z], ...], ...}`` or ``[[x, y, z], ...]`` (LPS), or a 3D
        Slicer point list ``*.mrk.json`` (:func:`~vhm_viz.io.markups.read_markups`).

    Returns
    -------
    (d, 3) float64

    Raises
    ------
    FileNotFoundError, ReadError
    """
    p = Path(path)
    require_file(p, "anchors")
    check_file_size(p, "anchors")
    if is_markups_path(p):
        return read_markups(p)
    try:
        data = parse_json(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, JSONTextError) as exc:
        raise ReadError(f"{p}: not a JSON anchors file ({first_line(exc)})") from exc
    if isinstance(data, dict):
        data = data.get("anchors")
    try:
        pts = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        pts = np.zeros((0,))
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.isfinite(pts).all():
        raise ReadError(f"{p}: expected a non-empty list of [x, y, z] anchor points")
    return pts


def write_anchors(path, anchors, **info) -> None:
    """Write anchors as ``{"anchors": [[x, y, z], ...], "count": d, **info}`` (atomic).

    A ``*.mrk.json`` path gets a 3D Slicer point list instead (LPS; ``info`` is not
    written there).
    """
    a = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    if is_markups_path(path):
        write_markups(path, a, name="anchors")
        return
    write_text(path, json_text({"anchors": a.tolist(), "count": len(a), **info}))
