"""Agreement between MPI ranks for filters run by ParaView under ``mpiexec``.

In ParaView every rank runs every pipeline update, so a filter can meet the other ranks in
a collective operation at fixed points of ``RequestData``. The filters do that only when
asked (:meth:`DeformationSource.SetParallelReporting`, set by the ParaView plugin): in a
plain VTK script under MPI the ranks need not update together, and a collective would hang.

With one process (or without VTK's parallel module) every function here is a no-op.
"""

from __future__ import annotations

__all__ = [
    "process_count",
    "rank",
    "all_ranks",
    "any_rank",
    "min_max_over_ranks",
    "mpi_command",
]


def mpi_command(cmd: list[str], ranks: int, env: dict) -> tuple[list[str], dict]:
    """``mpiexec -n ranks cmd`` and its environment: one thread per rank, idle ranks yield.

    On a machine with as many cores as ranks, a rank that busy-waits in a collective (or
    spawns numba/BLAS threads) starves the other. One rank: ``cmd`` and ``env`` unchanged.
    """
    if ranks <= 1:
        return list(cmd), dict(env)
    single = {"OMPI_MCA_mpi_yield_when_idle": "1", "NUMBA_NUM_THREADS": "1",
              "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}  # fmt: skip
    return ["mpiexec", "-n", str(ranks), *cmd], {**env, **single}


def _controller():
    try:
        from vtkmodules.vtkParallelCore import vtkMultiProcessController
    except ImportError:  # a VTK build without the parallel module: one process
        return None
    controller = vtkMultiProcessController.GetGlobalController()
    if controller is None or controller.GetNumberOfProcesses() <= 1:
        return None
    return controller


def process_count() -> int:
    """Number of MPI processes taking part in the pipeline (1 without MPI)."""
    controller = _controller()
    return 1 if controller is None else int(controller.GetNumberOfProcesses())


def rank() -> int:
    """Rank of the calling process (0 without MPI)."""
    controller = _controller()
    return 0 if controller is None else int(controller.GetLocalProcessId())


def _all_reduce(values: list[int], operation: str) -> list[int]:
    controller = _controller()
    if controller is None:
        return list(values)
    from vtkmodules.vtkCommonCore import vtkIntArray
    from vtkmodules.vtkParallelCore import vtkCommunicator

    send, receive = vtkIntArray(), vtkIntArray()
    send.SetNumberOfTuples(len(values))
    for i, v in enumerate(values):
        send.SetValue(i, int(v))
    op = vtkCommunicator.MIN_OP if operation == "min" else vtkCommunicator.MAX_OP
    controller.AllReduce(send, receive, op)
    return [int(receive.GetValue(i)) for i in range(len(values))]


def all_ranks(flag: bool) -> bool:
    """Whether ``flag`` holds on every rank (a collective call: every rank must make it)."""
    return bool(_all_reduce([1 if flag else 0], "min")[0])


def any_rank(flag: bool) -> bool:
    """Whether ``flag`` holds on at least one rank (a collective call)."""
    return bool(_all_reduce([1 if flag else 0], "max")[0])


def min_max_over_ranks(value: int) -> tuple[int, int]:
    """Smallest and largest ``value`` over the ranks (a collective call)."""
    lo = _all_reduce([int(value)], "min")[0]
    hi = _all_reduce([int(value)], "max")[0]
    return lo, hi
