"""Live frames of the explorer: a handle or the rotation gizmo dragged, solved, shown.

Each frame edits a target (:meth:`ExplorerController.drag` or
:meth:`ExplorerController.rotate`: warm-started solve, deform), moves the markers and the
gizmo, deforms the volume's drag slices and, with the live section, the section. The
sphere widget renders right after its callback, so the frame's render time is measured by
observers on the render window. On release the shape is solved to convergence
(:meth:`~vhm_viz.app.editing.Editing.solve_and_show`). A drag proxy shown while dragging is
replaced by the full shape after :data:`REFINE_DELAY_MS` without motion.
"""

from __future__ import annotations

import time
import traceback

import numpy as np
from PySide6.QtCore import QTimer

__all__ = ["DragFrames", "REFINE_DELAY_MS"]

# the full shape replaces the drag proxy after this long without handle motion (ms)
REFINE_DELAY_MS = 400


class DragFrames:
    """The window's drag frames (handles and gizmo), their timing and the refinement.

    Parameters
    ----------
    window : ExplorerWindow

    Attributes
    ----------
    last_frame : FrameTiming or None
    frame_times : list of float
        Seconds of every frame shown.
    dragging : bool
        A drag (handle or gizmo) is under way.
    live_section : bool
        Recompute the section every frame (analysis dock's "live").
    """

    def __init__(self, window):
        self.window = window
        self.last_frame = None
        self.frame_times: list[float] = []
        self.dragging = False
        self.live_section = False
        self._pending = None
        self._render_t0: float | None = None
        # full-resolution refinement once the handle rests (restarted by every drag frame)
        self._refine_timer = QTimer(window)
        self._refine_timer.setSingleShot(True)
        self._refine_timer.setInterval(REFINE_DELAY_MS)
        self._refine_timer.timeout.connect(self._refine)

    def observe(self, render_window) -> None:
        """Time the renders of ``render_window`` (the widget's render completes a frame)."""
        render_window.AddObserver("StartEvent", self._on_render_start)
        render_window.AddObserver("EndEvent", self._on_render_end)

    def handle_moved(self, index: int, center) -> None:
        """A sphere widget's callback: the widget renders right after it."""
        self.move_handle(index, center, render=False)

    def move_handle(self, index: int, center, render: bool = True) -> None:
        """One live frame: move target ``index`` to ``center``, solve, deform, render.

        ``render=False`` is the sphere widget's path: rendering here too would draw every
        frame twice; that render's time completes :attr:`last_frame` instead.
        """
        win = self.window
        self._pending = None
        if not self._may_edit():
            if win.busy and index < len(win.ctrl.positions):
                # the widget moved by itself: back onto the target the drag did not change
                win.shape_view.move_handle(index, win.ctrl.positions[index].target)
                win.status(f"busy ({win.runner.job.name}): wait or cancel it first")
            return
        if not self.dragging:  # one undo step per drag
            win.ctrl.checkpoint()
            self.dragging = True
            win.selected = ("position", index)
        self._frame(lambda: win.ctrl.drag(index, np.asarray(center, float)), render)

    def rotated(self, index: int, rotation) -> None:
        """The gizmo turned: one live frame with the new target rotation."""
        win = self.window
        if not self._may_edit():
            if win.busy:  # the box turns by itself: back onto its target on release
                win.status(f"busy ({win.runner.job.name}): wait or cancel it first")
            return
        if win.gizmo.turn_started:  # one undo step per rotation
            win.ctrl.checkpoint()
            win.selected = ("jacobian", index)
        self.dragging = True
        self._frame(lambda: win.ctrl.rotate(index, rotation), render=False)

    def _may_edit(self) -> bool:
        """Whether a drag frame may run now.

        A running resampling of the volume is dropped: the drag makes its image stale and
        the release resamples again. Any other background job refuses the frame.
        """
        win = self.window
        if win.busy and win.runner.job is win.volume_job:
            win.runner.cancel()
        return not win.busy and win.ctrl.ready

    def _frame(self, step, render: bool) -> None:
        """One live frame: ``step()`` edits, solves and deforms (returns its FrameTiming)."""
        win = self.window
        shape = win.shape_view
        try:
            t = step()
            t0 = time.perf_counter()
            if t.mesh == "proxy":
                shape.rebuild_proxy()  # a proxy built since the last scene rebuild
            win.volume_display.dragging = True
            self.show_proxy(t.mesh == "proxy")
            if shape.showing_proxy:
                self._refine_timer.start()
            shape.update_markers()
            win.gizmo.follow()
            if self.live_section and win.analysis_view.slice is not None:
                win.analysis_view.update(full=False)
            if win.volume_display.slices:
                win.volume_display.update_slices(drag=True)
            t.analysis = time.perf_counter() - t0
            if not render:
                self.last_frame = self._pending = t  # completed by _on_render_end
                return
            t0 = time.perf_counter()
            win.plotter.ren_win.Render()
            t.render = time.perf_counter() - t0
        except Exception as exc:  # noqa: BLE001
            win.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())
            return
        self.show_frame(t)

    def _on_render_start(self, *args) -> None:
        self._render_t0 = time.perf_counter()

    def _on_render_end(self, *args) -> None:
        t, self._pending = self._pending, None
        if t is not None and self._render_t0 is not None:
            t.render = time.perf_counter() - self._render_t0
            self.show_frame(t)

    def released(self) -> None:
        """End of a drag: solve to convergence, refresh the analysis and the table."""
        win = self.window
        self.dragging = win.volume_display.dragging = False
        self.stop()
        if not win.busy and win.ctrl.ready:
            win.editing.solve_and_show(rebuild=False)

    def gizmo_released(self) -> None:
        """End of a gizmo turn (see :meth:`released`); a refused turn turns the box back."""
        if self.dragging:
            self.released()
        else:
            self.window.gizmo.follow()

    def stop(self) -> None:
        """Forget a pending frame and the refinement (a full solve follows)."""
        self._refine_timer.stop()
        self._pending = None

    def _refine(self) -> None:
        """The handle rests: show the full shape at the current (drag) solution."""
        win = self.window
        if win.busy or not win.ctrl.ready or not win.shape_view.showing_proxy:
            return
        try:
            win.ctrl.deform()
            self.show_proxy(False)
            win.plotter.render()
        except Exception as exc:  # noqa: BLE001
            win.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())

    def show_proxy(self, on: bool) -> None:
        """Show the drag proxy or the full shape, and say which in the status bar."""
        self.window.shape_view.show_proxy(on)
        self.window.lod_label.setText(self.window.shape_view.lod_text())

    def show_frame(self, t) -> None:
        """Show a frame's timing in the status bar."""
        self.last_frame = t
        self.frame_times.append(t.total)
        fps = 1.0 / t.total if t.total > 0 else float("inf")
        self.window.frame_label.setText(
            f"frame {1e3 * t.total:.1f} ms ({fps:.0f} fps): solve {1e3 * t.solve:.1f}, "
            f"deform {1e3 * t.deform:.1f}, render {1e3 * t.render:.1f} ms, {t.iterations} it"
        )
