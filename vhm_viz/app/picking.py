"""Picking on the deformed shape: from a click to a rest-space point, and what it does.

:func:`rest_point_of_pick` maps a pick on the *deformed* display dataset back to rest
space. :class:`ShapePicker` is the window's click path: the interaction mode (toolbar)
decides whether a click adds a position or Jacobian constraint, or adds or removes an
anchor.
"""

from __future__ import annotations

import numpy as np
import vtk

__all__ = ["MODES", "ShapePicker", "apply_pick", "rest_point_of_pick"]


def rest_point_of_pick(display, rest_points: np.ndarray, cell_id: int, world_point) -> np.ndarray:
    """Rest-space point of a pick on the deformed ``display`` dataset.

    The picked point's interpolation weights in the deformed cell are applied to the
    cell's rest points (exact for linear cells); vertex-only cells give the vertex, and a
    pick without a cell (``cell_id`` None or negative) the nearest point.

    Parameters
    ----------
    display : pyvista.DataSet
        The deformed dataset that was picked.
    rest_points : (P, 3) ndarray
        Its points' rest positions.
    cell_id : int or None
    world_point : (3,) array_like
        The picked position (deformed space).

    Returns
    -------
    (3,) ndarray
    """
    x = np.asarray(world_point, dtype=float).reshape(3)
    deformed = np.asarray(display.points)
    if cell_id is None or cell_id < 0:
        i = int(np.argmin(np.linalg.norm(deformed - x, axis=1)))
        return rest_points[i].copy()
    cell = display.GetCell(int(cell_id))
    n = cell.GetNumberOfPoints()
    ids = np.array([cell.GetPointId(k) for k in range(n)])
    if n == 1:
        return rest_points[ids[0]].copy()
    closest = [0.0, 0.0, 0.0]
    sub = vtk.reference(0)
    pc = [0.0, 0.0, 0.0]
    d2 = vtk.reference(0.0)
    w = [0.0] * n
    cell.EvaluatePosition(list(x), closest, sub, pc, d2, w)
    w = np.asarray(w, dtype=float)
    if not np.isfinite(w).all() or abs(w.sum() - 1) > 1e-6:
        i = ids[int(np.argmin(np.linalg.norm(deformed[ids] - x, axis=1)))]
        return rest_points[i].copy()
    return w @ rest_points[ids]


#: What a left click on the shape does, per interaction mode (the toolbar's labels).
MODES = {
    "view": "View / drag handles",
    "position": "Add position constraint",
    "jacobian": "Add Jacobian constraint",
    "anchor+": "Add anchor",
    "anchor-": "Remove anchor",
}


class ShapePicker:
    """Picks the shape's actor at a display pixel (the explorer's click path).

    Parameters
    ----------
    plotter : pyvistaqt.QtInteractor
    """

    def __init__(self, plotter):
        self.plotter = plotter

    def pick(self, actor, x: int, y: int):
        """``(cell_id, (3,) world point)`` of ``actor`` under display pixel ``(x, y)``, or None."""
        picker = vtk.vtkCellPicker()
        picker.SetTolerance(0.0005)
        picker.PickFromListOn()
        picker.AddPickList(actor)
        if not picker.Pick(x, y, 0, self.plotter.renderer):
            return None
        return picker.GetCellId(), np.array(picker.GetPickPosition())

    def display_coordinates(self, world_point) -> tuple[int, int]:
        """Display pixel of a world point (for scripted clicks)."""
        ren = self.plotter.renderer
        ren.SetWorldPoint(*np.asarray(world_point, float), 1.0)
        ren.WorldToDisplay()
        x, y, _ = ren.GetDisplayPoint()
        return int(round(x)), int(round(y))


def apply_pick(controller, mode: str, rest, world_point):
    """Do what ``mode`` says at a picked point (rest-space ``rest``, deformed ``world_point``).

    Returns
    -------
    (message, selected) or None
        A status message and the ``(kind, index)`` of the constraint added (None for
        anchors); None when nothing changed.
    """
    if mode == "position":
        i = controller.add_position_constraint(rest, target=np.asarray(world_point, float))
        return f"position constraint {i} added", ("position", i)
    if mode == "jacobian":
        i = controller.add_jacobian_constraint(rest)
        return f"Jacobian constraint {i} added", ("jacobian", i)
    if mode == "anchor+":
        i = controller.add_anchor(rest)
        return f"anchor {i} added", None
    if mode == "anchor-":
        i = controller.nearest_anchor(rest)
        if i is None:
            return None
        controller.remove_anchor(i)
        return f"anchor {i} removed", None
    return None
