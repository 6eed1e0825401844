"""Reading in a forked child process: a reader that crashes takes only the child with it.

A library reader (VTK's, in C++) that dereferences a corrupt count ends the process it
runs in. :func:`read_isolated` runs it in a child and turns a crash into a
:class:`~vhm_viz.io.ReadError` naming the file; the child's address space is capped, so
a corrupt count cannot exhaust the machine's memory either. While the child reads, this
process does the work :func:`meanwhile` hands it, if any.

What a library prints on stderr is not for the user, who reads the one line vhm_viz
words of what went wrong: the child's stderr goes nowhere, and
:func:`native_stderr_silenced` sends this process's there while a library works in it
(ITK's writers).
"""

from __future__ import annotations

import contextlib
import faulthandler
import os
import pickle
import signal
import sys
import threading
from pathlib import Path

import numpy as np

from vhm_viz import interrupts
from vhm_viz.io.errors import ReadError, first_line
from vhm_viz.resources import memory_limit

__all__ = ["meanwhile", "native_stderr_silenced", "read_isolated"]

#: The work handed to the reads in progress (:func:`meanwhile`), innermost last; each a
#: list holding the work until a read (or the block's end) takes it.
_pending: list[list] = []


@contextlib.contextmanager
def meanwhile(work):
    """Run ``work()`` here while a forked child reads, in the block; else when it ends.

    Work a process would do anyway, done while it waits for the child instead of after:
    the first read in a child within the block runs it once, after the fork; if no read in
    the block forks (a format read in this process), it runs when the block ends, unless
    the block raises.

    Parameters
    ----------
    work : callable() or None
        None: nothing to do.
    """
    held = [] if work is None else [work]
    _pending.append(held)
    try:
        yield
    finally:
        _pending.remove(held)
    if held:
        held.pop()()


#: Guards :data:`_silenced`: the blocks of :func:`native_stderr_silenced` open (in all
#: threads) and the descriptor of the stderr they put back, while any is open.
_silencing = threading.Lock()
_silenced = {"blocks": 0, "stderr": -1}


@contextlib.contextmanager
def native_stderr_silenced():
    """In the block, what is printed on stderr (file descriptor 2) goes to the null device.

    For a library that prints its own diagnostics beside the exception it raises, or
    instead of one (ITK's NIfTI writer's ``** ERROR: NWAD: wrote only ...``): the caller
    words what went wrong in one line. Python's own prints in the block go too. Blocks
    open in several threads at once share the redirection; stderr comes back when the
    last one ends.
    """
    sys.stderr.flush()  # what was printed before the block is not lost with it
    with _silencing:
        if _silenced["blocks"] == 0:
            _silenced["stderr"] = os.dup(2)
            quiet = os.open(os.devnull, os.O_WRONLY)
            os.dup2(quiet, 2)
            os.close(quiet)
        _silenced["blocks"] += 1
    try:
        yield
    finally:
        with _silencing:
            _silenced["blocks"] -= 1
            if _silenced["blocks"] == 0:
                os.dup2(_silenced["stderr"], 2)
                os.close(_silenced["stderr"])


def _take_pending() -> None:
    """Run the innermost block's work (:func:`meanwhile`), if no read has taken it yet."""
    if _pending and _pending[-1]:
        _pending[-1].pop()()


def read_isolated(path, read, what: str = "the reader"):
    """``read(path)`` in a forked child process (where there is fork), its result here.

    The child sends the dataset back pickled (PyVista serialises it with VTK's own
    writer); an image's direction, which that serialisation drops, travels beside it.

    Parameters
    ----------
    path : path-like
        The file (or folder) read; it sizes the child's memory cap and is named in
        messages.
    read : callable
        ``read(path) -> pyvista.DataSet``, run in the child.
    what : str
        The reader, as messages name it (``"VTK's .ply reader"``).

    Returns
    -------
    pyvista.DataSet
        What ``read`` returned.

    Raises
    ------
    ReadError
        The child crashed (a signal or no result), or ``read`` raised (its first line).
    """
    p = Path(path)
    if not hasattr(os, "fork"):  # pragma: no cover - Windows: the header checks alone must do
        with native_stderr_silenced():
            return read(p)
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child (coverage does not follow the fork)
        status = 0
        try:
            faulthandler.disable()  # a crash here is expected and reported by the parent
            os.close(read_end)
            # what a library prints (MetaIO's complaints on std::cerr, the HDF5 diagnostics
            # of ITK's format probes) is not for the user: the child's result or error
            # goes back through the pipe, as one line
            quiet = os.open(os.devnull, os.O_WRONLY)
            os.dup2(quiet, 1)
            os.dup2(quiet, 2)
            _limit_memory(p)
            try:
                payload = ("ok", _parcel(read(p)))
            except BaseException as exc:  # noqa: BLE001 - everything goes back as text
                payload = ("error", first_line(exc))
            with os.fdopen(write_end, "wb") as fh:
                pickle.dump(payload, fh, protocol=pickle.HIGHEST_PROTOCOL)
        except BaseException:  # noqa: BLE001
            status = 1
        finally:
            os._exit(status)
    os.close(write_end)
    try:
        interrupts.check()  # a signal during the fork may have been swallowed by its hooks
        _take_pending()
        with os.fdopen(read_end, "rb") as fh:
            blob = fh.read()
        _, status = os.waitpid(pid, 0)
        pid = None
    finally:
        if pid is not None:  # interrupted while waiting: do not leave the child behind
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) or not blob:
        how = (
            f"signal {signal.Signals(os.WTERMSIG(status)).name}"
            if os.WIFSIGNALED(status)
            else f"exit status {os.WEXITSTATUS(status)}"
        )
        raise ReadError(f"{p}: {what} crashed on this file ({how}): corrupt file")
    kind, value = pickle.loads(blob)  # noqa: S301 - our own child's data
    if kind == "error":  # a ReadError of the reader names the file already
        raise ReadError(value if value.startswith(f"{p}: ") else f"{p}: cannot read ({value})")
    return _unpack(value)


def _parcel(data):
    """What the child sends back of a dataset ``read`` returned (:func:`_unpack` opens it).

    An image with numeric arrays goes as its grid and its arrays' numpy data, which pickle
    writes as they are in memory. Anything else goes as the dataset, which PyVista pickles
    through VTK's legacy writer (several times slower for a large image, and without the
    image's direction, which travels beside it).
    """
    import pyvista as pv

    if isinstance(data, pv.ImageData) and not data.field_data.keys():
        arrays = {
            where: [(name, np.asarray(part[name])) for name in part.keys()]
            for where, part in (("point", data.point_data), ("cell", data.cell_data))
        }
        if all(a.dtype.kind in "biuf" for part in arrays.values() for _, a in part):
            grid = {
                "extent": tuple(data.extent),
                "origin": tuple(data.origin),
                "spacing": tuple(data.spacing),
                "direction": np.array(data.direction_matrix, dtype=np.float64),
                "active": (data.point_data.active_scalars_name, data.cell_data.active_scalars_name),
            }
            return "image", (grid, arrays)
    direction = np.array(data.direction_matrix) if hasattr(data, "direction_matrix") else None
    return "dataset", (data, direction)


def _unpack(parcel):
    """The dataset of a child's :func:`_parcel`."""
    import pyvista as pv

    kind, (first, second) = parcel
    if kind == "image":
        grid, arrays = first, second
        image = pv.ImageData()
        image.extent = grid["extent"]
        image.origin = grid["origin"]
        image.spacing = grid["spacing"]
        image.direction_matrix = grid["direction"]
        for where, part in (("point", image.point_data), ("cell", image.cell_data)):
            for name, values in arrays[where]:
                part[name] = values
        for part, name in zip((image.point_data, image.cell_data), grid["active"], strict=True):
            if name is not None:
                part.active_scalars_name = name
        return image
    data, direction = first, second
    if direction is not None:
        data.direction_matrix = direction
    return data


def _limit_memory(p: Path) -> None:
    """Cap the reading child's address space: a corrupt count cannot exhaust the machine.

    What it may add to what the process already maps: 2 GiB, 64 times the file (folder)
    size, or half the memory this process may still take (:func:`memory_limit`),
    whichever is most. The last keeps a compressed file that expands a hundredfold
    readable: the child holds the dataset and its pickled copy at once.
    """
    try:
        import resource

        size = sum(f.stat().st_size for f in p.iterdir()) if p.is_dir() else p.stat().st_size
        with open("/proc/self/statm") as fh:
            mapped = int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        room = memory_limit().available or 0
        resource.setrlimit(resource.RLIMIT_AS, (mapped + max(2 << 30, 64 * size, room // 2),) * 2)
    except (ImportError, OSError, ValueError):  # pragma: no cover - not Linux
        pass
