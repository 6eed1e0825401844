"""A volume format vhm_viz reads but does not write: SLC.

After a check of the header against the file, the 8-bit variants (every SLC file met in
practice) are decoded here, as VTK's reader reads them but for the voxels that reader leaves
uninitialised; others go through VTK's reader (:mod:`vhm_viz.io.vtk_files`).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError, TruncatedError, need
from vhm_viz.io.vtk_files import read_vtk_file

__all__ = ["check_slc", "read_slc"]


def check_slc(p: Path) -> None:
    """SLC: header, icon and every slice (run-length encoded or not) inside the file."""
    blob = p.read_bytes()
    tokens = re.compile(rb"\S+")
    it = tokens.finditer(blob)
    try:
        head = [next(it).group() for _ in range(14)]
        magic, nx, ny, nz, bits = (int(t) for t in head[:5])
        compression = int(head[11])
        icon_w, icon_h = int(head[12]), int(head[13])
        marker = re.compile(rb"\s*X").match(blob, it.__next__().start())
    except (StopIteration, ValueError):
        raise TruncatedError(f"{p}: truncated or malformed SLC header") from None
    if magic != 11111 or min(nx, ny, nz) <= 0 or marker is None or bits != 8:
        raise ReadError(f"{p}: not a valid 8-bit SLC file (header {head[:5]})")
    pos = marker.end() + 3 * icon_w * icon_h
    need(p, "the icon", pos, len(blob))
    for z in range(nz):
        if compression:
            m = re.compile(rb"\s*(-?\d+)\s*X").match(blob, pos)
            if m is None:
                raise TruncatedError(
                    f"{p}: truncated or corrupt SLC: slice {z} of {nz} has no header"
                )
            size = int(m.group(1))
            pos = m.end()
            need(p, f"slice {z} of {nz}", pos + max(size, 0), len(blob))
            pos += max(size, 0)
        else:
            pos += nx * ny
    need(p, f"{nz} slices of {nx} x {ny}", pos, len(blob))


def _slc_image(p: Path):
    """The grid and voxels of an 8-bit SLC file: ``(dimensions, spacing, voxels)``, or None.

    Decoded here, in this process (:func:`~vhm_viz.io.run_length.decode_slices`): no
    library parses the file, so none can crash on it. The grid is VTK's reading of the
    header (origin 0, the header's spacing; ``voxels`` is ``(nz, ny * nx)``). A voxel that a
    slice's run-length code stops short of is 0 (VTK's reader leaves it uninitialised, so
    that its value changes from run to run; files whose every slice stops one voxel short
    exist). None for files this decoder does not handle (other than 8 bits).
    """
    raw = p.read_bytes()
    head = re.match(
        # magic; nx ny nz bits; spacing (3); units, origin, model, compression; icon w h
        rb"\s*11111\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\S+)\s+(\S+)\s+(\S+)\s+"
        rb"(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+X",
        raw,
    )
    if head is None:
        return None
    nx, ny, nz, bits = (int(head.group(i)) for i in range(1, 5))
    try:
        spacing = tuple(float(head.group(i)) for i in range(5, 8))
    except ValueError:
        return None
    compression = int(head.group(11))
    icon_w, icon_h = int(head.group(12)), int(head.group(13))
    if bits != 8 or compression not in (0, 1):
        return None
    pos = head.end() + 3 * icon_w * icon_h
    starts = np.zeros(nz, dtype=np.int64)
    sizes = np.zeros(nz, dtype=np.int64)
    slice_head = re.compile(rb"\s*(\d+)\s+X")
    for z in range(nz):
        m = slice_head.match(raw, pos)
        if m is None:
            return None
        starts[z] = m.end()
        sizes[z] = min(int(m.group(1)), len(raw) - m.end())
        pos = m.end() + int(m.group(1))
    out = np.zeros((nz, ny * nx), dtype=np.uint8)
    blob = np.frombuffer(raw, dtype=np.uint8)
    if compression == 0:
        for z in range(nz):
            n = min(int(sizes[z]), ny * nx)
            out[z, :n] = blob[starts[z] : starts[z] + n]
    else:
        from vhm_viz.io.run_length import decode_slices  # compiled: only for SLC files

        decode_slices(blob, starts, sizes, out)
    return (nx, ny, nz), spacing, out


def read_slc(path):
    """An SLC volume, decoded here (:func:`_slc_image`); other variants through VTK's reader."""
    import pyvista as pv

    p = Path(path)
    decoded = _slc_image(p)
    if decoded is None:
        return read_vtk_file(p)
    dimensions, spacing, voxels = decoded
    image = pv.ImageData(dimensions=dimensions, spacing=spacing, origin=(0.0, 0.0, 0.0))
    image.point_data["SLCImage"] = voxels.reshape(-1)
    return image
