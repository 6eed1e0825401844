"""Values typed into the explorer's constraint table that the scene cannot take.

An edit that is refused, or whose solve fails, leaves everything as it was: the scene, the
shown shape, the table, the handles and the undo history; one line says why, and editing,
undo and redo go on working. Driven through the table's cells under a real X display.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pyvistaqt")
pytest.importorskip("pytestqt")

pytestmark = pytest.mark.gui

# the real X display, one-thread BLAS and the window (fixtures shared with other GUI tests)
from tests.gui import bar_with_a_gizmo, single_threaded_blas, window, xvfb_display  # noqa: E402, F401


def _shown(win, qtbot) -> dict:
    """What an edit may change: constraints, shape, table, handles (deferred fills done)."""
    qtbot.wait(20)  # the table is refilled when the event loop is idle
    ctrl, table = win.ctrl, win.constraints_panel.table
    cells = [(r, c) for r in range(table.rowCount()) for c in range(table.columnCount())]
    return {
        "constraints": {k: v.copy() for k, v in ctrl.scene.constraints.items()},
        "points": ctrl.deformed_points.copy(),
        "table": [table.item(r, c).text() for r, c in cells],
        "handles": np.array([h.GetCenter() for h in win.shape_view.handles]),
    }


def _assert_same(before: dict, after: dict, atol: float = 1e-6) -> None:
    """The same scene and table; the shape within ``atol`` (it may have been solved again)."""
    for name, array in before["constraints"].items():
        np.testing.assert_array_equal(after["constraints"][name], array, err_msg=name)
    np.testing.assert_allclose(after["points"], before["points"], atol=atol)
    assert after["table"] == before["table"]
    np.testing.assert_allclose(after["handles"], before["handles"], atol=1e-9)


def _type(win, row: int, column: int, text: str) -> None:
    """Type ``text`` into a cell of the constraint table and wait for what follows."""
    with win.waiting_for_jobs():
        win.constraints_panel.table.item(row, column).setText(text)


def _history(win, action: str) -> None:
    with win.waiting_for_jobs():
        getattr(win, f"{action}_action").trigger()
    assert win.last_error is None, win.last_error


# (row of the bar with a gizmo: 0 the first position constraint, "J" the Jacobian one;
#  column; text; what the message says)
FIELDS = {
    "target x beyond the scene's range": (0, 1, "1e300", "out of range"),
    "scale beyond the scene's range": ("J", 4, "1e308", "out of range"),
    "scale whose matrix is singular in float64": ("J", 4, "1e-200", "edit was undone"),
}


@pytest.mark.parametrize("field", FIELDS, ids=list(FIELDS))
def test_a_value_the_scene_cannot_take_leaves_everything_as_it_was(window, qtbot, field):
    win = window
    ctrl, _ = bar_with_a_gizmo(win)
    jrow = len(ctrl.positions)
    row, column, text, says = FIELDS[field]
    row = jrow if row == "J" else row
    # an edit then undone: there is one step to undo and one to redo
    _type(win, jrow, 4, "1.5")
    assert ctrl.jacobians[0].scale == pytest.approx(1.5)
    _history(win, "undo")
    before, errors = _shown(win, qtbot), len(win.errors)

    _type(win, row, column, text)

    _assert_same(before, _shown(win, qtbot))
    assert len(win.errors) == errors + 1, win.errors[errors:]
    message = win.last_error
    assert says in message and "\n" not in message, message
    assert win.statusBar().currentMessage() == message
    # the history is the one before the edit: redo, then two undos back to no Jacobian
    win.last_error = None
    _history(win, "redo")
    assert ctrl.jacobians[0].scale == pytest.approx(1.5)
    _history(win, "undo")
    _assert_same(before, _shown(win, qtbot), atol=1e-9)
    _history(win, "undo")
    assert not ctrl.jacobians
    # and editing goes on: a valid edit solves, undo and redo step over it
    _history(win, "redo")
    _type(win, jrow, 4, "1.2")
    assert win.last_error is None, win.last_error
    jacobian = ctrl.jacobians[0]
    J = ctrl.deformer.harmonic_map.jacobian(jacobian.point[None])[0]
    np.testing.assert_allclose(J, jacobian.matrix, atol=1e-6)
    _history(win, "undo")
    assert ctrl.jacobians[0].scale == pytest.approx(1.0)
    _history(win, "redo")
    assert ctrl.jacobians[0].scale == pytest.approx(1.2)


@pytest.mark.parametrize("scale", ["1e4", "50"])
def test_undo_and_redo_bring_back_the_shapes_that_were_shown(window, qtbot, scale):
    # the solve is not convex: solved again from the current shape, a scene undone (or
    # redone) can settle on another solution than the one shown before; undo and redo show
    # the shapes that were shown, twice over
    win = window
    ctrl, _ = bar_with_a_gizmo(win)
    jrow = len(ctrl.positions)
    before = _shown(win, qtbot)
    _type(win, jrow, 4, scale)
    assert win.last_error is None, win.last_error
    after = _shown(win, qtbot)
    assert np.abs(after["points"] - before["points"]).max() > 1.0
    for _ in range(2):
        _history(win, "undo")
        _assert_same(before, _shown(win, qtbot), atol=1e-9)
        _history(win, "redo")
        _assert_same(after, _shown(win, qtbot), atol=1e-9)
