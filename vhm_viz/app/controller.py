"""UI-free state of the explorer: data, cage, anchors, constraints, deformer and binding.

:class:`ExplorerController` holds everything the main window shows and every operation the
user can trigger, without importing Qt, so that it can be driven and tested directly. The
window (:mod:`vhm_viz.app.main_window`) only translates events into calls on it and
re-renders.

Life cycle
----------
* The *rest* dataset (:attr:`ExplorerController.rest`) is what was loaded; the *display*
  dataset (:attr:`ExplorerController.display`) is a float64 copy whose points are rewritten
  **in place** by :meth:`ExplorerController.deform` (the renderer keeps the same actor).
* Editing the cage, anchors or alpha marks the deformer stale; adding or removing
  constraints marks the constraint layout stale; both are rebuilt by
  :meth:`ExplorerController.prepare`, the only expensive call (basis evaluation at every
  point of the shape, in chunks with progress and cancellation). Moving a target or changing
  a Jacobian's angles or scale only calls ``Deformer.update_targets`` (no refactorisation),
  so :meth:`ExplorerController.drag` (update + warm-started solve + deform) is cheap.
* Level of detail: a shape with more than :attr:`ExplorerController.lod_points` points
  gets a *proxy* (:attr:`ExplorerController.proxy`, a decimated triangle surface of about
  :attr:`ExplorerController.proxy_triangles` triangles, or a subset of a point cloud) with
  its own float32 binding, built by :meth:`ExplorerController.prepare`. While dragging only
  the proxy is deformed (:meth:`ExplorerController.drag`; :attr:`full_stale` is then true);
  :meth:`ExplorerController.deform` (on release) deforms the full shape.
* Constraint points live in rest space; targets in deformed space. A position constraint
  added at a point starts with the point's current image as target (the shape does not
  jump); a Jacobian constraint starts at the closest similarity to the current Jacobian.
* Analysis: :meth:`ExplorerController.metrics` counts the inverted cells of data with 3D
  cells (from the displayed, float32-bound positions; ``vhm-viz analyze`` and the export
  evaluate in float64), and :meth:`ExplorerController.certify` proves the current map
  injective over the shape or finds witnesses (:func:`vhm_viz.certify_injectivity`); the
  certificate is dropped by the next solve, since it belongs to one solution.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vhm_viz.core.errors import AbortedError, CageError, ConstraintError
from vhm_viz.io import read_dataset, refuse_inputs, write_dataset
from vhm_viz.scene import DEFAULT_SOLVER, Scene

__all__ = [
    "ExplorerController",
    "PositionConstraint",
    "JacobianConstraint",
    "FrameTiming",
    "Cancelled",
    "SETTLE_SOLVER",
    "settle_settings",
    "make_proxy",
]

# Solver settings of the explorer's full solves (on release, after loading): the solver's
# fixed-point estimate is optimistic at small alpha, so settle tighter than the scene
# default. They are saved with the scene, so `vhm-viz deform` reproduces the explorer.
SETTLE_SOLVER = dict(DEFAULT_SOLVER, max_iterations=50000, tolerance=1e-8)


def settle_settings(solver: dict) -> dict:
    """The settings the explorer settles a scene with, and saves it with.

    A scene's own cap and tolerance, at least as strict as :data:`SETTLE_SOLVER`: a
    scene written with ``max_iterations: 200`` would otherwise be settled (and saved)
    unconverged, and ``vhm-viz deform`` would refuse it.
    """
    out = dict(solver)
    out["max_iterations"] = max(int(out["max_iterations"]), SETTLE_SOLVER["max_iterations"])
    out["tolerance"] = min(float(out["tolerance"]), SETTLE_SOLVER["tolerance"])
    return out


# undo steps kept
UNDO_LIMIT = 100
# level of detail: shapes with more points than this are dragged as a decimated proxy
LOD_POINTS = 30000
# triangles of the proxy (software OpenGL renders ~10k triangles well within a frame)
PROXY_TRIANGLES = 12000

ProgressFn = Callable[[float, str], None]


class Cancelled(Exception):
    """Raised inside a long operation when the user cancelled it."""


def _noop_progress(fraction: float, message: str) -> None:
    return None


# ----------------------------------------------------------------------------------------
# Constraints
# ----------------------------------------------------------------------------------------


@dataclass
class PositionConstraint:
    """``f(point) = target``; ``point`` in rest space, ``target`` in deformed space (3,)."""

    point: np.ndarray
    target: np.ndarray

    def to_json(self) -> dict:
        """JSON-serialisable form."""
        return {"point": self.point.tolist(), "target": self.target.tolist()}


@dataclass
class JacobianConstraint:
    """``J_f(point) = scale * R(angles)``.

    ``angles`` are extrinsic x, y, z rotation angles in degrees (scipy's ``"xyz"`` Euler
    convention); ``scale`` is a positive factor.
    """

    point: np.ndarray
    angles: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) target Jacobian ``J[i, j] = d f_i / d x_j``."""
        from scipy.spatial.transform import Rotation

        return float(self.scale) * Rotation.from_euler("xyz", self.angles, degrees=True).as_matrix()

    @classmethod
    def from_matrix(cls, point, matrix) -> JacobianConstraint:
        """Closest similarity ``s R`` to a Jacobian (polar decomposition)."""
        from scipy.spatial.transform import Rotation

        u, s, vt = np.linalg.svd(np.asarray(matrix, dtype=float))
        r = u @ vt
        if np.linalg.det(r) < 0:
            u[:, -1] *= -1
            r = u @ vt
        scale = float(np.mean(s))
        with warnings.catch_warnings():  # gimbal lock: the angles still reproduce r
            warnings.simplefilter("ignore", UserWarning)
            angles = Rotation.from_matrix(r).as_euler("xyz", degrees=True)
        return cls(np.asarray(point, float).copy(), np.asarray(angles, float), scale)

    def to_json(self) -> dict:
        """JSON-serialisable form."""
        return {"point": self.point.tolist(), "angles": self.angles.tolist(), "scale": self.scale}


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


# ----------------------------------------------------------------------------------------
# Level of detail
# ----------------------------------------------------------------------------------------


def make_proxy(data, triangles: int = PROXY_TRIANGLES):
    """A light stand-in of ``data`` to deform and render while dragging.

    Parameters
    ----------
    data : pyvista.DataSet
        The shape (rest space).
    triangles : int
        Target size: triangles of a decimated surface, or twice the points of a point subset.

    Returns
    -------
    pyvista.PolyData
        Float64 points. Surfaces (polygons, or the outer surface of volumetric cells) are
        triangulated and reduced by quadric decimation (``vtkQuadricDecimation``); point
        clouds and line sets become a regular subset of their points (vertex cells).
    """
    import pyvista as pv

    if isinstance(data, pv.PolyData) and data.GetNumberOfPolys() == 0:
        surf = None
    elif isinstance(data, pv.PolyData):
        surf = data
    else:
        surf = data.extract_surface(algorithm="dataset_surface")
        if surf.GetNumberOfPolys() == 0:
            surf = None
    if surf is None:  # points (and lines): a regular subset of the points
        n = data.n_points
        step = max(1, int(np.ceil(n / max(triangles // 2, 1))))
        pts = np.asarray(data.points, dtype=np.float64)[::step]
        proxy = pv.PolyData(np.ascontiguousarray(pts))
    else:
        surf = pv.PolyData(surf.points, surf.faces) if surf.n_points else surf
        surf = surf.triangulate().clean()
        if surf.n_cells > triangles:
            surf = surf.decimate(1.0 - triangles / surf.n_cells)
        proxy = pv.PolyData(np.asarray(surf.points, dtype=np.float64), surf.faces)
    proxy.points = np.ascontiguousarray(proxy.points, dtype=np.float64)
    return proxy


# ----------------------------------------------------------------------------------------
# The controller
# ----------------------------------------------------------------------------------------


class ExplorerController:
    """Everything the explorer shows and does, without Qt.

    Attributes
    ----------
    rest : pyvista.DataSet or None
        The loaded dataset (never modified).
    display : pyvista.DataSet or None
        A copy with float64 points, deformed in place.
    source : dict
        Where the data came from: ``{"path": ...}`` or ``{"bar": kind, "resolution": r}``.
    cage : vhm_viz.Cage or None
    anchors : (d, 3) ndarray
    positions : list of PositionConstraint
    jacobians : list of JacobianConstraint
    mode : {"rigid", "similar"}
    alpha : float
    max_iterations, tolerance : the interactive solve's cap and tolerance (:meth:`drag`,
        and :meth:`solve` unless told otherwise).
    solver : dict
        The scene's solver settings (:data:`vhm_viz.scene.DEFAULT_SOLVER` keys), used by
        :meth:`settle` and saved with the scene (:data:`SETTLE_SOLVER` by default).
    last_report : SolveReport or None
    lod : bool
        Drag a proxy when the shape has more than ``lod_points`` points (read by
        :meth:`prepare`, which builds the proxy, and by :meth:`drag`).
    lod_points, proxy_triangles : int
        Level-of-detail threshold and proxy size (see :func:`make_proxy`).
    proxy : pyvista.PolyData or None
        The proxy (deformed in place by :meth:`drag`), built by :meth:`prepare`.
    full_stale : bool
        The display dataset lags behind the solution (dragging showed the proxy).
    certificate : InjectivityCertificate or None
        The last :meth:`certify` answer, while the solution it certified is shown.
    """

    def __init__(self) -> None:
        self.rest = None
        self.display = None
        self.source: dict = {}
        #: Files read since the data was loaded (data, cage, anchors): never written.
        self.input_files: list[Path] = []
        self.cage = None
        self.anchors = np.zeros((0, 3))
        self.positions: list[PositionConstraint] = []
        self.jacobians: list[JacobianConstraint] = []
        self.mode = "rigid"
        self.alpha = 0.01
        self.max_iterations = 200
        self.tolerance = 1e-6
        self.solver = dict(SETTLE_SOLVER)
        self.deformer = None
        self.binding = None
        self.last_report = None
        self.lod = True
        self.lod_points = LOD_POINTS
        self.proxy_triangles = PROXY_TRIANGLES
        self.proxy = None
        self.proxy_binding = None
        self._proxy_rest = np.zeros((0, 3))
        self.full_stale = False
        self._deformer_stale = True
        self._layout_stale = True
        self._targets_stale = False
        self._rest_points = np.zeros((0, 3))
        # local matrices to start the next solve from (a loaded scene's solution)
        self._initial_rotations = None
        self._initial_contraction = None
        #: Messages for the user from the last load (e.g. an old scene file converted).
        self.notes: list[str] = []
        self.certificate = None
        self._certified_map = None
        #: Volumes: the threshold whose region (values strictly above it) a cage must
        #: enclose -- a number, ``"otsu"``, or None for every voxel; see :meth:`set_cage`.
        self.threshold = None
        #: A loaded volume (:class:`~vhm_viz.app.volume.VolumeView`); its outline box
        #: surface is then the display dataset (voxels are never bound one by one).
        self.volume = None
        # undo / redo: snapshots of the edited state (see :meth:`checkpoint`)
        self._undo: list[dict] = []
        self._redo: list[dict] = []

    # ------------------------------------------------------------------ data
    @property
    def has_data(self) -> bool:
        """Whether a dataset is loaded."""
        return self.rest is not None

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
            and len(self.positions) > 0
        )

    def _set_data(self, data, source: dict) -> None:
        import pyvista as pv

        from vhm_viz.app.volume import VolumeView, is_volume

        self.volume = VolumeView(data) if is_volume(data) else None
        if self.volume is not None:
            display = self.volume.outline()
        else:
            if isinstance(data, pv.ImageData | pv.RectilinearGrid):
                data = data.cast_to_structured_grid()
            display = data.copy(deep=True)
        display.points = np.asarray(display.points, dtype=np.float64)
        # the rest pose's normals would shade (and export) the deformed shape wrongly: drop
        # them; the renderer then shades each triangle by its deformed geometry
        for name in {"Normals", display.point_data.active_normals_name} - {None}:
            if name in display.point_data:
                del display.point_data[name]
        self.rest = data
        self.display = display
        self._rest_points = np.array(display.points, dtype=np.float64)
        self.source = source
        self.input_files = [Path(source["path"])] if "path" in source else []
        self.cage = None
        self.threshold = None
        self.anchors = np.zeros((0, 3))
        self.positions = []
        self.jacobians = []
        self.deformer = None
        self.binding = None
        self.proxy = None
        self.proxy_binding = None
        self.full_stale = False
        self.last_report = None
        self.certificate = None
        self._initial_rotations = None
        self._initial_contraction = None
        self._deformer_stale = True
        self._layout_stale = True
        self._undo, self._redo = [], []

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
        from vhm_viz.examples import bar

        sc = bar(kind, mode=self.mode, alpha=self.alpha, resolution=resolution)
        self._set_data(sc.surface, {"bar": kind, "resolution": int(resolution)})
        self.cage = sc.cage
        self.anchors = np.array(sc.anchors, dtype=float)
        if apply:
            c = sc.constraints
            self.positions = [
                PositionConstraint(np.array(p), np.array(t))
                for p, t in zip(c["positions"], c["targets"], strict=True)
            ]
            self.jacobians = [
                JacobianConstraint.from_matrix(p, j)
                for p, j in zip(c["jacobian_points"], c["jacobians"], strict=True)
            ]
        else:
            # hold the bottom cap so that dragging has something to pull against
            self.positions = [
                PositionConstraint(np.array(p), np.array(p))
                for p in sc.constraints["positions"][:5]
            ]
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
        self.cage = cage
        self.anchors = (
            self.anchors[cage.contains(self.anchors)] if len(self.anchors) else self.anchors
        )
        self._drop_outside_constraints()
        self._deformer_stale = True

    def _volume_values(self):
        """The scalar values of a volume's points; None for other data."""
        import pyvista as pv

        if self.volume is not None:
            return self.volume.values
        if not isinstance(self.rest, pv.StructuredGrid | pv.ImageData | pv.RectilinearGrid):
            return None
        from vhm_viz.autocage.cage import volume_values

        try:
            values, _ = volume_values(self.rest)
        except ValueError:
            return None
        return values if len(values) == len(self._rest_points) else None

    def _check_region_inside(self, inside: np.ndarray) -> None:
        """Accept a cage that leaves points out only when it encloses a volume's region."""
        from vhm_viz.autocage.cage import resolve_threshold
        from vhm_viz.core.errors import describe_indices

        values = self._volume_values()
        bad = np.nonzero(~inside)[0]
        if values is None:
            raise CageError(
                f"the cage does not enclose the shape: {bad.size} of {len(inside)} points "
                f"are outside (indices {describe_indices(bad)})"
            )
        if self.threshold is not None:
            thr = resolve_threshold(values, self.threshold)
            missed = np.nonzero(~inside & (values > thr))[0]
            if missed.size:
                raise CageError(
                    f"the cage does not enclose the region above {thr:.6g}: {missed.size} of "
                    f"{int((values > thr).sum())} voxels are outside (indices "
                    f"{describe_indices(missed)})"
                )
            return
        thr = float(values[~inside].max())
        region = int((values > thr).sum())
        if region == 0:
            raise CageError(
                f"the cage does not enclose the volume: {bad.size} of {len(inside)} voxels are "
                "outside, among them the largest values"
            )
        self.threshold = thr
        self.notes.append(
            f"the cage encloses the {region} voxels above {thr:.6g} (threshold set to it); "
            f"the {bad.size} voxels outside stay put"
        )

    def load_cage(self, path) -> None:
        """Read, validate and use a cage file (OBJ, OFF, PLY, STL, VTP, VTK)."""
        from vhm_viz.io import read_cage

        try:
            cage = read_cage(path)
        except CageError:
            raise
        except (OSError, ValueError) as exc:
            raise CageError(f"{Path(path).name}: {exc}") from exc
        self.set_cage(cage)
        self.input_files.append(Path(path))

    def auto_cage(self, max_faces: int = 500, progress: ProgressFn = _noop_progress):
        """Generate a cage around the data (:func:`vhm_viz.autocage.auto_cage`); not applied.

        Returns the cage; call :meth:`set_cage` with it (on the UI thread).
        """
        from vhm_viz.autocage import auto_cage

        if self.rest is None:
            raise ValueError("load data first")
        progress(0.05, "generating cage")
        return auto_cage(self.rest, max_faces=int(max_faces), threshold=self.threshold)

    def _drop_outside_constraints(self) -> None:
        if self.cage is None:
            return
        if self.positions:
            keep = self.cage.contains(np.array([c.point for c in self.positions]))
            self.positions = [c for c, k in zip(self.positions, keep, strict=True) if k]
        if self.jacobians:
            keep = self.cage.contains(np.array([c.point for c in self.jacobians]))
            self.jacobians = [c for c, k in zip(self.jacobians, keep, strict=True) if k]

    # ------------------------------------------------------------------ anchors
    def set_anchors(self, anchors) -> None:
        """Use these anchor points (must lie inside the cage)."""
        a = np.asarray(anchors, dtype=float).reshape(-1, 3)
        if self.cage is not None and len(a):
            inside = self.cage.contains(a)
            if not inside.all():
                from vhm_viz.core.errors import describe_indices

                raise ValueError(
                    f"anchors {describe_indices(np.nonzero(~inside)[0])} are outside the cage"
                )
        self.anchors = a
        self._deformer_stale = True

    def load_anchors(self, path, count: int = 50) -> None:
        """Anchors from a file: the JSON ``vhm-viz anchors`` writes, or rigidity lines.

        Rigidity lines (``.tgf`` skeleton, OFF polylines, any VTK polyline dataset) get
        ``count`` anchors spread along them (:func:`vhm_viz.anchors_from_polylines`).
        """
        from vhm_viz.core.anchors import anchors_from_polylines
        from vhm_viz.io import read_anchors, read_rigidity_lines

        if Path(path).suffix.lower() == ".json":
            self.set_anchors(read_anchors(path))
        else:
            pts, edges = read_rigidity_lines(path)
            self.set_anchors(anchors_from_polylines(pts, edges, int(count)))
        self.input_files.append(Path(path))

    def auto_anchors(self, count: int = 50) -> np.ndarray:
        """Compute ``count`` anchors automatically (not applied; see :meth:`set_anchors`)."""
        from vhm_viz.autocage import auto_anchors

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
        self.anchors = np.vstack([self.anchors, p])
        self._deformer_stale = True
        return len(self.anchors) - 1

    def remove_anchor(self, index: int) -> None:
        """Remove anchor ``index``."""
        if not 0 <= index < len(self.anchors):
            raise IndexError(f"anchor {index} does not exist ({len(self.anchors)} anchors)")
        self.anchors = np.delete(self.anchors, index, axis=0)
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
        self.positions.append(PositionConstraint(p.copy(), t.copy()))
        self._layout_stale = True
        return len(self.positions) - 1

    def add_jacobian_constraint(self, point, angles=None, scale=None) -> int:
        """Add a Jacobian constraint (default: the closest similarity to the current one)."""
        p = np.asarray(point, dtype=float).reshape(3)
        self._check_constraint_point(p)
        c = JacobianConstraint.from_matrix(p, self.jacobian_of(p))
        if angles is not None:
            c.angles = np.asarray(angles, float).reshape(3)
        if scale is not None:
            c.scale = float(scale)
        if not c.scale > 0:
            raise ConstraintError(f"the Jacobian scale must be positive; got {c.scale}")
        self.jacobians.append(c)
        self._layout_stale = True
        return len(self.jacobians) - 1

    def remove_constraint(self, kind: str, index: int) -> None:
        """Remove position (``kind="position"``) or Jacobian (``"jacobian"``) constraint."""
        items = self.positions if kind == "position" else self.jacobians
        if not 0 <= index < len(items):
            raise IndexError(f"{kind} constraint {index} does not exist ({len(items)})")
        del items[index]
        self._layout_stale = True

    def set_target(self, index: int, target) -> None:
        """Move the target of position constraint ``index`` (no refactorisation)."""
        t = np.asarray(target, dtype=float).reshape(3)
        if not np.isfinite(t).all():
            raise ValueError("target must be finite")
        self.positions[index].target = t.copy()
        self._targets_stale = True

    def set_jacobian(self, index: int, angles=None, scale=None) -> None:
        """Change the angles (degrees) and/or scale of Jacobian constraint ``index``."""
        c = self.jacobians[index]
        if scale is not None:
            if not float(scale) > 0:
                raise ConstraintError(f"Jacobian constraint {index}: scale must be positive")
            c.scale = float(scale)
        if angles is not None:
            c.angles = np.asarray(angles, float).reshape(3)
        self._targets_stale = True

    def set_jacobian_rotation(self, index: int, rotation) -> None:
        """Set the target rotation of Jacobian constraint ``index`` (scale kept).

        ``rotation`` (3, 3) is replaced by its closest rotation (polar decomposition).
        """
        r = JacobianConstraint.from_matrix(self.jacobians[index].point, rotation)
        self.set_jacobian(index, angles=r.angles)

    def set_point(self, kind: str, index: int, point) -> None:
        """Move the rest-space point of a constraint (changes the layout)."""
        p = np.asarray(point, dtype=float).reshape(3)
        self._check_constraint_point(p)
        (self.positions if kind == "position" else self.jacobians)[index].point = p.copy()
        self._layout_stale = True

    def constraint_arrays(self) -> dict:
        """The constraints in :meth:`Deformer.set_constraints` form."""
        pos = np.array([c.point for c in self.positions]).reshape(-1, 3)
        tgt = np.array([c.target for c in self.positions]).reshape(-1, 3)
        out = {"positions": pos, "targets": tgt}
        if self.jacobians:
            out["jacobian_points"] = np.array([c.point for c in self.jacobians])
            out["jacobians"] = np.array([c.matrix for c in self.jacobians])
        return out

    # ------------------------------------------------------------------ settings
    def set_mode(self, mode: str) -> None:
        """Rigid or similar (no refactorisation; re-solve to see the effect)."""
        if mode not in ("rigid", "similar"):
            raise ValueError(f"mode must be 'rigid' or 'similar'; got {mode!r}")
        self.mode = mode
        if self.deformer is not None:
            self.deformer.mode = mode

    def set_alpha(self, alpha: float) -> None:
        """Stiffness (changes lambda: the deformer is rebuilt by the next :meth:`prepare`)."""
        alpha = float(alpha)
        if not (np.isfinite(alpha) and alpha > 0):
            raise ValueError(f"alpha must be positive; got {alpha}")
        if alpha != self.alpha:
            self.alpha = alpha
            self._deformer_stale = True

    # ------------------------------------------------------------------ pipeline
    def prepare(self, progress: ProgressFn = _noop_progress, cancelled=lambda: False) -> None:
        """Build what is stale: deformer, constraint layout, shape binding.

        Safe to run in a worker thread while the UI does not modify the controller.

        Raises
        ------
        Cancelled
            ``cancelled()`` became true (state stays stale, nothing half-built is kept).
        OutsideCageError, ConstraintError, ValueError
            Invalid anchors or constraints (the message names them).
        """

        def check():
            if cancelled():
                raise Cancelled("cancelled")

        if not self.can_solve:
            missing = [
                name
                for name, ok in (
                    ("data", self.rest is not None),
                    ("a cage", self.cage is not None),
                    ("anchors", len(self.anchors) > 0),
                    ("a position constraint", len(self.positions) > 0),
                )
                if not ok
            ]
            raise ConstraintError("cannot deform yet: missing " + ", ".join(missing))
        deformer, binding = self.deformer, self.binding
        rebuilt = False
        scene = self.scene()
        try:
            if self._deformer_stale or deformer is None:
                progress(0.0, "building the deformer")
                deformer = scene.build(cage=self.cage)  # also factorises the constraints
                binding = None
                rebuilt = True
            elif self._layout_stale:
                progress(0.02, "factorising the constraints")
                deformer.set_constraints(**scene.constraint_arguments())
            check()
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
            proxy, proxy_binding = self._prepare_proxy(deformer, rebuilt, cancelled)
        except AbortedError as exc:
            raise Cancelled("cancelled") from exc
        self.deformer, self.binding = deformer, binding
        self.notes.extend(n for n in deformer.notes if n not in self.notes)  # pinned shells
        self.proxy, self.proxy_binding = proxy, proxy_binding
        self._deformer_stale = self._layout_stale = False
        self._targets_stale = False
        progress(1.0, "ready")

    @property
    def uses_proxy(self) -> bool:
        """Whether :meth:`drag` deforms the proxy instead of the full shape."""
        return bool(self.lod) and self.proxy_binding is not None

    def copy_lod_settings(self, other: ExplorerController) -> None:
        """Take ``lod``, ``lod_points`` and ``proxy_triangles`` from another controller."""
        self.lod, self.lod_points = other.lod, other.lod_points
        self.proxy_triangles = other.proxy_triangles

    @property
    def proxy_rest_points(self) -> np.ndarray:
        """(Q, 3) rest positions of the drag proxy's points (empty without a proxy)."""
        return self._proxy_rest

    def _prepare_proxy(self, deformer, rebuilt: bool, cancelled):
        """Build or refresh the level-of-detail proxy and its binding (see :func:`make_proxy`)."""
        proxy, pb = self.proxy, self.proxy_binding
        if not self.lod or self.display is None or self.display.n_points <= self.lod_points:
            return None, None
        if proxy is None:
            proxy = make_proxy(self.rest, self.proxy_triangles)
            self._proxy_rest = np.array(proxy.points, dtype=np.float64)
            pb = None
        if pb is None or rebuilt:
            pb = deformer.bind(
                self._proxy_rest, outside="passthrough", dtype=np.float32, abort=cancelled
            )
        else:
            pb.refresh(abort=cancelled)
        return proxy, pb

    def _push_targets(self) -> None:
        arr = self.constraint_arrays()
        self.deformer.update_targets(targets=arr["targets"], jacobians=arr.get("jacobians"))
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
        contraction = None
        if self._initial_rotations is not None:
            init, self._initial_rotations = self._initial_rotations, None
            contraction, self._initial_contraction = self._initial_contraction, None
        rep = self.deformer.solve(
            max_iterations=self.max_iterations if max_iterations is None else max_iterations,
            tolerance=self.tolerance if tolerance is None else float(tolerance),
            init=init,
            contraction=contraction,
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

    def deform_proxy(self) -> np.ndarray:
        """Write the deformed points into :attr:`proxy` in place (the full shape lags)."""
        out = np.asarray(self.proxy.points)
        self.proxy_binding.deform(out=out)
        self.proxy.GetPoints().Modified()
        self.full_stale = True
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
        if proxy:
            self.deform_proxy()
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
        if self.proxy is not None:
            np.asarray(self.proxy.points)[:] = self._proxy_rest
            self.proxy.GetPoints().Modified()
        self.full_stale = False

    # ------------------------------------------------------------------ analysis
    def metrics(self) -> dict:
        """E_rigid and E_volume of triangle surfaces (NaN otherwise), last energy."""
        from vhm_viz.core import metrics as M

        out = {"E_rigid": float("nan"), "E_volume": float("nan")}
        self._catch_up()
        tris = self.triangles()
        if tris is not None and len(tris):
            d = self.deformed_points
            out["E_rigid"] = float(M.rigidity_distortion(self._rest_points, d, tris))
            try:
                out["E_volume"] = float(M.volume_change(self._rest_points, d, tris))
            except ValueError:
                pass
        if self.last_report is not None:
            out["energy"] = self.last_report.final_energy
            out["iterations"] = self.last_report.iterations
        if self.rest is not None and self.display is not None and self.volume is None:
            from vhm_viz.filters import cell_quality

            quality = cell_quality(self.rest, self.deformed_points)
            if quality is not None:
                out["inverted_cells"] = quality["summary"]["inverted"]
                out["cells"] = quality["summary"]["cells"]
        if self.certificate is not None:
            out["certificate"] = self.certificate.status
        return out

    def certify(
        self,
        max_cubes: int = 200_000,
        progress: ProgressFn = _noop_progress,
        cancelled=lambda: False,
    ):
        """Certify the current map injective over the shape, or find witnesses of folds.

        The region is :func:`vhm_viz.filters.region_of` of the loaded data (a tet mesh's
        tetrahedra, a closed surface's solid, a volume's box, or the cage's interior for a
        point cloud). Safe to run in a worker thread while the UI does not modify the
        controller; the answer is kept in :attr:`certificate` until the next solve.

        Returns
        -------
        InjectivityCertificate

        Raises
        ------
        ConstraintError
            Nothing solved yet.
        Cancelled
            ``cancelled()`` became true.
        """
        from vhm_viz.core.certify import certify_injectivity
        from vhm_viz.filters import region_of

        if not self.ready or self.last_report is None:
            raise ConstraintError("solve before certifying (nothing is deformed yet)")
        hm = self.deformer.harmonic_map
        region = region_of(self.rest, self.cage)
        try:
            cert = certify_injectivity(
                hm, region, max_cubes=max_cubes, progress=progress, abort=cancelled
            )
        except AbortedError as exc:
            raise Cancelled("cancelled") from exc
        self.certificate, self._certified_map = cert, hm
        return cert

    def certificate_geometry(self):
        """What to draw of :attr:`certificate`, in deformed space.

        Returns
        -------
        witnesses : (w, 3) ndarray
            Images of the witnesses (``det J <= 0`` there).
        undecided : pyvista.UnstructuredGrid or None
            The undecided cubes as hexahedra with mapped corners.
        """
        if self.certificate is None:
            return np.zeros((0, 3)), None
        from vhm_viz.plotting import mapped_boxes

        hm, cert = self._certified_map, self.certificate
        witnesses = (
            hm.map(cert.witnesses, outside="passthrough")
            if len(cert.witnesses)
            else np.zeros((0, 3))
        )
        cubes = mapped_boxes(cert.undecided, hm) if len(cert.undecided) else None
        return witnesses, cubes

    def triangles(self) -> np.ndarray | None:
        """(m, 3) triangles of a polygonal surface made only of triangles, else None."""
        import pyvista as pv

        d = self.display
        if not isinstance(d, pv.PolyData) or d.GetNumberOfPolys() == 0:
            return None
        if not d.is_all_triangles:
            return None
        return np.asarray(d.regular_faces)

    # ------------------------------------------------------------------ export / scenes
    def export(self, path) -> None:
        """Write the deformed dataset (format from the suffix, default the input's).

        The display is deformed through a float32 binding (fast to drag); the export
        evaluates the harmonic map in float64, so it equals ``vhm-viz deform`` of the saved
        scene to rounding.
        """
        path = Path(path)
        if self.display is None:
            raise ValueError("nothing loaded")
        self._catch_up()
        if not path.suffix:
            src = self.source.get("path")
            path = path.with_suffix(Path(src).suffix if src else ".vtp")
        refuse_inputs(path, self.input_files)
        if self.volume is not None:
            self._export_volume(path)
            return
        data = self.display.copy(deep=True)
        if self.ready and self.last_report is not None:
            data.points = self.deformer.harmonic_map.map(self._rest_points, outside="passthrough")
        for name in [n for n in data.point_data.keys() if n.startswith("_")]:
            del data.point_data[name]  # display helpers (e.g. the slice clipping distance)
        try:
            write_dataset(path, data)
        except (ValueError, TypeError) as exc:  # a suffix VTK cannot write this type to
            raise ValueError(f"cannot write {path.name}: {exc}") from exc

    def _export_volume(self, path: Path) -> None:
        """A volume: resampled (image suffixes) or warped, as ``vhm-viz deform`` does it."""
        from vhm_viz.cli.deform import RESAMPLED_SUFFIXES
        from vhm_viz.io import suffix_of

        if not (self.ready and self.last_report is not None):
            raise ValueError("nothing to export yet: solve first")
        hm = self.deformer.harmonic_map
        if suffix_of(path) in RESAMPLED_SUFFIXES:
            data = self.rest.vhm.resample(hm, outside="passthrough")
        else:
            data = self.rest.vhm.deform(hm, outside="passthrough")
        write_dataset(path, data)

    # ------------------------------------------------------------------ undo / redo
    _SNAPSHOT_KEYS = ("cage", "anchors", "positions", "jacobians", "mode", "alpha", "threshold")

    def snapshot(self) -> dict:
        """The edited state (cage, anchors, constraints, mode, alpha, threshold), copied."""
        from copy import deepcopy

        snap = {k: getattr(self, k) for k in ("cage", "mode", "alpha", "threshold")}
        snap["anchors"] = np.array(self.anchors, copy=True)
        snap["positions"] = deepcopy(self.positions)
        snap["jacobians"] = deepcopy(self.jacobians)
        return snap

    def checkpoint(self, state: dict | None = None) -> None:
        """Remember the state before a user action (default: now); clears the redo history.

        The window calls this for every constraint, anchor, cage and setting edit (with the
        :meth:`snapshot` taken before it, once the edit succeeded) and once at the start of
        a drag, so :meth:`undo` steps back one user action.
        """
        self._undo.append(self.snapshot() if state is None else state)
        del self._undo[:-UNDO_LIMIT]
        self._redo.clear()

    @property
    def can_undo(self) -> bool:
        """Whether :meth:`undo` has a state to go back to."""
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        """Whether :meth:`redo` has a state to go forward to."""
        return bool(self._redo)

    def undo(self) -> bool:
        """Go back to the state before the last user action; False when there is none."""
        return self._step(self._undo, self._redo)

    def redo(self) -> bool:
        """Re-apply the last undone action; False when there is none."""
        return self._step(self._redo, self._undo)

    def _step(self, source: list, target: list) -> bool:
        if not source:
            return False
        target.append(self.snapshot())
        self._restore(source.pop())
        return True

    def _restore(self, snap: dict) -> None:
        """Set a snapshot and mark stale exactly what differs (cheapest rebuild)."""
        same_shape = (
            snap["cage"] is self.cage
            and snap["alpha"] == self.alpha
            and np.array_equal(snap["anchors"], self.anchors)
        )
        points = [c.point.tolist() for c in snap["positions"] + snap["jacobians"]]
        layout = [c.point.tolist() for c in self.positions + self.jacobians]
        kinds = (len(snap["positions"]), len(snap["jacobians"]))
        same_layout = kinds == (len(self.positions), len(self.jacobians)) and points == layout
        for k in self._SNAPSHOT_KEYS:
            setattr(self, k, snap[k])
        if self.deformer is not None:
            self.deformer.mode = self.mode
        if not same_shape:
            self._deformer_stale = True
        elif not same_layout:
            self._layout_stale = True
        self._targets_stale = True
        self.certificate = None

    def scene(self, relative_to=None) -> Scene:
        """The deformation being edited, as a :class:`~vhm_viz.scene.Scene`.

        Parameters
        ----------
        relative_to : path-like, optional
            Directory that the data path is written relative to (the scene file's).

        Raises
        ------
        ValueError
            Without a cage, anchors or a position constraint (a scene needs them).
        """
        if self.cage is None or not len(self.anchors) or not self.positions:
            raise ValueError(
                "nothing to describe yet: a scene needs a cage, anchors and a position constraint"
            )
        arr = self.constraint_arrays()
        data = None
        if "path" in self.source:
            path = self.source["path"]
            if relative_to is not None:
                try:
                    path = os.path.relpath(path, Path(relative_to).resolve())
                except ValueError:  # another drive
                    pass
            data = {"path": path}
        elif "bar" in self.source:
            data = dict(self.source)
        solver, solution, contraction = dict(self.solver), None, None
        if self.ready and self.last_report is not None and self.last_report.converged:
            # the solved state: the command line starts there and reproduces it
            solution = np.array(self.deformer.rotations_at_anchors)
            rho = self.last_report.contraction
            contraction = float(rho) if np.isfinite(rho) else None
            solver["init"] = "solution"
        elif solver["init"] == "solution":
            solver["init"] = "identity"
        scene = Scene(
            cage={
                "vertices": np.array(self.cage.vertices, dtype=np.float64),
                "faces": np.array(self.cage.faces, dtype=np.int64),
            },
            anchors={"points": np.array(self.anchors, dtype=np.float64)},
            constraints={
                "positions": arr["positions"],
                "targets": arr["targets"],
                "jacobian_points": arr.get("jacobian_points", np.zeros((0, 3))),
                "jacobians": arr.get("jacobians", np.zeros((0, 3, 3))),
            },
            mode=self.mode,
            alpha=float(self.alpha),
            solver=solver,
            data=data,
            solution=solution,
            solution_contraction=contraction,
        )
        if solution is not None:
            # the solved map too: ParaView's filters then use it instead of solving again
            scene.record_map(self.deformer)
        return scene

    def save_scene(self, path) -> None:
        """Write the scene (:mod:`vhm_viz.scene`'s format, the one ``vhm-viz deform`` reads).

        The data the scene was made for is referenced relative to the scene file, and a
        converged solution is stored with ``"init": "solution"``, with its map
        (:meth:`~vhm_viz.scene.Scene.record_map`).
        """
        path = Path(path)
        refuse_inputs(path, self.input_files)
        self.scene(relative_to=path.parent).save(path)

    def load_scene(self, path, data_from: ExplorerController | None = None) -> list[str]:
        """Load a scene; the state is replaced only on success.

        A scene that names no data applies to the data already loaded (in ``data_from``,
        default this controller).

        Returns
        -------
        list of str
            Notes for the user (e.g. that an old explorer file was converted).
        """
        path = Path(path)
        current = self if data_from is None else data_from
        scene = Scene.load(path)
        new = ExplorerController()
        new.copy_lod_settings(self)
        new.max_iterations, new.tolerance = self.max_iterations, self.tolerance
        new.mode, new.alpha = scene.mode, float(scene.alpha)
        new.solver = settle_settings(scene.solver)
        new._load_data_ref(scene.data, path, current)
        cage = scene.build_cage(new.rest)
        new.set_cage(cage)
        new.set_anchors(scene.build_anchors(cage, new.rest))
        args = scene.constraint_arguments()
        new.positions = [
            PositionConstraint(np.array(p, float), np.array(t, float))
            for p, t in zip(args["positions"], args["targets"], strict=True)
        ]
        new.jacobians = [
            JacobianConstraint.from_matrix(p, j)
            for p, j in zip(args.get("jacobian_points", ()), args.get("jacobians", ()), strict=True)
        ]
        new._layout_stale = True
        if scene.solution is not None and scene.solution.shape == (len(new.anchors), 3, 3):
            new._initial_rotations = np.array(scene.solution)
            new._initial_contraction = scene.solution_contraction
        new.notes = list(scene.notes)
        self.adopt(new)
        return list(scene.notes)

    def adopt(self, other: ExplorerController) -> None:
        """Take over another controller's whole state (built in a worker thread)."""
        self.__dict__.update(other.__dict__)

    def _load_data_ref(self, src: dict | None, scene_path: Path, current) -> None:
        """Load the data a scene names, or take the current controller's."""
        src = src or {}
        if "bar" in src:
            self.load_bar(src["bar"], resolution=int(src.get("resolution", 39)), apply=False)
            self.positions = []
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

    # ------------------------------------------------------------------ picking
    def rest_point_from_cell(self, cell_id: int, world_point) -> np.ndarray:
        """Rest-space point of a pick on the *deformed* display dataset.

        The picked point's interpolation weights in the deformed cell are applied to the
        cell's rest points (exact for linear cells); vertex-only cells give the vertex.
        """
        import vtk

        x = np.asarray(world_point, dtype=float).reshape(3)
        if cell_id is None or cell_id < 0:
            i = int(np.argmin(np.linalg.norm(self.deformed_points - x, axis=1)))
            return self._rest_points[i].copy()
        cell = self.display.GetCell(int(cell_id))
        n = cell.GetNumberOfPoints()
        ids = np.array([cell.GetPointId(k) for k in range(n)])
        if n == 1:
            return self._rest_points[ids[0]].copy()
        closest = [0.0, 0.0, 0.0]
        sub = vtk.reference(0)
        pc = [0.0, 0.0, 0.0]
        d2 = vtk.reference(0.0)
        w = [0.0] * n
        cell.EvaluatePosition(list(x), closest, sub, pc, d2, w)
        w = np.asarray(w, dtype=float)
        if not np.isfinite(w).all() or abs(w.sum() - 1) > 1e-6:
            i = ids[int(np.argmin(np.linalg.norm(self.deformed_points[ids] - x, axis=1)))]
            return self._rest_points[i].copy()
        return w @ self._rest_points[ids]
