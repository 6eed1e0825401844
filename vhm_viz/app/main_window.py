"""The explorer's main window: a pyvistaqt ``QtInteractor`` inside a ``QMainWindow``.

All state lives in :class:`~vhm_viz.app.controller.ExplorerController`; this module maps
menus, clicks and widget callbacks onto it, runs long work in :mod:`vhm_viz.app.workers`,
and updates the scene **in place** (the shape's points are rewritten, actors are never
re-added while dragging).

Interaction modes (toolbar): *View* (camera; drag the orange handles to move position
targets), *Add position*, *Add Jacobian*, *Add anchor*, *Remove anchor* (left click on the
shape). Every click goes through :meth:`ExplorerWindow.click_at_display`, which tests call
directly.

Level of detail: for large shapes the controller keeps a decimated *proxy*
(:attr:`ExplorerController.proxy`). While a handle is dragged the proxy is deformed and
shown instead of the shape; on release (or after :data:`REFINE_DELAY_MS` without motion)
the full shape is deformed and shown again. The status bar says which one is displayed.
"""

from __future__ import annotations

import contextlib
import functools
import time
import traceback
from pathlib import Path

import numpy as np
from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QAction, QActionGroup, QKeySequence
from PySide6.QtWidgets import (
    QDockWidget,
    QFileDialog,
    QInputDialog,
    QLabel,
    QMainWindow,
    QMessageBox,
    QProgressBar,
    QPushButton,
)

from vhm_viz.app.controller import ExplorerController
from vhm_viz.app.panels import AnalysisPanel, ConstraintPanel, ViewPanel
from vhm_viz.app.workers import JobRunner
from vhm_viz.core.cage import MIN_FACE_ANGLE

__all__ = ["ExplorerWindow", "MODES"]

MODES = ("view", "position", "jacobian", "anchor+", "anchor-")
_MODE_LABELS = {
    "view": "View / drag handles",
    "position": "Add position constraint",
    "jacobian": "Add Jacobian constraint",
    "anchor+": "Add anchor",
    "anchor-": "Remove anchor",
}
SHAPE_COLOR = (0.85, 0.85, 0.80)
# the full shape replaces the drag proxy after this long without handle motion (ms)
REFINE_DELAY_MS = 400
HANDLE_COLOR = "orange"
CAGE_COLOR = (0.62, 0.74, 0.86)  # steel blue at half opacity on white
ANCHOR_COLOR = "green"
JACOBIAN_COLOR = "magenta"
GIZMO_COLOR = (0.75, 0.1, 0.75)
ISO_COLOR = (0.95, 0.85, 0.70)
# opacity of a volume's outline box (the draggable "shape" of a volume)
OUTLINE_OPACITY = 0.15
# the full-resolution volume slice replaces the drag slice this long after a slider stops
SLICE_DELAY_MS = 250
# data formats offered in the open dialog (anything pyvista.read accepts works)
_OPEN_FILTER = (
    "Data (*.obj *.ply *.stl *.vtp *.vtk *.vtu *.vti *.vts *.off *.mesh *.msh *.mhd *.nii "
    "*.nii.gz *.slc *.xyz *.pts *.las);;All files (*)"
)


def _cage_mesh(cage):
    """Triangle PolyData of a (core or public) cage."""
    import pyvista as pv

    return pv.PolyData.from_regular_faces(np.array(cage.vertices), np.array(cage.faces))


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
    """

    def __init__(
        self,
        controller: ExplorerController | None = None,
        *,
        off_screen=False,
        dialogs: bool = True,
    ):
        super().__init__()
        import pyvista as pv
        from pyvistaqt import QtInteractor

        self.setWindowTitle("vhm_viz explorer")
        self.resize(1280, 860)
        self.ctrl = controller or ExplorerController()
        self.dialogs = dialogs
        self.last_error: str | None = None
        self.errors: list[str] = []
        self.interaction_mode = "view"
        self.measure = "determinant"
        self.live_slice = False
        self.last_frame = None
        self.frame_times: list[float] = []
        self.slice = None
        self._slice_plane = None  # (origin, normal) in rest space
        self._actors: dict[str, object] = {}
        self._handles: list = []
        self._marker_binding = None
        self._open_dialogs: list = []
        self._fill_pending = False
        self._clipper = None
        self._shape_data = None
        self._proxy_clipper = None
        self._proxy_data = None
        self.showing_proxy = False
        # volumes: per axis {"drag": SliceProbe, "full": SliceProbe}, the rendered image
        self._vslices: dict[int, dict] = {}
        self._vslices_for = None  # (volume, deformer) the slices are bound to
        self.slice_colour = "value"
        self.volume_image = None  # the rendered (deformed) volume, pyvista.ImageData
        self._volume_stale = False
        self._dragging = False
        #: ("position" | "jacobian", index) of the constraint Delete removes.
        self.selected = None
        self._gizmo = None
        self._gizmo_start = None
        #: Jacobian constraint the rotation gizmo edits (default: the last one).
        self.gizmo_index = None
        self._slice_timer = QTimer(self)
        self._slice_timer.setSingleShot(True)
        self._slice_timer.setInterval(SLICE_DELAY_MS)
        self._slice_timer.timeout.connect(self._full_slices)
        # full-resolution refinement once the handle rests (restarted by every drag frame)
        self._refine_timer = QTimer(self)
        self._refine_timer.setSingleShot(True)
        self._refine_timer.setInterval(REFINE_DELAY_MS)
        self._refine_timer.timeout.connect(self._refine)
        # shape metrics after a solve: computed when the event loop is idle
        self._pending_metrics: dict | None = None
        self._metrics_timer = QTimer(self)
        self._metrics_timer.setSingleShot(True)
        self._metrics_timer.setInterval(0)
        self._metrics_timer.timeout.connect(self._deferred_metrics)

        # software OpenGL (llvmpipe) costs: no multi-sampling (doubles the frame time), one
        # headlight instead of pyvista's five-light kit (a third of the shape's render time)
        self.plotter = QtInteractor(
            self, off_screen=off_screen, auto_update=False, multi_samples=1, lighting="none"
        )
        self.plotter.add_light(pv.Light(light_type="headlight"))
        self.plotter.set_background("white")
        self.setCentralWidget(self.plotter.interactor)
        self.runner = JobRunner(self)
        self._build_docks()
        self._build_menus()
        self._build_status()
        self.runner.progressed.connect(self._on_progress)
        self.runner.started.connect(self._on_job_started)
        self.runner.finished.connect(self._on_job_finished)
        # off screen (``--screenshot``) there is no interactor: no clicks, no widgets
        self.interactive = self.plotter.iren is not None
        if self.interactive:
            self.plotter.iren.add_observer("LeftButtonPressEvent", self._on_left_press)
        # drag frames rendered by the sphere widget are timed by these observers
        self._pending_frame = None
        self._render_t0: float | None = None
        self.plotter.ren_win.AddObserver("StartEvent", self._on_render_start)
        self.plotter.ren_win.AddObserver("EndEvent", self._on_render_end)

    # ================================================================== construction
    def _build_docks(self) -> None:
        self.constraints_panel = ConstraintPanel()
        dock = QDockWidget("Constraints", self)
        dock.setWidget(self.constraints_panel)
        self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, dock)
        self.analysis_panel = AnalysisPanel()
        adock = QDockWidget("Analysis", self)
        adock.setWidget(self.analysis_panel)
        self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, adock)
        self.analysis_dock = adock
        cp, ap = self.constraints_panel, self.analysis_panel
        cp.mode_changed.connect(self.set_mode)
        cp.alpha_changed.connect(self.set_alpha)
        cp.iterations.valueChanged.connect(lambda v: setattr(self.ctrl, "max_iterations", int(v)))
        cp.target_edited.connect(self.edit_target)
        cp.jacobian_edited.connect(self.edit_jacobian)
        cp.delete_requested.connect(self.delete_constraint)
        ap.slice_toggled.connect(self.show_slice)
        ap.measure_changed.connect(self.set_measure)
        ap.live_toggled.connect(lambda on: setattr(self, "live_slice", bool(on)))
        ap.clip_toggled.connect(self._on_clip_toggled)
        self.view_panel = vp = ViewPanel()
        vdock = QDockWidget("View", self)
        vdock.setWidget(vp)
        self.addDockWidget(Qt.DockWidgetArea.LeftDockWidgetArea, vdock)
        vp.shape_opacity_changed.connect(self.set_shape_opacity)
        vp.cage_opacity_changed.connect(self.set_cage_opacity)
        vp.slices_toggled.connect(lambda on: self._update_volume_actors())
        vp.slice_moved.connect(self.move_volume_slice)
        vp.slice_released.connect(lambda a: self._full_slices())
        vp.slice_colour_changed.connect(self.set_slice_colour)
        vp.volume_toggled.connect(self.show_volume)
        vp.transfer_changed.connect(self.set_transfer)
        vp.iso_changed.connect(self.show_isosurface)
        cp.table.itemSelectionChanged.connect(self._on_table_selection)

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
        from vhm_viz.examples import BAR_KINDS

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
        self.undo_action = self._action(e, "&Undo", lambda: self.undo(), "Ctrl+Z")
        self.redo_action = self._action(e, "&Redo", lambda: self.redo(), "Ctrl+Shift+Z")
        self.redo_action.setShortcuts([QKeySequence("Ctrl+Shift+Z"), QKeySequence("Ctrl+Y")])
        self.delete_action = self._action(
            e, "&Delete selected constraint", lambda: self.delete_selected(), "Delete"
        )

        c = mb.addMenu("&Cage")
        self._action(c, "&Load cage...", lambda: self.load_cage())
        self._action(c, "&Generate cage...", lambda: self.generate_cage())
        self.show_cage_action = self._action(c, "Show cage", self._toggle_cage, checkable=True)
        self.show_cage_action.setChecked(True)

        a = mb.addMenu("&Anchors")
        self._action(a, "&Load rigidity lines...", lambda: self.load_anchors())
        self._action(a, "&Compute automatically...", lambda: self.generate_anchors())
        self._action(a, "Clear", self.clear_anchors)

        s = mb.addMenu("&Solve")
        self._action(s, "Solve to convergence", self.full_solve, "F5")
        self.certify_action = self._action(s, "&Certify injectivity", lambda: self.certify(), "F6")
        self._action(s, "Reset camera", lambda: self.frame_all(), "R")

        tb = self.addToolBar("Interaction")
        group = QActionGroup(self)
        self.mode_actions = {}
        for mode in MODES:
            act = QAction(_MODE_LABELS[mode], self)
            act.setCheckable(True)
            act.triggered.connect(functools.partial(self.set_interaction_mode, mode))
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
        sb.addPermanentWidget(self.lod_label)
        sb.addPermanentWidget(self.frame_label)
        sb.addPermanentWidget(self.progress)
        sb.addPermanentWidget(self.cancel_button)

    # ================================================================== messages / jobs
    def report_error(self, message: str, details: str = "") -> None:
        """Show an error (status bar and, unless disabled, a non-modal dialog)."""
        self.last_error = message
        self.errors.append(message)
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

    @property
    def busy(self) -> bool:
        """Whether a background job runs (edits are refused meanwhile)."""
        return self.runner.busy

    def run_job(self, name, fn, on_success, on_cancel=None) -> bool:
        """Run ``fn(progress=, cancelled=)`` in the background; ``on_success(result)`` after."""
        if self.runner.busy:
            self.status(f"busy ({self.runner.job.name}); cancel it first")
            return False

        def on_error(msg, tb):
            self.report_error(msg, tb)

        return self.runner.start(
            name, fn, self._guard_cb(on_success), on_error, self._guard_cb(on_cancel)
        )

    def _guard_cb(self, cb):
        if cb is None:
            return None

        def wrapped(*args):
            try:
                cb(*args)
            except Exception as exc:  # noqa: BLE001
                self.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())

        return wrapped

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

    def wait_idle(self, timeout_s: float = 120.0) -> None:
        """Process events until no job runs (tests and scripts)."""
        from PySide6.QtWidgets import QApplication

        t0 = time.perf_counter()
        while self.runner.busy and time.perf_counter() - t0 < timeout_s:
            QApplication.processEvents()
            time.sleep(0.005)
        QApplication.processEvents()

    # ================================================================== loading
    def _adopt(self, new: ExplorerController) -> None:
        self.ctrl.adopt(new)
        if self.ctrl.notes:
            self.status("; ".join(self.ctrl.notes), 15000)
            self.ctrl.notes = []
        if self.slice is not None:
            self.show_slice(False)
            self.analysis_panel.show_slice.setChecked(False)
        self.slice = None
        self._marker_binding = None
        self.gizmo_index = self.selected = None
        vp = self.view_panel
        vp.shape_opacity.blockSignals(True)
        vp.shape_opacity.setValue(
            int(100 * OUTLINE_OPACITY) if self.ctrl.volume is not None else 100
        )
        vp.shape_opacity.blockSignals(False)
        self._vslices_for = None
        self.volume_image = None
        self._volume_stale = self.ctrl.volume is not None
        self.rebuild_scene(reset_camera=True)
        if self.ctrl.ready and self.ctrl.last_report is not None:
            self.update_analysis()
        self._refresh_volume_image()
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

    @guarded
    def open_file(self, path: str | None = None) -> bool:
        """Open any dataset PyVista reads (dialog when ``path`` is None)."""
        if path is None:
            path, _ = QFileDialog.getOpenFileName(self, "Open data", "", _OPEN_FILTER)
            if not path:
                return False
        return self._load_job(f"open {Path(path).name}", lambda c, progress: c.load_file(path))

    @guarded
    def open_bar(self, kind: str = "bend-u", resolution: int = 39, apply: bool = True) -> bool:
        """Open a bundled bar scenario (solved, with its constraints)."""
        return self._load_job(
            f"bar {kind}", lambda c, progress: c.load_bar(kind, resolution, apply)
        )

    @guarded
    def load_scene(self, path: str | None = None) -> bool:
        """Open a scene file (dialog when ``path`` is None)."""
        if path is None:
            path, _ = QFileDialog.getOpenFileName(self, "Open scene", "", "Scenes (*.json)")
            if not path:
                return False
        current = self.ctrl
        return self._load_job(
            f"scene {Path(path).name}",
            lambda c, progress: c.load_scene(path, data_from=current, progress=progress),
        )

    @guarded
    def save_scene(self, path: str | None = None) -> None:
        """Save the scene (dialog when ``path`` is None)."""
        if path is None:
            path, _ = QFileDialog.getSaveFileName(
                self, "Save scene", "scene.json", "Scenes (*.json)"
            )
            if not path:
                return
        self.ctrl.save_scene(path)
        self.status(f"scene saved to {path}")

    @guarded
    def export(self, path: str | None = None) -> None:
        """Write the deformed data (dialog when ``path`` is None; default: input format)."""
        if self.ctrl.display is None:
            raise ValueError("nothing to export: open data first")
        if path is None:
            src = self.ctrl.source.get("path")
            default = Path(src).stem + "_deformed" + Path(src).suffix if src else "deformed.vtp"
            path, _ = QFileDialog.getSaveFileName(self, "Export deformed data", default)
            if not path:
                return
        self.ctrl.export(path)
        self.status(f"exported {path}")

    @guarded
    def screenshot(self, path: str | None = None):
        """Save (or, with ``path=False``, return) an image of the 3D view."""
        if path is None:
            path, _ = QFileDialog.getSaveFileName(
                self, "Screenshot", "screenshot.png", "PNG (*.png)"
            )
            if not path:
                return None
        self.plotter.render()
        img = self.plotter.screenshot(None if path is False else path, return_img=True)
        if path:
            self.status(f"screenshot saved to {path}")
        return img

    # ================================================================== cage / anchors
    @guarded
    def load_cage(self, path: str | None = None) -> None:
        """Load a cage file; invalid or non-enclosing cages are reported, not applied."""
        if path is None:
            path, _ = QFileDialog.getOpenFileName(
                self, "Load cage", "", "Cages (*.obj *.off *.ply *.stl *.vtp *.vtk)"
            )
            if not path:
                return
        if self.ctrl.rest is None:
            raise ValueError("open data before loading a cage")
        with self._recorded():
            self.ctrl.load_cage(path)
        repaired = self.ctrl.cage.repairs
        notes = "; ".join(self.ctrl.notes)
        self.ctrl.notes = []
        message = f"cage {Path(path).name}: {self.ctrl.cage.n_faces} faces"
        if repaired:
            message += f"; repaired {len(repaired)} slivers: {'; '.join(repaired)}"
        self.status(message + (f"; {notes}" if notes else ""), 15000 if notes else 5000)
        self.after_edit(structure=True)

    @guarded
    def generate_cage(self, max_faces: int | None = None) -> None:
        """Generate a cage in the background (progress, cancel)."""
        if self.ctrl.rest is None:
            raise ValueError("open data before generating a cage")
        if max_faces is None:
            max_faces, ok = QInputDialog.getInt(self, "Generate cage", "Max faces", 500, 12, 5000)
            if not ok:
                return
        ctrl = self.ctrl

        def job(progress, cancelled):
            return ctrl.auto_cage(max_faces, progress)

        def done(cage):
            with self._recorded():
                self.ctrl.set_cage(cage)
            thin = cage.thin_faces
            self.status(
                f"generated cage: {cage.n_faces} faces"
                + (
                    f"; {len(thin)} faces thinner than {MIN_FACE_ANGLE:g} degrees (the "
                    "smoothness weight collapses on them: the result may be poor)"
                    if len(thin)
                    else ""
                )
            )
            self.after_edit(structure=True)

        self.run_job("generate cage", job, done)

    @guarded
    def load_anchors(self, path: str | None = None, count: int | None = None) -> None:
        """Anchors from rigidity lines (``.tgf``, OFF polylines, VTK polylines)."""
        if path is None:
            path, _ = QFileDialog.getOpenFileName(
                self, "Load rigidity lines", "", "Rigidity lines (*.tgf *.off *.vtp *.vtk);;All (*)"
            )
            if not path:
                return
        if count is None:
            count, ok = QInputDialog.getInt(self, "Anchors", "Number of anchors", 50, 1, 5000)
            if not ok:
                return
        with self._recorded():
            self.ctrl.load_anchors(path, count)
        self.after_edit(structure=True)

    @guarded
    def generate_anchors(self, count: int | None = None) -> None:
        """Compute anchors automatically in the background."""
        if count is None:
            count, ok = QInputDialog.getInt(self, "Anchors", "Number of anchors", 50, 1, 5000)
            if not ok:
                return
        ctrl = self.ctrl

        def job(progress, cancelled):
            progress(0.1, "computing anchors")
            return ctrl.auto_anchors(count)

        def done(anchors):
            with self._recorded():
                self.ctrl.set_anchors(anchors)
            self.status(f"{len(anchors)} anchors")
            self.after_edit(structure=True)

        self.run_job("anchors", job, done)

    @guarded
    def clear_anchors(self) -> None:
        """Remove all anchors."""
        with self._recorded():
            self.ctrl.set_anchors(np.zeros((0, 3)))
        self.after_edit(structure=True)

    # ================================================================== settings
    @guarded
    def set_mode(self, mode: str) -> None:
        """Rigid / similar; re-solves warm-started."""
        if mode == self.ctrl.mode:
            return
        with self._recorded():
            self.ctrl.set_mode(mode)
        self.constraints_panel.set_mode(mode)
        if self.ctrl.ready:
            self.solve_and_show()

    @guarded
    def set_alpha(self, alpha: float) -> None:
        """Stiffness alpha (rebuilds the deformer in the background)."""
        with self._recorded():
            self.ctrl.set_alpha(alpha)
        self.constraints_panel.set_alpha(alpha)
        self.after_edit(structure=False)

    def set_interaction_mode(self, mode: str) -> None:
        """Choose what a left click on the shape does (see :data:`MODES`)."""
        if mode not in MODES:
            raise ValueError(f"unknown interaction mode {mode!r}")
        self.interaction_mode = mode
        self.mode_actions[mode].setChecked(True)
        self.status(_MODE_LABELS[mode])

    def set_measure(self, measure: str) -> None:
        """Colour the slice by ``determinant`` or ``condition_number``."""
        self.measure = measure
        self.update_analysis()

    # ================================================================== editing
    @guarded
    def edit_target(self, index: int, target) -> None:
        """Numeric edit of a position target (from the side panel)."""
        if index < 0 or target is None:
            self.refresh_panels()
            raise ValueError("not a number")
        if not np.isfinite(target).all():
            self.refresh_panels()
            raise ValueError("target values must be numbers")
        with self._recorded():
            self.ctrl.set_target(index, target)
        self.selected = ("position", index)
        self._move_handle(index, target)
        self.solve_and_show()

    @guarded
    def edit_jacobian(self, index: int, angles, scale: float) -> None:
        """Numeric edit of a Jacobian constraint's angles (degrees) and scale."""
        if not (np.isfinite(angles).all() and np.isfinite(scale)):
            self.refresh_panels()
            raise ValueError("angles and scale must be numbers")
        try:
            with self._recorded():
                self.ctrl.set_jacobian(index, angles, scale)
        except Exception:
            self.refresh_panels()
            raise
        self.selected = ("jacobian", index)
        self.solve_and_show()

    @guarded
    def delete_constraint(self, kind: str, index: int) -> None:
        """Delete a constraint (the last position constraint is kept)."""
        if kind == "position" and len(self.ctrl.positions) == 1:
            raise ValueError(
                "the last position constraint cannot be deleted (it fixes the translation)"
            )
        with self._recorded():
            self.ctrl.remove_constraint(kind, index)
        self.selected = None
        if kind == "jacobian":
            self.gizmo_index = None
        self.after_edit(structure=False)

    @contextlib.contextmanager
    def _recorded(self):
        """Record the state before an edit for undo, once the edit succeeded."""
        state = self.ctrl.snapshot()
        yield
        self.ctrl.checkpoint(state)

    def undo(self) -> bool:
        """Ctrl+Z: back to the state before the last edit, solved and shown."""
        return self._history(self.ctrl.undo, "undo")

    def redo(self) -> bool:
        """Ctrl+Shift+Z: re-apply the last undone edit."""
        return self._history(self.ctrl.redo, "redo")

    @guarded
    def _history(self, step, what: str) -> bool:
        if self.busy:
            self.status("busy: wait or cancel the running job")
            return False
        if not step():
            self.status(f"nothing to {what}")
            return False
        self._after_history(f"{what} done")
        return True

    def _after_history(self, what: str) -> None:
        self.selected = None
        if self.gizmo_index is not None and self.gizmo_index >= len(self.ctrl.jacobians):
            self.gizmo_index = None
        self.status(what)
        self.after_edit(structure=True)

    def _on_table_selection(self) -> None:
        rows = self.constraints_panel.selected_rows()
        if rows:
            self.selected = rows[0]
            if rows[0][0] == "jacobian" and rows[0][1] != self.gizmo_index:
                self.gizmo_index = rows[0][1]
                self._rebuild_gizmo()
                self.plotter.render()

    @guarded
    def delete_selected(self) -> bool:
        """Delete: remove the constraint selected in the table (or last added / dragged)."""
        rows = self.constraints_panel.selected_rows() or ([self.selected] if self.selected else [])
        if not rows:
            self.status("no constraint selected")
            return False
        for kind, index in sorted(rows, key=lambda r: (r[0], -r[1])):
            self.delete_constraint(kind, index)
        return True

    def after_edit(self, structure: bool) -> None:
        """Rebuild what the edit made stale (in the background), then solve and show."""
        self.refresh_panels()
        self.rebuild_scene(reset_camera=False, solve=False)
        self.plotter.render()  # the edit shows now, before any solve
        if not self.ctrl.can_solve:
            self.update_analysis()
            return
        if self.ctrl.ready:
            self.solve_and_show()
            return
        ctrl = self.ctrl

        def job(progress, cancelled):
            ctrl.prepare(progress, cancelled)
            return None

        def done(_):
            self.slice = None
            self._marker_binding = None
            self.solve_and_show()
            if self.ctrl.notes:  # e.g. cage shells without constraints stay put
                self.status("; ".join(self.ctrl.notes), 15000)
                self.ctrl.notes = []

        self.run_job("binding", job, done)

    # ================================================================== picking
    def _on_left_press(self, obj, event) -> None:
        if self.interaction_mode == "view":
            return
        x, y = self.plotter.iren.interactor.GetEventPosition()
        self.click_at_display(x, y)

    @guarded
    def click_at_display(self, x: int, y: int) -> bool:
        """Pick the shape at display pixel ``(x, y)`` and act per the interaction mode.

        This is the click path (the left-button observer calls it). Returns whether the
        shape was hit.
        """
        import vtk

        actor = self._actors.get("shape")
        if actor is None:
            return False
        picker = vtk.vtkCellPicker()
        picker.SetTolerance(0.0005)
        picker.PickFromListOn()
        picker.AddPickList(actor)
        if not picker.Pick(x, y, 0, self.plotter.renderer):
            self.status("no shape under the cursor")
            return False
        self.handle_pick(picker.GetCellId(), np.array(picker.GetPickPosition()))
        return True

    def display_coordinates(self, world_point) -> tuple[int, int]:
        """Display pixel of a world point (for scripted clicks)."""
        ren = self.plotter.renderer
        ren.SetWorldPoint(*np.asarray(world_point, float), 1.0)
        ren.WorldToDisplay()
        x, y, _ = ren.GetDisplayPoint()
        return int(round(x)), int(round(y))

    @guarded
    def handle_pick(self, cell_id: int, world_point) -> None:
        """Act on a picked point of the deformed shape (see :data:`MODES`)."""
        if self.busy:
            self.status("busy: wait or cancel the running job")
            return
        mode = self.interaction_mode
        rest = self.ctrl.rest_point_from_cell(cell_id, world_point)
        with self._recorded():
            if not self._apply_pick(mode, rest, world_point):
                return
        self.after_edit(structure=mode.startswith("anchor"))

    def _apply_pick(self, mode: str, rest, world_point) -> bool:
        """Add or remove what ``mode`` says at a picked point; whether anything changed."""
        if mode == "position":
            i = self.ctrl.add_position_constraint(rest, target=np.asarray(world_point, float))
            self.selected = ("position", i)
            self.status(f"position constraint {i} added")
        elif mode == "jacobian":
            i = self.ctrl.add_jacobian_constraint(rest)
            self.selected = ("jacobian", i)
            self.gizmo_index = i
            self.status(f"Jacobian constraint {i} added")
        elif mode == "anchor+":
            i = self.ctrl.add_anchor(rest)
            self.status(f"anchor {i} added")
        elif mode == "anchor-":
            i = self.ctrl.nearest_anchor(rest)
            if i is None:
                self.status("no anchors to remove")
                return False
            self.ctrl.remove_anchor(i)
            self.status(f"anchor {i} removed")
        else:
            return False
        return True

    # ================================================================== drag
    def on_handle_moved(self, index: int, center, render: bool = True) -> None:
        """One live frame: move target ``index`` to ``center``, solve, deform, render.

        ``render=False`` is the sphere widget's path (:meth:`_handle_cb`): the widget renders
        right after its ``InteractionEvent`` callback, so rendering here too would draw
        every frame twice; that render's time completes :attr:`last_frame` instead.
        """
        self._pending_frame = None
        if self.busy or not self.ctrl.ready:
            return
        if not self._dragging:  # one undo step per drag
            self.ctrl.checkpoint()
            self._dragging = True
            self.selected = ("position", index)
        self._frame(lambda: self.ctrl.drag(index, np.asarray(center, float)), render)

    def _frame(self, step, render: bool) -> None:
        """One live frame: ``step()`` edits, solves and deforms (returns its FrameTiming)."""
        try:
            t = step()
            t0 = time.perf_counter()
            if t.mesh == "proxy" and self._proxy_data is not self.ctrl.proxy:
                self._rebuild_proxy()  # a proxy built since the last scene rebuild
            self._show_proxy(t.mesh == "proxy")
            if self.showing_proxy:
                self._refine_timer.start()
            self._update_markers()
            self._move_gizmo()
            if self.live_slice and self.slice is not None:
                self.update_analysis(full=False)
            if self._vslices:
                self._update_volume_slices(drag=True)
            t.analysis = time.perf_counter() - t0
            if not render:
                self.last_frame = self._pending_frame = t  # completed by _on_render_end
                return
            t0 = time.perf_counter()
            self.plotter.ren_win.Render()
            t.render = time.perf_counter() - t0
        except Exception as exc:  # noqa: BLE001
            self.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())
            return
        self._show_frame(t)

    def _on_render_start(self, *args) -> None:
        self._render_t0 = time.perf_counter()

    def _on_render_end(self, *args) -> None:
        """Complete a drag frame rendered by the sphere widget (see :meth:`on_handle_moved`)."""
        t, self._pending_frame = self._pending_frame, None
        if t is not None and self._render_t0 is not None:
            t.render = time.perf_counter() - self._render_t0
            self._show_frame(t)

    def on_handle_released(self, *args) -> None:
        """End of a drag: solve to convergence, refresh the analysis and the table."""
        self._dragging = False
        self._refine_timer.stop()
        if self.busy or not self.ctrl.ready:
            return
        self.solve_and_show(rebuild=False)

    def _refine(self) -> None:
        """The handle rests: show the full shape at the current (drag) solution."""
        if self.busy or not self.ctrl.ready or not self.showing_proxy:
            return
        try:
            self.ctrl.deform()
            self._show_proxy(False)
            self.plotter.render()
        except Exception as exc:  # noqa: BLE001
            self.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())

    def _show_proxy(self, on: bool) -> None:
        """Display the drag proxy (``on``) or the full shape; say which in the status bar."""
        shape, proxy = self._actors.get("shape"), self._actors.get("proxy")
        on = bool(on) and proxy is not None and self._proxy_data is self.ctrl.proxy
        if shape is not None:
            shape.SetVisibility(not on)
        if proxy is not None:
            proxy.SetVisibility(on)
        self.showing_proxy = on
        self.lod_label.setText(self._lod_text(on))  # QLabel ignores an unchanged text

    def _lod_text(self, proxy: bool) -> str:
        d = self.ctrl.proxy if proxy else self.ctrl.display
        if d is None:
            return ""
        points = d.n_cells == d.n_points
        n = d.n_points if points else d.n_cells
        what = "drag proxy" if proxy else "full mesh"
        return f"{what} {n:,} {'points' if points else 'cells'}"

    def _show_frame(self, t) -> None:
        self.last_frame = t
        self.frame_times.append(t.total)
        fps = 1.0 / t.total if t.total > 0 else float("inf")
        self.frame_label.setText(
            f"frame {1e3 * t.total:.1f} ms ({fps:.0f} fps): solve {1e3 * t.solve:.1f}, "
            f"deform {1e3 * t.deform:.1f}, render {1e3 * t.render:.1f} ms, {t.iterations} it"
        )

    @guarded
    def solve_and_show(self, rebuild: bool = True) -> None:
        """Warm-started solve to convergence, deform in place, update the scene and panels.

        ``rebuild=False`` keeps the actors and handles (only moves the markers).
        """
        t0 = time.perf_counter()
        rep = self.ctrl.settle()
        t1 = time.perf_counter()
        self._refine_timer.stop()
        self._pending_frame = None
        self.ctrl.deform()
        t2 = time.perf_counter()
        if rebuild:
            self.rebuild_scene(reset_camera=False, solve=False)
        else:
            self._update_markers()
            self.refresh_panels()
        self._show_proxy(False)
        self._move_gizmo()
        if self.ctrl.volume is not None:
            self._update_volume_slices(drag=False)
            self._volume_stale = True
            self._refresh_volume_image()
        self.update_analysis(defer_metrics=True)
        t3 = time.perf_counter()
        self.plotter.render()
        from vhm_viz.app.controller import FrameTiming

        self._show_frame(
            FrameTiming(
                solve=t1 - t0,
                deform=t2 - t1,
                analysis=t3 - t2,
                render=time.perf_counter() - t3,
                iterations=rep.iterations,
            )
        )
        if not rep.converged:
            self.status(f"solver stopped after {rep.iterations} iterations (not converged)")

    @guarded
    def certify(self, max_cubes: int = 200_000) -> None:
        """Certify the shown deformation over the shape in the background, then draw it.

        Witnesses (``det J <= 0``) are drawn as red spheres, undecided cubes as orange
        wireframes, both in deformed space; the analysis dock shows the answer.
        """
        ctrl = self.ctrl

        def job(progress, cancelled):
            return ctrl.certify(max_cubes, progress, cancelled)

        def done(cert):
            self._show_certificate()
            self.update_analysis()
            self.plotter.render()
            self.status(cert.summary(), 15000)

        self.run_job("certify", job, done)

    def _show_certificate(self) -> None:
        """Draw (or remove) the current certificate's witnesses and undecided cubes."""
        import pyvista as pv

        for name in ("witnesses", "undecided"):
            self._remove(name)
        witnesses, cubes = self.ctrl.certificate_geometry()
        if len(witnesses):
            self._actors["witnesses"] = self.plotter.add_mesh(
                pv.PolyData(witnesses), color="red", point_size=16,
                render_points_as_spheres=True, name="witnesses", render=False,
                reset_camera=False, pickable=False,
            )  # fmt: skip
        if cubes is not None:
            self._actors["undecided"] = self.plotter.add_mesh(
                cubes, style="wireframe", color="darkorange", name="undecided", render=False,
                reset_camera=False, pickable=False,
            )  # fmt: skip

    @guarded
    def full_solve(self) -> None:
        """Solve to convergence (builds what is stale first)."""
        if not self.ctrl.ready:
            self.after_edit(structure=True)
            return
        self.solve_and_show()

    # ================================================================== scene
    def _remove(self, name: str) -> None:
        actor = self._actors.pop(name, None)
        if actor is not None:
            self.plotter.remove_actor(actor, render=False)

    def rebuild_scene(self, reset_camera: bool = False, solve: bool = False) -> None:
        """(Re)create the actors after a structural change (not used while dragging)."""
        import pyvista as pv

        ctrl = self.ctrl
        p = self.plotter
        if ctrl.display is None:
            return
        shape = self._actors.get("shape")
        if shape is None or self._shape_data is not ctrl.display:
            self._remove("shape")
            self._clipper = None
            self._shape_data = ctrl.display
            style = (
                "points"
                if ctrl.display.n_cells == ctrl.display.n_points
                and isinstance(ctrl.display, pv.PolyData)
                and ctrl.display.GetNumberOfPolys() == 0
                else "surface"
            )
            self._actors["shape"] = p.add_mesh(
                ctrl.display,
                color=SHAPE_COLOR,
                style=style,
                point_size=3,
                name="shape",
                scalars=None,
                render=False,
                reset_camera=False,
            )
            if ctrl.volume is not None:  # the outline box: light, never hides the slices
                self._actors["shape"].GetProperty().SetLighting(False)
        self._apply_opacity("shape", self.view_panel.shape_opacity.value() / 100.0)
        self._rebuild_proxy()
        self._remove("cage")
        if ctrl.cage is not None:
            self._actors["cage"] = p.add_mesh(
                _cage_mesh(ctrl.cage),
                style="wireframe",
                color=CAGE_COLOR,  # opaque: translucency adds a costly compositing pass
                line_width=1,
                name="cage",
                render=False,
                reset_camera=False,
                pickable=False,
            )
            self._actors["cage"].SetVisibility(self.show_cage_action.isChecked())
            self._apply_opacity("cage", self.view_panel.cage_opacity.value() / 100.0)
        self._rebuild_markers()
        self._rebuild_handles()
        self._rebuild_gizmo()
        self._rebuild_volume()
        self.refresh_panels()
        if reset_camera:
            self.frame_all(render=False)
            self.status(self._summary())

    # ================================================================== view
    def _apply_opacity(self, name: str, opacity: float) -> None:
        for key in (name, "proxy") if name == "shape" else (name,):
            actor = self._actors.get(key)
            if actor is not None:
                actor.GetProperty().SetOpacity(float(opacity))

    @guarded
    def set_shape_opacity(self, opacity: float) -> None:
        """Opacity of the shape (and its drag proxy), 0..1."""
        self._apply_opacity("shape", opacity)
        self.plotter.render()

    @guarded
    def set_cage_opacity(self, opacity: float) -> None:
        """Opacity of the cage wireframe, 0..1."""
        self._apply_opacity("cage", opacity)
        self.plotter.render()

    def scene_bounds(self) -> np.ndarray:
        """(2, 3) box around the shown shape, cage, handles and volume (deformed space)."""
        ctrl = self.ctrl
        boxes = []
        for data in (ctrl.display, self.volume_image):
            if data is not None and data.n_points:
                b = np.asarray(data.bounds).reshape(3, 2).T
                boxes.append(b)
        if ctrl.cage is not None:
            v = np.asarray(ctrl.cage.vertices)
            boxes.append(np.vstack([v.min(0), v.max(0)]))
        if ctrl.positions:
            t = np.array([c.target for c in ctrl.positions])
            boxes.append(np.vstack([t.min(0), t.max(0)]))
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

    def _rebuild_proxy(self) -> None:
        """Add the (hidden) drag proxy's actor when the controller has a new proxy."""
        proxy = self.ctrl.proxy
        if proxy is self._proxy_data and (proxy is None or "proxy" in self._actors):
            return
        self._remove("proxy")
        self._proxy_clipper = None
        self._proxy_data = proxy
        self._show_proxy(False)
        if proxy is None:
            return
        self._actors["proxy"] = self.plotter.add_mesh(
            proxy,
            color=SHAPE_COLOR,
            style="surface" if proxy.n_cells != proxy.n_points else "points",
            point_size=3,
            name="proxy",
            scalars=None,
            render=False,
            reset_camera=False,
            pickable=False,
        )
        self._actors["proxy"].SetVisibility(False)
        if self._clipper is not None:
            self._clip_proxy(True)

    def _summary(self) -> str:
        c = self.ctrl
        src = c.source.get("path") or f"bar {c.source.get('bar')}"
        n = c.display.n_points if c.display is not None else 0
        cage = f"{c.cage.n_faces}-face cage" if c.cage is not None else "no cage"
        return f"{Path(str(src)).name}: {n} points, {cage}, {len(c.anchors)} anchors"

    def _rebuild_markers(self) -> None:
        import pyvista as pv

        for name in ("anchors", "jacobians"):
            self._remove(name)
        self._marker_binding = None
        ctrl = self.ctrl
        diag = ctrl.cage.diagonal if ctrl.cage is not None else 1.0
        self._marker_radius = 0.012 * diag
        anchors = self._marker_images(ctrl.anchors, "anchors")
        if len(anchors):
            self._anchor_mesh = pv.PolyData(anchors)
            self._actors["anchors"] = self.plotter.add_mesh(
                self._anchor_mesh,
                color=ANCHOR_COLOR,
                point_size=10,
                render_points_as_spheres=True,
                name="anchors",
                render=False,
                reset_camera=False,
                pickable=False,
            )
        jpts = np.array([c.point for c in ctrl.jacobians]).reshape(-1, 3)
        if len(jpts):
            self._jac_mesh = pv.PolyData(self._marker_images(jpts, "jacobians"))
            self._actors["jacobians"] = self.plotter.add_mesh(
                self._jac_mesh,
                color=JACOBIAN_COLOR,
                point_size=14,
                render_points_as_spheres=True,
                name="jacobians",
                render=False,
                reset_camera=False,
                pickable=False,
            )

    def _marker_images(self, points: np.ndarray, what: str) -> np.ndarray:
        ctrl = self.ctrl
        if len(points) == 0 or not ctrl.ready or ctrl.last_report is None:
            return np.asarray(points, float).reshape(-1, 3)
        return ctrl.deformer.harmonic_map.map(points)

    def _update_markers(self) -> None:
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
        if "anchors" in self._actors:
            np.asarray(self._anchor_mesh.points)[:] = img[:na]
            self._anchor_mesh.GetPoints().Modified()
        if "jacobians" in self._actors:
            np.asarray(self._jac_mesh.points)[:] = img[na:]
            self._jac_mesh.GetPoints().Modified()

    def _rebuild_handles(self) -> None:
        p = self.plotter
        p.clear_sphere_widgets()
        self._handles = []
        if not self.ctrl.ready or not self.interactive:
            return
        radius = getattr(self, "_marker_radius", 0.02)
        for i, c in enumerate(self.ctrl.positions):
            w = p.add_sphere_widget(
                functools.partial(self._handle_cb, i),
                center=tuple(c.target),
                radius=radius,
                color=HANDLE_COLOR,
                interaction_event="always",
                test_callback=False,
            )
            w.AddObserver("EndInteractionEvent", self.on_handle_released)
            self._handles.append(w)

    def _handle_cb(self, index: int, center, *args) -> None:
        self.on_handle_moved(index, center, render=False)  # the widget renders next

    def _move_handle(self, index: int, target) -> None:
        if index < len(self._handles):
            self._handles[index].SetCenter(*np.asarray(target, float))

    def _toggle_cage(self, on: bool) -> None:
        if "cage" in self._actors:
            self._actors["cage"].SetVisibility(bool(on))
            self.plotter.render()

    def refresh_panels(self) -> None:
        """Refill the constraint table (deferred: may be called from the table's signals)."""
        if not self._fill_pending:
            self._fill_pending = True
            QTimer.singleShot(0, self._fill_panels)

    def _fill_panels(self) -> None:
        self._fill_pending = False
        self.constraints_panel.fill(self.ctrl.positions, self.ctrl.jacobians)
        self.constraints_panel.set_mode(self.ctrl.mode)
        self.constraints_panel.set_alpha(self.ctrl.alpha)

    # ================================================================== analysis
    @guarded
    def show_slice(self, on: bool = True, origin=None, normal=None) -> None:
        """Show the Jacobian slice (plane widget in rest space) or hide it."""
        p = self.plotter
        if not on:
            self._clip_shape(False)
            p.clear_plane_widgets()
            self._remove("slice")
            self.slice = None
            self._slice_plane = None
            p.render()
            return
        if not self.ctrl.ready:
            raise ValueError("the slice needs a solved deformation (add constraints first)")
        b = self.ctrl.cage.bounds
        origin = np.asarray(origin if origin is not None else 0.5 * (b[0] + b[1]), float)
        if normal is None:  # face the camera: the cut opens the shape towards the viewer
            cam = p.camera
            normal = np.subtract(cam.position, cam.focal_point)
        normal = np.asarray(normal, float)
        self._slice_plane = (origin, normal)
        p.clear_plane_widgets()
        if self.interactive:
            p.add_plane_widget(
                self._plane_moved,
                normal=normal,
                origin=origin,
                bounds=np.ravel(np.column_stack([b[0], b[1]])),
                interaction_event="end",
                color="gray",
                outline_opacity=0.3,
            )
        if not self.analysis_panel.show_slice.isChecked():
            self.analysis_panel.show_slice.blockSignals(True)
            self.analysis_panel.show_slice.setChecked(True)
            self.analysis_panel.show_slice.blockSignals(False)
        self._make_slice()

    def _clip_shape(self, on: bool) -> None:
        """Cut the shape open along the slice plane (rest space) so the slice is visible.

        A ``vtkClipDataSet`` on the rest-space signed distance, between the (in place
        deformed) display dataset and the shape's mapper: it re-runs on each render.
        """
        actor = self._actors.get("shape")
        if actor is None:
            return
        mapper = actor.GetMapper()
        display = self.ctrl.display
        if not on or self._slice_plane is None:
            if self._clipper is not None:
                mapper.SetInputData(display)
                self._clipper = None
            self._clip_proxy(False)
            return
        self._clipper = self._clip_mapper(mapper, display, self.ctrl.rest_points)
        self._clip_proxy(True)

    def _clip_mapper(self, mapper, data, rest_points: np.ndarray):
        """Feed ``mapper`` the part of ``data`` behind the slice plane (rest space)."""
        import vtk

        origin, normal = self._slice_plane
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        data.point_data["_rest_side"] = (rest_points - origin) @ n
        clip = vtk.vtkClipDataSet()
        clip.SetInputData(data)
        clip.SetInputArrayToProcess(
            0, 0, 0, vtk.vtkDataObject.FIELD_ASSOCIATION_POINTS, "_rest_side"
        )
        clip.SetValue(0.0)
        clip.InsideOutOn()  # keep the side behind the plane (the normal points away from it)
        mapper.SetInputConnection(clip.GetOutputPort())
        mapper.ScalarVisibilityOff()
        return clip

    def _clip_proxy(self, on: bool) -> None:
        """Cut the drag proxy like the shape (see :meth:`_clip_shape`)."""
        actor, proxy = self._actors.get("proxy"), self.ctrl.proxy
        if actor is None or proxy is None or proxy is not self._proxy_data:
            return
        if on and self._slice_plane is not None:
            rest = self.ctrl.proxy_rest_points
            self._proxy_clipper = self._clip_mapper(actor.GetMapper(), proxy, rest)
        elif self._proxy_clipper is not None:
            actor.GetMapper().SetInputData(proxy)
            self._proxy_clipper = None

    def _on_clip_toggled(self, on: bool) -> None:
        self._clip_shape(bool(on) and self.slice is not None)
        self.plotter.render()

    def _plane_moved(self, normal, origin) -> None:
        self._slice_plane = (np.asarray(origin, float), np.asarray(normal, float))
        try:
            self._make_slice()
        except Exception as exc:  # noqa: BLE001
            self.report_error(f"slice: {exc}", traceback.format_exc())

    def _make_slice(self) -> None:
        from vhm_viz.app.analysis import SliceProbe

        self._remove("slice")
        self.slice = None
        if self._slice_plane is None or not self.ctrl.ready:
            return
        res = int(self.analysis_panel.resolution.value())
        self.slice = SliceProbe(self.ctrl, *self._slice_plane, resolution=res)
        self._clip_shape(self.analysis_panel.clip.isChecked())
        style = self.slice.colour(self.measure, self.slice.update(self.measure))
        if self.slice.n_points and self.slice.mesh.n_cells:
            self._actors["slice"] = self._add_measure_mesh(self.slice.mesh, "slice", style)
        self.update_analysis()

    def _add_measure_mesh(self, mesh, name: str, style: dict):
        """Add a mesh coloured by its ``"shown"`` measure in the :mod:`vhm_viz.colours` style."""
        return self.plotter.add_mesh(
            mesh,
            scalars="shown",
            cmap=style["cmap"],
            clim=style["clim"],
            log_scale=style["log_scale"],
            below_color=style["below_color"],
            name=name,
            render=False,
            reset_camera=False,
            pickable=False,
            scalar_bar_args={"title": style["title"]},
        )

    def update_analysis(self, full: bool = True, defer_metrics: bool = False) -> None:
        """Recompute the slice colours, histogram, energy plot and metrics.

        ``full=False``: the slice only (live slice while dragging). ``defer_metrics``: the
        shape metrics (E_rigid, E_volume: a pass over every triangle, ~0.4 s at 346k
        triangles) are computed once the event loop is idle, after the frame is shown.
        """
        from vhm_viz.colours import histogram, measure_style

        ap = self.analysis_panel
        m: dict = {}
        probes = [self.slice] if self.slice is not None else []
        if not probes and not full:
            return
        probes += [e["drag"] for e in self._vslices.values() if e["drag"].binding is not None]
        if probes and self.ctrl.ready and self.ctrl.last_report is not None:
            vals = np.concatenate([p.update(self.measure) for p in probes])
            style = measure_style(self.measure, vals)
            if self.slice is not None:
                self.slice.colour(self.measure, vals[: self.slice.n_points])
                actor = self._actors.get("slice")
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
            return
        rep = self.ctrl.last_report
        if rep is not None:
            ap.energy.set_lines([rep.energy, rep.rigidity, rep.smoothness], logy=True)
        if defer_metrics:
            self._pending_metrics = m
            self._metrics_timer.start()
            return
        self._metrics_timer.stop()
        self._finish_metrics(m)

    def _deferred_metrics(self) -> None:
        # not while a drag runs (the proxy is shown): the next release schedules them again
        if self._pending_metrics is None or self.showing_proxy or self.ctrl.full_stale:
            return
        m, self._pending_metrics = self._pending_metrics, None
        try:
            self._finish_metrics(m)
        except Exception as exc:  # noqa: BLE001
            self.report_error(f"metrics: {exc}", traceback.format_exc())

    def _finish_metrics(self, m: dict) -> None:
        if self.ctrl.certificate is None and (
            "witnesses" in self._actors or "undecided" in self._actors
        ):
            self._show_certificate()  # the solution changed: the old answer is gone
        ap = self.analysis_panel
        if self.ctrl.ready and self.ctrl.last_report is not None:
            m.update(self.ctrl.metrics())
            if "foldovers" not in m:
                from vhm_viz.core.metrics import foldover_count

                m["foldovers"] = foldover_count(self.ctrl.deformer.jacobians_at_anchors)
        ap.show_metrics(m)
        self.analysis_metrics = m

    # ================================================================== volumes
    def _rebuild_volume(self) -> None:
        """A volume's slices: (re)made when the volume or its deformer changed."""
        ctrl, vp = self.ctrl, self.view_panel
        vol = ctrl.volume
        key = (id(vol), id(ctrl.deformer) if ctrl.ready and ctrl.last_report is not None else None)
        if vol is None:
            for name in [n for n in self._actors if n.startswith("vslice")]:
                self._remove(name)
            for name in ("volume", "iso"):
                self._remove(name)
            self._vslices, self._vslices_for = {}, None
            vp.set_volume(None, None, None)
            return
        if key == self._vslices_for:
            return
        if self._vslices_for is None or self._vslices_for[0] != key[0]:
            vp.set_volume(vol.dimensions, vol.range, vol.index)
            lo, hi = vol.window()
            vp.set_transfer(0.5 * (lo + hi), hi - lo, 0.3)
        self._vslices_for = key
        for axis in range(3):
            self._make_volume_slice(axis, ("drag", "full"))
        self._update_volume_slices(drag=False)
        self._update_volume_actors()

    def _make_volume_slice(self, axis: int, parts) -> None:
        from vhm_viz.app.volume import DRAG_SAMPLES, FULL_SAMPLES

        ctrl = self.ctrl
        bound = ctrl if ctrl.ready and ctrl.last_report is not None else None
        entry = self._vslices.setdefault(axis, {})
        for part in parts:
            samples = DRAG_SAMPLES if part == "drag" else FULL_SAMPLES
            probe = ctrl.volume.slice_probe(bound, axis, samples)
            entry[part] = probe
            self._add_volume_slice_actor(axis, part)

    def _add_volume_slice_actor(self, axis: int, part: str, style: dict | None = None) -> None:
        name = f"vslice{axis}{part}"
        self._remove(name)
        mesh = self._vslices[axis][part].mesh
        if style is not None:
            self._actors[name] = self._add_measure_mesh(mesh, name, style)
            self._actors[name].SetPickable(True)
        else:
            level, width, _ = self.view_panel.transfer
            self._actors[name] = self.plotter.add_mesh(
                mesh, scalars="value", cmap="gray", show_scalar_bar=False, name=name,
                clim=(level - width / 2, level + width / 2), render=False, reset_camera=False,
            )  # fmt: skip
        self._actors[name].GetProperty().SetLighting(False)  # the values, unshaded

    def _update_volume_slices(self, drag: bool) -> None:
        """Deform the volume's slices: the drag resolution always, the full one at rest."""
        if not self._vslices or not self.ctrl.ready:
            return
        measure = None if self.slice_colour == "value" else self.slice_colour
        values = []
        for e in self._vslices.values():
            values.append(e["drag"].update(measure))
            if not drag:
                e["full"].update(None)
        if measure is not None:
            from vhm_viz.colours import measure_style

            style = measure_style(measure, np.concatenate(values))
            for axis, e in self._vslices.items():
                e["drag"].colour(measure, values[axis])
                actor = self._actors.get(f"vslice{axis}drag")
                if actor is not None:
                    actor.mapper.scalar_range = style["clim"]
        self._update_volume_actors(visibility_only=True)

    @guarded
    def move_volume_slice(self, axis: int, index: int) -> None:
        """Move the volume's slice along ``axis`` to voxel ``index``.

        The drag-resolution slice follows at once, the full one when the slider rests.
        """
        vol = self.ctrl.volume
        if vol is None or not self._vslices:
            return
        vol.index[axis] = int(index)
        self._make_volume_slice(axis, ("drag",))
        self._moving_slice = axis
        self._restyle_volume_slices()
        self._update_volume_slices(drag=True)
        self._slice_timer.start()
        self.plotter.render()

    def _full_slices(self) -> None:
        """The slider rests: the full-resolution slice of the moved axis."""
        axis = getattr(self, "_moving_slice", None)
        self._moving_slice = None
        if axis is None or not self._vslices:
            return
        try:
            self._make_volume_slice(axis, ("full",))
            self._update_volume_slices(drag=False)
            self.update_analysis()
            self.plotter.render()
        except Exception as exc:  # noqa: BLE001
            self.report_error(f"slice: {exc}", traceback.format_exc())

    @guarded
    def set_slice_colour(self, colour: str) -> None:
        """Colour the volume's slices by ``value``, ``determinant`` or ``condition_number``."""
        self.slice_colour = colour
        if colour != "value" and colour != self.measure:
            self.analysis_panel.measure.setCurrentText(colour)  # one measure in the dock
        self._restyle_volume_slices()
        self._update_volume_slices(drag=False)
        self.plotter.render()

    def _restyle_volume_slices(self) -> None:
        from vhm_viz.colours import measure_style

        style = None
        if self.slice_colour != "value":
            style = measure_style(self.slice_colour, [1.0])
        for axis, e in self._vslices.items():
            if style is not None and "shown" not in e["drag"].mesh.point_data:
                e["drag"].mesh.point_data["shown"] = np.ones(e["drag"].n_points)
            self._add_volume_slice_actor(axis, "drag", style)

    def _update_volume_actors(self, visibility_only: bool = False) -> None:
        """Show the slices of the current resolution; the volume rendering and isosurface."""
        vp = self.view_panel
        on = vp.slices.isChecked()
        use_drag = (
            self.slice_colour != "value"
            or self._dragging
            or bool(getattr(self, "_moving_slice", None) is not None)
        )
        for axis in self._vslices:
            for part, shown in (("drag", use_drag), ("full", not use_drag)):
                actor = self._actors.get(f"vslice{axis}{part}")
                if actor is not None:
                    actor.SetVisibility(on and shown)
        for name in ("volume", "iso"):
            actor = self._actors.get(name)
            if actor is not None:  # they lag behind a drag: hidden until the release
                actor.SetVisibility(not self._dragging)
        if visibility_only:
            return
        self._remove("volume")
        img = self.volume_image
        if vp.volume.isChecked() and img is not None:
            lo, hi = self.ctrl.volume.range
            self._actors["volume"] = self.plotter.add_volume(
                img, scalars="values", cmap="gray", clim=(lo, hi), mapper="smart",
                show_scalar_bar=False, name="volume", render=False, reset_camera=False,
            )  # fmt: skip
            self.set_transfer(*vp.transfer, render=False)
        self.show_isosurface(vp.iso.isChecked(), vp.value_of(vp.iso_value.value()), render=False)

    @guarded
    def show_volume(self, on: bool = True) -> None:
        """Volume rendering of the deformed volume (resampled in the background)."""
        if self.view_panel.volume.isChecked() != bool(on):
            self.view_panel.volume.setChecked(bool(on))  # comes back here
            return
        self._refresh_volume_image()
        self._update_volume_actors()
        self.plotter.render()

    @guarded
    def set_transfer(self, level: float, width: float, opacity: float, render=True) -> None:
        """Window/level ramp of the volume rendering (and grey window of the slices).

        Opacity 0 below ``level - width/2``, rising to ``opacity`` at ``level + width/2``.
        """
        a, b = level - 0.5 * width, level + 0.5 * width
        vol = self._actors.get("volume")
        if vol is not None and self.ctrl.volume is not None:
            lo, hi = self.ctrl.volume.range
            prop = vol.GetProperty()
            otf = prop.GetScalarOpacity()
            otf.RemoveAllPoints()
            otf.AddPoint(min(lo, a) - 1e-6, 0.0)
            otf.AddPoint(a, 0.0)
            otf.AddPoint(b, float(opacity))
            otf.AddPoint(max(hi, b) + 1e-6, float(opacity))
            ctf = prop.GetRGBTransferFunction()
            ctf.RemoveAllPoints()
            ctf.AddRGBPoint(a, 0.0, 0.0, 0.0)
            ctf.AddRGBPoint(b, 1.0, 1.0, 1.0)
        for axis in self._vslices:
            for part in ("drag", "full"):
                actor = self._actors.get(f"vslice{axis}{part}")
                if actor is not None and actor.mapper.scalar_range is not None:
                    if part == "full" or self.slice_colour == "value":
                        actor.mapper.scalar_range = (a, b)
        if render:
            self.plotter.render()

    @guarded
    def show_isosurface(self, on: bool, value: float, render: bool = True) -> None:
        """The isosurface ``value`` of the deformed volume (None: hidden)."""
        self._remove("iso")
        if on and self.volume_image is None:
            self._refresh_volume_image()
        if on and self.volume_image is not None:
            iso = self.volume_image.contour([float(value)], scalars="values")
            if iso.n_points:
                self._actors["iso"] = self.plotter.add_mesh(
                    iso, color=ISO_COLOR, name="iso", render=False, reset_camera=False,
                    pickable=False, scalars=None,
                )  # fmt: skip
        if render:
            self.plotter.render()

    def _refresh_volume_image(self) -> None:
        """Resample the deformed volume (background job) if rendering or iso needs it."""
        ctrl, vp = self.ctrl, self.view_panel
        vol = ctrl.volume
        if vol is None or not (vp.volume.isChecked() or vp.iso.isChecked()):
            return
        if not (ctrl.ready and ctrl.last_report is not None):
            self.volume_image, self._volume_stale = vol.rest_image(), False
            return
        if not self._volume_stale and self.volume_image is not None:
            return
        if self.busy:
            QTimer.singleShot(200, self._refresh_volume_image)
            return
        hm = ctrl.deformer.harmonic_map

        def job(progress, cancelled):
            return vol.deformed_image(hm, progress=progress, abort=cancelled)

        def done(img):
            self.volume_image, self._volume_stale = img, False
            self._update_volume_actors()
            self.plotter.render()

        self._volume_stale = False
        self.run_job("volume rendering", job, done)

    @guarded
    def colour_by(self, measure: str) -> None:
        """Show ``measure`` (det J or cond J): a volume's slices, else a section of the shape."""
        self.analysis_panel.measure.setCurrentText(measure)
        if self.ctrl.volume is not None:
            self.view_panel.slice_colour.setCurrentText(measure)
        elif self.ctrl.ready:
            self.show_slice(True)
        self.plotter.render()

    # ================================================================== rotation gizmo
    def _rebuild_gizmo(self) -> None:
        """A box around the selected Jacobian constraint: rotate it to set the target."""
        import vtk

        if self._gizmo is not None:
            self._gizmo.Off()
            self._gizmo = None
        ctrl = self.ctrl
        if not ctrl.jacobians or not ctrl.ready or not self.interactive:
            self.gizmo_index = None
            return
        if self.gizmo_index is None or self.gizmo_index >= len(ctrl.jacobians):
            self.gizmo_index = len(ctrl.jacobians) - 1
        c = ctrl.jacobians[self.gizmo_index]
        centre = ctrl.image_of(c.point)
        r = 3.0 * getattr(self, "_marker_radius", 0.02)
        w = vtk.vtkBoxWidget()
        w.SetInteractor(self.plotter.iren.interactor)
        w.SetPlaceFactor(1.0)
        w.PlaceWidget(*np.ravel(np.column_stack([centre - r, centre + r])))
        w.TranslationEnabledOff()
        w.ScalingEnabledOff()
        w.RotationEnabledOn()
        w.HandlesOff()
        w.GetOutlineProperty().SetColor(*GIZMO_COLOR)
        w.GetOutlineProperty().SetLineWidth(2)
        w.GetSelectedOutlineProperty().SetLineWidth(3)
        w.AddObserver("InteractionEvent", self._on_gizmo_moved)
        w.AddObserver("EndInteractionEvent", self._on_gizmo_released)
        self._gizmo, self._gizmo_centre = w, centre
        self._gizmo_active = False
        self._move_gizmo()
        w.On()

    def _move_gizmo(self) -> None:
        """Orient the gizmo by its constraint's target rotation, at the point's image."""
        import vtk

        w, i = self._gizmo, self.gizmo_index
        if w is None or i is None or getattr(self, "_gizmo_active", False):
            return
        if i >= len(self.ctrl.jacobians):
            return
        c = self.ctrl.jacobians[i]
        centre = self.ctrl.image_of(c.point)
        m = np.eye(4)
        rot = c.matrix / c.scale
        m[:3, :3] = rot
        m[:3, 3] = centre - rot @ self._gizmo_centre
        t = vtk.vtkTransform()
        t.SetMatrix(m.ravel())
        w.SetTransform(t)

    def gizmo_rotation(self) -> np.ndarray:
        """(3, 3) rotation the gizmo box shows now (the linear part of its transform)."""
        import vtk

        t = vtk.vtkTransform()
        self._gizmo.GetTransform(t)
        m = t.GetMatrix()
        return np.array([[m.GetElement(r, k) for k in range(3)] for r in range(3)])

    def _on_gizmo_moved(self, *args) -> None:
        if self.busy or not self.ctrl.ready or self.gizmo_index is None:
            return
        if not self._gizmo_active:  # one undo step per rotation
            self.ctrl.checkpoint()
            self._gizmo_active = True
            self.selected = ("jacobian", self.gizmo_index)
        rot = self.gizmo_rotation()
        self._dragging = True
        self._frame(lambda: self.ctrl.rotate(self.gizmo_index, rot), render=False)

    def _on_gizmo_released(self, *args) -> None:
        self._gizmo_active = False
        if self._dragging:
            self.on_handle_released()
            self.refresh_panels()

    # ================================================================== shutdown
    def closeEvent(self, event) -> None:  # noqa: N802, D102 - Qt override
        if self.runner.busy:
            self.runner.cancel()
        self.runner.wait(5000)
        self.plotter.close()
        super().closeEvent(event)
