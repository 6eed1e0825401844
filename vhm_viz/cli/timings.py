"""Where a command's time goes: the stage breakdown that ``--timings`` prints."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager

from vhm_viz import interrupts

__all__ = ["STAGES", "StageTimer"]

#: The stages of a command, in the order they run.
STAGES = ("read", "solve", "map", "checks", "write")


class StageTimer:
    """Wall-clock seconds per stage of one command, from its start.

    Use :meth:`stage` around each stage's work; :meth:`line` gives the breakdown, with
    the time outside every stage (start-up, imports, argument checks) as ``other``.
    """

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.seconds: dict[str, float] = {}
        #: The stage under way and its start (a process ended inside one reports it too).
        self.running: tuple[str, float] | None = None

    @contextmanager
    def stage(self, name: str):
        """Add the time spent in the ``with`` block to stage ``name``.

        The start and the end of a stage are abort points: a SIGINT or SIGTERM received
        and not yet acted on (one that arrived where Python could not raise it) is raised
        there (:func:`vhm_viz.interrupts.check`).
        """
        interrupts.check()
        t0 = time.perf_counter()
        self.running = (name, t0)
        try:
            yield
        finally:
            self.running = None
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
        interrupts.check()

    @property
    def total(self) -> float:
        """Seconds since the timer was made."""
        return time.perf_counter() - self.start

    def line(self) -> str:
        """``timings: read 0.12 s, solve 0.30 s, ..., other 0.05 s, total 1.79 s``."""
        total = self.total
        seconds = dict(self.seconds)
        if self.running is not None:
            name, t0 = self.running
            seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - t0
        names = [s for s in STAGES if s in seconds]
        names += sorted(set(seconds) - set(STAGES))
        parts = [f"{n} {seconds[n]:.2f} s" for n in names]
        other = max(0.0, total - sum(seconds.values()))
        parts += [f"other {other:.2f} s", f"total {total:.2f} s"]
        return "timings: " + ", ".join(parts)

    def report(self, enabled: bool, stream=None) -> None:
        """Print :meth:`line` as ``vhm-viz: timings: ...`` on ``stream`` (stderr) if enabled."""
        if enabled:
            print(f"vhm-viz: {self.line()}", file=stream or sys.stderr)
