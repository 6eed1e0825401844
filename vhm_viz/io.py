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
  :func:`json_text` -- compact JSON, one point per line.

Writers take the destination first: ``write_*(path, what)``.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from pathlib import Path

import numpy as np

from vhm_viz.atomic import atomic_path
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
    "json_text",
    "suffix_of",
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
_MESHIO_SUFFIXES = (".mesh", ".off")


class ReadError(ValueError):
    """A file that cannot be read as what was asked for; the message names the file."""


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
    """Read a mesh, tet mesh, point cloud or volume.

    Parameters
    ----------
    path : str or os.PathLike
        One of :data:`DATASET_SUFFIXES`. ``.npy``/``.xyz``/``.txt``/``.csv`` hold one point
        per row (the first three columns are x, y, z).

    Returns
    -------
    pyvista.DataSet
        ``PolyData`` for surfaces and point lists (an OBJ/OFF read as polygon cells becomes
        a surface again), ``UnstructuredGrid`` for volumetric meshes, ``ImageData`` for
        volumes, and so on. A MultiBlock file with one block gives that block.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ReadError
        Unknown suffix, unreadable or empty file, several datasets in one file.
    """
    import pyvista as pv

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no such file: {p}")
    if not p.is_file():
        raise ReadError(f"{p}: not a file")
    suffix = suffix_of(p)
    if suffix not in DATASET_SUFFIXES:
        raise ReadError(
            f"{p}: unsupported file type {suffix or '(none)'!r}; use one of "
            f"{', '.join(DATASET_SUFFIXES)}"
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if suffix in _POINT_LIST_SUFFIXES:
                data = pv.PolyData(_read_point_list(p, suffix))
            elif suffix in _MESHIO_SUFFIXES:
                data = _read_meshio(p)
            else:
                data = pv.read(os.fspath(p))
        except ReadError:
            raise
        except Exception as exc:  # noqa: BLE001 -- VTK and meshio raise many types
            raise ReadError(f"{p}: cannot read ({_first_line(exc)})") from exc
    if isinstance(data, pv.MultiBlock):
        blocks = [b for b in data if b is not None]
        if len(blocks) != 1:
            raise ReadError(f"{p}: holds {len(blocks)} datasets (a MultiBlock); give one dataset")
        data = blocks[0]
    if data is None or data.n_points == 0:
        why = f" ({_first_line(caught[0].message)})" if caught else ""
        raise ReadError(f"{p}: no points (empty, or not a valid {suffix} file){why}")
    if suffix in VOLUME_WRITE_SUFFIXES:
        _apply_orientation(p, suffix, data)
    return _surface_if_polygonal(data)


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
    pts = np.ascontiguousarray(pts[:, :3])
    if not np.isfinite(pts).all():
        raise ReadError(f"{p}: points with non-finite coordinates")
    return pts


def _read_meshio(p: Path):
    import meshio
    import pyvista as pv

    try:
        mesh = meshio.read(os.fspath(p))
    except SystemExit as exc:  # meshio's OFF reader calls sys.exit on malformed files
        raise ReadError(f"{p}: malformed {suffix_of(p)} file") from exc
    return pv.from_meshio(mesh)


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
    merged when bit-identical.

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
    if suffix == ".obj":
        points, polys = _read_obj(p)
        return Cage(points, triangulate_polygons(points, polys), **kwargs)
    if suffix == ".off":
        points, polys = _read_off(p)
        return Cage(points, triangulate_polygons(points, polys), **kwargs)
    if suffix in CAGE_SUFFIXES:
        import pyvista as pv

        try:
            mesh = pv.read(os.fspath(p))
        except Exception as exc:  # noqa: BLE001
            raise CageError(f"{p}: cannot read ({_first_line(exc)})") from exc
        if suffix == ".stl":
            points, polys = _polygons_of(mesh)
            points, tris = _merge_exact_duplicates(points, triangulate_polygons(points, polys))
            return Cage(points, tris, **kwargs)
        return cage_from_dataset(mesh, **kwargs)
    raise CageError(
        f"unsupported cage file type {suffix!r} ({p}); use {', '.join(CAGE_SUFFIXES)}"
    )


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
        types = _cell_types(data)
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


def _cell_types(grid) -> np.ndarray:
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


def _read_off(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    with open(path, encoding="utf-8", errors="replace") as fh:
        lines = [ln.split("#", 1)[0].split() for ln in fh]
    lines = [t for t in lines if t]
    if not lines or not lines[0][0].endswith("OFF"):
        raise CageError(f"{path}: not an OFF file (no OFF header)")
    head = lines[0][1:]
    rest = lines[1:]
    if not head:
        head, rest = rest[0], rest[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
        verts = np.array([[float(x) for x in t[:3]] for t in rest[:nv]], dtype=np.float64)
        polys = []
        for t in rest[nv : nv + nf]:
            k = int(t[0])
            polys.append(np.array([int(x) for x in t[1 : 1 + k]], dtype=np.int64))
    except (ValueError, IndexError) as exc:
        raise CageError(f"{path}: malformed OFF file: {exc}") from exc
    if len(verts) != nv or len(polys) != nf:
        raise CageError(f"{path}: OFF header announces {nv} vertices / {nf} faces, file is short")
    return verts.reshape(-1, 3), polys



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


def _data_lines(text: str):
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            yield line


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
    with open(os.fspath(path), encoding="utf-8", errors="replace") as fh:
        lines = list(_data_lines(fh.read()))
    if not lines or not lines[0].upper().startswith("OFF"):
        raise ValueError(f"{path}: not an OFF file (missing 'OFF' header)")
    head = lines[0][3:].split()
    idx = 1
    if not head:
        if len(lines) < 2:
            raise ValueError(f"{path}: missing the counts line")
        head = lines[1].split()
        idx = 2
    try:
        n_points = int(head[0])
        n_records = int(head[1]) + (int(head[2]) if len(head) > 2 else 0)
    except (IndexError, ValueError) as exc:
        raise ValueError(f"{path}: bad counts line {' '.join(head)!r}") from exc
    if len(lines) < idx + n_points:
        raise ValueError(f"{path}: expected {n_points} points, file is truncated")
    try:
        pts = np.array([[float(v) for v in lines[idx + i].split()[:3]] for i in range(n_points)])
    except ValueError as exc:
        raise ValueError(f"{path}: bad point line") from exc
    pts = pts.reshape(-1, 3)
    edges = []
    for line in lines[idx + n_points :]:
        vals = line.split()
        k = int(vals[0])
        ids = [int(v) for v in vals[1 : 1 + k]]
        if len(ids) != k:
            raise ValueError(f"{path}: truncated record {line!r}")
        if k == 2:
            edges.append(ids)
        elif k > 2:
            edges.extend([ids[i], ids[(i + 1) % k]] for i in range(k))
    del n_records  # informational only
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if e.size and (e.min() < 0 or e.max() >= n_points):
        raise ValueError(f"{path}: edge index out of range [0, {n_points})")
    return pts, e


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
