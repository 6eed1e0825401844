"""3D Slicer markups: point lists (``.mrk.json``) read and written in vhm_viz's LPS frame.

Slicer's markups format (schema ``markups-schema-v1.0.3.json``) stores each point list as
a markup of type ``"Fiducial"`` whose ``controlPoints`` carry a ``position`` in the
markup's ``coordinateSystem``, ``"LPS"`` (the default, what Slicer writes) or ``"RAS"``.
vhm_viz's world is ITK's (LPS, millimetres): RAS positions are converted on reading,
``RAS = diag(-1, -1, 1) LPS``, a half turn about z (its own inverse).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError, first_line, require_file
from vhm_viz.io.text import JSONTextError, json_text, parse_json, write_text

__all__ = [
    "MARKUPS_SCHEMA",
    "MARKUPS_SUFFIX",
    "RAS_TO_LPS",
    "SPACES",
    "is_markups_path",
    "lps_points",
    "read_markups",
    "write_markups",
]

#: The schema Slicer's point lists follow; written into every file.
MARKUPS_SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/Markups/"
    "Resources/Schema/markups-schema-v1.0.3.json#"
)
#: The suffix of Slicer's markups files.
MARKUPS_SUFFIX = ".mrk.json"
#: RAS <-> LPS (x and y negated; the matrix is its own inverse).
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0])
#: The world frames a scene or a markups file may be written in.
SPACES = ("LPS", "RAS")


def is_markups_path(path) -> bool:
    """Whether ``path`` names a Slicer markups file (``*.mrk.json``)."""
    return str(path).lower().endswith(MARKUPS_SUFFIX)


def lps_points(points, space: str) -> np.ndarray:
    """``points`` (n, 3) given in ``space`` ("LPS" or "RAS") as LPS points (n, 3) float64."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return pts @ RAS_TO_LPS if space == "RAS" else pts.copy()


def read_markups(path) -> np.ndarray:
    """The control points of a Slicer point list, in LPS millimetres.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.mrk.json`` file holding one markup of type ``"Fiducial"`` (a point list);
        its ``coordinateSystem`` (``"LPS"`` when absent, or ``"RAS"``) is honoured.

    Returns
    -------
    (n, 3) float64
        The control points' ``position`` in file order, in LPS.

    Raises
    ------
    FileNotFoundError, ReadError
        Not JSON, not a markups file, no or several point lists, a coordinate system or
        unit other than LPS/RAS and mm, a control point without a defined position.
    """
    p = Path(path)
    require_file(p, "markups")
    try:
        data = parse_json(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, JSONTextError) as exc:
        raise ReadError(f"{p}: not a JSON markups file ({first_line(exc)})") from exc
    markups = data.get("markups") if isinstance(data, dict) else None
    if not isinstance(markups, list):
        raise ReadError(f'{p}: not a Slicer markups file (no "markups" list)')
    lists = [m for m in markups if isinstance(m, dict) and m.get("type") == "Fiducial"]
    if len(lists) != 1:
        raise ReadError(
            f"{p}: holds {len(lists)} point lists (markups of type Fiducial); "
            "save exactly one point list in the file"
        )
    markup = lists[0]
    space = markup.get("coordinateSystem", "LPS")
    if space not in SPACES:
        raise ReadError(f"{p}: coordinateSystem {space!r} is not one of {', '.join(SPACES)}")
    units = markup.get("coordinateUnits", "mm")
    if units not in ("mm", ["mm", "UCUM", "millimeter"]):
        raise ReadError(f"{p}: coordinateUnits {units!r}: vhm_viz reads millimetres (mm)")
    points = []
    for i, cp in enumerate(markup.get("controlPoints") or []):
        label = cp.get("label", "") if isinstance(cp, dict) else ""
        where = f"control point {i}" + (f" ({label})" if label else "")
        if not isinstance(cp, dict) or cp.get("positionStatus", "defined") == "undefined":
            raise ReadError(f"{p}: {where} has no position; place it or delete it in Slicer")
        try:
            xyz = np.asarray(cp["position"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            xyz = np.zeros(0)
        if xyz.shape != (3,) or not np.isfinite(xyz).all():
            raise ReadError(f"{p}: {where}: expected a position [x, y, z] of finite numbers")
        points.append(xyz)
    if not points:
        raise ReadError(f"{p}: the point list has no control points")
    return lps_points(points, space)


def write_markups(path, points, *, name: str = "anchors", space: str = "LPS") -> None:
    """Write LPS points as a Slicer point list (atomic), in ``space``.

    Parameters
    ----------
    path : str or os.PathLike
        ``*.mrk.json``.
    points : (n, 3) array_like
        Points in vhm_viz's world (LPS, mm).
    name : str
        The point list's name in Slicer; control points are labelled ``name-1``, ...
    space : {"LPS", "RAS"}
        The ``coordinateSystem`` the file is written in (positions converted to it).
    """
    if space not in SPACES:
        raise ValueError(f"space must be one of {', '.join(SPACES)}; got {space!r}")
    pts = lps_points(points, space)  # the half turn is its own inverse
    control = [
        {"id": str(i + 1), "label": f"{name}-{i + 1}", "position": xyz.tolist(),
         "positionStatus": "defined"}
        for i, xyz in enumerate(pts)
    ]  # fmt: skip
    markup = {
        "type": "Fiducial",
        "name": name,
        "coordinateSystem": space,
        "coordinateUnits": "mm",
        "controlPoints": control,
    }
    write_text(path, json_text({"@schema": MARKUPS_SCHEMA, "markups": [markup]}))
