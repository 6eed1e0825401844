"""Where a command's time goes: the stage breakdown that ``--timings`` prints.

A command that maps data has the stages read, solve, map, checks and write, in that order;
``cage`` and ``anchors`` have read, their own work (a stage of the command's name) and
write.
"""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager

from vhm_viz import interrupts

__all__ = ["StageTimer"]


class StageTimer:
    """Wall-clock seconds per stage of one command, from its start.

    Use :meth:`stage` around each stage's work; :meth:`line` gives the breakdown, with
    the time outside every stage (start-up, imports, argument checks) as ``other``. Work
    of that kind done inside a stage, while the stage waits (loading compiled code while
    a child process reads the input), is wrapped with :meth:`aside` and counts as
    ``other`` too, so that a stage's time is its own work.

    Parameters
    ----------
    clock : callable() -> float, optional
        Seconds from an arbitrary start (default :func:`time.perf_counter`).
    start : float, optional
        When the command began, on ``clock`` (default: now); what ran since is ``other``.
    """

    def __init__(self, clock=time.perf_counter, start: float | None = None) -> None:
        self.clock = clock
        self.start = clock() if start is None else start
        self.seconds: dict[str, float] = {}
        #: The stage under way, its start and :attr:`set_aside` then (a process ended inside
        #: one reports it too).
        self.running: tuple[str, float, float] | None = None
        #: Seconds of :meth:`aside` work so far (taken off the stages it ran in).
        self.set_aside = 0.0

    def aside(self, work):
        """``work`` wrapped so that its time counts as ``other``, also inside a stage.

        Parameters
        ----------
        work : callable() or None
            None gives None.

        Returns
        -------
        callable() or None
            Runs ``work`` and returns what it returns.
        """
        if work is None:
            return None

        def timed():
            t0 = self.clock()
            try:
                return work()
            finally:
                self.set_aside += self.clock() - t0

        return timed

    @contextmanager
    def stage(self, name: str):
        """Add the time spent in the ``with`` block to stage ``name``.

        The start and the end of a stage are abort points: a SIGINT or SIGTERM received
        and not yet acted on (one that arrived where Python could not raise it) is raised
        there (:func:`vhm_viz.interrupts.check`).
        """
        interrupts.check()
        t0, aside0 = self.clock(), self.set_aside
        self.running = (name, t0, aside0)
        try:
            yield
        finally:
            self.running = None
            spent = self.clock() - t0 - (self.set_aside - aside0)
            self.seconds[name] = self.seconds.get(name, 0.0) + spent
        interrupts.check()

    @property
    def total(self) -> float:
        """Seconds since the timer was made."""
        return self.clock() - self.start

    def line(self) -> str:
        """``timings: read 0.12 s, solve 0.30 s, ..., other 0.05 s, total 1.79 s``."""
        total = self.total
        seconds = dict(self.seconds)
        if self.running is not None:
            name, t0, aside0 = self.running
            spent = self.clock() - t0 - (self.set_aside - aside0)
            seconds[name] = seconds.get(name, 0.0) + spent
        parts = [f"{n} {t:.2f} s" for n, t in seconds.items()]  # in the order they began
        other = max(0.0, total - sum(seconds.values()))
        parts += [f"other {other:.2f} s", f"total {total:.2f} s"]
        return "timings: " + ", ".join(parts)

    def report(self, enabled: bool, stream=None) -> None:
        """Print :meth:`line` as ``vhm-viz: timings: ...`` on ``stream`` (stderr) if enabled."""
        if enabled:
            print(f"vhm-viz: {self.line()}", file=stream or sys.stderr)
