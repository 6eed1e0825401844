"""UI-free state of the explorer: a :class:`~vhm_viz.scene.Scene`, its data and deformer.

:class:`ExplorerController` holds everything the main window shows and every operation the
user can trigger, without importing Qt, so that it can be driven and tested directly. The
window (:mod:`vhm_viz.app.window`) only translates events into calls on it and re-renders.

Life cycle
----------
* The *rest* dataset (:attr:`ExplorerController.rest`) is what was loaded; the *display*
  dataset (:attr:`ExplorerController.display`) is a float64 copy whose points are rewritten
  **in place** by :meth:`ExplorerController.deform` (the renderer keeps the same actor).
* The edited deformation is :attr:`ExplorerController.scene`: cage, anchors, constraint
  arrays, mode, alpha and solver settings. Its constraint arrays are the only constraint
  model; :attr:`~ExplorerController.positions` and :attr:`~ExplorerController.jacobians`
  are views of them (:mod:`vhm_viz.app.constraints`). Undo and redo step through
  snapshots of the scene (:class:`~vhm_viz.app.history.SceneHistory`).
* Editing the cage, anchors or alpha marks the deformer stale, adding or removing
  constraints the constraint layout; :meth:`ExplorerController.prepare` rebuilds them (the
  only expensive call: basis evaluation at every point of the shape, with progress and
  cancellation). Moving a target or turning a Jacobian only updates the targets, so
  :meth:`ExplorerController.drag` (update + warm-started solve + deform) is cheap.
* A scene file is loaded and solved through :meth:`vhm_viz.scene.Scene.solve_map`, the path
  every front end takes from a scene to a solved map.
* Level of detail (:mod:`vhm_viz.app.lod`): a shape with more than
  :attr:`ExplorerController.lod_points` points gets a *proxy* with its own binding, built by
  :meth:`ExplorerController.prepare`. While dragging only the proxy is deformed
  (:attr:`full_stale` is then true); :meth:`ExplorerController.deform` (on release) deforms
  the full shape.
* Constraint points live in rest space; targets in deformed space. A position constraint
  added at a point starts with the point's current image as target (the shape does not
  jump); a Jacobian constraint starts at the closest similarity to the current Jacobian.
* Analysis: :meth:`ExplorerController.metrics` (shape distortion, inverted cells) and
  :meth:`ExplorerController.certify` (:mod:`vhm_viz.app.certify`); the certificate is
  dropped by the next solve, since it belongs to one solution.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vhm_viz.app.analysis import shape_metrics
from vhm_viz.app.cage_fit import point_values, region_threshold
from vhm_viz.app.cancellation import Cancelled, ProgressFn, never_cancelled, no_progress
from vhm_viz.app.certify import certificate_geometry, certify_shape
from vhm_viz.app.constraints import (
    ARRAYS,
    JacobianConstraint,
    PositionConstraint,
    appended,
    closest_rotation,
    kept,
    removed,
    replaced,
    similarity_matrix,
    similarity_of,
    with_row,
)
from vhm_viz.app.explorer_scene import (
    SETTLE_SOLVER,
    empty_scene,
    scene_for_file,
    settle_settings,
    solve_loaded,
)
from vhm_viz.app.export import export_path, write_deformed, write_deformed_volume
from vhm_viz.app.history import SceneHistory, UndoRedo
from vhm_viz.app.lod import LevelOfDetail, level_of_detail_setting
from vhm_viz.app.volume import displayed
from vhm_viz.autocage import auto_anchors, auto_cage
from vhm_viz.core.anchors import anchors_from_polylines
from vhm_viz.core.errors import AbortedError, CageError, ConstraintError, describe_indices
from vhm_viz.examples import bar
from vhm_viz.io import read_anchors, read_cage, read_dataset, read_rigidity_lines, refuse_inputs
from vhm_viz.scene import Scene

__all__ = [
    "ExplorerController",
    "PositionConstraint",
    "JacobianConstraint",
    "FrameTiming",
    "Cancelled",
    "SETTLE_SOLVER",
    "settle_settings",
]


@dataclass
class FrameTiming:
    """Seconds spent in one interactive update (render time is filled in by the window)."""

    solve: float = 0.0
    deform: float = 0.0
    analysis: float = 0.0
    render: float = 0.0
    iterations: int = 0
    mesh: str = "full"  # what was deformed: "full" shape or its "proxy"

    @property
    def total(self) -> float:
        """Sum of all parts (s)."""
        return self.solve + self.deform + self.analysis + self.render


class ExplorerController(UndoRedo):
    """Everything the explorer shows and does, without Qt.

    Attributes
    ----------
    rest : pyvista.DataSet or None
        The loaded dataset (never modified).
    display : pyvista.DataSet or None
        A copy with float64 points, deformed in place.
    scene : Scene
        The edited deformation: inline cage, anchor points, constraint arrays, mode, alpha,
        solver settings (:data:`SETTLE_SOLVER` by default) and the data reference.
    cage : vhm_viz.Cage or None
        The scene's cage, built.
    max_iterations, tolerance : the interactive solve's cap and tolerance (:meth:`drag`,
        and :meth:`solve` unless told otherwise).
    deformer : Deformer or None
    binding : ShapeBinding or None
        The display's float32 binding.
    last_report : SolveReport or None
    level_of_detail : LevelOfDetail
        The drag proxy (see :attr:`lod`, :attr:`lod_points`, :attr:`proxy_triangles`).
    full_stale : bool
        The display dataset lags behind the solution (dragging showed the proxy).
    certificate : InjectivityCertificate or None
        The last :meth:`certify` answer, while the solution it certified is shown.
    threshold : float, str or None
        Volumes: the threshold whose region (values strictly above it) a cage must
        enclose -- a number, ``"otsu"``, or None for every voxel; see :meth:`set_cage`.
    volume : VolumeView or None
        A loaded volume; its outline box surface is then the display dataset (voxels are
        never bound one by one).
    history : SceneHistory
        Undo and redo.
    """

    def __init__(self) -> None:
        self.rest = None
        self.display = None
        #: Files read since the data was loaded (data, cage, anchors): never written.
        self.input_files: list[Path] = []
        self.scene = empty_scene()
        self.cage = None
        self.max_iterations = 200
        self.tolerance = 1e-6
        self.deformer = None
        self.binding = None
        self.last_report = None
        self.level_of_detail = LevelOfDetail()
        self.full_stale = False
        self._deformer_stale = True
        self._layout_stale = True
        self._targets_stale = False
        self._rest_points = np.zeros((0, 3))
        # a loaded scene's contraction rate: the next solve starts at its solution with it
        self._resume_contraction = None
        # the local matrices an undone or redone scene was solved with: its next solve
        # starts there, so that the shape shown before comes back (the solve is not convex)
        self._resume_solution = None
        #: Messages for the user from the last load (e.g. an old scene file converted).
        self.notes: list[str] = []
        self.certificate = None
        self._certified_map = None
        self.threshold = None
        self.volume = None
        self.history = SceneHistory()

    # ------------------------------------------------------------------ the scene's fields
    @property
    def source(self) -> dict:
        """Where the data came from: ``{"path": ...}``, ``{"bar": kind, "resolution": r}``."""
        return self.scene.data or {}

    @property
    def anchors(self) -> np.ndarray:
        """(d, 3) anchor points (the scene's)."""
        return self.scene.anchors["points"]

    @property
    def mode(self) -> str:
        """``"rigid"`` or ``"similar"``; see :meth:`set_mode`."""
        return self.scene.mode

    @property
    def alpha(self) -> float:
        """Stiffness; see :meth:`set_alpha`."""
        return self.scene.alpha

    @property
    def solver(self) -> dict:
        """The scene's solver settings, used by :meth:`settle` and saved with the scene."""
        return self.scene.solver

    @property
    def positions(self) -> list[PositionConstraint]:
        """Views of the scene's position constraints."""
        n = len(self.scene.constraints["positions"])
        return [PositionConstraint(self, i) for i in range(n)]

    @property
    def jacobians(self) -> list[JacobianConstraint]:
        """Views of the scene's Jacobian constraints."""
        n = len(self.scene.constraints["jacobian_points"])
        return [JacobianConstraint(self, i) for i in range(n)]

    # ------------------------------------------------------------------ data
    @property
    def ready(self) -> bool:
        """Whether :meth:`drag` can run without :meth:`prepare` (nothing stale)."""
        return (
            self.deformer is not None
            and self.binding is not None
            and not self._deformer_stale
            and not self._layout_stale
        )

    @property
    def can_solve(self) -> bool:
        """Data, cage, anchors and at least one position constraint are present."""
        return (
            self.rest is not None
            and self.cage is not None
            and len(self.anchors) > 0
            and len(self.scene.constraints["positions"]) > 0
        )

    def _set_data(self, data, source: dict) -> None:
        data, display, self.volume = displayed(data)
        self.rest = data
        self.display = display
        self._rest_points = np.array(display.points, dtype=np.float64)
        self.scene = empty_scene(self.mode, self.alpha, self.solver, dict(source) or None)
        self.input_files = [Path(source["path"])] if "path" in source else []
        self.cage = None
        self.threshold = None
        self.deformer = None
        self.binding = None
        self.level_of_detail.clear()
        self.full_stale = False
        self.last_report = None
        self.certificate = None
        self._resume_contraction = self._resume_solution = None
        self._deformer_stale = True
        self._layout_stale = True
        self.history.clear()

    def load_file(self, path) -> None:
        """Load any dataset PyVista reads. On error the current state is kept.

        Raises
        ------
        OSError, ValueError
            Missing or unreadable file (message names the file).
        """
        data = read_dataset(path)
        self._set_data(data, {"path": str(Path(path).resolve())})

    def load_bar(self, kind: str = "bend-u", resolution: int = 39, apply: bool = True) -> None:
        """Load a bundled bar scenario: shape, cage, anchors and (optionally) constraints."""
        sc = bar(kind, mode=self.mode, alpha=self.alpha, resolution=resolution)
        self._set_data(sc.surface, {"bar": kind, "resolution": int(resolution)})
        self._use_cage(sc.cage)
        self.scene.anchors = {"points": np.array(sc.anchors, dtype=np.float64)}
        c = sc.constraints
        if apply:
            self._edit_constraints(replaced, **{k: c[k] for k in self.scene.constraints})
        else:
            # hold the bottom cap so that dragging has something to pull against
            p = np.array(c["positions"][:5])
            self._edit_constraints(replaced, positions=p, targets=p)
        # the scenario's deformer has this cage, anchors, mode and alpha: reuse it
        self.deformer = sc.deformer
        self._deformer_stale = False
        self._layout_stale = not apply
        self._targets_stale = True

    @property
    def rest_points(self) -> np.ndarray:
        """(P, 3) float64 rest positions of the display dataset's points."""
        return self._rest_points

    @property
    def deformed_points(self) -> np.ndarray:
        """(P, 3) view of the display dataset's (deformed) points."""
        return np.asarray(self.display.points)

    # ------------------------------------------------------------------ cage
    def _use_cage(self, cage) -> None:
        """Make ``cage`` the scene's cage (inline vertices and faces)."""
        self.cage = cage
        self.scene.cage = {
            "vertices": np.array(cage.vertices, dtype=np.float64),
            "faces": np.array(cage.faces, dtype=np.int64),
        }
        self.history.remember_cage(cage)

    def set_cage(self, cage) -> None:
        """Use a cage; it must enclose every point of the data (or of a volume's region).

        "Inside" is the one test everything uses (:meth:`vhm_viz.Cage.contains`: winding
        number at least 1/2). A volume's cage may enclose only the region above a
        threshold, as ``auto_cage(..., threshold=...)`` and ``vhm-viz cage --threshold``
        build it: with :attr:`threshold` set, every voxel above it must be inside; with
        None, a cage that leaves voxels out is taken for the region above the largest value
        it leaves out (set as :attr:`threshold`, with a note). Voxels outside stay put.

        Raises
        ------
        CageError
            Points of the data (or voxels of the region) outside the cage, with count and
            indices; for a volume also a cage that encloses no region above a threshold.
        """
        if self.volume is not None:
            inside = self.volume.inside(cage)
            if not inside.all():
                self._check_region_inside(inside)
        elif self.rest is not None:
            inside = cage.contains(self._rest_points)
            if not inside.all():
                self._check_region_inside(inside)
        self._use_cage(cage)
        if len(self.anchors):
            self.scene.anchors = {"points": self.anchors[cage.contains(self.anchors)]}
        self._drop_outside_constraints()
        self._deformer_stale = True

    def _check_region_inside(self, inside: np.ndarray) -> None:
        """Accept a cage that leaves points out only when it encloses a volume's region."""
        values = point_values(self.volume, self.rest, len(self._rest_points))
        self.threshold, note = region_threshold(values, inside, self.threshold)
        if note is not None:
            self.notes.append(note)

    def load_cage(self, path) -> None:
        """Read, validate and use a cage file (OBJ, OFF, PLY, STL, VTP, VTK)."""
        try:
            cage = read_cage(path)
        except CageError:
            raise
        except (OSError, ValueError) as exc:
            raise CageError(f"{Path(path).name}: {exc}") from exc
        self.set_cage(cage)
        self.input_files.append(Path(path))

    def auto_cage(self, max_faces: int = 500, progress: ProgressFn = no_progress):
        """Generate a cage around the data (:func:`vhm_viz.autocage.auto_cage`); not applied.

        Returns the cage; call :meth:`set_cage` with it (on the UI thread).
        """
        if self.rest is None:
            raise ValueError("load data first")
        progress(0.05, "generating cage")
        return auto_cage(self.rest, max_faces=int(max_faces), threshold=self.threshold)

    def _drop_outside_constraints(self) -> None:
        for kind, (points, _) in ARRAYS.items():
            if self.cage is not None and len(self.scene.constraints[points]):
                keep = self.cage.contains(self.scene.constraints[points])
                self._edit_constraints(kept, kind, keep)

    def _edit_constraints(self, edit, *args, **kwargs) -> None:
        """Replace the scene's constraints by ``edit(constraints, *args, **kwargs)``."""
        self.scene.constraints = edit(self.scene.constraints, *args, **kwargs)

    # ------------------------------------------------------------------ anchors
    def set_anchors(self, anchors) -> None:
        """Use these anchor points (must lie inside the cage)."""
        a = np.array(anchors, dtype=np.float64).reshape(-1, 3)
        if self.cage is not None and len(a):
            inside = self.cage.contains(a)
            if not inside.all():
                raise ValueError(
                    f"anchors {describe_indices(np.nonzero(~inside)[0])} are outside the cage"
                )
        self.scene.anchors = {"points": a}
        self._deformer_stale = True

    def load_anchors(self, path, count: int = 50) -> None:
        """Anchors from a file: the JSON ``vhm-viz anchors`` writes, or rigidity lines.

        Rigidity lines (``.tgf`` skeleton, OFF polylines, any VTK polyline dataset) get
        ``count`` anchors spread along them (:func:`vhm_viz.anchors_from_polylines`).
        """
        if Path(path).suffix.lower() == ".json":
            self.set_anchors(read_anchors(path))
        else:
            pts, edges = read_rigidity_lines(path)
            self.set_anchors(anchors_from_polylines(pts, edges, int(count)))
        self.input_files.append(Path(path))

    def auto_anchors(self, count: int = 50) -> np.ndarray:
        """Compute ``count`` anchors automatically (not applied; see :meth:`set_anchors`)."""
        if self.rest is None or self.cage is None:
            raise ValueError("load data and a cage first")
        return np.asarray(
            auto_anchors(self.rest, self.cage, int(count), threshold=self.threshold), dtype=float
        )

    def add_anchor(self, point) -> int:
        """Add an anchor at a rest-space point; returns its index."""
        p = np.asarray(point, dtype=float).reshape(1, 3)
        if self.cage is not None and not self.cage.contains(p)[0]:
            raise ValueError("the anchor is outside the cage")
        self.scene.anchors = {"points": np.vstack([self.anchors, p])}
        self._deformer_stale = True
        return len(self.anchors) - 1

    def remove_anchor(self, index: int) -> None:
        """Remove anchor ``index``."""
        if not 0 <= index < len(self.anchors):
            raise IndexError(f"anchor {index} does not exist ({len(self.anchors)} anchors)")
        self.scene.anchors = {"points": np.delete(self.anchors, index, axis=0)}
        self._deformer_stale = True

    def nearest_anchor(self, point) -> int | None:
        """Index of the anchor closest to a rest-space point (None without anchors)."""
        if not len(self.anchors):
            return None
        return int(np.argmin(np.linalg.norm(self.anchors - np.asarray(point), axis=1)))

    # ------------------------------------------------------------------ constraints
    def image_of(self, point) -> np.ndarray:
        """Current image ``f(point)`` of a rest-space point (identity before any solve)."""
        p = np.asarray(point, dtype=float).reshape(1, 3)
        if self.deformer is None or self.last_report is None:
            return p[0].copy()
        return self.deformer.harmonic_map.map(p)[0]

    def jacobian_of(self, point) -> np.ndarray:
        """Current Jacobian at a rest-space point (identity before any solve)."""
        p = np.asarray(point, dtype=float).reshape(1, 3)
        if self.deformer is None or self.last_report is None:
            return np.eye(3)
        return self.deformer.harmonic_map.jacobian(p)[0]

    def _check_constraint_point(self, p: np.ndarray) -> None:
        if self.cage is None:
            raise ValueError("load or generate a cage first")
        if not self.cage.contains(p.reshape(1, 3))[0]:
            raise ConstraintError(f"the point {np.round(p, 4).tolist()} is outside the cage")

    def add_position_constraint(self, point, target=None) -> int:
        """Add ``f(point) = target`` (default: the point's current image); returns its index."""
        p = np.asarray(point, dtype=float).reshape(3)
        self._check_constraint_point(p)
        t = self.image_of(p) if target is None else np.asarray(target, float).reshape(3)
        self._edit_constraints(appended, "position", p, t)
        self._layout_stale = True
        return len(self.scene.constraints["positions"]) - 1

    def add_jacobian_constraint(self, point, angles=None, scale=None) -> int:
        """Add a Jacobian constraint (default: the closest similarity to the current one)."""
        p = np.asarray(point, dtype=float).reshape(3)
        self._check_constraint_point(p)
        current_angles, current_scale = similarity_of(self.jacobian_of(p))
        angles = current_angles if angles is None else np.asarray(angles, float).reshape(3)
        scale = current_scale if scale is None else float(scale)
        if not scale > 0:
            raise ConstraintError(f"the Jacobian scale must be positive; got {scale}")
        self._edit_constraints(appended, "jacobian", p, similarity_matrix(angles, scale))
        self._layout_stale = True
        return len(self.scene.constraints["jacobian_points"]) - 1

    def remove_constraint(self, kind: str, index: int) -> None:
        """Remove position (``kind="position"``) or Jacobian (``"jacobian"``) constraint."""
        self._edit_constraints(removed, kind, index)
        self._layout_stale = True

    def set_target(self, index: int, target) -> None:
        """Move the target of position constraint ``index`` (no refactorisation)."""
        t = np.asarray(target, dtype=float).reshape(3)
        self._edit_constraints(with_row, "targets", index, t)
        self._targets_stale = True

    def set_jacobian(self, index: int, angles=None, scale=None) -> None:
        """Change the angles (degrees) and/or scale of Jacobian constraint ``index``."""
        current_angles, current_scale = similarity_of(self.jacobians[index].matrix)
        if scale is not None:
            if not float(scale) > 0:
                raise ConstraintError(f"Jacobian constraint {index}: scale must be positive")
            current_scale = float(scale)
        if angles is not None:
            current_angles = np.asarray(angles, float).reshape(3)
        self._edit_constraints(
            with_row, "jacobians", index, similarity_matrix(current_angles, current_scale)
        )
        self._targets_stale = True

    def set_jacobian_rotation(self, index: int, rotation) -> None:
        """Set the target rotation of Jacobian constraint ``index`` (scale kept).

        ``rotation`` (3, 3) is replaced by its closest rotation (polar decomposition).
        """
        scale = similarity_of(self.jacobians[index].matrix)[1]
        self._edit_constraints(with_row, "jacobians", index, scale * closest_rotation(rotation))
        self._targets_stale = True

    # ------------------------------------------------------------------ settings
    def set_mode(self, mode: str) -> None:
        """Rigid or similar (no refactorisation; re-solve to see the effect)."""
        if mode not in ("rigid", "similar"):
            raise ValueError(f"mode must be 'rigid' or 'similar'; got {mode!r}")
        self.scene.mode = mode
        if self.deformer is not None:
            self.deformer.mode = mode

    def set_alpha(self, alpha: float) -> None:
        """Stiffness (changes lambda: the deformer is rebuilt by the next :meth:`prepare`)."""
        alpha = float(alpha)
        if not (np.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha must be positive; got {alpha}")
        if alpha != self.alpha:
            self.scene.alpha = alpha
            self._deformer_stale = True

    def copy_settings(self, other: ExplorerController) -> None:
        """Take the level-of-detail and interactive solve settings of another controller."""
        self.level_of_detail.settings_from(other.level_of_detail)
        self.max_iterations, self.tolerance = other.max_iterations, other.tolerance

    # ------------------------------------------------------------------ level of detail
    lod = level_of_detail_setting(
        "enabled", "Drag a proxy when the shape has more than :attr:`lod_points`."
    )
    lod_points = level_of_detail_setting(
        "points", "Level-of-detail threshold (points of the shape)."
    )
    proxy_triangles = level_of_detail_setting("triangles", "Size of the drag proxy (triangles).")

    @property
    def proxy(self):
        """The drag proxy (pyvista.PolyData, deformed in place by :meth:`drag`) or None."""
        return self.level_of_detail.proxy

    @property
    def proxy_rest_points(self) -> np.ndarray:
        """(Q, 3) rest positions of the drag proxy's points (empty without a proxy)."""
        return self.level_of_detail.rest_points

    @property
    def uses_proxy(self) -> bool:
        """Whether :meth:`drag` deforms the proxy instead of the full shape."""
        return self.level_of_detail.active

    # ------------------------------------------------------------------ pipeline
    def prepare(self, progress: ProgressFn = no_progress, cancelled=never_cancelled) -> None:
        """Build what is stale: deformer, constraint layout, shape binding.

        Safe to run in a worker thread while the UI does not modify the controller.

        Raises
        ------
        Cancelled
            ``cancelled()`` became true (state stays stale, nothing half-built is kept).
        OutsideCageError, ConstraintError, ValueError
            Invalid anchors or constraints (the message names them).
        """
        if not self.can_solve:
            n = len(self.scene.constraints["positions"])
            have = {"data": self.rest is not None, "a cage": self.cage is not None,
                    "anchors": len(self.anchors) > 0, "a position constraint": n > 0}  # fmt: skip
            missing = ", ".join(name for name, ok in have.items() if not ok)
            raise ConstraintError("cannot deform yet: missing " + missing)
        deformer, binding = self.deformer, self.binding
        rebuilt = False
        try:
            if self._deformer_stale or deformer is None:
                progress(0.0, "building the deformer")
                deformer = self.scene.build(cage=self.cage)  # also factorises the constraints
                binding = None
                rebuilt = True
            elif self._layout_stale:
                progress(0.02, "factorising the constraints")
                deformer.set_constraints(**self.scene.constraint_arguments())
            if cancelled():
                raise Cancelled("cancelled")
            if binding is None:
                # float32 halves memory and deform time; export evaluates the map exactly
                binding = deformer.bind(
                    self._rest_points,
                    outside="passthrough",
                    dtype=np.float32,
                    progress=progress,
                    abort=cancelled,
                )
            else:
                binding.refresh(progress, cancelled)
            proxy = self.level_of_detail.prepared(
                self.rest, self.display.n_points, deformer, rebuilt, cancelled
            )
        except AbortedError as exc:
            raise Cancelled("cancelled") from exc
        self.deformer, self.binding = deformer, binding
        self.notes.extend(n for n in deformer.notes if n not in self.notes)  # pinned shells
        self.level_of_detail.adopt(*proxy)
        self._deformer_stale = self._layout_stale = False
        self._targets_stale = False
        progress(1.0, "ready")

    def _push_targets(self) -> None:
        c = self.scene.constraints
        jacobians = c["jacobians"] if len(c["jacobians"]) else None
        self.deformer.update_targets(targets=c["targets"], jacobians=jacobians)
        self._targets_stale = False

    def solve(self, init="previous", max_iterations: int | None = None, tolerance=None):
        """Warm-started solve of the current constraints; the shape is not deformed yet.

        ``max_iterations`` and ``tolerance`` default to :attr:`max_iterations` and
        :attr:`tolerance` (the drag settings).
        """
        if not self.ready:
            self.prepare()
        if self._targets_stale:
            self._push_targets()
        self.certificate = None  # it certified the previous solution
        self.deformer.mode = self.mode
        contraction, self._resume_contraction = self._resume_contraction, None
        resume, self._resume_solution = self._resume_solution, None
        previous = isinstance(init, str) and init == "previous"
        if previous and resume is not None and resume.shape == (len(self.anchors), 3, 3):
            init = resume
        rep = self.deformer.solve(
            max_iterations=self.max_iterations if max_iterations is None else max_iterations,
            tolerance=self.tolerance if tolerance is None else float(tolerance),
            init=init,
            contraction=contraction if previous else None,
        )
        self.last_report = rep
        return rep

    def settle(self, init="previous"):
        """Solve to convergence with the scene's settings (:attr:`solver`)."""
        return self.solve(
            init=init,
            max_iterations=int(self.solver["max_iterations"]),
            tolerance=float(self.solver["tolerance"]),
        )

    def deform(self) -> np.ndarray:
        """Write the deformed points into :attr:`display` in place and return them."""
        pts = self.display.points
        out = np.asarray(pts)
        if out.dtype != np.float64 or not out.flags.c_contiguous:
            raise RuntimeError("display points must be contiguous float64")
        self.binding.deform(out=out)
        self.display.GetPoints().Modified()
        self.full_stale = False
        return out

    def _catch_up(self) -> None:
        """Deform the full shape if a drag left it behind the solution (proxy shown)."""
        if self.full_stale and self.ready:
            self.deform()

    def drag(self, index: int, target, lod: bool | None = None) -> FrameTiming:
        """One interactive frame: move target ``index``, warm-started solve, deform.

        With ``lod`` (default :attr:`uses_proxy`) only the proxy is deformed; call
        :meth:`deform` when the drag ends.
        """
        t0 = time.perf_counter()
        self.set_target(index, target)
        return self._frame(t0, lod)

    def rotate(self, index: int, rotation, lod: bool | None = None) -> FrameTiming:
        """One interactive frame of the rotation gizmo (see :meth:`drag`).

        Jacobian constraint ``index`` gets the target rotation ``rotation`` (3, 3; its
        closest rotation is used, the scale is kept), then a warm-started solve and
        deformation.
        """
        t0 = time.perf_counter()
        self.set_jacobian_rotation(index, rotation)
        return self._frame(t0, lod)

    def _frame(self, t0: float, lod: bool | None) -> FrameTiming:
        rep = self.solve()
        t1 = time.perf_counter()
        proxy = self.uses_proxy if lod is None else bool(lod) and self.uses_proxy
        if proxy:  # the full shape lags behind
            self.level_of_detail.deform()
            self.full_stale = True
        else:
            self.deform()
        t2 = time.perf_counter()
        return FrameTiming(
            solve=t1 - t0,
            deform=t2 - t1,
            iterations=rep.iterations,
            mesh="proxy" if proxy else "full",
        )

    def reset(self) -> None:
        """Show the rest shape (targets kept)."""
        if self.display is not None:
            np.asarray(self.display.points)[:] = self._rest_points
            self.display.GetPoints().Modified()
        self.level_of_detail.reset()
        self.full_stale = False

    # ------------------------------------------------------------------ analysis
    def metrics(self) -> dict:
        """Shape distortion and inverted cells, the last energy, the certificate's answer.

        See :func:`vhm_viz.app.analysis.shape_metrics`.
        """
        self._catch_up()
        out = shape_metrics(self.rest, self.display, self._rest_points, self.volume is None)
        if self.last_report is not None:
            out["energy"] = self.last_report.final_energy
            out["iterations"] = self.last_report.iterations
        if self.certificate is not None:
            out["certificate"] = self.certificate.status
        return out

    def certify(self, max_cubes: int = 200_000, progress: ProgressFn = no_progress,
                cancelled=never_cancelled):  # fmt: skip
        """Certify the current map injective over the shape, or find witnesses of folds.

        See :func:`vhm_viz.app.certify.certify_shape`. Safe to run in a worker thread while
        the UI does not modify the controller; the answer is kept in :attr:`certificate`
        until the next solve. Returns the :class:`InjectivityCertificate`.

        Raises
        ------
        ConstraintError
            Nothing solved yet.
        Cancelled
            ``cancelled()`` became true.
        """
        if not self.ready or self.last_report is None:
            raise ConstraintError("solve before certifying (nothing is deformed yet)")
        hm = self.deformer.harmonic_map
        cert = certify_shape(hm, self.rest, self.cage, max_cubes, progress, cancelled)
        self.certificate, self._certified_map = cert, hm
        return cert

    def certificate_geometry(self):
        """What to draw of :attr:`certificate`: witnesses (w, 3) and undecided cubes or None."""
        return certificate_geometry(self.certificate, self._certified_map)

    # ------------------------------------------------------------------ export / scenes
    def export(self, path) -> list:
        """Write the deformed dataset (format from the suffix, default the input's).

        The map is evaluated in float64 (:mod:`vhm_viz.app.export`), so the file equals
        ``vhm-viz deform`` of the saved scene to rounding. Returns the lines that say how
        the written deformation folds the data, if it does (:mod:`vhm_viz.folds`).
        """
        if self.display is None:
            raise ValueError("nothing loaded")
        self._catch_up()
        path = export_path(path, self.source, self.input_files)
        solved = self.ready and self.last_report is not None
        hm = self.deformer.harmonic_map if solved else None
        if self.volume is None:
            return write_deformed(path, self.display, self._rest_points, hm, self.input_files)
        if hm is None:
            raise ValueError("nothing to export yet: solve first")
        return write_deformed_volume(path, self.rest, hm, self.input_files)

    def scene_to_save(self, relative_to=None) -> Scene:
        """The edited scene as it is saved: data path, solved state and map.

        Parameters
        ----------
        relative_to : path-like, optional
            Directory that the data path is written relative to (the scene file's).

        Raises
        ------
        ValueError
            Without a cage, anchors or a position constraint (a scene needs them).
        """
        if self.cage is None or not len(self.anchors) or not len(self.positions):
            raise ValueError(
                "nothing to describe yet: a scene needs a cage, anchors and a position constraint"
            )
        solved = self.ready and self.last_report is not None
        return scene_for_file(
            self.scene, self.deformer if solved else None, self.last_report, relative_to
        )

    def save_scene(self, path) -> None:
        """Write the scene (:mod:`vhm_viz.scene`'s format, the one ``vhm-viz deform`` reads).

        The data the scene was made for is referenced relative to the scene file, and a
        converged solution is stored with ``"init": "solution"``, with its map
        (:meth:`~vhm_viz.scene.Scene.record_map`).
        """
        path = Path(path)
        refuse_inputs(path, self.input_files)
        self.scene_to_save(relative_to=path.parent).save(path)

    def load_scene(self, path, data_from: ExplorerController | None = None,
                   progress: ProgressFn = no_progress) -> list[str]:  # fmt: skip
        """Load a scene and solve it (:meth:`Scene.solve_map`); the state is replaced on success.

        A scene that names no data applies to the data already loaded (in ``data_from``,
        default this controller). A stored solution for the scene's anchors is the solve's
        starting point; the scene's cap and tolerance are tightened to :func:`settle_settings`.

        Returns
        -------
        list of str
            Notes for the user (e.g. that an old explorer file was converted).
        """
        path = Path(path)
        current = self if data_from is None else data_from
        stored = Scene.load(path)
        new = ExplorerController()
        new.copy_settings(self)
        new.scene.mode, new.scene.alpha = stored.mode, float(stored.alpha)
        new.scene.solver = settle_settings(stored.solver)
        new._load_data_ref(stored.data, path, current)
        cage = stored.build_cage(new.rest)
        new.set_cage(cage)
        new.set_anchors(stored.build_anchors(cage, new.rest))
        new._edit_constraints(replaced, **stored.constraints)
        new._layout_stale = True
        new.notes.extend(stored.notes)
        if new.can_solve:
            new._solve_loaded(stored, progress)
        self.adopt(new)
        return list(new.notes)

    def _solve_loaded(self, stored: Scene, progress: ProgressFn) -> None:
        solved = solve_loaded(self.scene, stored, self.rest, self.cage, progress)
        self.deformer, self.last_report = solved.deformer, solved.last_report
        rho = solved.last_report.contraction
        if solved.converged and np.isfinite(rho):
            self._resume_contraction = float(rho)
        self.notes.extend(n for n in solved.notes if n not in self.notes)
        self._deformer_stale = self._layout_stale = False

    def adopt(self, other: ExplorerController) -> None:
        """Take over another controller's whole state (built in a worker thread)."""
        self.__dict__.update(other.__dict__)

    def _load_data_ref(self, src: dict | None, scene_path: Path, current) -> None:
        """Load the data a scene names, or take the current controller's."""
        src = src or {}
        if "bar" in src:
            self.load_bar(src["bar"], resolution=int(src.get("resolution", 39)), apply=False)
            self._edit_constraints(replaced, positions=np.zeros((0, 3)), targets=np.zeros((0, 3)))
            self._layout_stale = True
        elif "path" in src:
            p = Path(src["path"])
            if not p.is_absolute():
                p = (scene_path.parent / p).resolve()
            self.load_file(p)
        elif current is not None and current.rest is not None:
            self._set_data(current.rest, dict(current.source))
        else:
            raise ValueError(f"{scene_path.name}: the scene names no data: open the data first")
