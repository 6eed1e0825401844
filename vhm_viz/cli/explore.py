"""``vhm-viz explore [FILE] [--scene SCENE] [--screenshot PNG]``: the Qt desktop explorer."""

from __future__ import annotations

#: What ``--timings`` reports, besides "other".
TIMING_STAGES = "explorer (the window open)"

HELP = "open the interactive Qt explorer"

DESCRIPTION = (
    "Open a mesh, tet mesh, point cloud or volume (or a scene) in the "
    "interactive explorer: load or generate a cage and anchors, click to add "
    "constraints, drag them and analyse the deformation live. With --screenshot, render "
    "one frame of the solved scene to a PNG file and exit."
)


def add_arguments(p) -> None:
    """The ``explore`` subcommand's arguments."""
    from vhm_viz.app import add_arguments as add_explorer_arguments

    add_explorer_arguments(p)


def run(args) -> int:
    """Run the explorer until its window closes."""
    from vhm_viz import interrupts
    from vhm_viz.cli._util import check_input, load_scene
    from vhm_viz.io import CAGE_SUFFIXES

    # what the command line names is checked before a window opens: a missing or
    # malformed file is one line and exit status 1, not a dialog in a window
    if args.file:
        check_input(args.file)
    if args.cage:
        check_input(args.cage, CAGE_SUFFIXES)
    if args.scene:
        load_scene(args.scene)

    # A signal raised as an exception inside the import of a compiled module can abort
    # the interpreter (shiboken's start-up turns it into "Fatal Python error"): the
    # imports only record a SIGINT/SIGTERM, which is raised once they are done.
    with interrupts.deferred():
        try:
            import PySide6.QtWidgets  # noqa: F401
            import pyvistaqt  # noqa: F401
        except ImportError as exc:
            raise RuntimeError(
                f"the explorer needs the Qt extra: pip install 'vhm_viz[qt]' ({exc})"
            ) from exc
        import vhm_viz.app.window  # noqa: F401
        from vhm_viz.app import run as run_app

    with args.timer.stage("explorer"):
        return run_app(args)  # an error becomes one line and exit status 1 (vhm_viz.cli.main)
