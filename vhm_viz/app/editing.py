"""What the user edits in the explorer, and what follows each edit.

:class:`Editing` maps the constraint table, the settings, clicks on the shape (per the
interaction mode, :mod:`vhm_viz.app.picking`), Delete, undo and redo onto the controller.
Every edit is recorded for undo (:meth:`Editing.recorded`) and followed by
:meth:`Editing.after_edit`: what the edit made stale is rebuilt in a background job, then
the scene is solved to convergence and shown (:meth:`Editing.solve_and_show`). An edit
solved at once (a target or Jacobian typed into the table, the mode) whose solve fails is
taken back: the scene, the undo history and the shown shape stay as they were before it.
"""

from __future__ import annotations

import contextlib
import time
import traceback
from pathlib import Path

import numpy as np
from PySide6.QtCore import QTimer
from PySide6.QtWidgets import QInputDialog

from vhm_viz.app.controller import FrameTiming
from vhm_viz.app.picking import MODES, apply_pick, rest_point_of_pick
from vhm_viz.core.cage import MIN_FACE_ANGLE

__all__ = ["Editing"]


class Editing:
    """Edits, picks, undo/redo, and the solve that follows them, for one window.

    Parameters
    ----------
    window : ExplorerWindow

    Attributes
    ----------
    interaction_mode : str
        What a left click on the shape does (a key of :data:`~vhm_viz.app.picking.MODES`).
    """

    def __init__(self, window):
        self.window = window
        self.ctrl = window.ctrl
        self.interaction_mode = "view"
        self._fill_pending = False
        # shape metrics after a solve: computed when the event loop is idle
        self._pending_metrics: dict | None = None
        self._metrics_timer = QTimer(window)
        self._metrics_timer.setSingleShot(True)
        self._metrics_timer.setInterval(0)
        self._metrics_timer.timeout.connect(self._deferred_metrics)

    def _guarded(self, fn, *args):
        """Run ``fn(*args)``; an exception becomes an error message. Returns its result."""
        try:
            return fn(*args)
        except Exception as exc:  # noqa: BLE001 - the UI must survive everything
            self.window.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())
            return None

    # ------------------------------------------------------------------ settings
    def set_mode(self, mode: str) -> None:
        """Rigid / similar; re-solves warm-started."""
        self._guarded(self._set_mode, mode)

    def _set_mode(self, mode: str) -> None:
        if mode == self.ctrl.mode:
            return
        with self.recorded():
            self.ctrl.set_mode(mode)
        self.window.constraints_panel.set_mode(mode)
        if self.ctrl.ready:
            self._solve_edit()

    def set_alpha(self, alpha: float) -> None:
        """Stiffness alpha (rebuilds the deformer in the background)."""
        self._guarded(self._set_alpha, alpha)

    def _set_alpha(self, alpha: float) -> None:
        with self.recorded():
            self.ctrl.set_alpha(alpha)
        self.window.constraints_panel.set_alpha(alpha)
        self.after_edit(structure=False)

    def set_interaction_mode(self, mode: str) -> None:
        """Choose what a left click on the shape does (see :data:`MODES`)."""
        if mode not in MODES:
            raise ValueError(f"unknown interaction mode {mode!r}")
        self.interaction_mode = mode
        self.window.mode_actions[mode].setChecked(True)
        self.window.status(MODES[mode])

    # ------------------------------------------------------------------ cage and anchors
    def load_cage(self, path: str | None = None) -> None:
        """Load a cage file; invalid or non-enclosing cages are reported, not applied."""
        return self._guarded(self._load_cage, path)

    def _load_cage(self, path: str | None = None) -> None:
        path = self.window.ask_path(
            path, "Load cage", "Cages (*.obj *.off *.ply *.stl *.vtp *.vtk)"
        )
        if path is None:
            return
        if self.ctrl.rest is None:
            raise ValueError("open data before loading a cage")
        with self.recorded():
            self.ctrl.load_cage(path)
        repaired = self.ctrl.cage.repairs
        notes = "; ".join(self.ctrl.notes)
        self.ctrl.notes = []
        message = f"cage {Path(path).name}: {self.ctrl.cage.n_faces} faces"
        if repaired:
            message += f"; repaired {len(repaired)} slivers: {'; '.join(repaired)}"
        self.window.status(message + (f"; {notes}" if notes else ""), 15000 if notes else 5000)
        self.after_edit(structure=True)

    def _ask_count(self, count, title: str, label: str, default: int, lowest: int):
        """``count``, or when None the number the user enters (None if cancelled)."""
        if count is not None:
            return count
        count, ok = QInputDialog.getInt(self.window, title, label, default, lowest, 5000)
        return count if ok else None

    def generate_cage(self, max_faces: int | None = None):
        """Generate a cage in the background (progress, cancel); returns the job."""
        return self._guarded(self._generate_cage, max_faces)

    def _generate_cage(self, max_faces: int | None = None):
        if self.ctrl.rest is None:
            raise ValueError("open data before generating a cage")
        max_faces = self._ask_count(max_faces, "Generate cage", "Max faces", 500, 12)
        if max_faces is None:
            return None
        ctrl = self.ctrl

        def done(cage):
            with self.recorded():
                self.ctrl.set_cage(cage)
            thin = cage.thin_faces
            self.window.status(
                f"generated cage: {cage.n_faces} faces"
                + (
                    f"; {len(thin)} faces thinner than {MIN_FACE_ANGLE:g} degrees (the "
                    "smoothness weight collapses on them: the result may be poor)"
                    if len(thin)
                    else ""
                )
            )
            self.after_edit(structure=True)

        return self.window.run_job(
            "generate cage", lambda progress, cancelled: ctrl.auto_cage(max_faces, progress), done
        )

    def load_anchors(self, path: str | None = None, count: int | None = None) -> None:
        """Anchors from rigidity lines (``.tgf``, OFF polylines, VTK polylines)."""
        return self._guarded(self._load_anchors, path, count)

    def _load_anchors(self, path: str | None = None, count: int | None = None) -> None:
        lines = "Rigidity lines (*.tgf *.off *.vtp *.vtk);;All (*)"
        path = self.window.ask_path(path, "Load rigidity lines", lines)
        if path is None:
            return
        count = self._ask_count(count, "Anchors", "Number of anchors", 50, 1)
        if count is None:
            return
        with self.recorded():
            self.ctrl.load_anchors(path, count)
        self.after_edit(structure=True)

    def generate_anchors(self, count: int | None = None):
        """Compute anchors automatically in the background; returns the job."""
        return self._guarded(self._generate_anchors, count)

    def _generate_anchors(self, count: int | None = None):
        count = self._ask_count(count, "Anchors", "Number of anchors", 50, 1)
        if count is None:
            return None
        ctrl = self.ctrl

        def job(progress, cancelled):
            progress(0.1, "computing anchors")
            return ctrl.auto_anchors(count)

        def done(anchors):
            with self.recorded():
                self.ctrl.set_anchors(anchors)
            self.window.status(f"{len(anchors)} anchors")
            self.after_edit(structure=True)

        return self.window.run_job("anchors", job, done)

    def clear_anchors(self) -> None:
        """Remove all anchors."""
        return self._guarded(
            self._clear_anchors,
        )

    def _clear_anchors(self) -> None:
        with self.recorded():
            self.ctrl.set_anchors(np.zeros((0, 3)))
        self.after_edit(structure=True)

    # ------------------------------------------------------------------ the constraint table
    def edit_target(self, index: int, target) -> None:
        """Numeric edit of a position target (from the side panel)."""
        self._guarded(self._edit_target, index, target)

    def _edit_target(self, index: int, target) -> None:
        if index < 0 or target is None:
            self.refresh_panels()
            raise ValueError("not a number")
        if not np.isfinite(target).all():
            self.refresh_panels()
            raise ValueError("target values must be numbers")
        with self._table_edit():
            self.ctrl.set_target(index, target)
        self.window.selected = ("position", index)
        self.window.shape_view.move_handle(index, target)
        self._solve_edit()

    def edit_jacobian(self, index: int, angles, scale: float) -> None:
        """Numeric edit of a Jacobian constraint's angles (degrees) and scale."""
        self._guarded(self._edit_jacobian, index, angles, scale)

    def _edit_jacobian(self, index: int, angles, scale: float) -> None:
        if not (np.isfinite(angles).all() and np.isfinite(scale)):
            self.refresh_panels()
            raise ValueError("angles and scale must be numbers")
        with self._table_edit():
            self.ctrl.set_jacobian(index, angles, scale)
        self.window.selected = ("jacobian", index)
        self._solve_edit()

    @contextlib.contextmanager
    def _table_edit(self):
        """Record an edit typed into the table; a refused one shows the scene's values again."""
        try:
            with self.recorded():
                yield
        except Exception:
            self.refresh_panels()
            raise

    def delete_constraint(self, kind: str, index: int) -> None:
        """Delete a constraint (the last position constraint is kept)."""
        self._guarded(self._delete_constraint, kind, index)

    def _delete_constraint(self, kind: str, index: int) -> None:
        if kind == "position" and len(self.ctrl.positions) == 1:
            raise ValueError(
                "the last position constraint cannot be deleted (it fixes the translation)"
            )
        with self.recorded():
            self.ctrl.remove_constraint(kind, index)
        self.window.selected = None
        if kind == "jacobian":
            self.window.gizmo.index = None
        self.after_edit(structure=False)

    def on_table_selection(self) -> None:
        """A row of the constraint table was selected: Delete and the gizmo follow it."""
        rows = self.window.constraints_panel.selected_rows()
        if rows:
            self.window.selected = rows[0]
            gizmo = self.window.gizmo
            if rows[0][0] == "jacobian" and rows[0][1] != gizmo.index:
                gizmo.index = rows[0][1]
                gizmo.rebuild(3.0 * self.window.shape_view.marker_radius)
                self.window.plotter.render()

    def delete_selected(self) -> bool:
        """Delete: remove the constraint selected in the table (or last added / dragged)."""
        selected = self.window.selected
        rows = self.window.constraints_panel.selected_rows() or ([selected] if selected else [])
        if not rows:
            self.window.status("no constraint selected")
            return False
        for kind, index in sorted(rows, key=lambda r: (r[0], -r[1])):
            self.delete_constraint(kind, index)
        return True

    def refresh_panels(self) -> None:
        """Refill the constraint table (deferred: may be called from the table's signals)."""
        if not self._fill_pending:
            self._fill_pending = True
            QTimer.singleShot(0, self._fill_panels)

    def _fill_panels(self) -> None:
        self._fill_pending = False
        cp = self.window.constraints_panel
        cp.fill(self.ctrl.positions, self.ctrl.jacobians)
        cp.set_mode(self.ctrl.mode)
        cp.set_alpha(self.ctrl.alpha)

    # ------------------------------------------------------------------ undo
    @contextlib.contextmanager
    def recorded(self):
        """Record the scene before an edit for undo, once the edit succeeded."""
        state = self.ctrl.snapshot()
        yield
        self.ctrl.checkpoint(state)

    def undo(self) -> bool:
        """Ctrl+Z: back to the scene before the last edit, solved and shown."""
        return bool(self._guarded(self._history, self.ctrl.undo, "undo"))

    def redo(self) -> bool:
        """Ctrl+Shift+Z: re-apply the last undone edit."""
        return bool(self._guarded(self._history, self.ctrl.redo, "redo"))

    def _history(self, step, what: str) -> bool:
        win = self.window
        if win.busy:
            win.status("busy: wait or cancel the running job")
            return False
        if not step():
            win.status(f"nothing to {what}")
            return False
        win.selected = None
        if win.gizmo.index is not None and win.gizmo.index >= len(self.ctrl.jacobians):
            win.gizmo.index = None
        win.status(f"{what} done")
        self.after_edit(structure=True)
        return True

    # ------------------------------------------------------------------ picks
    def click_at_display(self, x: int, y: int) -> bool:
        """Pick the shape at display pixel ``(x, y)`` and act per the interaction mode.

        This is the click path (the left-button observer calls it). Returns whether the
        shape was hit.
        """
        return bool(self._guarded(self._click, x, y))

    def _click(self, x: int, y: int) -> bool:
        win = self.window
        actor = win.shape_view.actors.get("shape")
        if actor is None:
            return False
        hit = win.picker.pick(actor, x, y)
        if hit is None:
            win.status("no shape under the cursor")
            return False
        self.handle_pick(*hit)
        return True

    def handle_pick(self, cell_id: int, world_point) -> None:
        """Act on a picked point of the deformed shape (see :data:`MODES`)."""
        self._guarded(self._handle_pick, cell_id, world_point)

    def _handle_pick(self, cell_id: int, world_point) -> None:
        win = self.window
        if win.busy:
            win.status("busy: wait or cancel the running job")
            return
        mode = self.interaction_mode
        rest = rest_point_of_pick(self.ctrl.display, self.ctrl.rest_points, cell_id, world_point)
        with self.recorded():
            done = apply_pick(self.ctrl, mode, rest, world_point)
            if done is None:
                if mode == "anchor-":
                    win.status("no anchors to remove")
                return
        message, selected = done
        win.status(message)
        if selected is not None:
            win.selected = selected
            if selected[0] == "jacobian":
                win.gizmo.index = selected[1]
        self.after_edit(structure=mode.startswith("anchor"))

    # ------------------------------------------------------------------ solving
    def after_edit(self, structure: bool):
        """Rebuild what the edit made stale (in the background), then solve and show.

        Returns the background job, or None when nothing had to be rebuilt.
        """
        win, ctrl = self.window, self.ctrl
        self.refresh_panels()
        win.rebuild_scene(reset_camera=False)
        win.plotter.render()  # the edit shows now, before any solve
        if not ctrl.can_solve:
            self.update_analysis()
            return None
        if ctrl.ready:
            self.solve_and_show()
            return None

        def done(_):
            av = win.analysis_view
            av.slice = None  # bound to the deformer before the rebuild
            win.shape_view.forget()
            self.solve_and_show()
            if av.plane is not None:  # a section is shown: sampled again, on the new map
                av.make_section()
                self.update_analysis()
            if ctrl.notes:  # e.g. cage shells without constraints stay put
                win.status("; ".join(ctrl.notes), 15000)
                ctrl.notes = []

        return win.run_job(
            "binding", lambda progress, cancelled: ctrl.prepare(progress, cancelled), done
        )

    def solve_and_show(self, rebuild: bool = True) -> None:
        """Warm-started solve to convergence, deform in place, update the scene and panels.

        ``rebuild=False`` keeps the actors and handles (only moves the markers).
        """
        self._guarded(self._solve_and_show, rebuild)

    def _solve_edit(self) -> None:
        """Solve and show the edit just recorded; an edit whose solve fails is taken back.

        The scene, the undo history and the shown shape return to what they were before the
        edit (solved again from the local matrices the failed solve started from), and one
        line says so.
        """
        ctrl = self.ctrl
        start = ctrl.deformer.rotations_at_anchors if ctrl.ready else "previous"
        try:
            self._solve_and_show(True)
        except Exception as exc:  # noqa: BLE001 - whatever failed, the edit is taken back
            failure, details = f"{type(exc).__name__}: {exc}", traceback.format_exc()
            if not ctrl.take_back():
                raise
            self.refresh_panels()
            self._solve_and_show(True, start)
            self.window.report_error(
                f"the solve failed, so the edit was undone: {failure}", details
            )

    def _solve_and_show(self, rebuild: bool, init="previous") -> None:
        win, ctrl = self.window, self.ctrl
        t0 = time.perf_counter()
        rep = ctrl.settle(init)
        t1 = time.perf_counter()
        win.drag.stop()
        ctrl.deform()
        t2 = time.perf_counter()
        if rebuild:
            win.rebuild_scene(reset_camera=False)
        else:
            win.shape_view.update_markers()
            self.refresh_panels()
        win.drag.show_proxy(False)
        win.gizmo.follow()
        if ctrl.volume is not None:
            win.volume_display.update_slices(drag=False)
            win.volume_display.stale = True
            win.refresh_volume_image()
        self.update_analysis(defer_metrics=True)
        t3 = time.perf_counter()
        win.plotter.render()
        win.drag.show_frame(
            FrameTiming(
                solve=t1 - t0, deform=t2 - t1, analysis=t3 - t2,
                render=time.perf_counter() - t3, iterations=rep.iterations,
            )
        )  # fmt: skip
        if not rep.converged:
            win.status(f"solver stopped after {rep.iterations} iterations (not converged)")

    def full_solve(self) -> None:
        """Solve to convergence (builds what is stale first)."""
        if not self.ctrl.ready:
            self._guarded(self.after_edit, True)
            return
        self.solve_and_show()

    def certify(self, max_cubes: int = 200_000):
        """Certify the shown deformation over the shape in the background, then draw it.

        Witnesses (``det J <= 0``) are drawn as red spheres, undecided cubes as orange
        wireframes, both in deformed space; the analysis dock shows the answer. Returns
        the background job.
        """
        win, ctrl = self.window, self.ctrl

        def done(cert):
            win.analysis_view.show_certificate()
            self.update_analysis()
            win.plotter.render()
            win.status(cert.summary(), 15000)

        return win.run_job(
            "certify", lambda progress, cancelled: ctrl.certify(max_cubes, progress, cancelled),
            done,
        )  # fmt: skip

    # ------------------------------------------------------------------ analysis
    def update_analysis(self, full: bool = True, defer_metrics: bool = False) -> None:
        """Recompute the section colours, histogram, energy plot and metrics.

        ``full=False``: the section only (live section while dragging). ``defer_metrics``:
        the shape metrics (E_rigid, E_volume: a pass over every triangle) are computed once
        the event loop is idle, after the frame is shown.
        """
        m = self.window.analysis_view.update(full)
        if m is None:
            return
        if defer_metrics:
            self._pending_metrics = m
            self._metrics_timer.start()
            return
        self._metrics_timer.stop()
        self.window.analysis_view.finish(m)

    def _deferred_metrics(self) -> None:
        # not while a drag runs (the proxy is shown): the next release schedules them again
        if (
            self._pending_metrics is None
            or self.window.shape_view.showing_proxy
            or self.ctrl.full_stale
        ):
            return
        m, self._pending_metrics = self._pending_metrics, None
        self._guarded(self.window.analysis_view.finish, m)
