"""How much more memory this process may take: RLIMIT_AS, the cgroup's limit, free RAM.

A job that cannot fit should say so before it allocates (:func:`require_memory`), not
fail a minute later with a ``MemoryError`` or be killed by the kernel. What bounds a
process is the least of three things, each found here in one place:

* its address-space limit (``ulimit -v``, ``RLIMIT_AS``) less the address space it
  already maps (``VmSize``: every mapping counts, reserved or touched);
* its control group's memory limit (cgroup v2 ``memory.max``, v1
  ``memory.limit_in_bytes``) less the group's current use, for containers and batch
  schedulers;
* the memory the system can give without swapping (``MemAvailable``).

The estimate itself, of what a job needs, is the core's
(:func:`vhm_viz.core.memory.volume_job_bytes`).
"""

from __future__ import annotations

import resource
from pathlib import Path
from typing import NamedTuple

__all__ = ["MemoryLimit", "memory_limit", "require_memory", "memory_error_line", "format_bytes"]

#: cgroup v1 reports "no limit" as a huge number (a page count near 2**63).
_UNLIMITED = 2**60


class MemoryLimit(NamedTuple):
    """The memory a process may still take, and what sets it.

    Attributes
    ----------
    available : int or None
        Bytes; None when nothing could be found (not Linux, no limit).
    source : str
        What sets it, for messages: ``the address-space limit (ulimit -v) of 1.1 GiB``.
    """

    available: int | None
    source: str


def format_bytes(nbytes: float) -> str:
    """``1.2 GiB``, ``340 MiB``: a byte count for people."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if abs(nbytes) >= size:
            return f"{nbytes / size:.3g} {unit}"
    return f"{int(nbytes)} B"


def _status_bytes(key: str) -> int | None:
    """A ``kB`` field of ``/proc/self/status`` (``VmSize``) in bytes."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    if not text or text == "max":
        return None
    try:
        value = int(text)
    except ValueError:
        return None
    return None if value >= _UNLIMITED else value


def _cgroup_folders() -> list[tuple[str, Path]]:
    """``(version, folder)`` of this process's memory cgroup(s), from ``/proc/self/cgroup``."""
    folders = []
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return folders
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, rel = parts
        if controllers == "":
            folders.append(("v2", Path("/sys/fs/cgroup") / rel.lstrip("/")))
        elif "memory" in controllers.split(","):
            folders.append(("v1", Path("/sys/fs/cgroup/memory") / rel.lstrip("/")))
    return folders


def _cgroup_room() -> tuple[int, int] | None:
    """``(room, limit)`` of the tightest memory cgroup on the way to the root, if any."""
    best = None
    for version, folder in _cgroup_folders():
        limit_name = "memory.max" if version == "v2" else "memory.limit_in_bytes"
        usage_name = "memory.current" if version == "v2" else "memory.usage_in_bytes"
        # a limit set on a parent group holds too; inside a container the process's own
        # path may not exist (its group is the mount's root), which the walk also covers
        for level in (folder, *folder.parents):
            if not str(level).startswith("/sys/fs/cgroup"):
                break
            limit = _read_int(level / limit_name)
            if limit is None:
                continue
            usage = _read_int(level / usage_name) or 0
            room = max(limit - usage, 0)
            if best is None or room < best[0]:
                best = (room, limit)
    return best


def memory_limit() -> MemoryLimit:
    """The bytes this process may still allocate, and what limits it (see the module)."""
    candidates = []
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        used = _status_bytes("VmSize") or 0
        source = f"the address-space limit (ulimit -v) of {format_bytes(soft)}"
        candidates.append((max(soft - used, 0), source))
    cgroup = _cgroup_room()
    if cgroup is not None:
        candidates.append((cgroup[0], f"the cgroup memory limit of {format_bytes(cgroup[1])}"))
    try:
        meminfo = Path("/proc/meminfo").read_text().splitlines()
        free = next(int(ln.split()[1]) * 1024 for ln in meminfo if ln.startswith("MemAvailable:"))
        candidates.append((free, "the memory available on this machine"))
    except (OSError, StopIteration, ValueError, IndexError):
        pass
    if not candidates:
        return MemoryLimit(None, "no known limit")
    room, source = min(candidates)
    return MemoryLimit(int(room), source)


def memory_error_line(exc: MemoryError) -> str:
    """One line for a ``MemoryError``: :func:`require_memory`'s as it is, else reworded.

    An allocation that failed where no estimate refused the job first raises NumPy's
    ("Unable to allocate ... for an array with shape ...") or Python's (no message); the
    line says instead how much was asked for, what limits this process, and what to do.
    """
    text = str(exc).strip()
    if type(exc) is MemoryError and text:
        return text.splitlines()[0]
    size = getattr(exc, "_total_size", None)  # NumPy's: the bytes of the failed array
    asked = (
        f"a step asked for {format_bytes(size)}, more" if size else "an allocation asked for more"
    )
    return (
        f"out of memory: {asked} than is left under {memory_limit().source}; make the job "
        "smaller (a cage of fewer faces, fewer anchors, coarser data) or give it more memory"
    )


def require_memory(needed: int, what: str, remedy: str, error: type = MemoryError) -> None:
    """Refuse, before allocating, a job that needs more memory than this process may take.

    Parameters
    ----------
    needed : int
        Bytes the job will still allocate (its estimate).
    what : str
        The job, for the message (``resampling 256x256x256 voxels``).
    remedy : str
        What lowers it (``a smaller --memory-budget or a coarser --spacing``).
    error : type
        The exception raised (a reader's ``ReadError``, say).

    Raises
    ------
    MemoryError
        (or ``error``) One line: the estimate, the limit and the remedy.
    """
    limit = memory_limit()
    if limit.available is not None and needed > limit.available:
        raise error(
            f"{what} needs about {format_bytes(needed)} more memory, but only "
            f"{format_bytes(limit.available)} is left under {limit.source}; {remedy}"
        )
