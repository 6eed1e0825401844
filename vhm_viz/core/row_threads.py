"""Serial compiled kernels run over ranges of rows on a small pool of threads.

A numba ``parallel=True`` kernel costs far more to compile than the same loop written
serially (the parallel-loop lowering and its generated wrappers), which a first run pays
for every such kernel. The kernels here are compiled serially with ``nogil=True`` and take
the range of rows they work on (``start, stop``) as their first two arguments;
:func:`run_rows` splits the rows into chunks and runs them on threads, as many as the
compiled kernels may use (:func:`vhm_viz.core.threads.use_threads` sets that count through
numba, which is where it is read). Chunks are handed out as threads come free, so uneven
rows balance themselves.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba

__all__ = ["run_rows"]

_pool: dict = {"executor": None, "threads": 0, "pid": 0}
_lock = threading.Lock()
_worker = threading.local()
#: Chunks per thread: enough for threads that finish early to take over others' work.
_CHUNKS_PER_THREAD = 4


def _mark_worker() -> None:
    _worker.active = True


def _executor(threads: int) -> ThreadPoolExecutor:
    """The shared pool, (re)created with ``threads`` workers when that count changes.

    A forked child inherits the pool but not its threads: it gets a new one.
    """
    with _lock:
        if _pool["threads"] != threads or _pool["pid"] != os.getpid():
            old = _pool["executor"] if _pool["pid"] == os.getpid() else None
            _pool["executor"] = ThreadPoolExecutor(
                threads, thread_name_prefix="vhm-rows", initializer=_mark_worker
            )
            _pool["threads"] = threads
            _pool["pid"] = os.getpid()
            if old is not None:
                old.shutdown(wait=False)
        return _pool["executor"]


def run_rows(kernel, n_rows: int, *args, grain: int = 256) -> None:
    """Call ``kernel(start, stop, *args)`` over ``[0, n_rows)`` in chunks, on threads.

    Parameters
    ----------
    kernel : callable
        A compiled ``nogil`` kernel that handles rows ``start <= k < stop`` and writes its
        results into arrays among ``args`` (each row independently of the others).
    n_rows : int
    *args
        The kernel's remaining arguments, the same for every chunk.
    grain : int
        Chunk boundaries are multiples of it (a kernel's own block of rows); at most one
        chunk is made per ``grain`` rows, so small calls run in the calling thread.
    """
    threads = numba.get_num_threads()
    blocks = -(-n_rows // grain)
    chunks = min(blocks, threads * _CHUNKS_PER_THREAD)
    if threads <= 1 or chunks <= 1 or getattr(_worker, "active", False):
        kernel(0, n_rows, *args)
        return
    bounds = [min(n_rows, (blocks * i // chunks) * grain) for i in range(chunks + 1)]
    executor = _executor(threads)
    futures = [
        executor.submit(kernel, bounds[i], bounds[i + 1], *args)
        for i in range(chunks)
        if bounds[i + 1] > bounds[i]
    ]
    try:
        for f in futures:
            f.result()
    finally:
        for f in futures:
            f.cancel()
