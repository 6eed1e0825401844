"""Output guards: never write over an input, write to a temporary and then rename.

Every writer of user-named outputs (the command line, the explorer's export) first asks
:func:`refuse_inputs`; the writers in :mod:`vhm_viz.io` then use :func:`atomic_path` (one
file) and :func:`atomic_directory` (several files that belong together, such as the
report of ``vhm-viz analyze``).

An error, a crash or an interrupt never leaves a half-written output or a temporary file,
and an existing file is only replaced once the new one is complete: temporaries are
created and renamed inside :func:`vhm_viz.interrupts.deferred`, and an interrupt received
before the rename stops it. The result gets ordinary permissions (``0o666`` less the
process umask), not the private ``0o600`` of a temporary file.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from vhm_viz import interrupts

__all__ = ["OverwriteError", "same_file", "refuse_inputs", "atomic_path", "atomic_directory"]


class OverwriteError(ValueError):
    """An output that would overwrite one of the inputs (:func:`refuse_inputs`)."""


def same_file(a, b) -> bool:
    """Whether two paths name the same file: same inode (hard links), or same real path."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


def refuse_inputs(output, inputs) -> None:
    """Raise :class:`OverwriteError` if ``output`` is any of ``inputs``.

    The one guard every writer of user-named outputs uses (the command line, the
    explorer's export): whatever path, symbolic link or hard link names an input, it is
    never written.

    Parameters
    ----------
    output : path-like
    inputs : iterable of path-like or None
        Every file the operation reads: the data, the scene, every file the scene
        references (:meth:`vhm_viz.scene.Scene.referenced_files`).
    """
    for src in inputs:
        if src is not None and same_file(Path(src), Path(output)):
            raise OverwriteError(
                f"refusing to overwrite the input file {src} (as {output}); choose another output"
            )


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _sync_file(path: Path) -> None:
    """Flush a written file's data to the disk (before it is renamed into place)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _sync_directory(directory: Path) -> None:
    """Flush a folder's entries (a rename into it) to the disk, where the system allows."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # file systems without directory sync (some network mounts)
    finally:
        os.close(fd)


def _directory_of(path: Path) -> Path:
    directory = path.parent if str(path.parent) else Path(".")
    directory.mkdir(parents=True, exist_ok=True)
    return directory


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    Parameters
    ----------
    path : path-like
        Final output path. Its directory is created if needed.

    Yields
    ------
    Path
        Where to write. It keeps ``path``'s suffix, so writers that pick the format from
        the extension (PyVista, meshio) work unchanged.
    """
    path = Path(path)
    directory = _directory_of(path)
    tmp = None
    try:
        with interrupts.deferred():  # own the temporary before an interrupt can strike
            fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=directory)
            os.close(fd)
            tmp = Path(name)
        yield tmp
        # the data reaches the disk before the name does: a power loss leaves the old file
        # or the whole new one, never an empty file under the final name
        _sync_file(tmp)
        with interrupts.deferred():
            interrupts.check()  # an interrupt received (even one VTK swallowed): no rename
            os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, path)
            tmp = None
        _sync_directory(directory)
    finally:
        if tmp is not None:
            with interrupts.deferred(), contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)


@contextlib.contextmanager
def atomic_directory(directory: str | os.PathLike) -> Iterator[Path]:
    """Yield a staging folder inside ``directory``; on success move its files there.

    Everything written into the staging folder appears in ``directory`` only when the block
    ends without an error or interrupt; otherwise ``directory`` keeps its previous files,
    byte for byte, and the staging folder is removed.

    Parameters
    ----------
    directory : path-like
        Created if needed.

    Yields
    ------
    Path
        The staging folder (hidden, in ``directory``, so the renames stay on one file
        system).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stage = None
    try:
        with interrupts.deferred():
            stage = Path(tempfile.mkdtemp(prefix=".vhm-staging.", dir=directory))
        yield stage
        for item in stage.iterdir():
            if item.is_file():
                _sync_file(item)
        with interrupts.deferred():
            interrupts.check()
            mode = 0o666 & ~_umask()
            for item in sorted(stage.iterdir()):
                os.chmod(item, mode)
                os.replace(item, directory / item.name)
        _sync_directory(directory)
    finally:
        if stage is not None:
            with interrupts.deferred():
                shutil.rmtree(stage, ignore_errors=True)
