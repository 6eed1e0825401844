"""VTK filters: deformation per input type, caching, pieces, resampling, analysis."""

from __future__ import annotations

import re

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
vtk = pytest.importorskip("vtkmodules.vtkCommonDataModel")

from conftest import (  # noqa: E402
    affine_resampled,
    box_cage,
    data_path,
    extent_box,
    fd_jacobian,
    trilinear_corner_dets,
    write_folding_volume,
)
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase  # noqa: E402
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline  # noqa: E402
from vtkmodules.vtkImagingCore import vtkRTAnalyticSource  # noqa: E402

from vhm_viz import Cage, HarmonicMap  # noqa: E402
from vhm_viz.core.deformer import Deformer  # noqa: E402
from vhm_viz.core.errors import OutsideCageError  # noqa: E402
from vhm_viz.core.metrics import jacobian_measures  # noqa: E402
from vhm_viz.filters import (  # noqa: E402
    HarmonicDeformationFilter,
    HarmonicResampleFilter,
    JacobianAnalysisFilter,
    output_type_for,
    update,
)
from vhm_viz.filters.mpi import (  # noqa: E402
    DEAL_RUN,
    balanced_shares,
    dealing_order,
    pack_part,
    unpack_part,
)
from vhm_viz.io import cage_to_polydata  # noqa: E402
from vhm_viz.scene import Scene  # noqa: E402

SDDP = vtkStreamingDemandDrivenPipeline


def _cage_around(bounds, margin=0.15, divisions=2):
    lo = np.asarray(bounds[0::2], float)
    hi = np.asarray(bounds[1::2], float)
    pad = margin * (hi - lo).max()
    v, f = box_cage(lo - pad, hi + pad, divisions)
    return Cage(v, f)


def _random_map(cage, scale=0.04, seed=0):
    rng = np.random.default_rng(seed)
    z = np.array(HarmonicMap.identity(cage).coefficients)
    z += scale * cage.diagonal * rng.standard_normal(z.shape)
    return HarmonicMap(cage, z)


def _expected_normals(jac, n):
    # independent formula: cof(J) n = det(J) J^{-T} n
    m = np.linalg.det(jac)[:, None] * np.einsum("kji,kj->ki", np.linalg.inv(jac), n)
    return m / np.linalg.norm(m, axis=1, keepdims=True)


def _reference_measures(jac):
    """det, s_max / s_min and the polar rotation's angle (degrees), by scipy, per Jacobian."""
    from scipy.linalg import polar
    from scipy.spatial.transform import Rotation

    det = np.linalg.det(jac)
    sv = np.linalg.svd(jac, compute_uv=False)
    angle = np.array([Rotation.from_matrix(polar(j)[0]).magnitude() for j in jac])
    return det, sv[:, 0] / sv[:, 2], np.degrees(angle)


def _datasets():
    sphere = pv.Sphere(radius=0.5, theta_resolution=24, phi_resolution=16)
    cloud = pv.PolyData(np.random.default_rng(3).uniform(-0.4, 0.4, (500, 3)))
    normals = np.random.default_rng(4).standard_normal((500, 3))
    cloud.point_data["Normals"] = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    img = pv.ImageData(dimensions=(7, 6, 5), spacing=(0.15, 0.17, 0.2), origin=(-0.45, -0.4, -0.4))
    rect = pv.RectilinearGrid(
        np.array([-0.4, -0.3, 0.0, 0.25, 0.4]),
        np.linspace(-0.4, 0.4, 6),
        np.array([-0.35, 0.1, 0.3]),
    )
    sgrid = img.cast_to_structured_grid()
    sgrid.points = sgrid.points + 0.01 * np.sin(7 * sgrid.points)
    tets = pv.ImageData(dimensions=(4, 4, 4), spacing=(0.25,) * 3, origin=(-0.4,) * 3)
    tets = tets.cast_to_unstructured_grid().triangulate()
    return {
        "polydata": (sphere, "vtkPolyData"),
        "point_cloud": (cloud, "vtkPolyData"),
        "image": (img, "vtkStructuredGrid"),
        "rectilinear": (rect, "vtkStructuredGrid"),
        "structured": (sgrid, "vtkStructuredGrid"),
        "tets": (tets, "vtkUnstructuredGrid"),
    }


@pytest.mark.parametrize("kind", list(_datasets()))
def test_filter_matches_harmonic_map(kind):
    mesh, out_type = _datasets()[kind]
    mesh = mesh.copy()
    mesh.point_data["pid"] = np.arange(mesh.n_points, dtype=np.int32)
    mesh.cell_data["cid"] = np.arange(mesh.n_cells, dtype=np.float32) if mesh.n_cells else []
    cage = _cage_around(mesh.bounds)
    hm = _random_map(cage)
    flt = HarmonicDeformationFilter()
    flt.SetInputData(mesh)
    flt.SetHarmonicMap(hm)
    flt.SetComputeDisplacement(True)
    flt.SetComputeJacobianDeterminant(True)
    flt.SetComputeConditionNumber(True)
    out = update(flt)
    assert out.GetClassName() == out_type == output_type_for(mesh.GetClassName())
    out = pv.wrap(out)
    rest = np.asarray(mesh.points)
    f, jac, _ = hm.evaluate(rest, order=1)
    np.testing.assert_allclose(out.points, f, atol=1e-12)
    np.testing.assert_array_equal(out.point_data["pid"], mesh.point_data["pid"])
    if mesh.n_cells:
        np.testing.assert_array_equal(out.cell_data["cid"], mesh.cell_data["cid"])
        assert out.n_cells == mesh.n_cells
    np.testing.assert_allclose(out.point_data["displacement"], f - rest, atol=1e-12)
    np.testing.assert_allclose(
        out.point_data["jacobian_determinant"], np.linalg.det(jac), rtol=1e-10
    )
    sv = np.linalg.svd(jac, compute_uv=False)
    np.testing.assert_allclose(out.point_data["condition_number"], sv[:, 0] / sv[:, 2], rtol=1e-10)
    if "Normals" in mesh.point_data:
        n = np.asarray(mesh.point_data["Normals"])
        got = np.asarray(out.point_data["Normals"])
        np.testing.assert_allclose(got, _expected_normals(jac, n), atol=1e-10)
        assert not np.allclose(got, n, atol=1e-3)  # deformed, not copied
    assert flt.outside_count == 0
    # the input is untouched
    np.testing.assert_array_equal(mesh.points, rest)


@pytest.mark.parametrize("kind", list(_datasets()))
def test_filter_reproduces_an_affine_map_exactly(kind):
    """Green coordinates reproduce affine maps: the filter output is ``A p + T`` itself."""
    from scipy.spatial.transform import Rotation

    mesh, _ = _datasets()[kind]
    cage = _cage_around(mesh.bounds)
    A = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix() @ np.diag([1.3, 0.8, 1.1])
    T = np.array([0.25, -0.1, 0.4])
    flt = _filter(mesh, HarmonicMap.affine(cage, A, T))
    flt.SetComputeDisplacement(True)
    flt.SetComputeJacobianDeterminant(True)
    flt.SetComputeConditionNumber(True)
    out = pv.wrap(update(flt))
    rest = np.asarray(mesh.points)
    np.testing.assert_allclose(out.points, rest @ A.T + T, rtol=0, atol=1e-10)
    np.testing.assert_allclose(out.point_data["displacement"], rest @ A.T + T - rest, atol=1e-10)
    np.testing.assert_allclose(out.point_data["jacobian_determinant"], 1.3 * 0.8 * 1.1, rtol=1e-9)
    np.testing.assert_allclose(out.point_data["condition_number"], 1.3 / 0.8, rtol=1e-9)
    if "Normals" in mesh.point_data:
        n = np.asarray(mesh.point_data["Normals"])
        m = n @ np.linalg.inv(A)  # cof(A) n is parallel to A^-T n
        m /= np.linalg.norm(m, axis=1, keepdims=True)
        np.testing.assert_allclose(out.point_data["Normals"], m, atol=1e-10)


@pytest.mark.parametrize("kind", ["image", "rectilinear", "structured", "tets"])
def test_cell_quality_of_every_dataset_with_3d_cells(kind):
    """SetComputeCellQuality adds the deformed cells' arrays for every input with 3D cells,
    images (warped through the volume engine) included: under an affine map each cell's
    determinant and condition number are A's, and a reflection inverts every cell."""
    mesh, _ = _datasets()[kind]
    cage = _cage_around(mesh.bounds)
    for A in (np.diag([1.3, 0.8, 1.1]), np.diag([1.0, 1.0, -1.0])):
        flt = _filter(mesh, HarmonicMap.affine(cage, A, np.zeros(3)))
        flt.SetComputeCellQuality(True)
        out = pv.wrap(update(flt))
        assert out.n_cells == mesh.n_cells > 0
        det = np.linalg.det(A)
        np.testing.assert_allclose(out.cell_data["cell_jacobian_determinant"], det, rtol=1e-9)
        np.testing.assert_allclose(out.cell_data["cell_condition_number"], 1.3 / 0.8 if det > 0
                                   else 1.0, rtol=1e-9)  # fmt: skip
        inverted = mesh.n_cells if det < 0 else 0
        assert np.count_nonzero(out.cell_data["cell_inverted"]) == inverted
        assert out.field_data["vhm_cells_inverted"][0] == inverted
        assert flt.cell_summary["inverted"] == inverted


def test_numpy_points_are_vtks_points_on_every_lattice_kind():
    import runpy
    from pathlib import Path

    script = Path(__file__).parent / "paraview" / "points_check.py"
    assert runpy.run_path(str(script))["check"]() == "points ok"


def test_filter_on_hand_tets():
    path = data_path("hand_tet", "hand.mesh")
    mesh = pv.read(path)
    mesh.point_data["pid"] = np.arange(mesh.n_points)
    cage = _cage_around(mesh.bounds, margin=0.05)
    hm = _random_map(cage, scale=0.02, seed=1)
    out = pv.wrap(update(_filter(mesh, hm)))
    assert isinstance(out, pv.UnstructuredGrid)
    assert out.n_cells == mesh.n_cells
    np.testing.assert_array_equal(np.asarray(out.celltypes), np.asarray(mesh.celltypes))
    np.testing.assert_allclose(out.points, hm.map(mesh.points), atol=1e-12)
    np.testing.assert_array_equal(out.point_data["pid"], mesh.point_data["pid"])


def _filter(mesh, deformation, outside="error"):
    flt = HarmonicDeformationFilter()
    flt.SetInputData(mesh)
    flt.SetDeformation(deformation)
    flt.SetOutsidePolicy(outside)
    return flt


def test_cell_normals_are_deformed():
    mesh = pv.Sphere(radius=0.5).compute_normals(cell_normals=True, point_normals=False)
    cage = _cage_around(mesh.bounds)
    hm = _random_map(cage)
    out = pv.wrap(update(_filter(mesh, hm)))
    centres = np.asarray(mesh.cell_centers().points)
    jac = hm.jacobian(centres)
    expected = _expected_normals(jac, np.asarray(mesh.cell_data["Normals"]))
    np.testing.assert_allclose(out.cell_data["Normals"], expected, atol=1e-10)


# ------------------------------------------------------------------ outside the cage


def _sphere_in_small_box():
    """A sphere partly outside an axis-aligned box cage, and which points are inside,
    decided by the box's own inequalities (no winding number)."""
    mesh = pv.Sphere(radius=0.5)
    half = 0.42
    cage = _cage_around((-half, half, -half, half, -half, half), margin=0.0, divisions=1)
    p = np.asarray(mesh.points)
    assert np.abs(np.abs(p) - half).min() > 1e-6  # no point on the box
    inside = (np.abs(p) < half).all(axis=1)
    assert 0 < inside.sum() < mesh.n_points
    return mesh, _random_map(cage), inside


def test_outside_points_error_and_passthrough():
    mesh, hm, inside = _sphere_in_small_box()
    flt = _filter(mesh, hm)
    with pytest.raises(OutsideCageError) as err:
        update(flt)
    np.testing.assert_array_equal(np.sort(err.value.indices), np.nonzero(~inside)[0])
    flt.SetOutsidePolicy("passthrough")
    out = pv.wrap(update(flt))
    assert flt.outside_count == int((~inside).sum())
    np.testing.assert_array_equal(out.point_data["vhm_outside"], (~inside).astype(np.uint8))
    np.testing.assert_array_equal(out.points[~inside], mesh.points[~inside])
    np.testing.assert_allclose(out.points[inside], hm.map(mesh.points[inside]), atol=1e-12)
    assert int(out.field_data["vhm_outside_count"][0]) == flt.outside_count


# NaN outside the cage is the asked-for result: no numpy warning about it
@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_outside_points_nan_policy():
    mesh, hm, inside = _sphere_in_small_box()
    flt = _filter(mesh, hm, outside="nan")
    flt.SetComputeDisplacement(True)
    flt.SetComputeJacobianDeterminant(True)
    out = pv.wrap(update(flt))
    flags = np.asarray(out.point_data["vhm_outside"])
    assert flags.dtype == np.uint8
    np.testing.assert_array_equal(flags, (~inside).astype(np.uint8))
    assert flt.outside_count == int((~inside).sum())
    assert int(out.field_data["vhm_outside_count"][0]) == int((~inside).sum())
    pts = np.asarray(out.points)
    assert np.isnan(pts[~inside]).all()
    np.testing.assert_allclose(pts[inside], hm.map(mesh.points[inside]), atol=1e-12)
    det = np.asarray(out.point_data["jacobian_determinant"])
    assert np.isnan(det[~inside]).all()
    np.testing.assert_allclose(
        det[inside], np.linalg.det(hm.jacobian(mesh.points[inside])), rtol=1e-10
    )
    assert np.isnan(np.asarray(out.point_data["displacement"])[~inside]).all()
    # the input is untouched
    assert np.isfinite(mesh.points).all()


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("which", ["deformation_condition", "analysis"])
def test_outside_nan_policy_with_svd_measures(which):
    # regression: these raised "SVD did not converge" on the NaN Jacobians outside the cage
    mesh, hm, inside = _sphere_in_small_box()
    if which == "analysis":
        flt = _analysis(mesh, hm)
        flt.SetOutsidePolicy("nan")
    else:
        flt = _filter(mesh, hm, outside="nan")
        flt.SetComputeConditionNumber(True)
    out = pv.wrap(update(flt))
    cond = np.asarray(out.point_data["condition_number"])
    assert np.isnan(cond[~inside]).all()
    sv = np.linalg.svd(hm.jacobian(mesh.points[inside]), compute_uv=False)
    np.testing.assert_allclose(cond[inside], sv[:, 0] / sv[:, 2], rtol=1e-10)
    np.testing.assert_array_equal(out.point_data["vhm_outside"], (~inside).astype(np.uint8))
    if which == "analysis":
        np.testing.assert_array_equal(out.points, mesh.points)
        for name in ("jacobian_determinant", "rotation_angle"):
            values = np.asarray(out.point_data[name])
            assert np.isnan(values[~inside]).all() and np.isfinite(values[inside]).all()
        assert not np.asarray(out.point_data["foldover"]).any()


# ------------------------------------------------------------------ caching


def _small_deformer(mesh_bounds):
    cage = _cage_around(mesh_bounds, margin=0.2, divisions=2)
    anchors = np.column_stack([np.zeros(5), np.zeros(5), np.linspace(-0.4, 0.4, 5)])
    dfm = Deformer(cage, anchors)
    positions = np.array([[0.0, 0.0, -0.45], [0.0, 0.0, 0.45]])
    dfm.set_constraints(positions=positions, targets=positions)
    return dfm, positions


def test_binding_cache_targets_vs_geometry():
    mesh = pv.Sphere(radius=0.45, theta_resolution=16, phi_resolution=12)
    dfm, positions = _small_deformer(mesh.bounds)
    flt = _filter(mesh, dfm)
    out1 = np.array(pv.wrap(update(flt)).points)
    assert flt.bind_count == 1
    np.testing.assert_allclose(out1, mesh.points, atol=1e-9)  # rest targets: identity

    # moving a target re-executes without rebinding
    flt.UpdateTargets(targets=positions + [[0, 0, 0], [0.2, 0.0, 0.0]])
    out2 = np.array(pv.wrap(update(flt)).points)
    assert flt.bind_count == 1
    assert np.abs(out2 - out1).max() > 0.05
    np.testing.assert_allclose(out2, dfm.harmonic_map.map(mesh.points), atol=1e-9)

    # updating again without changes neither rebinds nor re-executes differently
    update(flt)
    assert flt.bind_count == 1

    # changing the geometry rebinds
    mesh.points = mesh.points * 0.9
    out3 = np.array(pv.wrap(update(flt)).points)
    assert flt.bind_count == 2
    np.testing.assert_allclose(out3, dfm.harmonic_map.map(mesh.points), atol=1e-9)

    # changing the constraint layout rebinds
    dfm.set_constraints(positions=positions * 0.9, targets=positions * 0.9)
    dfm.solve()
    flt.Modified()
    update(flt)
    assert flt.bind_count == 3

    # a different cage on port 1 rebuilds the deformer on it and rebinds
    cage2 = _cage_around(mesh.bounds, margin=0.3, divisions=2)
    flt.SetCageData(cage2)
    out4 = pv.wrap(update(flt))
    assert flt.bind_count == 4
    assert flt.GetDeformer() is not dfm
    np.testing.assert_allclose(
        out4.points, flt.GetDeformer().harmonic_map.map(mesh.points), atol=1e-9
    )


def test_unconverged_solve_is_refused_unless_allowed():
    """A solve the filter runs that stops at its iteration cap is no silent result:
    refused by default, let through with one warning when allowed; a deformer the caller
    solved is taken as it is (its report went to the caller)."""
    import warnings

    from vhm_viz.scene import Scene

    mesh = pv.Sphere(radius=0.45, theta_resolution=16, phi_resolution=12)
    dfm, positions = _small_deformer(mesh.bounds)
    dfm.update_targets(targets=positions + [[0, 0, 0], [0.25, 0.1, 0.0]])
    flt = _filter(mesh, dfm)  # unsolved: the filter solves it
    flt.SetSolverSettings(max_iterations=1, tolerance=1e-12)
    with pytest.raises(RuntimeError, match="not converged: the solver stopped at max_iterati"):
        update(flt)
    report = flt.solve_reports[-1]
    assert not report.converged and report.shortfall() in str(flt.last_error)
    assert f"{report.distance_estimate:.3g}" in report.shortfall()

    flt.SetAllowUnconverged(True)
    with pytest.warns(UserWarning, match="deforming with an unconverged solve") as seen:
        out = pv.wrap(update(flt))
        update(flt)  # the same solve: said once
    assert len(seen) == 1 and flt.warnings == [str(seen[0].message)]
    np.testing.assert_allclose(out.points, dfm.harmonic_map.map(mesh.points), atol=1e-9)

    # UpdateTargets solves too (the filter's settings): refused again once not allowed
    flt.SetAllowUnconverged(False)
    assert not flt.UpdateTargets(targets=positions + [[0, 0, 0], [0.2, 0.1, 0.0]]).converged
    with pytest.raises(RuntimeError, match="not converged"):
        update(flt)

    # solved by the caller, to convergence or not: no error, no warning
    for cap in (10000, 1):
        dfm.solve(max_iterations=cap, tolerance=1e-8)
        flt.Modified()
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            update(flt)
        assert flt.warnings == []

    # a scene's solve (the filter's own) with too few iterations
    scene = Scene.from_deformer(dfm, solver={"max_iterations": 1, "tolerance": 1e-12})
    flt2 = _filter(mesh, scene)
    with pytest.raises(RuntimeError, match="no output .*AllowUnconverged"):
        update(flt2)
    assert not flt2.solve_reports[-1].converged


def test_harmonic_map_rejects_other_cage():
    mesh = pv.Sphere(radius=0.4)
    hm = _random_map(_cage_around(mesh.bounds))
    flt = _filter(mesh, hm)
    flt.SetCageData(_cage_around(mesh.bounds, margin=0.3))
    with pytest.raises(ValueError, match="port 1"):
        update(flt)
    flt.SetCageData(hm.cage)  # the same cage is fine, and is the map's cage
    np.testing.assert_allclose(pv.wrap(update(flt)).points, hm.map(mesh.points), atol=1e-12)
    # so is a copy moved by far less than the tolerance (1e-9 of the diagonal) ...
    near = Cage(hm.cage.vertices + 1e-12 * hm.cage.diagonal, hm.cage.faces)
    flt.SetCageData(near)
    np.testing.assert_allclose(pv.wrap(update(flt)).points, hm.map(mesh.points), atol=1e-12)
    # ... but not one moved by more
    far = Cage(hm.cage.vertices + 1e-6 * hm.cage.diagonal, hm.cage.faces)
    flt.SetCageData(far)
    with pytest.raises(ValueError, match="port 1"):
        update(flt)


# ------------------------------------------------------------------ pieces


class _CageSource(VTKPythonAlgorithmBase):
    """Produces the cage and records the piece requests it receives."""

    def __init__(self, cage):
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=0, nOutputPorts=1, outputType="vtkPolyData"
        )
        self.cage = pv.wrap(cage_to_polydata(cage))
        self.requests = []

    def RequestData(self, request, in_info, out_info):
        info = out_info.GetInformationObject(0)
        self.requests.append(
            (info.Get(SDDP.UPDATE_PIECE_NUMBER()), info.Get(SDDP.UPDATE_NUMBER_OF_PIECES()))
        )
        out = vtk.vtkPolyData.GetData(out_info, 0)
        out.ShallowCopy(self.cage)
        return 1


@pytest.mark.parametrize("streaming_source", [True, False])
def test_pieces_reassemble_to_whole(streaming_source):
    whole_ext = (0, 11, 0, 9, 0, 13)
    rt = vtkRTAnalyticSource()
    rt.SetWholeExtent(*whole_ext)
    rt.Update()
    whole_img = pv.wrap(rt.GetOutput()).copy()
    cage = _cage_around(whole_img.bounds, margin=0.1)
    hm = _random_map(cage, scale=0.03)
    cage_src = _CageSource(cage)

    def make():
        flt = HarmonicDeformationFilter()
        if streaming_source:
            flt.SetInputConnection(0, rt.GetOutputPort())
        else:
            flt.SetInputData(whole_img)
        flt.SetCageConnection(cage_src.GetOutputPort())
        flt.SetHarmonicMap(hm)
        return flt

    whole = pv.wrap(update(make()))
    nx, ny, nz = whole.dimensions
    expected = np.asarray(whole.points).reshape(nz, ny, nx, 3)
    scalars = np.asarray(whole.point_data["RTData"]).reshape(nz, ny, nx)
    got = np.full_like(expected, np.nan)
    got_s = np.full_like(scalars, np.nan)
    pieces = []
    for p in range(4):
        flt = make()
        out = update(flt, p, 4)
        ext = out.GetExtent()
        pieces.append(ext)
        o = pv.wrap(out)
        shape, box = extent_box(ext)
        assert o.n_points == np.prod(shape) < whole.n_points
        got[box] = np.asarray(o.points).reshape(shape + (3,))
        got_s[box] = np.asarray(o.point_data["RTData"]).reshape(shape)
    assert len(set(pieces)) == 4
    np.testing.assert_allclose(got, expected, atol=1e-12)
    np.testing.assert_array_equal(got_s, scalars)
    # the cage was requested whole (piece 0 of 1) in every piece
    assert cage_src.requests and set(cage_src.requests) == {(0, 1)}


# ------------------------------------------------------------------ resampling


def _smooth_volume(dims=(20, 18, 16), spacing=(0.1, 0.11, 0.12), origin=(-1.0, -1.0, -0.9)):
    img = pv.ImageData(dimensions=dims, spacing=spacing, origin=origin)
    p = np.asarray(img.points)
    img.point_data["density"] = np.sin(2.1 * p[:, 0]) * np.cos(1.7 * p[:, 1]) + 0.5 * p[:, 2] + 2.0
    img.point_data["label"] = (p[:, 0] > 0).astype(np.uint8) * 200
    return img


def test_resample_affine_matches_affine_resampling():
    from scipy.spatial.transform import Rotation

    img = _smooth_volume()
    cage = _cage_around(img.bounds, margin=0.05, divisions=1)
    A = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix() @ np.diag([1.1, 0.95, 1.0])
    T = np.array([0.05, -0.08, 0.02])
    hm = HarmonicMap.affine(cage, A, T)
    flt = HarmonicResampleFilter()
    flt.SetInputData(img)
    flt.SetHarmonicMap(hm)
    flt.SetOutputMode("input")
    flt.SetFillValue(-7.0)  # not a value of the uint8 labels: refused, never clipped
    with pytest.raises(ValueError, match="fill_value -7 is not a uint8 value of the array 'label'"):
        update(flt)
    flt.SetFillValue(7.0)
    out = pv.wrap(update(flt))
    assert isinstance(out, pv.ImageData)
    assert out.dimensions == img.dimensions
    np.testing.assert_allclose(out.origin, img.origin)

    # independent reference: scipy's affine resampling, same grid in and out
    ref, clearly_in, clearly_out = affine_resampled(img, "density", A, T)
    y = np.asarray(out.points)
    mask = np.asarray(out.point_data["vtkValidPointMask"]).astype(bool)
    assert clearly_in.sum() > 0.5 * len(y) and clearly_out.sum() > 0
    assert mask[clearly_in].all() and not mask[clearly_out].any()
    got = np.asarray(out.point_data["density"])
    np.testing.assert_allclose(got[clearly_in], ref[clearly_in], atol=1e-6)
    np.testing.assert_array_equal(got[clearly_out], 7.0)
    assert out.point_data["label"].dtype == np.uint8
    np.testing.assert_array_equal(np.asarray(out.point_data["label"])[clearly_out], 7)


def test_resample_pieces_and_deformed_grid():
    img = _smooth_volume(dims=(12, 11, 10))
    cage = _cage_around(img.bounds, margin=0.05)
    hm = _random_map(cage, scale=0.01, seed=5)
    flt = HarmonicResampleFilter()
    flt.SetInputData(img)
    flt.SetHarmonicMap(hm)
    whole = pv.wrap(update(flt)).copy()
    np.testing.assert_allclose(whole.spacing, img.spacing)
    valid = np.asarray(whole.point_data["vtkValidPointMask"]).astype(bool)
    assert valid.mean() > 0.5
    # valid voxels hold the input sampled at their pre-image, found here independently
    # (scipy's root finder with a finite-difference Jacobian)
    from scipy.ndimage import map_coordinates
    from scipy.optimize import root

    rng = np.random.default_rng(0)
    pick = rng.choice(np.nonzero(valid)[0], 25, replace=False)
    nx, ny, nz = img.dimensions
    vol = np.asarray(img.point_data["density"]).reshape(nz, ny, nx)
    for k in pick:
        y = np.asarray(whole.points[k])
        sol = root(lambda x, y=y: hm.map(x[None])[0] - y, y, tol=1e-12)
        assert sol.success
        idx = (sol.x - np.asarray(img.origin)) / np.asarray(img.spacing)
        ref = map_coordinates(vol, idx[::-1, None], order=1, mode="nearest")[0]
        # the engine's pre-images are within 0.05 voxel; |grad density| < 3 per unit
        assert abs(whole.point_data["density"][k] - ref) < 3 * 0.05 * max(img.spacing)
    # pieces
    nx, ny, nz = whole.dimensions
    expected = np.asarray(whole.point_data["density"]).reshape(nz, ny, nx)
    got = np.full_like(expected, np.nan)
    for p in range(3):
        f2 = HarmonicResampleFilter()
        f2.SetInputData(img)
        f2.SetHarmonicMap(hm)
        out = update(f2, p, 3)
        shape, box = extent_box(out.GetExtent())
        got[box] = np.asarray(pv.wrap(out).point_data["density"]).reshape(shape)
    np.testing.assert_allclose(got, expected, atol=1e-9)


def test_resample_ct_rigid_rotation_preserves_voxel_sum():
    from scipy.spatial.transform import Rotation

    img = pv.read(data_path("volumes", "headsq_64x64x93.vti"))
    cage = _cage_around(img.bounds, margin=0.02, divisions=1)
    R = Rotation.from_rotvec([0.0, 0.0, np.radians(30)]).as_matrix()
    c = np.asarray(img.center)
    hm = HarmonicMap.affine(cage, R, c - R @ c)
    flt = HarmonicResampleFilter()
    flt.SetInputData(img)
    flt.SetHarmonicMap(hm)
    out = pv.wrap(update(flt))
    name = img.active_scalars_name
    s0 = float(np.asarray(img.point_data[name], dtype=np.float64).sum())
    s1 = float(np.asarray(out.point_data[name], dtype=np.float64).sum())
    np.testing.assert_allclose(out.spacing, img.spacing)
    assert abs(s1 / s0 - 1.0) < 0.01


def test_resample_spacing_with_another_output_grid_is_refused(tmp_path):
    """An output spacing sizes the grid that holds the deformed volume; with the input's
    grid or a reference image's it would be dropped, so the update fails saying so."""
    image = pv.ImageData(dimensions=(5, 5, 5), spacing=(0.2, 0.2, 0.2), origin=(-0.4,) * 3)
    image["s"] = np.arange(image.n_points, dtype=np.float32)
    v, f = box_cage((-1, -1, -1), (1, 1, 1))
    hm = HarmonicMap.identity(Cage(v, f))
    for kw, grid in ((dict(output="input"), "input"), (dict(reference=image), "reference")):
        with pytest.raises(ValueError, match=f"output spacing .*; the {grid} grid has its own"):
            image.vhm.resample(hm, spacing=(0.1, 0.1, 0.1), **kw)
    out = image.vhm.resample(hm, spacing=(0.1, 0.1, 0.1))
    np.testing.assert_allclose(out.spacing, (0.1, 0.1, 0.1))
    assert out.dimensions == (9, 9, 9)


def _corners(text: str) -> np.ndarray:
    """The two corners of ``(x, y, z)-(x, y, z)`` in a line."""
    return np.array([[float(v) for v in c.split(",")] for c in re.findall(r"\(([^)]*)\)", text)])


def test_resample_with_voxels_in_folds_says_how_many_and_where(tmp_path):
    """A resample whose output voxels lie in folds is made, and said: a FoldWarning (once
    per update) with their count and the box of their positions, as the output's own
    ``vhm_foldover`` mask and VTK's positions of its voxels give them."""
    import warnings

    from vhm_viz.core.errors import FoldWarning

    write_folding_volume(tmp_path)
    image = pv.read(tmp_path / "image.vti")
    flt = HarmonicResampleFilter()
    flt.SetInputData(image)
    flt.SetScene(str(tmp_path / "scene.json"))
    with pytest.warns(FoldWarning) as seen:
        out = pv.wrap(update(flt))
    assert len(seen) == 1 and flt.warnings == [str(seen[0].message)]
    marked = np.flatnonzero(np.asarray(out.point_data["vhm_foldover"]))
    at = np.asarray(out.points)[marked]
    assert marked.size > 0
    m = re.fullmatch(
        r"the deformation folds the data: (\d+) of (\d+) output voxels in folds "
        r"\(several pre-images; output positions within (\([^)]*\)-\([^)]*\))\)",
        flt.warnings[0],
    )
    assert m, flt.warnings[0]
    assert int(m.group(1)) == marked.size == flt.fold_voxels["count"]
    assert int(m.group(2)) == out.n_points
    box = np.array([at.min(axis=0), at.max(axis=0)])
    np.testing.assert_allclose(_corners(m.group(3)), box, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose([flt.fold_voxels["lo"], flt.fold_voxels["hi"]], box, atol=1e-12)
    # an update that folds nothing leaves no warning behind
    scene = Scene.load(tmp_path / "scene.json")
    flt.SetHarmonicMap(HarmonicMap.identity(scene.build_cage()))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = pv.wrap(update(flt))
    assert not np.asarray(out.point_data["vhm_foldover"]).any()
    assert flt.warnings == [] and flt.fold_voxels["count"] == 0


def test_warp_with_inverted_cells_says_how_many_and_worst_where(tmp_path, monkeypatch):
    """SetCheckFolds: the warped folding volume's inverted voxel cells, counted as a
    brute-force trilinear corner Jacobian of the output's points counts them, the worst
    ratio and its cell's rest centre, in one FoldWarning; off (the default), none. The
    same when the lattice's proof spares the cells it proves (as it does for large
    images)."""
    import warnings

    import vhm_viz.folds
    from vhm_viz.core.errors import FoldWarning

    write_folding_volume(tmp_path)
    image = pv.read(tmp_path / "image.vti")
    flt = HarmonicDeformationFilter()
    flt.SetInputData(image)
    flt.SetScene(str(tmp_path / "scene.json"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plain = pv.wrap(update(flt))
    assert flt.warnings == [] and flt.fold_cells is None
    flt.SetCheckFolds(True)
    with pytest.warns(FoldWarning) as seen:
        out = pv.wrap(update(flt))
    np.testing.assert_array_equal(out.points, plain.points)
    assert len(seen) == 1 and flt.warnings == [str(seen[0].message)]
    dims = tuple(image.dimensions)
    spacing = float(np.prod(image.spacing))
    ratio = trilinear_corner_dets(np.asarray(out.points).reshape(dims[::-1] + (3,))) / spacing
    bad = np.flatnonzero(ratio <= 0)
    assert bad.size > 0
    m = re.fullmatch(
        r"the deformation folds the data: (\d+) of (\d+) cells inverted \(cell det <= 0; "
        r"worst (\S+) at (\([^)]*\)), within (\([^)]*\)-\([^)]*\))\) \(rest positions\)",
        flt.warnings[0],
    )
    assert m, flt.warnings[0]
    assert int(m.group(1)) == bad.size == flt.fold_cells["count"]
    assert int(m.group(2)) == image.n_cells
    worst = int(bad[np.argmin(ratio[bad])])
    assert float(m.group(3)) == pytest.approx(ratio[worst], rel=1e-2)
    centres = np.asarray(image.cell_centers().points)
    np.testing.assert_allclose(_corners(m.group(4))[0], centres[worst], rtol=1e-3, atol=1e-3)
    box = [centres[bad].min(axis=0), centres[bad].max(axis=0)]
    np.testing.assert_allclose(_corners(m.group(5)), box, rtol=1e-3, atol=1e-3)
    monkeypatch.setattr(vhm_viz.folds, "PROOF_MIN_CELLS", 1)
    flt.SetTolerance(0.04)  # a new update (the same filter, the same map)
    with pytest.warns(FoldWarning):
        out = pv.wrap(update(flt))
    ratio = trilinear_corner_dets(np.asarray(out.points).reshape(dims[::-1] + (3,))) / spacing
    assert flt.fold_cells["count"] == np.count_nonzero(ratio <= 0)
    assert flt.fold_cells["worst"] == pytest.approx(ratio.min(), rel=1e-9)


def test_warp_of_a_tet_mesh_with_inverted_cells_counts_them(tmp_path):
    """SetCheckFolds on a tet mesh: its tetrahedra whose signed volume the warp turns
    (numpy, from the output's points) are the warning's count."""
    from vhm_viz.core.errors import FoldWarning

    write_folding_volume(tmp_path)
    tets = pv.read(tmp_path / "image.vti").to_tetrahedra()
    flt = HarmonicDeformationFilter()
    flt.SetInputData(tets)
    flt.SetScene(str(tmp_path / "scene.json"))
    flt.SetCheckFolds(True)
    with pytest.warns(FoldWarning):
        out = pv.wrap(update(flt))

    def volumes(points):
        x = np.asarray(points)[tets.cells_dict[pv.CellType.TETRA]]
        a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
        return np.einsum("ij,ij->i", a, np.cross(b, c))

    ratio = volumes(out.points) / volumes(tets.points)
    assert (ratio <= 0).sum() > 0
    assert flt.fold_cells["count"] == (ratio <= 0).sum()
    assert flt.fold_cells["cells"] == tets.n_cells
    assert f"{(ratio <= 0).sum()} of {tets.n_cells} cells inverted" in flt.warnings[0]


@pytest.mark.parametrize("kind", ["tets", "image"])
def test_fold_check_counts_inverted_cells_straddling_the_cage(kind):
    """SetCheckFolds with points left outside the cage (passthrough): of the inverted
    cells, those with a point outside span the map and the identity; the summary and the
    warning count them as the output's signed volumes (trilinear corner Jacobians) and
    its outside flags do."""
    from vhm_viz import examples
    from vhm_viz.core.errors import FoldWarning

    scene = examples.bar("bend-u", resolution=12).scene  # its cage ends at z = 5.2
    if kind == "tets":
        points, tets = examples.bar_tets(5)
        cells = np.hstack([np.full((len(tets), 1), 4), tets]).ravel()
        data = pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA),
                                   points * [1.0, 1.0, 1.3])  # fmt: skip
    else:
        data = pv.ImageData(dimensions=(6, 6, 34), spacing=(0.2, 0.2, 0.2), origin=(-0.5, -0.5, 0))
    flt = HarmonicDeformationFilter()
    flt.SetInputData(data)
    flt.SetScene(scene)
    flt.SetOutsidePolicy("passthrough")
    flt.SetCheckFolds(True)
    with pytest.warns(FoldWarning):
        out = pv.wrap(update(flt))
    flags = np.asarray(out.point_data["vhm_outside"]) != 0
    if kind == "tets":
        x = np.asarray(out.points)[tets]
        inverted = np.einsum("ij,ij->i", x[:, 1] - x[:, 0],
                             np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) <= 0  # fmt: skip
        touching = flags[tets].any(axis=1)
    else:
        dims = tuple(data.dimensions)
        inverted = trilinear_corner_dets(np.asarray(out.points).reshape(dims[::-1] + (3,))) <= 0
        corners = flags.reshape(dims[::-1])
        touching = np.zeros(inverted.size, bool).reshape(np.subtract(dims[::-1], 1))
        for dk, dj, di in np.ndindex(2, 2, 2):
            touching |= corners[dk : dk + dims[2] - 1, dj : dj + dims[1] - 1, di : di + dims[0] - 1]
        touching = touching.reshape(-1)
    straddling = int(np.count_nonzero(inverted & touching))
    assert straddling > 0 and flt.fold_cells["count"] == int(inverted.sum())
    assert flt.fold_cells["straddling"] == straddling
    count = "all" if straddling == inverted.sum() else straddling
    assert f", {count} of them straddling the cage" in flt.warnings[0]


@pytest.mark.parametrize("source", ["reader", "data set"])
def test_warp_fold_check_of_pieces_with_ghost_levels_counts_each_cell_once(tmp_path, source):
    """Pieces asked for with a ghost level (as ParaView's ranks are when a filter downstream
    needs ghost cells) hold a layer of their neighbours' cells: each piece's fold summary
    counts its own cells only, so that the pieces' summaries add up to the whole warped
    image's, as a brute-force trilinear corner Jacobian of the whole output counts them,
    whether a reader crops the pieces or the filter crops the data set it was given."""
    import warnings

    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    from vhm_viz.core.fold_voxels import merge_inverted_cells

    write_folding_volume(tmp_path)
    image = pv.read(tmp_path / "image.vti")
    flt = HarmonicDeformationFilter()
    if source == "reader":
        reader = vtkXMLImageDataReader()
        reader.SetFileName(str(tmp_path / "image.vti"))
        flt.SetInputConnection(reader.GetOutputPort())
    else:
        flt.SetInputData(image)
    flt.SetScene(str(tmp_path / "scene.json"))
    flt.SetCheckFolds(True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        whole = pv.wrap(update(flt))
        dims = tuple(image.dimensions)
        points = np.asarray(whole.points).reshape(dims[::-1] + (3,))
        ratio = trilinear_corner_dets(points) / float(np.prod(image.spacing))
        bad = np.flatnonzero(ratio <= 0)
        assert bad.size > 0 and flt.fold_cells["count"] == bad.size
        centres = np.asarray(image.cell_centers().points)[bad]
        for n in (2, 3):
            parts = []
            for piece in range(n):
                flt.UpdatePiece(piece, n, 1)
                assert flt.last_error is None
                out = flt.GetOutputDataObject(0)
                assert out.GetCellData().GetArray("vtkGhostType") is not None  # ghosts held
                parts.append(flt.fold_cells)
            merged = merge_inverted_cells(parts)
            assert (merged["count"], merged["cells"]) == (bad.size, image.n_cells), n
            assert merged["worst"] == pytest.approx(ratio[bad].min(), rel=1e-9)
            np.testing.assert_allclose(merged["lo"], centres.min(axis=0), atol=1e-9)
            np.testing.assert_allclose(merged["hi"], centres.max(axis=0), atol=1e-9)


# ------------------------------------------------------------------ analysis


def test_analysis_arrays_equal_metrics():
    mesh = pv.Sphere(radius=0.45, theta_resolution=20, phi_resolution=14)
    mesh.point_data["keep"] = np.arange(mesh.n_points)
    hm = _random_map(_cage_around(mesh.bounds), scale=0.05)
    flt = JacobianAnalysisFilter()
    flt.SetInputData(mesh)
    flt.SetHarmonicMap(hm)
    out = pv.wrap(update(flt))
    assert isinstance(out, pv.PolyData)
    np.testing.assert_array_equal(out.points, mesh.points)  # rest geometry
    np.testing.assert_array_equal(out.point_data["keep"], mesh.point_data["keep"])
    # the closed form against finite differences of the mapped positions
    fd = fd_jacobian(hm.map, mesh.points)
    np.testing.assert_allclose(hm.jacobian(mesh.points), fd, atol=1e-7)
    det, cond, angle = _reference_measures(fd)
    assert det.min() > 0 and np.ptp(det) > 0.05 and angle.max() > 1.0  # a real deformation
    np.testing.assert_allclose(out.point_data["jacobian_determinant"], det, rtol=1e-8)
    np.testing.assert_allclose(out.point_data["condition_number"], cond, rtol=1e-8)
    np.testing.assert_allclose(out.point_data["rotation_angle"], angle, atol=1e-6)
    np.testing.assert_array_equal(out.point_data["foldover"], np.zeros(mesh.n_points))
    # and bit-for-bit the library's measures of the closed-form Jacobian
    m = jacobian_measures(hm.jacobian(mesh.points))
    np.testing.assert_allclose(out.point_data["jacobian_determinant"], m["determinant"], rtol=1e-12)


def test_analysis_identity_map_and_foldover():
    img = pv.ImageData(dimensions=(5, 5, 5), spacing=(0.2,) * 3, origin=(-0.4,) * 3)
    cage = _cage_around(img.bounds)
    out = pv.wrap(update(_analysis(img, HarmonicMap.identity(cage))))
    assert isinstance(out, pv.ImageData)
    np.testing.assert_allclose(out.point_data["jacobian_determinant"], 1.0, atol=1e-10)
    np.testing.assert_allclose(out.point_data["condition_number"], 1.0, atol=1e-9)
    np.testing.assert_allclose(out.point_data["rotation_angle"], 0.0, atol=1e-5)
    assert not np.asarray(out.point_data["foldover"]).any()
    # a reflection folds everything over
    out = pv.wrap(update(_analysis(img, HarmonicMap.affine(cage, np.diag([1.0, 1.0, -1.0])))))
    assert np.asarray(out.point_data["foldover"]).all()


def _analysis(mesh, hm):
    flt = JacobianAnalysisFilter()
    flt.SetInputData(mesh)
    flt.SetDeformation(hm)
    return flt


def test_analysis_with_deformer_matches_binding():
    mesh = pv.Sphere(radius=0.45, theta_resolution=12, phi_resolution=10)
    dfm, positions = _small_deformer(mesh.bounds)
    dfm.update_targets(targets=positions + [[0, 0, 0], [0.15, 0.05, 0.0]])
    dfm.solve()
    out = pv.wrap(update(_analysis(mesh, dfm)))
    # finite differences of the deformer's own deformation of nearby points
    fd = fd_jacobian(lambda p: dfm.bind(p).deform(), mesh.points)
    det, cond, angle = _reference_measures(fd)
    assert np.abs(det - 1).max() > 0.01  # not the identity
    np.testing.assert_allclose(out.point_data["jacobian_determinant"], det, rtol=1e-8)
    np.testing.assert_allclose(out.point_data["condition_number"], cond, rtol=1e-8)
    np.testing.assert_allclose(out.point_data["rotation_angle"], angle, atol=1e-6)


# ------------------------------------------------------------------ accessor and errors


def test_accessor_deform_and_analyze():
    import vhm_viz.accessor  # noqa: F401 -- registers mesh.vhm

    mesh = pv.Sphere(radius=0.45)
    hm = _random_map(_cage_around(mesh.bounds))
    out = mesh.vhm.deform(hm, determinant=True)
    np.testing.assert_allclose(out.points, hm.map(mesh.points), atol=1e-12)
    det, cond, angle = _reference_measures(fd_jacobian(hm.map, mesh.points))
    np.testing.assert_allclose(out.point_data["jacobian_determinant"], det, rtol=1e-8)
    ana = mesh.vhm.analyze(hm)
    np.testing.assert_array_equal(ana.points, mesh.points)
    np.testing.assert_allclose(ana.point_data["jacobian_determinant"], det, rtol=1e-8)
    np.testing.assert_allclose(ana.point_data["condition_number"], cond, rtol=1e-8)
    np.testing.assert_allclose(ana.point_data["rotation_angle"], angle, atol=1e-6)
    np.testing.assert_array_equal(ana.point_data["foldover"], (det <= 0).astype(np.uint8))
    with pytest.raises(TypeError, match="ImageData"):
        mesh.vhm.resample(hm)


def _entry_point_value():
    from importlib.metadata import entry_points

    for ep in entry_points(group="pyvista.accessors"):
        if ep.name == "vhm":
            return ep.value
    return None


@pytest.mark.xfail(
    ":" in (_entry_point_value() or ""),
    reason="pyproject's pyvista.accessors entry point must name the module "
    "('vhm_viz.accessor'): PyVista imports the value as a module",
    strict=True,
)
def test_accessor_entry_point_without_import():
    import subprocess
    import sys

    code = (
        "import pyvista as pv, sys\n"
        "m = pv.Sphere()\n"
        "assert 'vhm_viz' not in sys.modules\n"
        "print(type(m.vhm).__name__)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "VHMAccessor"


def test_no_deformation_set_is_a_clear_error():
    flt = HarmonicDeformationFilter()
    flt.SetInputData(pv.Sphere())
    with pytest.raises(RuntimeError, match="no deformation set"):
        update(flt)


def _progress_trace(flt):
    seen = []
    flt.AddObserver("ProgressEvent", lambda obj, ev: seen.append(obj.GetProgress()))
    out = pv.wrap(update(flt))
    return np.array(out.points), seen


def test_memory_budget_sets_the_chunks_not_the_result():
    from vhm_viz.core.basis import chunk_rows

    mesh = pv.Sphere(radius=0.45, theta_resolution=30, phi_resolution=30)
    dfm, positions = _small_deformer(mesh.bounds)
    dfm.update_targets(targets=positions + [[0, 0, 0], [0.1, 0.05, 0.0]])
    dfm.solve()
    n_cols = dfm.cage.n_vertices + dfm.cage.n_faces  # basis functions evaluated per point
    budget = 64 * n_cols * 8 * 2  # 64 points per chunk of F (order 0)
    assert chunk_rows(n_cols, 0, budget) == 64
    whole, seen_whole = _progress_trace(_filter(mesh, dfm))
    flt = _filter(mesh, dfm)
    flt.SetMemoryBudget(budget)
    chunked, seen = _progress_trace(flt)
    # one progress report per chunk while binding (between 0.05 and 0.6), plus the fixed ones
    binding = [p for p in seen if 0.05 < p <= 0.6 + 1e-12]
    assert len(binding) == -(-mesh.n_points // 64)
    assert len(seen) > len(seen_whole)
    np.testing.assert_allclose(chunked, whole, rtol=0, atol=1e-13)
    np.testing.assert_allclose(whole, dfm.harmonic_map.map(mesh.points), atol=1e-12)
    with pytest.raises(ValueError, match=r"memory_budget must be an integer in \[1, "):
        flt.SetMemoryBudget(0)


def test_progress_events_and_abort():
    mesh = pv.Sphere(radius=0.45, theta_resolution=30, phi_resolution=30)
    dfm, _ = _small_deformer(mesh.bounds)
    flt = _filter(mesh, dfm)
    flt.SetMemoryBudget(100 * 1000)  # a few dozen points per chunk
    _, seen = _progress_trace(flt)
    assert len(seen) >= 5 and seen[-1] == 1.0
    assert all(b >= a for a, b in zip(seen, seen[1:], strict=False))

    flt2 = _filter(mesh.copy(), dfm)
    flt2.SetMemoryBudget(100 * 1000)
    chunks = []

    def abort(obj, ev):
        chunks.append(obj.GetProgress())
        if obj.GetProgress() > 0.2:
            obj.SetAbortExecute(1)

    flt2.AddObserver("ProgressEvent", abort)
    with pytest.raises(RuntimeError, match="abort"):
        update(flt2)
    # stopped during the binding (progress 0.05 to 0.6), then VTK's closing 1.0
    assert chunks[-1] == 1.0 and 0.2 < max(chunks[:-1]) < 0.6
    assert len(chunks) < len(seen)


def test_lattice_exchange_shares_even_out_the_ranks_busy_time():
    """The MPI ranks' shares of a round's evaluations (filters.mpi.balanced_shares)."""

    def header(busy, seconds=1.0, points=1000):
        return np.array([[1, 10, b, seconds, points] for b in busy], dtype=float)

    # no cost measured yet: equal, the remainder to the first ranks
    first = np.array([[1, 5, 0, 0, 0], [1, 5, 0, 0, 0], [1, 0, 0, 0, 0]], dtype=float)
    assert balanced_shares(10, first).tolist() == [4, 3, 3]
    # equally busy: equal
    assert balanced_shares(1000, header([2.0, 2.0])).tolist() == [500, 500]
    # at 1 ms a point, a rank 0.2 s behind takes 200 points fewer; all are dealt
    assert balanced_shares(1000, header([2.2, 2.0])).tolist() == [400, 600]
    # one rank far behind: the others take every point
    assert balanced_shares(1000, header([9.0, 2.0, 2.0])).tolist() == [0, 500, 500]
    for busy in ([3.0, 1.0, 2.5], [0.1, 0.0, 7.0, 0.3]):
        share = balanced_shares(777, header(busy))
        assert share.sum() == 777 and (share >= 0).all()


def test_parts_are_packed_with_their_values_and_rows_taken_straight_from_a_source():
    """An MPI part's buffer (filters.mpi.pack_part / unpack_part): every field's
    values come back exactly (int64 beyond 2**53, bools, odd lengths between 8-byte aligned fields),
    and an (array, index) field is the rows array[index], as if taken first."""
    rng = np.random.default_rng(3)
    source = rng.normal(size=(50, 8, 3))
    index = np.array([7, 0, 49, 7, 3])
    fields = {"ok": ((), np.uint8), "keys": ((2,), np.int64), "flag": ((), np.bool_),
              "data": ((8, 3), np.float64), "none": ((3,), np.float64)}  # fmt: skip
    keys = np.array([[2**62 + 1, -5], [3, 2**53 + 1], [0, 1]], dtype=np.int64)
    flags = np.array([True, False, True])
    part = {"ok": np.ones(1, dtype=np.uint8), "keys": keys, "flag": flags,
            "data": (source, index), "none": np.zeros((0, 3))}  # fmt: skip
    flat = pack_part(part, fields)
    assert flat.dtype == np.uint8 and len(flat) % 8 == 0
    assert part["data"][0] is source  # the caller's part is left as it was
    got = unpack_part(flat.copy(), fields)
    assert got.keys() == fields.keys()
    np.testing.assert_array_equal(got["keys"], keys)
    np.testing.assert_array_equal(got["flag"], flags)
    np.testing.assert_array_equal(got["data"], source[index])
    assert got["data"].shape == (5, 8, 3) and got["none"].shape == (0, 3)
    assert got["ok"].tolist() == [1]
    # rows taken from an array of another dtype are converted, as a copy would be
    ints = np.arange(12).reshape(6, 2)
    back = unpack_part(pack_part({**part, "keys": (ints, np.array([5, 1]))}, fields), fields)
    np.testing.assert_array_equal(back["keys"], ints[[5, 1]])


def test_lattice_exchange_deals_runs_of_neighbours_in_a_mixed_order():
    """Each rank's share is whole runs of consecutive keys, from all over the lattice."""
    n = 20 * DEAL_RUN + 123
    order = dealing_order(n)
    assert np.array_equal(np.sort(order), np.arange(n))  # every key, once
    # a run ascends by one; runs start on run boundaries (the odd-sized last one aside)
    starts = order[np.flatnonzero(np.diff(order, prepend=-2) != 1)]
    assert (starts % DEAL_RUN == 0).all() and len(starts) == 21
    # either half of the deal reaches both halves of the key range, not one end of it
    for half in (order[: n // 2], order[n // 2 :]):
        assert (half < n // 4).any() and (half > 3 * n // 4).any()
    assert not np.array_equal(order, np.arange(n))
