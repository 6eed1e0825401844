"""SIGINT and SIGTERM turned into a clean, prompt stop.

While :func:`handled` is active (the command line, the explorer, :func:`vhm_viz.filters.update`)
a SIGINT or SIGTERM is recorded (:func:`pending`) and raised as :class:`Interrupted` at the
next Python instruction. Long work stops promptly because it runs in chunks: the core's
bindings call their ``abort()`` callback between chunks and the VTK filters check their
``AbortExecute`` flag (the filters' base, ``vhm_viz.filters._common.DeformationSource``),
both of which also look at :func:`pending`. That matters because VTK's Python wrapper swallows an
exception raised inside a callback (a progress observer, ``RequestData``): the recorded
signal survives it, and :func:`check` raises it again afterwards.

Only the first signal raises; later ones (a user pressing Ctrl-C twice) are recorded and
otherwise ignored, so clean-up code (removing temporary files) is never cut short. Inside
:func:`deferred` a signal is only recorded, and raised when the block ends: the atomic
writers (:mod:`vhm_viz.atomic`) create and rename their temporaries there, so an
interrupt leaves either the previous output or the complete new one, never a temporary.

Some work cannot stop part-way (VTK's XML writers ignore their abort flag and write the
whole file). A process that is wholly one command (``vhm-viz``) installs an
:func:`ending_now` action, which such work calls through :func:`end_now` once a signal is
pending: the command's temporaries are removed and the process ends at once.

The exit status of an interrupted command is ``128 + signal number``: 130 for SIGINT,
143 for SIGTERM (:attr:`Interrupted.exit_status`).

A signal whose handler was installed outside Python is left to it: in ParaView's
``pvpython`` and ``pvbatch`` SIGINT is ParaView's own, so there Ctrl-C during
:func:`vhm_viz.filters.update` does what ParaView does with it, not the above.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator

__all__ = ["Interrupted", "check", "deferred", "handled", "pending", "ending_now", "end_now"]

_state = {"pending": None, "raised": False, "defer": 0, "depth": 0, "on_signal": None,
          "end_now": None, "retry": False}  # fmt: skip
#: Seconds after which a signal that arrived while a module was being imported is
#: delivered again (see :func:`_handler`).
_IMPORT_RETRY_SECONDS = 0.02


class Interrupted(BaseException):
    """The process received SIGINT or SIGTERM.

    A ``BaseException`` (so ``except Exception`` clauses let it through) but not a
    ``KeyboardInterrupt``: VTK's Python wrapper ends the whole process, with exit status 1
    and no clean-up, when a ``KeyboardInterrupt`` escapes one of its observers.
    :func:`vhm_viz.filters.update` re-raises a SIGINT as ``KeyboardInterrupt`` for Python
    callers.

    Attributes
    ----------
    signum : int
    exit_status : int
        ``128 + signum``: 130 for SIGINT, 143 for SIGTERM.
    """

    def __init__(self, signum: int):
        self.signum = int(signum)
        self.exit_status = 128 + self.signum
        super().__init__(f"interrupted by {signal.Signals(self.signum).name}")


def pending() -> int | None:
    """The signal received while :func:`handled` was active (None if none)."""
    return _state["pending"]


def check() -> None:
    """Raise :class:`Interrupted` if a signal was received (even if already raised once)."""
    signum = _state["pending"]
    if signum is not None:
        _state["raised"] = True
        raise Interrupted(signum)


#: Functions that Python calls around ``os.fork`` (logging's at-fork handlers): an
#: exception raised in them is printed as "Exception ignored" with a traceback, and lost.
_AT_FORK = frozenset({"_acquireLock", "_releaseLock", "_after_at_fork_child_reinit_locks"})


def _importing(frame) -> bool:
    """Whether ``frame`` or a caller of it imports a module or runs an at-fork handler."""
    while frame is not None:
        code = frame.f_code
        if code.co_filename.startswith("<frozen importlib") or code.co_name in _AT_FORK:
            return True
        frame = frame.f_back
    return False


def _deliver_again(signum: int) -> None:
    """Send ``signum`` to the main thread again shortly, while signals are still handled."""
    main = threading.main_thread().ident

    def again() -> None:
        if _state["retry"] and _state["depth"]:
            signal.pthread_kill(main, signum)

    timer = threading.Timer(_IMPORT_RETRY_SECONDS, again)
    timer.daemon = True
    timer.start()


def _handler(signum, frame) -> None:
    first = _state["pending"] is None
    if first:
        _state["pending"] = signum
    if _state["on_signal"] is not None:
        _state["on_signal"](signum)
        return
    if (first or _state["retry"]) and not _state["defer"] and not _state["raised"]:
        if _importing(frame):
            # an exception inside an import leaves the module half made (VTK's wrapped
            # modules then fail to load for the rest of the process, or crash), and one
            # inside an at-fork handler is printed and lost: raise once that is over, from
            # the same signal delivered again
            _state["retry"] = True
            _deliver_again(signum)
            return
        _state["retry"] = False
        _state["raised"] = True
        raise Interrupted(signum)


@contextlib.contextmanager
def handled(
    signals=(signal.SIGINT, signal.SIGTERM), on_signal: Callable[[int], None] | None = None
) -> Iterator[None]:
    """Handle ``signals`` for the duration of the block (see the module documentation).

    Parameters
    ----------
    signals : sequence of int
        Default SIGINT and SIGTERM.
    on_signal : callable(signum), optional
        Called instead of raising (the explorer quits its event loop this way).

    Nested uses keep the outermost handlers (and the signals they catch); an ``on_signal``
    given to a nested use replaces the outer behaviour inside the block (``vhm-viz
    explore`` runs the explorer's event loop inside the command line's handling). Outside
    the main thread (where Python cannot install signal handlers) the block runs
    unchanged, and so do signals whose handler was installed outside Python (ParaView's
    ``pvpython`` installs its own for SIGINT): Python cannot put such a handler back, so
    it is left in place. A signal the process was started ignoring stays ignored, as
    Python leaves it: a shell script's background job ignores SIGINT, so that a Ctrl-C
    meant for the script does not end the job too.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if _state["depth"]:
        outer = _state["on_signal"]
        if on_signal is not None:
            _state["on_signal"] = on_signal
        try:
            yield
        finally:
            _state["on_signal"] = outer
        return
    # getsignal gives None for a handler installed outside Python: signal.signal cannot
    # restore it (TypeError), so that signal stays with its owner
    previous = {s: h for s in signals if (h := signal.getsignal(s)) not in (None, signal.SIG_IGN)}
    _state.update(pending=None, raised=False, defer=0, on_signal=on_signal, retry=False)
    _state["depth"] = 1
    try:
        for s in previous:
            signal.signal(s, _handler)
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _state.update(depth=0, on_signal=None, defer=0, pending=None, raised=False, retry=False)


@contextlib.contextmanager
def deferred(raise_at_end: bool = True) -> Iterator[None]:
    """Record signals without raising inside the block; raise the recorded one at its end.

    With ``raise_at_end=False`` nothing is raised at the end either: for code that VTK
    calls back (progress observers), where an exception would only be printed and lost;
    the work then stops at its next :func:`check` or ``abort()`` test.
    """
    _state["defer"] += 1
    try:
        yield
    finally:
        _state["defer"] -= 1
    if raise_at_end and not _state["defer"] and not _state["raised"]:
        check()


@contextlib.contextmanager
def ending_now(action: Callable[[int], None]) -> Iterator[None]:
    """Inside the block, :func:`end_now` calls ``action(signum)`` (which should not return).

    For a process that is wholly one command: ``action`` removes its temporaries, reports
    the interrupt and exits (``os._exit``).
    """
    outer = _state["end_now"]
    _state["end_now"] = action
    try:
        yield
    finally:
        _state["end_now"] = outer


def end_now() -> None:
    """Where work cannot stop part-way: end the process now if a signal is pending.

    Only when an :func:`ending_now` action is installed (the command line); elsewhere
    nothing happens and the work runs to its end, where the signal is raised as usual.
    """
    signum, action = _state["pending"], _state["end_now"]
    if signum is not None and action is not None:
        action(signum)
