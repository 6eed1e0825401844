"""Per-cell quality of deformed tet meshes (and cells split into tets) against brute force.

References: signed tet volumes of the deformed vertex positions (an inverted cell is one
whose deformed volume changed sign), the edge equations ``F (x_i - x_0) = y_i - y_0``, and
affine maps (every cell gets ``det A`` and ``cond A``).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage, data_path

pv = pytest.importorskip("pyvista")

from vhm_viz import examples  # noqa: E402
from vhm_viz.core.cage import Cage  # noqa: E402
from vhm_viz.core.certify import Region, certify_injectivity  # noqa: E402
from vhm_viz.core.harmonic_map import HarmonicMap  # noqa: E402
from vhm_viz.core.metrics import cell_measures, cell_summary, tetrahedron_gradients  # noqa: E402
from vhm_viz.filters import (  # noqa: E402
    HarmonicDeformationFilter,
    JacobianAnalysisFilter,
    cell_quality,
    update,
)
from vhm_viz.filters.cells import cell_centres, cell_tetrahedra  # noqa: E402


def _signed_volumes(points, tets):
    x = np.asarray(points, dtype=np.float64)[tets]
    return np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]))


def _tet_grid(points, tets):
    cells = np.hstack([np.full((len(tets), 1), 4), tets]).ravel()
    return pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA), points)


def _analyse(data, deformation):
    f = JacobianAnalysisFilter()
    f.SetInputData(data)
    f.SetDeformation(deformation)
    f.SetOutsidePolicy("passthrough")
    return pv.wrap(update(f)), f.cell_summary


@pytest.fixture(scope="module")
def bar_tets():
    return examples.bar_tets(10)


def _solved(kind, **kw):
    sc = examples.bar(kind, **kw)
    sc.solve()
    return sc.deformer


# ------------------------------------------------------------------------- core
def test_gradients_map_rest_edges_onto_deformed_edges():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3))
    y = x @ rng.normal(size=(3, 3)).T + 0.1 * rng.normal(size=x.shape)
    tets = np.array([rng.choice(40, 4, replace=False) for _ in range(30)])
    grads, rest_det = tetrahedron_gradients(x, y, tets)
    for k, t in enumerate(tets):
        assert np.allclose(grads[k] @ (x[t[1:]] - x[t[0]]).T, (y[t[1:]] - y[t[0]]).T)
    ratio = _signed_volumes(y, tets) / _signed_volumes(x, tets)
    assert np.allclose(np.linalg.det(grads), ratio)
    assert np.allclose(rest_det, _signed_volumes(x, tets))


def test_vertex_order_does_not_blame_the_deformation():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    y = x * [2.0, 1.0, 1.0]
    upright, flipped = np.array([[0, 1, 2, 3]]), np.array([[0, 2, 1, 3]])
    a = cell_measures(x, y, upright)
    b = cell_measures(x, y, flipped)
    assert np.allclose(a["determinant"], 2.0) and np.allclose(b["determinant"], 2.0)
    assert not a["rest_inverted"][0] and b["rest_inverted"][0]
    s = cell_summary(b)
    assert s["inverted"] == 0 and s["rest_inverted"] == 1


def test_cells_take_the_worst_of_their_tets_and_flat_tets_are_degenerate():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0], [1, 1, 1.0], [2, 0, 0]])
    y = x.copy()
    y[4] = [0.1, 0.1, 0.1]  # pushes the second tet through its base
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [0, 1, 5, 2]])  # the last one is flat
    m = cell_measures(x, y, tets, cells=[0, 0, 1], n_cells=3)
    assert m["determinant"][0] < 0 and np.isnan(m["determinant"][1:]).all()
    assert m["degenerate"].tolist() == [False, True, False]
    s = cell_summary(m)
    assert s == {**s, "cells": 1, "inverted": 1, "degenerate": 1, "rest_inverted": 0}


def test_a_cell_per_tet_and_cells_beyond_them():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0], [1, 1, 1.0]])
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    m = cell_measures(x, 2.0 * x, tets, n_cells=4)  # cells 2 and 3 have no tet
    np.testing.assert_allclose(m["determinant"][:2], 8.0)
    assert np.isnan(m["determinant"][2:]).all()
    with pytest.raises(ValueError, match="cell ids"):
        cell_measures(x, x, tets, n_cells=1)


# ------------------------------------------------------------------------- against brute force
@pytest.mark.parametrize(
    ("kind", "height", "folds"), [("push", 2.5, True), ("bend-u", None, False)]
)
def test_inverted_cells_equal_brute_force_signed_volumes(bar_tets, kind, height, folds):
    points, tets = bar_tets
    dfm = _solved(kind, top_height=height) if height else _solved(kind)
    out, summary = _analyse(_tet_grid(points, tets), dfm)
    moved = dfm.harmonic_map.map(points)
    brute = np.count_nonzero(_signed_volumes(moved, tets) <= 0)  # all rest tets are positive
    assert summary["inverted"] == brute
    assert (brute > 50) if folds else (brute == 0)  # the push folds many tets, bend-u none
    inverted = np.asarray(out.cell_data["cell_inverted"], bool)
    assert np.array_equal(np.nonzero(inverted)[0], np.nonzero(_signed_volumes(moved, tets) <= 0)[0])
    ratio = _signed_volumes(moved, tets) / _signed_volumes(points, tets)
    assert np.allclose(out.cell_data["cell_jacobian_determinant"], ratio, rtol=1e-9, atol=1e-12)
    assert summary["det_min"] == pytest.approx(ratio.min())
    assert summary["cond_max"] >= 1.0


def test_subtle_fold_inverts_no_tet_but_the_certificate_sees_it(bar_tets):
    points, tets = bar_tets
    dfm = _solved("push", top_height=3.582)
    moved = dfm.harmonic_map.map(points)
    assert np.all(_signed_volumes(moved, tets) > 0)  # every tet comes back upright
    _, summary = _analyse(_tet_grid(points, tets), dfm)
    assert summary["inverted"] == 0
    cert = certify_injectivity(dfm, Region.tetrahedra(points, tets))
    assert cert.status == "not injective"
    assert np.all(np.linalg.det(dfm.harmonic_map.jacobian(cert.witnesses)) <= 0)


def test_rest_inverted_cells_are_reported_not_blamed():
    mesh = pv.read(data_path("tets", "tetraMesh_inverted.vtk"))
    points = np.asarray(mesh.points, dtype=np.float64)
    tets = np.asarray(mesh.cells_dict[pv.CellType.TETRA])
    lo, hi = points.min(0) - 1.0, points.max(0) + 1.0
    cage = Cage(*box_cage(lo, hi, 2))
    stored_inverted = np.count_nonzero(_signed_volumes(points, tets) < 0)
    assert stored_inverted == 80  # the data's README: 80 of 160
    out, summary = _analyse(mesh, HarmonicMap.identity(cage))
    assert summary["rest_inverted"] == stored_inverted
    assert summary["inverted"] == 0  # the identity inverts nothing
    assert np.asarray(out.cell_data["cell_rest_inverted"]).sum() == stored_inverted
    # a reflection inverts every cell, stored inverted or not
    _, summary = _analyse(mesh, HarmonicMap.affine(cage, np.diag([1.0, 1.0, -1.0])))
    assert summary["inverted"] == 160 and summary["rest_inverted"] == 80


def test_volumes_and_hexahedra_under_an_affine_map():
    cage = Cage(*box_cage((-1, -1, -1), (2, 2, 2), 2))
    a = np.array([[1.1, 0.2, 0.0], [0.0, 0.8, 0.3], [0.1, 0.0, 1.2]])
    hm = HarmonicMap.affine(cage, a, [0.3, 0.0, -0.2])
    img = pv.ImageData(dimensions=(5, 4, 6), spacing=(0.2, 0.25, 0.15))
    cond = np.linalg.cond(a)
    for data in (img, img.cast_to_unstructured_grid(), img.cast_to_structured_grid()):
        out, summary = _analyse(data, hm)
        assert out.n_cells == img.n_cells
        assert np.allclose(out.cell_data["cell_jacobian_determinant"], np.linalg.det(a))
        assert np.allclose(out.cell_data["cell_condition_number"], cond)
        assert summary["inverted"] == 0 and summary["rest_inverted"] == 0


def test_cells_without_volume_get_nan():
    grid = pv.UnstructuredGrid(
        np.array([4, 0, 1, 2, 3, 3, 0, 1, 2]),
        np.array([pv.CellType.TETRA, pv.CellType.TRIANGLE]),
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
    )
    q = cell_quality(grid, np.asarray(grid.points) * 2.0)
    assert q["determinant"][0] == pytest.approx(8.0) and np.isnan(q["determinant"][1])
    assert q["summary"]["cells"] == 1
    assert cell_quality(pv.Sphere(), pv.Sphere().points) is None


@pytest.mark.parametrize("arrangement", ["interleaved", "tets first", "tets last"])
def test_tets_beside_surface_cells_are_measured_as_stored(bar_tets, arrangement):
    # a tet mesh with its boundary triangles and a vertex cell (as medit and Gmsh files
    # come, the tets in one run, or the kinds interleaved): the tets are taken as stored,
    # the others get NaN; with a hexahedron too, every cell goes through VTK's
    # triangulation, and the tets' numbers are the same
    points, tets = bar_tets
    rng = np.random.default_rng(4)
    moved = points + 0.08 * rng.normal(size=points.shape)
    tris = tets[::5, :3]
    cells = [np.hstack([np.full((len(tets), 1), 4), tets]).ravel()]
    cells.append(np.hstack([np.full((len(tris), 1), 3), tris]).ravel())
    cells.append(np.array([1, 7]))
    types = [pv.CellType.TETRA] * len(tets) + [pv.CellType.TRIANGLE] * len(tris)
    types += [pv.CellType.VERTEX]
    order = {
        "interleaved": rng.permutation(len(types)),
        "tets first": np.arange(len(types)),
        "tets last": np.roll(np.arange(len(types)), -len(tets)),
    }[arrangement]
    starts = np.cumsum([0] + [5] * len(tets) + [4] * len(tris) + [2])[:-1]
    flat = np.concatenate(cells)
    lengths = np.array([5] * len(tets) + [4] * len(tris) + [2])
    grid = pv.UnstructuredGrid(
        np.concatenate([flat[starts[i] : starts[i] + lengths[i]] for i in order]),
        np.asarray(types)[order],
        points,
    )
    q = cell_quality(grid, moved)
    is_tet = np.asarray(grid.celltypes) == pv.CellType.TETRA
    stored = grid.cells_dict[pv.CellType.TETRA]
    ratio = _signed_volumes(moved, stored) / _signed_volumes(points, stored)
    np.testing.assert_allclose(q["determinant"][is_tet], ratio, rtol=1e-9)
    assert np.isnan(q["determinant"][~is_tet]).all()
    assert q["summary"]["cells"] == len(tets) and q["summary"]["inverted"] == (ratio <= 0).sum()
    hexa = pv.UnstructuredGrid(
        np.array([8, *range(len(points), len(points) + 8)]),
        np.array([pv.CellType.HEXAHEDRON]),
        np.vstack([points, pv.Box(bounds=(5, 6, 5, 6, 5, 6)).points[:8]]),
    )
    mixed = grid.merge(hexa, merge_points=False)
    assert mixed.n_cells == grid.n_cells + 1
    q2 = cell_quality(mixed, np.vstack([moved, mixed.points[len(points) :]]))
    # VTK may store a tet from another corner: the same det F, to rounding of |F|^3
    np.testing.assert_allclose(q2["determinant"][: grid.n_cells], q["determinant"], atol=1e-12)
    assert q2["determinant"][-1] == pytest.approx(1.0)


def _quadratic_tets(points, tets):
    """The tets as quadratic tets (VTK's edge order), each mid-edge point at its midpoint."""
    edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]
    pairs = np.concatenate([np.sort(tets[:, e], axis=1) for e in edges])
    unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
    mid = len(points) + inverse.reshape(len(edges), -1).T
    return pv.UnstructuredGrid(
        {pv.CellType.QUADRATIC_TETRA: np.hstack([tets, mid])},
        np.vstack([points, points[unique].mean(axis=1)]),
    )


def test_cells_split_into_tets_come_in_chunks_of_whole_cells(bar_tets):
    # quadratic tets go through VTK's triangulation (8 tets each, filling the cell): run
    # by run of cells, so that neither the triangulation nor the arrays made of it grow
    # with the mesh; the chunks' tets still fill every cell, each cell in one chunk
    points, tets = bar_tets
    grid = _quadratic_tets(points, tets)
    chunks = list(cell_tetrahedra(grid, chunk_tets=20_000))
    assert len(chunks) > 1 and max(len(t) for t, _ in chunks) <= 20_000
    owners = [cells for _, cells in chunks]
    assert all(a.max() < b.min() for a, b in zip(owners, owners[1:], strict=False))
    split, owner = np.concatenate([t for t, _ in chunks]), np.concatenate(owners)
    filled = np.bincount(owner, np.abs(_signed_volumes(grid.points, split)), len(tets))
    np.testing.assert_allclose(filled, np.abs(_signed_volumes(points, tets)), rtol=1e-9)
    # and the per-cell measures over the chunks: an affine map gives every cell det A
    a = np.array([[1.1, 0.2, 0.0], [0.0, 0.8, 0.3], [0.1, 0.0, -1.2]])
    q = cell_quality(grid, np.asarray(grid.points) @ a.T)
    np.testing.assert_allclose(q["determinant"], np.linalg.det(a), rtol=1e-9)
    assert q["summary"]["inverted"] == len(tets)


def test_cell_centres_are_vtks(bar_tets):
    points, tets = bar_tets
    grid = _tet_grid(points, tets)
    mixed = grid.merge(pv.PolyData(points[:40], np.array([3, 0, 1, 2, 3, 5, 6, 7, 1, 9])))
    hexa = mixed.merge(pv.ImageData(dimensions=(2, 2, 2), origin=(4, 4, 4)))
    for ds, index in (
        (grid, np.arange(0, grid.n_cells, 7)),
        (mixed, np.arange(mixed.n_cells - 5, mixed.n_cells)),  # tets, triangles, a vertex
        (hexa, np.array([3, hexa.n_cells - 1])),  # with a hexahedron: VTK's
        (pv.ImageData(dimensions=(4, 3, 5)).cast_to_structured_grid(), np.array([0, 5, 23])),
    ):
        expected = np.asarray(ds.extract_cells(index).cell_centers().points)
        np.testing.assert_allclose(cell_centres(ds, index), expected, rtol=1e-6, atol=1e-6)


def test_cells_touching_flagged_points_are_vtks_cell_points(bar_tets):
    """Which cells have a flagged point: as each cell's point ids from VTK's
    ``GetCellPoints`` say, for tet and mixed meshes (a hexahedron, triangles, a vertex),
    images and structured grids."""
    from vtkmodules.vtkCommonCore import vtkIdList

    from vhm_viz.filters.cells import cells_touching

    points, tets = bar_tets
    grid = _tet_grid(points, tets)
    mixed = grid.merge(pv.PolyData(points[:40], np.array([3, 0, 1, 2, 3, 5, 6, 7, 1, 9])))
    mixed = mixed.merge(pv.ImageData(dimensions=(2, 2, 2), origin=(4, 4, 4)))
    image = pv.ImageData(dimensions=(5, 4, 6), origin=(1, 2, 3), spacing=(0.5, 1, 2))
    rng = np.random.default_rng(3)
    for ds in (grid, mixed, image, image.cast_to_structured_grid()):
        flags = (rng.random(ds.n_points) < 0.05).astype(np.uint8)
        cells = rng.permutation(ds.n_cells)[: ds.n_cells // 2]
        expected = []
        for c in cells:
            ids = vtkIdList()
            ds.GetCellPoints(int(c), ids)
            expected.append(any(flags[ids.GetId(k)] for k in range(ids.GetNumberOfIds())))
        got = cells_touching(ds, cells, flags)
        assert got.dtype == bool and 0 < got.sum() < got.size
        np.testing.assert_array_equal(got, expected)
        assert not cells_touching(ds, cells, np.zeros(ds.n_points)).any()


def test_cell_centres_and_fold_positions_skip_empty_cells(tmp_path):
    """Empty cells (which VTK's vtkCellCenters gives no centre) leave every other cell its
    own centre: a voxel mesh with empty cells among its voxels has the centres that the
    same voxels have without them, and the warp's fold check says the same cells, worst
    cell and box with them as without."""
    import warnings

    from conftest import write_folding_volume
    from vtkmodules.vtkCommonCore import vtkIdList
    from vtkmodules.vtkCommonDataModel import vtkUnstructuredGrid

    write_folding_volume(tmp_path)
    voxels = pv.read(tmp_path / "image.vti").cast_to_unstructured_grid()
    with_empty = vtkUnstructuredGrid()
    with_empty.SetPoints(voxels.GetPoints())
    with_empty.Allocate()
    own = []  # with_empty's id of each voxel
    for c in range(voxels.n_cells):
        if c in (0, voxels.n_cells // 2):
            with_empty.InsertNextCell(0, vtkIdList())  # VTK_EMPTY_CELL
        ids = vtkIdList()
        voxels.GetCellPoints(c, ids)
        own.append(with_empty.InsertNextCell(voxels.GetCellType(c), ids))
    own = np.asarray(own)
    expected = np.asarray(voxels.cell_centers().points)
    np.testing.assert_allclose(cell_centres(with_empty, own), expected, atol=1e-12)
    assert np.isnan(cell_centres(with_empty, [0])).all()
    folds = []
    for mesh in (voxels, with_empty):
        f = HarmonicDeformationFilter()
        f.SetInputData(mesh)
        f.SetScene(str(tmp_path / "scene.json"))
        f.SetCheckFolds(True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            update(f)
        folds.append(f.fold_cells)
    assert folds[0]["count"] > 1
    assert (folds[1]["count"], folds[1]["cells"]) == (folds[0]["count"], folds[0]["cells"])
    for key in ("worst", "at", "lo", "hi"):
        np.testing.assert_allclose(folds[1][key], folds[0][key], atol=1e-12)


def test_deformation_filter_writes_the_same_cell_arrays(bar_tets):
    points, tets = bar_tets
    dfm = _solved("push", top_height=2.5)
    grid = _tet_grid(points, tets)
    analysed, summary = _analyse(grid, dfm)
    f = HarmonicDeformationFilter()
    f.SetInputData(grid)
    f.SetDeformer(dfm)
    f.SetComputeCellQuality(True)
    bent = pv.wrap(update(f))
    for name in ("cell_jacobian_determinant", "cell_condition_number", "cell_inverted"):
        assert np.allclose(bent.cell_data[name], analysed.cell_data[name])
    assert f.cell_summary == summary


def test_accessor_analyze_and_certify(bar_tets):
    import vhm_viz
    import vhm_viz.accessor  # noqa: F401 -- registers mesh.vhm

    points, tets = bar_tets
    grid = _tet_grid(points, tets)
    dfm = _solved("push", top_height=2.5)
    out = grid.vhm.analyze(dfm)
    inverted = int(np.count_nonzero(_signed_volumes(dfm.harmonic_map.map(points), tets) <= 0))
    assert int(np.asarray(out.cell_data["cell_inverted"]).sum()) == inverted
    assert int(out.field_data["vhm_cells_inverted"][0]) == inverted
    assert int(out.field_data["vhm_cells_rest_inverted"][0]) == 0
    cert = grid.vhm.certify(dfm)
    assert cert.status == "not injective" and cert.region["kind"] == "tetrahedra"
    # the same through the top-level API, and a dataset is refused by the core with advice
    again = vhm_viz.certify_injectivity(dfm, vhm_viz.region_of(grid))
    assert np.array_equal(again.witnesses, cert.witnesses)
    with pytest.raises(TypeError, match="region_of"):
        vhm_viz.certify_injectivity(dfm, grid)


def test_region_of_each_kind_of_dataset():
    from vhm_viz.core.certify import INSIDE, OUTSIDE
    from vhm_viz.filters import region_of

    bar = examples.bar("bend-u", resolution=8)
    lo, hi = np.array([-0.5, -0.5, 0.0]), np.array([0.5, 0.5, 5.0])
    rng = np.random.default_rng(3)
    q = rng.uniform(lo - 0.2, hi + 0.2, (3000, 3))
    truth = np.all((q >= lo) & (q <= hi), axis=1)
    # a closed surface: its solid, exactly
    solid = region_of(bar.surface)
    assert solid.kind == "solid" and np.array_equal(solid.contains(q), truth)
    half = np.full(3, 0.06)
    state = solid.classify(q, half)
    meets = np.all((q + half >= lo) & (q - half <= hi), axis=1)
    within = np.all((q - half >= lo) & (q + half <= hi), axis=1)
    assert not np.any(meets & (state == OUTSIDE)) and not np.any(~within & (state == INSIDE))
    assert (state == INSIDE).any() and (state == OUTSIDE).any()
    # a volume: the box of its points; a point cloud: the cage's interior
    img = pv.ImageData(dimensions=(3, 3, 6), spacing=(0.5, 0.5, 1.0), origin=(-0.5, -0.5, 0))
    box = region_of(img)
    assert box.kind == "box" and np.allclose(box.lo, lo) and np.allclose(box.hi, hi)
    cloud = region_of(pv.PolyData(bar.points[::50]), bar.cage)
    assert cloud.kind == "cage" and cloud.description["margin"] > 0
    with pytest.raises(ValueError, match="cage"):
        region_of(pv.PolyData(bar.points[::50]))
    # a tet mesh: its tetrahedra
    points, tets = examples.bar_tets(3)
    tet_region = region_of(_tet_grid(points, tets))
    assert tet_region.kind == "tetrahedra" and np.array_equal(tet_region.contains(q), truth)
