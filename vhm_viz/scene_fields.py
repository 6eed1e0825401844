"""The scene file's fields: their defaults, parsers and validation, in one place.

Each parser takes the JSON value of one field and returns the normalised Python value
(float64 arrays, dicts of settings) or raises :class:`SceneError` naming the field
(``constraints.targets[3]``). Numeric settings must lie in their documented ranges
(:mod:`vhm_viz.core.limits`): ``alpha`` in [1e-4, 100], ``solver.max_iterations`` an
integer in [1, 1e6], ``solver.tolerance`` in (0, 0.1], ``solver.steps`` in [1, 1000],
``solver.anderson_window`` in [0, 100], anchor counts in [1, 1e5], ``data.resolution`` in
[1, 200], ``solution.contraction`` in [0, 1); the error names the field and the range.
:func:`explorer_v1_to_current` converts the explorer's old scene format.

``space`` names the world frame of the scene's coordinates: ``"LPS"`` (ITK's, what
:func:`vhm_viz.read_dataset` places scans in, and what every scene is written in) or
``"RAS"`` (Slicer's view and nibabel's), converted to LPS on loading by
:func:`lps_fields`. 3D Slicer point lists (``{"markups": "points.mrk.json"}``) carry
their own frame (:mod:`vhm_viz.io.markups`).
"""

from __future__ import annotations

import copy
import json
import math
import os
from pathlib import Path

import numpy as np

from vhm_viz.core.errors import SettingError
from vhm_viz.core.limits import check_setting
from vhm_viz.core.solver import DEFAULT_ANDERSON_WINDOW
from vhm_viz.io.errors import ReadError, first_line
from vhm_viz.io.markups import RAS_TO_LPS, SPACES, lps_points, read_markups

__all__ = [
    "SceneError",
    "MAX_SCENE_BYTES",
    "MAX_SCENE_ROWS",
    "check_scene_size",
    "check_scene_values",
    "SCENE_FORMAT",
    "SCENE_VERSION",
    "SCENE_FIELDS",
    "CONSTRAINT_FIELDS",
    "DEFAULT_SOLVER",
    "DEFAULT_SPACE",
    "parse_setting",
    "parse_space",
    "constraint_markups",
    "lps_fields",
    "parse_cage",
    "parse_anchors",
    "parse_constraints",
    "parse_mode",
    "parse_solver",
    "parse_data",
    "parse_map",
    "parse_solution",
    "parse_contraction",
    "explorer_data_reference",
    "explorer_v1_to_current",
    "to_lists",
]

SCENE_FORMAT = "vhm_viz.scene"
SCENE_VERSION = 1
DEFAULT_SOLVER = {
    "max_iterations": 1000,
    "tolerance": 1e-6,
    "init": "identity",
    "steps": 1,
    "anderson_window": DEFAULT_ANDERSON_WINDOW,
}
#: The frame scenes are written in (and read in when they name none).
DEFAULT_SPACE = "LPS"
SCENE_FIELDS = {
    "format",
    "version",
    "space",
    "cage",
    "anchors",
    "constraints",
    "mode",
    "alpha",
    "solver",
    "data",
    "solution",
    "map",
}
#: Version of what a stored map's digest covers (:meth:`Scene.map_inputs`): a change of
#: the solver that changes its results must change this, so that old maps are re-solved.

CONSTRAINT_FIELDS = ("positions", "targets", "jacobian_points", "jacobians")

#: The largest scene file read (bytes): far beyond any scene of :data:`MAX_SCENE_ROWS`
#: rows written by vhm_viz, far below what parsing a file into Python objects can hold
#: (tens of bytes of memory per byte of JSON).
MAX_SCENE_BYTES = 64 * 2**20
#: The most rows an array of a scene may hold (anchors, cage vertices and faces,
#: constraints, rotations; twice this for a stored map's coefficients, one per cage vertex
#: and face): the upper end of the documented anchor counts (:mod:`vhm_viz.core.limits`).
#: A dense harmonic map over that many anchors or cage elements does not fit in memory.
MAX_SCENE_ROWS = 100_000
#: The largest magnitude of a scene's coordinates and matrix entries: far beyond any model
#: in any unit, far enough below the float64 range that products and squares of
#: coordinates (distances, determinants) stay finite.
MAX_SCENE_VALUE = 1e15
#: The largest magnitude of a scene's integers (cage face indices): exact in float64.
MAX_SCENE_INTEGER = 2**53


class SceneError(ValueError):
    """A malformed scene; ``field`` names the offending field (dotted path)."""

    def __init__(self, field_name: str, message: str, source: str | None = None):
        self.field = field_name
        self.message = message
        where = f"{source}: " if source else ""
        what = (
            f"scene {field_name}" if field_name.startswith("(") else (f"scene field '{field_name}'")
        )
        super().__init__(f"{where}{what}: {message}")


# ----------------------------------------------------------------------------------------
# validation helpers
# ----------------------------------------------------------------------------------------


def check_scene_size(path, size: int) -> None:
    """Refuse a scene file of ``size`` bytes beyond :data:`MAX_SCENE_BYTES`, before reading."""
    if size > MAX_SCENE_BYTES:
        raise SceneError(
            "(file)",
            f"{size} bytes: a scene file may hold at most {MAX_SCENE_BYTES} bytes (keep large "
            "point sets in their own files: anchors, cage)",
            str(path),
        )


def _shown(value) -> str:
    """A short text of a JSON value for a message (containers by their type and length)."""
    if isinstance(value, (list, dict)):
        return f"{'a list' if isinstance(value, list) else 'an object'} of {len(value)}"
    return json.dumps(value)[:40] if isinstance(value, (str, int, float, type(None))) else "?"


def _number(value, name: str, *, positive: bool = False, integer: bool = False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(name, f"expected a number, got {_shown(value)}")
    if not math.isfinite(value):
        raise SceneError(name, f"expected a finite number, got {value}")
    if integer:
        if isinstance(value, float) and not value.is_integer():
            raise SceneError(name, f"expected an integer, got {value}")
        if abs(value) >= MAX_SCENE_INTEGER:
            raise SceneError(name, f"{value:g} is out of range (magnitude below 2**53)")
        value = int(value)
    elif abs(value) > MAX_SCENE_VALUE:
        raise SceneError(name, f"{value:g} is out of range (magnitude at most {MAX_SCENE_VALUE:g})")
    if positive and value <= 0:
        raise SceneError(name, f"must be positive, got {value}")
    return value


def check_scene_values(values, name: str) -> np.ndarray:
    """``values`` as a float64 array, if every entry may stand in a scene file.

    The rule the scene's coordinates and matrix entries are read with (finite, magnitude
    at most :data:`MAX_SCENE_VALUE`), for arrays edited in memory (the explorer's
    constraints): a scene that passes can be saved and read back.

    Raises
    ------
    SceneError
        Naming the first offending entry (``constraints.targets[0][2]``), as reading does.
    """
    array = np.asarray(values, dtype=np.float64)
    bad = ~(np.abs(array) <= MAX_SCENE_VALUE)  # NaN compares false
    if bad.any():
        index = np.unravel_index(np.argmax(bad), array.shape)
        _number(float(array[index]), name + "".join(f"[{i}]" for i in index))
    return array


def parse_setting(kind: str, value, name: str):
    """A numeric setting checked against its documented range (:mod:`vhm_viz.core.limits`)."""
    try:
        return check_setting(kind, value, name)
    except SettingError as exc:
        raise SceneError(name, exc.detail) from None


def _matrix(
    value, name: str, shape: tuple[int, ...], *, integer: bool = False, limit=MAX_SCENE_ROWS
) -> np.ndarray:
    """Nested lists -> array of ``shape`` (first dimension free when -1, at most ``limit``)."""
    if not isinstance(value, list):
        raise SceneError(name, f"expected a list, got {type(value).__name__}")
    if len(value) > limit:
        raise SceneError(name, f"{len(value)} rows: a scene may hold at most {limit}")
    if shape[1:]:
        rows = [
            _matrix(v, f"{name}[{i}]", (shape[1],) + shape[2:], integer=integer)
            for i, v in enumerate(value)
        ]
        if shape[0] >= 0 and len(rows) != shape[0]:
            raise SceneError(name, f"expected {shape[0]} rows, got {len(rows)}")
        inner = (shape[1],) + shape[2:] if shape[1] >= 0 else (0,)
        return np.array(rows, dtype=np.int64 if integer else np.float64).reshape(
            (len(rows), *inner)
        )
    if shape[0] >= 0 and len(value) != shape[0]:
        raise SceneError(name, f"expected {shape[0]} numbers, got {len(value)}")
    nums = [_number(v, f"{name}[{i}]", integer=integer) for i, v in enumerate(value)]
    return np.array(nums, dtype=np.int64 if integer else np.float64)


def _points(value, name: str) -> np.ndarray:
    return _matrix(value, name, (-1, 3)).reshape(-1, 3)


def to_lists(a: np.ndarray):
    """An array as nested lists (for JSON)."""
    return np.asarray(a).tolist()


def _path_text(value, name: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise SceneError(name, "expected a non-empty path string")
    try:
        os.fsencode(value)
        if "\0" in value:
            raise ValueError("a NUL character")
        Path(value).expanduser()
    except (ValueError, RuntimeError) as exc:  # (unencodable, NUL, ~unknown-user)
        raise SceneError(name, f"not a usable file name ({str(exc).splitlines()[0]})") from None
    return value


# ----------------------------------------------------------------------------------------
# field parsers
# ----------------------------------------------------------------------------------------


def unknown_field(name: str, allowed) -> SceneError:
    """The error for field ``name`` (a dotted path) where only ``allowed`` are known."""
    return SceneError(name, f"unknown field; use one of {', '.join(sorted(allowed))}")


def _check_fields(value, field: str, allowed) -> None:
    """Refuse keys of ``value`` (the scene's ``field``) that are not in ``allowed``."""
    extra = sorted(set(value) - set(allowed))
    if extra:
        raise unknown_field(f"{field}.{extra[0]}", allowed)


def auto_cage_options() -> list[str]:
    """The options of ``{"cage": {"auto": {...}}}``: :func:`vhm_viz.auto_cage`'s keywords."""
    import inspect

    from vhm_viz.autocage import auto_cage  # only a scene with an automatic cage needs it

    params = inspect.signature(auto_cage).parameters.values()
    return [p.name for p in params if p.kind is p.KEYWORD_ONLY and p.name != "return_report"]


def _object_of(value, field: str, allowed) -> dict:
    """``value``, a JSON object with keys from ``allowed`` only (else a SceneError)."""
    if not isinstance(value, dict):
        raise SceneError(field, "expected an object")
    _check_fields(value, field, allowed)
    return value


def _path_form(value, field: str) -> dict | None:
    """``{"path": text}`` of a file named as a string or as ``{"path": ...}``, else None."""
    if isinstance(value, str):
        return {"path": _path_text(value, field)}
    if isinstance(value, dict) and set(value) == {"path"}:
        return {"path": _path_text(value["path"], f"{field}.path")}
    return None


def parse_cage(value) -> dict:
    """``cage``: ``{"path"}``, ``{"auto": options}`` or ``{"vertices" (n, 3), "faces" (m, 3)}``."""
    if value == "auto":
        return {"auto": {}}
    path = _path_form(value, "cage")
    if path:
        return path
    if not isinstance(value, dict):
        raise SceneError("cage", 'expected a path, "auto" or an object')
    keys = set(value)
    if keys == {"auto"}:
        opts = value["auto"]
        if not isinstance(opts, dict):
            raise SceneError("cage.auto", "expected an object of auto_cage options")
        if opts:
            _check_fields(opts, "cage.auto", auto_cage_options())
        return {"auto": copy.deepcopy(opts)}
    if keys == {"vertices", "faces"}:
        v = _points(value["vertices"], "cage.vertices")
        f = _matrix(value["faces"], "cage.faces", (-1, 3), integer=True).reshape(-1, 3)
        if len(v) < 4:
            raise SceneError("cage.vertices", f"a cage needs at least 4 vertices, got {len(v)}")
        if len(f) < 4:
            raise SceneError("cage.faces", f"a cage needs at least 4 faces, got {len(f)}")
        bad = np.nonzero((f < 0).any(axis=1) | (f >= len(v)).any(axis=1))[0]
        if bad.size:
            raise SceneError(f"cage.faces[{bad[0]}]", f"vertex index out of range [0, {len(v)})")
        return {"vertices": v, "faces": f}
    _check_fields(keys, "cage", {"path", "auto", "vertices", "faces"})
    raise SceneError("cage", "expected one of {path}, {auto}, {vertices, faces}")


def parse_anchors(value) -> dict:
    """``anchors``: points (d, 3), ``{"path"}``, ``{"markups"}``, ``{"auto": d}``, lines."""
    path = _path_form(value, "anchors")
    if path:
        return path
    if isinstance(value, dict) and set(value) == {"markups"}:
        return {"markups": _path_text(value["markups"], "anchors.markups")}
    if isinstance(value, list):
        pts = _points(value, "anchors")
        if len(pts) == 0:
            raise SceneError("anchors", "no anchor points")
        return {"points": pts}
    if not isinstance(value, dict):
        raise SceneError("anchors", "expected a list of points or an object")
    keys = set(value)
    if keys == {"auto"}:
        return {"auto": parse_setting("anchor_count", value["auto"], "anchors.auto")}
    for kind in ("polylines", "skeleton"):
        if keys == {kind, "count"}:
            return {
                kind: _path_text(value[kind], f"anchors.{kind}"),
                "count": parse_setting("anchor_count", value["count"], "anchors.count"),
            }
    _check_fields(keys, "anchors", {"path", "markups", "auto", "polylines", "skeleton", "count"})
    raise SceneError(
        "anchors", "expected {path}, {markups}, {auto}, {polylines, count} or {skeleton, count}"
    )


def parse_constraints(value) -> dict:
    """``constraints``: positions, targets (r, 3), jacobian_points (s, 3), jacobians (s, 3, 3)."""
    _object_of(value, "constraints", CONSTRAINT_FIELDS)
    for required in ("positions", "targets"):
        if required not in value:
            raise SceneError(f"constraints.{required}", "missing")
    pos = _points(value["positions"], "constraints.positions")
    tgt = _points(value["targets"], "constraints.targets")
    if len(pos) == 0:
        raise SceneError("constraints.positions", "at least one position constraint is needed")
    if len(tgt) != len(pos):
        raise SceneError("constraints.targets", f"{len(tgt)} targets for {len(pos)} positions")
    jp = _points(value.get("jacobian_points", []), "constraints.jacobian_points")
    jac = _matrix(value.get("jacobians", []), "constraints.jacobians", (-1, 3, 3))
    jac = jac.reshape(-1, 3, 3)
    if len(jac) != len(jp):
        raise SceneError(
            "constraints.jacobians", f"{len(jac)} jacobians for {len(jp)} jacobian_points"
        )
    return {"positions": pos, "targets": tgt, "jacobian_points": jp, "jacobians": jac}


def parse_space(value) -> str:
    """``space``: the frame of the scene's coordinates, ``"LPS"`` or ``"RAS"``."""
    if value not in SPACES:
        raise SceneError(
            "space",
            f"expected {' or '.join(json.dumps(s) for s in SPACES)} (the world frame of the "
            f"scene's coordinates), got {json.dumps(value)[:40]}",
        )
    return value


def constraint_markups(value, resolve, space: str):
    """``constraints`` with each ``{"markups": path}`` of positions/targets read, in ``space``.

    Parameters
    ----------
    value : object
        The scene's ``constraints`` JSON value.
    resolve : callable(str) -> Path
        Resolves a path against the scene file's folder.
    space : {"LPS", "RAS"}
        The scene's frame: the points (read in LPS) are expressed in it, so that
        :func:`lps_fields` treats them like the inline ones.

    Returns
    -------
    object
        ``value`` itself, or a copy with point lists in place of the markups references.
    """
    if not isinstance(value, dict):
        return value
    out = dict(value)
    for name in ("positions", "targets"):
        ref = value.get(name)
        if isinstance(ref, dict) and set(ref) == {"markups"}:
            field_name = f"constraints.{name}.markups"
            try:
                points = read_markups(resolve(_path_text(ref["markups"], field_name)))
            except (OSError, ReadError) as exc:
                raise SceneError(field_name, first_line(exc)) from None
            out[name] = lps_points(points, space).tolist()
    return out


def lps_fields(space: str, fields: dict) -> dict:
    """The parsed geometric fields of a scene written in ``space``, in LPS.

    RAS = diag(-1, -1, 1) LPS, a half turn about z: points (inline cage vertices,
    anchors, constraint positions, targets and Jacobian points) are turned by it, matrices
    (Jacobians, the solution's local matrices) conjugated, ``J_LPS = F J_RAS F``, and a
    stored map's coefficient rows turned (the harmonic basis is invariant under the
    rotation: Ben-Chen, Weber and Gotsman 2009 build it from
    distances and normals alone).

    Parameters
    ----------
    space : {"LPS", "RAS"}
    fields : dict
        ``cage``, ``anchors``, ``constraints``, ``solution`` and ``map`` as their
        parsers return them.

    Returns
    -------
    dict
        ``fields`` (unchanged for LPS), converted copies for RAS.
    """
    if space == "LPS":
        return fields
    f = RAS_TO_LPS
    out = dict(fields)
    if "vertices" in fields["cage"]:
        out["cage"] = {**fields["cage"], "vertices": fields["cage"]["vertices"] @ f}
    if "points" in fields["anchors"]:
        out["anchors"] = {"points": fields["anchors"]["points"] @ f}
    c = fields["constraints"]
    out["constraints"] = {
        **{name: c[name] @ f for name in ("positions", "targets", "jacobian_points")},
        "jacobians": f @ c["jacobians"] @ f,
    }
    if fields.get("solution") is not None:
        out["solution"] = f @ fields["solution"] @ f
    if fields.get("map") is not None:
        out["map"] = {**fields["map"], "coefficients": fields["map"]["coefficients"] @ f}
    return out


def parse_mode(value) -> str:
    """``mode``: ``"rigid"`` or ``"similar"``."""
    if value not in ("rigid", "similar"):
        raise SceneError("mode", f'expected "rigid" or "similar", got {_shown(value)}')
    return value


def parse_solver(value) -> dict:
    """``solver``: every key of :data:`DEFAULT_SOLVER`, missing ones at their defaults."""
    _object_of(value, "solver", DEFAULT_SOLVER)
    out = dict(DEFAULT_SOLVER)
    out.update(value)
    for key in ("max_iterations", "tolerance", "steps", "anderson_window"):
        out[key] = parse_setting(key, out[key], f"solver.{key}")
    if out["init"] not in ("identity", "previous", "solution"):
        raise SceneError(
            "solver.init",
            f'expected "identity", "previous" or "solution", got {_shown(out["init"])}',
        )
    return {k: out[k] for k in DEFAULT_SOLVER}


def parse_data(value) -> dict | None:
    """``data``: ``{"path": str}``, ``{"bar": kind, "resolution": n}`` or None."""
    if value is None:
        return None
    if isinstance(value, str):
        return {"path": _path_text(value, "data")}
    if isinstance(value, dict) and set(value) <= {"bar", "resolution"} and "bar" in value:
        if not isinstance(value["bar"], str):
            raise SceneError("data.bar", "expected the name of a bar scenario")
        res = parse_setting("resolution", value.get("resolution", 39), "data.resolution")
        return {"bar": value["bar"], "resolution": res}
    raise SceneError("data", 'expected a path or {"bar": kind, "resolution": n}')


def parse_map(value) -> dict | None:
    """``map``: ``{"coefficients": (n + m, 3) array, "inputs": sha256 hex}`` or None."""
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) != {"coefficients", "inputs"}:
        raise SceneError("map", 'expected {"coefficients": [[x, y, z], ...], "inputs": "..."}')
    inputs = value["inputs"]
    if not (isinstance(inputs, str) and len(inputs) == 64
            and all(ch in "0123456789abcdef" for ch in inputs)):  # fmt: skip
        raise SceneError("map.inputs", "expected a sha256 digest (64 hexadecimal digits)")
    coefficients = _matrix(value["coefficients"], "map.coefficients", (-1, 3),
                           limit=2 * MAX_SCENE_ROWS)  # fmt: skip
    return {"coefficients": coefficients.reshape(-1, 3), "inputs": inputs}


def parse_solution(value) -> np.ndarray | None:
    """``solution.rotations``: the anchors' local matrices (d, 3, 3), or None."""
    if value is None:
        return None
    keys = set(value) if isinstance(value, dict) else set()
    if not {"rotations"} <= keys <= {"rotations", "contraction"}:
        raise SceneError("solution", 'expected {"rotations": [[[..3..], ...], ...]}')
    return _matrix(value["rotations"], "solution.rotations", (-1, 3, 3)).reshape(-1, 3, 3)


def parse_contraction(value) -> float | None:
    """``solution.contraction``: the solver's contraction rate in [0, 1), or None."""
    if not isinstance(value, dict) or value.get("contraction") is None:
        return None
    return parse_setting("contraction", value["contraction"], "solution.contraction")


def explorer_data_reference(src):
    """The old explorer's data reference (``{"path": p}`` or a bar) in this format's terms."""
    if not isinstance(src, dict) or not src:
        return None
    if "path" in src:
        return src["path"]
    return src


def explorer_v1_to_current(d: dict) -> dict:
    """The explorer's old single-file scene (``{"vhm_viz_scene": 1, ...}``) as this format."""
    from scipy.spatial.transform import Rotation  # here: importing it is slow, rarely used

    if d.get("vhm_viz_scene") != 1:
        version = d.get("vhm_viz_scene")
        raise SceneError("vhm_viz_scene", f"unsupported explorer scene version {version}")
    if not d.get("cage"):
        raise SceneError("cage", "the explorer scene has no cage")
    try:
        positions = [c["point"] for c in d.get("positions", [])]
        targets = [c["target"] for c in d.get("positions", [])]
        jac_points = [c["point"] for c in d.get("jacobians", [])]
        jacobians = [
            (
                float(c["scale"])
                * Rotation.from_euler("xyz", c["angles"], degrees=True).as_matrix()
            ).tolist()
            for c in d.get("jacobians", [])
        ]
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneError("positions", f"malformed explorer constraint ({exc})") from None
    solver = {k: v for k, v in (d.get("solver") or {}).items() if k in DEFAULT_SOLVER}
    out = {
        "format": SCENE_FORMAT,
        "version": SCENE_VERSION,
        "cage": d["cage"],
        "anchors": d.get("anchors", []),
        "constraints": {
            "positions": positions,
            "targets": targets,
            "jacobian_points": jac_points,
            "jacobians": jacobians,
        },
        "mode": d.get("mode", "rigid"),
        "alpha": d.get("alpha", 0.01),
        "solver": solver,
    }
    data = explorer_data_reference(d.get("data"))
    if data is not None:
        out["data"] = data
    if d.get("rotations") is not None:
        out["solution"] = {"rotations": d["rotations"]}
        out["solver"]["init"] = "solution"
    return out
