"""The error every reader raises, and the helpers that word it."""

from __future__ import annotations

import os


class ReadError(ValueError):
    """A file that cannot be read as what was asked for; the message names the file."""


class TruncatedError(ReadError):
    """A file that ends before what its header announces."""


#: What every message about a file that holds less than its header announces says to do.
AGAIN = "copy or export it again"

#: The largest cage or anchor-point file read (bytes): a cage of a million faces takes
#: some 40 MB as OBJ; what lies beyond is no cage a harmonic map can be solved on, and
#: reading it would take the memory of many copies of it.
MAX_POINT_FILE_BYTES = 64 * 2**20


def require_file(path, what: str) -> None:
    """Refuse a ``path`` that is not a file: missing, or a folder.

    Parameters
    ----------
    path : pathlib.Path
        Named in the message.
    what : str
        What the file should hold (``"cage"``): ``no such cage file``, ``a folder, not a
        cage file``.

    Raises
    ------
    FileNotFoundError
        Nothing is there.
    ReadError
        Something other than a file is (a folder, a device), or the file is empty.
    """
    if path.is_file():
        refuse_empty(path)
        return
    if not path.exists():
        raise FileNotFoundError(f"no such {what} file: {path}")
    kind = "a folder" if path.is_dir() else "not a regular file"
    raise ReadError(f"{path}: {kind}, not a {what} file; name the file itself")


def refuse_empty(path) -> None:
    """Refuse a file of no bytes, whatever its format, in one line (a failed copy or save)."""
    if os.stat(path).st_size == 0:
        raise ReadError(f"{path}: empty file (0 bytes); {AGAIN}")


def check_file_size(path, what: str, limit: int = MAX_POINT_FILE_BYTES) -> None:
    """Raise :class:`ReadError` for a file ``path`` larger than ``limit`` bytes, unread.

    Parameters
    ----------
    path : pathlib.Path
        The file, named in the message.
    what : str
        What the file should hold (``"cage"``).
    limit : int
        Bytes.
    """
    size = path.stat().st_size
    if size > limit:
        raise ReadError(f"{path}: {size} bytes: {what} files may hold at most {limit} bytes")


def need(path, what: str, needed: int, available: int) -> None:
    """Raise :class:`TruncatedError` when ``what`` needs more bytes than are available.

    Parameters
    ----------
    path : path-like
        The file, named in the message.
    what : str
        What the bytes hold (``"the voxels"``, ``"element 'face'"``).
    needed, available : int
        Bytes.
    """
    if needed > available:
        raise TruncatedError(
            f"{path}: truncated or corrupt: {what} needs {needed} bytes, the file has "
            f"{max(available, 0)}; {AGAIN}"
        )


def complex_voxels(kind: str) -> str:
    """Why an image of complex voxels is not read, and what to do, for ``cannot read (...)``.

    Read as two components, a complex voxel's real and imaginary parts would be deformed
    as a vector's, which they are not. ``kind`` is the voxel type as SimpleITK names it
    (``"complex of 32-bit float"``).
    """
    return (
        f"its voxel type is {kind}, which vhm_viz does not deform; convert it to its "
        "magnitude or real part first, e.g. with SimpleITK's ComplexToModulus or ComplexToReal"
    )


def check_count(
    path, what: str, announced: int, held: int, *, unit: str = "entries", ends: bool, exact=False
) -> None:
    """Refuse a file in which ``what`` holds fewer ``unit`` than it lists (or, ``exact``, more).

    The one wording of a count that does not match what follows it, whatever the format.

    Parameters
    ----------
    path : path-like
        The file, named in the message.
    what : str
        What lists the count (``"its Tetrahedra block"``, ``"the header"``).
    announced, held : int
        The count, and the entries (points, values, rows) the file holds for it.
    unit : str
        What is counted, plural.
    ends : bool
        The file ends inside ``what``: it was cut short (:class:`TruncatedError`);
        otherwise more follows, and the count is wrong (:class:`ReadError`).
    exact : bool
        Refuse more entries than the count too.
    """
    if held == announced or (held > announced and not exact):
        return
    if held < announced and ends:
        raise TruncatedError(
            f"{path}: truncated: {what} lists {announced} {unit}, the file ends after {held}; "
            f"{AGAIN}"
        )
    raise ReadError(
        f"{path}: corrupt: {what} lists {announced} {unit} but holds {held}; correct the count "
        "or export the file again"
    )


def cut_short(path, where: str) -> TruncatedError:
    """The error for a file that ends inside ``where`` (``"its $Nodes section"``)."""
    return TruncatedError(f"{path}: truncated: the file ends inside {where}; {AGAIN}")


def first_line(exc) -> str:
    """The first line of an exception's message (its type's name when it has none)."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]
