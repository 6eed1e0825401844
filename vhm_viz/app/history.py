"""Undo and redo for the explorer: a history of :class:`~vhm_viz.scene.Scene` snapshots.

:class:`SceneHistory` keeps the snapshots; :class:`UndoRedo`, a base of the explorer's
controller, records and restores them with the solved state each was shown with.
"""

from __future__ import annotations

import copy

import numpy as np

from vhm_viz.core.cage import Cage
from vhm_viz.scene import Scene

__all__ = ["SceneHistory", "UNDO_LIMIT", "UndoRedo"]

# undo steps kept
UNDO_LIMIT = 100


class SceneHistory:
    """Scenes before each user action (undo) and after each undone one (redo).

    Parameters
    ----------
    limit : int
        Undo steps kept (the oldest are forgotten).
    """

    def __init__(self, limit: int = UNDO_LIMIT):
        self.limit = int(limit)
        self._undo: list[Scene] = []
        self._redo: list[Scene] = []
        self._cages: list = []
        # what the last record forgot (oldest undo steps, the redo history), for take_back
        self._forgotten: tuple[list, list] | None = None

    @staticmethod
    def snapshot(scene: Scene) -> Scene:
        """An independent copy of ``scene`` (arrays copied)."""
        return copy.deepcopy(scene)

    @staticmethod
    def changes(old: Scene, new: Scene) -> tuple[bool, bool]:
        """What going from ``old`` to ``new`` keeps.

        Returns
        -------
        same_shape : bool
            Same cage, alpha and anchors (the deformer holds).
        same_layout : bool
            Same constraint points (the constraint factorisation holds).
        """
        same_shape = (
            np.array_equal(old.cage["vertices"], new.cage["vertices"])
            and np.array_equal(old.cage["faces"], new.cage["faces"])
            and old.alpha == new.alpha
            and np.array_equal(old.anchors["points"], new.anchors["points"])
        )
        same_layout = all(
            np.array_equal(old.constraints[k], new.constraints[k])
            for k in ("positions", "jacobian_points")
        )
        return same_shape, same_layout

    def record(self, before: Scene) -> None:
        """Remember the scene before a user action; clears the redo history."""
        self._undo.append(before)
        self._forgotten = (self._undo[: -self.limit], self._redo)
        del self._undo[: -self.limit]
        self._redo = []

    def take_back(self) -> Scene | None:
        """Forget the last :meth:`record` (its action failed): the history is as before it.

        Returns the scene it recorded, or None when undo or redo came since (or nothing
        was recorded).
        """
        if self._forgotten is None:
            return None
        oldest, self._redo = self._forgotten
        self._forgotten = None
        before = self._undo.pop()
        self._undo[:0] = oldest
        return before

    def clear(self) -> None:
        """Forget everything (new data loaded)."""
        self._undo.clear()
        self._redo.clear()
        self._cages.clear()
        self._forgotten = None

    def remember_cage(self, cage) -> None:
        """Keep a cage in use, so that :meth:`cage_of` finds it without rebuilding it."""
        if not any(c is cage for c in self._cages):
            self._cages.append(cage)

    def cage_of(self, scene: Scene):
        """The built cage of ``scene``'s inline cage (None without one).

        One remembered by :meth:`remember_cage` when it has the same vertices and faces,
        else a new :class:`~vhm_viz.Cage`.
        """
        v, f = scene.cage["vertices"], scene.cage["faces"]
        if not len(f):
            return None
        for cage in reversed(self._cages):
            if np.array_equal(cage.vertices, v) and np.array_equal(cage.faces, f):
                return cage
        return Cage(v, f)

    @property
    def can_undo(self) -> bool:
        """Whether :meth:`undo` has a scene to go back to."""
        return bool(self._undo)

    @property
    def can_redo(self) -> bool:
        """Whether :meth:`redo` has a scene to go forward to."""
        return bool(self._redo)

    def undo(self, current: Scene) -> Scene | None:
        """The scene before the last action; None if none.

        ``current``, a :meth:`snapshot` of the scene now, becomes redoable (kept as given,
        as :meth:`record` keeps its scene).
        """
        return self._step(self._undo, self._redo, current)

    def redo(self, current: Scene) -> Scene | None:
        """The scene after the last undone action; None if none (``current``: as for undo)."""
        return self._step(self._redo, self._undo, current)

    def _step(self, source: list, target: list, current: Scene) -> Scene | None:
        if not source:
            return None
        self._forgotten = None
        target.append(current)
        return source.pop()


class UndoRedo:
    """Undo and redo of :class:`~vhm_viz.app.controller.ExplorerController`, a base of it.

    Steps through :class:`SceneHistory` snapshots of its ``scene``, each with the solved
    state it was shown with, and marks stale only what a step changes.
    """

    def snapshot(self) -> Scene:
        """A copy of the edited scene (what :meth:`checkpoint` records).

        With the deformer's local matrices as its ``solution`` once it has solved, so that
        undo and redo bring back the shape that was shown, not another solution of the same
        scene.
        """
        snap = SceneHistory.snapshot(self.scene)
        if self.deformer is not None and self.last_report is not None:
            snap.solution = np.array(self.deformer.rotations_at_anchors)
            rho = self.last_report.contraction
            snap.solution_contraction = float(rho) if np.isfinite(rho) else None
        return snap

    def checkpoint(self, state: Scene | None = None) -> None:
        """Remember the scene before a user action (default: now); clears the redo history.

        The window calls this for every constraint, anchor, cage and setting edit (with the
        :meth:`snapshot` taken before it, once the edit succeeded) and once at the start of
        a drag, so :meth:`undo` steps back one user action.
        """
        self.history.record(self.snapshot() if state is None else state)
        self._resume_solution = None

    def undo(self) -> bool:
        """Go back to the scene before the last user action; False when there is none."""
        return self._restore(self.history.undo(self.snapshot()))

    def redo(self) -> bool:
        """Re-apply the last undone action; False when there is none."""
        return self._restore(self.history.redo(self.snapshot()))

    def take_back(self) -> bool:
        """Back to the scene before the last recorded action, which failed; nothing to redo.

        False when undo or redo came since the record (:meth:`SceneHistory.take_back`).
        """
        return self._restore(self.history.take_back())

    def _restore(self, scene: Scene | None) -> bool:
        """Edit the recorded ``scene``, marking stale exactly what differs (cheapest rebuild)."""
        if scene is None:
            return False
        same_shape, same_layout = SceneHistory.changes(self.scene, scene)
        new = scene
        # the solved state travels beside the scene, which the explorer edits without one
        self._resume_solution, new.solution = new.solution, None
        self._resume_contraction, new.solution_contraction = new.solution_contraction, None
        self.scene = new
        self.cage = self.history.cage_of(new)
        if self.deformer is not None:
            self.deformer.mode = self.mode
        if not same_shape:
            self._deformer_stale = True
        elif not same_layout:
            self._layout_stale = True
        self._targets_stale = True
        self.certificate = None
        return True
