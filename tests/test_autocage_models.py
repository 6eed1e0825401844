"""The automatic set-up on every bundled model, against independent checks.

Cages: re-validated from their arrays, every input point inside by winding number.
Anchors: inside the cage and the shape, every input point within 15% of the bounding-box
diagonal of one (nearest-neighbour distances). Tet meshes: the default cage, 24 automatic
anchors and two position constraints give a deformer that moves every point finitely.
Volumes: every voxel above the threshold inside, the same cage accepted by the explorer.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import data_path
from scipy.spatial import cKDTree

pv = pytest.importorskip("pyvista")

from vhm_viz.app.controller import ExplorerController  # noqa: E402
from vhm_viz.autocage import auto_anchors, auto_cage, otsu_threshold  # noqa: E402
from vhm_viz.cli import main  # noqa: E402
from vhm_viz.core.basis import domain_columns, winding_number  # noqa: E402
from vhm_viz.core.cage import MIN_FACE_ANGLE, face_angles, validate_cage  # noqa: E402
from vhm_viz.core.deformer import Deformer  # noqa: E402
from vhm_viz.core.errors import CageError  # noqa: E402
from vhm_viz.io import read_cage, read_dataset  # noqa: E402

pytestmark = pytest.mark.data

MODELS = {
    "armadillo": (("armadillo", "armadillo_43k.obj"), {}),
    "beast": (("beast", "beast.obj"), {}),
    "hand": (("hand", "hand.obj"), {}),
    "horse": (("horse", "horse.obj"), {}),
    "bar": (("bar", "bar_dense.obj"), {}),
    "hand_tet": (("hand_tet", "hand.mesh"), {}),
    "dragon": (("tets", "dragon.tet.vtk"), {}),
    "tetra_inverted": (("tets", "tetraMesh_inverted.vtk"), {}),
    "ct_head": (("volumes", "headsq_64x64x93.vti"), {"threshold": "otsu"}),
    "embryo": (("volumes", "embryo.slc"), {"threshold": "otsu"}),
}
TET_MESHES = ["hand_tet", "dragon", "tetra_inverted"]


def _load(name):
    parts, kw = MODELS[name]
    return read_dataset(data_path(*parts)), kw


def _points(data, kw) -> np.ndarray:
    """The points a cage must enclose, computed here: all of them, or the voxels above."""
    pts = np.asarray(data.points, dtype=np.float64)
    if "threshold" in kw:
        vals = np.asarray(data.active_scalars)
        pts = pts[vals > otsu_threshold(vals)]
    return pts


@pytest.fixture(scope="module")
def setups():
    """Cage and 24 anchors per model, built once (the expensive part)."""
    cache = {}

    def get(name):
        if name not in cache:
            data, kw = _load(name)
            cage = auto_cage(data, **kw)
            anchors = auto_anchors(data, cage, 24, **kw)
            cache[name] = (data, kw, cage, anchors)
        return cache[name]

    return get


@pytest.mark.parametrize("name", list(MODELS))
def test_cage_encloses_every_point_within_the_budget(name, setups):
    data, kw, cage, _ = setups(name)
    validate_cage(cage.vertices, cage.faces)  # closed, manifold, outward, no crossings
    assert cage.n_faces <= 500
    pts = _points(data, kw)
    w = winding_number(pts, cage.vertices, cage.faces)
    assert w.min() > 1 - 1e-6, f"{int((w < 0.5).sum())} of {len(pts)} points outside"


@pytest.mark.parametrize("name", list(MODELS))
def test_few_faces_are_thinner_than_the_solve_takes(name, setups):
    # quadric simplification leaves needles on curved strips (the rounded edges of the
    # bar's offset surface); the cage flips or collapses them away where it can
    _, _, cage, _ = setups(name)
    angles = face_angles(cage.vertices, cage.faces).min(axis=1)  # computed here
    thin = int((angles < MIN_FACE_ANGLE).sum())
    assert thin == len(cage.thin_faces)
    assert thin <= 0.05 * cage.n_faces, f"{thin} of {cage.n_faces} faces below 3 degrees"


@pytest.mark.parametrize("name", list(MODELS))
def test_24_anchors_cover_the_shape(name, setups):
    data, kw, cage, anchors = setups(name)
    assert anchors.shape == (24, 3)
    assert cage.contains(anchors).all()
    pts = _points(data, kw)
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    dist, _ = cKDTree(anchors).query(pts)
    assert dist.max() <= 0.15 * diag, f"a point {dist.max() / diag:.1%} of the diagonal away"
    if isinstance(data, pv.PolyData) and data.n_cells:  # inside the closed input surface
        surf = data.triangulate()
        faces = np.asarray(surf.faces).reshape(-1, 4)[:, 1:]
        assert (np.abs(winding_number(anchors, surf.points, faces)) > 0.5).all()
    if "threshold" in kw:  # in the region: the nearest voxel is above the threshold
        vals = np.asarray(data.active_scalars)
        near = cKDTree(np.asarray(data.points)).query(anchors)[1]
        assert (vals[near] > otsu_threshold(vals)).all()


@pytest.mark.parametrize("name", TET_MESHES)
def test_tet_mesh_default_pipeline_deforms_every_point(name, setups):
    data, _, cage, anchors = setups(name)
    pts = np.asarray(data.points, dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    low, high = pts[np.argmin(pts[:, 2])], pts[np.argmax(pts[:, 2])]
    positions = np.array([low, high])
    targets = positions + [[0.0, 0.0, 0.0], [0.1 * diag, 0.0, 0.0]]
    deformer = Deformer(cage, anchors)  # default smoothness samples: inside however thin
    deformer.set_constraints(positions=positions, targets=targets)
    report = deformer.solve(max_iterations=3000)
    assert np.isfinite(report.final_energy)
    out = deformer.bind(pts).deform()
    assert np.isfinite(out).all()
    np.testing.assert_allclose(deformer.harmonic_map.map(positions), targets, atol=1e-8 * diag)
    assert np.abs(out - pts).max() > 0.05 * diag  # it really deformed


def test_cli_otsu_cage_of_a_volume_is_accepted_by_the_explorer(tmp_path):
    """The CLI, the explorer and Python agree on which voxels the Otsu cage encloses."""
    path = data_path("volumes", "headsq_64x64x93.vti")
    out = tmp_path / "ct_otsu.obj"
    assert main(["cage", str(path), "-o", str(out), "--threshold", "otsu", "-q"]) == 0
    cage = read_cage(out)
    data = read_dataset(path)
    vals = np.asarray(data.active_scalars)
    region = vals > otsu_threshold(vals)
    assert cage.contains(np.asarray(data.points)[region]).all()  # Python: every voxel above

    ctrl = ExplorerController()
    ctrl.load_file(path)
    ctrl.load_cage(out)  # the explorer finds its shape enclosed by the CLI's Otsu cage
    assert ctrl.cage is not None and ctrl.threshold is not None
    assert ctrl.threshold <= otsu_threshold(vals)  # it encloses at least the Otsu region
    assert any("voxels above" in n for n in ctrl.notes)
    # asked for the Otsu region explicitly, the explorer accepts it too
    ctrl2 = ExplorerController()
    ctrl2.load_file(path)
    ctrl2.threshold = "otsu"
    ctrl2.load_cage(out)
    # and refuses a cage that leaves voxels of the region out
    ctrl3 = ExplorerController()
    ctrl3.load_file(path)
    ctrl3.threshold = float(vals.min()) - 1.0  # every voxel
    with pytest.raises(CageError, match="region above"):
        ctrl3.load_cage(out)


def test_a_volume_shell_nobody_constrains_stays_put():
    """The CT head above 500 has a one-voxel speck: its shell is pinned, not singular."""
    data = read_dataset(data_path("volumes", "headsq_64x64x93.vti"))
    cage, report = auto_cage(data, threshold=500, return_report=True)
    assert report.n_components >= 2
    anchors = auto_anchors(data, cage, 24, threshold=500)
    vals = np.asarray(data.active_scalars)
    pts = np.asarray(data.points)[vals > 500]
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    positions = pts[[np.argmin(pts[:, 2]), np.argmax(pts[:, 2])]]
    deformer = Deformer(cage, anchors)
    with pytest.warns(UserWarning, match="stays put"):
        deformer.set_constraints(positions=positions, targets=positions + [0, 0.05 * diag, 0])
    assert len(deformer.pinned_shells) >= 1
    deformer.solve(max_iterations=2000)
    out = deformer.bind(pts).deform()
    assert np.isfinite(out).all()
    # the points of pinned shells do not move
    n = len(cage.vertices)
    cols = domain_columns(cage.vertices, cage.faces)
    for k in deformer.pinned_shells:
        faces = np.asarray(cage.faces)[cols[k][cols[k] >= n] - n]
        mine = winding_number(pts, cage.vertices, faces) > 0.5
        assert mine.any()
        np.testing.assert_allclose(out[mine], pts[mine], atol=1e-9 * diag)
