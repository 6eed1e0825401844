"""How many threads the compiled kernels use: the CPUs this process may really run on.

``os.cpu_count()`` counts the machine's processors, not the ones a process gets: a job
pinned to some cores (``taskset``, a batch scheduler's affinity), a container with a CPU
quota (cgroups) or several MPI ranks on one node each get fewer. Threads beyond that share
cores and wait on each other at every parallel loop's barrier, which can make a kernel many
times slower than running on fewer threads.

The count, in order of precedence: ``requested`` (``--threads N``), the ``VHM_THREADS``
environment variable, else the usable CPUs (:func:`available_cpus`) divided among the MPI
ranks on this machine.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numba
from threadpoolctl import threadpool_limits

__all__ = [
    "BLAS_THREADS_VARIABLE",
    "THREADS_VARIABLE",
    "available_cpus",
    "cgroup_cpu_limit",
    "limit_blas_threads",
    "load_compiled_runtime",
    "thread_count",
    "use_threads",
]

#: Environment variable that sets the thread count (a positive integer).
THREADS_VARIABLE = "VHM_THREADS"
#: Environment variable that sets BLAS/LAPACK's thread count (a positive integer; default 1).
BLAS_THREADS_VARIABLE = "VHM_BLAS_THREADS"


def _cgroup_path(proc_cgroup: Path) -> tuple[str | None, str | None]:
    """The cgroup v2 path of this process and cgroup v1 ``cpu`` controller path, if any."""
    v2 = v1 = None
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None, None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        hierarchy, controllers, path = parts
        if hierarchy == "0" and controllers == "":
            v2 = path
        elif "cpu" in controllers.split(","):
            v1 = path
    return v2, v1


def cgroup_cpu_limit(root: str | os.PathLike = "/sys/fs/cgroup", proc_cgroup=None) -> float | None:
    """The CPU quota of this process's cgroup, in CPUs (None without one).

    Reads cgroup v2's ``cpu.max`` (``"QUOTA PERIOD"`` or ``"max PERIOD"``) or cgroup v1's
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``, at the process's own cgroup and at the
    mount root (how containers usually see theirs).

    Parameters
    ----------
    root : path
        Where the cgroup file system is mounted.
    proc_cgroup : path, optional
        The process's cgroup membership file (default ``/proc/self/cgroup``).

    Returns
    -------
    float or None
        Quota / period, e.g. 1.5 for "150000 100000".
    """
    root = Path(root)
    v2, v1 = _cgroup_path(Path(proc_cgroup or "/proc/self/cgroup"))
    candidates = []
    if v2 is not None:
        candidates += [(root / v2.lstrip("/") / "cpu.max", None), (root / "cpu.max", None)]
    for base in [root / "cpu", root / "cpu,cpuacct"] if v1 is not None else []:
        for sub in (v1.lstrip("/"), ""):
            folder = base / sub
            candidates.append((folder / "cpu.cfs_quota_us", folder / "cpu.cfs_period_us"))
    for quota_file, period_file in candidates:
        try:
            if period_file is None:
                quota, period = quota_file.read_text().split()[:2]
            else:
                quota, period = quota_file.read_text().strip(), period_file.read_text().strip()
        except (OSError, ValueError):
            continue
        if quota in ("max", "-1"):
            return None
        try:
            q, p = float(quota), float(period)
        except ValueError:
            continue
        if q > 0 and p > 0:
            return q / p
    return None


def available_cpus() -> int:
    """CPUs this process may run on: its affinity mask, capped by a cgroup CPU quota."""
    try:
        count = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        count = os.cpu_count() or 1
    limit = cgroup_cpu_limit()
    if limit is not None:
        count = min(count, max(1, math.floor(limit)))
    return max(1, count)


def thread_count(requested: int | None = None, ranks_on_machine: int = 1) -> int:
    """The number of threads for the compiled kernels (see the module documentation).

    Parameters
    ----------
    requested : int, optional
        An explicit count (``--threads``); wins over everything else.
    ranks_on_machine : int
        MPI ranks sharing this machine's CPUs (each gets its share).

    Raises
    ------
    ValueError
        ``requested`` or ``VHM_THREADS`` is not a positive integer.
    """
    if requested is None:
        text = os.environ.get(THREADS_VARIABLE, "").strip()
        if text:
            try:
                requested = int(text)
            except ValueError:
                raise ValueError(
                    f"{THREADS_VARIABLE} must be a positive integer; got {text!r}"
                ) from None
            if requested < 1:
                raise ValueError(f"{THREADS_VARIABLE} must be a positive integer; got {text!r}")
    elif int(requested) != requested or requested < 1:
        raise ValueError(f"the thread count must be a positive integer; got {requested!r}")
    if requested is not None:
        return int(requested)
    return max(1, available_cpus() // max(1, int(ranks_on_machine)))


def use_threads(requested: int | None = None, ranks_on_machine: int = 1) -> int:
    """Set the compiled kernels' thread count (:func:`thread_count`); returns the count set.

    numba cannot start more threads than it was loaded with (``NUMBA_NUM_THREADS``,
    the machine's CPUs by default), so a larger request is capped there.
    """
    n = min(thread_count(requested, ranks_on_machine), numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(n)
    limit_blas_threads()
    return n


def limit_blas_threads() -> int:
    """Give BLAS/LAPACK one thread, or ``VHM_BLAS_THREADS``; returns the count set.

    The linear algebra here is small (a QR of a few hundred columns, products with three
    columns), and OpenBLAS's pool spins while it waits: beside numba's kernels, Qt's
    threads or another busy process on the cores, a small QR then takes many times
    longer than on one thread. Applies to the BLAS libraries loaded so far: numpy's and
    SciPy's (loaded here when not yet, as the solver and the compiled kernels load it).

    Raises
    ------
    ValueError
        ``VHM_BLAS_THREADS`` is not a positive integer.
    """
    text = os.environ.get(BLAS_THREADS_VARIABLE, "").strip() or "1"
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{BLAS_THREADS_VARIABLE} must be a positive integer; got {text!r}")
    from vhm_viz.core.lapack import flapack, register_cython_linalg

    flapack()  # loads SciPy's own BLAS, so that the limit reaches it
    register_cython_linalg()  # numba's kernels then find it without all of scipy.linalg

    threadpool_limits(limits=n, user_api="blas")
    return n


@numba.njit(cache=True)
def _no_work():  # pragma: no cover - compiled
    return 0


def load_compiled_runtime() -> None:
    """Load numba's runtime for compiled code now (its CPU target and type registries).

    The first compiled kernel a process calls loads it, a noticeable part of a short
    command. Called while the process would otherwise wait (for a child reading its
    input: :func:`vhm_viz.io.read_dataset`'s ``meanwhile``), it costs nothing, and the
    first kernel then loads only itself.
    """
    _no_work()
