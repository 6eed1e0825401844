"""The ``vhm-viz`` command line.

Each subcommand lives in its own module of this package, listed in :data:`COMMANDS`,
exposing ``HELP``, ``DESCRIPTION`` (and optionally ``EPILOG``), ``add_arguments(parser)``
and ``run(args) -> int``, and optionally ``RUN_IMPORTS``, the libraries it imports when
it runs (not for its help), imported with the start-up's modules
(:func:`_finish_start_up`). Every subcommand also takes ``--timings`` (the stage
breakdown, :mod:`vhm_viz.cli.timings`) and ``--threads`` (:mod:`vhm_viz.core.threads`);
a command records its stages in ``args.timer``. Subcommands simply raise; :func:`main` reports
every error as one line on stderr with a non-zero exit status. A command line that names
its subcommand imports only that subcommand's module (each imports what it uses), so a
command starts without loading the others' libraries.

Exit statuses:

===  ===========================================================================
0    success
1    an error (one line on stderr naming the problem); no output was written
2    command-line arguments that do not parse: an unknown option, a missing value, a
     value of the wrong type or not among an option's choices (argparse's usage
     message); a value that parses but is out of its range is status 1
3    the solver did not converge within ``solver.max_iterations`` (the last step's,
     for a ramp); no output was written (``--allow-unconverged`` writes it anyway,
     with a ``not converged`` warning, and exits 0)
4    ``deform``: the result folds the data (inverted cells, resampled voxels in
     folds, or ``det J <= 0`` at sampled points; the line says how many and where);
     no output was written (``--allow-folds`` writes it anyway, with the warning,
     and exits 0)
130  interrupted by SIGINT (Ctrl-C); 143: by SIGTERM. Previous outputs are left
     byte-identical and no temporary file remains
===  ===========================================================================
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import os
import sys
import time
import warnings

from vhm_viz import __version__, interrupts
from vhm_viz.cli.first_run import notice_when_compiling
from vhm_viz.cli.timings import StageTimer

#: When the command line's module was imported: a command that is its process counts its
#: ``--timings`` from here, its libraries' imports included.
_STARTED = time.perf_counter()

#: The subcommands (modules of this package), in the order ``--help`` shows them.
COMMANDS = ("demo", "deform", "analyze", "cage", "anchors", "explore", "paraview")
#: The subcommands that run compiled kernels (their first run on a machine compiles them).
COMPILING = frozenset(COMMANDS) - {"paraview"}


def _threads(text: str) -> int:
    """``--threads``: a positive integer."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer; got {text!r}")
    return value


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Build the argument parser with every registered subcommand.

    Parameters
    ----------
    only : str, optional
        Register just this subcommand (one of :data:`COMMANDS`): the one a command line
        names, so that only its module is imported. The top-level usage line is the same.
    """
    parser = argparse.ArgumentParser(
        prog="vhm-viz",
        description="Variational harmonic maps for space deformation of meshes, "
        "tet meshes, point clouds and volumes.",
    )
    from vhm_viz.core.threads import THREADS_VARIABLE  # numba: with the command's modules

    parser.add_argument("--version", action="version", version=f"vhm-viz {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS if only is None else (only,):
        module = importlib.import_module(f"vhm_viz.cli.{name}")
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=module.DESCRIPTION,
            epilog=getattr(module, "EPILOG", None),
        )
        module.add_arguments(p)
        p.add_argument(
            "--timings",
            action="store_true",
            help="print where the time went on stderr: "
            f"{getattr(module, 'TIMING_STAGES', 'read, solve, map, checks, write')}, and "
            "other (start-up, imports, loading compiled code)",
        )
        p.add_argument(
            "--threads",
            type=_threads,
            default=None,
            metavar="N",
            help=f"threads of the numeric kernels (default: ${THREADS_VARIABLE}, else the "
            "CPUs this process may use: its affinity and any cgroup CPU quota)",
        )
        p.set_defaults(func=module.run)
    return parser


#: Exit status of a solve that stopped at its iteration cap (see the module documentation):
#: :class:`~vhm_viz.scene.NotConverged`, raised by the scene's solved map.
EXIT_NOT_CONVERGED = 3


def named_command(argv: list[str]) -> str | None:
    """The subcommand a command line starts with, or None.

    None when the first argument is not one of :data:`COMMANDS`: no command, an unknown
    one, or a top-level option before it (``vhm-viz -h deform`` shows every command).
    """
    return argv[0] if argv and argv[0] in COMMANDS else None


def _not_converged(exc: BaseException) -> bool:
    """Whether ``exc`` is the scene's :class:`~vhm_viz.scene.NotConverged`.

    Only a command that imported :mod:`vhm_viz.scene` can raise it; the others need not
    import it to tell.
    """
    scene = sys.modules.get("vhm_viz.scene")
    return scene is not None and isinstance(exc, scene.NotConverged)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status.

    Parameters
    ----------
    argv : list of str, optional
        The arguments; None: ``sys.argv[1:]``, and this process is the command: it ends
        when the command does, with that status (:func:`_end_process`).
    """
    status = _run_command(argv)
    if argv is None:
        _end_process(status)
    return status


def _end_process(status: int) -> None:
    """End the process that ran the command, as Python's exit does but for its teardown.

    The command is done, its outputs written and on the disk. Python's exit would then
    tear its modules down and collect every object made so far (numba's types and
    compiled code, VTK's wrappers), a noticeable share of a short command's time, only
    for the memory to go back to the system anyway. Everything else of that exit happens
    here, in its order: the threads are joined (and the thread pools' own exit hooks
    run), then the ``atexit`` handlers (logging's, a coverage tool's), then the standard
    streams are flushed.
    """
    import atexit
    import threading

    shutdown_threads = getattr(threading, "_shutdown", None)
    run_exit_handlers = getattr(atexit, "_run_exitfuncs", None)
    if shutdown_threads is None or run_exit_handlers is None:  # pragma: no cover
        sys.exit(status)  # another Python: its own exit
    shutdown_threads()
    run_exit_handlers()
    _flush_and_exit(status)


def _flush_and_exit(status: int) -> None:
    """Flush stdout and stderr, then end the process with ``status`` at once."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(status)


def _run_command(argv: list[str] | None) -> int:
    """:func:`main` but for the process's end."""
    words = sys.argv[1:] if argv is None else list(argv)
    if argv is None:
        gc.disable()  # through the start-up: see _finish_start_up
    command = named_command(words)
    try:  # the command's libraries are imported here: a Ctrl-C may land in them
        parser = build_parser(command)
        args = parser.parse_args(words)
    except KeyboardInterrupt:
        print(f"vhm-viz{f' {command}' if command else ''}: interrupted by SIGINT", file=sys.stderr)
        return 130
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    args.timer = StageTimer(start=_STARTED if argv is None else None)
    # a process that is wholly this command ends at once when work cannot stop part-way
    ending = interrupts.ending_now(lambda signum: _end_now(signum, args))
    notice = args.command in COMPILING and not getattr(args, "quiet", False)
    with (
        interrupts.handled(),
        ending if argv is None else contextlib.nullcontext(),
        warnings.catch_warnings(),
        contextlib.ExitStack() as stack,
    ):
        warnings.showwarning = _warning_as_note
        try:
            if notice:  # (it imports numba: a signal may land in it, as in any import here)
                stack.enter_context(notice_when_compiling())
            if argv is None:
                _finish_start_up(args.command)
            from vhm_viz.core.threads import use_threads

            threads = use_threads(args.threads)
            if argv is None and args.command in COMPILING:
                from vhm_viz.cli._util import use_vtk_threads

                use_vtk_threads(threads)  # process-wide: only where the process is the command
            return int(args.func(args) or 0)
        except (interrupts.Interrupted, KeyboardInterrupt) as exc:
            status = getattr(exc, "exit_status", 130)
            print(f"vhm-viz {args.command}: {exc or 'interrupted by SIGINT'}", file=sys.stderr)
            if argv is None:  # this process is the command: end it now (see _end_now)
                _end_now(None, args, status)
            return status
        except Exception as exc:  # noqa: BLE001 - every error is one line and a non-zero exit
            if _not_converged(exc):
                print(f"vhm-viz {args.command}: {one_line(exc)}", file=sys.stderr)
                return EXIT_NOT_CONVERGED
            if isinstance(exc, MemoryError):
                from vhm_viz.resources import memory_error_line

                text = memory_error_line(exc)
            else:
                text = one_line(exc)
            print(f"vhm-viz {args.command}: error: {text}", file=sys.stderr)
            return getattr(exc, "exit_status", 1)
        finally:
            args.timer.report(args.timings)


def _warning_as_note(message, category, filename, lineno, file=None, line=None) -> None:
    """A Python warning during a command: one ``vhm-viz: note:`` line, not its source line."""
    text = str(message).strip().splitlines()
    print(f"vhm-viz: note: {text[0] if text else category.__name__}", file=sys.stderr)


def _finish_start_up(command: str) -> None:
    """Import the libraries ``command`` runs with, then hand the collector its objects.

    The collector is off from the command line's start: modules, classes and functions made
    while importing live as long as the process, and the collector would only walk them,
    again and again, finding nothing. The command module's ``RUN_IMPORTS`` (the libraries
    it imports when it runs, not for its help) are imported here too; then everything so
    far is frozen out of the collector's passes (:func:`gc.freeze`) and the collector is
    on again for what the command itself makes.
    """
    for name in getattr(sys.modules[f"vhm_viz.cli.{command}"], "RUN_IMPORTS", ()):
        importlib.import_module(name)
    gc.freeze()
    gc.enable()


def _end_now(signum: int | None, args, status: int | None = None) -> None:
    """End an interrupted command's process at once, its temporaries removed.

    The interpreter's own teardown (the kernels' thread pools, VTK's objects) can take
    most of a second on a busy machine, and some work cannot stop part-way (VTK's XML
    writers); an interrupted command should end promptly. Only used when :func:`main`
    runs as the process's command (no ``argv`` given), never when called from Python.

    Parameters
    ----------
    signum : int or None
        The signal, when called from work that cannot stop (it is reported here); None
        when the interrupt was already reported.
    args : argparse.Namespace
    status : int, optional
        Exit status (default ``128 + signum``).
    """
    from vhm_viz.atomic import remove_temporaries_in_progress

    remove_temporaries_in_progress()
    if signum is not None:
        status = 128 + signum
        print(f"vhm-viz {args.command}: {interrupts.Interrupted(signum)}", file=sys.stderr)
    args.timer.report(args.timings)
    _flush_and_exit(status)


def one_line(exc: BaseException) -> str:
    """An exception as one line: its message's first line, or its type name."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
