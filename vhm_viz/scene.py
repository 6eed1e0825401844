"""Versioned JSON scene files: cage, anchors, constraints, mode, alpha, solver settings.

A scene describes one deformation completely, so it can be saved, shared and re-run from
the command line (``vhm-viz deform INPUT --scene SCENE``) or in ParaView. Format,
version 1::

    {
      "format": "vhm_viz.scene",
      "version": 1,
      "space": "LPS" | "RAS",                    # the frame of the coordinates below
      "cage": "cage.obj"                         # a path (relative to the scene file), or
              | {"path": "cage.obj"}             # the same, or
              | {"vertices": [[x, y, z], ...], "faces": [[i, j, k], ...]}   # inline, or
              | "auto" | {"auto": {"max_faces": 300, ...}},  # vhm_viz.auto_cage of the data
      "anchors": [[x, y, z], ...]                # explicit, or
                 | "anchors.json"                # a file `vhm-viz anchors` writes, or
                 | {"markups": "anchors.mrk.json"}   # a 3D Slicer point list, or
                 | {"auto": 24}                  # vhm_viz.auto_anchors, or
                 | {"polylines": "lines.off", "count": 24}   # OFF polylines, or
                 | {"skeleton": "hand.tgf", "count": 24},    # libigl TGF skeleton
      "constraints": {
        "positions": [[x, y, z], ...], "targets": [[x, y, z], ...],   # (or each
                     # {"markups": "points.mrk.json"}, read when the scene loads)
        "jacobian_points": [[x, y, z], ...], "jacobians": [[[..3..], [..3..], [..3..]], ...]
      },
      "mode": "rigid" | "similar",
      "alpha": 0.01,
      "solver": {"max_iterations": 1000, "tolerance": 1e-6, "init": "identity",
                 "steps": 1, "anderson_window": 10},
      "data": "model.vtp" | {"bar": "bend-u", "resolution": 39},   # optional
      "solution": {"rotations": [[[..3..], [..3..], [..3..]], ...],   # optional
                   "contraction": 0.97},
      "map": {"coefficients": [[x, y, z], ...], "inputs": "sha256 hex"}   # optional
    }

``space`` is the world frame the scene's coordinates are written in: ``"LPS"`` (the
default, ITK's frame, in which :func:`vhm_viz.read_dataset` places scans; every scene is
written in it) or ``"RAS"`` (Slicer's and nibabel's), whose coordinates are converted to
LPS on loading (``RAS = diag(-1, -1, 1) LPS``). Files a scene references (cage, anchors,
polylines) hold coordinates in the data's own world (LPS for scans); Slicer markups say
their frame themselves.

``data`` names the dataset the scene was made for (a path relative to the scene file, or a
bundled bar scenario); the explorer re-opens it, the command line takes its input
explicitly. ``solution`` holds the anchors' local matrices of a solved state (one per
anchor) and the contraction rate the solver measured when it reached it; ``"init":
"solution"`` starts the solver there, so a scene saved after interactive editing reproduces
the same local minimum of the (non-convex) problem -- and, when the stored state still meets
the stopping rule, the same result to rounding (see :meth:`Deformer.solve`).

``map`` holds the solved harmonic map itself (its coefficients ``[a; b]``, one row per cage
vertex then per face) with a digest of everything the solve depended on: the cage and
anchors as built, the constraints, mode, alpha, solver settings and stored solution
(:meth:`Scene.map_inputs`). :meth:`Scene.record_map` writes it for a converged solve;
:meth:`Scene.map_for` hands it back only while the digest still matches, so a scene edited
by hand (or a cage file changed) is solved again. ParaView's filters use it: no rank then
builds and solves the deformer, which on a large cage takes seconds and hundreds of
megabytes on every rank.

Jacobians are user-facing, ``J[i][j] = d f_i / d x_j``. ``jacobian_points``/``jacobians``,
``mode``, ``alpha``, ``solver`` (and each solver key), ``data`` and ``solution`` are
optional; saving writes every field with its value (one point per line), so
``Scene.load(path).save(other)`` writes a normalised file and
``Scene.from_dict(s.to_dict()) == s`` exactly (floats are written with full precision).
Unknown fields, unknown versions and malformed values raise :class:`SceneError`, whose
message names the offending field (``constraints.targets[3]``); each field's default, parser
and documented range live in :mod:`vhm_viz.scene_fields`.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vhm_viz.core.anchors import anchors_from_polylines
from vhm_viz.core.cage import MIN_FACE_ANGLE, Cage
from vhm_viz.core.deformer import Deformer
from vhm_viz.core.errors import SettingError
from vhm_viz.core.harmonic_map import HarmonicMap
from vhm_viz.io import (
    JSONTextError,
    json_text,
    parse_json,
    read_anchors,
    read_cage,
    read_polylines,
    read_tgf,
    write_text,
)
from vhm_viz.io.markups import read_markups
from vhm_viz.scene_fields import (
    CONSTRAINT_FIELDS,
    DEFAULT_SOLVER,
    DEFAULT_SPACE,
    SCENE_FIELDS,
    SCENE_FORMAT,
    SCENE_VERSION,
    SceneError,
    check_scene_size,
    constraint_markups,
    explorer_data_reference,
    explorer_v1_to_current,
    lps_fields,
    parse_anchors,
    parse_cage,
    parse_constraints,
    parse_contraction,
    parse_data,
    parse_map,
    parse_mode,
    parse_setting,
    parse_solution,
    parse_solver,
    parse_space,
    to_lists,
    unknown_field,
)

__all__ = [
    "Scene",
    "SceneError",
    "SolvedMap",
    "NotConverged",
    "SCENE_FORMAT",
    "SCENE_VERSION",
    "DEFAULT_SOLVER",
    "MAP_INPUTS_VERSION",
]

#: Version of what a stored map's digest covers (:meth:`Scene.map_inputs`): a change of
#: the solver that changes its results must change this, so that old maps are re-solved.
MAP_INPUTS_VERSION = "vhm_viz.map/1"


@dataclass(eq=False)
class Scene:
    """A deformation scene (see the module documentation for the JSON format).

    Attributes
    ----------
    cage : dict
        ``{"path": str}``, ``{"vertices": (n, 3) array, "faces": (m, 3) array}`` or
        ``{"auto": dict_of_auto_cage_options}``.
    anchors : dict
        ``{"points": (d, 3) array}``, ``{"path": anchors_json}``,
        ``{"markups": slicer_point_list}``, ``{"auto": d}``,
        ``{"polylines": path, "count": d}`` or ``{"skeleton": path, "count": d}``.
    constraints : dict
        ``positions``, ``targets`` (r, 3); ``jacobian_points`` (s, 3), ``jacobians``
        (s, 3, 3) -- float64 arrays.
    mode : str
    alpha : float
    solver : dict
        ``max_iterations``, ``tolerance``, ``init``, ``steps``, ``anderson_window``.
    data : dict or None
        ``{"path": str}`` or ``{"bar": kind, "resolution": int}``.
    solution : (d, 3, 3) ndarray or None
        The anchors' local matrices of a solved state.
    solution_contraction : float or None
        The solver's contraction-rate estimate for that state.
    stored_map : dict or None
        ``{"coefficients": (n + m, 3) array, "inputs": str}``: a converged solve's map and
        the digest of its inputs (:meth:`record_map`, :meth:`map_for`).
    base_dir : Path or None
        Directory relative paths are resolved against (the scene file's); not saved.
    notes : list of str
        What loading had to do that the user should know (an old file converted); not
        saved.
    """

    cage: dict
    anchors: dict
    constraints: dict
    mode: str = "rigid"
    alpha: float = 0.01
    solver: dict = field(default_factory=lambda: dict(DEFAULT_SOLVER))
    data: dict | None = None
    solution: np.ndarray | None = None
    solution_contraction: float | None = None
    stored_map: dict | None = None
    base_dir: Path | None = None
    notes: list = field(default_factory=list)

    # ------------------------------------------------------------------ (de)serialise
    @classmethod
    def from_dict(
        cls, data: Any, *, source: str | None = None, base_dir: str | os.PathLike | None = None
    ) -> Scene:
        """Validate a parsed JSON object and build the scene.

        Raises
        ------
        SceneError
            Naming the offending field.
        """
        try:
            return cls._from_dict(data, base_dir)
        except SceneError as exc:
            if source is None:
                raise
            raise SceneError(exc.field, exc.message, source) from None

    @classmethod
    def _from_dict(cls, data, base_dir) -> Scene:
        if not isinstance(data, dict):
            raise SceneError("(top level)", f"expected a JSON object, got {type(data).__name__}")
        if "vhm_viz_scene" in data and "format" not in data:
            scene = cls._from_dict(explorer_v1_to_current(data), base_dir)
            scene.notes.append(
                "converted from the explorer's old scene format; save the scene to write it "
                "in the current format"
            )
            return scene
        fmt = data.get("format")
        if fmt != SCENE_FORMAT:
            raise SceneError("format", f"expected {SCENE_FORMAT!r}, got {json.dumps(fmt)}")
        if "version" not in data:
            raise SceneError("version", "missing")
        version = data["version"]
        if isinstance(version, bool) or not isinstance(version, int):
            raise SceneError("version", f"expected an integer, got {json.dumps(version)}")
        if version != SCENE_VERSION:
            raise SceneError(
                "version",
                f"unsupported version {version} (this vhm_viz reads version {SCENE_VERSION})",
            )
        unknown = sorted(set(data) - SCENE_FIELDS)
        if unknown:
            raise unknown_field(unknown[0], SCENE_FIELDS)
        for required in ("cage", "anchors", "constraints"):
            if required not in data:
                raise SceneError(required, "missing")
        base = Path(base_dir) if base_dir is not None else None
        space = parse_space(data.get("space", DEFAULT_SPACE))
        constraints = constraint_markups(
            data["constraints"], lambda text: _resolve(base, text), space
        )
        geometry = lps_fields(
            space,
            {
                "cage": parse_cage(data["cage"]),
                "anchors": parse_anchors(data["anchors"]),
                "constraints": parse_constraints(constraints),
                "solution": parse_solution(data.get("solution")),
                "map": parse_map(data.get("map")),
            },
        )
        scene = cls(
            cage=geometry["cage"],
            anchors=geometry["anchors"],
            constraints=geometry["constraints"],
            mode=parse_mode(data.get("mode", "rigid")),
            alpha=parse_setting("alpha", data.get("alpha", 0.01), "alpha"),
            solver=parse_solver(data.get("solver", {})),
            data=parse_data(data.get("data")),
            solution=geometry["solution"],
            solution_contraction=parse_contraction(data.get("solution")),
            stored_map=geometry["map"],
            base_dir=base,
        )
        if space != DEFAULT_SPACE:
            scene.notes.append(
                f"converted the scene's coordinates from {space} to {DEFAULT_SPACE}; save the "
                f"scene to write it in {DEFAULT_SPACE}"
            )
        if scene.solver["init"] == "solution":
            if scene.solution is None:
                raise SceneError("solver.init", '"solution" needs the scene\'s "solution" field')
            if "points" in scene.anchors and len(scene.solution) != len(scene.anchors["points"]):
                raise SceneError(
                    "solution.rotations",
                    f"{len(scene.solution)} matrices for {len(scene.anchors['points'])} anchors",
                )
        return scene

    def to_dict(self) -> dict:
        """The JSON object (every field written, normalised)."""
        cage: Any
        if "path" in self.cage:
            cage = {"path": self.cage["path"]}
        elif "auto" in self.cage:
            cage = {"auto": copy.deepcopy(self.cage["auto"])}
        else:
            cage = {
                "vertices": to_lists(self.cage["vertices"]),
                "faces": to_lists(self.cage["faces"]),
            }
        if "points" in self.anchors:
            anchors: Any = to_lists(self.anchors["points"])
        elif "path" in self.anchors:
            anchors = self.anchors["path"]
        else:  # markups, auto, polylines, skeleton
            anchors = copy.deepcopy(self.anchors)
        c = self.constraints
        out = {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "space": DEFAULT_SPACE,
            "cage": cage,
            "anchors": anchors,
            "constraints": {k: to_lists(c[k]) for k in CONSTRAINT_FIELDS},
            "mode": self.mode,
            "alpha": self.alpha,
            "solver": dict(self.solver),
        }
        if self.data is not None:
            out["data"] = self.data["path"] if "path" in self.data else dict(self.data)
        if self.solution is not None:
            out["solution"] = {"rotations": to_lists(self.solution)}
            if self.solution_contraction is not None:
                out["solution"]["contraction"] = float(self.solution_contraction)
        if self.stored_map is not None:
            out["map"] = {"coefficients": to_lists(self.stored_map["coefficients"]),
                          "inputs": self.stored_map["inputs"]}  # fmt: skip
        return out

    @classmethod
    def loads(cls, text: str, *, source: str | None = None, base_dir=None) -> Scene:
        """Parse a scene from JSON text."""
        try:
            data = parse_json(text)
        except JSONTextError as exc:
            raise SceneError("(json)", str(exc), source) from None
        return cls.from_dict(data, source=source, base_dir=base_dir)

    def dumps(self) -> str:
        """JSON text (one point per line, floats at full precision)."""
        return json_text(self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> Scene:
        """Read a scene file; relative paths in it resolve against its directory.

        Raises
        ------
        FileNotFoundError
        SceneError
        """
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"no such scene file: {p}")
        check_scene_size(p, p.stat().st_size)
        try:
            text = p.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise SceneError("(json)", "not a text file", str(p)) from None
        scene = cls.loads(text, source=str(p), base_dir=p.parent)
        # earlier explorers kept the data reference and the solution in a sidecar file
        sidecar = p.with_name(p.stem + ".explorer.json")
        if sidecar.is_file() and scene.data is None and scene.solution is None:
            scene._merge_sidecar(sidecar)
        return scene

    def _merge_sidecar(self, sidecar: Path) -> None:
        try:
            side = parse_json(sidecar.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, JSONTextError) as exc:
            raise SceneError("(sidecar)", f"{sidecar.name} is unreadable ({exc})") from None
        if not isinstance(side, dict):
            return
        try:
            self.data = parse_data(explorer_data_reference(side.get("data")))
            rotations = side.get("rotations")
            if rotations is not None:
                self.solution = parse_solution({"rotations": rotations})
        except SceneError as exc:
            raise SceneError(f"(sidecar) {exc.field}", exc.message, str(sidecar)) from None
        self.notes.append(
            f"read the data reference and solution from the old sidecar {sidecar.name}; "
            "save the scene to keep them in one file"
        )

    def save(self, path: str | os.PathLike) -> None:
        """Write the scene atomically (temporary file in the same directory, then rename)."""
        write_text(path, self.dumps())

    def __eq__(self, other) -> bool:
        if not isinstance(other, Scene):
            return NotImplemented
        return json.dumps(self.to_dict(), sort_keys=True) == json.dumps(
            other.to_dict(), sort_keys=True
        )

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_deformer(
        cls, deformer, *, cage_path: str | None = None, solver: dict | None = None
    ) -> Scene:
        """The scene of an existing deformer (inline cage unless ``cage_path`` is given)."""
        c = deformer.constraints
        cage = (
            {"path": cage_path}
            if cage_path is not None
            else {
                "vertices": np.array(deformer.cage.vertices, dtype=np.float64),
                "faces": np.array(deformer.cage.faces, dtype=np.int64),
            }
        )
        settings = dict(DEFAULT_SOLVER)
        settings["anderson_window"] = int(deformer.anderson_window)
        settings.update(solver or {})
        return cls(
            cage=cage,
            anchors={"points": np.array(deformer.anchors, dtype=np.float64)},
            constraints={
                "positions": np.array(c["positions"], dtype=np.float64).reshape(-1, 3),
                "targets": np.array(c["targets"], dtype=np.float64).reshape(-1, 3),
                "jacobian_points": np.array(c["jacobian_points"], dtype=np.float64).reshape(-1, 3),
                "jacobians": np.array(c["jacobians"], dtype=np.float64).reshape(-1, 3, 3),
            },
            mode=deformer.mode,
            alpha=float(deformer.alpha),
            solver=parse_solver(settings),
        )

    def referenced_files(self) -> list[Path]:
        """Every file the scene reads (cage, anchors, rigidity lines, data), resolved."""
        paths = []
        if "path" in self.cage:
            paths.append(self._resolve_path(self.cage["path"]))
        for key in ("path", "markups", "polylines", "skeleton"):
            if key in self.anchors:
                paths.append(self._resolve_path(self.anchors[key]))
        if self.data is not None and "path" in self.data:
            paths.append(self._resolve_path(self.data["path"]))
        return paths

    @property
    def cage_file(self) -> Path | None:
        """The file the cage is read from, resolved; None for an inline or automatic cage.

        Messages about the cage name it: a user may have several cages at hand.
        """
        return self._resolve_path(self.cage["path"]) if "path" in self.cage else None

    @property
    def needs_data(self) -> bool:
        """Whether building needs the data to deform (automatic cage or anchors)."""
        return "auto" in self.cage or "auto" in self.anchors

    def _resolve_path(self, text: str) -> Path:
        return _resolve(self.base_dir, text)

    def build_cage(self, data=None):
        """The scene's cage (a :class:`vhm_viz.Cage`); ``data`` is needed for ``"auto"``."""
        if "path" in self.cage:
            return read_cage(self._resolve_path(self.cage["path"]))
        if "auto" in self.cage:
            if data is None:
                raise SceneError("cage", '"auto" needs the data to deform')
            # imported here: only a scene with an automatic cage needs vhm_viz.autocage
            from vhm_viz.autocage import auto_cage

            try:
                return auto_cage(data, **self.cage["auto"])
            except SettingError as exc:  # an option's value, named as the scene's field
                raise SceneError(f"cage.auto.{exc.field}", exc.detail) from None
        return Cage(self.cage["vertices"], self.cage["faces"])

    def build_anchors(self, cage, data=None) -> np.ndarray:
        """The anchor points (d, 3)."""
        a = self.anchors
        if "points" in a:
            return np.array(a["points"], dtype=np.float64)
        if "path" in a:
            return read_anchors(self._resolve_path(a["path"]))
        if "markups" in a:
            return read_markups(self._resolve_path(a["markups"]))
        if "auto" in a:
            if data is None:
                raise SceneError("anchors", '"auto" needs the data to deform')
            # a volume's automatic cage encloses the region above its threshold: the
            # anchors go in that region too
            options = self.cage.get("auto") if isinstance(self.cage.get("auto"), dict) else {}
            # imported here: only automatic anchors need vhm_viz.autocage
            from vhm_viz.autocage import auto_anchors

            # the map checks the data against the cage itself (deform's --outside): the
            # anchors cover the part of the shape the cage holds
            return auto_anchors(
                data,
                cage,
                int(a["auto"]),
                threshold=options.get("threshold"),
                scalars=options.get("scalars"),
                outside="ignore",
            )
        if "polylines" in a:
            pts, edges = read_polylines(self._resolve_path(a["polylines"]))
        else:
            pts, edges = read_tgf(self._resolve_path(a["skeleton"]))
        return anchors_from_polylines(pts, edges, int(a["count"]))

    def build(self, data=None, cage=None, anchors=None):
        """A :class:`~vhm_viz.Deformer` with the scene's constraints (not solved).

        Parameters
        ----------
        data : pyvista.DataSet, optional
            The data to deform (needed for automatic cages and anchors).
        cage : Cage, optional
            Use this cage instead of the scene's (e.g. the cage on a filter's port 1).
        anchors : (d, 3) float array, optional
            The anchors as :meth:`build_anchors` gives them for ``cage``, when the caller
            has them already.
        """
        if cage is None:
            cage = self.build_cage(data)
        if anchors is None:
            anchors = self.build_anchors(cage, data)
        dfm = Deformer(
            cage,
            anchors,
            mode=self.mode,
            alpha=self.alpha,
            anderson_window=int(self.solver["anderson_window"]),
        )
        dfm.set_constraints(**self.constraint_arguments())
        return dfm

    def solve_map(
        self,
        data=None,
        cage=None,
        *,
        progress=None,
        reuse_stored: bool = True,
        on_note=None,
        **overrides,
    ) -> SolvedMap:
        """The scene's solved map: the one path from a scene to a deformation.

        Builds the cage (or takes ``cage``) and the anchors, then either takes the map
        stored in the scene, while its inputs still hold (:meth:`map_for`), or builds the
        deformer and solves it with the scene's settings (:meth:`solve`). A solve that
        does not converge is returned as it is: callers decide with
        :meth:`SolvedMap.require_converged`.

        Parameters
        ----------
        data : pyvista.DataSet, optional
            The data to deform (needed for automatic cages and anchors).
        cage : Cage, optional
            Use this cage instead of the scene's.
        progress : callable(fraction, message), optional
            Called after each solve step.
        reuse_stored : bool
            Use the stored map when it holds (no deformer is built then). Solver
            ``overrides`` always solve anew.
        on_note : callable(str), optional
            Called with each of the notes (see :class:`SolvedMap`) as soon as it is known,
            before the solve.
        **overrides
            Solver settings, as for :meth:`solve`.

        Returns
        -------
        SolvedMap
        """
        if cage is None:
            cage = self.build_cage(data)
        notes = [*self.notes, *(f"cage repaired: {r}" for r in cage.repairs)]
        thin = cage.thin_faces
        if len(thin):
            notes.append(
                f"the cage has {len(thin)} faces with an angle below {MIN_FACE_ANGLE:g} "
                f"degrees (e.g. face {int(thin[0])}): the smoothness weight collapses on "
                "them and the result may be poor"
            )
        if on_note is not None:
            for note in notes:
                on_note(note)
        anchors = self.build_anchors(cage, data)
        if reuse_stored and not overrides:
            stored = self.map_for(cage, anchors)
            if stored is not None:
                return SolvedMap(self, stored, None, [], notes)
        deformer = self.build(data=data, cage=cage, anchors=anchors)
        reports = self.solve(deformer, progress=progress, **overrides)
        return SolvedMap(self, deformer.harmonic_map, deformer, reports, notes)

    def map_inputs(self, cage, anchors) -> str:
        """Digest (sha256, hex) of what a solve of this scene depends on.

        The cage and anchors as built (``cage.vertices``/``faces``, ``anchors``: a cage
        or anchors file that changes changes it), the constraints, mode, alpha, every
        solver setting and the stored solution (a starting point), and
        :data:`MAP_INPUTS_VERSION`.
        """
        h = hashlib.sha256(MAP_INPUTS_VERSION.encode())

        def add(a, dtype):
            a = np.ascontiguousarray(a, dtype=dtype)
            h.update(repr(a.shape).encode())
            h.update(a.tobytes())

        add(cage.vertices, np.float64)
        add(cage.faces, np.int64)
        add(anchors, np.float64)
        for name in CONSTRAINT_FIELDS:
            add(self.constraints[name], np.float64)
        settings = {k: v for k, v in self.solver.items() if isinstance(v, (int, float, str))}
        text = json.dumps([self.mode, repr(float(self.alpha)), settings], sort_keys=True)
        h.update(text.encode())
        if self.solution is not None:
            add(self.solution, np.float64)
            h.update(repr(self.solution_contraction).encode())
        return h.hexdigest()

    def record_map(self, deformer) -> bool:
        """Store ``deformer``'s solved map in the scene (written by :meth:`save`).

        Only a converged solve of this scene's constraints is stored (the one
        :meth:`solve` ran); otherwise any stored map is dropped. Returns whether a map
        was stored.
        """
        self.stored_map = None
        report = deformer.last_report
        if report is None or not report.converged:
            return False
        c, mine = deformer.constraints, self.constraints
        for name in CONSTRAINT_FIELDS:
            theirs = np.asarray(c[name], dtype=np.float64)
            if theirs.size != mine[name].size or not np.array_equal(
                theirs.reshape(mine[name].shape), mine[name]
            ):
                return False
        self.stored_map = {
            "coefficients": np.array(deformer.harmonic_map.coefficients, dtype=np.float64),
            "inputs": self.map_inputs(deformer.cage, deformer.anchors),
        }
        return True

    def map_for(self, cage, anchors):
        """The stored map (a :class:`~vhm_viz.HarmonicMap` on ``cage``), if it still holds.

        None without a stored map, or when the scene's inputs (with this ``cage`` and
        ``anchors``, as :meth:`build` would use them) differ from those it was solved for.
        """
        stored = self.stored_map
        if stored is None:
            return None
        n = len(cage.vertices) + len(cage.faces)
        if stored["coefficients"].shape != (n, 3) or stored["inputs"] != self.map_inputs(
            cage, anchors
        ):
            return None
        return HarmonicMap(cage, stored["coefficients"])

    def constraint_arguments(self) -> dict:
        """The constraints as keyword arguments of :meth:`Deformer.set_constraints`."""
        c = self.constraints
        kw = {"positions": c["positions"], "targets": c["targets"]}
        if len(c["jacobian_points"]):
            kw.update(jacobian_points=c["jacobian_points"], jacobians=c["jacobians"])
        return kw

    def solve_kwargs(self) -> dict:
        """Keyword arguments of :meth:`Deformer.solve` from the solver settings (no steps)."""
        return {
            "max_iterations": int(self.solver["max_iterations"]),
            "tolerance": float(self.solver["tolerance"]),
        }

    def solve(self, deformer, progress=None, **overrides) -> list:
        """Solve ``deformer`` with the scene's settings, ramping over ``steps`` solves.

        With ``steps > 1``, the targets go from the rest positions (and identity
        Jacobians) to the scene's targets in ``steps`` warm-started solves (positions
        linearly, Jacobian rotations by angle), which avoids the symmetric saddle of large
        twists.

        Parameters
        ----------
        deformer : Deformer
            Built by :meth:`build`.
        progress : callable(fraction, message), optional
            Called after each step.
        **overrides
            Any of the solver settings (``max_iterations``, ``tolerance``, ``init`` -- also
            a (d, 3, 3) array of starting local matrices --, ``steps``,
            ``anderson_window``).

        Returns
        -------
        list of SolveReport
        """
        unknown = sorted(set(overrides) - set(DEFAULT_SOLVER))
        if unknown:
            raise TypeError(f"unknown solver setting {unknown[0]!r}; use {sorted(DEFAULT_SOLVER)}")
        settings = dict(self.solver)
        settings.update(overrides)
        init = settings["init"]
        settings = parse_solver({**settings, "init": "identity"}) | {"init": init}
        steps = settings["steps"]
        contraction = None
        if isinstance(init, str) and init == "solution":
            if self.solution is None or len(self.solution) != deformer.n_anchors:
                raise SceneError("solution", "no stored solution for these anchors")
            init, contraction = self.solution, self.solution_contraction
        c = self.constraints
        reports = []
        for k in range(1, steps + 1):
            s = k / steps
            if steps > 1 and k == steps:
                # the last step solves the scene's own targets, bit for bit (the ramp at
                # s = 1 is only close to them), so that the result is a solve of this
                # scene's constraints and record_map stores it
                jac = c["jacobians"]
                deformer.update_targets(targets=c["targets"], jacobians=jac if len(jac) else None)
            elif steps > 1:
                targets = c["positions"] + s * (c["targets"] - c["positions"])
                jac = np.array([_interpolate_jacobian(j, s) for j in c["jacobians"]])
                deformer.update_targets(targets=targets, jacobians=jac if len(jac) else None)
            reports.append(
                deformer.solve(
                    max_iterations=settings["max_iterations"],
                    tolerance=settings["tolerance"],
                    init=init if k == 1 else "previous",
                    anderson_window=settings["anderson_window"],
                    contraction=contraction if k == 1 and steps == 1 else None,
                )
            )
            if progress is not None:
                progress(k / steps, "solving")
        return reports


class NotConverged(RuntimeError):
    """A solve stopped at ``solver.max_iterations`` and the caller did not allow it."""


@dataclass
class SolvedMap:
    """A scene's solved map, as :meth:`Scene.solve_map` returns it.

    Attributes
    ----------
    scene : Scene
        The scene it was solved for.
    harmonic_map : HarmonicMap
        The map.
    deformer : Deformer or None
        The solved deformer (None when the scene's stored map was used).
    reports : list of SolveReport
        One per solve step (empty when the stored map was used).
    notes : list of str
        What loading had to change or warns of (old scene format, cage repairs, thin
        cage faces), one line each.
    """

    scene: Scene
    harmonic_map: Any
    deformer: Any
    reports: list
    notes: list

    @property
    def reused(self) -> bool:
        """Whether the scene's stored map was used instead of a solve."""
        return self.deformer is None

    @property
    def last_report(self):
        """The last solve step's report (None when the stored map was used)."""
        return self.reports[-1] if self.reports else None

    @property
    def converged(self) -> bool:
        """Whether the map is a converged solve (a stored map always is)."""
        report = self.last_report
        return report is None or bool(report.converged)

    def shortfall(self) -> str:
        """Why the solve stopped short, in the scene's terms (empty when it converged).

        Names the scene's settings (``solver.max_iterations``, ``solver.tolerance``) with
        the values the solve ran with, so the user knows which field to raise, and, for a
        ramp, that its last step stopped there (the cap holds for each step).
        """
        report = self.last_report
        if report is None or report.converged:
            return ""
        steps = len(self.reports)
        # the cap holds for each solve of a ramp: the last one stopped at it
        where = f" in the last of its {steps} solver.steps" if steps > 1 else ""
        return (
            f"the solver stopped at solver.max_iterations = {report.max_iterations}{where} "
            f"with the estimated distance to the solution {report.distance_estimate:.3g} "
            f"above solver.tolerance = {report.tolerance:g}"
        )

    def require_converged(self, allow: bool = False, remedy: str = "") -> None:
        """Raise :class:`NotConverged` for an unconverged solve unless ``allow``.

        Parameters
        ----------
        allow : bool
            Let an unconverged solve through.
        remedy : str
            What the caller's user can do, appended to the message (e.g. the command
            line's ``--allow-unconverged``).
        """
        if self.converged or allow:
            return
        text = f"not converged: {self.shortfall()}"
        if remedy:
            text += f"; {remedy}"
        raise NotConverged(text)


def _resolve(base_dir: Path | None, text: str) -> Path:
    """A path of the scene file, relative ones against ``base_dir`` (the scene's folder)."""
    p = Path(text).expanduser()
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    return p


def _interpolate_jacobian(j: np.ndarray, s: float) -> np.ndarray:
    """Interpolate ``I -> j = scale * R`` by rotation angle and scale."""
    from scipy.spatial.transform import Rotation  # here: importing it is slow, rarely used

    scale = np.cbrt(np.linalg.det(j))
    rot = Rotation.from_matrix(j / scale)
    return (1 + s * (scale - 1)) * Rotation.from_rotvec(s * rot.as_rotvec()).as_matrix()
