"""Anchor files: the JSON that ``vhm-viz anchors`` writes, or a bare list of points."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError, check_file_size, first_line
from vhm_viz.io.text import json_text, write_text

__all__ = ["read_anchors", "write_anchors"]


def read_anchors(path) -> np.ndarray:
    """Anchor points from a JSON file: what ``vhm-viz anchors`` writes, or a bare list.

    Parameters
    ----------
    path : str or os.PathLike
        ``{"anchors": [[x, y, z], ...], ...}`` or ``[[x, y, z], ...]``.

    Returns
    -------
    (d, 3) float64

    Raises
    ------
    FileNotFoundError, ReadError
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no such anchors file: {p}")
    check_file_size(p, "anchors")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
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
    """Write anchors as ``{"anchors": [[x, y, z], ...], "count": d, **info}`` (atomic)."""
    a = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    write_text(path, json_text({"anchors": a.tolist(), "count": len(a), **info}))
