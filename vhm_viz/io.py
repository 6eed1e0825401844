"""The one place that reads and writes files: datasets, cages, rigidity lines, anchors, text.

Everything that turns a path into numbers (or numbers into a file) lives here, so that the
command line, the explorer, scenes, the automatic cage and the filters agree on what a file
means:

* :func:`read_dataset` -- any mesh, tet mesh, point cloud or volume, as a PyVista dataset;
* :func:`read_cage`, :func:`cage_from_dataset`, :func:`cage_to_polydata`,
  :func:`write_cage` -- the one :class:`~vhm_viz.core.cage.Cage`, from and to files and
  VTK surfaces (VTK only, no PyVista: this path runs inside ParaView);
* :func:`read_rigidity_lines` (:func:`read_polylines`, :func:`read_tgf`, VTK polylines) --
  rigidity lines for anchors;
* :func:`read_anchors`, :func:`write_anchors` -- anchor files (what ``vhm-viz anchors``
  writes);
* :func:`write_dataset`, :func:`write_text` -- atomic outputs (:mod:`vhm_viz.atomic`);
  :func:`atomic_outputs` -- several files that appear together or not at all;
  :func:`refuse_inputs` -- the one guard against writing over an input;
  :func:`json_text` -- compact JSON, one point per line.

Writers take the destination first: ``write_*(path, what)``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import warnings
from pathlib import Path

import numpy as np

from vhm_viz.atomic import atomic_directory, atomic_path
from vhm_viz.core.cage import Cage
from vhm_viz.core.errors import CageError
from vhm_viz.core.geometry import triangulate_polygons

__all__ = [
    "DATASET_SUFFIXES",
    "CAGE_SUFFIXES",
    "ReadError",
    "read_dataset",
    "read_cage",
    "cage_from_dataset",
    "cage_to_polydata",
    "write_cage",
    "read_polylines",
    "read_tgf",
    "read_rigidity_lines",
    "read_anchors",
    "write_anchors",
    "write_dataset",
    "write_text",
    "atomic_outputs",
    "refuse_inputs",
    "same_file",
    "OverwriteError",
    "json_text",
    "suffix_of",
    "cell_types",
]

#: Dataset formats :func:`read_dataset` reads (VTK's readers, meshio for MEDIT/OFF, and
#: plain point lists). ``.nii.gz`` counts as one suffix.
DATASET_SUFFIXES = (
    ".vtu", ".vtp", ".vti", ".vts", ".vtr", ".vtk", ".ply", ".obj", ".stl", ".mesh",
    ".off", ".mhd", ".mha", ".nii", ".nii.gz", ".nrrd", ".slc",
    ".npy", ".xyz", ".txt", ".csv",
)  # fmt: skip
#: Cage formats :func:`read_cage` reads.
CAGE_SUFFIXES = (".obj", ".off", ".ply", ".stl", ".vtp", ".vtk", ".vtu")
_POINT_LIST_SUFFIXES = (".npy", ".xyz", ".txt", ".csv")


class ReadError(ValueError):
    """A file that cannot be read as what was asked for; the message names the file."""


class OverwriteError(ValueError):
    """An output that would overwrite one of the inputs (:func:`refuse_inputs`)."""


def suffix_of(path) -> str:
    """Lower-case suffix of a path, with ``.nii.gz`` kept whole."""
    name = Path(path).name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return Path(name).suffix


# ----------------------------------------------------------------------------------------
# Datasets
# ----------------------------------------------------------------------------------------


def read_dataset(path):
    """Read a mesh, tet mesh, point cloud or volume; never crash, never guess.

    Every file is checked before a library parses it, and a file that is truncated,
    inconsistent or not what its suffix says is refused with a :class:`ReadError` -- never
    read as a partial mesh or a point cloud:

    * PLY: the header's element counts and property types against the file size (binary)
      or the number of values (ASCII); legacy VTK: the point and cell counts against the
      bytes or values that follow; binary STL: the triangle count against the file size;
      MetaImage (``.mhd``/``.mha``), NIfTI (``.nii``/``.nii.gz``), NRRD and SLC: the voxel
      count against the (decompressed) data; OFF: parsed here;
    * VTK's readers then run in a forked child process, so that a crash of a reader on a
      file these checks could not fully vet becomes an error message, not the end of the
      process; an error VTK reports while reading refuses the file too;
    * the result must have finite points and cells whose point ids exist;
    * meshio (MEDIT ``.mesh``) runs with its printed output captured and its ``sys.exit``
      turned into a :class:`ReadError`.

    Parameters
    ----------
    path : str or os.PathLike
        One of :data:`DATASET_SUFFIXES`, or a folder of DICOM files. ``.npy``/``.xyz``/
        ``.txt``/``.csv`` hold one point per row (the first three columns are x, y, z).

    Returns
    -------
    pyvista.DataSet
        ``PolyData`` for surfaces and point lists (an OBJ/OFF read as polygon cells becomes
        a surface again), ``UnstructuredGrid`` for volumetric meshes, ``ImageData`` for
        volumes (DICOM folders included), and so on. A MultiBlock file with one block gives
        that block.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ReadError
        Unknown suffix, unreadable, truncated, inconsistent or empty file, several datasets
        in one file; the message names the file and the problem.
    """
    import pyvista as pv

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no such file: {p}")
    suffix = suffix_of(p)
    if p.is_dir():
        suffix = DICOM_FOLDER
    elif not p.is_file():
        raise ReadError(f"{p}: not a file")
    elif suffix not in DATASET_SUFFIXES:
        raise ReadError(
            f"{p}: unsupported file type {suffix or '(none)'!r}; use one of "
            f"{', '.join(DATASET_SUFFIXES)} (or a folder of DICOM files)"
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if suffix in _POINT_LIST_SUFFIXES:
                data = pv.PolyData(_read_point_list(p, suffix))
            elif suffix == ".off":
                data = _off_dataset(p)
            elif suffix == ".mesh":
                data = _read_meshio(p)
            else:
                _check_format(p, suffix)
                data = _read_vtk_isolated(p, suffix)
                if suffix == ".nrrd":
                    data = _nrrd_volume(data, p)
                if suffix == ".slc":
                    _fix_slc_voxels(p, data)
        except ReadError:
            raise
        except MemoryError as exc:
            raise ReadError(f"{p}: cannot read (it asks for more memory than there is)") from exc
        except Exception as exc:  # noqa: BLE001 -- VTK, numpy and meshio raise many types
            raise ReadError(f"{p}: cannot read ({_first_line(exc)})") from exc
    if isinstance(data, pv.MultiBlock):
        blocks = [b for b in data if b is not None]
        if len(blocks) != 1:
            raise ReadError(f"{p}: holds {len(blocks)} datasets (a MultiBlock); give one dataset")
        data = blocks[0]
    if data is None or data.n_points == 0:
        why = f" ({_first_line(caught[0].message)})" if caught else ""
        raise ReadError(f"{p}: no points (empty, or not a valid {suffix} file){why}")
    _check_dataset(data, p)
    if suffix in VOLUME_WRITE_SUFFIXES:
        _apply_orientation(p, suffix, data)
    return _surface_if_polygonal(data)


#: What :func:`read_dataset` calls a folder of DICOM files in its messages.
DICOM_FOLDER = "DICOM folder"


def _first_line(exc) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def _read_point_list(p: Path, suffix: str) -> np.ndarray:
    if suffix == ".npy":
        pts = np.load(p, allow_pickle=False)
    else:
        pts = np.loadtxt(p, delimiter="," if suffix == ".csv" else None, ndmin=2)
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ReadError(f"{p}: expected one point per row (x y z ...), got shape {pts.shape}")
    return np.ascontiguousarray(pts[:, :3])


def _slc_voxels(p: Path) -> np.ndarray | None:
    """The voxels of an 8-bit SLC file, ``(nz, ny, nx)``, missing ones set to 0.

    VTK's SLC reader leaves a voxel uninitialised when a slice's run-length code stops
    short of it (the bundled embryo's slices all stop one voxel short): its value then
    changes from run to run, and so does the region above a threshold. Returns None for
    files this decoder does not handle (other than 8 bits).
    """
    import re

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


def _fix_slc_voxels(p: Path, data) -> None:
    """Replace the scalars VTK read from an SLC file by :func:`_slc_voxels` (in place)."""
    voxels = _slc_voxels(p)
    name = data.active_scalars_name
    if voxels is None or name is None or data.point_data[name].size != voxels.size:
        return
    data.point_data[name] = voxels.ravel()


def _read_meshio(p: Path):
    import contextlib
    import io as _io

    import meshio
    import pyvista as pv

    printed = _io.StringIO()  # meshio prints (and logs) its complaints: keep them
    try:
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
            mesh = meshio.read(os.fspath(p))
    except SystemExit as exc:  # meshio's readers call sys.exit on some malformed files
        said = printed.getvalue().strip().splitlines()
        raise ReadError(
            f"{p}: malformed {suffix_of(p)} file" + (f" ({said[0]})" if said else "")
        ) from exc
    return pv.from_meshio(mesh)


def _check_dataset(data, p: Path) -> None:
    """Refuse what no reader should have returned: non-finite points, dangling cell ids."""
    import pyvista as pv

    if data.GetNumberOfPoints() and isinstance(
        data, pv.PointSet | pv.PolyData | pv.UnstructuredGrid
    ):
        pts = np.asarray(data.points)
        if not np.isfinite(pts).all():
            bad = np.nonzero(~np.isfinite(pts).all(axis=1))[0]
            raise ReadError(
                f"{p}: {bad.size} points with non-finite coordinates (e.g. point {bad[0]})"
            )
    cells = []
    if isinstance(data, pv.PolyData):
        cells = [data.GetVerts(), data.GetLines(), data.GetPolys(), data.GetStrips()]
    elif isinstance(data, pv.UnstructuredGrid):
        cells = [data.GetCells()]
    n = data.GetNumberOfPoints()
    for arr in cells:
        if arr is None or arr.GetNumberOfCells() == 0:
            continue
        from vtkmodules.util import numpy_support as ns

        conn = ns.vtk_to_numpy(arr.GetConnectivityArray())
        if conn.size and (conn.min() < 0 or conn.max() >= n):
            raise ReadError(
                f"{p}: cells refer to points that do not exist (ids up to {int(conn.max())}, "
                f"{n} points)"
            )


# ----------------------------------------------------------------------------------------
# Reading through VTK, isolated: a reader that crashes takes a child process with it
# ----------------------------------------------------------------------------------------


def _read_vtk_isolated(p: Path, suffix: str):
    """Read with VTK's reader for ``suffix`` in a forked child process (where there is fork).

    The child sends the dataset back pickled (PyVista serialises it with VTK's own writer);
    a crash of the child (a reader dereferencing a corrupt count) becomes a
    :class:`ReadError`; an error VTK reports while reading refuses the file too.
    """
    if not hasattr(os, "fork"):  # pragma: no cover - Windows: the checks alone must do
        return _read_vtk(p, suffix)
    import pickle

    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child (coverage does not follow the fork)
        status = 0
        try:
            import faulthandler

            faulthandler.disable()  # a crash here is expected and reported by the parent
            os.close(read_end)
            _limit_memory(p)
            try:
                data = _read_vtk(p, suffix)
                # PyVista's pickling (the legacy VTK format) drops an image's direction
                direction = (
                    np.array(data.direction_matrix) if hasattr(data, "direction_matrix") else None
                )
                payload = ("ok", (data, direction))
            except BaseException as exc:  # noqa: BLE001 - everything goes back as text
                payload = ("error", _first_line(exc))
            with os.fdopen(write_end, "wb") as fh:
                pickle.dump(payload, fh, protocol=pickle.HIGHEST_PROTOCOL)
        except BaseException:  # noqa: BLE001
            status = 1
        finally:
            os._exit(status)
    os.close(write_end)
    try:
        with os.fdopen(read_end, "rb") as fh:
            blob = fh.read()
        _, status = os.waitpid(pid, 0)
        pid = None
    finally:
        if pid is not None:  # interrupted while waiting: do not leave the child behind
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) or not blob:
        how = (
            f"signal {signal.Signals(os.WTERMSIG(status)).name}"
            if os.WIFSIGNALED(status)
            else f"exit status {os.WEXITSTATUS(status)}"
        )
        raise ReadError(f"{p}: VTK's {suffix} reader crashed on this file ({how}): corrupt file")
    kind, value = pickle.loads(blob)  # noqa: S301 - our own child's data
    if kind == "error":
        raise ReadError(f"{p}: cannot read ({value})")
    data, direction = value
    if direction is not None:
        data.direction_matrix = direction
    return data


def _limit_memory(p: Path) -> None:
    """Cap the reading child's address space: a corrupt count cannot exhaust the machine.

    What it may add to what the process already maps: 2 GiB, or 64 times the file
    (folder) size when that is more -- far above any real reader's needs.
    """
    try:
        import resource

        size = sum(f.stat().st_size for f in p.iterdir()) if p.is_dir() else p.stat().st_size
        with open("/proc/self/statm") as fh:
            mapped = int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        resource.setrlimit(resource.RLIMIT_AS, (mapped + max(2 << 30, 64 * size),) * 2)
    except (ImportError, OSError, ValueError):  # pragma: no cover - not Linux
        pass


def _read_vtk(p: Path, suffix: str):
    """Read with PyVista/VTK; an ``ErrorEvent`` of the reader refuses the file."""
    import pyvista as pv

    if suffix == DICOM_FOLDER:
        reader = pv.DICOMReader(os.fspath(p))
    else:
        reader = pv.get_reader(os.fspath(p))
    errors: list[str] = []
    vtk_reader = getattr(reader, "reader", None)
    if vtk_reader is not None and hasattr(vtk_reader, "AddObserver"):

        def on_error(obj, _event, *args):
            errors.append(str(args[0]) if args else "error")

        def on_warning(obj, _event, *args):
            # VTK's legacy reader reports short reads ("Error reading binary data!") as
            # warnings, and then returns what it got
            text = str(args[0]) if args else ""
            if re.search(r"error|premature|unexpected end|truncat", text, re.IGNORECASE):
                errors.append(text)

        on_error.CallDataType = on_warning.CallDataType = "string0"
        vtk_reader.AddObserver("ErrorEvent", on_error)
        vtk_reader.AddObserver("WarningEvent", on_warning)
    data = reader.read()
    if errors:
        text = " ".join(errors[0].split())
        raise ReadError(f"{p}: VTK reports an error reading it ({text[-160:]})")
    return data


# ----------------------------------------------------------------------------------------
# Format checks: counts in headers against what the file holds, before VTK reads it
# ----------------------------------------------------------------------------------------


def _check_format(p: Path, suffix: str) -> None:
    """Refuse a file whose header promises more than it holds (see :func:`read_dataset`)."""
    check = {
        ".ply": _check_ply,
        ".vtk": _check_legacy_vtk,
        ".stl": _check_stl,
        ".mhd": _check_metaimage,
        ".mha": _check_metaimage,
        ".nii": _check_nifti,
        ".nii.gz": _check_nifti,
        ".nrrd": _check_nrrd,
        ".slc": _check_slc,
    }.get(suffix)
    if check is not None:
        check(p)


class _Truncated(ReadError):
    pass


def _need(p: Path, what: str, needed: int, available: int) -> None:
    if needed > available:
        raise _Truncated(
            f"{p}: truncated or corrupt: {what} needs {needed} bytes, the file has "
            f"{max(available, 0)}"
        )


def _header_lines(blob: bytes, end_marker: bytes, p: Path, limit: int = 1 << 16):
    """Lines of a text header ending with ``end_marker``, and the offset after it."""
    at = blob.find(end_marker, 0, limit)
    if at < 0:
        raise ReadError(f"{p}: no {end_marker.decode().strip()!r} line: not a valid file")
    end = at + len(end_marker)
    lines = blob[:at].decode("latin-1").splitlines()
    return lines, end


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def _check_ply(p: Path) -> None:
    """PLY: header, element counts and list lengths against the file's bytes or values."""
    blob = p.read_bytes()
    if not blob.startswith(b"ply"):
        raise ReadError(f"{p}: not a PLY file (no 'ply' magic)")
    at = blob.find(b"end_header", 0, 1 << 16)
    if at < 0:
        raise ReadError(f"{p}: PLY header has no 'end_header' line")
    nl = blob.find(b"\n", at)
    body = len(blob) if nl < 0 else nl + 1
    fmt, elements = None, []
    for raw in blob[:at].decode("latin-1").splitlines()[1:]:
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        try:
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                count = int(tok[2])
                if count < 0:
                    raise ValueError
                elements.append((tok[1], count, []))
            elif tok[0] == "property" and elements:
                if tok[1] == "list":
                    elements[-1][2].append((tok[-1], _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
                else:
                    elements[-1][2].append((tok[-1], _PLY_TYPES[tok[1]], None))
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError):
            raise ReadError(f"{p}: malformed PLY header line {raw.strip()!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ReadError(f"{p}: unknown PLY format {fmt!r}")
    n_vertices = next((c for name, c, _ in elements if name == "vertex"), 0)
    if fmt == "ascii":
        _check_ply_ascii(p, blob[body:], elements, n_vertices)
    else:
        _check_ply_binary(p, blob, body, elements, n_vertices, "<" if "little" in fmt else ">")


def _check_ply_binary(p, blob, pos, elements, n_vertices, order) -> None:
    for name, count, props in elements:
        if all(kind is None for _, _, kind in props):
            row = sum(np.dtype(t).itemsize for _, t, _ in props)
            _need(p, f"element '{name}' ({count} x {row} bytes)", count * row, len(blob) - pos)
            pos += count * row
            continue
        if len(props) == 1 and count:
            # one list per row (faces): usually all of one length -- check it vectorised
            _, count_type, item_type = props[0]
            ct, it = (
                np.dtype(count_type).newbyteorder(order),
                np.dtype(item_type).newbyteorder(order),
            )
            _need(p, f"element '{name}'", ct.itemsize, len(blob) - pos)
            k = int(np.frombuffer(blob, ct, 1, pos)[0])
            if k >= 0:
                rec = np.dtype([("k", ct), ("ids", it, (k,))])
                if len(blob) - pos >= count * rec.itemsize:
                    rows = np.frombuffer(blob, rec, count, pos)
                    if (rows["k"] == k).all():
                        _check_ids(p, name, rows["ids"], n_vertices)
                        pos += count * rec.itemsize
                        continue
        pos = _walk_ply_rows(p, blob, pos, name, count, props, order, n_vertices)
    return None


def _walk_ply_rows(p, blob, pos, name, count, props, order, n_vertices) -> int:
    """Row by row (lists of varying length): every list inside the file, ids in range."""
    size = len(blob)
    for _ in range(count):
        for prop, scalar_or_count, item in props:
            ct = np.dtype(scalar_or_count).newbyteorder(order)
            _need(p, f"element '{name}'", pos + ct.itemsize, size)
            if item is None:
                pos += ct.itemsize
                continue
            k = int(np.frombuffer(blob, ct, 1, pos)[0])
            pos += ct.itemsize
            it = np.dtype(item).newbyteorder(order)
            if k < 0:
                raise ReadError(f"{p}: corrupt PLY: a list of length {k} in element '{name}'")
            _need(p, f"element '{name}'", pos + k * it.itemsize, size)
            if prop in ("vertex_indices", "vertex_index"):
                _check_ids(p, name, np.frombuffer(blob, it, k, pos), n_vertices)
            pos += k * it.itemsize
    return pos


def _check_ids(p, element, ids, n_vertices) -> None:
    ids = np.asarray(ids)
    if ids.size and (ids.min() < 0 or ids.max() >= n_vertices):
        raise ReadError(
            f"{p}: corrupt PLY: element '{element}' refers to vertex {int(ids.max())} "
            f"(or {int(ids.min())}); there are {n_vertices} vertices"
        )


def _check_ply_ascii(p, body: bytes, elements, n_vertices) -> None:
    tokens = body.split()
    pos = 0
    for name, count, props in elements:
        for _ in range(count):
            for prop, _t, item in props:
                if pos >= len(tokens):
                    raise _Truncated(
                        f"{p}: truncated: element '{name}' has fewer rows than {count}"
                    )
                if item is None:
                    pos += 1
                    continue
                try:
                    k = int(tokens[pos])
                    ids = [int(t) for t in tokens[pos + 1 : pos + 1 + k]]
                except ValueError:
                    raise ReadError(f"{p}: corrupt PLY: non-integer list in '{name}'") from None
                if k < 0 or len(ids) < k:
                    raise _Truncated(f"{p}: truncated or corrupt list in element '{name}'")
                if prop in ("vertex_indices", "vertex_index"):
                    _check_ids(p, name, ids, n_vertices)
                pos += 1 + k


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
            _need(
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
                raise _Truncated(
                    f"{self.p}: truncated: {what} announces {count} values, the file ends "
                    f"after {seen}"
                )
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


def _check_legacy_vtk(p: Path) -> None:
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
                    raise _Truncated(f"{p}: truncated or corrupt: {key} without CONNECTIVITY")
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
                    raise _Truncated(f"{p}: truncated: FIELD {tok[1]} lacks arrays")
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
        raise _Truncated(f"{p}: truncated or corrupt legacy VTK file: no POINTS")


def _check_stl(p: Path) -> None:
    """STL: binary -- 84 + 50 n bytes for n triangles; ASCII -- ends with ``endsolid``."""
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(84)
    if len(head) == 84 and 84 + 50 * int.from_bytes(head[80:84], "little") == size:
        return
    if head.lstrip().lower().startswith(b"solid"):
        with open(p, "rb") as fh:
            fh.seek(max(0, size - 1024))
            if b"endsolid" in fh.read().lower():
                return
        raise _Truncated(f"{p}: truncated ASCII STL (no 'endsolid' at the end)")
    n = int.from_bytes(head[80:84], "little") if len(head) == 84 else 0
    raise _Truncated(
        f"{p}: truncated or corrupt binary STL: {n} triangles need {84 + 50 * n} bytes, the "
        f"file has {size}"
    )


_MET_TYPES = {
    "MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4,
    "MET_UINT": 4, "MET_LONG": 8, "MET_ULONG": 8, "MET_LONG_LONG": 8,
    "MET_ULONG_LONG": 8, "MET_FLOAT": 4, "MET_DOUBLE": 8,
}  # fmt: skip


def _check_metaimage(p: Path) -> None:
    """MetaImage: DimSize x ElementType x channels against the (uncompressed) data file."""
    blob = p.read_bytes()[: 1 << 16] if p.stat().st_size > 1 << 16 else p.read_bytes()
    fields, header_end = {}, 0
    for line in blob.split(b"\n"):
        header_end += len(line) + 1
        key, _, value = line.decode("latin-1").partition("=")
        key = key.strip()
        if key:
            fields[key] = value.strip()
        if key == "ElementDataFile":
            break
    try:
        dims = [int(v) for v in fields["DimSize"].split()]
        item = _MET_TYPES[fields["ElementType"].upper()]
        channels = int(fields.get("ElementNumberOfChannels", "1"))
        data_file = fields["ElementDataFile"]
    except (KeyError, ValueError):
        raise ReadError(
            f"{p}: malformed MetaImage header (DimSize, ElementType, ElementDataFile)"
        ) from None
    if min(dims, default=0) <= 0 or channels <= 0:
        raise ReadError(f"{p}: corrupt MetaImage header: DimSize {dims}")
    if fields.get("CompressedData", "False").lower() == "true" or data_file.upper() == "LIST":
        return
    needed = int(np.prod(dims, dtype=np.int64)) * item * channels
    if data_file.upper() == "LOCAL":
        _need(p, "the voxels", needed, p.stat().st_size - header_end)
        return
    raw = (p.parent / data_file) if not Path(data_file).is_absolute() else Path(data_file)
    if not raw.is_file():
        raise ReadError(f"{p}: its data file {raw.name} is missing")
    skip = int(fields.get("HeaderSize", "0") or 0)
    _need(raw, "the voxels of " + p.name, needed, raw.stat().st_size - max(skip, 0))


def _check_nifti(p: Path) -> None:
    """NIfTI-1/2: the voxel count of the header against the (decompressed) data."""
    import gzip
    import struct

    if suffix_of(p) == ".nii.gz":
        try:
            with gzip.open(p, "rb") as fh:
                blob = fh.read()
        except (OSError, EOFError) as exc:
            raise _Truncated(f"{p}: truncated or corrupt gzip data ({_first_line(exc)})") from None
    else:
        blob = p.read_bytes()
    _need(p, "a NIfTI header", 348, len(blob))
    for order in "<>":
        size = struct.unpack_from(order + "i", blob, 0)[0]
        if size in (348, 540):
            break
    else:
        raise ReadError(f"{p}: not a NIfTI file (header size field is not 348 or 540)")
    if size == 348:
        dim = struct.unpack_from(order + "8h", blob, 40)
        bitpix = struct.unpack_from(order + "h", blob, 72)[0]
        offset = struct.unpack_from(order + "f", blob, 108)[0]
    else:
        _need(p, "a NIfTI-2 header", 540, len(blob))
        bitpix = struct.unpack_from(order + "h", blob, 14)[0]
        dim = struct.unpack_from(order + "8q", blob, 16)
        offset = struct.unpack_from(order + "q", blob, 168)[0]
    ndim = dim[0]
    if not 1 <= ndim <= 7 or any(d <= 0 for d in dim[1 : ndim + 1]) or bitpix <= 0:
        raise ReadError(f"{p}: corrupt NIfTI header (dim {list(dim)}, bitpix {bitpix})")
    if not (np.isfinite(offset) and offset >= 0):
        raise ReadError(f"{p}: corrupt NIfTI header (vox_offset {offset})")
    voxels = int(np.prod(dim[1 : ndim + 1], dtype=np.int64))
    _need(p, f"{voxels} voxels of {bitpix} bits", int(offset) + voxels * bitpix // 8, len(blob))


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
        raise _Truncated(f"{p}: truncated NRRD file (no end of header)")
    fields = {}
    for line in blob[:sep].decode("latin-1").splitlines()[1:]:
        key, colon, value = line.partition(":")
        if colon and not line.startswith("#"):
            fields[key.strip().lower()] = value.strip().lstrip("=").strip()
    return fields, blob, sep


def _nrrd_volume(data, p: Path):
    """A 3-D scalar NRRD as the volume it is.

    VTK's reader takes the first axis of any 3-D NRRD for vector components and returns a
    2-D image of ``sizes[0]``-component pixels; a scalar volume (no vector ``kinds``) is
    rebuilt here from the same values, with the header's spacing and origin.
    """
    import pyvista as pv

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


def _check_nrrd(p: Path) -> None:
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
        _need(p, f"{needed // item} voxels", needed, len(blob) - sep - 2)


def _check_slc(p: Path) -> None:
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
        raise _Truncated(f"{p}: truncated or malformed SLC header") from None
    if magic != 11111 or min(nx, ny, nz) <= 0 or marker is None or bits != 8:
        raise ReadError(f"{p}: not a valid 8-bit SLC file (header {head[:5]})")
    pos = marker.end() + 3 * icon_w * icon_h
    _need(p, "the icon", pos, len(blob))
    for z in range(nz):
        if compression:
            m = re.compile(rb"\s*(-?\d+)\s*X").match(blob, pos)
            if m is None:
                raise _Truncated(f"{p}: truncated or corrupt SLC: slice {z} of {nz} has no header")
            size = int(m.group(1))
            pos = m.end()
            _need(p, f"slice {z} of {nz}", pos + max(size, 0), len(blob))
            pos += max(size, 0)
        else:
            pos += nx * ny
    _need(p, f"{nz} slices of {nx} x {ny}", pos, len(blob))


def _surface_if_polygonal(data):
    """An UnstructuredGrid of triangles/quads/polygons only (OBJ/OFF via meshio) -> PolyData."""
    import pyvista as pv

    if isinstance(data, pv.UnstructuredGrid) and data.n_cells:
        types = set(np.unique(np.asarray(data.celltypes)).tolist())
        polygonal = {int(pv.CellType.TRIANGLE), int(pv.CellType.QUAD), int(pv.CellType.POLYGON)}
        if types <= polygonal:
            surf = pv.PolyData(np.asarray(data.points), faces=np.asarray(data.cells))
            for name, values in data.point_data.items():
                surf.point_data[name] = values
            return surf
    return data


def same_file(a, b) -> bool:
    """Whether two paths name the same file: same inode (hard links), or same real path."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


def refuse_inputs(output, inputs) -> None:
    """Raise :class:`OverwriteError` if ``output`` is any of ``inputs``.

    The one guard every writer of user-named outputs uses (the command line, the
    explorer's export): whatever path, symbolic link or hard link names an input, it is
    never written.

    Parameters
    ----------
    output : path-like
    inputs : iterable of path-like or None
        Every file the operation reads: the data, the scene, every file the scene
        references (:meth:`vhm_viz.scene.Scene.referenced_files`).
    """
    for src in inputs:
        if src is not None and same_file(Path(src), Path(output)):
            raise OverwriteError(
                f"refusing to overwrite the input file {src} (as {output}); choose another output"
            )


def atomic_outputs(directory):
    """Write several files that belong together: all of them appear, or none.

    A context manager yielding a staging folder; the files written into it are moved into
    ``directory`` when the block ends without an error or interrupt (see
    :func:`vhm_viz.atomic.atomic_directory`).
    """
    return atomic_directory(directory)


def write_dataset(path, data) -> None:
    """Write a PyVista dataset atomically (format from the suffix).

    Images may also go to MetaImage (``.mhd`` + ``.raw``, or ``.mha``) and NIfTI
    (``.nii``, ``.nii.gz``), written here with their origin, spacing and direction
    (:func:`write_volume`).

    Parameters
    ----------
    path : str or os.PathLike
    data : pyvista.DataSet
    """
    if suffix_of(path) in VOLUME_WRITE_SUFFIXES:
        write_volume(path, data)
        return
    with atomic_path(path) as tmp:
        data.save(os.fspath(tmp))


# ----------------------------------------------------------------------------------------
# Volumes in medical formats
# ----------------------------------------------------------------------------------------
#: Image formats written by :func:`write_volume` (and whose orientation
#: :func:`read_dataset` reads from the header).
VOLUME_WRITE_SUFFIXES = (".mhd", ".mha", ".nii", ".nii.gz")
# NIfTI's world is RAS; vhm_viz follows ITK and DICOM (LPS), like MetaImage: x and y flip.
_RAS_LPS = np.diag([-1.0, -1.0, 1.0])
_META_TYPES = {
    "uint8": "MET_UCHAR", "int8": "MET_CHAR", "uint16": "MET_USHORT", "int16": "MET_SHORT",
    "uint32": "MET_UINT", "int32": "MET_INT", "uint64": "MET_ULONG_LONG",
    "int64": "MET_LONG_LONG", "float32": "MET_FLOAT", "float64": "MET_DOUBLE",
}  # fmt: skip
_NIFTI_TYPES = {  # NIfTI-1 datatype code, bits per voxel
    "uint8": (2, 8), "int16": (4, 16), "int32": (8, 32), "float32": (16, 32),
    "float64": (64, 64), "int8": (256, 8), "uint16": (512, 16), "uint32": (768, 32),
    "int64": (1024, 64), "uint64": (1280, 64),
}  # fmt: skip


def _volume_array(image) -> tuple[np.ndarray, str]:
    """The array a single-array format stores: the active scalars, else the first one."""
    name = image.active_scalars_name or (image.point_data.keys() or [None])[0]
    if name is None:
        raise ValueError("the image has no point array to write")
    values = np.ascontiguousarray(image.point_data[name])
    if values.dtype.name not in _META_TYPES:
        values = values.astype(np.float64)
    return values, name


def write_volume(path, image) -> None:
    """Write an image as MetaImage or NIfTI, keeping origin, spacing and direction.

    Formats with one array per file get the active scalars (or the first point array);
    multi-component arrays become channels (MetaImage) or a vector (NIfTI). Conventions
    are ITK's, so SimpleITK and ITK-based tools read the same geometry: MetaImage lists the
    direction matrix column by column (``TransformMatrix``, each image axis's direction in
    turn); NIfTI stores its RAS world, so x and y are negated from vhm_viz's (LPS) world.
    ``.mhd`` puts the voxels in a ``.raw`` file beside it; both are written atomically.

    Parameters
    ----------
    path : str or os.PathLike
        ``.mhd``, ``.mha``, ``.nii`` or ``.nii.gz``.
    image : pyvista.ImageData
    """
    suffix = suffix_of(path)
    if suffix not in VOLUME_WRITE_SUFFIXES:
        raise ValueError(f"write_volume writes {', '.join(VOLUME_WRITE_SUFFIXES)}; got {suffix!r}")
    if not hasattr(image, "direction_matrix"):
        raise ValueError(f"{suffix} holds an image (vtkImageData); got {type(image).__name__}")
    values, _ = _volume_array(image)
    if suffix in (".mhd", ".mha"):
        _write_metaimage(Path(path), image, values)
    else:
        _write_nifti(Path(path), image, values)


def _write_metaimage(path: Path, image, values: np.ndarray) -> None:
    direction = np.asarray(image.direction_matrix, dtype=np.float64)
    comps = 1 if values.ndim == 1 else values.shape[1]
    fmt = lambda v: " ".join(f"{x:.17g}" for x in v)  # noqa: E731
    data_file = "LOCAL" if path.suffix.lower() == ".mha" else path.with_suffix(".raw").name
    header = [
        "ObjectType = Image",
        "NDims = 3",
        "BinaryData = True",
        "BinaryDataByteOrderMSB = False",
        "CompressedData = False",
        f"TransformMatrix = {fmt(direction.T.ravel())}",  # ITK: one image axis after another
        f"Offset = {fmt(image.origin)}",
        "CenterOfRotation = 0 0 0",
        f"ElementSpacing = {fmt(image.spacing)}",
        f"DimSize = {' '.join(str(int(d)) for d in image.dimensions)}",
        *([f"ElementNumberOfChannels = {comps}"] if comps > 1 else []),
        f"ElementType = {_META_TYPES[values.dtype.name]}",
        f"ElementDataFile = {data_file}",
    ]
    text = ("\n".join(header) + "\n").encode("ascii")
    raw = values.astype(values.dtype.newbyteorder("<"), copy=False).tobytes()
    if data_file == "LOCAL":
        with atomic_path(path) as tmp:
            tmp.write_bytes(text + raw)
        return
    with atomic_path(path.with_suffix(".raw")) as tmp:
        tmp.write_bytes(raw)
    with atomic_path(path) as tmp:
        tmp.write_bytes(text)


def _write_nifti(path: Path, image, values: np.ndarray) -> None:
    """NIfTI-1 (single file, 352-byte header) with matching qform and sform."""
    import gzip
    import struct

    from scipy.spatial.transform import Rotation

    if values.dtype.name not in _NIFTI_TYPES:
        values = values.astype(np.float64)
    code, bits = _NIFTI_TYPES[values.dtype.name]
    comps = 1 if values.ndim == 1 else values.shape[1]
    spacing = np.asarray(image.spacing, dtype=np.float64)
    rot = _RAS_LPS @ np.asarray(image.direction_matrix, dtype=np.float64)
    offset = _RAS_LPS @ np.asarray(image.origin, dtype=np.float64)
    # the quaternion holds a proper rotation; a reflection flips the third axis (qfac = -1)
    qfac = 1.0 if np.linalg.det(rot) > 0 else -1.0
    quat = Rotation.from_matrix(rot * [1.0, 1.0, qfac]).as_quat()  # x, y, z, w
    if quat[3] < 0:
        quat = -quat
    affine = rot * spacing
    dims = [5 if comps > 1 else 3, *image.dimensions, 1, comps, 1, 1]
    header = bytearray(352)
    struct.pack_into("<i", header, 0, 348)
    struct.pack_into("<8h", header, 40, *dims)
    if comps > 1:
        struct.pack_into("<h", header, 68, 1007)  # intent: vector
    struct.pack_into("<2h", header, 70, code, bits)
    struct.pack_into("<8f", header, 76, qfac, *spacing, 1.0, 1.0, 1.0, 1.0)
    struct.pack_into("<f", header, 108, 352.0)  # vox_offset
    struct.pack_into("<f", header, 112, 1.0)  # scl_slope
    header[123] = 2  # xyzt_units: millimetres
    struct.pack_into("<2h", header, 252, 1, 1)  # qform_code, sform_code: scanner
    struct.pack_into("<6f", header, 256, *quat[:3], *offset)
    for r in range(3):
        struct.pack_into("<4f", header, 280 + 16 * r, *affine[r], offset[r])
    header[344:348] = b"n+1\0"
    raw = values.astype(values.dtype.newbyteorder("<"), copy=False)
    # NIfTI orders a vector's components slowest: (c, z, y, x)
    blob = bytes(header) + (raw.T if comps > 1 else raw).tobytes()
    with atomic_path(path) as tmp:
        if suffix_of(path) == ".nii.gz":
            with gzip.open(tmp, "wb", compresslevel=6) as fh:
                fh.write(blob)
        else:
            tmp.write_bytes(blob)


def _apply_orientation(p: Path, suffix: str, image) -> None:
    """Origin and direction of a MetaImage or NIfTI file, read as ITK reads them.

    VTK's MetaImage reader takes ``TransformMatrix`` row by row (the transpose of what ITK
    writes), and its NIfTI reader keeps the qform/sform apart from the image.
    """
    if not hasattr(image, "direction_matrix"):
        return
    if suffix in (".mhd", ".mha"):
        fields = {}
        with open(p, "rb") as fh:
            for raw in fh:
                line = raw.decode("latin-1").strip()
                key, _, value = line.partition("=")
                fields[key.strip()] = value.strip()
                if key.strip() == "ElementDataFile":
                    break
        text = fields.get("TransformMatrix") or fields.get("Rotation") or fields.get("Orientation")
        if text:
            m = np.array([float(v) for v in text.split()], dtype=np.float64)
            if m.size == 9:
                image.direction_matrix = m.reshape(3, 3).T
        return
    from vtkmodules.vtkIOImage import vtkNIFTIImageReader

    reader = vtkNIFTIImageReader()
    reader.SetFileName(os.fspath(p))
    reader.UpdateInformation()
    matrix = reader.GetSFormMatrix() or reader.GetQFormMatrix()
    if matrix is None:
        return
    m = np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])
    image.origin = tuple(_RAS_LPS @ m[:3, 3])
    image.direction_matrix = _RAS_LPS @ m[:3, :3]


def write_text(path, text: str) -> None:
    """Write UTF-8 text atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def json_text(obj) -> str:
    """JSON text with one point (a list of numbers) per line, floats at full precision.

    ``json.dumps(indent=...)`` writes one number per line, which makes a scene of a
    500-face cage 5,000 lines long; here innermost lists stay on one line.
    """
    text = json.dumps(obj, indent=1)
    # join the lines of every innermost list of numbers: "[\n  1.0,\n  2.0\n ]" -> "[1.0, 2.0]"
    number_list = re.compile(r"\[\s*(-?[0-9][^\[\]{}\"]*?)\s*\]")
    joined = number_list.sub(lambda m: "[" + ", ".join(re.split(r",\s*", m.group(1))) + "]", text)
    return joined + "\n"


# ----------------------------------------------------------------------------------------
# Cages
# ----------------------------------------------------------------------------------------


def read_cage(path, **kwargs) -> Cage:
    """Read a cage (OBJ, OFF, PLY, STL, VTP, VTK, VTU) and validate it.

    OBJ and OFF are parsed here, so vertex numbering matches the file exactly (VTK's OBJ
    reader can split vertices that carry several texture coordinates or normals); the other
    formats go through VTK. Quads and polygons are triangulated
    (:func:`~vhm_viz.core.geometry.triangulate_polygons`); STL's per-facet corners are
    merged when bit-identical. Slivers are repaired or refused (:class:`Cage`), unless an
    OBJ file accepts them with a ``# vhm_viz min_angle 0`` comment line (what
    :func:`write_cage` writes for automatic cages, whose thin faces are then reported).

    Parameters
    ----------
    path : str or os.PathLike
    **kwargs
        Passed to :class:`~vhm_viz.core.cage.Cage` (``check_self_intersection``).

    Returns
    -------
    Cage

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    CageError
        Unreadable file, or not a valid cage (the message says why).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no such cage file: {p}")
    suffix = suffix_of(p)
    if suffix not in CAGE_SUFFIXES:
        raise CageError(
            f"unsupported cage file type {suffix!r} ({p}); use {', '.join(CAGE_SUFFIXES)}"
        )
    try:
        if suffix == ".obj":
            points, polys = _read_obj(p)
            kwargs.setdefault("min_angle", _obj_min_angle(p))
        elif suffix == ".off":
            points, polys = _read_off(p)
        else:
            _check_format(p, suffix)
            mesh = _read_vtk_isolated(p, suffix)
            _check_dataset(mesh, p)
            points, polys = _polygons_of(mesh)
    except ReadError as exc:
        raise CageError(str(exc)) from None
    except CageError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise CageError(f"{p}: cannot read ({_first_line(exc)})") from exc
    tris = triangulate_polygons(points, polys)
    if suffix == ".stl":
        points, tris = _merge_exact_duplicates(points, tris)
    try:
        return Cage(points, tris, **kwargs)
    except CageError as exc:  # name the file: a scene may read several
        raise CageError(f"{p.name}: {exc}", exc.indices) from None


def cage_from_dataset(data, **kwargs) -> Cage:
    """The cage of a VTK (or PyVista) surface; polygons are triangulated.

    An unstructured grid of triangles/quads/polygons is used as is (point order kept); any
    other dataset contributes its outer surface. Uses VTK only (no PyVista).

    Parameters
    ----------
    data : vtkDataSet
    **kwargs
        Passed to :class:`~vhm_viz.core.cage.Cage`.

    Returns
    -------
    Cage
    """
    points, polys = _polygons_of(data)
    return Cage(points, triangulate_polygons(points, polys), **kwargs)


def cage_to_polydata(cage):
    """The cage as a triangle ``vtkPolyData`` (point order kept), VTK only.

    Cell data ``"Normals"`` holds the unit outward face normals. ``pyvista.wrap`` of the
    result is a ``pyvista.PolyData``.
    """
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    v = np.ascontiguousarray(cage.vertices, dtype=np.float64)
    f = np.asarray(cage.faces, dtype=np.int64)
    pts = vtkPoints()
    pts.SetData(ns.numpy_to_vtk(v, deep=1))
    cells = vtkCellArray()
    cells.SetData(
        ns.numpy_to_vtkIdTypeArray(np.arange(0, 3 * len(f) + 1, 3, dtype=np.int64), deep=1),
        ns.numpy_to_vtkIdTypeArray(np.ascontiguousarray(f.ravel()), deep=1),
    )
    pd = vtkPolyData()
    pd.SetPoints(pts)
    pd.SetPolys(cells)
    normals = ns.numpy_to_vtk(np.ascontiguousarray(cage.face_normals, dtype=np.float64), deep=1)
    normals.SetName("Normals")
    pd.GetCellData().SetNormals(normals)
    return pd


def write_cage(path, cage, comment: str = "") -> None:
    """Write a cage atomically: OBJ (text, full precision) or any format VTK writes.

    Parameters
    ----------
    path : str or os.PathLike
        ``.obj`` is written here, with ``comment`` as ``#`` lines; other suffixes (PLY,
        STL, VTP, VTK) through VTK.
    cage : Cage
    comment : str
    """
    if suffix_of(path) == ".obj":
        lines = [f"# {line}" for line in comment.splitlines()]
        if len(getattr(cage, "thin_faces", ())):
            # a cage accepted with thin faces (an automatic one) reads back the same way
            lines.append(f"{_MIN_ANGLE_DIRECTIVE} {cage.min_angle:g}")
        lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in np.asarray(cage.vertices)]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(cage.faces)]
        write_text(path, "\n".join(lines) + "\n")
        return
    import pyvista as pv

    write_dataset(path, pv.wrap(cage_to_polydata(cage)))


def _polygons_of(data) -> tuple[np.ndarray, list[np.ndarray]]:
    """Points and polygon list of a VTK dataset's surface cells (VTK only)."""
    from vtkmodules.vtkCommonDataModel import VTK_POLYGON, VTK_QUAD, VTK_TRIANGLE
    from vtkmodules.vtkFiltersCore import vtkTriangleFilter
    from vtkmodules.vtkFiltersGeometry import vtkDataSetSurfaceFilter

    if data.IsA("vtkUnstructuredGrid") and data.GetNumberOfCells():
        types = cell_types(data)
        if np.isin(types, [VTK_TRIANGLE, VTK_QUAD, VTK_POLYGON]).all():
            return _points_of(data), _cell_lists(data.GetCells())
    if not data.IsA("vtkPolyData"):
        surf = vtkDataSetSurfaceFilter()
        surf.SetInputData(data)
        surf.Update()
        data = surf.GetOutput()
    if data.GetNumberOfStrips():
        tri = vtkTriangleFilter()
        tri.SetInputData(data)
        tri.Update()
        data = tri.GetOutput()
    return _points_of(data), _cell_lists(data.GetPolys())


def cell_types(grid) -> np.ndarray:
    """Cell type of every cell of an unstructured grid (VTK 9.2 to 9.6 spell it differently)."""
    from vtkmodules.util import numpy_support as ns

    if grid.GetNumberOfCells() == 0:
        return np.zeros(0, np.uint8)
    try:  # VTK >= 9.6: an array; older versions take a vtkCellTypes argument instead
        arr = grid.GetCellTypes()
    except TypeError:
        arr = None
    if arr is None or not hasattr(arr, "GetNumberOfTuples"):
        arr = grid.GetCellTypesArray()
    return ns.vtk_to_numpy(arr)


def _points_of(data) -> np.ndarray:
    from vtkmodules.util import numpy_support as ns

    if data.GetPoints() is None:
        return np.zeros((0, 3))
    return np.array(ns.vtk_to_numpy(data.GetPoints().GetData()), dtype=np.float64).reshape(-1, 3)


def _cell_lists(cells) -> list[np.ndarray]:
    from vtkmodules.util import numpy_support as ns

    if cells is None or cells.GetNumberOfCells() == 0:
        return []
    offsets = ns.vtk_to_numpy(cells.GetOffsetsArray()).astype(np.int64)
    conn = ns.vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64)
    return [conn[offsets[i] : offsets[i + 1]] for i in range(len(offsets) - 1)]


def _merge_exact_duplicates(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical points (STL stores each facet's corners separately)."""
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(first)  # keep first-occurrence order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return points[np.sort(first)], rank[inverse][tris]


#: An OBJ cage comment line accepting thin faces (``# vhm_viz min_angle 0``): what
#: :func:`write_cage` writes for a cage that has them (automatic cages), so that reading it
#: back accepts the same cage; :func:`read_cage` then reports them rather than repairing or
#: refusing them (:attr:`~vhm_viz.core.cage.Cage.thin_faces`).
_MIN_ANGLE_DIRECTIVE = "# vhm_viz min_angle"


def _obj_min_angle(path: Path) -> float:
    """The ``min_angle`` an OBJ cage asks for (:data:`MIN_FACE_ANGLE` unless it says)."""
    from vhm_viz.core.cage import MIN_FACE_ANGLE

    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith(_MIN_ANGLE_DIRECTIVE):
                try:
                    return min(float(line[len(_MIN_ANGLE_DIRECTIVE) :].split()[0]), MIN_FACE_ANGLE)
                except (IndexError, ValueError):
                    break
            elif line.strip() and not line.startswith("#"):
                break  # directives come first, with the other comments
    return MIN_FACE_ANGLE


def _read_obj(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    verts: list[list[float]] = []
    polys: list[np.ndarray] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "v":
                try:
                    verts.append([float(x) for x in tok[1:4]])
                except ValueError as exc:
                    raise CageError(f"{path}:{lineno}: bad vertex line {line.strip()!r}") from exc
                if len(verts[-1]) != 3:
                    raise CageError(f"{path}:{lineno}: vertex with fewer than 3 coordinates")
            elif tok[0] == "f":
                try:
                    ids = [int(t.split("/")[0]) for t in tok[1:]]
                except ValueError as exc:
                    raise CageError(f"{path}:{lineno}: bad face line {line.strip()!r}") from exc
                nv = len(verts)
                # 1-based; negative indices count back from the latest vertex
                polys.append(np.array([i - 1 if i > 0 else nv + i for i in ids], dtype=np.int64))
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), polys


def _parse_off(path: Path) -> tuple[np.ndarray, list[np.ndarray], int]:
    """The one OFF parser: points, every record after them, and the header's face count.

    Records are index lists (``k i j ...``): faces, and -- in rigidity-line files such as
    the hand's ``polylines.off`` -- edges (``k = 2``) after the faces. Refuses a file whose
    header announces more points or faces than it holds, and indices out of range.
    """
    with open(path, encoding="utf-8", errors="replace") as fh:
        lines = [t for t in (ln.split("#", 1)[0].split() for ln in fh) if t]
    if not lines or not lines[0][0].upper().endswith("OFF"):
        raise ReadError(f"{path}: not an OFF file (no OFF header)")
    head, rest = lines[0][1:], lines[1:]
    if not head:
        if not rest:
            raise _Truncated(f"{path}: truncated OFF file (no counts line)")
        head, rest = rest[0], rest[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
        if nv < 0 or nf < 0:
            raise ValueError(f"negative count in {' '.join(head)!r}")
        if len(rest) < nv:
            raise _Truncated(
                f"{path}: truncated: the header announces {nv} points, the file has {len(rest)}"
            )
        verts = np.array([[float(x) for x in t[:3]] for t in rest[:nv]], dtype=np.float64)
        if verts.size and verts.shape[1:] != (3,):
            raise ValueError("a point line with fewer than 3 coordinates")
        records = []
        for t in rest[nv:]:
            k = int(t[0])
            ids = np.array([int(x) for x in t[1 : 1 + k]], dtype=np.int64)
            if k < 1 or len(ids) != k:
                raise ValueError(f"bad record {' '.join(t)[:40]!r}")
            records.append(ids)
    except ReadError:
        raise
    except (ValueError, IndexError) as exc:
        raise ReadError(f"{path}: malformed OFF file: {exc}") from None
    if len(records) < nf:
        raise _Truncated(
            f"{path}: truncated: the header announces {nv} points and {nf} faces, the file "
            f"holds {len(records)} faces"
        )
    bad = [i for i, r in enumerate(records) if r.min() < 0 or r.max() >= nv]
    if bad:
        raise ReadError(f"{path}: record {bad[0]} refers to a point outside [0, {nv})")
    return verts.reshape(-1, 3), records, nf


def _read_off(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """Points and the faces (the header's count of records) of an OFF cage."""
    points, records, nf = _parse_off(path)
    return points, records[:nf]


def _off_dataset(path: Path):
    """An OFF file as PolyData: polygons, and any edge (2) or vertex (1) records."""
    import pyvista as pv

    points, records, _ = _parse_off(path)
    by_kind: dict[str, list] = {"faces": [], "lines": [], "verts": []}
    for r in records:
        kind = "faces" if len(r) >= 3 else ("lines" if len(r) == 2 else "verts")
        by_kind[kind].append(np.concatenate([[len(r)], r]))
    cells = {k: np.concatenate(v) for k, v in by_kind.items() if v}
    return pv.PolyData(points, **cells)


# ----------------------------------------------------------------------------------------
# Anchors
# ----------------------------------------------------------------------------------------


def read_anchors(path) -> np.ndarray:
    """Anchor points from a JSON file: what ``vhm-viz anchors`` writes, or a bare list.

    Parameters
    ----------
    path : str or os.PathLike
        ``{"anchors": [[x, y, z], ...], ...}`` or ``[[x, y, z], ...]``.

    Returns
    -------
    (d, 3) float64

    Raises
    ------
    FileNotFoundError, ReadError
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no such anchors file: {p}")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReadError(f"{p}: not a JSON anchors file ({_first_line(exc)})") from exc
    if isinstance(data, dict):
        data = data.get("anchors")
    try:
        pts = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        pts = np.zeros((0,))
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.isfinite(pts).all():
        raise ReadError(f"{p}: expected a non-empty list of [x, y, z] anchor points")
    return pts


def write_anchors(path, anchors, **info) -> None:
    """Write anchors as ``{"anchors": [[x, y, z], ...], "count": d, **info}`` (atomic)."""
    a = np.asarray(anchors, dtype=np.float64).reshape(-1, 3)
    write_text(path, json_text({"anchors": a.tolist(), "count": len(a), **info}))


# ----------------------------------------------------------------------------------------
# Rigidity lines
# ----------------------------------------------------------------------------------------


def read_polylines(path) -> tuple[np.ndarray, np.ndarray]:
    """Read polylines stored as an OFF file with edge records.

    The format (used e.g. by the hand model's ``polylines.off``)::

        OFF
        <n_points> <n_faces> <n_edges>
        x y z                 (n_points lines)
        k i j ...             (n_faces + n_edges records; a record with k = 2 is an edge)

    Records with ``k > 2`` (polygons) are read as closed polylines: their consecutive
    vertex pairs (and last to first) become edges. ``n_faces`` and ``n_edges`` are only
    used to know how many records follow; all records are read either way.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    points : (P, 3) float64
    edges : (E, 2) int64

    Raises
    ------
    ValueError
        Not an OFF file, truncated, or indices out of range.
    """
    pts, records, _ = _parse_off(Path(path))
    edges = []
    for ids in records:
        k = len(ids)
        if k == 2:
            edges.append(ids)
        elif k > 2:
            edges.extend([ids[i], ids[(i + 1) % k]] for i in range(k))
    return pts, np.asarray(edges, dtype=np.int64).reshape(-1, 2)


def read_tgf(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a libigl ``.tgf`` skeleton: joints, then bones.

    Format: one line per joint ``index x y z [ignored...]`` (1-based index), a line ``#``,
    then one line per bone ``a b [ignored...]`` (1-based joint indices), optionally another
    ``#`` followed by point handles or cage edges (ignored).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    joints : (J, 3) float64
        In file order.
    bones : (B, 2) int64
        0-based joint indices.

    Raises
    ------
    ValueError
        Malformed lines or bone indices out of range.
    """
    with open(os.fspath(path), encoding="utf-8", errors="replace") as fh:
        raw = fh.read().splitlines()
    section = 0
    joints, bones = [], []
    for n, line in enumerate(raw, 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            section += 1
            if section >= 2:
                break
            continue
        vals = s.split()
        try:
            if section == 0:
                joints.append([float(v) for v in vals[1:4]])
                if len(joints[-1]) != 3:
                    raise ValueError
            else:
                bones.append([int(vals[0]) - 1, int(vals[1]) - 1])
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{path}:{n}: malformed line {s!r}") from exc
    j = np.asarray(joints, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(bones, dtype=np.int64).reshape(-1, 2)
    if b.size and (b.min() < 0 or b.max() >= len(j)):
        raise ValueError(f"{path}: bone index out of range [1, {len(j)}]")
    return j, b


def read_rigidity_lines(path) -> tuple[np.ndarray, np.ndarray]:
    """Rigidity lines from any file that holds them, by suffix.

    ``.tgf`` (libigl skeleton, :func:`read_tgf`), ``.off`` (OFF polylines,
    :func:`read_polylines`), or any dataset with line cells (``.vtp``, ``.vtk``, ...).

    Returns
    -------
    points : (P, 3) float64
    edges : (E, 2) int64

    Raises
    ------
    FileNotFoundError, ReadError, ValueError
    """
    suffix = suffix_of(path)
    if suffix == ".tgf":
        return read_tgf(path)
    if suffix == ".off":
        return read_polylines(path)
    data = read_dataset(path)
    lines = np.asarray(getattr(data, "lines", np.zeros(0, int)))
    if not len(lines):
        raise ReadError(f"{path}: no polylines in this file")
    edges, i = [], 0
    while i < len(lines):
        k = int(lines[i])
        ids = lines[i + 1 : i + 1 + k]
        edges.extend(zip(ids[:-1], ids[1:], strict=True))
        i += k + 1
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    return np.asarray(data.points, dtype=np.float64), edges
