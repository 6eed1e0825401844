"""NRRD (``.nrrd``, and ``.nhdr`` with its data file): 3D Slicer's volume format.

Read and written through SimpleITK (:mod:`vhm_viz.io.itk_images`), which places the
voxels by ``space directions`` and ``space origin`` and converts a RAS (or any other)
``space`` to ITK's LPS world; VTK's reader keeps the spacing only. The header is checked
here first: a file (or detached data file) with fewer bytes than ``sizes`` x ``type``
promise is refused before SimpleITK parses it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError, TruncatedError, need
from vhm_viz.io.itk_images import read_with_sitk, write_with_sitk
from vhm_viz.io.medical import HEADER_SCAN_LIMIT, data_files_named, volume_array

__all__ = ["check_nrrd", "nrrd_files", "read_nrrd", "write_nrrd"]


# every spelling of the NRRD format's types (ITK writes "long long int", ...)
_NRRD_TYPES = {
    "signed char": 1, "int8": 1, "int8_t": 1, "uchar": 1, "unsigned char": 1, "uint8": 1,
    "uint8_t": 1, "short": 2, "short int": 2, "signed short": 2, "signed short int": 2,
    "int16": 2, "int16_t": 2, "ushort": 2, "unsigned short": 2, "unsigned short int": 2,
    "uint16": 2, "uint16_t": 2, "int": 4, "signed int": 4, "int32": 4, "int32_t": 4,
    "uint": 4, "unsigned int": 4, "uint32": 4, "uint32_t": 4, "longlong": 8,
    "long long": 8, "long long int": 8, "signed long long": 8, "signed long long int": 8,
    "int64": 8, "int64_t": 8, "ulonglong": 8, "unsigned long long": 8,
    "unsigned long long int": 8, "uint64": 8, "uint64_t": 8, "float": 4, "double": 8,
}  # fmt: skip

#: What SimpleITK writes a NRRD with; other dtypes are written as float64.
_WRITABLE = {"uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64", "int64",
             "float32", "float64"}  # fmt: skip


def _nrrd_header(p: Path) -> tuple[dict, bytes, int]:
    """A NRRD header's fields (lower-case keys), the file's bytes, where the data start.

    A ``.nhdr`` (detached header) may end without the blank line; its data start is its
    end.
    """
    blob = p.read_bytes()
    if not blob.startswith(b"NRRD"):
        raise ReadError(f"{p}: not a NRRD file (no 'NRRD' magic)")
    sep = blob.find(b"\n\n")
    if sep < 0:
        if p.suffix.lower() != ".nhdr":
            raise TruncatedError(f"{p}: truncated NRRD file (no end of header)")
        sep = len(blob)
    fields = {}
    for line in blob[:sep].decode("latin-1").splitlines()[1:]:
        key, colon, value = line.partition(":")
        if colon and not line.startswith("#"):
            fields[key.strip().lower()] = value.strip().lstrip("=").strip()
    return fields, blob, min(sep + 2, len(blob))


def check_nrrd(p: Path) -> None:
    """Raw NRRD voxels: ``sizes`` x ``type`` against the bytes after the header.

    The bytes are those after the header (attached data) or those of the one data file a
    ``.nhdr`` names; compressed data, data file lists and ``byte skip`` are left to the
    reader, which refuses what it cannot read.
    """
    fields, blob, start = _nrrd_header(p)
    try:
        sizes = [int(v) for v in fields["sizes"].split()]
        item = _NRRD_TYPES[fields["type"].lower()]
    except (KeyError, ValueError):
        raise ReadError(f"{p}: malformed NRRD header (sizes, type)") from None
    if not sizes or min(sizes) <= 0:
        raise ReadError(f"{p}: corrupt NRRD header: sizes {sizes}")
    if fields.get("dimension", str(len(sizes))) != str(len(sizes)):
        raise ReadError(
            f"{p}: corrupt NRRD header: dimension {fields['dimension']} but sizes "
            f"{fields['sizes']}"
        )
    if fields.get("encoding", "raw").lower() != "raw" or "byte skip" in fields:
        return
    needed = int(np.prod(sizes, dtype=np.int64)) * item
    data_file = fields.get("data file", fields.get("datafile"))
    if data_file is None:
        need(p, f"{needed // item} voxels", needed, len(blob) - start)
        return
    if " " in data_file.strip() or data_file.strip().upper().startswith("LIST"):
        return  # a list or a printf pattern of files
    raw = Path(data_file.strip())
    raw = raw if raw.is_absolute() else p.parent / raw
    if not raw.is_file():
        raise ReadError(f"{p}: its data file {raw.name} is missing")
    need(raw, f"{needed // item} voxels of {p.name}", needed, raw.stat().st_size)


def nrrd_files(path, written: bool = False) -> list[Path]:
    """The data files a NRRD header names, besides itself (:func:`files_of`).

    Parameters
    ----------
    path : path-like
        ``.nrrd`` or ``.nhdr``.
    written : bool
        True: what :func:`write_nrrd` writes beside ``path``: nothing (the data are in the
        file). False: what an existing header's ``data file`` names (one file, a ``LIST``
        or a pattern; none for attached data or a header that cannot be read).

    Returns
    -------
    list of Path
    """
    p = Path(path)
    if written:
        return []
    lines = []
    try:
        with open(p, "rb") as fh:
            while fh.tell() < HEADER_SCAN_LIMIT:
                line = fh.readline(1 << 16).decode("latin-1")
                if not line.strip():  # the end of the header (or of a detached one)
                    break
                lines.append(line.rstrip("\r\n"))
    except OSError:
        return []
    for k, line in enumerate(lines):
        key, colon, value = line.partition(":")
        if colon and key.strip().lower() in ("data file", "datafile"):
            spec = value.strip().lstrip("=").strip()
            return data_files_named(p.parent, spec, lines[k + 1 :])
    return []


def read_nrrd(path):
    """A NRRD image (``.nrrd``, ``.nhdr``) in ITK's LPS world, through SimpleITK.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    pyvista.ImageData
        Placed by ``space directions`` and ``space origin``; the voxels in one point array
        ``"ImageFile"`` (a vector axis as components).
    """

    def read(p):
        import SimpleITK as sitk

        return sitk.ReadImage(str(p)), "ImageFile"

    return read_with_sitk(path, read, "SimpleITK's NRRD reader")


def write_nrrd(path, image) -> None:
    """Write an image as a gzip-compressed NRRD (LPS space), atomically.

    The active scalars (or the first point array) are written
    (:func:`~vhm_viz.io.medical.volume_array`); a multi-component array as a leading
    ``vector`` axis. :func:`~vhm_viz.io.write_dataset` writes the other arrays beside it.

    Parameters
    ----------
    path : path-like
        ``.nrrd``.
    image : pyvista.ImageData
        Origin, spacing and direction go to ``space origin`` and ``space directions``.
    """
    values = volume_array(image)
    if values.dtype.name not in _WRITABLE:
        values = values.astype(np.float64)
    write_with_sitk(path, image, values)
