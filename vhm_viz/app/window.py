"""The explorer's main window: a pyvistaqt ``QtInteractor`` inside a ``QMainWindow``.

All state lives in :class:`~vhm_viz.app.controller.ExplorerController`; this module holds
the shell (menus, docks, status bar, background jobs, file and edit actions) and composes
the views that own the 3D view's actors: :class:`~vhm_viz.app.shape_view.ShapeView` (shape,
drag proxy, cage, markers, handles), :class:`~vhm_viz.app.volume_view.VolumeDisplay`
(a volume's slices, rendering, isosurface), :class:`~vhm_viz.app.analysis_view.AnalysisView`
(the Jacobian section, the certificate, the analysis dock) and
:class:`~vhm_viz.app.gizmo.RotationGizmo`. The drag frames live in
:mod:`vhm_viz.app.dragging`.

Interaction modes (toolbar, :data:`vhm_viz.app.picking.MODES`): *View* (camera; drag the
orange handles to move position targets), *Add position*, *Add Jacobian*, *Add anchor*,
*Remove anchor* (left click on the shape). Every click goes through
:meth:`~vhm_viz.app.editing.Editing.click_at_display`, which tests call directly.

Long work runs in :mod:`vhm_viz.app.workers`; :meth:`ExplorerWindow.waiting_for_jobs`
waits for the jobs a block of code started.
"""

from __future__ import annotations

import functools
import traceback
from pathlib import Path

import numpy as np
import pyvista as pv
from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QAction, QActionGroup, QKeySequence
from PySide6.QtWidgets import (
    QDockWidget,
    QFileDialog,
    QLabel,
    QMainWindow,
    QMessageBox,
    QProgressBar,
    QPushButton,
)
from pyvistaqt import QtInteractor

from vhm_viz.app.analysis_view import AnalysisView
from vhm_viz.app.autosave import AUTOSAVE_INTERVAL_S, Autosave, recoverable
from vhm_viz.app.controller import ExplorerController
from vhm_viz.app.dragging import DragFrames
from vhm_viz.app.editing import Editing
from vhm_viz.app.gizmo import RotationGizmo
from vhm_viz.app.panels import AnalysisPanel, ConstraintPanel, ViewPanel
from vhm_viz.app.picking import MODES, ShapePicker
from vhm_viz.app.shape_view import OUTLINE_OPACITY, ShapeView
from vhm_viz.app.volume_view import VolumeDisplay
from vhm_viz.app.workers import JobRunner
from vhm_viz.examples import BAR_KINDS

__all__ = ["ExplorerWindow", "MODES", "guarded"]

# data formats offered in the open dialog (anything vhm_viz.read_dataset reads works; scans
# open in ITK's LPS frame, as on the command line and in ParaView)
_OPEN_FILTER = (
    "Data (*.obj *.ply *.stl *.vtp *.vtk *.vtu *.vti *.vts *.off *.mesh *.msh *.mhd *.mha "
    "*.nii *.nii.gz *.nrrd *.nhdr *.slc *.xyz *.pts *.las);;All files (*)"
)


def guarded(fn):
    """Slot decorator: any exception becomes an error message, never a crash."""

    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        try:
            return fn(self, *args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - the UI must survive everything
            self.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())
            return None

    return wrapper


class ExplorerWindow(QMainWindow):
    """Main window of ``vhm-viz explore``.

    Parameters
    ----------
    controller : ExplorerController, optional
    off_screen : bool
        Render off screen (tests without a window manager still use a real display).
    dialogs : bool
        Show error dialogs (tests set False and read :attr:`last_error`).

    Attributes
    ----------
    shape_view : ShapeView
    volume_display : VolumeDisplay
    analysis_view : AnalysisView
    gizmo : RotationGizmo
    drag : DragFrames
        Live frames while a handle or the gizmo is dragged.
    """

    def __init__(
        self,
        controller: ExplorerController | None = None,
        *,
        off_screen=False,
        dialogs: bool = True,
    ):
        super().__init__()
        self.setWindowTitle("vhm_viz explorer")
        self.resize(1280, 860)
        self.ctrl = controller or ExplorerController()
        self.dialogs = dialogs
        self.last_error: str | None = None
        self.errors: list[str] = []
        self.last_warning: str | None = None
        #: ("position" | "jacobian", index) of the constraint Delete removes.
        self.selected = None
        self._open_dialogs: list = []
        #: The session's :class:`~vhm_viz.app.autosave.Autosave` once :meth:`start_autosave` ran.
        self.autosave: Autosave | None = None
        self._autosave_timer: QTimer | None = None
        # software OpenGL (llvmpipe) costs: no multi-sampling (doubles the frame time), one
        # headlight instead of pyvista's five-light kit (a third of the shape's render time)
        self.plotter = QtInteractor(
            self, off_screen=off_screen, auto_update=False, multi_samples=1, lighting="none"
        )
        self.plotter.add_light(pv.Light(light_type="headlight"))
        self.plotter.set_background("white")
        self.setCentralWidget(self.plotter.interactor)
        self.runner = JobRunner(self)
        #: The latest resampling of the deformed volume (a drag cancels it while it runs).
        self.volume_job = None
        self._build_docks()
        self._build_menus()
        self._build_status()
        self.drag = DragFrames(self)
        self.shape_view = ShapeView(
            self.plotter, self.ctrl, self.drag.handle_moved, self.drag.released
        )
        self.analysis_view = AnalysisView(
            self.plotter, self.ctrl, self.analysis_panel, self.shape_view, None
        )
        self.volume_display = VolumeDisplay(
            self.plotter, self.ctrl, self.view_panel, self.analysis_view.add_measure_mesh
        )
        self.volume_display.request_image = self.refresh_volume_image
        self.volume_display.report_error = self.report_error
        self.volume_display.report_status = lambda message: self.status(message, 15000)
        self.analysis_view.volume = self.volume_display
        self.gizmo = RotationGizmo(
            self.plotter, self.ctrl, self.drag.rotated, self.drag.gizmo_released
        )
        self.picker = ShapePicker(self.plotter)
        self.editing = Editing(self)
        self._connect_panels()
        self.drag.observe(self.plotter.ren_win)

        self.runner.progressed.connect(self._on_progress)
        self.runner.started.connect(self._on_job_started)
        self.runner.finished.connect(self._on_job_finished)
        # off screen (``--screenshot``) there is no interactor: no clicks, no widgets
        self.interactive = self.plotter.iren is not None
        if self.interactive:
            self.plotter.iren.add_observer("LeftButtonPressEvent", self._on_left_press)

    # ================================================================== construction
    def _build_docks(self) -> None:
        self.constraints_panel = ConstraintPanel()
        self.analysis_panel = AnalysisPanel()
        self.view_panel = ViewPanel()
        for title, panel, area in (
            ("Constraints", self.constraints_panel, Qt.DockWidgetArea.RightDockWidgetArea),
            ("Analysis", self.analysis_panel, Qt.DockWidgetArea.RightDockWidgetArea),
            ("View", self.view_panel, Qt.DockWidgetArea.LeftDockWidgetArea),
        ):
            dock = QDockWidget(title, self)
            dock.setWidget(panel)
            self.addDockWidget(area, dock)
            if title == "Analysis":
                self.analysis_dock = dock

    def _connect_panels(self) -> None:
        cp, ap, vp = self.constraints_panel, self.analysis_panel, self.view_panel
        ed = self.editing
        cp.mode_changed.connect(ed.set_mode)
        cp.alpha_changed.connect(ed.set_alpha)
        cp.iterations.valueChanged.connect(lambda v: setattr(self.ctrl, "max_iterations", int(v)))
        cp.target_edited.connect(ed.edit_target)
        cp.jacobian_edited.connect(ed.edit_jacobian)
        cp.delete_requested.connect(ed.delete_constraint)
        cp.table.itemSelectionChanged.connect(ed.on_table_selection)
        av = self.analysis_view
        av.changed, av.report_error = self.editing.update_analysis, self.report_error
        ap.slice_toggled.connect(av.show_section)
        ap.measure_changed.connect(av.set_measure)
        ap.resolution.valueChanged.connect(av.set_resolution)
        ap.live_toggled.connect(lambda on: setattr(self.drag, "live_section", bool(on)))
        ap.clip_toggled.connect(av.set_clip)
        vp.shape_opacity_changed.connect(self.set_shape_opacity)
        vp.cage_opacity_changed.connect(self.set_cage_opacity)
        vd = self.volume_display
        vd.slice_rested = self.editing.update_analysis
        vp.slices_toggled.connect(lambda on: self._render(vd.update_actors))
        vp.slice_moved.connect(vd.move_slice)
        vp.slice_released.connect(lambda a: vd.finish_slice_move())
        vp.slice_colour_changed.connect(self._set_slice_colour)
        vp.volume_toggled.connect(vd.show_volume)
        vp.transfer_changed.connect(vd.set_transfer)
        vp.iso_changed.connect(vd.show_isosurface)

    def _action(self, menu, text, slot, shortcut=None, checkable=False):
        act = QAction(text, self)
        if shortcut:
            act.setShortcut(QKeySequence(shortcut))
        act.setCheckable(checkable)
        act.triggered.connect(slot)
        menu.addAction(act)
        return act

    def _build_menus(self) -> None:
        mb = self.menuBar()
        f = mb.addMenu("&File")
        self._action(f, "&Open data...", lambda: self.open_file(), "Ctrl+O")
        bars = f.addMenu("Bar scenario")
        for kind in BAR_KINDS:
            self._action(bars, kind, functools.partial(self.open_bar, kind))
        self._action(
            bars, "bar, bottom held (free play)", lambda: self.open_bar("bend-u", apply=False)
        )
        f.addSeparator()
        self._action(f, "Open &scene...", lambda: self.load_scene(), "Ctrl+L")
        self._action(f, "Save scene...", lambda: self.save_scene(), "Ctrl+S")
        self._action(f, "&Export deformed data...", lambda: self.export(), "Ctrl+E")
        self._action(f, "Screens&hot...", lambda: self.screenshot(), "Ctrl+P")
        f.addSeparator()
        self._action(f, "&Quit", self.close, "Ctrl+Q")

        e = mb.addMenu("&Edit")
        self.undo_action = self._action(e, "&Undo", lambda: self.editing.undo(), "Ctrl+Z")
        self.redo_action = self._action(e, "&Redo", lambda: self.editing.redo(), "Ctrl+Shift+Z")
        self.redo_action.setShortcuts([QKeySequence("Ctrl+Shift+Z"), QKeySequence("Ctrl+Y")])
        self.delete_action = self._action(
            e, "&Delete selected constraint", lambda: self.editing.delete_selected(), "Delete"
        )

        c = mb.addMenu("&Cage")
        self._action(c, "&Load cage...", lambda: self.editing.load_cage())
        self._action(c, "&Generate cage...", lambda: self.editing.generate_cage())
        self.show_cage_action = self._action(c, "Show cage", self.show_cage, checkable=True)
        self.show_cage_action.setChecked(True)

        a = mb.addMenu("&Anchors")
        self._action(a, "&Load rigidity lines...", lambda: self.editing.load_anchors())
        self._action(a, "&Compute automatically...", lambda: self.editing.generate_anchors())
        self._action(a, "Clear", lambda: self.editing.clear_anchors())

        s = mb.addMenu("&Solve")
        self._action(s, "Solve to convergence", lambda: self.editing.full_solve(), "F5")
        self.certify_action = self._action(
            s, "&Certify injectivity", lambda: self.editing.certify(), "F6"
        )
        self._action(s, "Reset camera", lambda: self.frame_all(), "R")

        tb = self.addToolBar("Interaction")
        group = QActionGroup(self)
        self.mode_actions = {}
        for mode, label in MODES.items():
            act = QAction(label, self)
            act.setCheckable(True)
            act.triggered.connect(
                lambda checked=False, m=mode: self.editing.set_interaction_mode(m)
            )
            group.addAction(act)
            tb.addAction(act)
            self.mode_actions[mode] = act
        self.mode_actions["view"].setChecked(True)

    def _build_status(self) -> None:
        sb = self.statusBar()
        self.frame_label = QLabel("")
        self.lod_label = QLabel("")  # which mesh is displayed: full shape or drag proxy
        self.progress = QProgressBar()
        self.progress.setMaximumWidth(220)
        self.progress.setRange(0, 1000)
        self.progress.hide()
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.hide()
        self.cancel_button.clicked.connect(self.cancel_job)
        for widget in (self.lod_label, self.frame_label, self.progress, self.cancel_button):
            sb.addPermanentWidget(widget)

    @property
    def actors(self) -> dict:
        """Every actor of the 3D view by name (shape, volume and analysis views' together)."""
        views = (self.shape_view, self.volume_display, self.analysis_view)
        return {name: a for view in views for name, a in view.actors.items()}

    # ================================================================== messages / jobs
    def report_error(self, message: str, details: str = "") -> None:
        """Show an error (status bar and, unless disabled, a non-modal dialog)."""
        self.last_error = message
        self.errors.append(message)
        self._show_message(message, details)

    def report_warning(self, message: str) -> None:
        """Show what a finished action made that was not asked for (as an error is shown)."""
        self.last_warning = message
        self._show_message(message)

    def _show_message(self, message: str, details: str = "") -> None:
        self.statusBar().showMessage(message, 15000)
        if self.dialogs:
            box = QMessageBox(QMessageBox.Icon.Warning, "vhm_viz", message, parent=self)
            if details:
                box.setDetailedText(details)
            box.setModal(False)
            box.finished.connect(lambda *_: self._open_dialogs.remove(box))
            self._open_dialogs.append(box)
            box.show()

    def status(self, message: str, ms: int = 5000) -> None:
        """Show a transient status-bar message."""
        self.statusBar().showMessage(message, ms)

    def _render(self, update) -> None:
        """Run ``update()`` and render."""
        update()
        self.plotter.render()

    @property
    def busy(self) -> bool:
        """Whether a background job runs (edits are refused meanwhile)."""
        return self.runner.busy

    def run_job(self, name, fn, on_success, on_cancel=None, queue: bool = False):
        """Run ``fn(progress=, cancelled=)`` in the background; ``on_success(result)`` after.

        Returns the :class:`~vhm_viz.app.workers.Job`, or None (with a message) while
        another job runs, unless ``queue``: then it starts once the runner is free.
        """
        if self.runner.busy and not queue:
            self.status(f"busy ({self.runner.job.name}); cancel it first")
            return None
        return self.runner.start(
            name, fn, self._guard_cb(on_success), self.report_error, self._guard_cb(on_cancel),
            queue=queue,
        )  # fmt: skip

    def _guard_cb(self, cb):
        if cb is None:
            return None

        def wrapped(*args):
            try:
                cb(*args)
            except Exception as exc:  # noqa: BLE001
                self.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())

        return wrapped

    def waiting_for_jobs(self, timeout_s: float = 120.0):
        """Context manager: run the block, then wait for the jobs it started.

        See :meth:`~vhm_viz.app.workers.JobRunner.waiting`; yields the list of jobs.
        """
        return self.runner.waiting(timeout_s)

    def cancel_job(self) -> None:
        """Cancel the running background job (its result is discarded)."""
        if self.runner.busy:
            name = self.runner.job.name
            self.runner.cancel()
            self.status(f"{name}: cancelled")

    def _on_job_started(self, name: str) -> None:
        self.progress.setValue(0)
        self.progress.setFormat(name)
        self.progress.show()
        self.cancel_button.show()

    def _on_progress(self, fraction: float, message: str) -> None:
        self.progress.setValue(int(1000 * min(max(fraction, 0.0), 1.0)))
        self.progress.setFormat(message)

    def _on_job_finished(self, name: str) -> None:
        self.progress.hide()
        self.cancel_button.hide()

    # ================================================================== loading
    def _adopt(self, new: ExplorerController) -> None:
        self.ctrl.adopt(new)
        if self.ctrl.notes:
            self.status("; ".join(self.ctrl.notes), 15000)
            self.ctrl.notes = []
        if self.analysis_view.slice is not None:
            self.analysis_view.show_section(False)
            self.analysis_panel.show_slice.setChecked(False)
        self.analysis_view.hide_section()
        self.shape_view.forget()
        self.gizmo.index = self.selected = None
        vp = self.view_panel
        vp.shape_opacity.blockSignals(True)
        volume = self.ctrl.volume is not None
        vp.shape_opacity.setValue(int(100 * OUTLINE_OPACITY) if volume else 100)
        vp.shape_opacity.blockSignals(False)
        self.volume_display.reset()
        self.rebuild_scene(reset_camera=True)
        if self.ctrl.ready and self.ctrl.last_report is not None:
            self.editing.update_analysis()
        self.refresh_volume_image()
        self.plotter.render()

    def _load_job(self, name: str, load):
        mode, alpha = self.ctrl.mode, self.ctrl.alpha

        def job(progress, cancelled):
            new = ExplorerController()
            new.copy_settings(self.ctrl)
            new.scene.mode, new.scene.alpha = mode, alpha
            progress(0.0, f"{name}: reading")
            load(new, progress)
            if new.can_solve:
                new.prepare(progress, cancelled)
                if new.last_report is None:  # a loaded scene comes solved
                    new.settle(init="identity")
                new.deform()
            return new

        return self.run_job(name, job, self._adopt)

    def ask_path(self, path, title: str, filter: str, save_as: str | None = None):
        """``path``, or (None) one the user picks in a file dialog; None if cancelled."""
        if path is not None:
            return path
        if save_as is not None:
            path, _ = QFileDialog.getSaveFileName(self, title, save_as, filter)
        else:
            path, _ = QFileDialog.getOpenFileName(self, title, "", filter)
        return path or None

    @guarded
    def open_file(self, path: str | None = None):
        """Open any dataset PyVista reads (dialog when ``path`` is None); returns the job."""
        path = self.ask_path(path, "Open data", _OPEN_FILTER)
        if path is None:
            return None
        return self._load_job(f"open {Path(path).name}", lambda c, progress: c.load_file(path))

    @guarded
    def open_bar(self, kind: str = "bend-u", resolution: int = 39, apply: bool = True):
        """Open a bundled bar scenario (solved, with its constraints); returns the job."""
        return self._load_job(
            f"bar {kind}", lambda c, progress: c.load_bar(kind, resolution, apply)
        )

    @guarded
    def load_scene(self, path: str | None = None):
        """Open a scene file and solve it (dialog when ``path`` is None); returns the job."""
        path = self.ask_path(path, "Open scene", "Scenes (*.json)")
        if path is None:
            return None
        current = self.ctrl
        return self._load_job(
            f"scene {Path(path).name}",
            lambda c, progress: c.load_scene(path, data_from=current, progress=progress),
        )

    @guarded
    def save_scene(self, path: str | None = None) -> None:
        """Save the scene (dialog when ``path`` is None)."""
        path = self.ask_path(path, "Save scene", "Scenes (*.json)", save_as="scene.json")
        if path is not None:
            self.ctrl.save_scene(path)
            self.status(f"scene saved to {path}")

    @guarded
    def export(self, path: str | None = None) -> None:
        """Write the deformed data (dialog when ``path`` is None; default: input format)."""
        if self.ctrl.display is None:
            raise ValueError("nothing to export: open data first")
        src = self.ctrl.source.get("path")
        default = Path(src).stem + "_deformed" + Path(src).suffix if src else "deformed.vtp"
        path = self.ask_path(path, "Export deformed data", "", save_as=default)
        if path is not None:
            warnings = self.ctrl.export(path)
            if warnings:  # written as it is, and said where the user looks
                self.report_warning(f"exported {path}, but " + "; ".join(warnings))
            else:
                self.status(f"exported {path}")

    @guarded
    def screenshot(self, path: str | None = None):
        """Save (or, with ``path=False``, return) an image of the 3D view."""
        path = self.ask_path(path, "Screenshot", "PNG (*.png)", save_as="screenshot.png")
        if path is None:
            return None
        self.plotter.render()
        img = self.plotter.screenshot(None if path is False else path, return_img=True)
        if path:
            self.status(f"screenshot saved to {path}")
        return img

    # ================================================================== the 3D view
    def rebuild_scene(self, reset_camera: bool = False) -> None:
        """(Re)create the actors after a structural change (not used while dragging)."""
        if self.ctrl.display is None:
            return
        vp = self.view_panel
        self.shape_view.rebuild(
            vp.shape_opacity.value() / 100.0,
            vp.cage_opacity.value() / 100.0,
            self.show_cage_action.isChecked(),
        )
        self.lod_label.setText(self.shape_view.lod_text())
        self.gizmo.rebuild(3.0 * self.shape_view.marker_radius)
        self.volume_display.rebuild()
        self.editing.refresh_panels()
        if reset_camera:
            self.frame_all(render=False)
            self.status(self._summary())

    def _summary(self) -> str:
        c = self.ctrl
        src = c.source.get("path") or f"bar {c.source.get('bar')}"
        n = c.display.n_points if c.display is not None else 0
        cage = f"{c.cage.n_faces}-face cage" if c.cage is not None else "no cage"
        return f"{Path(str(src)).name}: {n} points, {cage}, {len(c.anchors)} anchors"

    def _on_left_press(self, obj, event) -> None:
        if self.editing.interaction_mode == "view":
            return
        x, y = self.plotter.iren.interactor.GetEventPosition()
        self.editing.click_at_display(x, y)

    @guarded
    def set_shape_opacity(self, opacity: float) -> None:
        """Opacity of the shape (and its drag proxy), 0..1."""
        self._render(lambda: self.shape_view.set_opacity("shape", opacity))

    @guarded
    def set_cage_opacity(self, opacity: float) -> None:
        """Opacity of the cage wireframe, 0..1."""
        self._render(lambda: self.shape_view.set_opacity("cage", opacity))

    def show_cage(self, on: bool) -> None:
        """Show or hide the cage (menu Cage > Show cage)."""
        self._render(lambda: self.shape_view.show_cage(on))

    def scene_bounds(self) -> np.ndarray:
        """(2, 3) box around the shown shape, cage, handles and volume (deformed space)."""
        boxes = self.shape_view.bounds()
        image = self.volume_display.image
        if image is not None and image.n_points:
            boxes.append(np.asarray(image.bounds).reshape(3, 2).T)
        if not boxes:
            return np.array([[-1.0, -1, -1], [1, 1, 1]])
        b = np.stack(boxes)
        return np.vstack([b[:, 0].min(0), b[:, 1].max(0)])

    def frame_all(self, render: bool = True) -> None:
        """Reset the camera so that shape, cage and volume are all in view (key R)."""
        lo, hi = self.scene_bounds()
        cam = self.plotter.camera
        centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
        direction = np.subtract(cam.position, cam.focal_point)
        direction = direction / (np.linalg.norm(direction) or 1.0)
        # the bounding sphere fits the narrower of the two view angles, with a margin
        w, h = self.plotter.window_size
        half = np.radians(cam.view_angle) / 2
        if w < h:
            half = np.arctan(np.tan(half) * w / h)
        distance = 1.08 * radius / np.sin(half)
        cam.focal_point = tuple(centre)
        cam.position = tuple(centre + distance * direction)
        self.plotter.renderer.ResetCameraClippingRange()
        if render:
            self.plotter.render()

    # ================================================================== analysis
    @guarded
    def colour_by(self, measure: str) -> None:
        """Show ``measure`` (det J or cond J): a volume's slices, else a section of the shape."""
        self.analysis_panel.measure.setCurrentText(measure)
        if self.ctrl.volume is not None:
            self.view_panel.slice_colour.setCurrentText(measure)
        elif self.ctrl.ready:
            self.analysis_view.show_section(True)
        self.plotter.render()

    # ================================================================== volumes
    def _set_slice_colour(self, colour: str) -> None:
        if colour != "value" and colour != self.analysis_view.measure:
            self.analysis_panel.measure.setCurrentText(colour)  # one measure in the dock
        self.volume_display.set_colour(colour)

    def refresh_volume_image(self):
        """Resample the deformed volume if rendering or the isosurface needs it.

        A background job, queued behind a running one; returns it (None: nothing to do).
        """
        job = self.volume_display.image_job()
        if job is None:
            return None
        self.volume_job = self.run_job(
            "volume rendering", job, self.volume_display.set_image, queue=True
        )
        return self.volume_job

    # ================================================================== autosave
    def start_autosave(self, folder=None, interval_s: float = AUTOSAVE_INTERVAL_S) -> None:
        """Keep the edited scene on disk (:mod:`vhm_viz.app.autosave`) every ``interval_s``.

        The explorer's start (``vhm-viz explore``) calls this; a window that closes normally
        removes the file.
        """
        self.autosave = Autosave(folder)
        self._autosave_timer = QTimer(self)
        self._autosave_timer.timeout.connect(self.save_now)
        self._autosave_timer.start(max(50, int(interval_s * 1000)))

    def save_now(self) -> bool:
        """Write the autosave if the scene changed; skipped while a job edits the state."""
        if self.autosave is None or self.runner.busy:
            return False
        try:
            return self.autosave.update(self.ctrl)
        except OSError as exc:
            self.statusBar().showMessage(f"autosave failed: {exc}", 15000)
            return False

    def offer_recovery(self, folder=None) -> list[Path]:
        """Scenes left by explorers that crashed or were killed (newest first).

        With dialogs, asks whether to open the newest (:meth:`recover`), keep it for later
        or discard it.
        """
        if folder is None and self.autosave is not None:
            folder = self.autosave.folder
        found = recoverable(folder)
        if not found or not self.dialogs:
            return found
        box = QMessageBox(
            QMessageBox.Icon.Question,
            "vhm_viz",
            f"An explorer session ended without closing; its scene was kept in {found[0]}.\n"
            "Open it now?",
            QMessageBox.StandardButton.Open
            | QMessageBox.StandardButton.Discard
            | QMessageBox.StandardButton.Cancel,
            parent=self,
        )
        answer = box.exec()
        if answer == QMessageBox.StandardButton.Open:
            self.recover(found[0])
        elif answer == QMessageBox.StandardButton.Discard:
            found[0].unlink(missing_ok=True)
        return found

    def recover(self, path):
        """Open an autosaved scene (:meth:`load_scene`); it becomes this session's autosave.

        Returns the load job.
        """
        path = Path(path)
        if self.autosave is not None:
            self.autosave.folder.mkdir(parents=True, exist_ok=True)
            path.replace(self.autosave.path)
            path = self.autosave.path
        return self.load_scene(str(path))

    # ================================================================== shutdown
    def closeEvent(self, event) -> None:  # noqa: N802, D102 - Qt override
        if self.runner.busy:
            self.runner.cancel()
        self.runner.wait(5000)
        if self._autosave_timer is not None:
            self._autosave_timer.stop()
            self.autosave.discard()
        self.plotter.close()
        super().closeEvent(event)
