"""Say so when a command compiles numeric kernels, instead of going quiet.

The kernels are compiled by numba on first use and cached on disk (``NUMBA_CACHE_DIR``,
else beside the sources or, where those are read-only, in the user's cache folder). The
first run of a command on a machine, or after an upgrade, spends most of its time
compiling. numba announces each compilation that the cache does not spare (its
``numba:compile`` event, not sent for a kernel loaded from the cache): at the first one a
command prints one line, once. So the line comes exactly when compiling starts -- not
when the kernels are only loaded, and not before an input error that ends the command
before any kernel runs.
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Iterator

__all__ = ["NOTICE", "notice_when_compiling"]

#: The line a command prints when it starts compiling kernels.
NOTICE = (
    "vhm-viz: compiling numeric kernels once for this machine (up to a minute; later "
    "runs start at once)..."
)


@contextlib.contextmanager
def notice_when_compiling(stream=None) -> Iterator[None]:
    """Print :data:`NOTICE` to ``stream`` (default stderr) at the first compilation inside.

    Kernels compiled on other threads (the row threads, the checks' loader) count too; the
    line is printed once.
    """
    from numba.core import event

    said = threading.Event()

    class _Notice(event.Listener):
        def on_start(self, _event) -> None:
            # numba compiles under its own global lock: one thread at a time comes here
            if not said.is_set():
                said.set()
                print(NOTICE, file=stream or sys.stderr, flush=True)

        def on_end(self, _event) -> None:
            pass

    listener = _Notice()
    event.register("numba:compile", listener)
    try:
        yield
    finally:
        event.unregister("numba:compile", listener)
