"""A volume format vhm_viz reads but does not write: SLC.

It goes through VTK's reader (:mod:`vhm_viz.io.vtk_files`) after a check of the header
against the file, and what that reader gets wrong is put right here: voxels left
uninitialised.
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


def _slc_voxels(p: Path) -> np.ndarray | None:
    """The voxels of an 8-bit SLC file, ``(nz, ny, nx)``, missing ones set to 0.

    VTK's SLC reader leaves a voxel uninitialised when a slice's run-length code stops
    short of it (files whose every slice stops one voxel short exist): its value then
    changes from run to run, and so does the region above a threshold. Returns None for
    files this decoder does not handle (other than 8 bits).
    """
    raw = p.read_bytes()
    head = re.match(
        # magic; nx ny nz bits; spacing (3); units, origin, model, compression; icon w h
        rb"\s*11111\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(?:\S+\s+){3}"
        rb"(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+(\d+)\s+X",
        raw,
    )
    if head is None:
        return None
    nx, ny, nz, bits = (int(head.group(i)) for i in range(1, 5))
    compression = int(head.group(8))
    icon_w, icon_h = int(head.group(9)), int(head.group(10))
    if bits != 8 or compression not in (0, 1):
        return None
    pos = head.end() + 3 * icon_w * icon_h
    out = np.zeros((nz, ny * nx), dtype=np.uint8)
    for z in range(nz):
        m = re.match(rb"\s*(\d+)\s+X", raw[pos : pos + 64])
        if m is None:
            return None
        size = int(m.group(1))
        pos += m.end()
        code = raw[pos : pos + size]
        pos += size
        if compression == 0:
            values = np.frombuffer(code, dtype=np.uint8)
        else:
            values, i = bytearray(), 0
            while i < len(code):
                count = code[i] & 0x7F
                if count == 0:
                    break
                if code[i] & 0x80:  # a run of literal bytes
                    values += code[i + 1 : i + 1 + count]
                    i += 1 + count
                else:  # one byte repeated
                    values += code[i + 1 : i + 2] * count
                    i += 2
            values = np.frombuffer(bytes(values), dtype=np.uint8)
        n = min(len(values), ny * nx)
        out[z, :n] = values[:n]
    return out


def read_slc(path):
    """An SLC volume through VTK, its voxels decoded here (:func:`_slc_voxels`)."""
    p = Path(path)
    data = read_vtk_file(p)
    voxels = _slc_voxels(p)
    name = getattr(data, "active_scalars_name", None)
    if voxels is None or name is None or data.point_data[name].size != voxels.size:
        return data
    data.point_data[name] = voxels.ravel()
    return data
