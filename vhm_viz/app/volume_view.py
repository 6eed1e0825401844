"""A volume in the 3D view: three orthogonal slices that follow the map, rendering, isosurface.

:class:`VolumeDisplay` owns these actors. Each axis has a *drag* slice (coarse, deformed
every frame) and a *full* one (every voxel of the plane, deformed at rest); both are
:class:`~vhm_viz.app.analysis.SliceProbe` objects bound to the controller's deformer. The
volume rendering and the isosurface show the deformed volume, resampled in a background job
by the window (:meth:`VolumeDisplay.set_image`).
"""

from __future__ import annotations

import traceback

import numpy as np
from PySide6.QtCore import QTimer

from vhm_viz.app.shape_view import remove_named_actor
from vhm_viz.app.volume import DRAG_SAMPLES, FULL_SAMPLES
from vhm_viz.colours import measure_style

__all__ = ["VolumeDisplay", "ISO_COLOR"]

ISO_COLOR = (0.95, 0.85, 0.70)
# the full-resolution slice replaces the drag slice this long after a slider stops (ms)
SLICE_DELAY_MS = 250


class VolumeDisplay:
    """Actors of a volume: slices (``vslice{axis}{drag|full}``), ``volume`` and ``iso``.

    Parameters
    ----------
    plotter : pyvistaqt.QtInteractor
    controller : ExplorerController
    panel : ViewPanel
        The view dock: slice switches and sliders, transfer function, isosurface.
    add_measure_mesh : callable(mesh, name, style) -> actor
        Adds a mesh coloured by a measure in the :mod:`vhm_viz.colours` style.

    Attributes
    ----------
    actors : dict of str to actor
    slices : dict of int to dict
        Per axis ``{"drag": SliceProbe, "full": SliceProbe}``.
    colour : str
        What the slices show: ``"value"``, ``"determinant"`` or ``"condition_number"``.
    image : pyvista.ImageData or None
        The rendered (deformed) volume.
    stale : bool
        :attr:`image` lags behind the solution.
    dragging, moving_axis
        A drag is under way; the axis whose slider moves (None at rest).
    """

    def __init__(self, plotter, controller, panel, add_measure_mesh):
        self.plotter = plotter
        self.ctrl = controller
        self.panel = panel
        self.add_measure_mesh = add_measure_mesh
        self.actors: dict[str, object] = {}
        self.slices: dict[int, dict] = {}
        self._bound_to = None  # (volume, deformer) the slices are bound to
        self.colour = "value"
        self.image = None
        self.stale = False
        self.dragging = False
        self.moving_axis = None
        #: Called to resample the image (a background job), e.g. the window's.
        self.request_image = lambda: None
        #: Called after a moved slice came to rest at full resolution (analysis refresh).
        self.slice_rested = lambda: None
        #: Called with (message, details) when a control fails.
        self.report_error = lambda message, details="": None
        #: Called with a one-line message to show in the status bar.
        self.report_status = lambda message: None
        self._device_reported = None  # the volume whose device fallback was reported
        self._slice_timer = QTimer()
        self._slice_timer.setSingleShot(True)
        self._slice_timer.setInterval(SLICE_DELAY_MS)
        self._slice_timer.timeout.connect(self.finish_slice_move)

    def _remove(self, name: str) -> None:
        remove_named_actor(self.plotter, self.actors, name)

    def reset(self) -> None:
        """New data: slices rebound, the image resampled when shown."""
        self._bound_to = None
        self.image = None
        self.stale = self.ctrl.volume is not None

    @property
    def solved(self) -> bool:
        """Whether the controller has a solution the slices can follow."""
        return self.ctrl.ready and self.ctrl.last_report is not None

    def rebuild(self) -> None:
        """The slices: (re)made when the volume or its deformer changed."""
        ctrl, vp = self.ctrl, self.panel
        vol = ctrl.volume
        if vol is None:
            for name in list(self.actors):
                self._remove(name)
            self.slices, self._bound_to = {}, None
            vp.set_volume(None, None, None)
            return
        key = (id(vol), id(ctrl.deformer) if self.solved else None)
        if key == self._bound_to:
            return
        if self._bound_to is None or self._bound_to[0] != key[0]:
            vp.set_volume(vol.dimensions, vol.range, vol.index)
            lo, hi = vol.window()
            vp.set_transfer(0.5 * (lo + hi), hi - lo, 0.3)
        self._bound_to = key
        for axis in range(3):
            self._make_slice(axis, ("drag", "full"))
        self.update_slices(drag=False)
        self.update_actors()

    def _make_slice(self, axis: int, parts) -> None:
        bound = self.ctrl if self.solved else None
        entry = self.slices.setdefault(axis, {})
        for part in parts:
            samples = DRAG_SAMPLES if part == "drag" else FULL_SAMPLES
            entry[part] = self.ctrl.volume.slice_probe(bound, axis, samples)
            self._add_slice_actor(axis, part)

    def _add_slice_actor(self, axis: int, part: str, style: dict | None = None) -> None:
        name = f"vslice{axis}{part}"
        self._remove(name)
        mesh = self.slices[axis][part].mesh
        if style is not None:
            self.actors[name] = self.add_measure_mesh(mesh, name, style)
            self.actors[name].SetPickable(True)
        else:
            level, width, _ = self.panel.transfer
            self.actors[name] = self.plotter.add_mesh(
                mesh, scalars="value", cmap="gray", show_scalar_bar=False, name=name,
                clim=(level - width / 2, level + width / 2), render=False, reset_camera=False,
            )  # fmt: skip
        self.actors[name].GetProperty().SetLighting(False)  # the values, unshaded

    def drag_probes(self) -> list:
        """The bound drag slices (the analysis dock's histogram counts them)."""
        return [e["drag"] for e in self.slices.values() if e["drag"].binding is not None]

    def update_slices(self, drag: bool) -> None:
        """Deform the slices: the drag resolution always, the full one at rest."""
        if not self.slices or not self.ctrl.ready:
            return
        measure = None if self.colour == "value" else self.colour
        values = []
        for e in self.slices.values():
            values.append(e["drag"].update(measure))
            if not drag:
                e["full"].update(None)
        if measure is not None:
            style = measure_style(measure, np.concatenate(values))
            for axis, e in self.slices.items():
                e["drag"].colour(measure, values[axis])
                actor = self.actors.get(f"vslice{axis}drag")
                if actor is not None:
                    actor.mapper.scalar_range = style["clim"]
        self.update_actors(visibility_only=True)

    def _move_slice(self, axis: int, index: int) -> bool:
        vol = self.ctrl.volume
        if vol is None or not self.slices:
            return False
        vol.index[axis] = int(index)
        self._make_slice(axis, ("drag",))
        self.moving_axis = axis
        self.restyle()
        self.update_slices(drag=True)
        return True

    def _finish_slice_move(self) -> bool:
        axis, self.moving_axis = self.moving_axis, None
        if axis is None or not self.slices:
            return False
        self._make_slice(axis, ("full",))
        self.update_slices(drag=False)
        return True

    def restyle(self) -> None:
        """Re-add the drag slices in the style of :attr:`colour`."""
        style = None if self.colour == "value" else measure_style(self.colour, [1.0])
        for axis, e in self.slices.items():
            if style is not None and "shown" not in e["drag"].mesh.point_data:
                e["drag"].mesh.point_data["shown"] = np.ones(e["drag"].n_points)
            self._add_slice_actor(axis, "drag", style)

    def update_actors(self, visibility_only: bool = False) -> None:
        """Show the slices of the current resolution; the volume rendering and isosurface."""
        vp = self.panel
        on = vp.slices.isChecked()
        use_drag = self.colour != "value" or self.dragging or self.moving_axis is not None
        for axis in self.slices:
            for part, shown in (("drag", use_drag), ("full", not use_drag)):
                actor = self.actors.get(f"vslice{axis}{part}")
                if actor is not None:
                    actor.SetVisibility(on and shown)
        for name in ("volume", "iso"):
            actor = self.actors.get(name)
            if actor is not None:  # they lag behind a drag: hidden until the release
                actor.SetVisibility(not self.dragging)
        if visibility_only:
            return
        self._remove("volume")
        if vp.volume.isChecked() and self.image is not None:
            lo, hi = self.ctrl.volume.range
            self.actors["volume"] = self.plotter.add_volume(
                self.image, scalars="values", cmap="gray", clim=(lo, hi), mapper="smart",
                show_scalar_bar=False, name="volume", render=False, reset_camera=False,
            )  # fmt: skip
            self._apply_transfer(*vp.transfer)
        self._show_iso(vp.iso.isChecked(), vp.value_of(vp.iso_value.value()))

    def _apply_transfer(self, level: float, width: float, opacity: float) -> None:
        a, b = level - 0.5 * width, level + 0.5 * width
        vol = self.actors.get("volume")
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
        for axis in self.slices:
            for part in ("drag", "full"):
                actor = self.actors.get(f"vslice{axis}{part}")
                if actor is not None and actor.mapper.scalar_range is not None:
                    if part == "full" or self.colour == "value":
                        actor.mapper.scalar_range = (a, b)

    def _show_iso(self, on: bool, value: float) -> None:
        self._remove("iso")
        if on and self.image is not None:
            iso = self.image.contour([float(value)], scalars="values")
            if iso.n_points:
                self.actors["iso"] = self.plotter.add_mesh(
                    iso, color=ISO_COLOR, name="iso", render=False, reset_camera=False,
                    pickable=False, scalars=None,
                )  # fmt: skip

    @property
    def wants_image(self) -> bool:
        """Whether rendering or the isosurface is switched on for a loaded volume."""
        vp = self.panel
        return self.ctrl.volume is not None and (vp.volume.isChecked() or vp.iso.isChecked())

    def image_job(self):
        """What to resample, or None: ``fn(progress, cancelled) -> image`` for a background job.

        Before a solve the rest image is taken at once; an image that is current needs nothing.
        """
        vol = self.ctrl.volume
        if not self.wants_image:
            return None
        if not self.solved:
            self.image, self.stale = vol.rest_image(), False
            return None
        if not self.stale and self.image is not None:
            return None
        hm = self.ctrl.deformer.harmonic_map
        self.stale = False
        reason = vol.device()[1]
        if reason is not None and self._device_reported is not vol:
            self._device_reported = vol  # once per volume
            self.report_status(reason)

        def job(progress, cancelled):
            return vol.deformed_image(hm, progress=progress, abort=cancelled)

        return job

    def set_image(self, image) -> None:
        """Show a resampled deformed volume."""
        self.image, self.stale = image, False
        self.update_actors()
        self.plotter.render()

    # ------------------------------------------------------------------ the view dock
    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except Exception as exc:  # noqa: BLE001 - the UI must survive everything
            self.report_error(f"{type(exc).__name__}: {exc}", traceback.format_exc())
            return None

    def move_slice(self, axis: int, index: int) -> None:
        """Move the slice along ``axis`` to voxel ``index``.

        The drag-resolution slice follows at once, the full one when the slider rests
        (:data:`SLICE_DELAY_MS` later, or :meth:`finish_slice_move`).
        """
        if self._guard(self._move_slice, axis, index):
            self._slice_timer.start()
            self.plotter.render()

    def finish_slice_move(self) -> None:
        """The slider rests: the full-resolution slice of the moved axis."""
        self._slice_timer.stop()
        if self._guard(self._finish_slice_move):
            self._guard(self.slice_rested)
            self.plotter.render()

    def set_colour(self, colour: str) -> None:
        """Colour the slices by ``value``, ``determinant`` or ``condition_number``."""
        self.colour = colour
        self._guard(self.restyle)
        self._guard(self.update_slices, False)
        self.plotter.render()

    def show_volume(self, on: bool = True) -> None:
        """Volume rendering of the deformed volume (resampled in the background)."""
        if self.panel.volume.isChecked() != bool(on):
            self.panel.volume.setChecked(bool(on))  # comes back here
            return
        self.request_image()
        self._guard(self.update_actors)
        self.plotter.render()

    def set_transfer(self, level: float, width: float, opacity: float) -> None:
        """Window/level ramp of the volume rendering (and grey window of the slices).

        Opacity 0 below ``level - width/2``, rising to ``opacity`` at ``level + width/2``.
        """
        self._guard(self._apply_transfer, level, width, opacity)
        self.plotter.render()

    def show_isosurface(self, on: bool, value: float) -> None:
        """The isosurface ``value`` of the deformed volume (resampled first if needed)."""
        if on and self.image is None:
            self.request_image()
        self._guard(self._show_iso, on, value)
        self.plotter.render()
