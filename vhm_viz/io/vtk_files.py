"""VTK's own formats: reading through VTK (crash-isolated), writing, the legacy check.

:func:`read_vtk_file` reads every format VTK (through PyVista) has a reader for, in a
child process (:mod:`vhm_viz.io.isolated`), an error VTK reports refusing the file;
:func:`write_vtk_file` writes with VTK's writer for the suffix and checks its error code
(a full disk fails the write, not only a message); :func:`check_legacy_vtk` checks a
legacy ``.vtk`` file's counts against its bytes first, since VTK's legacy reader returns
whatever it got from a truncated file.
"""

from __future__ import annotations

import importlib
import os
import re
from pathlib import Path

from vhm_viz import interrupts
from vhm_viz.atomic import atomic_path
from vhm_viz.io.errors import ReadError, TruncatedError, check_count, cut_short, need
from vhm_viz.io.isolated import read_isolated
from vhm_viz.io.registry import suffix_of

__all__ = ["read_vtk_file", "read_vtk", "write_vtk_file", "check_legacy_vtk"]

#: VTK's writer class (in ``vtkmodules.vtkIOXML`` / ``vtkIOLegacy`` / ``vtkIOPLY`` /
#: ``vtkIOGeometry``) for each suffix, and whether it takes ``SetFileTypeToBinary``.
_WRITERS = {
    ".vtp": ("vtkIOXML", "vtkXMLPolyDataWriter", False),
    ".vtu": ("vtkIOXML", "vtkXMLUnstructuredGridWriter", False),
    ".vti": ("vtkIOXML", "vtkXMLImageDataWriter", False),
    ".vts": ("vtkIOXML", "vtkXMLStructuredGridWriter", False),
    ".vtr": ("vtkIOXML", "vtkXMLRectilinearGridWriter", False),
    ".vtk": ("vtkIOLegacy", "vtkDataSetWriter", True),
    ".ply": ("vtkIOPLY", "vtkPLYWriter", True),
    ".stl": ("vtkIOGeometry", "vtkSTLWriter", True),
    ".obj": ("vtkIOGeometry", "vtkOBJWriter", False),
}
#: XML formats written zlib-compressed rather than LZ4: ``.vtu`` is how unstructured
#: meshes go to the finite-element world, whose Python reader (meshio) knows zlib and LZMA
#: but not LZ4. Level 1: most of zlib's size for a fraction of its default level's time.
_ZLIB_SUFFIXES = (".vtu",)
_ZLIB_LEVEL = 1


def write_vtk_file(path, data) -> None:
    """Write ``data`` atomically with VTK's writer for the suffix, binary where it can.

    XML formats are LZ4-compressed, ``.vtu`` zlib-compressed (:data:`_ZLIB_SUFFIXES`).

    VTK's writers report a failed write (a full disk or quota, a file-size limit) through
    their error code and an error message that may be silenced, and leave a truncated
    file; the code is checked before the file is renamed into place. An interrupt
    (SIGINT, SIGTERM) stops the writer at its next progress step (see
    :func:`_abort_when_interrupted`) and is raised, ``path`` left as it was.

    Parameters
    ----------
    path : path-like
        ``.vtp``, ``.vtu``, ``.vti``, ``.vts``, ``.vtr``, ``.vtk``, ``.ply``, ``.stl`` or
        ``.obj``.
    data : pyvista.DataSet or vtkDataSet
        Of a type the format holds.

    Raises
    ------
    OSError
        The writer failed; names the file and VTK's reason. ``path`` is left as it was.
    """
    from vtkmodules.vtkCommonMisc import vtkErrorCode

    module, name, binary = _WRITERS[suffix_of(path)]
    writer = getattr(importlib.import_module(f"vtkmodules.{module}"), name)()
    if binary:
        writer.SetFileTypeToBinary()
    if suffix_of(path) in _ZLIB_SUFFIXES:
        writer.SetCompressorTypeToZLib()
        writer.SetCompressionLevel(_ZLIB_LEVEL)
    elif hasattr(writer, "SetCompressorTypeToLZ4"):
        # XML formats: LZ4 writes and reads several times faster than zlib, for a larger
        # file (every VTK reader since 8.1 and ParaView read it)
        writer.SetCompressorTypeToLZ4()
    if hasattr(writer, "SetEncodeAppendedData"):
        # the appended data as raw bytes, not base64 text: a quarter smaller, and encoding
        # it would take most of the write (every VTK XML reader and ParaView read both)
        writer.SetEncodeAppendedData(False)
    writer.AddObserver("ProgressEvent", _abort_when_interrupted)
    with atomic_path(path) as tmp:
        writer.SetFileName(os.fspath(tmp))
        writer.SetInputData(data)
        # a signal is only recorded while VTK writes (raised in the observer, VTK would
        # print and lose it); the observer stops the writer, the block's end raises it
        with interrupts.deferred():
            ok = writer.Write()
            code = writer.GetErrorCode()
            writer.SetInputData(None)
        if not ok or code:
            reason = vtkErrorCode.GetStringFromErrorCode(code) if code else "the writer failed"
            raise OSError(f"could not write {os.fspath(path)}: {reason}")


def _abort_when_interrupted(writer, _event) -> None:
    """A writer's progress observer: stop once SIGINT or SIGTERM was received.

    VTK's XML writers ignore their abort flag and write the whole file: the command
    line's process ends at once instead (:func:`vhm_viz.interrupts.end_now`).
    """
    if interrupts.pending() is not None:
        writer.SetAbortExecute(1)
        interrupts.end_now()


def read_vtk_file(path):
    """Read a file with VTK's reader for its suffix, in a child process.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    pyvista.DataSet or pyvista.MultiBlock

    Raises
    ------
    ReadError
        The reader crashed, or VTK reported an error reading the file.
    """
    suffix = suffix_of(path)
    if suffix in _WRITERS:
        # the reader's VTK module (its writer's): loaded here, before the reading child is
        # forked, the child shares it instead of loading it, and a write of the result in
        # this format finds it loaded
        importlib.import_module(f"vtkmodules.{_WRITERS[suffix][0]}")
    return read_isolated(path, read_vtk, f"VTK's {suffix} reader")


def read_vtk(path, reader=None):
    """Read with PyVista/VTK in this process; an ``ErrorEvent`` of the reader refuses the file.

    Parameters
    ----------
    path : path-like
    reader : pyvista reader, optional
        Default: PyVista's reader for the suffix.

    Raises
    ------
    ReadError
        VTK reported an error (or a warning of a short read) while reading.
    """
    import pyvista as pv

    p = Path(path)
    if reader is None:
        reader = pv.get_reader(os.fspath(p))
    errors: list[str] = []
    vtk_reader = getattr(reader, "reader", None)
    if vtk_reader is not None and hasattr(vtk_reader, "AddObserver"):

        def on_error(obj, _event, *args):
            text = str(args[0]) if args else "error"
            # an array's stored metadata (its range or L2 norm: an overflow written as inf
            # does not parse back) is recomputed from its values: not the data's error
            if "Error reading InformationKey element" not in text:
                errors.append(text)

        def on_warning(obj, _event, *args):
            # VTK's legacy reader reports short reads ("Error reading binary data!") as
            # warnings, and then returns what it got
            text = str(args[0]) if args else ""
            if re.search(r"error|premature|unexpected end|truncat", text, re.IGNORECASE):
                errors.append(text)

        on_error.CallDataType = on_warning.CallDataType = "string0"
        vtk_reader.AddObserver("ErrorEvent", on_error)
        vtk_reader.AddObserver("WarningEvent", on_warning)
        # PyVista's XML readers read the file's header when made, before the observers:
        # read it again under them
        vtk_reader.Modified()
    from vtkmodules.vtkCommonCore import vtkObject

    # VTK invokes a reader's ErrorEvent only while its messages are displayed, which the
    # command line turns off: on for the read, so that every command refuses alike
    shown = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOn()
    try:
        data = reader.read()
    except Exception:  # PyVista raises what it caught of VTK's output, its first line
        if not errors:
            raise
    finally:
        vtkObject.SetGlobalWarningDisplay(shown)
    if errors:
        raise ReadError(f"{p}: not a valid {suffix_of(p)} file ({_vtk_message(errors[0])})")
    return data


def _vtk_message(text: str) -> str:
    """VTK's message without its source file, line and object address, on one line."""
    text = re.sub(r"^\s*(ERROR|Warning): In .*?, line \d+\s+\w+ \(0x[0-9a-fA-F]+\):", "", text)
    text = " ".join(text.split())
    return text if len(text) <= 160 else text[:157] + "..."


def check_vtk_xml(p: Path) -> None:
    """VTK XML (``.vtu``, ``.vtp``, ...): an XML file that ends with ``</VTKFile>``.

    VTK's XML reader reports a file cut short as a parse error of its XML, deep inside; the
    closing tag missing says it plainly.
    """
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(256).lstrip()
        fh.seek(max(0, size - 1024))
        tail = fh.read()
    if not head.startswith((b"<?xml", b"<VTKFile")):
        raise ReadError(f"{p}: not a VTK XML file (no '<VTKFile' at its start)")
    if b"</VTKFile>" not in tail:
        raise cut_short(p, "its VTKFile element")


_VTK_TYPES = {
    "bit": 1, "char": 1, "signed_char": 1, "unsigned_char": 1, "short": 2,
    "unsigned_short": 2, "int": 4, "unsigned_int": 4, "long": 8, "unsigned_long": 8,
    "float": 4, "double": 8, "vtkidtype": 4, "vtktypeint64": 8, "vtktypeuint64": 8,
    "vtktypeint32": 4, "vtktypeuint32": 4, "vtktypeint8": 1, "vtktypeuint8": 1,
    "vtktypeint16": 2, "vtktypeuint16": 2, "vtktypefloat32": 4, "vtktypefloat64": 8,
}  # fmt: skip


class _Cursor:
    """Walk a legacy VTK file: keyword lines, then counted values (binary bytes or tokens)."""

    def __init__(self, p: Path, blob: bytes, binary: bool, pos: int):
        self.p, self.blob, self.binary, self.pos = p, blob, binary, pos

    def keyword(self) -> list[str] | None:
        """The next non-empty line's tokens (None at the end)."""
        blob = self.blob
        while self.pos < len(blob):
            nl = blob.find(b"\n", self.pos)
            end = len(blob) if nl < 0 else nl
            line = blob[self.pos : end].decode("latin-1").split()
            self.pos = end + 1
            if line:
                return line
        return None

    def skip_block(self) -> None:
        """Skip lines up to the next empty one (a METADATA block)."""
        blob = self.blob
        while self.pos < len(blob):
            nl = blob.find(b"\n", self.pos)
            end = len(blob) if nl < 0 else nl
            empty = not blob[self.pos : end].strip()
            self.pos = end + 1
            if empty:
                return

    def values(self, count: int, vtk_type: str, what: str) -> None:
        """Skip ``count`` values of ``vtk_type``; refuse when the file ends first."""
        if count < 0:
            raise ReadError(f"{self.p}: corrupt legacy VTK file: negative count for {what}")
        if self.binary:
            size = _VTK_TYPES.get(vtk_type.lower())
            if size is None:
                raise ReadError(f"{self.p}: unknown data type {vtk_type!r} for {what}")
            need(
                self.p,
                f"{what} ({count} {vtk_type} values)",
                count * size,
                len(self.blob) - self.pos,
            )
            self.pos += count * size
            return
        blob, seen = self.blob, 0
        while seen < count:
            # whole lines at a time: values never span lines
            nl = blob.find(b"\n", self.pos)
            end = len(blob) if nl < 0 else nl + 1
            if self.pos >= len(blob):
                check_count(self.p, what, count, seen, unit="values", ends=True)
            seen += len(blob[self.pos : end].split())
            self.pos = end
        if seen != count:
            raise ReadError(
                f"{self.p}: corrupt legacy VTK file: {what} has {seen} values, not {count}"
            )


def _int(text: str, p: Path, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise ReadError(f"{p}: corrupt legacy VTK file: {what} count {text!r}") from None
    if value < 0:
        raise ReadError(f"{p}: corrupt legacy VTK file: negative {what} count {value}")
    return value


def check_legacy_vtk(p: Path) -> None:
    """Legacy VTK: the geometry's counts (points, cells, coordinates) against the file."""
    blob = p.read_bytes()
    lines = blob.split(b"\n", 3)
    if len(lines) < 4 or not lines[0].lower().startswith(b"# vtk datafile"):
        raise ReadError(f"{p}: not a legacy VTK file (no '# vtk DataFile' header)")
    mode = lines[2].strip().upper()
    if mode not in (b"ASCII", b"BINARY"):
        raise ReadError(f"{p}: legacy VTK file is neither ASCII nor BINARY ({mode[:20]!r})")
    cur = _Cursor(p, blob, mode == b"BINARY", len(lines[0]) + len(lines[1]) + len(lines[2]) + 3)
    n_points, per = None, 0  # per: tuples in the current POINT_DATA / CELL_DATA block
    while (tok := cur.keyword()) is not None:
        key = tok[0].upper()
        if key == "POINTS" and len(tok) >= 3:
            n_points = _int(tok[1], p, "POINTS")
            cur.values(3 * n_points, tok[2], "POINTS")
        elif key in ("VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS", "CELLS") and len(tok) >= 3:
            n, size = _int(tok[1], p, key), _int(tok[2], p, key)
            if n_points is None:
                raise ReadError(f"{p}: corrupt legacy VTK file: {key} before POINTS")
            nxt = cur.pos
            head = cur.keyword()
            if head and head[0].upper() == "OFFSETS":  # file format 5: offsets, connectivity
                cur.values(n, head[1], f"{key} offsets")
                head = cur.keyword()
                if not head or head[0].upper() != "CONNECTIVITY":
                    raise TruncatedError(f"{p}: truncated or corrupt: {key} without CONNECTIVITY")
                cur.values(size, head[1], f"{key} connectivity")
            else:
                cur.pos = nxt
                cur.values(size, "int", key)
        elif key == "CELL_TYPES" and len(tok) >= 2:
            cur.values(_int(tok[1], p, key), "int", key)
        elif key in ("X_COORDINATES", "Y_COORDINATES", "Z_COORDINATES") and len(tok) >= 3:
            cur.values(_int(tok[1], p, key), tok[2], key)
        elif key in ("POINT_DATA", "CELL_DATA") and len(tok) >= 2:
            per = _int(tok[1], p, key)
        elif key == "SCALARS" and len(tok) >= 3:
            ncomp = _int(tok[3], p, key) if len(tok) > 3 else 1
            nxt = cur.pos
            head = cur.keyword()
            if not head or head[0].upper() != "LOOKUP_TABLE":
                cur.pos = nxt
            cur.values(per * ncomp, tok[2], f"SCALARS {tok[1]}")
        elif key in ("VECTORS", "NORMALS") and len(tok) >= 3:
            cur.values(3 * per, tok[2], f"{key} {tok[1]}")
        elif key == "TENSORS" and len(tok) >= 3:
            cur.values(9 * per, tok[2], f"TENSORS {tok[1]}")
        elif key == "TEXTURE_COORDINATES" and len(tok) >= 4:
            cur.values(_int(tok[2], p, key) * per, tok[3], f"{key} {tok[1]}")
        elif key == "COLOR_SCALARS" and len(tok) >= 3:
            kind = "unsigned_char" if cur.binary else "float"
            cur.values(_int(tok[2], p, key) * per, kind, f"{key} {tok[1]}")
        elif key == "LOOKUP_TABLE" and len(tok) >= 3:
            kind = "unsigned_char" if cur.binary else "float"
            cur.values(4 * _int(tok[2], p, key), kind, f"LOOKUP_TABLE {tok[1]}")
        elif key == "FIELD" and len(tok) >= 3:
            for _ in range(_int(tok[2], p, key)):
                arr = cur.keyword()
                if arr is None:
                    raise TruncatedError(f"{p}: truncated: FIELD {tok[1]} lacks arrays")
                if arr[0].upper() == "NULL_ARRAY":
                    continue
                if len(arr) < 4:
                    raise ReadError(f"{p}: corrupt FIELD array line {' '.join(arr)[:40]!r}")
                ncomp, ntup = _int(arr[1], p, "FIELD"), _int(arr[2], p, "FIELD")
                cur.values(ncomp * ntup, arr[3], f"FIELD array {arr[0]}")
        elif key == "METADATA":
            cur.skip_block()
        elif key in ("DATASET", "DIMENSIONS", "SPACING", "ORIGIN", "ASPECT_RATIO"):
            continue
        else:
            raise ReadError(f"{p}: corrupt legacy VTK file: unexpected line {' '.join(tok)[:40]!r}")
    head = blob[:300].upper()
    if n_points is None and b"STRUCTURED_POINTS" not in head and b"RECTILINEAR" not in head:
        raise TruncatedError(f"{p}: truncated or corrupt legacy VTK file: no POINTS")
