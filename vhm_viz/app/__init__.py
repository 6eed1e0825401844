"""The Qt desktop explorer (``vhm-viz explore``, ``python -m vhm_viz.app``).

:class:`~vhm_viz.app.controller.ExplorerController` holds the state without Qt;
:class:`~vhm_viz.app.window.ExplorerWindow` is the PySide6 + pyvistaqt window.
Qt is imported only by :func:`main` and the window module: the functions here import it
(and the window) when called, so that the command line starts without it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from vhm_viz import interrupts
from vhm_viz.atomic import atomic_path
from vhm_viz.colours import MEASURES
from vhm_viz.core.threads import limit_blas_threads
from vhm_viz.examples import BAR_KINDS, FOLD_KINDS

__all__ = ["main", "ExplorerController", "start_xvfb"]


def __getattr__(name: str):
    if name == "ExplorerController":
        from vhm_viz.app.controller import ExplorerController

        return ExplorerController
    if name == "ExplorerWindow":
        from vhm_viz.app.window import ExplorerWindow

        return ExplorerWindow
    raise AttributeError(f"module 'vhm_viz.app' has no attribute {name!r}")


def main(argv: list[str] | None = None) -> int:
    """Open the explorer window; ``argv``: ``[FILE] [--scene SCENE] [--bar KIND]``."""
    parser = argparse.ArgumentParser(prog="python -m vhm_viz.app", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


def add_arguments(parser) -> None:
    """Arguments shared with ``vhm-viz explore``."""
    parser.add_argument(
        "file",
        nargs="?",
        metavar="FILE",
        help="data file to open (any format vhm_viz.read_dataset reads, scans in ITK's LPS "
        "frame; default: none)",
    )
    parser.add_argument("--scene", help="scene file (.json) to open and solve (default: none)")
    parser.add_argument("--cage", help="cage file to load after the data (default: none)")
    parser.add_argument(
        "--bar",
        metavar="KIND",
        choices=BAR_KINDS + FOLD_KINDS,
        help=f"open a bundled bar scenario ({', '.join(BAR_KINDS + FOLD_KINDS)}; default: none)",
    )
    parser.add_argument(
        "--screenshot",
        metavar="PNG",
        help="render one frame of what FILE/--scene open (solved) to this PNG file and exit "
        "without showing a window (default: open the interactive window)",
    )
    parser.add_argument(
        "--size",
        nargs=2,
        type=int,
        metavar=("W", "H"),
        default=(1200, 900),
        help="with --screenshot: the image size in pixels (default: 1200 900)",
    )
    parser.add_argument(
        "--colour",
        choices=("none", *MEASURES),
        default="none",
        help="with --screenshot: colour the slices (a volume's orthogonal slices, or a "
        "section of other data, which needs a solved map: a --scene or --bar) by det J or "
        "cond J (default: none, the data's values)",
    )


def run(args) -> int:
    """Start Qt, open what ``args`` names, run the event loop; returns the exit status.

    0 when the window is closed, 130/143 after SIGINT/SIGTERM.
    """
    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication

    from vhm_viz.app.window import ExplorerWindow

    if getattr(args, "screenshot", None):
        return screenshot(args)
    limit_blas_threads()

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
            with win.waiting_for_jobs(float("inf")):
                win.open_file(args.file)
            if args.cage:
                win.editing.load_cage(args.cage)
        elif args.bar:
            with win.waiting_for_jobs(float("inf")):
                win.open_bar(args.bar)
        if args.scene:  # applies to FILE unless the scene's sidecar names its data
            win.load_scene(args.scene)
        # the edited scene is kept on disk while the session runs; one left by a session
        # that crashed or was killed is offered back
        win.start_autosave()
        win.offer_recovery()
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


def screenshot(args) -> int:
    """``--screenshot PNG``: open, solve, render one frame to ``PNG`` (atomically), exit 0.

    Renders off screen (Qt's ``offscreen`` platform when no display is set). Errors (a
    missing or unreadable file, a scene that cannot be solved) raise ``ValueError`` with
    one line, which the command line prints.
    """
    if not (args.file or args.bar or args.scene):
        raise ValueError("--screenshot needs FILE, --bar or --scene")
    w, h = (int(v) for v in args.size)
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ValueError(f"--size must be between 16 and 8192 pixels; got {w} {h}")
    out = Path(args.screenshot)
    if out.suffix.lower() != ".png":
        raise ValueError(f"--screenshot writes PNG: {out.name} does not end in .png")
    for name in (args.file, args.scene, args.cage):
        if name and not Path(name).is_file():
            raise ValueError(f"{name}: no such file")
    if not os.environ.get("DISPLAY"):
        # VTK needs an OpenGL context: a private X server gives one (it exits with its
        # last client, after Qt has closed its connection)
        proc, display = start_xvfb()
        if proc is None:
            raise ValueError("--screenshot needs an X display: set DISPLAY or install Xvfb")
        os.environ["DISPLAY"] = display
        os.environ["QT_QPA_PLATFORM"] = "xcb"
    from PySide6.QtWidgets import QApplication

    from vhm_viz.app.window import ExplorerWindow
    from vhm_viz.io import refuse_inputs

    refuse_inputs(out, [Path(p) for p in (args.file, args.scene, args.cage) if p])
    limit_blas_threads()
    app = QApplication.instance() or QApplication(sys.argv[:1])  # noqa: F841 - kept alive
    win = ExplorerWindow(dialogs=False)
    try:
        win.plotter.interactor.setFixedSize(w, h)  # the 3D view, docks around it
        win.show()
        app.processEvents()

        def step(action, what: str, needs_job: bool = True) -> None:
            # wait for the jobs the action started (and those they start: the rendering)
            with win.waiting_for_jobs(600):
                job = action()
            if win.last_error or needs_job and job is None:
                raise ValueError(f"{what}: {win.last_error or 'failed'}")

        if args.file:
            step(lambda: win.open_file(args.file), Path(args.file).name)
            if args.cage:
                step(lambda: win.editing.load_cage(args.cage), Path(args.cage).name, False)
        elif args.bar:
            step(lambda: win.open_bar(args.bar), f"bar {args.bar}")
        if args.scene:
            step(lambda: win.load_scene(args.scene), Path(args.scene).name)
        if args.colour != "none":
            if win.ctrl.volume is None and not win.ctrl.ready:  # a section needs a map
                raise ValueError(
                    f"--colour {args.colour}: no solved map to colour by (give a --scene, or --bar)"
                )
            step(lambda: win.colour_by(args.colour), "colour", False)
        win.frame_all()
        img = win.screenshot(False)
        if img is None:
            raise ValueError(f"no image rendered: {win.last_error}")
        from PIL import Image

        with atomic_path(out) as tmp:
            Image.fromarray(img).save(tmp, format="PNG")
    finally:
        win.runner.wait(60000)
        win.close()
    return 0


def start_xvfb(first: int = 99, last: int = 170, terminate: bool = True):
    """Start a private Xvfb server; returns ``(process, ":N")`` or ``(None, None)``.

    ``terminate``: the server exits with its last client (``-terminate``).
    """
    exe = shutil.which("Xvfb")
    if exe is None:
        return None, None
    for num in range(first, last):
        if Path(f"/tmp/.X{num}-lock").exists():
            continue
        cmd = [exe, f":{num}", "-screen", "0", "1920x1200x24", "-nolisten", "tcp"]
        proc = subprocess.Popen(
            cmd + (["-terminate"] if terminate else []),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for _ in range(100):
            if Path(f"/tmp/.X11-unix/X{num}").exists():
                return proc, f":{num}"
            if proc.poll() is not None:
                break
            time.sleep(0.05)
        proc.kill()
    return None, None
