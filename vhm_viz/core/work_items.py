"""Dynamic scheduling for the compiled parallel loops: workers claim items from a counter.

numba's ``prange`` hands each thread one fixed, contiguous share of the iterations (its
OpenMP and workqueue threading layers schedule statically; ``numba.parallel_chunksize``
is dynamic only under TBB). Work items of uneven cost -- rows of an output slab that
cross many leaves or none, leaves of 8^3 and 16^3 voxels -- then leave threads idle at
the loop's end, and a thread that the operating system preempts on a shared machine
holds up all the others. Instead, a kernel runs one ``prange`` iteration per worker
(``workers``: :func:`worker_count`, passed in by its Python caller, since
``numba.get_num_threads`` inside a compiled function keeps it out of the on-disk cache)
and each worker claims the next few items from a shared counter (:func:`claim`, an
atomic fetch-and-add) until none are left: whoever is free takes the next items,
whatever their cost.

Inside a kernel compiled with ``parallel=True``::

    counter = np.zeros(1, dtype=np.int64)
    for _ in numba.prange(workers):
        (per-worker scratch arrays, allocated once per worker)
        while True:
            first = claim(counter, CHUNK)
            if first >= n_items:
                break
            for item in range(first, min(first + CHUNK, n_items)):
                ...

or, cheaper to compile, in a serial ``nogil`` kernel ``worker(start, stop, counter, ...)``
whose loop over ``range(start, stop)`` takes the place of the ``prange``, run on the row
threads as ``run_rows(worker, workers, counter, ..., grain=1)``
(:func:`~vhm_viz.core.row_threads.run_rows`; the pull-back's rows do so).
"""

from __future__ import annotations

import numba
from numba import types
from numba.extending import intrinsic

__all__ = ["claim", "worker_count"]


@intrinsic
def _fetch_add(typingctx, counter, count):
    """``old = counter[0]; counter[0] += count; return old``, atomically (int64)."""
    if not (
        isinstance(counter, types.Array)
        and counter.dtype == types.int64
        and isinstance(count, types.Integer)
    ):
        return None
    sig = types.int64(counter, types.int64)

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", array.data, args[1], "monotonic")

    return sig, codegen


@numba.njit(inline="always", cache=True)
def claim(counter, count):  # pragma: no cover - compiled
    """Claim ``count`` work items: the first one's index (``counter[0]`` before the add).

    Parameters
    ----------
    counter : (1,) int64 ndarray
        Shared by the workers of one loop; zero before it starts.
    count : int
        Items claimed at once (a few, so that the atomic add is rare beside the work).

    Returns
    -------
    int
        The first claimed item; the claim is empty when it is at or past the last item.
    """
    return _fetch_add(counter, count)


def worker_count() -> int:
    """Workers of a dynamically scheduled loop: one per thread of the compiled kernels."""
    return numba.get_num_threads()
