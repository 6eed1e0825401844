"""The guard against writing over an input, the files a format is made of included.

A MetaImage ``.mhd`` is a header and the ``.raw`` file its ``ElementDataFile`` names; a
NRRD ``.nhdr`` names its data file; a DICOM series is its folder's files. An output must
be none of the files the inputs read, and none of the files it writes may be one either:
``-o data.mhd`` writes ``data.raw``, which may be the voxels of the input ``in.mhd``.
"""

from __future__ import annotations

from pathlib import Path

from vhm_viz.atomic import OverwriteError, same_file
from vhm_viz.io.registry import files_of

__all__ = ["refuse_inputs"]


def refuse_inputs(output, inputs) -> None:
    """Raise :class:`~vhm_viz.atomic.OverwriteError` if writing ``output`` writes an input.

    The one guard every writer of user-named outputs uses (the command line, the
    explorer's export): whatever path, symbolic link or hard link names an input, it is
    never written. The files compared are ``output`` and those written beside it
    (:func:`~vhm_viz.io.registry.files_of` with ``written``), against each input and the
    files it reads (its header's data files).

    Parameters
    ----------
    output : path-like
    inputs : iterable of path-like or None
        Every file the operation reads: the data, the scene, every file the scene
        references (:meth:`vhm_viz.scene.Scene.referenced_files`).

    Raises
    ------
    OverwriteError
        One line naming the input, the file of it that would be written, and the output.
    """
    output = Path(output)
    written = [output, *files_of(output, written=True)]
    for src in inputs:
        if src is None:
            continue
        src = Path(src)
        for part in (src, *files_of(src)):
            for target in written:
                if not same_file(part, target):
                    continue
                what = (
                    f"the input file {src}"
                    if part == src
                    else (f"{part}, which holds the data of the input {src}")
                )
                how = "" if target == output else f", which writes {target}"
                raise OverwriteError(
                    f"refusing to overwrite {what} (as {output}{how}); choose another output"
                )
