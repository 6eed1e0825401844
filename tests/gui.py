"""Fixtures for tests of the Qt explorer under a real X display (Xvfb).

A module imports them (``from tests.gui import xvfb_display, window, ...``): the session
fixture starts ``Xvfb`` when no display is set and makes Qt use it (``xcb``), overriding
``.ci/run``'s ``QT_QPA_PLATFORM=offscreen`` for the modules that import it.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

RES = 8  # bar resolution of the tests (1,410 surface points: fast bindings)


def _start_xvfb():
    from vhm_viz.app import start_xvfb

    # -terminate: the server exits when the test process (its last client) does, so Qt
    # never sees its display vanish while the QApplication is alive
    return start_xvfb()


@pytest.fixture(scope="session", autouse=True)
def xvfb_display():
    """A real X display for Qt and VTK: the current one, or a fresh Xvfb."""
    from PySide6.QtWidgets import QApplication

    old = {k: os.environ.get(k) for k in ("DISPLAY", "QT_QPA_PLATFORM")}
    proc = None
    if QApplication.instance() is None:
        if not os.environ.get("DISPLAY"):
            proc, display = _start_xvfb()
            if proc is None:
                pytest.skip("no X display and Xvfb not found (apt-get install xvfb)")
            os.environ["DISPLAY"] = display
        os.environ["QT_QPA_PLATFORM"] = "xcb"
    yield os.environ.get("DISPLAY")
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    if proc is not None and QApplication.instance() is None:
        proc.terminate()  # never connected: nothing will make it exit by itself


@pytest.fixture(scope="module", autouse=True)
def single_threaded_blas():
    """BLAS on one thread, as the explorer runs it (vhm_viz.app.run), in this module only.

    Rounding, and with it iteration counts, depend on BLAS's threads: the limit must not
    leak into the tests of other modules.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


@pytest.fixture
def window(qtbot):
    from vhm_viz.app.window import ExplorerWindow

    win = ExplorerWindow(dialogs=False)
    qtbot.addWidget(win)
    win.resize(1000, 700)
    win.show()
    qtbot.waitExposed(win)
    yield win
    win.runner.wait(60000)
    win.close()


def open_bar(win, kind="bend-90", apply=True):
    """Open the bundled bar ``kind`` in ``win`` and wait until it is solved and shown."""
    with win.waiting_for_jobs():
        assert win.open_bar(kind, resolution=RES, apply=apply)
    assert win.last_error is None, win.last_error
    assert win.ctrl.ready
    return win.ctrl


def bar_with_a_gizmo(win):
    """The bar bent 90 degrees, a Jacobian constraint near its top and its gizmo shown."""
    ctrl = open_bar(win, "bend-90", apply=False)
    top = ctrl.rest_points[np.argmax(ctrl.rest_points[:, 2])] * [0, 0, 0.9]
    with win.editing.recorded():
        ctrl.add_jacobian_constraint(top)
    win.gizmo.index = 0
    with win.waiting_for_jobs():
        win.editing.after_edit(structure=False)
    return ctrl, top
