"""Undo and redo for the explorer: a history of :class:`~vhm_viz.scene.Scene` snapshots."""

from __future__ import annotations

import copy

import numpy as np

from vhm_viz.core.cage import Cage
from vhm_viz.scene import Scene

__all__ = ["SceneHistory", "UNDO_LIMIT"]

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
        """The scene before the last action (``current`` becomes redoable); None if none."""
        return self._step(self._undo, self._redo, current)

    def redo(self, current: Scene) -> Scene | None:
        """The scene after the last undone action; None if none."""
        return self._step(self._redo, self._undo, current)

    def _step(self, source: list, target: list, current: Scene) -> Scene | None:
        if not source:
            return None
        self._forgotten = None
        target.append(self.snapshot(current))
        return source.pop()
