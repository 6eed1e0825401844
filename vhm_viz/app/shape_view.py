"""The shape in the 3D view: surface or tet mesh, its drag proxy, cage, markers and handles.

:class:`ShapeView` owns these actors. The shape's dataset is the controller's display
dataset, deformed **in place** (actors are never re-added while dragging). Level of detail:
while a handle is dragged the controller deforms a decimated proxy, which is shown instead
of the shape (:meth:`ShapeView.show_proxy`) until the full shape is deformed again.
The shape (and its proxy) can be cut open along a plane in rest space (:meth:`ShapeView.clip`)
so that a section through it is visible.
"""

from __future__ import annotations

import functools

import numpy as np
import pyvista as pv
import vtk

__all__ = ["ShapeView", "SHAPE_COLOR", "OUTLINE_OPACITY", "remove_named_actor"]

SHAPE_COLOR = (0.85, 0.85, 0.80)
HANDLE_COLOR = "orange"
CAGE_COLOR = (0.62, 0.74, 0.86)  # steel blue at half opacity on white
ANCHOR_COLOR = "green"
JACOBIAN_COLOR = "magenta"
# opacity of a volume's outline box (the draggable "shape" of a volume)
OUTLINE_OPACITY = 0.15


def cage_mesh(cage) -> pv.PolyData:
    """Triangle PolyData of a (core or public) cage."""
    return pv.PolyData.from_regular_faces(np.array(cage.vertices), np.array(cage.faces))


def remove_named_actor(plotter, actors: dict, name: str) -> None:
    """Take actor ``name`` out of ``actors`` and off ``plotter`` (no render), if there."""
    actor = actors.pop(name, None)
    if actor is not None:
        plotter.remove_actor(actor, render=False)


class ShapeView:
    """Actors of the shape, its drag proxy, the cage, anchor and Jacobian markers, handles.

    Parameters
    ----------
    plotter : pyvistaqt.QtInteractor
    controller : ExplorerController
    on_handle_moved : callable(index, center)
        A position handle moved (the sphere widget renders right after it).
    on_handle_released : callable()
        A handle drag ended.

    Attributes
    ----------
    actors : dict of str to vtkActor
        ``shape``, ``proxy``, ``cage``, ``anchors``, ``jacobians`` while shown.
    handles : list of vtkSphereWidget
        One per position constraint, at its target (only when the controller is ready).
    showing_proxy : bool
        The drag proxy is displayed instead of the shape.
    marker_radius : float
        Size of markers and handles (a fraction of the cage's diagonal).
    """

    def __init__(self, plotter, controller, on_handle_moved, on_handle_released):
        self.plotter = plotter
        self.ctrl = controller
        self.on_handle_moved = on_handle_moved
        self.on_handle_released = on_handle_released
        self.interactive = plotter.iren is not None
        self.actors: dict[str, object] = {}
        self.handles: list = []
        self.showing_proxy = False
        self.marker_radius = 0.02
        self._shape_data = None
        self._proxy_data = None
        self._clip_plane = None  # (origin, normal) in rest space
        self._clippers: dict[str, object] = {}
        self._marker_binding = None
        self._marker_meshes: dict[str, pv.PolyData] = {}

    def _remove(self, name: str) -> None:
        remove_named_actor(self.plotter, self.actors, name)

    def forget(self) -> None:
        """New data: the markers' binding belongs to the old deformer."""
        self._marker_binding = None

    # ------------------------------------------------------------------ building
    def rebuild(self, shape_opacity: float, cage_opacity: float, show_cage: bool) -> None:
        """(Re)create the actors after a structural change (not used while dragging)."""
        ctrl, p = self.ctrl, self.plotter
        if ctrl.display is None:
            return
        if self.actors.get("shape") is None or self._shape_data is not ctrl.display:
            self._remove("shape")
            self._clippers.pop("shape", None)
            self._shape_data = d = ctrl.display
            points_only = (
                d.n_cells == d.n_points and isinstance(d, pv.PolyData) and d.GetNumberOfPolys() == 0
            )
            self.actors["shape"] = p.add_mesh(
                d, color=SHAPE_COLOR, style="points" if points_only else "surface",
                point_size=3, name="shape", scalars=None, render=False, reset_camera=False,
            )  # fmt: skip
            if ctrl.volume is not None:  # the outline box: light, never hides the slices
                self.actors["shape"].GetProperty().SetLighting(False)
        self.set_opacity("shape", shape_opacity)
        self.rebuild_proxy()
        self._remove("cage")
        if ctrl.cage is not None:
            self.actors["cage"] = p.add_mesh(
                cage_mesh(ctrl.cage), style="wireframe",
                color=CAGE_COLOR,  # opaque: translucency adds a costly compositing pass
                line_width=1, name="cage", render=False, reset_camera=False, pickable=False,
            )  # fmt: skip
            self.actors["cage"].SetVisibility(show_cage)
            self.set_opacity("cage", cage_opacity)
        self._rebuild_markers()
        self._rebuild_handles()

    def rebuild_proxy(self) -> None:
        """Add the (hidden) drag proxy's actor when the controller has a new proxy."""
        proxy = self.ctrl.proxy
        if proxy is self._proxy_data and (proxy is None or "proxy" in self.actors):
            return
        self._remove("proxy")
        self._clippers.pop("proxy", None)
        self._proxy_data = proxy
        self.show_proxy(False)
        if proxy is None:
            return
        self.actors["proxy"] = self.plotter.add_mesh(
            proxy, color=SHAPE_COLOR,
            style="surface" if proxy.n_cells != proxy.n_points else "points",
            point_size=3, name="proxy", scalars=None, render=False, reset_camera=False,
            pickable=False,
        )  # fmt: skip
        self.actors["proxy"].SetVisibility(False)
        if self._clip_plane is not None:
            self._clip("proxy", proxy, self.ctrl.proxy_rest_points)

    def _rebuild_markers(self) -> None:
        for name in ("anchors", "jacobians"):
            self._remove(name)
        self._marker_binding = None
        ctrl = self.ctrl
        self.marker_radius = 0.012 * (ctrl.cage.diagonal if ctrl.cage is not None else 1.0)
        jpts = np.array([c.point for c in ctrl.jacobians]).reshape(-1, 3)
        for name, points, colour, size in (
            ("anchors", ctrl.anchors, ANCHOR_COLOR, 10),
            ("jacobians", jpts, JACOBIAN_COLOR, 14),
        ):
            if not len(points):
                continue
            self._marker_meshes[name] = mesh = pv.PolyData(self._marker_images(points))
            self.actors[name] = self.plotter.add_mesh(
                mesh, color=colour, point_size=size, render_points_as_spheres=True, name=name,
                render=False, reset_camera=False, pickable=False,
            )  # fmt: skip

    def _marker_images(self, points: np.ndarray) -> np.ndarray:
        ctrl = self.ctrl
        if len(points) == 0 or not ctrl.ready or ctrl.last_report is None:
            return np.asarray(points, float).reshape(-1, 3)
        return ctrl.deformer.harmonic_map.map(points)

    def update_markers(self) -> None:
        """Move anchor and Jacobian markers to their images (cheap, in place)."""
        ctrl = self.ctrl
        if not ctrl.ready:
            return
        if self._marker_binding is None:
            pts = np.vstack(
                [ctrl.anchors, np.array([c.point for c in ctrl.jacobians]).reshape(-1, 3)]
            )
            self._marker_binding = (
                ctrl.deformer.bind(pts, outside="passthrough") if len(pts) else None
            )
        if self._marker_binding is None:
            return
        img = self._marker_binding.deform()
        na = len(ctrl.anchors)
        for name, part in (("anchors", img[:na]), ("jacobians", img[na:])):
            if name in self.actors:
                mesh = self._marker_meshes[name]
                np.asarray(mesh.points)[:] = part
                mesh.GetPoints().Modified()

    def _rebuild_handles(self) -> None:
        self.plotter.clear_sphere_widgets()
        self.handles = []
        if not self.ctrl.ready or not self.interactive:
            return
        for i, c in enumerate(self.ctrl.positions):
            w = self.plotter.add_sphere_widget(
                functools.partial(self._handle_moved, i), center=tuple(c.target),
                radius=self.marker_radius, color=HANDLE_COLOR, interaction_event="always",
                test_callback=False,
            )  # fmt: skip
            w.AddObserver("EndInteractionEvent", lambda *args: self.on_handle_released())
            self.handles.append(w)

    def _handle_moved(self, index: int, center, *args) -> None:
        self.on_handle_moved(index, center)

    def move_handle(self, index: int, target) -> None:
        """Put handle ``index`` at ``target`` (deformed space)."""
        if index < len(self.handles):
            self.handles[index].SetCenter(*np.asarray(target, float))

    # ------------------------------------------------------------------ appearance
    def set_opacity(self, name: str, opacity: float) -> None:
        """Opacity of ``"shape"`` (and its proxy) or ``"cage"``, 0..1."""
        for key in (name, "proxy") if name == "shape" else (name,):
            actor = self.actors.get(key)
            if actor is not None:
                actor.GetProperty().SetOpacity(float(opacity))

    def show_cage(self, on: bool) -> None:
        """Show or hide the cage wireframe."""
        if "cage" in self.actors:
            self.actors["cage"].SetVisibility(bool(on))

    def show_proxy(self, on: bool) -> bool:
        """Display the drag proxy (``on``) or the full shape; returns what is shown."""
        shape, proxy = self.actors.get("shape"), self.actors.get("proxy")
        on = bool(on) and proxy is not None and self._proxy_data is self.ctrl.proxy
        if shape is not None:
            shape.SetVisibility(not on)
        if proxy is not None:
            proxy.SetVisibility(on)
        self.showing_proxy = on
        return on

    def lod_text(self) -> str:
        """Which mesh is displayed, for the status bar (e.g. ``full mesh 1,410 cells``)."""
        d = self.ctrl.proxy if self.showing_proxy else self.ctrl.display
        if d is None:
            return ""
        points = d.n_cells == d.n_points
        n = d.n_points if points else d.n_cells
        what = "drag proxy" if self.showing_proxy else "full mesh"
        return f"{what} {n:,} {'points' if points else 'cells'}"

    def bounds(self) -> list[np.ndarray]:
        """(2, 3) boxes of the shape, cage and position targets (deformed space)."""
        ctrl = self.ctrl
        boxes = []
        if ctrl.display is not None and ctrl.display.n_points:
            boxes.append(np.asarray(ctrl.display.bounds).reshape(3, 2).T)
        if ctrl.cage is not None:
            v = np.asarray(ctrl.cage.vertices)
            boxes.append(np.vstack([v.min(0), v.max(0)]))
        if ctrl.positions:
            t = np.array([c.target for c in ctrl.positions])
            boxes.append(np.vstack([t.min(0), t.max(0)]))
        return boxes

    # ------------------------------------------------------------------ clipping
    def clip(self, plane) -> None:
        """Cut the shape and its proxy open along ``plane`` (rest space); None: uncut.

        A ``vtkClipDataSet`` on the rest-space signed distance, between the (in place
        deformed) dataset and its mapper: it re-runs on each render.

        Parameters
        ----------
        plane : ((3,) origin, (3,) normal) or None
            The side the normal points to is cut away (it faces the viewer).
        """
        self._clip_plane = plane
        ctrl = self.ctrl
        for name, data, rest in (
            ("shape", ctrl.display, ctrl.rest_points),
            ("proxy", ctrl.proxy, ctrl.proxy_rest_points),
        ):
            actor = self.actors.get(name)
            if actor is None or data is None:
                continue
            if name == "proxy" and data is not self._proxy_data:
                continue
            if plane is not None:
                self._clip(name, data, rest)
            elif self._clippers.pop(name, None) is not None:
                actor.GetMapper().SetInputData(data)

    def _clip(self, name: str, data, rest_points: np.ndarray) -> None:
        """Feed actor ``name``'s mapper the part of ``data`` behind the clip plane."""
        origin, normal = self._clip_plane
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        data.point_data["_rest_side"] = (rest_points - origin) @ n
        clip = vtk.vtkClipDataSet()
        clip.SetInputData(data)
        clip.SetInputArrayToProcess(
            0, 0, 0, vtk.vtkDataObject.FIELD_ASSOCIATION_POINTS, "_rest_side"
        )
        clip.SetValue(0.0)
        clip.InsideOutOn()  # keep the side behind the plane (the normal points away from it)
        mapper = self.actors[name].GetMapper()
        mapper.SetInputConnection(clip.GetOutputPort())
        mapper.ScalarVisibilityOff()
        self._clippers[name] = clip
