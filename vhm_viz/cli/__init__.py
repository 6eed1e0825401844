"""The ``vhm-viz`` command line.

Each subcommand lives in its own module of this package exposing
``add_parser(subparsers)`` (registers the subcommand) and ``run(args) -> int``.
Subcommands simply raise; :func:`main` reports every error as one line on stderr
with a non-zero exit status.

Exit statuses:

===  ===========================================================================
0    success
1    an error (one line on stderr naming the problem); no output was written
2    bad command-line arguments (argparse's usage message)
3    the solver did not converge within ``solver.max_iterations``; no output was
     written (``--allow-unconverged`` writes it anyway and exits 0)
130  interrupted by SIGINT (Ctrl-C); 143: by SIGTERM. Previous outputs are left
     byte-identical and no temporary file remains
===  ===========================================================================
"""

from __future__ import annotations

import argparse
import importlib
import sys

from vhm_viz import __version__, interrupts
from vhm_viz.scene import NotConverged

# subcommand name -> module in this package; order is the order shown in --help
_COMMANDS = {
    "demo": "demo",
    "deform": "deform",
    "analyze": "analyze",
    "cage": "cage",
    "anchors": "anchors",
    "explore": "explore",
    "paraview": "paraview",
}


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="vhm-viz",
        description="Variational harmonic maps for space deformation of meshes, "
        "tet meshes, point clouds and volumes.",
    )
    parser.add_argument("--version", action="version", version=f"vhm-viz {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_name in _COMMANDS.values():
        module = importlib.import_module(f"vhm_viz.cli.{module_name}")
        module.add_parser(sub)
    return parser


#: Exit status of a solve that stopped at its iteration cap (see the module documentation):
#: :class:`~vhm_viz.scene.NotConverged`, raised by the scene's solved map.
EXIT_NOT_CONVERGED = 3


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    with interrupts.handled():
        try:
            return int(args.func(args) or 0)
        except (interrupts.Interrupted, KeyboardInterrupt) as exc:
            status = getattr(exc, "exit_status", 130)
            print(f"vhm-viz {args.command}: {exc or 'interrupted by SIGINT'}", file=sys.stderr)
            return status
        except NotConverged as exc:
            print(f"vhm-viz {args.command}: {one_line(exc)}", file=sys.stderr)
            return EXIT_NOT_CONVERGED
        except Exception as exc:  # noqa: BLE001 - every error is one line and a non-zero exit
            print(f"vhm-viz {args.command}: error: {one_line(exc)}", file=sys.stderr)
            return 1


def one_line(exc: BaseException) -> str:
    """An exception as one line: its message's first line, or its type name."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
