"""Agreement between MPI ranks for filters run by ParaView under ``mpiexec``.

In ParaView every rank runs every pipeline update, so a filter can meet the other ranks in
a collective operation at fixed points of ``RequestData``. The filters do that only when
asked (:meth:`DeformationSource.SetParallelReporting`, set by the ParaView plugin): in a
plain VTK script under MPI the ranks need not update together, and a collective would hang.

With one process (or without VTK's parallel module, imported where it is used, as it is
optional in VTK builds) every function here is a no-op.
"""

from __future__ import annotations

import os
import time

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonCore import vtkDoubleArray, vtkIntArray, vtkUnsignedCharArray

__all__ = [
    "LatticeExchange",
    "process_count",
    "rank",
    "all_ranks",
    "any_rank",
    "min_max_over_ranks",
    "check_whole_cage",
    "mpi_command",
    "gather_rows",
    "gather_rows_of",
    "ranks_on_this_machine",
    "send_parts",
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


def ranks_on_this_machine() -> int:
    """How many MPI processes share this machine (its memory and cores).

    From the launcher's environment (Open MPI's ``OMPI_COMM_WORLD_LOCAL_SIZE``, MPICH's
    ``MPI_LOCALNRANKS``); without either, every process is taken to share it (the
    cautious answer for sharing memory). 1 without MPI.
    """
    count = process_count()
    if count <= 1:
        return 1
    for name in ("OMPI_COMM_WORLD_LOCAL_SIZE", "MPI_LOCALNRANKS"):
        value = os.environ.get(name, "")
        if value.isdigit() and int(value) >= 1:
            return min(int(value), count)
    return count


def _all_reduce(values: list[int], operation: str) -> list[int]:
    controller = _controller()
    if controller is None:
        return list(values)
    # the parallel module exists: _controller found it
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


def check_whole_cage(connected: bool, n_points: int) -> None:
    """Raise unless a cage on port 1 reached every rank with the same number of points.

    Collective: every rank calls it, with its own count (0 when nothing arrived).
    """
    lo, hi = min_max_over_ranks(n_points)
    if connected and lo != hi:
        raise RuntimeError(
            f"the Cage input reached the ranks with {lo} to {hi} points: every rank needs "
            "the whole cage (read it with a reader that every rank runs, and do not "
            "distribute it)"
        )


def _all_gather(values) -> np.ndarray:
    """Every rank's float64 ``values``, concatenated in rank order (a collective)."""
    send = ns.numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64).ravel(), deep=1)
    receive = vtkDoubleArray()
    _controller().AllGatherV(send, receive)
    return ns.vtk_to_numpy(receive).copy() if receive.GetNumberOfTuples() else np.zeros(0)


def gather_rows(rows, width: int, ok: bool = True) -> np.ndarray:
    """Every rank's rows ``(n_r, width)`` stacked in rank order, agreeing on failure.

    A collective. ``ok`` False (this rank failed before it): every rank raises, none is
    left waiting. Values travel as float64 (integers below 2**53 exactly).
    """
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, width) if ok else np.zeros((0, width))
    got = _all_gather(np.concatenate([[1.0 if ok else 0.0, float(len(rows))], rows.ravel()]))
    out, pos, failed = [], 0, []
    for r in range(process_count()):
        n = int(got[pos + 1])
        if got[pos] == 0:
            failed.append(r)
        out.append(got[pos + 2 : pos + 2 + n * width].reshape(n, width))
        pos += 2 + n * width
    if failed:
        raise RuntimeError(f"rank {failed[0]} failed")
    return np.concatenate(out) if out else np.zeros((0, width))


def gather_rows_of(compute, width: int) -> np.ndarray:
    """:func:`gather_rows` of ``compute()``: an error on any rank stops every rank.

    The failing rank raises its own error; the others a RuntimeError naming it.
    """
    error, rows = None, np.zeros((0, width))
    try:
        rows = compute()
    except Exception as exc:  # noqa: BLE001 -- agreed with the other ranks, then raised
        error = exc
    try:
        return gather_rows(rows, width, error is None)
    except RuntimeError:
        if error is not None:
            raise error from None
        raise


def send_parts(make_part, fields: dict) -> list:
    """Hand rank ``q`` its part ``make_part(q)`` (a dict of ``fields`` arrays); gather mine.

    ``fields``: name -> (trailing shape, dtype); each field's leading length travels with
    it, and its values as they are (bytes: any dtype, 64-bit integers too, exactly). A
    field may also be an ``(array, index)`` pair, the rows ``array[index]``: they are
    copied straight into the buffer (no copy of the part besides the buffer). A
    collective: for each rank in turn the others send to it (point to point: each part
    goes to its rank only, freed as it is packed, its buffer freed once sent). The parts
    for the others are made first, then this rank's own part, then the exchange runs:
    ``make_part(me)`` may release what the others' parts were taken from. With more than
    two ranks a rank thus holds all its outgoing parts (packed) at once, and receives
    before it has sent them all. An error making a part, on any rank, stops every rank
    before any part is sent (the failing rank raises its own error). Returns the parts
    for this rank, in rank order: its own part as ``make_part`` made it ((array, index)
    pairs too), a received part's arrays (writeable) views of the one buffer it came in.
    """
    controller = _controller()
    me, n = rank(), process_count()
    if controller is None:
        return [make_part(0)]
    # every part this rank sends is made (and packed) first, then its own part, and only
    # then does anything arrive: a source that the own part releases (the window's
    # lattice) is gone before the others' parts come in, so the lattice and the incoming
    # parts are never held together. All the parts are made before any message: a rank
    # failing to make one (memory) is agreed here, and every rank raises rather than
    # waiting for its parts
    outgoing = {}
    got = [None] * n

    def make_all():
        for q in range(n):
            if q != me:
                outgoing[q] = pack_part(make_part(q), fields)
        got[me] = make_part(me)
        return np.zeros((0, 1))

    gather_rows_of(make_all, 1)
    for q in range(n):
        if q == me:
            for r in range(n):
                if r != q:
                    buffer = vtkUnsignedCharArray()
                    controller.Receive(buffer, r, 9317)
                    got[r] = unpack_part(ns.vtk_to_numpy(buffer), fields)
                    del buffer
        else:
            packed = outgoing.pop(q)
            controller.Send(ns.numpy_to_vtk(packed, deep=0), q, 9317)
            del packed
    return got


def pack_part(part: dict, fields: dict) -> np.ndarray:
    """A part of :func:`send_parts` in one uint8 buffer: per field its length, then its bytes.

    Straight into the buffer, each field released once copied: a part, a large share of
    a round's values, is never held twice. Each field starts 8-byte aligned.

    Parameters
    ----------
    part : dict
        Field name -> array of shape ``(m,) + shape``, or an ``(array, index)`` pair that
        stands for the rows ``array[index]`` (taken straight into the buffer, converted
        to the field's dtype). The caller's dict is left as it was.
    fields : dict
        Field name -> ``(shape, dtype)``, the trailing shape and dtype of each field, in
        the order they are packed.

    Returns
    -------
    numpy.ndarray
        ``(nbytes,)`` uint8, a multiple of 8 bytes; :func:`unpack_part` reads it back.
    """
    part = dict(part)
    rows = {name: _row_count(part[name], shape) for name, (shape, _) in fields.items()}
    nbytes = [rows[name] * int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
              for name, (shape, dtype) in fields.items()]  # fmt: skip
    sizes = [8 + b + (-b % 8) for b in nbytes]
    flat = np.empty(int(sum(sizes)), dtype=np.uint8)
    pos = 0
    for (name, (shape, dtype)), size, b in zip(fields.items(), sizes, nbytes, strict=True):
        flat[pos : pos + 8] = np.array([rows[name]], dtype=np.int64).view(np.uint8)
        view = flat[pos + 8 : pos + 8 + b].view(dtype).reshape((rows[name],) + tuple(shape))
        value = part.pop(name)
        if isinstance(value, tuple):  # rows of an array: taken straight into the buffer
            source, index = value
            if source.dtype == view.dtype:
                # (mode "clip": "raise" would take through a temporary copy)
                np.take(source, index, axis=0, out=view, mode="clip")
            else:
                view[...] = source[index]
        else:
            view[...] = np.asarray(value, dtype=dtype).reshape(view.shape)
        flat[pos + 8 + b : pos + size] = 0  # each field 8-byte aligned
        pos += size
        del value, view
    return flat


def unpack_part(flat: np.ndarray, fields: dict) -> dict:
    """The part packed by :func:`pack_part` into ``flat``, as views of it (no copies).

    The buffer lives as long as one of them does.

    Parameters
    ----------
    flat : numpy.ndarray
        ``(nbytes,)`` uint8 buffer made by :func:`pack_part` with the same ``fields``.
    fields : dict
        Field name -> ``(shape, dtype)``, as given to :func:`pack_part`.

    Returns
    -------
    dict
        Field name -> array of shape ``(m,) + shape``, values exactly as packed.
    """
    part, pos = {}, 0
    for name, (shape, dtype) in fields.items():
        m = int(flat[pos : pos + 8].view(np.int64)[0])
        size = m * int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
        values = flat[pos + 8 : pos + 8 + size].view(dtype)
        part[name] = values.reshape((m,) + tuple(shape))
        pos += 8 + size + (-size % 8)
    return part


def _row_count(value, shape) -> int:
    """Leading length of a field of :func:`send_parts` (an array or an (array, index) pair)."""
    if isinstance(value, tuple):
        return len(value[1])
    return int(np.size(value) // max(int(np.prod(shape, dtype=np.int64)), 1))


class LatticeExchange:
    """Exact evaluations of a lattice build shared by the MPI ranks, once each.

    The ``exchange`` of :func:`~vhm_viz.core.lattice.build_lattice`. Each round gathers
    the lattice points (keys) every rank needs and drops the duplicates -- the same point
    in two ranks' windows, or every point when each rank builds the whole lattice -- so
    that each is evaluated once, by one rank; then each rank receives the values of its
    own points from the ranks that evaluated them (point to point: no rank holds the
    whole round's values). A point's data depends on the point alone, so each rank gets
    the values a serial build computes, bit for bit, whoever evaluated them.

    **Shares.** The ranks' other work between rounds differs (a rank whose window holds
    more of the cage refines more cells), and a rank that is behind would keep the others
    waiting at the next round. So each round's points go to the ranks in proportion to
    what evens out their busy time so far (measured, excluding the waits), at the exact
    evaluations' measured cost per point; the first round splits them equally. Which
    rank evaluates a point never changes its value. Points are dealt in runs of
    neighbours taken in a hashed order (:func:`dealing_order`), so that each share mixes
    points inside and outside the cage (which cost differently).

    **Errors.** An error on one rank (an abort, memory) is agreed in the round it happens,
    or in the next one (:meth:`abandon`, when the build failed between rounds): every rank
    raises and none waits for the others. With one process every call evaluates locally.
    """

    def __init__(self):
        self._over = False  # a failure every rank has seen: no more rounds
        self._busy = 0.0  # seconds of work since the build began, waits excluded
        self._left_at = None  # when this rank left the last round
        self._seconds = 0.0  # exact evaluations here: seconds and points, for the cost
        self._points = 0
        #: Points this rank evaluated, and the distinct points of all rounds.
        self.evaluated = 0
        self.distinct = 0

    def __call__(self, keys, evaluate):
        """One round: ``evaluate`` this rank's share of every rank's ``keys``.

        Parameters
        ----------
        keys : (N,) int64 array_like
            Lattice point keys this rank needs in this round.
        evaluate : callable
            ``evaluate(keys) -> (f (M, 3), fu (M, 3, 3), inside (M,) bool)``, the exact
            map at points of any rank.

        Returns
        -------
        tuple of arrays
            ``f``, ``fu`` and ``inside`` at this rank's ``keys``, in their order.
        """
        if _controller() is None:
            return evaluate(keys)
        now = time.perf_counter()
        if self._left_at is not None:
            self._busy += now - self._left_at
        keys = np.ascontiguousarray(keys, dtype=np.int64).ravel()
        header = _all_gather(
            [1.0, float(len(keys)), self._busy, self._seconds, float(self._points)]
        ).reshape(-1, 5)
        failed = np.nonzero(header[:, 0] == 0)[0]
        if failed.size:
            self._over = True
            raise RuntimeError(f"rank {int(failed[0])} failed while building the lattice")
        counts = header[:, 1].astype(np.int64)
        if not counts.any():
            self._left_at = time.perf_counter()
            return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, dtype=bool)
        me, n = rank(), len(counts)
        # keys are below 2**53: exact as float64
        everyone = _all_gather(keys.astype(np.float64)).astype(np.int64)
        distinct, inverse = np.unique(everyone, return_inverse=True)
        inverse = inverse.ravel()
        del everyone
        order = dealing_order(len(distinct))
        bounds = np.concatenate([[0], np.cumsum(balanced_shares(len(distinct), header))])
        owner = np.empty(len(distinct), dtype=np.int32)  # who evaluates each point
        for r in range(n):
            owner[order[bounds[r] : bounds[r + 1]]] = r
        mine = order[bounds[me] : bounds[me + 1]]
        del order
        error, values = None, None
        t0 = time.perf_counter()
        try:
            f, fu, inside = evaluate(distinct[mine])
            values = {"f": f, "fu": fu.reshape(-1, 9), "inside": inside}
            del f, fu, inside
            self._seconds += time.perf_counter() - t0
            self._points += len(mine)
        except BaseException as exc:  # noqa: BLE001 -- agreed below, then re-raised
            error = exc
        self._busy += time.perf_counter() - t0
        # each rank gets the values of its own keys only (every rank's would hold the
        # whole round's results twice on every rank); the values go out as rows of the
        # evaluated arrays, taken straight into the send buffers and into this rank's own
        # arrays, never stacked into one table first (a copy of the finest round)
        row = np.full(len(distinct), -1, dtype=np.int64)
        row[mine] = np.arange(len(mine))
        starts = np.concatenate([[0], np.cumsum(counts)])

        def part_for(q):
            if values is None:
                return {"ok": np.zeros(1, dtype=np.uint8), "f": np.zeros((0, 3)),
                        "fu": np.zeros((0, 9)), "inside": np.zeros(0, dtype=bool)}  # fmt: skip
            need = inverse[starts[q] : starts[q + 1]]  # q's keys, in its order
            at = row[need[owner[need] == me]]
            return {"ok": np.ones(1, dtype=np.uint8),
                    **{name: (a, at) for name, a in values.items()}}  # fmt: skip

        got = send_parts(part_for, _VALUE_FIELDS)
        values = None  # (this rank's own part still holds what it takes of them)
        bad = [r for r, part in enumerate(got) if not part["ok"][0]]
        if bad:
            self._over = True
            if error is not None:
                raise error
            raise RuntimeError(f"rank {bad[0]} failed while building the lattice")
        self.evaluated += len(mine)
        self.distinct += len(distinct)
        who = owner[inverse[starts[me] : starts[me + 1]]]
        m = len(keys)
        f, fu, inside = np.empty((m, 3)), np.empty((m, 9)), np.empty(m, dtype=bool)
        for r in range(n):
            part, got[r] = got[r], None
            at = np.flatnonzero(who == r)
            for name, out in (("f", f), ("fu", fu), ("inside", inside)):
                value = part.pop(name)
                out[at] = value[0][value[1]] if isinstance(value, tuple) else value
            del part, value
        self._left_at = time.perf_counter()
        return f, fu.reshape(-1, 3, 3), inside

    def abandon(self) -> None:
        """Tell the other ranks, in the next round, that this rank's build failed."""
        if self._over or _controller() is None:
            return
        self._over = True
        _all_gather([0.0, 0.0, 0.0, 0.0, 0.0])


#: What :class:`LatticeExchange` sends: a status, then each point's value, u-Jacobian
#: (row-major) and side of the cage.
_VALUE_FIELDS = {"ok": ((), np.uint8), "f": ((3,), np.float64), "fu": ((9,), np.float64),
                 "inside": ((), np.bool_)}  # fmt: skip

#: Sorted lattice keys dealt together (neighbours along i, then j).
DEAL_RUN = 4096


def dealing_order(n: int) -> np.ndarray:
    """The order in which ``n`` sorted lattice keys are dealt out to the ranks.

    Runs of ``DEAL_RUN`` consecutive keys in a fixed pseudo-random order of runs
    (Fibonacci hashing). Runs of neighbours keep the exact evaluations' speed (the
    kernel's branches follow the geometry, so neighbours take the same branches, which a
    fully hashed order would mix). The hashed order of the runs mixes
    inside and outside points in every share.

    Parameters
    ----------
    n : int
        Number of sorted keys.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` int64 permutation of ``range(n)``: whole runs, each ascending by one.
    """
    run = np.arange(n, dtype=np.uint64) // np.uint64(DEAL_RUN)
    return np.argsort(run * np.uint64(0x9E3779B97F4A7C15), kind="stable")


def balanced_shares(n: int, header: np.ndarray) -> np.ndarray:
    """Points per rank that even out the ranks' busy seconds (see :class:`LatticeExchange`).

    The same ``header`` on every rank (gathered), so every rank computes the same shares.

    Parameters
    ----------
    n : int
        Number of points to deal out.
    header : numpy.ndarray
        ``(ranks, 5)`` float rows: status, own points, busy seconds, and the seconds and
        points of exact evaluations so far.

    Returns
    -------
    numpy.ndarray
        ``(ranks,)`` int64 non-negative shares summing to ``n``; equal (the remainder to
        the first ranks) while no cost is known.
    """
    n_ranks = len(header)
    equal = np.full(n_ranks, n // n_ranks) + (np.arange(n_ranks) < n % n_ranks)
    seconds, points = header[:, 3].sum(), header[:, 4].sum()
    if points <= 0 or seconds <= 0:
        return equal
    cost = seconds / points  # per point
    busy = header[:, 2]
    target = (busy.sum() + n * cost) / n_ranks  # everyone's busy time after this round
    want = np.clip((target - busy) / cost, 0.0, None)
    if want.sum() <= 0:
        return equal
    scaled = want * (n / want.sum())
    share = np.floor(scaled).astype(np.int64)
    share[np.argsort(-(scaled - share), kind="stable")[: n - share.sum()]] += 1
    return share
