"""Say so when a command is about to compile the numeric kernels, instead of going quiet.

The kernels are compiled by numba on first use and cached on disk (``NUMBA_CACHE_DIR``,
else beside the sources or, where those are read-only, in the user's cache folder). The
first run of a command on a machine, or after an upgrade, spends most of its time
compiling. A stamp per command records that the command has run with the current sources,
numba and Python; without it the command prints one line before it starts.
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
from pathlib import Path

import vhm_viz

__all__ = ["NOTICE", "stamp_path", "compiled_before", "record_compiled"]

#: The line a command prints when its kernels may need compiling.
NOTICE = (
    "vhm-viz: compiling numeric kernels once for this machine (up to a minute; later "
    "runs start at once)..."
)


def _sources_key() -> str:
    """A digest of what the compiled code depends on: sources, numba, Python, machine."""
    import numba  # here: ``vhm-viz --help`` and the commands without kernels skip it

    h = hashlib.sha256()
    h.update(f"{numba.__version__} {sys.version} {platform.machine()}".encode())
    root = Path(vhm_viz.__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        try:
            st = path.stat()
        except OSError:
            continue
        h.update(f"{path.relative_to(root)} {st.st_size} {st.st_mtime_ns}".encode())
    return h.hexdigest()[:32]


def _stamp_folder() -> Path:
    """Where the stamps live: beside numba's cache when it is named, else the user's cache."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    if configured:
        return Path(configured) / "vhm_viz-stamps"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "vhm_viz" / "stamps"


def stamp_path(command: str) -> Path:
    """The stamp file of ``command`` for the current sources."""
    return _stamp_folder() / f"{command}-{_sources_key()}"


def compiled_before(command: str) -> bool:
    """Whether ``command`` has completed with the current sources on this machine."""
    try:
        return stamp_path(command).exists()
    except OSError:
        return True  # no way to know: say nothing rather than always


def record_compiled(command: str) -> None:
    """Mark ``command`` as having run; a folder that cannot be written is left alone."""
    try:
        path = stamp_path(command)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()
    except OSError:
        pass
