"""The scene the explorer edits: its solver settings, an empty one, solving and saving it.

The explorer holds one :class:`~vhm_viz.scene.Scene` with an inline cage and anchor
points; it is solved through :meth:`~vhm_viz.scene.Scene.solve_map`, like every front end,
and saved with its solved state so that ``vhm-viz deform`` reproduces the explorer.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path

import numpy as np

from vhm_viz.scene import DEFAULT_SOLVER, Scene, SolvedMap

__all__ = ["SETTLE_SOLVER", "empty_scene", "scene_for_file", "settle_settings", "solve_loaded"]

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


def empty_scene(mode: str = "rigid", alpha: float = 0.01, solver: dict | None = None,
                data: dict | None = None) -> Scene:  # fmt: skip
    """A scene without cage, anchors or constraints (what the explorer edits from)."""
    return Scene(
        cage={"vertices": np.zeros((0, 3)), "faces": np.zeros((0, 3), dtype=np.int64)},
        anchors={"points": np.zeros((0, 3))},
        constraints={
            "positions": np.zeros((0, 3)),
            "targets": np.zeros((0, 3)),
            "jacobian_points": np.zeros((0, 3)),
            "jacobians": np.zeros((0, 3, 3)),
        },
        mode=mode,
        alpha=float(alpha),
        solver=dict(SETTLE_SOLVER if solver is None else solver),
        data=data,
    )


def solve_loaded(scene: Scene, stored: Scene, data, cage, progress) -> SolvedMap:
    """Solve ``scene`` (just loaded from ``stored``), from its stored solution if it fits.

    The stored solution is the starting point when it has one matrix per anchor, whatever
    the file's ``init``; ``scene``'s solution and ``init`` are as before on return.

    Parameters
    ----------
    scene : Scene
        The explorer's scene: inline cage, anchor points, the stored scene's constraints.
    stored : Scene
        The scene as read from the file.
    data : pyvista.DataSet
    cage : Cage
        ``scene``'s cage, built.
    progress : callable(fraction, message)
    """
    init = scene.solver["init"]
    if stored.solution is not None and stored.solution.shape == (
        len(scene.anchors["points"]),
        3,
        3,
    ):
        scene.solution = np.array(stored.solution)
        scene.solution_contraction = stored.solution_contraction
        scene.solver["init"] = "solution"
    elif init == "solution":
        scene.solver["init"] = "identity"
    try:
        return scene.solve_map(data=data, cage=cage, progress=progress, reuse_stored=False)
    finally:
        scene.solution = scene.solution_contraction = None
        scene.solver["init"] = init


def scene_for_file(scene: Scene, deformer=None, report=None, relative_to=None) -> Scene:
    """A copy of the edited ``scene`` as it is saved.

    Parameters
    ----------
    scene : Scene
        The explorer's scene (inline cage, anchor points, absolute data path).
    deformer : Deformer, optional
        The solved deformer: with a converged ``report`` its solution becomes the scene's
        starting point (``"init": "solution"``; the command line starts there and
        reproduces it) and its map is stored (:meth:`Scene.record_map`: ParaView's filters
        then use it instead of solving again).
    report : SolveReport, optional
        The deformer's last solve.
    relative_to : path-like, optional
        Directory that the data path is written relative to (the scene file's).
    """
    out = copy.deepcopy(scene)
    out.notes, out.base_dir, out.stored_map = [], None, None
    data = scene.data or {}
    if "path" in data and relative_to is not None:
        try:
            out.data = {"path": os.path.relpath(data["path"], Path(relative_to).resolve())}
        except ValueError:  # another drive
            pass
    out.solution = out.solution_contraction = None
    if deformer is not None and report is not None and report.converged:
        out.solution = np.array(deformer.rotations_at_anchors)
        rho = report.contraction
        out.solution_contraction = float(rho) if np.isfinite(rho) else None
        out.solver["init"] = "solution"
        out.record_map(deformer)
    elif out.solver["init"] == "solution":
        out.solver["init"] = "identity"
    return out
