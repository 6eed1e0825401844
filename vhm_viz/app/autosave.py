"""The explorer's autosave: the edited scene kept on disk while a session runs.

Each running explorer writes its scene, when it has changed, to ``explorer-PID.json`` in
the user's state folder (:func:`state_folder`), atomically, in the scene format that
``vhm-viz deform`` and :meth:`ExplorerController.load_scene
<vhm_viz.app.controller.ExplorerController.load_scene>` read, with the data's absolute
path. A window that closes normally removes its file; a file whose process is gone was
left by a session that crashed or was killed, and the next explorer offers it
(:func:`recoverable`). Nothing here imports Qt: the window drives :class:`Autosave` from a
timer.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

from vhm_viz.atomic import process_running
from vhm_viz.io import write_text

__all__ = ["Autosave", "AUTOSAVE_INTERVAL_S", "recoverable", "state_folder"]

#: Seconds between two looks at whether the scene changed.
AUTOSAVE_INTERVAL_S = 5.0

_NAME = re.compile(r"^explorer-(\d+)\.json$")


def state_folder() -> Path:
    """The autosave folder: ``autosave/`` in the user's state folder.

    That is ``$VHM_STATE_DIR``, else ``$XDG_STATE_HOME/vhm_viz``, else
    ``~/.local/state/vhm_viz`` (the XDG base-directory default).
    """
    base = os.environ.get("VHM_STATE_DIR")
    if not base:
        xdg = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
        base = str(Path(xdg) / "vhm_viz")
    return Path(base) / "autosave"


def recoverable(folder: str | os.PathLike | None = None) -> list[Path]:
    """Autosaves left by explorers that ended without closing their window, newest first.

    Parameters
    ----------
    folder : path-like, optional
        The autosave folder (default :func:`state_folder`).

    Returns
    -------
    list of Path
        ``explorer-PID.json`` files whose process no longer runs.
    """
    folder = Path(folder) if folder is not None else state_folder()
    if not folder.is_dir():
        return []
    found = []
    for path in folder.iterdir():
        match = _NAME.match(path.name)
        if match and path.is_file() and not process_running(int(match.group(1))):
            found.append(path)
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


class Autosave:
    """One session's autosave file.

    Parameters
    ----------
    folder : path-like, optional
        The autosave folder (default :func:`state_folder`); created on the first write.
    """

    def __init__(self, folder: str | os.PathLike | None = None):
        self.folder = Path(folder) if folder is not None else state_folder()
        self.path = self.folder / f"explorer-{os.getpid()}.json"
        self._written: str | None = None
        #: Wall-clock time of the last write (``time.time()``), None before the first.
        self.saved_at: float | None = None

    def update(self, controller) -> bool:
        """Write the controller's scene if it changed since the last write.

        A controller without a complete scene yet (no cage, anchors or position
        constraint) has nothing to keep. A failed write (full disk, no permission) leaves
        the previous autosave and is raised as :class:`OSError` for the window to report.

        Returns
        -------
        bool
            True when the file was written.
        """
        try:
            scene = controller.scene_to_save(relative_to=None)
        except ValueError:
            return False
        text = scene.dumps()
        if text == self._written:
            return False
        self.folder.mkdir(parents=True, exist_ok=True)
        write_text(self.path, text)
        self._written, self.saved_at = text, time.time()
        return True

    def discard(self) -> None:
        """Remove this session's file (the window closed normally)."""
        self.path.unlink(missing_ok=True)
        self._written = None
