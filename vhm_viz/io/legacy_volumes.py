"""A volume format vhm_viz reads but does not write: SLC.

The header, icon and slices are checked against the file, and the 8-bit voxels (the only
kind :func:`check_slc` accepts) are decoded here, as VTK's reader reads them but for the
voxels that reader leaves uninitialised.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError, TruncatedError, need

__all__ = ["check_slc", "read_slc"]


def check_slc(p: Path) -> None:
    """SLC: header, icon and every slice (run-length encoded or not) inside the file."""
    _slc_layout(p, p.read_bytes())


def _slc_layout(p: Path, blob: bytes):
    """Where an 8-bit SLC file's parts are, checked against the file.

    Returns ``(dimensions, spacing, compressed, starts, sizes)``: the grid (VTK's reading
    of the header: origin 0, the header's spacing), whether the slices are run-length
    encoded, and where each slice's bytes start in ``blob`` and how many there are.

    Raises
    ------
    TruncatedError
        A header, the icon or a slice runs past the end of the file.
    ReadError
        Not an 8-bit SLC file.
    """
    it = re.compile(rb"\S+").finditer(blob)
    try:
        head = [next(it).group() for _ in range(14)]
        magic, nx, ny, nz, bits = (int(t) for t in head[:5])
        spacing = tuple(float(t) for t in head[5:8])
        compression = int(head[11])
        icon_w, icon_h = int(head[12]), int(head[13])
        marker = re.compile(rb"\s*X").match(blob, it.__next__().start())
    except (StopIteration, ValueError):
        raise TruncatedError(f"{p}: truncated or malformed SLC header") from None
    if magic != 11111 or min(nx, ny, nz) <= 0 or marker is None or bits != 8:
        raise ReadError(f"{p}: not a valid 8-bit SLC file (header {head[:5]})")
    pos = marker.end() + 3 * icon_w * icon_h
    need(p, "the icon", pos, len(blob))
    starts = np.zeros(nz, dtype=np.int64)
    sizes = np.full(nz, nx * ny, dtype=np.int64)
    slice_head = re.compile(rb"\s*(-?\d+)\s*X")
    for z in range(nz):
        if compression:
            m = slice_head.match(blob, pos)
            if m is None:
                raise TruncatedError(
                    f"{p}: truncated or corrupt SLC: slice {z} of {nz} has no header"
                )
            pos = m.end()
            sizes[z] = max(int(m.group(1)), 0)
            need(p, f"slice {z} of {nz}", pos + sizes[z], len(blob))
        starts[z] = pos
        pos += sizes[z]
    need(p, f"{nz} slices of {nx} x {ny}", pos, len(blob))
    return (nx, ny, nz), spacing, bool(compression), starts, sizes


def read_slc(path):
    """An 8-bit SLC volume (:func:`check_slc` refuses others), decoded here.

    No library parses the file, so none can crash on it; run-length encoded slices go
    through :func:`~vhm_viz.io.run_length.decode_slices`. The grid is VTK's reading of the
    header, and the array VTK's name for it (``SLCImage``). A voxel that a slice's code
    stops short of is 0: VTK's reader leaves it uninitialised, so that its value changes
    from run to run (files whose every slice stops one voxel short exist).
    """
    import pyvista as pv

    p = Path(path)
    raw = p.read_bytes()
    (nx, ny, nz), spacing, compressed, starts, sizes = _slc_layout(p, raw)
    blob = np.frombuffer(raw, dtype=np.uint8)
    voxels = np.zeros((nz, ny * nx), dtype=np.uint8)
    if compressed:
        from vhm_viz.io.run_length import decode_slices  # compiled: only for SLC files

        decode_slices(blob, starts, sizes, voxels)
    else:
        voxels[:] = blob[starts[0] : starts[0] + voxels.size].reshape(nz, ny * nx)
    image = pv.ImageData(dimensions=(nx, ny, nz), spacing=spacing, origin=(0.0, 0.0, 0.0))
    image.point_data["SLCImage"] = voxels.reshape(-1)
    return image
