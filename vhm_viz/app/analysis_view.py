"""The analysis in the 3D view and its dock: the Jacobian section, metrics, the certificate.

:class:`AnalysisView` owns the section through the shape (a plane in rest space, sampled by
a :class:`~vhm_viz.app.analysis.SliceProbe` and coloured by det J or cond J), the
certificate's witnesses and undecided cubes, and fills the analysis dock (histogram, energy
plot, metrics).
"""

from __future__ import annotations

import traceback

import numpy as np
import pyvista as pv

from vhm_viz.app.analysis import SliceProbe
from vhm_viz.colours import histogram, measure_style
from vhm_viz.core.metrics import foldover_count

__all__ = ["AnalysisView"]


class AnalysisView:
    """Actors ``slice``, ``witnesses``, ``undecided``, and the analysis dock's contents.

    Parameters
    ----------
    plotter : pyvistaqt.QtInteractor
    controller : ExplorerController
    panel : AnalysisPanel
    shape : ShapeView
        Cut open along the section (see :meth:`ShapeView.clip`).
    volume : VolumeDisplay
        Its drag slices count in the histogram.

    Attributes
    ----------
    actors : dict of str to actor
    slice : SliceProbe or None
        The section through the shape.
    plane : ((3,) origin, (3,) normal) or None
        The section's plane in rest space.
    measure : str
        ``"determinant"`` or ``"condition_number"``.
    metrics : dict
        What the dock shows now (``foldovers``, ``E_rigid``, ``certificate``, ...).
    """

    def __init__(self, plotter, controller, panel, shape, volume):
        self.plotter = plotter
        self.ctrl = controller
        self.panel = panel
        self.shape = shape
        self.volume = volume
        self.actors: dict[str, object] = {}
        self.slice = None
        self.plane = None
        self.measure = "determinant"
        self.metrics: dict = {}
        #: Called after the section or the measure changed (the window refreshes the dock).
        self.changed = lambda: None
        #: Called with (message, details) when a control fails.
        self.report_error = lambda message, details="": None

    def _remove(self, name: str) -> None:
        actor = self.actors.pop(name, None)
        if actor is not None:
            self.plotter.remove_actor(actor, render=False)

    def add_measure_mesh(self, mesh, name: str, style: dict):
        """Add a mesh coloured by its ``"shown"`` measure in the :mod:`vhm_viz.colours` style."""
        return self.plotter.add_mesh(
            mesh, scalars="shown", cmap=style["cmap"], clim=style["clim"],
            log_scale=style["log_scale"], below_color=style["below_color"], name=name,
            render=False, reset_camera=False, pickable=False,
            scalar_bar_args={"title": style["title"]},
        )  # fmt: skip

    # ------------------------------------------------------------------ the section
    def show_section(self, on: bool = True, origin=None, normal=None) -> None:
        """Show the Jacobian section (with a plane widget to move it) or hide it.

        Parameters
        ----------
        on : bool
        origin : (3,) array_like, optional
            A point of the plane in rest space (default: the cage's centre).
        normal : (3,) array_like, optional
            Default: towards the camera (the cut opens the shape towards the viewer).
        """
        try:
            self._show_section(on, origin, normal)
        except Exception as exc:  # noqa: BLE001 - the UI must survive everything
            self.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())

    def _show_section(self, on: bool, origin, normal) -> None:
        p = self.plotter
        p.clear_plane_widgets()
        if not on:
            self.hide_section()
            p.render()
            return
        if not self.ctrl.ready:
            raise ValueError("the slice needs a solved deformation (add constraints first)")
        b = self.ctrl.cage.bounds
        origin = np.asarray(origin if origin is not None else 0.5 * (b[0] + b[1]), float)
        if normal is None:
            normal = np.subtract(p.camera.position, p.camera.focal_point)
        if p.iren is not None:
            p.add_plane_widget(
                self._plane_moved, normal=normal, origin=origin,
                bounds=np.ravel(np.column_stack([b[0], b[1]])), interaction_event="end",
                color="gray", outline_opacity=0.3,
            )  # fmt: skip
        box = self.panel.show_slice
        if not box.isChecked():
            box.blockSignals(True)
            box.setChecked(True)
            box.blockSignals(False)
        self._plane_moved(normal, origin)

    def _plane_moved(self, normal, origin) -> None:
        try:
            self.place_section(origin, normal)
            self.changed()
        except Exception as exc:  # noqa: BLE001
            self.report_error(f"slice: {exc}", traceback.format_exc())

    def set_clip(self, on: bool) -> None:
        """Cut the shape open along the section or not (the dock's switch)."""
        self.clip(bool(on))
        self.plotter.render()

    def set_measure(self, measure: str) -> None:
        """Colour the section (and the analysis) by ``determinant`` or ``condition_number``."""
        self.measure = measure
        self.changed()

    def set_resolution(self, samples: int) -> None:
        """Sample the shown section again with the dock's samples per side."""
        if self.plane is None:
            return
        try:
            self.make_section()
            self.changed()
        except Exception as exc:  # noqa: BLE001 - the UI must survive everything
            self.report_error(f"slice: {exc}", traceback.format_exc())

    def hide_section(self) -> None:
        """Remove the section and uncut the shape."""
        self.shape.clip(None)
        self._remove("slice")
        self.slice = None
        self.plane = None

    def place_section(self, origin, normal) -> None:
        """Put the section's plane (rest space) at ``origin`` with ``normal`` and sample it."""
        self.plane = (np.asarray(origin, float), np.asarray(normal, float))
        self.make_section()

    def make_section(self) -> None:
        """Sample the section on its plane, cut the shape open, colour, refresh the dock."""
        self._remove("slice")
        self.slice = None
        if self.plane is None or not self.ctrl.ready:
            return
        res = int(self.panel.resolution.value())
        self.slice = SliceProbe(self.ctrl, *self.plane, resolution=res)
        self.clip(self.panel.clip.isChecked())
        style = self.slice.colour(self.measure, self.slice.update(self.measure))
        if self.slice.n_points and self.slice.mesh.n_cells:
            self.actors["slice"] = self.add_measure_mesh(self.slice.mesh, "slice", style)
        self.update()

    def clip(self, on: bool) -> None:
        """Cut the shape open along the section (when one is shown)."""
        self.shape.clip(self.plane if on and self.slice is not None else None)

    # ------------------------------------------------------------------ the dock
    def update(self, full: bool = True) -> dict | None:
        """Recompute the section's colours, the histogram, the energy plot.

        ``full=False``: the section only (live section while dragging). Returns the
        metrics gathered so far (complete them with :meth:`finish`), None with
        ``full=False``.
        """
        ap = self.panel
        m: dict = {}
        probes = [self.slice] if self.slice is not None else []
        if not probes and not full:
            return None
        probes += self.volume.drag_probes()
        if probes and self.ctrl.ready and self.ctrl.last_report is not None:
            vals = np.concatenate([p.update(self.measure) for p in probes])
            style = measure_style(self.measure, vals)
            if self.slice is not None:
                self.slice.colour(self.measure, vals[: self.slice.n_points])
                actor = self.actors.get("slice")
                if actor is not None:
                    actor.mapper.scalar_range = style["clim"]
            log = style["log_scale"]
            what = "slice" if self.slice is not None else "volume slices"
            ap.histogram.title = f"Histogram of {self.measure} ({what}, {len(vals)} samples)"
            ap.histogram.set_histogram(histogram(vals, style["clim"], log=log), marker=1.0, log=log)
            m["foldovers"] = int(sum(p.foldovers() for p in probes))
        else:
            ap.histogram.set_histogram(None)
        if not full:
            return None
        rep = self.ctrl.last_report
        if rep is not None:
            ap.energy.set_lines([rep.energy, rep.rigidity, rep.smoothness], logy=True)
        return m

    def finish(self, m: dict) -> None:
        """Add the shape metrics (a pass over every cell) to ``m`` and show them."""
        ctrl = self.ctrl
        if ctrl.certificate is None and ("witnesses" in self.actors or "undecided" in self.actors):
            self.show_certificate()  # the solution changed: the old answer is gone
        if ctrl.ready and ctrl.last_report is not None:
            m.update(ctrl.metrics())
            if "foldovers" not in m:
                m["foldovers"] = foldover_count(ctrl.deformer.jacobians_at_anchors)
        self.panel.show_metrics(m)
        self.metrics = m

    # ------------------------------------------------------------------ the certificate
    def show_certificate(self) -> None:
        """Draw (or remove) the controller's certificate: witnesses and undecided cubes."""
        for name in ("witnesses", "undecided"):
            self._remove(name)
        witnesses, cubes = self.ctrl.certificate_geometry()
        if len(witnesses):
            self.actors["witnesses"] = self.plotter.add_mesh(
                pv.PolyData(witnesses), color="red", point_size=16,
                render_points_as_spheres=True, name="witnesses", render=False,
                reset_camera=False, pickable=False,
            )  # fmt: skip
        if cubes is not None:
            self.actors["undecided"] = self.plotter.add_mesh(
                cubes, style="wireframe", color="darkorange", name="undecided", render=False,
                reset_camera=False, pickable=False,
            )  # fmt: skip
