"""Output guards: never write over an input; outputs appear whole or not at all.

Every writer of user-named outputs (the command line, the explorer's export) first asks
:func:`vhm_viz.io.refuse_inputs`; the writers in :mod:`vhm_viz.io` then use
:func:`atomic_output_set` (several files that belong together: a MetaImage header and its
voxels), :func:`atomic_path` (one file) or :func:`atomic_directory` (the files of a
report folder, such as that of ``vhm-viz analyze``).

An error, a crash or an interrupt never leaves a half-written output or a temporary file,
and an existing output is only replaced once the new one is complete and on the disk
(``fsync`` of the files, then of their folder): temporaries are created and renamed
inside :func:`vhm_viz.interrupts.deferred`, and an interrupt received before the renames
stops them. A process killed outright (SIGKILL) leaves the previous outputs, or a journal
that the next write in that folder completes; that write also removes the temporaries of
processes that no longer run (:func:`remove_stale_temporaries`), whose names say what
they are (``.out.vhm-tmp-PID-N.vti``). The result gets ordinary permissions (``0o666``
less the process umask), not the private ``0o600`` of a temporary file.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import json
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

from vhm_viz import interrupts

__all__ = [
    "OverwriteError",
    "UnwritableFolderError",
    "WriteError",
    "require_writable",
    "same_file",
    "atomic_output_set",
    "atomic_path",
    "atomic_directory",
    "remove_stale_temporaries",
    "remove_temporaries_in_progress",
    "process_running",
]


class OverwriteError(ValueError):
    """An output that would overwrite one of the inputs (:func:`vhm_viz.io.refuse_inputs`)."""


class UnwritableFolderError(OSError):
    """A folder an output cannot be written in (permissions, a read-only or full disk).

    Its text names the folder, not the hidden temporary the write began with.
    """

    def __str__(self) -> str:
        return str(self.strerror)


class WriteError(OSError):
    """A write that failed part-way (a full disk or quota, a file-size limit).

    Its text names the output, not the temporary it was written as.
    """

    def __str__(self) -> str:
        return str(self.strerror)


def _unwritable(folder: Path, code: int | None, reason: str) -> UnwritableFolderError:
    return UnwritableFolderError(
        code, f"cannot write in {folder}/ ({reason}); choose another output folder"
    )


@contextlib.contextmanager
def _writing_in(folder: Path) -> Iterator[None]:
    """Turn a failure to create a file or folder in ``folder`` into its one line."""
    try:
        yield
    except FileExistsError:
        raise
    except OSError as exc:
        raise _unwritable(folder, exc.errno, exc.strerror or type(exc).__name__) from exc


def require_writable(folder) -> None:
    """Raise :class:`UnwritableFolderError` if this process may not create files in ``folder``.

    A folder that does not exist yet is asked of the nearest one above it that does (where
    it would be created). Checked before the work that the output waits for; the write
    itself reports what the permissions cannot tell (a read-only or full disk).
    """
    here = Path(os.path.abspath(folder))
    while not here.exists() and here.parent != here:
        here = here.parent
    if here.is_dir() and not os.access(here, os.W_OK | os.X_OK):
        raise _unwritable(here, errno.EACCES, "permission denied")


def same_file(a, b) -> bool:
    """Whether two paths name the same file: same inode (hard links), or same real path."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


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
    with _writing_in(directory.parent):
        directory.mkdir(parents=True, exist_ok=True)
    return directory


@contextlib.contextmanager
def atomic_output_set(paths) -> Iterator[list[Path]]:
    """Yield a temporary path for each of ``paths``; on success move them all into place.

    The one home of atomic outputs: :func:`atomic_path` (one file) and
    :func:`atomic_directory` (a report folder) are made of it, and writers of several
    files that belong together (a MetaImage ``.mhd`` header and its ``.raw`` voxels, a
    field and its mask) use it directly.

    Each temporary is a hidden sibling of its output, ``.NAME.vhm-tmp-PID-N.SUFFIX`` (the
    suffix kept, for writers that choose the format by it). When the block ends without
    an error or interrupt, every temporary is flushed to the disk, a journal listing the
    moves is written (for a set of several files), the temporaries are renamed onto the
    outputs in the order given (the header, which names the others, last), the folder is
    flushed and the journal removed. On an error or interrupt the temporaries are removed
    and every output keeps its previous bytes. A process killed (SIGKILL, power loss)
    leaves either the previous set, or a journal that the next atomic write in that
    folder (any ``vhm-viz`` command writing there) completes, giving the whole new set;
    that next write also removes every temporary of processes that no longer run.

    Parameters
    ----------
    paths : sequence of path-like
        The outputs, in the order they are to appear (the file that refers to the others
        last). Their folders are created if needed.

    Yields
    ------
    list of Path
        Where to write each output, in the order of ``paths``.
    """
    finals = [Path(p) for p in paths]
    # outputs in a folder an enclosing atomic_directory block stages: written into its
    # staging folder, moved with the rest of that set when the block ends
    staged = {k: _enclosing[_key(p.parent)] / p.name
              for k, p in enumerate(finals) if _key(p.parent) in _enclosing}  # fmt: skip
    own = [p for k, p in enumerate(finals) if k not in staged]
    for directory in {_directory_of(p) for p in own}:
        remove_stale_temporaries(directory)
    temps: list[Path] = []
    try:
        with interrupts.deferred():  # own the temporaries before an interrupt can strike
            for final in own:
                temps.append(_create_temporary(final))
                _in_progress.add(temps[-1])
        mine = iter(temps)
        where = [staged[k] if k in staged else next(mine) for k in range(len(finals))]
        with _naming_outputs(list(zip(where, finals, strict=True))):
            yield where
        for tmp in temps:
            # the data reaches the disk before the names do: a power loss leaves the old
            # file or the whole new one, never an empty file under the final name
            _sync_file(tmp)
        with interrupts.deferred():
            interrupts.check()  # an interrupt received (even one VTK swallowed): no rename
            _commit(list(zip(temps, own, strict=True)))
            _in_progress.difference_update(temps)
            temps = []
    finally:
        if temps:
            with interrupts.deferred():
                for tmp in temps:
                    _remove(tmp)
                _in_progress.difference_update(temps)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    :func:`atomic_output_set` of one file.

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
    with atomic_output_set([path]) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_directory(directory: str | os.PathLike, last: str | None = None) -> Iterator[Path]:
    """Yield a staging folder beside the files of ``directory``; on success move its files there.

    Everything written into the staging folder appears in ``directory`` as one set
    (:func:`atomic_output_set`: the previous files or the new ones, never a mix) when the
    block ends without an error or interrupt; otherwise ``directory`` keeps its previous
    files, byte for byte, and the staging folder is removed (with ``directory`` itself when
    the block created it and it is still empty). Atomic writes of this process
    into ``directory`` inside the block (:func:`atomic_path`, :func:`atomic_output_set`, a
    nested :func:`atomic_directory`) join the set: the command line writes an image, the
    arrays beside it and a displacement field as one set this way.

    Parameters
    ----------
    directory : path-like
        Created if needed.
    last : str, optional
        The name of the file to move last (the one that describes the others); the
        others move in name order.

    Yields
    ------
    Path
        The staging folder (hidden, ``.vhm-staging.PID-N`` in ``directory``, so the renames
        stay on one file system).
    """
    directory = Path(directory)
    if _key(directory) in _enclosing:  # inside a block staging this folder: part of its set
        yield _enclosing[_key(directory)]
        return
    created = _missing_folders(directory)
    with _writing_in(directory.parent):
        directory.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(directory)
    stage = None
    committed = False
    try:
        with interrupts.deferred(), _writing_in(directory):
            stage = directory / f".vhm-staging.{_token()}"
            stage.mkdir()
            _in_progress.add(stage)
            _enclosing[_key(directory)] = stage
        with _naming_outputs([(stage, directory)]):
            yield stage
        names = sorted(p.name for p in stage.iterdir() if p.is_file())
        if last in names:
            names.remove(last)
            names.append(last)
        for name in names:
            _sync_file(stage / name)
        with interrupts.deferred():
            interrupts.check()
            _commit([(stage / n, directory / n) for n in names])
            committed = True
    finally:
        if stage is not None:
            with interrupts.deferred():
                _enclosing.pop(_key(directory), None)
                shutil.rmtree(stage, ignore_errors=True)
                _in_progress.discard(stage)
        if not committed:  # no new set: the folders made for it go too (if still empty)
            for folder in created:
                try:
                    folder.rmdir()
                except OSError:
                    break


def _missing_folders(directory: Path) -> list[Path]:
    """The folders that creating ``directory`` makes, innermost first."""
    missing = []
    here = Path(os.path.abspath(directory))
    while not here.exists() and here.parent != here:
        missing.append(here)
        here = here.parent
    return missing


@contextlib.contextmanager
def _naming_outputs(pairs: list[tuple[Path, Path]]) -> Iterator[None]:
    """Word a failed write (a full disk, a file-size limit) with the output, not its temporary.

    ``pairs`` are (where it is written: a temporary or staging folder, the output). An
    ``OSError`` of the system (an errno, as a full disk raises it) becomes a
    :class:`WriteError` ``could not write OUTPUT: REASON``, the output that of the file it
    names, else the last (the file a set is read by); a message a writer worded names the
    outputs in place of their temporaries and staging folders.
    """
    try:
        yield
    except UnwritableFolderError:
        raise
    except OSError as exc:
        if exc.strerror and not isinstance(exc, WriteError):
            final = _output_of(exc.filename, pairs) if exc.filename is not None else None
            final = pairs[-1][1] if final is None else final
            raise WriteError(exc.errno, f"could not write {final}: {exc.strerror}") from exc
        text = str(exc)
        for written, final in pairs:
            # a file staged for the current folder is named as given: "x.vti", not "./x.vti"
            inside = "" if os.fspath(final) == "." else os.fspath(final) + os.sep
            text = text.replace(os.fspath(written) + os.sep, inside)
            text = text.replace(os.fspath(written), os.fspath(final))
        if text == str(exc):
            raise
        raise WriteError(exc.errno, text) from exc


def _output_of(name, pairs: list[tuple[Path, Path]]) -> Path | None:
    """The output written as ``name`` (a temporary, or a file in a staging folder)."""
    here = os.path.abspath(name)
    for written, final in pairs:
        there = os.path.abspath(written)
        if here == there:
            return final
        if here.startswith(there + os.sep):
            return final / os.path.relpath(here, there)
    return None


#: This process's temporaries and staging folders not yet renamed or removed.
_in_progress: set[Path] = set()

#: Folder -> the staging folder of the :func:`atomic_directory` block open on it: every
#: atomic write into that folder meanwhile joins the block's set.
_enclosing: dict[Path, Path] = {}


def _key(directory: Path) -> Path:
    return Path(os.path.abspath(directory if str(directory) else "."))


def remove_temporaries_in_progress() -> None:
    """Remove this process's temporaries of unfinished writes (before it ends at once).

    For :func:`vhm_viz.interrupts.ending_now`: the outputs keep their previous bytes.
    """
    for path in list(_in_progress):
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            _remove(path)
        _in_progress.discard(path)


#: A temporary, staging folder or journal of :func:`atomic_output_set`; group 1 is the PID.
_TEMPORARY = re.compile(r"\.vhm-(?:tmp-|staging\.|set-)(\d+)-\d+")
_counter = itertools.count()


def _token() -> str:
    """``PID-N``: unique within this process, its PID readable by the next run."""
    return f"{os.getpid()}-{next(_counter)}"


def _create_temporary(final: Path) -> Path:
    """Create (exclusively, private) the hidden temporary of ``final``: ``.NAME.vhm-tmp-...``."""
    head, dot, tail = final.name.partition(".")
    while True:
        tmp = final.with_name(f".{head}.vhm-tmp-{_token()}{dot}{tail}")
        try:
            with _writing_in(final.parent):
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
            return tmp
        except FileExistsError:
            continue


def _commit(moves: list[tuple[Path, Path]]) -> None:
    """Rename each temporary onto its output, in order, under a journal when several."""
    journal = None
    if len(moves) > 1:
        journal = moves[-1][1].parent / f".vhm-set-{_token()}.json"
        text = json.dumps([[os.fspath(t.absolute()), os.fspath(f.absolute())] for t, f in moves])
        part = journal.with_name(journal.name + ".part")
        try:
            part.write_text(text, encoding="utf-8")
            _sync_file(part)
            os.replace(part, journal)
        finally:
            _remove(part)  # gone after the rename; removed after a failed write
        _sync_directory(journal.parent)
    mode = 0o666 & ~_umask()
    for tmp, final in moves:
        os.chmod(tmp, mode)
        os.replace(tmp, final)
    for directory in {final.parent for _, final in moves}:
        _sync_directory(directory)
    if journal is not None:
        _remove(journal)


def process_running(pid: int) -> bool:
    """Whether process ``pid`` still runs (files named after it belong to a live process)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (PermissionError): alive
        return True
    return True


def remove_stale_temporaries(directory: str | os.PathLike) -> list[str]:
    """Finish or remove what killed processes left in ``directory``.

    A journal of a set whose process no longer runs is completed first (its remaining
    temporaries are renamed onto their outputs: the set was complete on the disk when the
    journal was written); then every temporary and staging folder of a process that no
    longer runs is removed. Those of running processes are left alone.

    Parameters
    ----------
    directory : path-like

    Returns
    -------
    list of str
        The names handled (journals completed, temporaries removed).
    """
    directory = Path(directory)
    try:
        entries = [e for e in os.scandir(directory) if _TEMPORARY.search(e.name)]
    except OSError:
        return []
    stale = [e for e in entries if not process_running(int(_TEMPORARY.search(e.name).group(1)))]
    handled = []
    for entry in sorted(stale, key=lambda e: not e.name.startswith(".vhm-set-")):
        path = Path(entry.path)
        if entry.name.startswith(".vhm-set-") and entry.name.endswith(".json"):
            _roll_forward(path)
        elif entry.is_dir(follow_symlinks=False):
            shutil.rmtree(path, ignore_errors=True)
        else:
            _remove(path)
        handled.append(entry.name)
    return handled


def _roll_forward(journal: Path) -> None:
    """Complete the moves a killed process's journal lists, then remove the journal."""
    try:
        moves = json.loads(journal.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        moves = []
    if not isinstance(moves, list) or not all(isinstance(m, list) for m in moves):
        moves = []
    owner = _TEMPORARY.search(journal.name).group(1)
    mode = 0o666 & ~_umask()
    moves = [m for m in moves if len(m) == 2 and all(isinstance(s, str) for s in m)]
    for tmp, final in moves:
        match = _TEMPORARY.search(Path(tmp).name)
        if match is None or match.group(1) != owner:
            continue  # only the journal's own process's temporaries are moved
        with contextlib.suppress(OSError):  # already moved
            os.chmod(tmp, mode)
            os.replace(tmp, final)
    for directory in {Path(final).parent for _, final in moves}:
        _sync_directory(directory)
    _remove(journal)


def _remove(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
