"""``vhm-viz explore [FILE] [--scene SCENE] [--screenshot PNG]``: the Qt desktop explorer."""

from __future__ import annotations


def add_parser(subparsers) -> None:
    """Register the ``explore`` subcommand."""
    from vhm_viz.app import add_arguments

    p = subparsers.add_parser(
        "explore",
        help="open the interactive Qt explorer",
        description="Open a mesh, tet mesh, point cloud or volume (or a scene) in the "
        "interactive explorer: load or generate a cage and anchors, click to add "
        "constraints, drag them and analyse the deformation live. With --screenshot, render "
        "one frame of the solved scene to a PNG file and exit.",
    )
    add_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    """Run the explorer until its window closes."""
    try:
        import PySide6  # noqa: F401
        import pyvistaqt  # noqa: F401
    except ImportError as exc:
        raise RuntimeError(
            f"the explorer needs the Qt extra: pip install 'vhm_viz[qt]' ({exc})"
        ) from exc
    from vhm_viz.app import run as run_app

    return run_app(args)  # an error becomes one line and exit status 1 (vhm_viz.cli.main)
