"""Atomic output files: write to a temporary file beside the target, then rename.

The writers in :mod:`vhm_viz.io` use :func:`atomic_path`; this module is only the mechanism.

A crash or an error never leaves a half-written output, and an existing file is only
replaced once the new one is complete. The result gets ordinary permissions (``0o666``
less the process umask), not the private ``0o600`` of a temporary file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


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
    directory = path.parent if str(path.parent) else Path(".")
    directory.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=directory)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
