"""Long sessions: the explorer's autosave and crash recovery, and memory that stays flat.

A real explorer process is killed with SIGKILL and the next window offers and restores its
scene; thousands of drag steps and hundreds of filter re-executions must not grow the
process's resident memory.
"""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.conftest import box_cage, subprocess_env

pytest.importorskip("PySide6")
pytest.importorskip("pyvistaqt")
pytest.importorskip("pytestqt")

from tests.gui import single_threaded_blas, window, xvfb_display  # noqa: E402, F401
from vhm_viz.app.autosave import recoverable  # noqa: E402
from vhm_viz.scene import Scene  # noqa: E402

RES = 8  # bar resolution (1,410 surface points)
GROWTH_LIMIT_MB = 50.0


def _resident_mb() -> float:
    """The process's resident memory now (not its peak), in MiB."""
    gc.collect()
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _open_bar(win, kind="bend-u"):
    with win.waiting_for_jobs():
        assert win.open_bar(kind, resolution=RES)
    assert win.last_error is None, win.last_error
    return win.ctrl


def _targets(scene: Scene) -> np.ndarray:
    return np.asarray(scene.constraints["targets"], dtype=float)


def test_autosave_writes_the_scene_when_it_changes(window, tmp_path):
    win = window
    ctrl = _open_bar(win)
    win.start_autosave(tmp_path, interval_s=3600)  # written on demand below
    assert win.save_now()
    saved = Scene.load(win.autosave.path)
    np.testing.assert_allclose(_targets(saved), _targets(ctrl.scene_to_save()))
    assert not win.save_now()  # nothing changed: nothing written
    moved = ctrl.positions[0].target + [0.1, 0.0, -0.05]
    ctrl.set_target(0, moved)
    assert win.save_now()
    np.testing.assert_allclose(_targets(Scene.load(win.autosave.path))[0], moved)
    # the running session's own file is not offered as left over
    assert recoverable(tmp_path) == []


def test_a_killed_explorer_s_scene_is_offered_and_recovered(window, qtbot, tmp_path):
    from vhm_viz.app.window import ExplorerWindow

    ctrl = _open_bar(window)
    ctrl.set_target(0, ctrl.positions[0].target + [0.15, 0.0, 0.05])
    scene_file = tmp_path / "edited.json"
    ctrl.save_scene(scene_file)
    expected = _targets(Scene.load(scene_file))

    state = tmp_path / "state"
    env = subprocess_env()
    env.update(VHM_STATE_DIR=str(state), QT_QPA_PLATFORM="xcb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "vhm_viz.app", "--scene", str(scene_file)],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    autosave = state / "autosave" / f"explorer-{proc.pid}.json"
    try:
        deadline = time.monotonic() + 300
        while not autosave.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert autosave.exists(), proc.stderr.read().decode() if proc.poll() is not None else ""
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        proc.stderr.close()

    folder = state / "autosave"
    assert recoverable(folder) == [autosave]
    win = ExplorerWindow(dialogs=False)
    qtbot.addWidget(win)
    win.show()
    win.start_autosave(folder, interval_s=3600)
    assert win.offer_recovery() == [autosave]
    with win.waiting_for_jobs():
        assert win.recover(autosave)
    assert win.last_error is None, win.last_error
    np.testing.assert_allclose(_targets(win.ctrl.scene_to_save()), expected, atol=1e-12)
    # the recovered scene is now this session's autosave: nothing left over is offered
    assert not autosave.exists() and win.autosave.path.exists()
    assert recoverable(folder) == []
    win.runner.wait(60000)
    win.close()
    assert not win.autosave.path.exists()  # a normal close leaves nothing behind


def test_memory_stays_flat_over_5000_drag_steps():
    from vhm_viz.app.controller import ExplorerController

    ctrl = ExplorerController()
    ctrl.load_bar("bend-u", resolution=RES)
    ctrl.prepare()
    ctrl.settle()
    start = ctrl.positions[0].target.copy()

    def drag(i: int) -> None:
        ctrl.drag(0, start + 0.08 * np.array([np.sin(i / 40), 0.0, np.cos(i / 55) - 1.0]))

    for i in range(300):  # warm: the solver's and the binding's buffers exist
        drag(i)
    before = _resident_mb()
    for i in range(300, 5300):
        drag(i)
    growth = _resident_mb() - before
    assert growth <= GROWTH_LIMIT_MB, f"resident memory grew {growth:.1f} MB over 5,000 drags"
    # the drags really moved the shape
    assert np.abs(ctrl.deformed_points - ctrl.rest_points).max() > 0.05


def test_memory_stays_flat_over_200_re_executions_of_each_filter():
    import pyvista as pv

    from vhm_viz import Cage, HarmonicMap
    from vhm_viz.filters import (
        HarmonicDeformationFilter,
        HarmonicResampleFilter,
        JacobianAnalysisFilter,
        update,
    )

    # a small image: each resample builds the pull-back lattice of a new map
    image = pv.ImageData(dimensions=(10, 10, 10), spacing=(0.09,) * 3, origin=(-0.42,) * 3)
    image.point_data["density"] = np.sin(5 * image.points).sum(axis=1)
    surface = pv.Sphere(radius=0.35, theta_resolution=30, phi_resolution=20)
    cage = Cage(*box_cage((-0.6,) * 3, (0.6,) * 3, 2))
    rest = np.array(HarmonicMap.identity(cage).coefficients)
    rng = np.random.default_rng(0)

    def new_map() -> HarmonicMap:  # what a drag in ParaView or the explorer hands the filter
        return HarmonicMap(cage, rest + 0.01 * rng.standard_normal(rest.shape))

    for make, data in (
        (HarmonicDeformationFilter, surface),
        (HarmonicResampleFilter, image),
        (JacobianAnalysisFilter, surface),
    ):
        flt = make()
        flt.SetInputData(data)
        for _ in range(20):
            flt.SetHarmonicMap(new_map())
            update(flt)
        before = _resident_mb()
        for _ in range(200):
            flt.SetHarmonicMap(new_map())
            out = pv.wrap(update(flt))
        growth = _resident_mb() - before
        assert out.n_points == data.n_points or make is HarmonicResampleFilter
        assert growth <= GROWTH_LIMIT_MB, f"{make.__name__}: grew {growth:.1f} MB in 200 runs"
