"""Fixtures for tests of the Qt explorer under a real X display (Xvfb).

A module imports them (``from tests.gui import xvfb_display, window, ...``): the session
fixture starts ``Xvfb`` when no display is set and makes Qt use it (``xcb``), overriding
``.ci/run``'s ``QT_QPA_PLATFORM=offscreen`` for the modules that import it.
"""

from __future__ import annotations

import os

import pytest


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
