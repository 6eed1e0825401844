"""The Qt explorer under a real X display (Xvfb), driven through its own code paths.

A session fixture starts ``Xvfb`` when no display is set and makes Qt use it (``xcb``),
overriding ``.ci/run``'s ``QT_QPA_PLATFORM=offscreen`` for this module only.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import (
    FOLDING_DIMS,
    data_path,
    trilinear_corner_dets,
    write_folding_volume,
)

pytest.importorskip("PySide6")
pytest.importorskip("pyvistaqt")
pytest.importorskip("pytestqt")

pytestmark = pytest.mark.gui

# the real X display, one-thread BLAS and the window (fixtures shared with other GUI tests)
from tests.gui import RES, single_threaded_blas, window, xvfb_display  # noqa: E402, F401
from tests.gui import bar_with_a_gizmo as _bar_with_a_gizmo  # noqa: E402
from tests.gui import open_bar as _open_bar  # noqa: E402


def _turn_gizmo(win, centre, degrees: float) -> None:
    """One frame of the user turning the gizmo's box ``degrees`` about y, around ``centre``."""
    import vtk
    from scipy.spatial.transform import Rotation

    r = Rotation.from_euler("y", degrees, degrees=True).as_matrix()
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, centre - r @ centre
    t = vtk.vtkTransform()
    t.SetMatrix(m.ravel())
    win.gizmo.widget.SetTransform(t)
    win.gizmo.widget.InvokeEvent("InteractionEvent")


def _direct_points(ctrl, mode=None):
    """Independent reference: a fresh Deformer solved to convergence from the identity."""
    from vhm_viz.core.deformer import Deformer

    dfm = Deformer(ctrl.cage, ctrl.anchors, mode=mode or ctrl.mode, alpha=ctrl.alpha)
    dfm.set_constraints(**ctrl.scene.constraint_arguments())
    # stiff set-ups (many anchors, few constraints) need several thousand accelerated
    # iterations (~0.1 s): give the reference room to converge
    rep = dfm.solve(max_iterations=50000, tolerance=1e-9, init="identity")
    assert rep.converged
    return dfm.harmonic_map.map(ctrl.rest_points)


def test_the_window_shows_on_the_display_and_draws_the_shape(window, qapp):
    """The explorer's window is exposed on Qt's display and its 3D view draws the shape."""
    if os.environ.get("QT_QPA_PLATFORM") == "xcb":
        assert qapp.platformName() == "xcb"
    assert window.isVisible() and window.windowHandle().isExposed()
    assert window.plotter.interactor.isVisible()
    _open_bar(window, "bend-90")
    img = np.asarray(window.screenshot(False))[..., :3].astype(int)
    w, h = window.plotter.window_size
    assert img.shape[:2] == (h, w)
    # the shape's light grey-beige, shaded, on the white background
    shape = (np.abs(img[..., 0] - img[..., 1]) < 12) & (img[..., 0] > 60) & (img[..., 0] < 245)
    assert 0.005 < shape.mean() < 0.9, shape.mean()


def test_bar_click_constraint_and_drag_match_direct_solve(window):
    win = window
    ctrl = _open_bar(win, "bend-90")
    p = win.plotter
    # the scene shows the shape (deformed), cage, anchors and one handle per position target
    assert "shape" in win.actors and "cage" in win.actors and "anchors" in win.actors
    assert "jacobians" in win.actors
    assert len(win.shape_view.handles) == len(ctrl.positions) == 6
    assert not np.allclose(ctrl.deformed_points, ctrl.rest_points)

    # click on the shape in "add position" mode: a vertex on the y = -0.5 face mid-way up
    p.view_xz()  # camera on -y, looking at the y = -0.5 face
    p.render()
    rest = ctrl.rest_points
    k = int(np.argmin(np.linalg.norm(rest - [0.0, -0.5, 2.5], axis=1)))
    world = ctrl.deformed_points[k].copy()
    win.editing.set_interaction_mode("position")
    x, y = win.picker.display_coordinates(world)
    with win.waiting_for_jobs():
        assert win.editing.click_at_display(x, y)
    assert win.last_error is None, win.last_error
    assert len(ctrl.positions) == 7 and len(win.shape_view.handles) == 7
    new = ctrl.positions[-1]
    cell = 5.0 / (5 * RES)
    assert np.linalg.norm(new.point - rest[k]) < 1.5 * cell  # rest point under the cursor
    assert np.linalg.norm(new.target - world) < 1.5 * cell
    # adding a constraint at the current image does not move the shape
    before = ctrl.deformed_points.copy()
    np.testing.assert_allclose(before, _direct_points(ctrl), atol=2e-4)

    # drag its handle through the sphere widget's callback
    win.editing.set_interaction_mode("view")
    widget = win.shape_view.handles[-1]
    goal = new.target + np.array([0.3, -0.2, 0.1])
    widget.SetCenter(*goal)
    widget.InvokeEvent("InteractionEvent")
    widget.InvokeEvent("EndInteractionEvent")
    assert win.last_error is None, win.last_error
    np.testing.assert_allclose(ctrl.positions[-1].target, goal)
    after = ctrl.deformed_points
    assert np.abs(after - before).max() > 0.05
    np.testing.assert_allclose(after, _direct_points(ctrl), atol=5e-4)
    # the constraint holds and the frame time is shown
    img = ctrl.deformer.harmonic_map.map(new.point[None])[0]
    np.testing.assert_allclose(img, goal, atol=1e-6)
    assert "ms" in win.frame_label.text() and win.drag.last_frame.total > 0
    # the display dataset was updated in place: the same actor and dataset
    assert win.actors["shape"].mapper.dataset is ctrl.display


def test_mode_switch_and_alpha(window):
    win = window
    ctrl = _open_bar(win, "bulge")
    rigid = ctrl.deformed_points.copy()
    np.testing.assert_allclose(rigid, _direct_points(ctrl, "rigid"), atol=5e-4)
    with win.waiting_for_jobs():
        win.constraints_panel.mode.setCurrentText("similar")  # the UI path
    assert ctrl.mode == "similar" and ctrl.deformer.mode == "similar"
    similar = ctrl.deformed_points.copy()
    assert np.abs(similar - rigid).max() > 1e-3
    np.testing.assert_allclose(similar, _direct_points(ctrl, "similar"), atol=5e-4)
    # alpha: the slider rebuilds the deformer in the background
    with win.waiting_for_jobs():
        win.editing.set_alpha(0.001)
    assert ctrl.ready and ctrl.deformer.alpha == pytest.approx(0.001)
    np.testing.assert_allclose(ctrl.deformed_points, _direct_points(ctrl), atol=5e-4)


def _click_on_the_y_face(win, ctrl, near, mode: str) -> int:
    """Click, in ``mode``, the shape's vertex nearest ``near`` (rest), seen from -y.

    Returns the vertex's index.
    """
    win.plotter.view_xz()  # camera on -y, looking at the y = -0.5 face
    win.plotter.render()
    k = int(np.argmin(np.linalg.norm(ctrl.rest_points - near, axis=1)))
    win.editing.set_interaction_mode(mode)
    with win.waiting_for_jobs():
        assert win.editing.click_at_display(
            *win.picker.display_coordinates(ctrl.deformed_points[k])
        )
    return k


def test_jacobian_constraint_numeric_edit_and_delete(window):
    win = window
    ctrl = _open_bar(win, "bend-90", apply=False)  # bottom held only
    _click_on_the_y_face(win, ctrl, [0.0, -0.5, 4.0], "jacobian")
    assert len(ctrl.jacobians) == 1 and win.last_error is None
    np.testing.assert_allclose(ctrl.jacobians[0].matrix, np.eye(3), atol=1e-6)
    # numeric editing in the side panel: rotate 40 degrees about y, scale 1.2
    table = win.constraints_panel.table
    row = len(ctrl.positions)
    assert table.item(row, 0).text() == "J 0"
    table.item(row, 2).setText("40")
    with win.waiting_for_jobs():
        table.item(row, 4).setText("1.2")
    assert ctrl.jacobians[0].scale == pytest.approx(1.2)
    assert ctrl.jacobians[0].angles[1] == pytest.approx(40)
    J = ctrl.deformer.harmonic_map.jacobian(ctrl.jacobians[0].point[None])[0]
    np.testing.assert_allclose(J, ctrl.jacobians[0].matrix, atol=1e-6)
    np.testing.assert_allclose(ctrl.deformed_points, _direct_points(ctrl), atol=5e-4)
    # a bad number is refused with a message, nothing changes
    table.item(row, 4).setText("-1")
    assert win.last_error is not None and ctrl.jacobians[0].scale == pytest.approx(1.2)
    win.last_error = None
    # delete it: back to the rest shape (only the bottom is held)
    with win.waiting_for_jobs():
        win.editing.delete_constraint("jacobian", 0)
    assert not ctrl.jacobians
    np.testing.assert_allclose(ctrl.deformed_points, ctrl.rest_points, atol=1e-4)


def test_save_and_reload_scene(window, tmp_path):
    win = window
    ctrl = _open_bar(win, "bend-u")
    win.editing.set_mode("similar")
    i = ctrl.add_position_constraint(ctrl.rest_points[50])
    with win.waiting_for_jobs():
        win.editing.after_edit(structure=False)
    w = win.shape_view.handles[i]
    w.SetCenter(*(ctrl.positions[i].target + [0.1, 0.1, 0.0]))
    w.InvokeEvent("InteractionEvent")
    w.InvokeEvent("EndInteractionEvent")  # release: solved to convergence
    expected = ctrl.deformed_points.copy()
    path = tmp_path / "scene.json"
    win.save_scene(str(path))
    assert path.exists()
    from vhm_viz.scene import Scene  # the shared scene format (vhm-viz deform --scene)

    scene = Scene.load(path)
    assert scene.mode == "similar" and len(scene.constraints["positions"]) == 7
    with win.waiting_for_jobs():
        win.open_bar("twist", resolution=RES)  # something else in between
    assert not np.allclose(ctrl.deformed_points[: len(expected)], expected, atol=1e-2)
    with win.waiting_for_jobs():
        assert win.load_scene(str(path))
    assert win.last_error is None, win.last_error
    assert win.ctrl.mode == "similar" and len(win.ctrl.positions) == 7
    np.testing.assert_allclose(win.ctrl.deformed_points, expected, atol=1e-6)
    # the reloaded solve started at the saved solution
    assert win.ctrl.last_report.iterations < 20
    # export the deformed data and read it back
    import pyvista as pv

    out = tmp_path / "deformed.vtp"
    win.export(str(out))
    exact = win.ctrl.deformer.harmonic_map.map(win.ctrl.rest_points)
    # the export is the map in float64; the display went through the float32 binding
    np.testing.assert_allclose(pv.read(out).points, exact, rtol=0, atol=1e-12)
    diag = np.linalg.norm(np.ptp(exact, axis=0))
    assert np.abs(exact - expected).max() <= 1e-6 * diag


def test_export_of_a_resampled_volume_in_folds_says_so(window, tmp_path):
    """The export writes the resampled or warped volume as it is, and the window says how
    it folds, in the status bar: the resampled voxels in folds (the file's vhm_foldover
    mask), the warped voxel cells inverted."""
    import pyvista as pv

    write_folding_volume(tmp_path)
    win = window
    with win.waiting_for_jobs():
        assert win.open_file(str(tmp_path / "image.vti"))
    with win.waiting_for_jobs():
        assert win.load_scene(str(tmp_path / "scene.json"))
    assert win.last_error is None, win.last_error
    out = tmp_path / "bent.vti"
    win.export(str(out))
    assert win.last_error is None, win.last_error
    folds = int(np.count_nonzero(pv.read(out).point_data["vhm_foldover"]))
    assert folds > 0
    said = f"exported {out}, but the deformation folds the data: {folds} of "
    assert win.last_warning.startswith(said), win.last_warning
    assert win.statusBar().currentMessage() == win.last_warning
    # warped, the same volume's voxel cells are inverted: counted as a brute force counts
    # the cells whose trilinear corner Jacobians are not all positive
    warped = tmp_path / "bent.vts"
    win.export(str(warped))
    grid = np.asarray(pv.read(warped).points).reshape(*FOLDING_DIMS[::-1], 3)
    inverted = int((trilinear_corner_dets(grid) <= 0).sum())
    assert inverted > 0
    said = f"exported {warped}, but the deformation folds the data: {inverted} of "
    assert win.last_warning.startswith(said) and "cells inverted" in win.last_warning


def test_screenshot_shows_shape_and_slice(window, tmp_path):
    win = window
    ctrl = _open_bar(win, "bulge")
    win.show_cage_action.trigger()  # Cage > Show cage: off
    assert not win.show_cage_action.isChecked()
    assert not win.actors["cage"].GetVisibility()
    b = ctrl.cage.bounds
    win.analysis_view.show_section(True, origin=0.5 * (b[0] + b[1]), normal=(0.0, -1.0, 0.0))
    assert win.last_error is None, win.last_error
    assert win.analysis_view.slice is not None and win.analysis_view.slice.n_points > 50
    # slice values are closed-form Jacobian determinants of the map at the slice samples
    dets = win.analysis_view.slice.mesh.point_data["measure"]
    ref = np.linalg.det(ctrl.deformer.harmonic_map.jacobian(win.analysis_view.slice.rest_points))
    np.testing.assert_allclose(dets, ref, rtol=1e-6, atol=1e-8)
    assert "foldovers" in win.analysis_view.metrics and np.isfinite(
        win.analysis_view.metrics["E_rigid"]
    )
    win.plotter.view_xz()
    win.plotter.reset_camera()
    path = tmp_path / "explorer.png"
    img = win.screenshot(str(path))
    if os.environ.get("VHM_KEEP_SCREENSHOT"):
        shutil.copy(path, os.environ["VHM_KEEP_SCREENSHOT"])
    assert path.exists() and img is not None
    img = np.asarray(img)[..., :3].astype(int)
    assert img.std() > 5  # not blank
    # shape: light grey-beige (0.85, 0.85, 0.80) shaded; slice: saturated jet colours
    img = img[: int(0.8 * img.shape[0])]  # above the scalar bar
    r, g, bl = img[..., 0], img[..., 1], img[..., 2]
    greyish = (np.abs(r - g) < 12) & (r - bl > 3) & (r > 60) & (r < 250)
    saturated = (img.max(axis=2) - img.min(axis=2)) > 120
    assert greyish.sum() > 2000, greyish.sum()
    assert saturated.sum() > 1000, saturated.sum()
    # condition number colouring switches the measure in place
    win.analysis_panel.measure.setCurrentText("condition_number")
    assert win.analysis_view.measure == "condition_number"
    assert np.all(win.analysis_view.slice.mesh.point_data["measure"] >= 1 - 1e-9)


def _section_shows_the_map(win):
    """The section drawn is the current map of its samples, coloured by its det J."""
    ctrl, section = win.ctrl, win.analysis_view.slice
    assert section is not None and section.n_points > 50
    assert win.actors["slice"].mapper.dataset is section.mesh
    hm = ctrl.deformer.harmonic_map
    np.testing.assert_allclose(section.mesh.points, hm.map(section.rest_points), atol=1e-6)
    det = np.linalg.det(hm.jacobian(section.rest_points))
    np.testing.assert_allclose(section.mesh.point_data["measure"], det, rtol=1e-6, atol=1e-8)
    assert win.analysis_panel.histogram._bars.total == section.n_points


def test_the_section_follows_the_map_after_an_edit_that_rebuilds_the_deformer(window):
    """An anchor added while the section shows: the section is sampled on the new map."""
    win = window
    ctrl = _open_bar(win, "bend-90")
    b = ctrl.cage.bounds
    win.analysis_view.show_section(True, origin=0.5 * (b[0] + b[1]), normal=(0.0, -1.0, 0.0))
    assert win.last_error is None, win.last_error
    _section_shows_the_map(win)
    before = ctrl.deformer
    _click_on_the_y_face(win, ctrl, [0.0, -0.5, 2.5], "anchor+")
    assert win.last_error is None, win.last_error
    assert ctrl.deformer is not before and ctrl.ready
    assert win.analysis_panel.show_slice.isChecked()
    _section_shows_the_map(win)


def test_the_section_takes_the_samples_per_side_of_the_dock(window):
    """The dock's samples per side resample the shown section at once."""
    win = window
    ctrl = _open_bar(win, "bend-90")
    b = ctrl.cage.bounds
    win.analysis_view.show_section(True, origin=0.5 * (b[0] + b[1]), normal=(0.0, -1.0, 0.0))
    coarse = win.analysis_view.slice.n_points
    win.analysis_panel.resolution.setValue(120)
    assert win.last_error is None, win.last_error
    assert win.analysis_view.slice.n_points > 3 * coarse
    _section_shows_the_map(win)


def test_errors_are_messages_and_the_app_survives(window, tmp_path):
    win = window
    ctrl = _open_bar(win, "bend-90")
    before = ctrl.deformed_points.copy()
    cage_before = ctrl.cage
    # unreadable data file
    bad = tmp_path / "garbage.vtp"
    bad.write_text("this is not a VTK file")
    with win.waiting_for_jobs():
        win.open_file(str(bad))
    assert win.last_error and "garbage.vtp" in win.last_error
    with win.waiting_for_jobs():
        win.open_file(str(tmp_path / "missing.obj"))
    assert "missing.obj" in win.last_error
    assert win.ctrl.display is not None and np.allclose(win.ctrl.deformed_points, before)
    # a cage file that is not a valid cage (self-intersecting)
    win.last_error = None
    win.editing.load_cage(str(data_path("bad_cages", "selfintersecting_armadillo_cage.obj")))
    assert win.last_error and "CageError" in win.last_error
    # a valid cage that does not enclose the shape
    win.last_error = None
    small = tmp_path / "small_cage.obj"
    from tests.conftest import box_cage

    cv, cf = box_cage((-0.2, -0.2, 1.0), (0.2, 0.2, 2.0))
    with open(small, "w") as fh:
        fh.writelines(f"v {x} {y} {z}\n" for x, y, z in cv)
        fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in cf)
    win.editing.load_cage(str(small))
    assert win.last_error and "does not enclose" in win.last_error
    assert win.ctrl.cage is cage_before
    # a constraint outside the cage is refused
    win.last_error = None
    with pytest.raises(Exception, match="outside the cage"):
        win.ctrl.add_position_constraint([50.0, 0, 0])
    # impossible constraints (same point, two targets): a message; deleting one recovers
    c0 = win.ctrl.positions[0]
    win.ctrl.add_position_constraint(c0.point, target=c0.target + 1.0)
    with win.waiting_for_jobs():
        win.editing.after_edit(structure=False)
    assert win.last_error and "ConstraintError" in win.last_error
    with win.waiting_for_jobs():
        win.editing.delete_constraint("position", len(win.ctrl.positions) - 1)
    assert win.ctrl.ready
    # the app still works: a drag deforms the shape
    win.last_error = None
    w = win.shape_view.handles[-1]
    w.SetCenter(*(win.ctrl.positions[-1].target + [0.2, 0, 0]))
    w.InvokeEvent("InteractionEvent")
    assert win.last_error is None
    assert np.abs(win.ctrl.deformed_points - before).max() > 0.05


def test_cancel_releases_the_ui(window):
    import threading

    win = window
    _open_bar(win, "bend-90")
    release = threading.Event()

    def slow(progress, cancelled):
        for k in range(200):
            if cancelled():
                from vhm_viz.app.controller import Cancelled

                raise Cancelled()
            progress(k / 200, "working")
            release.wait(0.01)
        return "done"

    results = []
    assert win.run_job("slow", slow, results.append)
    assert win.busy and win.progress.isVisible() is True
    win.cancel_job()
    assert not win.busy and not win.progress.isVisible()
    win.runner.wait(5000)
    assert results == []


def test_cli_explore_registered():
    from vhm_viz.cli import build_parser

    args = build_parser().parse_args(["explore", "mesh.obj", "--scene", "s.json"])
    assert args.command == "explore" and args.file == "mesh.obj" and args.scene == "s.json"


def test_open_file_generate_cage_anchors_and_drag(window):
    """The file path: open a mesh, generate a cage and anchors in the background, click, drag."""
    win = window
    with win.waiting_for_jobs():
        assert win.open_file(str(data_path("bar", "bar_dense.obj")))
    assert win.last_error is None, win.last_error
    ctrl = win.ctrl
    assert ctrl.display.n_points == 6146 and ctrl.cage is None
    with win.waiting_for_jobs() as jobs:
        win.editing.generate_cage(max_faces=120)
        assert win.busy and len(jobs) == 1  # runs in the worker, with a progress bar
    assert win.last_error is None, win.last_error
    assert ctrl.cage is not None and ctrl.cage.n_faces <= 120
    assert ctrl.cage.contains(ctrl.rest_points).all()
    with win.waiting_for_jobs():
        win.editing.generate_anchors(count=12)
    assert win.last_error is None, win.last_error
    assert len(ctrl.anchors) > 0 and ctrl.cage.contains(ctrl.anchors).all()
    # two clicks: hold one end, grab the other (bar along y in [-1, 4.74])
    win.editing.set_interaction_mode("position")
    win.plotter.view_xy()
    win.plotter.render()
    p = ctrl.rest_points
    for goal in ([0.0, -0.9, 1.0], [0.0, 4.6, 1.0]):
        k = int(np.argmin(np.linalg.norm(p - goal, axis=1)))
        with win.waiting_for_jobs():
            assert win.editing.click_at_display(
                *win.picker.display_coordinates(ctrl.deformed_points[k])
            )
        assert win.last_error is None, win.last_error
    assert len(ctrl.positions) == 2 and ctrl.ready
    np.testing.assert_allclose(ctrl.deformed_points, p, atol=1e-6)  # nothing moved yet
    w = win.shape_view.handles[1]
    w.SetCenter(*(ctrl.positions[1].target + [1.0, 0.0, 0.0]))
    w.InvokeEvent("InteractionEvent")
    w.InvokeEvent("EndInteractionEvent")
    assert win.last_error is None, win.last_error
    assert np.abs(ctrl.deformed_points - p).max() > 0.5
    np.testing.assert_allclose(ctrl.deformed_points, _direct_points(ctrl), atol=5e-4)


def test_drag_shows_the_proxy_and_release_the_full_mesh(window, qtbot):
    """Level of detail: the decimated proxy while dragging, the full shape after release."""
    win = window
    win.ctrl.lod_points, win.ctrl.proxy_triangles = 500, 400  # the bar (1,410 points) is "large"
    ctrl = _open_bar(win, "bend-90")
    assert ctrl.uses_proxy and "proxy" in win.actors
    proxy = ctrl.proxy
    assert 0 < proxy.n_cells <= 450 and proxy.n_cells < ctrl.display.n_cells
    assert not win.shape_view.showing_proxy and "full mesh" in win.lod_label.text()
    before = ctrl.deformed_points.copy()
    # one drag frame through the sphere widget's callback: only the proxy moves
    w = win.shape_view.handles[0]
    goal = ctrl.positions[0].target + np.array([0.2, -0.1, 0.1])
    w.SetCenter(*goal)
    renders = []
    obs = win.plotter.ren_win.AddObserver("EndEvent", lambda *a: renders.append(1))
    w.InvokeEvent("InteractionEvent")
    assert win.last_error is None, win.last_error
    assert not renders  # the callback leaves the render to the widget (one per frame)
    win.plotter.iren.interactor.Render()  # what vtkSphereWidget does after its callback
    win.plotter.ren_win.RemoveObserver(obs)
    assert len(renders) == 1 and win.drag.last_frame.render > 0 and "ms" in win.frame_label.text()
    assert win.drag.last_frame.mesh == "proxy" and win.shape_view.showing_proxy and ctrl.full_stale
    assert "drag proxy" in win.lod_label.text()
    assert win.actors["proxy"].GetVisibility() and not win.actors["shape"].GetVisibility()
    np.testing.assert_array_equal(ctrl.deformed_points, before)  # the full shape waits
    # the proxy shows the map of its rest points at the drag solution (float32 binding)
    expected = ctrl.deformer.harmonic_map.map(ctrl.proxy_rest_points)
    np.testing.assert_allclose(proxy.points, expected, atol=1e-5)
    # release: full shape, solved to convergence, equal to a direct Deformer solve
    w.InvokeEvent("EndInteractionEvent")
    assert win.last_error is None, win.last_error
    assert (
        not win.shape_view.showing_proxy
        and not ctrl.full_stale
        and win.drag.last_frame.mesh == "full"
    )
    assert "full mesh" in win.lod_label.text()
    assert win.actors["shape"].GetVisibility() and not win.actors["proxy"].GetVisibility()
    assert np.abs(ctrl.deformed_points - before).max() > 0.05
    np.testing.assert_allclose(ctrl.deformed_points, _direct_points(ctrl), atol=5e-4)
    # a handle resting without release: the full shape replaces the proxy after a moment
    w.SetCenter(*(goal + [0.05, 0.0, 0.0]))
    w.InvokeEvent("InteractionEvent")
    assert win.shape_view.showing_proxy
    qtbot.waitUntil(lambda: not win.shape_view.showing_proxy, timeout=5000)
    np.testing.assert_allclose(
        ctrl.deformed_points, ctrl.deformer.harmonic_map.map(ctrl.rest_points), atol=1e-5
    )
    # without level of detail the drag deforms the full shape
    ctrl.lod = False
    w.InvokeEvent("InteractionEvent")
    assert win.drag.last_frame.mesh == "full" and not win.shape_view.showing_proxy


def test_make_proxy_surfaces_volumes_and_points():
    import pyvista as pv

    from vhm_viz.app.lod import make_proxy

    sphere = pv.Sphere(theta_resolution=60, phi_resolution=60)  # 6,844 triangles
    p = make_proxy(sphere, 1000)
    assert p.is_all_triangles and 900 <= p.n_cells <= 1000
    assert p.points.dtype == np.float64
    r = np.linalg.norm(p.points, axis=1)  # decimation keeps the points near the surface
    assert np.abs(r - 0.5).max() < 0.02
    tets = pv.ImageData(dimensions=(12, 12, 12)).cast_to_unstructured_grid().triangulate()
    p = make_proxy(tets, 300)
    assert p.n_cells <= 300 and p.GetNumberOfPolys() == p.n_cells
    np.testing.assert_allclose(p.bounds, tets.bounds, atol=1e-9)  # the outer surface
    cloud = pv.PolyData(np.random.default_rng(0).random((5000, 3)))
    p = make_proxy(cloud, 1000)
    assert p.n_points == 500 and p.GetNumberOfPolys() == 0
    np.testing.assert_array_equal(p.points, cloud.points[::10])


def test_display_drops_the_rest_normals(tmp_path):
    """Rest-pose normals would shade the deformed shape wrongly: the display has none."""
    import pyvista as pv

    from vhm_viz.app.controller import ExplorerController

    path = tmp_path / "sphere.vtp"
    pv.Sphere().compute_normals().save(path)
    ctrl = ExplorerController()
    ctrl.load_file(path)
    assert "Normals" in ctrl.rest.point_data
    assert "Normals" not in ctrl.display.point_data
    assert ctrl.display.point_data.active_normals_name is None


def test_certify_action_draws_witnesses_and_the_dock_shows_the_answer(window):
    """Solve > Certify injectivity: runs in the background, draws, reports; a solve clears."""
    win = window
    ctrl = _open_bar(win, "push")
    assert win.certify_action.text().replace("&", "") == "Certify injectivity"
    with win.waiting_for_jobs() as jobs:
        win.certify_action.trigger()
        assert win.busy and [job.name for job in jobs] == ["certify"]
    assert win.last_error is None, win.last_error
    assert ctrl.certificate.status == "not injective"
    assert "witnesses" in win.actors and "undecided" not in win.actors
    assert win.analysis_view.metrics["certificate"] == "not injective"
    assert "certificate: not injective" in win.analysis_panel.metrics.text()
    win.editing.full_solve()
    win.editing.update_analysis()
    assert ctrl.certificate is None and "witnesses" not in win.actors


# ---------------------------------------------------------------------------- analysis dock


def test_solved_bar_fills_the_analysis_dock_and_a_cage_shows_at_once(window, tmp_path):
    win = window
    ctrl = _open_bar(win, "bend-90")
    # the dock shows the solved state right after loading (no other change needed)
    assert "energy" in win.analysis_panel.metrics.text()
    assert win.analysis_panel.energy._lines
    # a loaded cage is drawn by the edit itself: a render happens inside load_cage
    renders = []
    obs = win.plotter.ren_win.AddObserver("EndEvent", lambda *a: renders.append(1))
    path = tmp_path / "cage.obj"
    v, f = np.asarray(ctrl.cage.vertices), np.asarray(ctrl.cage.faces)
    with open(path, "w") as fh:
        fh.writelines(f"v {x} {y} {z}\n" for x, y, z in 1.05 * v)
        fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f)
    with win.waiting_for_jobs():
        win.editing.load_cage(str(path))
        win.plotter.ren_win.RemoveObserver(obs)
        assert win.last_error is None, win.last_error
        assert renders
        cage_pts = np.asarray(win.actors["cage"].mapper.dataset.points)
        np.testing.assert_allclose(cage_pts, 1.05 * v)
    # camera reset frames shape and cage: every cage vertex projects inside the view
    win.frame_all()
    w, h = win.plotter.window_size
    for x in np.asarray(win.ctrl.cage.vertices):
        px, py = win.picker.display_coordinates(x)
        assert 0 <= px < w and 0 <= py < h


def test_undo_redo_delete_of_constraints_and_anchors(window):
    win = window
    ctrl = _open_bar(win, "bend-90", apply=False)  # bottom held only
    rest = ctrl.rest_points
    n0, a0 = len(ctrl.positions), len(ctrl.anchors)
    assert win.undo_action.shortcut().toString() == "Ctrl+Z"
    assert "Ctrl+Shift+Z" in [s.toString() for s in win.redo_action.shortcuts()]
    assert win.delete_action.shortcut().toString() == "Del"
    # add a position constraint at the top (click path), drag it
    k = _click_on_the_y_face(win, ctrl, [0.0, -0.5, 4.5], "position")
    assert len(ctrl.positions) == n0 + 1
    start = ctrl.positions[-1].target.copy()
    w = win.shape_view.handles[-1]
    for step in (0.2, 0.4, 0.6):  # one drag of three frames = one undo step
        w.SetCenter(*(start + [step, 0.0, 0.0]))
        w.InvokeEvent("InteractionEvent")
    w.InvokeEvent("EndInteractionEvent")
    dragged = ctrl.deformed_points.copy()
    np.testing.assert_allclose(dragged, _direct_points(ctrl), atol=5e-4)
    # an anchor edit
    win.editing.set_interaction_mode("anchor-")
    with win.waiting_for_jobs():
        assert win.editing.click_at_display(
            *win.picker.display_coordinates(ctrl.deformed_points[k])
        )
    assert len(ctrl.anchors) == a0 - 1
    # undo: the anchor comes back, then the drag is undone, then the constraint goes
    with win.waiting_for_jobs():
        win.undo_action.trigger()
    assert len(ctrl.anchors) == a0 and win.last_error is None
    np.testing.assert_allclose(ctrl.deformed_points, dragged, atol=5e-4)
    with win.waiting_for_jobs():
        win.undo_action.trigger()
    np.testing.assert_allclose(ctrl.positions[-1].target, start)
    np.testing.assert_allclose(ctrl.deformed_points, rest, atol=1e-4)  # nothing pulled
    with win.waiting_for_jobs():
        win.undo_action.trigger()
    assert len(ctrl.positions) == n0 and len(win.shape_view.handles) == n0
    # redo twice: the constraint and its drag are back, solved as before
    with win.waiting_for_jobs():
        win.redo_action.trigger()
    with win.waiting_for_jobs():
        win.redo_action.trigger()
    assert len(ctrl.positions) == n0 + 1
    np.testing.assert_allclose(ctrl.positions[-1].target, start + [0.6, 0, 0])
    np.testing.assert_allclose(ctrl.deformed_points, dragged, atol=5e-4)
    # Delete removes the constraint selected in the table
    win.constraints_panel.fill(ctrl.positions, ctrl.jacobians)
    win.constraints_panel.table.selectRow(n0)
    with win.waiting_for_jobs():
        win.delete_action.trigger()
    assert len(ctrl.positions) == n0 and win.last_error is None
    np.testing.assert_allclose(ctrl.deformed_points, rest, atol=1e-4)
    with win.waiting_for_jobs():
        win.undo_action.trigger()  # and that is undone too
    assert len(ctrl.positions) == n0 + 1


def test_rotation_gizmo_sets_the_jacobian_target(window):
    from scipy.spatial.transform import Rotation

    win = window
    ctrl, top = _bar_with_a_gizmo(win)
    assert win.gizmo.widget is not None and win.gizmo.widget.GetEnabled()
    np.testing.assert_allclose(win.gizmo.rotation(), np.eye(3), atol=1e-9)
    # the user turns the box 35 degrees about y (the widget's transform), frame by frame
    centre = ctrl.image_of(top)
    for deg in (10, 25, 35):
        _turn_gizmo(win, centre, deg)
    win.gizmo.widget.InvokeEvent("EndInteractionEvent")
    assert win.last_error is None, win.last_error
    expected = Rotation.from_euler("y", 35, degrees=True).as_matrix()
    np.testing.assert_allclose(ctrl.jacobians[0].matrix, expected, atol=1e-9)
    J = ctrl.deformer.harmonic_map.jacobian(top[None])[0]
    np.testing.assert_allclose(J, expected, atol=1e-6)  # the solve follows the gizmo
    np.testing.assert_allclose(ctrl.deformed_points, _direct_points(ctrl), atol=5e-4)
    with win.waiting_for_jobs():
        win.undo_action.trigger()  # one rotation = one undo step
    np.testing.assert_allclose(ctrl.jacobians[0].matrix, np.eye(3), atol=1e-9)


def _grey_levels(img) -> int:
    a = np.asarray(img)[..., :3].astype(int)
    grey = (np.abs(a[..., 0] - a[..., 1]) < 3) & (np.abs(a[..., 1] - a[..., 2]) < 3)
    grey &= a[..., 0] < 235  # not the white background
    return len(np.unique(a[..., 0][grey]))


def test_volume_slices_follow_the_map_and_show_the_data(window):
    win = window
    head = data_path("volumes", "headsq_64x64x93.vti")
    scene = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"
    with win.waiting_for_jobs():
        assert win.open_file(str(head))
    with win.waiting_for_jobs():
        assert win.load_scene(str(scene))
    assert win.last_error is None, win.last_error
    ctrl = win.ctrl
    assert ctrl.volume is not None and ctrl.ready and ctrl.last_report.converged
    # three slices at full resolution (every voxel of the plane), mapped by the solution
    hm = ctrl.deformer.harmonic_map
    for axis, e in win.volume_display.slices.items():
        full = e["full"]
        n = [d for a, d in enumerate(ctrl.volume.dimensions) if a != axis]
        assert full.n_points == n[0] * n[1]
        assert win.actors[f"vslice{axis}full"].GetVisibility()
        ref = hm.map(full.rest_points, outside="passthrough")
        np.testing.assert_allclose(full.mesh.points, ref, atol=1e-3)
        vals = np.asarray(full.mesh.point_data["value"])
        assert len(np.unique(vals)) > 100  # CT values, not a flat box
    win.frame_all()
    img = win.screenshot(False)
    assert _grey_levels(img) > 60
    # drag the target: the drag slices follow each frame, the full ones on release
    w = win.shape_view.handles[-1]
    goal = ctrl.positions[-1].target + np.array([-10.0, 0.0, 5.0])
    w.SetCenter(*goal)
    w.InvokeEvent("InteractionEvent")
    assert win.last_error is None, win.last_error
    assert win.actors["vslice2drag"].GetVisibility()
    drag = win.volume_display.slices[2]["drag"]
    np.testing.assert_allclose(
        drag.mesh.points, ctrl.deformer.harmonic_map.map(drag.rest_points, outside="passthrough"),
        atol=1e-6,
    )  # fmt: skip
    w.InvokeEvent("EndInteractionEvent")
    full = win.volume_display.slices[2]["full"]
    assert win.actors["vslice2full"].GetVisibility()
    np.testing.assert_allclose(
        full.mesh.points, ctrl.deformer.harmonic_map.map(full.rest_points, outside="passthrough"),
        atol=1e-3,
    )  # fmt: skip
    # det J on the same slices, in the colours' convention; the histogram counts all
    from vhm_viz.colours import det_range

    win.view_panel.slice_colour.setCurrentText("determinant")
    drag = win.volume_display.slices[0]["drag"]
    det = np.linalg.det(ctrl.deformer.harmonic_map.jacobian(drag.rest_points))
    inside = ctrl.cage.contains(drag.rest_points)
    np.testing.assert_allclose(drag.mesh.point_data["measure"][inside], det[inside], rtol=1e-5)
    shown = np.asarray(drag.mesh.point_data["shown"])
    slices = win.volume_display.slices
    lo, hi = det_range(np.concatenate(
        [np.asarray(e["drag"].mesh.point_data["measure"]) for e in slices.values()]
    ))  # fmt: skip
    assert shown.min() >= lo * 0.5 - 1e-12 and shown.max() <= hi + 1e-12
    hist = win.analysis_panel.histogram._bars
    assert hist.total == sum(e["drag"].n_points for e in win.volume_display.slices.values())
    # move a slice: the new plane, at full resolution once the slider rests
    win.view_panel.slice_sliders[2].setValue(20)
    win.volume_display.finish_slice_move()
    assert ctrl.volume.index[2] == 20
    z = ctrl.volume.grid_points(np.array([[0, 0, 20]]))[0, 2]
    np.testing.assert_allclose(win.volume_display.slices[2]["full"].rest_points[:, 2], z)
    # volume rendering and an isosurface of the deformed volume
    with win.waiting_for_jobs():
        win.view_panel.volume.setChecked(True)
    assert win.last_error is None, win.last_error
    assert "volume" in win.actors and win.volume_display.image is not None
    level, width, opacity = 1000.0, 400.0, 0.5
    win.view_panel.set_transfer(level, width, opacity)
    otf = win.actors["volume"].GetProperty().GetScalarOpacity()
    lvl, wid, op = win.view_panel.transfer
    assert otf.GetValue(lvl - wid / 2 - 1) == pytest.approx(0.0)
    assert otf.GetValue(lvl + wid / 2 + 1) == pytest.approx(op, abs=1e-6)
    assert otf.GetValue(lvl) == pytest.approx(op / 2, abs=0.02)
    win.view_panel.iso_value.setValue(win.view_panel.step_of(1000.0))
    win.view_panel.iso.setChecked(True)
    assert "iso" in win.actors and win.actors["iso"].mapper.dataset.n_points > 100


def test_the_isosurface_follows_its_slider_moved_by_keys_and_by_dragging(window):
    """The contour is redrawn at the slider's value however the slider moved."""
    from PySide6.QtCore import Qt
    from PySide6.QtTest import QTest

    win = window
    with win.waiting_for_jobs():
        assert win.open_file(str(data_path("volumes", "headsq_64x64x93.vti")))
    vp = win.view_panel
    with win.waiting_for_jobs():
        vp.iso.setChecked(True)
    assert win.last_error is None, win.last_error
    image = win.volume_display.image

    def shown_matches_slider():
        expected = image.contour([vp.value_of(vp.iso_value.value())], scalars="values")
        shown = win.actors["iso"].mapper.dataset
        return shown.n_points == expected.n_points and np.allclose(shown.points, expected.points)

    assert shown_matches_slider()
    before = win.actors["iso"].mapper.dataset.n_points
    # keys (what the wheel and a click on the groove do too): one contour per step
    vp.iso_value.setFocus()
    QTest.keyClick(vp.iso_value, Qt.Key.Key_PageUp)
    QTest.keyClick(vp.iso_value, Qt.Key.Key_PageUp)
    assert win.actors["iso"].mapper.dataset.n_points != before
    assert shown_matches_slider()
    # a dragged handle: the contour waits for the release, then shows the new value
    shown = win.actors["iso"]
    vp.iso_value.setSliderDown(True)
    vp.iso_value.setSliderPosition(vp.step_of(1000.0))
    assert win.actors["iso"] is shown
    vp.iso_value.setSliderDown(False)
    assert vp.iso_value.value() == vp.step_of(1000.0)
    assert shown_matches_slider()


def test_a_drag_during_a_background_job_never_leaves_the_handle_off_its_target(window):
    """A volume's resampling gives way to a drag; another job refuses it, handle unmoved."""
    import threading

    win = window
    with win.waiting_for_jobs():
        assert win.open_file(str(data_path("volumes", "headsq_64x64x93.vti")))
    scene = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"
    with win.waiting_for_jobs():
        assert win.load_scene(str(scene))
    with win.waiting_for_jobs():
        win.view_panel.volume.setChecked(True)
    assert win.last_error is None, win.last_error
    ctrl, w = win.ctrl, win.shape_view.handles[-1]
    # a drag released: the deformed volume is resampled in the background
    first = ctrl.positions[-1].target + np.array([-10.0, 0.0, 5.0])
    w.SetCenter(*first)
    w.InvokeEvent("InteractionEvent")
    w.InvokeEvent("EndInteractionEvent")
    assert win.busy and win.runner.job.name == "volume rendering"
    # the next drag at once: it moves the target, and its release resamples again
    second = first + np.array([-10.0, 0.0, 5.0])
    with win.waiting_for_jobs():
        w.SetCenter(*second)
        w.InvokeEvent("InteractionEvent")
        w.InvokeEvent("EndInteractionEvent")
    assert win.last_error is None, win.last_error
    np.testing.assert_allclose(ctrl.positions[-1].target, second)
    np.testing.assert_allclose(w.GetCenter(), second)
    hm = ctrl.deformer.harmonic_map
    np.testing.assert_allclose(ctrl.image_of(ctrl.positions[-1].point), second, atol=1e-6)
    expected = ctrl.volume.deformed_image(hm)
    np.testing.assert_allclose(win.volume_display.image["values"], expected["values"])
    # another job runs: the drag is refused and the handle goes back onto its target
    release = threading.Event()
    assert win.run_job("slow", lambda progress, cancelled: release.wait(30), lambda r: None)
    w.SetCenter(*(second + [5.0, 0.0, 0.0]))
    w.InvokeEvent("InteractionEvent")
    w.InvokeEvent("EndInteractionEvent")
    np.testing.assert_allclose(ctrl.positions[-1].target, second)
    np.testing.assert_allclose(w.GetCenter(), second)
    assert "busy" in win.statusBar().currentMessage()
    release.set()
    win.runner.wait(30000)


def test_a_turn_refused_during_a_background_job_turns_the_gizmo_back(window):
    import threading

    win = window
    ctrl, top = _bar_with_a_gizmo(win)
    before = ctrl.jacobians[0].matrix.copy()
    release = threading.Event()
    assert win.run_job("slow", lambda progress, cancelled: release.wait(30), lambda r: None)
    _turn_gizmo(win, ctrl.image_of(top), 30)
    assert "busy" in win.statusBar().currentMessage()
    win.gizmo.widget.InvokeEvent("EndInteractionEvent")
    np.testing.assert_allclose(ctrl.jacobians[0].matrix, before)  # the target is unchanged
    np.testing.assert_allclose(win.gizmo.rotation(), before, atol=1e-9)  # and so is the box
    release.set()
    win.runner.wait(30000)


def _run_cli(*args, timeout=600):
    import sys

    from tests.conftest import subprocess_env

    env = subprocess_env()
    env.pop("DISPLAY", None)  # the command starts its own X server
    env.pop("QT_QPA_PLATFORM", None)
    return subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", *args], capture_output=True, text=True,
        env=env, timeout=timeout,
    )  # fmt: skip


def test_screenshot_command_head_volume_and_errors(tmp_path):
    head = data_path("volumes", "headsq_64x64x93.vti")
    scene = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"
    out = tmp_path / "head.png"
    r = _run_cli("explore", str(head), "--scene", str(scene), "--screenshot", str(out),
                 "--size", "640", "480")  # fmt: skip
    assert r.returncode == 0, r.stderr
    from PIL import Image

    img = np.asarray(Image.open(out))
    assert img.shape[:2] == (480, 640)
    assert _grey_levels(img) > 60  # the CT's grey levels inside, not an opaque box
    assert [p.name for p in tmp_path.iterdir()] == ["head.png"]  # no temporary left
    # bad input: one line, non-zero exit, nothing written
    bad = tmp_path / "bad.png"
    r = _run_cli("explore", str(tmp_path / "missing.vti"), "--screenshot", str(bad))
    assert r.returncode != 0 and not bad.exists()
    assert len(r.stderr.strip().splitlines()) == 1 and "missing.vti" in r.stderr
    r = _run_cli("explore", "--help")
    help_text = " ".join(r.stdout.split())
    assert "(default: 1200 900)" in help_text and "(default: none" in help_text


def test_screenshot_colour_without_a_solved_map_is_refused(tmp_path):
    """--colour asks for a section coloured by the map's det J or cond J: for data
    without a solved map (no scene) the command says so in one line and writes nothing,
    rather than a plain grey picture."""
    import pyvista as pv

    tets = tmp_path / "tets.vtu"
    pv.ImageData(dimensions=(4, 4, 4)).cast_to_unstructured_grid().triangulate().save(tets)
    out = tmp_path / "tets.png"
    r = _run_cli("explore", str(tets), "--colour", "determinant", "--screenshot", str(out),
                 "--size", "320", "240")  # fmt: skip
    assert r.returncode == 1 and not out.exists()
    assert r.stderr.strip().splitlines()[-1] == (
        "vhm-viz explore: error: --colour determinant: no solved map to colour by (give a "
        "--scene, or --bar)"
    )


def _constrain(ctrl, sc) -> None:
    """A bar scenario's cage, anchors and position constraints on loaded data."""
    ctrl.set_cage(sc.cage)
    ctrl.set_anchors(sc.anchors)
    for p, t in zip(sc.constraints["positions"], sc.constraints["targets"], strict=True):
        ctrl.add_position_constraint(p, t)


def test_screenshot_command_tet_mesh_coloured_by_det(tmp_path):
    from tests.test_explorer_analysis import bar_tet_file
    from vhm_viz import examples
    from vhm_viz.app.controller import ExplorerController

    bar_tet_file(tmp_path / "bar.vtu")
    sc = examples.bar("bend-90", resolution=8)
    ctrl = ExplorerController()
    ctrl.load_file(tmp_path / "bar.vtu")
    _constrain(ctrl, sc)
    ctrl.prepare()
    ctrl.settle(init="identity")
    ctrl.save_scene(tmp_path / "scene.json")
    out = tmp_path / "bar.png"
    r = _run_cli("explore", "--scene", str(tmp_path / "scene.json"), "--colour", "determinant",
                 "--screenshot", str(out), "--size", "640", "480")  # fmt: skip
    assert r.returncode == 0, r.stderr
    from PIL import Image

    img = np.asarray(Image.open(out))[..., :3].astype(int)
    # coolwarm: saturated blue (det < 1) and red (det > 1) pixels of the section
    blue = img[..., 2] - img[..., 0] > 60
    red = img[..., 0] - img[..., 2] > 60
    assert blue.sum() > 200 and red.sum() > 200, (blue.sum(), red.sum())


def test_explorer_save_of_a_200_iteration_scene_converges_in_the_cli(tmp_path):
    """A scene written with max_iterations 200 is settled and saved with settings under
    which `vhm-viz deform` converges to the explorer's result."""
    import json

    from vhm_viz import examples
    from vhm_viz.app.controller import ExplorerController

    sc = examples.bar("bend-90", resolution=8)
    sc.surface.save(tmp_path / "bar.vtp")
    ctrl = ExplorerController()
    ctrl.load_file(tmp_path / "bar.vtp")
    _constrain(ctrl, sc)
    ctrl.solver["max_iterations"] = 200
    ctrl.save_scene(tmp_path / "s200.json")
    assert json.loads((tmp_path / "s200.json").read_text())["solver"]["max_iterations"] == 200
    ex = ExplorerController()
    ex.load_scene(tmp_path / "s200.json")
    ex.prepare()
    rep = ex.settle(init="identity")
    assert rep.converged
    ex.deform()
    ex.export(tmp_path / "explorer.vtp")
    ex.save_scene(tmp_path / "saved.json")
    solver = json.loads((tmp_path / "saved.json").read_text())["solver"]
    assert solver["max_iterations"] >= rep.iterations  # what it solved with
    r = _run_cli("deform", str(tmp_path / "bar.vtp"), "--scene", str(tmp_path / "saved.json"),
                 "-o", str(tmp_path / "cli.vtp"), "-q")  # fmt: skip
    assert r.returncode == 0, r.stderr  # converged: no --allow-unconverged needed
    import pyvista as pv

    np.testing.assert_allclose(
        pv.read(tmp_path / "cli.vtp").points, pv.read(tmp_path / "explorer.vtp").points,
        atol=1e-9,
    )  # fmt: skip
