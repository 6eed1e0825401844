"""Freed heap memory handed back to the operating system.

Building a lattice or a deformer allocates and frees many mid-sized arrays (node tables,
level data, evaluation chunks). glibc serves arrays below its dynamic mmap threshold
(which grows up to 32 MiB once a large block has been freed) from the heap, and freed
heap memory stays in the process: on the 256^3 embryo about 140 MiB of it, which would
add to the peak when the output is allocated next. :func:`release_free_memory` asks the
allocator to return it (``malloc_trim``), a few milliseconds.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

__all__ = ["release_free_memory"]

_LIBC = None


def release_free_memory() -> bool:
    """Return the heap's free pages to the operating system (glibc); elsewhere a no-op.

    Returns
    -------
    bool
        Whether memory could be handed back (glibc's ``malloc_trim`` reports it).
    """
    global _LIBC
    if not sys.platform.startswith("linux"):
        return False
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _LIBC.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
            _LIBC = False
    if not _LIBC:
        return False
    return bool(_LIBC.malloc_trim(0))
