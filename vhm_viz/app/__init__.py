"""The Qt desktop explorer (``vhm-viz explore``, ``python -m vhm_viz.app``).

:class:`~vhm_viz.app.controller.ExplorerController` holds the state without Qt;
:class:`~vhm_viz.app.main_window.ExplorerWindow` is the PySide6 + pyvistaqt window.
Qt is imported only by :func:`main` and the window module.
"""

from __future__ import annotations

__all__ = ["main", "ExplorerController"]


def __getattr__(name: str):
    if name == "ExplorerController":
        from vhm_viz.app.controller import ExplorerController

        return ExplorerController
    if name == "ExplorerWindow":
        from vhm_viz.app.main_window import ExplorerWindow

        return ExplorerWindow
    raise AttributeError(f"module 'vhm_viz.app' has no attribute {name!r}")


def main(argv: list[str] | None = None) -> int:
    """Open the explorer window; ``argv``: ``[FILE] [--scene SCENE] [--bar KIND]``."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m vhm_viz.app", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


def add_arguments(parser) -> None:
    """Arguments shared with ``vhm-viz explore``."""
    parser.add_argument("file", nargs="?", help="data file to open (any format pyvista reads)")
    parser.add_argument("--scene", help="scene file (.json) to open")
    parser.add_argument("--cage", help="cage file to load after the data")
    parser.add_argument(
        "--bar", metavar="KIND", help="open a bundled bar scenario (bend-u, bend-90, twist, bulge)"
    )


def run(args) -> int:
    """Start Qt, open what ``args`` names, run the event loop; returns the exit status.

    0 when the window is closed, 130/143 after SIGINT/SIGTERM.
    """
    import os
    import sys

    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication
    from threadpoolctl import threadpool_limits

    from vhm_viz import interrupts
    from vhm_viz.app.main_window import ExplorerWindow

    # The explorer's linear algebra is small (QR of a few hundred columns, products with
    # 3 columns) but runs next to Qt, VTK, a worker thread and numba's parallel kernels;
    # OpenBLAS's spinning pool then fights them for the cores (a 3138 x 314 QR measured
    # 1-6 s with the default pool under load, 0.11 s with one thread).
    threadpool_limits(limits=int(os.environ.get("VHM_BLAS_THREADS", "1")), user_api="blas")

    app = QApplication.instance() or QApplication(sys.argv[:1])

    def on_signal(signum: int) -> None:
        # leave the event loop (now, or as soon as it runs) with 128 + the signal number
        QTimer.singleShot(0, lambda: app.exit(128 + signum))

    # SIGINT/SIGTERM from here on: jobs see cancelled() and stop at their next chunk, the
    # window closes, the status is 130/143
    with interrupts.handled(on_signal=on_signal):
        win = ExplorerWindow()
        win.show()
        if args.file:
            win.open_file(args.file)
            win.wait_idle()
            if args.cage:
                win.load_cage(args.cage)
        elif args.bar:
            win.open_bar(args.bar)
            win.wait_idle()
        if args.scene:  # applies to FILE unless the scene's sidecar names its data
            win.load_scene(args.scene)
        # Python runs signal handlers only between its own instructions, which a Qt event
        # loop waiting in C++ never executes: a timer gives it the chance every 200 ms
        tick = QTimer()
        tick.timeout.connect(lambda: None)
        tick.start(200)
        # a signal during start-up may have asked the loop to exit before it ran
        signum = interrupts.pending()
        status = 128 + signum if signum is not None else int(app.exec())
        tick.stop()
        win.runner.wait()
    return status
