"""The rotation gizmo: a box around a Jacobian constraint's image; turning it sets the target.

:class:`RotationGizmo` owns one ``vtkBoxWidget`` (rotation only) placed at the image of the
selected Jacobian constraint's point and oriented by its target rotation.
"""

from __future__ import annotations

import numpy as np
import vtk

__all__ = ["RotationGizmo", "GIZMO_COLOR"]

GIZMO_COLOR = (0.75, 0.1, 0.75)


class RotationGizmo:
    """A rotation box widget bound to one Jacobian constraint of the controller.

    Parameters
    ----------
    plotter : pyvistaqt.QtInteractor
    controller : ExplorerController
    on_rotate : callable(index, rotation)
        The user turned the box: the (3, 3) rotation it shows now, for constraint ``index``.
        The first call of a turn comes with :attr:`turning` just set.
    on_release : callable()
        The turn ended.

    Attributes
    ----------
    widget : vtkBoxWidget or None
        The box, while a Jacobian constraint is shown and the controller is ready.
    index : int or None
        The Jacobian constraint it edits (default: the last one).
    turning : bool
        A turn is under way (the box is not re-oriented meanwhile).
    """

    def __init__(self, plotter, controller, on_rotate, on_release):
        self.plotter = plotter
        self.ctrl = controller
        self.on_rotate = on_rotate
        self.on_release = on_release
        self.widget = None
        self.index = None
        self.turning = False
        self.turn_started = False
        self._centre = np.zeros(3)

    def rebuild(self, size: float) -> None:
        """A box of half-width ``size`` around the selected constraint's image (or none)."""
        if self.widget is not None:
            self.widget.Off()
            self.widget = None
        ctrl = self.ctrl
        if not ctrl.jacobians or not ctrl.ready or self.plotter.iren is None:
            self.index = None
            return
        if self.index is None or self.index >= len(ctrl.jacobians):
            self.index = len(ctrl.jacobians) - 1
        centre = ctrl.image_of(ctrl.jacobians[self.index].point)
        w = vtk.vtkBoxWidget()
        w.SetInteractor(self.plotter.iren.interactor)
        w.SetPlaceFactor(1.0)
        w.PlaceWidget(*np.ravel(np.column_stack([centre - size, centre + size])))
        w.TranslationEnabledOff()
        w.ScalingEnabledOff()
        w.RotationEnabledOn()
        w.HandlesOff()
        w.GetOutlineProperty().SetColor(*GIZMO_COLOR)
        w.GetOutlineProperty().SetLineWidth(2)
        w.GetSelectedOutlineProperty().SetLineWidth(3)
        w.AddObserver("InteractionEvent", self._moved)
        w.AddObserver("EndInteractionEvent", self._released)
        self.widget, self._centre = w, centre
        self.turning = False
        self.follow()
        w.On()

    def follow(self) -> None:
        """Orient the box by its constraint's target rotation, at the point's image."""
        w, i = self.widget, self.index
        if w is None or i is None or self.turning or i >= len(self.ctrl.jacobians):
            return
        c = self.ctrl.jacobians[i]
        centre = self.ctrl.image_of(c.point)
        m = np.eye(4)
        rot = c.matrix / c.scale
        m[:3, :3] = rot
        m[:3, 3] = centre - rot @ self._centre
        t = vtk.vtkTransform()
        t.SetMatrix(m.ravel())
        w.SetTransform(t)

    def rotation(self) -> np.ndarray:
        """(3, 3) rotation the box shows now (the linear part of its transform)."""
        t = vtk.vtkTransform()
        self.widget.GetTransform(t)
        m = t.GetMatrix()
        return np.array([[m.GetElement(r, k) for k in range(3)] for r in range(3)])

    def _moved(self, *args) -> None:
        if self.index is None:
            return
        self.turn_started = not self.turning
        self.turning = True
        self.on_rotate(self.index, self.rotation())

    def _released(self, *args) -> None:
        self.turning = False
        self.on_release()
