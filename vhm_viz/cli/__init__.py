"""The ``vhm-viz`` command line.

Each subcommand lives in its own module of this package exposing
``add_parser(subparsers)`` (registers the subcommand) and ``run(args) -> int``.
Every error is reported as one line on stderr with a non-zero exit status.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# subcommand name -> module in this package; order is the order shown in --help
_COMMANDS = {
    "demo": "demo",
    "deform": "deform",
    "analyze": "analyze",
    "cage": "cage",
    "anchors": "anchors",
    "explore": "explore",
}


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="vhm-viz",
        description="Variational harmonic maps for space deformation of meshes, "
        "tet meshes, point clouds and volumes.",
    )
    from vhm_viz import __version__

    parser.add_argument("--version", action="version", version=f"vhm-viz {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in _COMMANDS.values():
        module = importlib.import_module(f"vhm_viz.cli.{module_name}")
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("vhm-viz: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"vhm-viz {args.command}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
