"""Background jobs for the explorer: a function run in a ``QThread`` with progress and cancel.

A job function receives two keyword arguments, ``progress(fraction, message)`` and
``cancelled() -> bool``; it reports progress through the first and should stop (raise
:class:`~vhm_viz.app.controller.Cancelled`) when the second turns true -- after
:meth:`Job.cancel`, or once the explorer received SIGINT or SIGTERM
(:func:`vhm_viz.interrupts.pending`). Functions that
cannot stop early (e.g. a library call) are *abandoned* on cancel: their result is
discarded when they finish and the UI is released immediately.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable

from PySide6.QtCore import QObject, QThread, Signal

from vhm_viz import interrupts
from vhm_viz.app.controller import Cancelled

__all__ = ["Job", "JobRunner"]


class Job(QThread):
    """Run ``fn(progress=..., cancelled=...)`` off the UI thread.

    Signals
    -------
    progressed(float, str)
        Fraction in [0, 1] and a message.
    succeeded(object)
        The function's return value.
    failed(str, str)
        Error message and formatted traceback.
    was_cancelled()
        The function stopped (or was abandoned) after :meth:`cancel`.
    """

    progressed = Signal(float, str)
    succeeded = Signal(object)
    failed = Signal(str, str)
    was_cancelled = Signal()

    def __init__(self, fn: Callable, name: str = "job", parent: QObject | None = None):
        super().__init__(parent)
        self.fn = fn
        self.name = name
        self._cancel = False

    def cancel(self) -> None:
        """Ask the job to stop; its result will be discarded."""
        self._cancel = True

    @property
    def cancel_requested(self) -> bool:
        """Whether :meth:`cancel` was called."""
        return self._cancel

    def run(self) -> None:  # noqa: D102 - QThread entry point
        try:
            result = self.fn(
                progress=lambda f, m: self.progressed.emit(float(f), str(m)),
                cancelled=lambda: self._cancel or interrupts.pending() is not None,
            )
        except Cancelled:
            self.was_cancelled.emit()
            return
        except BaseException as exc:  # report everything to the UI, never crash
            if self._cancel:
                self.was_cancelled.emit()
            else:
                msg = str(exc) or type(exc).__name__
                self.failed.emit(f"{type(exc).__name__}: {msg}", traceback.format_exc())
            return
        if self._cancel:
            self.was_cancelled.emit()
        else:
            self.succeeded.emit(result)


class JobRunner(QObject):
    """Runs one :class:`Job` at a time and forwards its outcome to callbacks.

    Signals
    -------
    started(str)
        A job began (its name).
    progressed(float, str)
    finished(str)
        A job ended in any way (its name); the runner is idle again.
    """

    started = Signal(str)
    progressed = Signal(float, str)
    finished = Signal(str)

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self.job: Job | None = None
        self._abandoned: list[Job] = []

    @property
    def busy(self) -> bool:
        """Whether a job runs."""
        return self.job is not None

    def start(
        self,
        name: str,
        fn: Callable,
        on_success: Callable[[object], None],
        on_error: Callable[[str, str], None],
        on_cancel: Callable[[], None] | None = None,
    ) -> bool:
        """Start ``fn`` in a thread; returns False (and does nothing) while busy."""
        if self.job is not None:
            return False
        job = Job(fn, name, self)
        self.job = job

        def done(cb, *args):
            if self.job is not job:  # abandoned earlier
                return
            self.job = None
            try:
                if cb is not None:
                    cb(*args)
            finally:
                self.finished.emit(name)

        job.progressed.connect(self.progressed)
        job.succeeded.connect(lambda r: done(on_success, r))
        job.failed.connect(lambda m, tb: done(on_error, m, tb))
        job.was_cancelled.connect(lambda: done(on_cancel))
        job.finished.connect(lambda: self._reap(job))
        self.started.emit(name)
        job.start()
        return True

    def cancel(self) -> None:
        """Cancel the running job and release the runner at once (the thread is abandoned)."""
        job = self.job
        if job is None:
            return
        job.cancel()
        self._abandoned.append(job)
        self.job = None
        self.finished.emit(job.name)

    def _reap(self, job: Job) -> None:
        if job in self._abandoned:
            self._abandoned.remove(job)
        job.deleteLater()

    def wait(self, msecs: int = 60000) -> None:
        """Block until the running and abandoned threads have finished (tests, shutdown)."""
        for j in [self.job, *self._abandoned]:
            if j is not None:
                j.wait(msecs)
