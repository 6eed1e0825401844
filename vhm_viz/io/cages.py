"""Cages from and to files and VTK surfaces: the one :class:`~vhm_viz.core.cage.Cage`.

Which files are cages, and who reads each, is the format table's ``cage`` column
(:mod:`vhm_viz.io.registry`). OBJ and OFF are parsed here and in
:mod:`vhm_viz.io.mesh_files`, so vertex numbering matches the file; the other formats go
through VTK. This module uses VTK only, no PyVista, on the paths ParaView runs
(:func:`cage_from_dataset`, :func:`cage_to_polydata`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vhm_viz.core.cage import MIN_FACE_ANGLE, Cage
from vhm_viz.core.errors import CageError
from vhm_viz.core.geometry import triangulate_polygons
from vhm_viz.io.datasets import check_dataset, write_dataset
from vhm_viz.io.errors import AGAIN, ReadError, check_file_size, first_line, require_file
from vhm_viz.io.mesh_files import parse_off
from vhm_viz.io.registry import cage_suffixes, format_of, suffix_of
from vhm_viz.io.text import write_text
from vhm_viz.io.vtk_files import read_vtk_file

__all__ = [
    "read_cage",
    "cage_from_dataset",
    "cage_to_polydata",
    "write_cage",
    "cell_types",
    "read_obj_cage",
    "read_off_cage",
    "read_vtk_cage",
    "read_stl_cage",
]


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
    require_file(p, "cage")
    check_file_size(p, "cage")
    fmt = format_of(p)
    if fmt is None or fmt.cage is None:
        raise CageError(
            f"unsupported cage file type {suffix_of(p)!r} ({p}); use {', '.join(cage_suffixes())}"
        )
    try:
        check = fmt.function("check")
        if check is not None:
            check(p)
        points, polygons, options = fmt.function("cage")(p)
    except ReadError as exc:
        raise CageError(str(exc)) from None
    except CageError:
        raise
    except Exception as exc:  # noqa: BLE001
        raise CageError(f"{p}: cannot read ({first_line(exc)})") from exc
    for key, value in options.items():
        kwargs.setdefault(key, value)
    try:
        return Cage(points, triangulate_polygons(points, polygons), **kwargs)
    except CageError as exc:  # name the file: a scene may read several
        raise CageError(f"{p.name}: {exc}", exc.indices) from None


def read_obj_cage(path) -> tuple[np.ndarray, list[np.ndarray], dict]:
    """Points and polygons of an OBJ cage, parsed here, and the ``min_angle`` it asks for.

    Parsed here, not by VTK, so that vertex numbering matches the file exactly (VTK's OBJ
    reader can split vertices that carry several texture coordinates or normals).
    """
    points, polygons = _read_obj(Path(path))
    return points, polygons, {"min_angle": _obj_min_angle(Path(path))}


def read_off_cage(path) -> tuple[np.ndarray, list[np.ndarray], dict]:
    """Points and faces (the header's count of records) of an OFF cage."""
    points, records, n_faces = parse_off(Path(path))
    return points, records[:n_faces], {}


def read_vtk_cage(path) -> tuple[np.ndarray, list[np.ndarray], dict]:
    """Points and surface polygons of a file VTK reads (PLY, VTP, VTK, VTU)."""
    mesh = read_vtk_file(path)
    check_dataset(mesh, path)
    points, polygons = _polygons_of(mesh)
    return points, polygons, {}


def read_stl_cage(path) -> tuple[np.ndarray, np.ndarray, dict]:
    """Points and triangles of an STL cage, bit-identical corners merged.

    STL stores each facet's corners separately; merged, the facets share their vertices.
    """
    points, polygons, _ = read_vtk_cage(path)
    points, triangles = _merge_exact_duplicates(points, triangulate_polygons(points, polygons))
    return points, triangles, {}


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
    short = None  # the first face of fewer than 3 vertices: (line number, text)
    last = 0  # the last line that holds anything
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            tok = line.split()
            if not tok:
                continue
            last = lineno
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
                if len(ids) < 3 and short is None:
                    short = (lineno, line.strip())
                nv = len(verts)
                # 1-based; negative indices count back from the latest vertex
                polys.append(np.array([i - 1 if i > 0 else nv + i for i in ids], dtype=np.int64))
    if short is not None:
        # left out, it would open the cage; on the last line, the file was likely cut there
        cut = f"; the file may be cut short: {AGAIN}" if short[0] == last else ""
        raise CageError(f"{path}:{short[0]}: face with fewer than 3 vertices {short[1]!r}{cut}")
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), polys
