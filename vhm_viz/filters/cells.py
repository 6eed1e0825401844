"""Cells as tetrahedra, and datasets as regions: the VTK edge of the cell and injectivity analysis.

The numeric core measures linear tetrahedra (:func:`vhm_viz.core.metrics.cell_measures`)
and certifies regions (:mod:`vhm_viz.core.certify`); this module turns VTK datasets into
those arrays:

* :func:`cell_tetrahedra` -- the 3D cells of a dataset split into tetrahedra, chunk by chunk
  with the cell each tet came from: tet meshes as they are; image and structured data six
  tets per voxel around its main diagonal (Kuhn's conforming split), slab by slab so a
  large volume never materialises as an unstructured grid; every other cell type through
  ``vtkDataSetTriangleFilter``.
* :func:`cell_quality` -- the per-cell determinant and condition number of a deformation,
  plus the counts ``metrics.json`` reports.
* :func:`region_of` -- the region to certify for a dataset: a volume's box, a mesh's
  tetrahedra, a closed surface's solid, or the cage's interior.
"""

from __future__ import annotations

import itertools

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonCore import vtkIdList
from vtkmodules.vtkCommonDataModel import vtkDataSetAttributes

from vhm_viz.core.basis import inside_cage, winding_number
from vhm_viz.core.cell_kernels import kuhn_corners, lattice_tetrahedron_measures
from vhm_viz.core.certify import INSIDE, MEETS, OUTSIDE, Region, default_margin
from vhm_viz.core.geometry import open_edge_count, signed_volume
from vhm_viz.core.metrics import cell_measures, cell_summary
from vhm_viz.filters._vtk import numpy_points, set_field_counts
from vhm_viz.io import cell_types

__all__ = [
    "CELL_ARRAYS",
    "has_3d_cells",
    "cell_tetrahedra",
    "tetra_cells",
    "cell_centres",
    "cells_touching",
    "cell_quality",
    "add_cell_arrays",
    "region_of",
]

#: Cell arrays written by the analysis (and, on request, the deformation) filter.
CELL_ARRAYS = ("cell_jacobian_determinant", "cell_condition_number", "cell_inverted")
# Tetrahedra per chunk (bounds the work arrays at about 100 MB).
_CHUNK_TETS = 2_000_000
_VTK_TETRA = 10
_VTK_POLYHEDRON = 42
_ID_ARRAY = "vhm_cell_id"


def _dimensions(ds):
    """Point dimensions of image, rectilinear and structured data (else None)."""
    if ds.IsA("vtkImageData") or ds.IsA("vtkRectilinearGrid") or ds.IsA("vtkStructuredGrid"):
        dims = [0, 0, 0]
        ds.GetDimensions(dims)
        return tuple(int(d) for d in dims)
    return None


def _cell_dimension(cell_type: int) -> int:
    """Topological dimension of a VTK cell type (VTK >= 9.6 moved the function)."""
    try:
        from vtkmodules.vtkCommonDataModel import vtkCellTypeUtilities as utilities
    except ImportError:  # VTK < 9.6
        from vtkmodules.vtkCommonDataModel import vtkCellTypes as utilities
    return int(utilities.GetDimension(int(cell_type)))


def has_3d_cells(ds) -> bool:
    """Whether ``ds`` has the 3D cells that the cell arrays measure.

    A grid none of whose dimensions is flat has them, and so has an unstructured grid
    with at least one 3D cell; surfaces and point clouds have none.
    """
    dims = _dimensions(ds)
    if dims is not None:
        return all(d >= 2 for d in dims)
    if not ds.IsA("vtkUnstructuredGrid") or ds.GetNumberOfCells() == 0:
        return False
    return any(_cell_dimension(t) == 3 for t in np.unique(cell_types(ds)))


def _kuhn_tets(dims, k0: int, k1: int):
    """Tets (point ids) and voxel ids of the voxel layers ``k0 <= k < k1`` of a lattice."""
    nx, ny, _ = dims
    i, j, k = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(k0, k1), indexing="ij")
    i, j, k = (np.ravel(a, order="F") for a in (i, j, k))  # VTK order: i fastest
    voxel = i + (nx - 1) * (j + (ny - 1) * k)
    base = i + nx * (j + ny * k)
    corners = kuhn_corners()
    delta = corners[..., 0] + nx * (corners[..., 1] + ny * corners[..., 2])
    tets = (base[None, :, None] + delta[:, None, :]).reshape(-1, 4)
    return tets, np.tile(voxel, len(delta))


def cell_tetrahedra(ds, chunk_tets: int = _CHUNK_TETS):
    """The 3D cells of a dataset as tetrahedra, in chunks.

    Parameters
    ----------
    ds : vtkDataSet
    chunk_tets : int
        Tetrahedra per chunk, about: lattices are split by layers of voxels, other cells
        than tets (quadratic tets, hexahedra, ...) by runs of cells, whose tets all come
        in one chunk; a mesh whose 3D cells are all tets comes whole, as stored.

    Yields
    ------
    tets : (T, 4) int64
        Point ids of the dataset's points.
    cells : (T,) int64
        The cell each tet belongs to. Cells that are not 3D get no tets.
    """
    dims = _dimensions(ds)
    if dims is not None:
        if not all(d >= 2 for d in dims):
            return
        per_layer = 6 * (dims[0] - 1) * (dims[1] - 1)
        step = max(1, chunk_tets // max(per_layer, 1))
        for k0 in range(0, dims[2] - 1, step):
            yield _kuhn_tets(dims, k0, min(dims[2] - 1, k0 + step))
        return
    if not has_3d_cells(ds):
        return
    tets = tetra_cells(ds)
    if tets is not None:
        yield tets
    elif (cell_types(ds) == _VTK_POLYHEDRON).any():  # its faces are not sliced by cell
        yield _triangulated(_with_cell_ids(ds), ds)
    else:
        # runs of cells holding about chunk_tets point ids each: a cell gives fewer tets
        # than it has points (a quadratic tet 8 of 10, a hexahedron 5 or 6 of 8), so the
        # triangulation and the arrays made of it stay about a chunk's size
        offsets = ns.vtk_to_numpy(ds.GetCells().GetOffsetsArray())
        n, c0 = ds.GetNumberOfCells(), 0
        while c0 < n:
            c1 = int(np.searchsorted(offsets, offsets[c0] + chunk_tets, side="right")) - 1
            c1 = min(n, max(c1, c0 + 1))
            yield _triangulated(_cell_run(ds, c0, c1), ds)
            c0 = c1


def tetra_cells(ds):
    """The tetra cells of an unstructured grid whose only 3D cells are tetra.

    Parameters
    ----------
    ds : vtkUnstructuredGrid

    Returns
    -------
    tuple or None
        ``(tets, cells)``: the point ids ``(T, 4)`` int64 of the tetra cells and their cell
        ids ``(T,)``, ascending (other cells, of lower dimension, are left out); None where
        another kind of 3D cell is present (:func:`cell_tetrahedra` splits those).
    """
    types = cell_types(ds)
    is_tetra = types == _VTK_TETRA
    if not is_tetra.all() and any(_cell_dimension(t) == 3 for t in np.unique(types[~is_tetra])):
        return None
    conn = ns.vtk_to_numpy(ds.GetCells().GetConnectivityArray()).astype(np.int64, copy=False)
    if is_tetra.all():
        return conn.reshape(-1, 4), np.arange(len(types), dtype=np.int64)
    cells = np.flatnonzero(is_tetra)
    offsets = ns.vtk_to_numpy(ds.GetCells().GetOffsetsArray())
    if len(cells) and cells[-1] - cells[0] == len(cells) - 1:
        # one run of consecutive tets (a mesh stored with its boundary faces before or
        # after them): their points are one block of the connectivity
        start = int(offsets[cells[0]])
        return conn[start : start + 4 * len(cells)].reshape(-1, 4), cells
    return conn[offsets[cells][:, None] + np.arange(4)], cells


def _with_cell_ids(ds):
    """``ds``'s points and cells (no arrays) with each cell's index in ``_ID_ARRAY``.

    What a VTK filter that drops or splits cells hands on, to match its output to them.
    """
    tagged = ds.NewInstance()
    tagged.CopyStructure(ds)
    ids = ns.numpy_to_vtk(np.arange(ds.GetNumberOfCells(), dtype=np.int64), deep=1)
    ids.SetName(_ID_ARRAY)
    tagged.GetCellData().AddArray(ids)
    return tagged


def _cell_run(ds, c0: int, c1: int):
    """The cells ``c0 <= c < c1`` of an unstructured grid (no polyhedra) on all its points.

    Each cell carries its index in ``ds`` in ``_ID_ARRAY``; the points are ``ds``'s own
    (shared, not copied), and only the run's connectivity is copied.
    """
    from vtkmodules.util.vtkConstants import VTK_ID_TYPE
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkUnstructuredGrid

    cells = ds.GetCells()
    offsets = ns.vtk_to_numpy(cells.GetOffsetsArray())
    lo, hi = int(offsets[c0]), int(offsets[c1])
    conn = ns.vtk_to_numpy(cells.GetConnectivityArray())[lo:hi]
    run = vtkCellArray()
    run.SetData(
        ns.numpy_to_vtk(offsets[c0 : c1 + 1].astype(np.int64) - lo, deep=1, array_type=VTK_ID_TYPE),
        ns.numpy_to_vtk(conn.astype(np.int64), deep=1, array_type=VTK_ID_TYPE),
    )
    part = vtkUnstructuredGrid()
    part.SetPoints(ds.GetPoints())
    part.SetCells(ns.numpy_to_vtk(cell_types(ds)[c0:c1].astype(np.uint8), deep=1), run)
    ids = ns.numpy_to_vtk(np.arange(c0, c1, dtype=np.int64), deep=1)
    ids.SetName(_ID_ARRAY)
    part.GetCellData().AddArray(ids)
    return part


def _triangulated(tagged, ds):
    """Tets of the 3D cells of ``tagged`` through ``vtkDataSetTriangleFilter``.

    ``tagged`` holds cells of ``ds`` on ``ds``'s points, each with its index in ``ds`` in
    ``_ID_ARRAY`` (:func:`_with_cell_ids`, :func:`_cell_run`).
    """
    from vtkmodules.vtkFiltersGeneral import vtkDataSetTriangleFilter  # here: slow to import

    tri = vtkDataSetTriangleFilter()
    tri.SetInputData(tagged)
    tri.TetrahedraOnlyOn()
    tri.Update()
    out = tri.GetOutput()
    if out.GetNumberOfCells() == 0:
        return np.zeros((0, 4), np.int64), np.zeros(0, np.int64)
    if out.GetNumberOfPoints() != ds.GetNumberOfPoints() or not np.array_equal(
        numpy_points(out), numpy_points(ds)
    ):
        raise ValueError(
            "VTK's triangulation of these cells adds points; per-cell analysis needs cells "
            "whose tetrahedra use the dataset's own points"
        )
    conn = ns.vtk_to_numpy(out.GetCells().GetConnectivityArray()).astype(np.int64)
    owner = ns.vtk_to_numpy(out.GetCellData().GetArray(_ID_ARRAY)).astype(np.int64)
    return conn.reshape(-1, 4), owner


#: VTK's linear simplices (vertex, line, triangle, tetra): a cell's centre is its points'
#: mean (the image of its parametric centre).
_SIMPLICES = (1, 3, 5, 10)


def cell_centres(ds, cells) -> np.ndarray:
    """Centres of the cells ``cells`` (indices) of a dataset: VTK's cell centres.

    Linear simplices' centres in an unstructured grid are their points' mean, taken from
    the connectivity; other cells' go through VTK's ``vtkCellCenters`` (plain VTK: it runs
    in ParaView's Python, which has no PyVista), matched to their cells by id: it gives
    empty cells no centre, so its output is not in cell order where there are any.

    Returns
    -------
    (K, 3) float64
        NaN for an empty cell.
    """
    cells = np.asarray(cells, dtype=np.int64).reshape(-1)
    if not ds.IsA("vtkUnstructuredGrid") or not np.isin(cell_types(ds)[cells], _SIMPLICES).all():
        from vtkmodules.vtkFiltersCore import vtkCellCenters

        centres = vtkCellCenters()
        centres.SetInputData(_with_cell_ids(ds))
        centres.CopyArraysOn()
        centres.Update()
        got = centres.GetOutput()
        out = np.full((ds.GetNumberOfCells(), 3), np.nan)
        out[ns.vtk_to_numpy(got.GetPointData().GetArray(_ID_ARRAY))] = numpy_points(got)
        return out[cells]
    conn = ns.vtk_to_numpy(ds.GetCells().GetConnectivityArray())
    offsets = ns.vtk_to_numpy(ds.GetCells().GetOffsetsArray())
    points = numpy_points(ds)
    out = np.empty((len(cells), 3))
    sizes = offsets[cells + 1] - offsets[cells]
    for size in np.unique(sizes):
        take = np.flatnonzero(sizes == size)
        ids = conn[offsets[cells[take]][:, None] + np.arange(size)]
        out[take] = points[ids].mean(axis=1)
    return out


def cells_touching(ds, cells, flags) -> np.ndarray:
    """Which of the cells ``cells`` (indices) of a dataset have a flagged point.

    Image and structured cells by their corners' indices, other cells by VTK's
    connectivity (a polyhedron's point ids, not its faces).

    Parameters
    ----------
    ds : vtkDataSet
    cells : (K,) int array_like
    flags : (N,) array_like
        Per point of ``ds``; nonzero flags a point.

    Returns
    -------
    (K,) bool
    """
    cells = np.asarray(cells, dtype=np.int64).reshape(-1)
    flagged = np.asarray(flags).reshape(-1) != 0
    out = np.zeros(cells.size, dtype=bool)
    if not cells.size or not flagged.any():
        return out
    dims = _dimensions(ds)
    if dims is not None and min(dims) >= 2:  # a 3D grid: a cell's corners by its index
        nx, ny, _ = dims
        row, i = np.divmod(cells, nx - 1)
        k, j = np.divmod(row, ny - 1)
        base = i + nx * (j + ny * k)
        for di, dj, dk in itertools.product((0, 1), repeat=3):
            out |= flagged[base + di + nx * (dj + ny * dk)]
        return out
    if ds.IsA("vtkUnstructuredGrid"):
        conn = ns.vtk_to_numpy(ds.GetCells().GetConnectivityArray())
        offsets = ns.vtk_to_numpy(ds.GetCells().GetOffsetsArray())
        sizes = offsets[cells + 1] - offsets[cells]
        for size in np.unique(sizes[sizes > 0]):
            take = np.flatnonzero(sizes == size)
            out[take] = flagged[conn[offsets[cells[take]][:, None] + np.arange(size)]].any(axis=1)
        return out
    ids = vtkIdList()
    for n, c in enumerate(cells):
        ds.GetCellPoints(int(c), ids)
        out[n] = any(flagged[ids.GetId(m)] for m in range(ids.GetNumberOfIds()))
    return out


def cell_quality(ds, deformed_points, *, condition: bool = True) -> dict | None:
    """Per-cell determinant and condition number of a deformation of ``ds``'s 3D cells.

    Parameters
    ----------
    ds : vtkDataSet
        The rest dataset.
    deformed_points : (N, 3) array_like
        Its points after the deformation (same order).
    condition : bool
        Compute the condition numbers too (NaN when False).

    Returns
    -------
    dict or None
        None without 3D cells; else :func:`~vhm_viz.core.metrics.cell_measures`'s arrays
        (one entry per cell of ``ds``) and ``"summary"``
        (:func:`~vhm_viz.core.metrics.cell_summary`).
    """
    if not has_3d_cells(ds):
        return None
    rest = numpy_points(ds)
    moved = np.asarray(deformed_points, dtype=np.float64).reshape(-1, 3)
    dims = _dimensions(ds)
    if dims is not None:  # a lattice: its cells measured where they lie, six tets each
        out = lattice_tetrahedron_measures(rest, moved, dims, condition=condition)
        out["rest_inverted"][:] = False  # the tets are ours: a lattice stores no orientation
    else:
        out = _split_cell_measures(ds, rest, moved, condition)
    out["summary"] = cell_summary(out)
    return out


def _split_cell_measures(ds, rest, moved, condition: bool) -> dict:
    """:func:`cell_quality`'s measures of a mesh's 3D cells, chunk by chunk of their tets."""
    n = ds.GetNumberOfCells()
    det = np.full(n, np.nan)
    cond = np.full(n, np.nan)
    rest_inverted = np.zeros(n, bool)
    degenerate = np.zeros(n, bool)
    for tets, cells in cell_tetrahedra(ds):
        if len(tets) == 0:
            continue
        if np.all(cells[1:] > cells[:-1]):  # a cell per tet (a tet mesh): as they come
            used = cells
            m = cell_measures(rest, moved, tets, condition=condition)
        else:  # renumber the chunk's cells so the work arrays stay the chunk's size
            used, local = np.unique(cells, return_inverse=True)
            m = cell_measures(rest, moved, tets, local, len(used), condition=condition)
        det[used], cond[used] = m["determinant"], m["condition_number"]
        degenerate[used] |= m["degenerate"]
        rest_inverted[used] |= m["rest_inverted"]
    return {
        "determinant": det,
        "condition_number": cond,
        "rest_inverted": rest_inverted,
        "degenerate": degenerate,
    }


def add_cell_arrays(data, quality: dict) -> None:
    """Write :data:`CELL_ARRAYS` (and ``cell_rest_inverted``) into ``data``'s cell data.

    The counts go to the field arrays ``vhm_cells_inverted`` and ``vhm_cells_rest_inverted``
    (one value each), so they travel down a pipeline with the data.
    """
    summary = quality["summary"]
    set_cell_counts(data, summary["inverted"], summary["rest_inverted"])
    cd = data.GetCellData()
    det = quality["determinant"]
    arrays = {
        "cell_jacobian_determinant": det,
        "cell_condition_number": quality["condition_number"],
        "cell_inverted": (det <= 0).astype(np.uint8),  # NaN (no tets) compares False
        "cell_rest_inverted": quality["rest_inverted"].astype(np.uint8),
    }
    for name, values in arrays.items():
        arr = ns.numpy_to_vtk(np.ascontiguousarray(values), deep=1)
        arr.SetName(name)
        cd.RemoveArray(name)
        cd.AddArray(arr)


def set_cell_counts(data, inverted: int, rest_inverted: int) -> None:
    """The field arrays ``vhm_cells_inverted`` and ``vhm_cells_rest_inverted`` of ``data``."""
    set_field_counts(data, "vhm_cells_inverted", [inverted])
    set_field_counts(data, "vhm_cells_rest_inverted", [rest_inverted])


def own_cells(data) -> np.ndarray:
    """Which of ``data``'s cells are its own: (C,) bool.

    Cells that ``vtkGhostType`` marks as duplicates (ghost cells, another piece's own) are
    not.
    """
    ghosts = data.GetCellData().GetArray(vtkDataSetAttributes.GhostArrayName())
    if ghosts is None:
        return np.ones(data.GetNumberOfCells(), dtype=bool)
    return (ns.vtk_to_numpy(ghosts) & vtkDataSetAttributes.DUPLICATECELL) == 0


def own_cell_counts(data) -> np.ndarray:
    """``[inverted, rest_inverted, has the arrays]`` of ``data``'s own cells (float64).

    From the cell arrays ``cell_inverted`` and ``cell_rest_inverted``; cells that
    ``vtkGhostType`` marks as duplicates (ghost cells, another piece's own) are left out.
    """
    cd = data.GetCellData()
    inverted, rest = cd.GetArray("cell_inverted"), cd.GetArray("cell_rest_inverted")
    if inverted is None or rest is None:
        return np.zeros(3)
    own = own_cells(data)
    return np.array([np.count_nonzero(ns.vtk_to_numpy(inverted)[own]),
                     np.count_nonzero(ns.vtk_to_numpy(rest)[own]), 1.0])  # fmt: skip


def region_of(ds, cage=None):
    """The region of a dataset to certify (:class:`vhm_viz.core.certify.Region`).

    * image, rectilinear and structured data: the box of their points;
    * meshes with 3D cells: their tetrahedra (:func:`cell_tetrahedra`);
    * closed surfaces: the solid they bound (exact signed distances near the surface,
      the generalised winding number elsewhere);
    * anything else (point clouds, open surfaces): the cage's interior farther than
      :func:`~vhm_viz.core.certify.default_margin` from the cage (needs ``cage``).

    Parameters
    ----------
    ds : vtkDataSet or pyvista.DataSet
    cage : Cage, optional

    Returns
    -------
    Region
    """
    import pyvista as pv  # only here: ParaView's Python may lack PyVista

    ds = pv.wrap(ds)
    if _dimensions(ds) is not None:
        b = np.asarray(ds.bounds, dtype=np.float64)
        return Region.box(b[0::2], b[1::2])
    if has_3d_cells(ds):
        tets = [t for t, _ in cell_tetrahedra(ds)]
        return Region.tetrahedra(numpy_points(ds), np.concatenate(tets))
    if isinstance(ds, pv.PolyData) and ds.n_cells and ds.GetNumberOfPolys():
        surf = ds.triangulate() if not ds.is_all_triangles else ds
        if open_edge_count(np.asarray(surf.faces).reshape(-1, 4)[:, 1:], surf.n_points) == 0:
            return _solid_region(surf)
    if cage is None:
        raise ValueError(
            "this dataset bounds no solid (a point cloud or an open surface): certify the "
            "cage's interior instead (pass the cage)"
        )
    return Region.cage_interior(cage, default_margin(cage))


def _solid_region(surface):
    """The solid a closed, consistently oriented triangle surface bounds.

    Cubes near the surface are classified by exact signed distances (angle-weighted
    pseudo-normals, :mod:`vhm_viz.autocage.proximity`); the few first-level cubes far
    from it, and witnesses, by the surface's generalised winding number. Children of a
    cube that straddles the surface lie within four of their radii of it, so the exact
    distance covers every later test.
    """
    # imported here: of the filters, only a closed surface's region needs vhm_viz.autocage
    from vhm_viz.autocage.proximity import NearDistance, grid_signed_distance

    v = np.ascontiguousarray(surface.points, dtype=np.float64)
    f = np.ascontiguousarray(np.asarray(surface.faces).reshape(-1, 4)[:, 1:], dtype=np.int64)
    if signed_volume(v, f) < 0:
        f = f[:, ::-1]  # inward-oriented: the signs below assume outward normals
    near = NearDistance(v, f)

    def inside(points):
        return inside_cage(winding_number(points, v, f))

    def test(centres, e):
        r = float(np.linalg.norm(e))
        sd, _ = grid_signed_distance(near, centres, 4.0 * r)
        state = np.full(len(centres), MEETS, dtype=np.int8)
        state[sd < -r] = INSIDE
        state[np.isfinite(sd) & (sd > r)] = OUTSIDE
        far = ~np.isfinite(sd)
        if far.any():
            state[far] = np.where(inside(centres[far]), INSIDE, OUTSIDE)
        return state

    b = np.asarray(surface.bounds, dtype=np.float64)
    return Region("solid", b[0::2], b[1::2], test, inside, {"triangles": int(len(f))})
