"""The error every reader raises, and the helpers that word it."""

from __future__ import annotations


class ReadError(ValueError):
    """A file that cannot be read as what was asked for; the message names the file."""


class TruncatedError(ReadError):
    """A file that ends before what its header announces."""


#: The largest cage or anchor-point file read (bytes): a cage of a million faces takes
#: some 40 MB as OBJ; what lies beyond is no cage a harmonic map can be solved on, and
#: reading it would take the memory of many copies of it.
MAX_POINT_FILE_BYTES = 64 * 2**20


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
            f"{max(available, 0)}"
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


def first_line(exc) -> str:
    """The first line of an exception's message (its type's name when it has none)."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]
