"""Background jobs for the explorer: a function run in a ``QThread`` with progress and cancel.

A job function receives two keyword arguments, ``progress(fraction, message)`` and
``cancelled() -> bool``; it reports progress through the first and should stop (raise
:class:`~vhm_viz.app.controller.Cancelled`) when the second turns true -- after
:meth:`Job.cancel`, or once the explorer received SIGINT or SIGTERM
(:func:`vhm_viz.interrupts.pending`). Functions that
cannot stop early (e.g. a library call) are *abandoned* on cancel: their result is
discarded when they finish and the UI is released immediately.

Every job ends with :attr:`Job.ended` set and its ``ended`` signal, after its callbacks ran:
callers wait for the job they started (:meth:`JobRunner.start` returns it;
:meth:`JobRunner.waiting`), never for "no job running", which also holds before a
just-submitted job has started.
"""

from __future__ import annotations

import contextlib
import time
import traceback
from collections.abc import Callable

from PySide6.QtCore import QCoreApplication, QObject, QThread, Signal

from vhm_viz import interrupts
from vhm_viz.app.cancellation import Cancelled

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
    #: Emitted on the UI thread once the job's callbacks ran (or it was dropped unstarted).
    ended = Signal()

    def __init__(self, fn: Callable, name: str = "job", parent: QObject | None = None):
        super().__init__(parent)
        self.fn = fn
        self.name = name
        self._cancel = False
        #: Whether the job is over: callbacks run, cancelled, or dropped from the queue.
        self.is_over = False

    def end(self) -> None:
        """Mark the job over and say so (:attr:`ended`); called by the runner."""
        if not self.is_over:
            self.is_over = True
            self.ended.emit()

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
    """Runs one :class:`Job` at a time (others may wait in a queue) with callbacks.

    Signals
    -------
    submitted(object)
        A job was accepted (started or queued): the :class:`Job`.
    started(str)
        A job began (its name).
    progressed(float, str)
    finished(str)
        A job ended in any way (its name); the next queued job starts after this.
    """

    submitted = Signal(object)
    started = Signal(str)
    progressed = Signal(float, str)
    finished = Signal(str)

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self.job: Job | None = None
        self._abandoned: list[Job] = []
        self._queue: list[tuple[Job, tuple]] = []

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
        queue: bool = False,
    ) -> Job | None:
        """Start ``fn`` in a thread and return its :class:`Job`.

        While another job runs: None (nothing done), or with ``queue`` the job waits and
        starts when the runner is free; a queued job of the same name is replaced (and
        ends unstarted).
        """
        if self.job is not None and not queue:
            return None
        job = Job(fn, name, self)
        callbacks = (on_success, on_error, on_cancel)
        self.submitted.emit(job)
        if self.job is None:
            self._run(job, callbacks)
            return job
        for entry in [e for e in self._queue if e[0].name == name]:
            self._queue.remove(entry)
            entry[0].end()
        self._queue.append((job, callbacks))
        return job

    def _run(self, job: Job, callbacks: tuple) -> None:
        on_success, on_error, on_cancel = callbacks
        self.job = job

        def done(cb, *args):
            if self.job is not job:  # abandoned earlier
                return
            self.job = None
            try:
                if cb is not None:
                    cb(*args)
            finally:
                self.finished.emit(job.name)
                job.end()
                self._next()

        job.progressed.connect(self.progressed)
        job.succeeded.connect(lambda r: done(on_success, r))
        job.failed.connect(lambda m, tb: done(on_error, m, tb))
        job.was_cancelled.connect(lambda: done(on_cancel))
        job.finished.connect(lambda: self._reap(job))
        self.started.emit(job.name)
        job.start()

    def _next(self) -> None:
        if self.job is None and self._queue:
            self._run(*self._queue.pop(0))

    def cancel(self) -> None:
        """Cancel the running job and release the runner at once (the thread is abandoned).

        Queued jobs are dropped too.
        """
        for job, _ in self._queue:
            job.end()
        self._queue.clear()
        job = self.job
        if job is None:
            return
        job.cancel()
        self._abandoned.append(job)
        self.job = None
        self.finished.emit(job.name)
        job.end()

    @contextlib.contextmanager
    def waiting(self, timeout_s: float = 120.0):
        """Run the ``with`` block, then wait for the jobs it started, processing events.

        Waits for every job submitted during the block (started or queued) and every job
        those submit in turn (e.g. a solve that starts the volume's resampling), until each
        has ended. Yields the list of those jobs.

        Raises
        ------
        TimeoutError
            A job still runs after ``timeout_s`` seconds.
        """
        jobs: list[Job] = []

        def record(job: Job) -> None:
            jobs.append(job)

        self.submitted.connect(record)
        try:
            yield jobs
            t0 = time.perf_counter()
            while not all(job.is_over for job in jobs):
                if time.perf_counter() - t0 > timeout_s:
                    names = [job.name for job in jobs if not job.is_over]
                    raise TimeoutError(f"jobs still running after {timeout_s:g} s: {names}")
                QCoreApplication.processEvents()
                time.sleep(0.005)
            QCoreApplication.processEvents()
        finally:
            self.submitted.disconnect(record)

    def _reap(self, job: Job) -> None:
        if job in self._abandoned:
            self._abandoned.remove(job)
        job.deleteLater()

    def wait(self, msecs: int = 60000) -> None:
        """Block until the running and abandoned threads have finished (tests, shutdown)."""
        for j in [self.job, *self._abandoned]:
            if j is not None:
                j.wait(msecs)
