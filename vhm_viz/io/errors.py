"""The error every reader raises, and the helpers that word it."""

from __future__ import annotations


class ReadError(ValueError):
    """A file that cannot be read as what was asked for; the message names the file."""


class TruncatedError(ReadError):
    """A file that ends before what its header announces."""


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


def first_line(exc) -> str:
    """The first line of an exception's message (its type's name when it has none)."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]
