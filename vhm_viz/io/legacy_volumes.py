"""Volume formats vhm_viz reads but does not write: NRRD and SLC.

Both go through VTK's readers (:mod:`vhm_viz.io.vtk_files`) after a check of the header
against the file, and what those readers get wrong is put right here: a 3-D scalar NRRD
read as a 2-D vector image, SLC voxels left uninitialised.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError, TruncatedError, need
from vhm_viz.io.vtk_files import read_vtk_file

__all__ = ["check_nrrd", "read_nrrd", "check_slc", "read_slc"]


_NRRD_TYPES = {
    "signed char": 1, "int8": 1, "int8_t": 1, "uchar": 1, "unsigned char": 1, "uint8": 1,
    "uint8_t": 1, "short": 2, "short int": 2, "signed short": 2, "int16": 2, "int16_t": 2,
    "ushort": 2, "unsigned short": 2, "uint16": 2, "uint16_t": 2, "int": 4, "signed int": 4,
    "int32": 4, "int32_t": 4, "uint": 4, "unsigned int": 4, "uint32": 4, "uint32_t": 4,
    "longlong": 8, "long long": 8, "int64": 8, "int64_t": 8, "ulonglong": 8, "uint64": 8,
    "uint64_t": 8, "float": 4, "double": 8,
}  # fmt: skip


def _nrrd_header(p: Path) -> tuple[dict, bytes, int]:
    """A NRRD header's fields (lower-case keys), the file's bytes, the header's end."""
    blob = p.read_bytes()
    if not blob.startswith(b"NRRD"):
        raise ReadError(f"{p}: not a NRRD file (no 'NRRD' magic)")
    sep = blob.find(b"\n\n")
    if sep < 0:
        raise TruncatedError(f"{p}: truncated NRRD file (no end of header)")
    fields = {}
    for line in blob[:sep].decode("latin-1").splitlines()[1:]:
        key, colon, value = line.partition(":")
        if colon and not line.startswith("#"):
            fields[key.strip().lower()] = value.strip().lstrip("=").strip()
    return fields, blob, sep


def read_nrrd(path):
    """A NRRD file through VTK; a 3-D scalar NRRD as the volume it is.

    VTK's reader takes the first axis of any 3-D NRRD for vector components and returns a
    2-D image of ``sizes[0]``-component pixels; a scalar volume (no vector ``kinds``) is
    rebuilt here from the same values, with the header's spacing and origin.
    """
    import pyvista as pv

    p = Path(path)
    data = read_vtk_file(p)
    fields, _, _ = _nrrd_header(p)
    sizes = [int(v) for v in fields.get("sizes", "").split()]
    kinds = fields.get("kinds", "domain domain domain").lower().split()
    names = data.array_names if isinstance(data, pv.ImageData) else []
    if len(sizes) != 3 or data.dimensions[2] != 1 or len(names) != 1:
        return data
    if kinds[0] not in ("domain", "space", "none", "???"):
        return data  # really a vector axis
    values = np.asarray(data.point_data[names[0]])
    if values.ndim != 2 or values.shape[1] != sizes[0]:
        return data
    spacing = [1.0, 1.0, 1.0]
    if "spacings" in fields:
        spacing = [float(v) for v in fields["spacings"].split()]
    elif "space directions" in fields:
        rows = re.findall(r"\(([^)]*)\)", fields["space directions"])
        spacing = [float(np.linalg.norm([float(x) for x in r.split(",")])) for r in rows]
    origin = [0.0, 0.0, 0.0]
    if "space origin" in fields:
        origin = [float(x) for x in fields["space origin"].strip("()").split(",")]
    out = pv.ImageData(dimensions=sizes, spacing=spacing, origin=origin)
    out.point_data[names[0]] = values.reshape(-1)
    return out


def check_nrrd(p: Path) -> None:
    """NRRD with attached raw data: ``sizes`` x ``type`` against the bytes after the header."""
    fields, blob, sep = _nrrd_header(p)
    if "data file" in fields or "datafile" in fields:
        return  # detached data: VTK's reader reports what is missing
    try:
        sizes = [int(v) for v in fields["sizes"].split()]
        item = _NRRD_TYPES[fields["type"].lower()]
    except (KeyError, ValueError):
        raise ReadError(f"{p}: malformed NRRD header (sizes, type)") from None
    if fields.get("encoding", "raw").lower() == "raw":
        needed = int(np.prod(sizes, dtype=np.int64)) * item
        need(p, f"{needed // item} voxels", needed, len(blob) - sep - 2)


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
