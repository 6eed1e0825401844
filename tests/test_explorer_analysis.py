"""The explorer's analysis without Qt: inverted cells and the injectivity certificate.

The controller (UI-free) is driven directly; the window's Certify action is exercised in
``test_app.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from vhm_viz import examples  # noqa: E402
from vhm_viz.app.controller import Cancelled, ExplorerController  # noqa: E402
from vhm_viz.core.errors import ConstraintError  # noqa: E402


def _bar(kind, **kw):
    ctrl = ExplorerController()
    ctrl.load_bar(kind, resolution=8, **kw)
    ctrl.prepare()
    ctrl.settle(init="identity")
    ctrl.deform()
    return ctrl


def test_certify_finds_the_fold_and_a_solve_drops_the_answer():
    ctrl = _bar("push")
    cert = ctrl.certify()
    assert cert.status == "not injective" and ctrl.certificate is cert
    hm = ctrl.deformer.harmonic_map
    assert np.all(np.linalg.det(hm.jacobian(cert.witnesses)) <= 0)
    witnesses, cubes = ctrl.certificate_geometry()
    np.testing.assert_allclose(witnesses, hm.map(cert.witnesses))
    assert cubes is None  # a witness ends the search: nothing left undecided
    assert ctrl.metrics()["certificate"] == "not injective"
    ctrl.drag(len(ctrl.positions) - 1, ctrl.positions[-1].target + [0.0, 0.0, 0.5])
    assert ctrl.certificate is None and "certificate" not in ctrl.metrics()


def test_certify_budget_undecided_cubes_are_drawn_mapped():
    ctrl = _bar("bend-90")
    cert = ctrl.certify(max_cubes=30)
    assert cert.status == "undecided"
    _, cubes = ctrl.certificate_geometry()
    assert cubes.n_cells == len(cert.undecided)
    corners = cert.undecided[:, 0]  # the lo corner is each hexahedron's first point
    mapped = np.asarray(cubes.points).reshape(-1, 8, 3)[:, 0]
    np.testing.assert_allclose(mapped, ctrl.deformer.harmonic_map.map(corners), atol=1e-12)


def test_certify_needs_a_solution_and_can_be_cancelled():
    ctrl = ExplorerController()
    ctrl.load_bar("bend-90", resolution=8)
    with pytest.raises(ConstraintError, match="solve"):
        ctrl.certify()
    ctrl = _bar("bend-90")
    with pytest.raises(Cancelled):
        ctrl.certify(cancelled=lambda: True)
    assert ctrl.certificate is None


def bar_tet_file(path, resolution: int = 4) -> np.ndarray:
    """Write the bar as a tet mesh (``examples.bar_tets``) to ``path``; its tets."""
    points, tets = examples.bar_tets(resolution)
    cells = np.hstack([np.full((len(tets), 1), 4), tets]).ravel()
    pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA), points).save(path)
    return tets


def _pushed_tets(tmp_path):
    """The bar as a tet mesh, pushed: some of its tets inverted. ``(controller, tets)``."""
    tets = bar_tet_file(tmp_path / "bar.vtu")
    sc = examples.bar("push", resolution=8)
    ctrl = ExplorerController()
    ctrl.load_file(tmp_path / "bar.vtu")
    ctrl.set_cage(sc.cage)
    ctrl.set_anchors(sc.anchors)
    for p, t in zip(sc.constraints["positions"], sc.constraints["targets"], strict=True):
        ctrl.add_position_constraint(p, t)
    for p in sc.constraints["jacobian_points"]:
        ctrl.add_jacobian_constraint(p)  # identity: bottom and top stay upright
    ctrl.prepare()
    ctrl.settle(init="identity")
    ctrl.deform()
    return ctrl, tets


def _inverted(points, tets) -> int:
    """Tets of ``points`` with a signed volume <= 0 (brute force)."""
    p = np.asarray(points)[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    return int(np.count_nonzero(vol <= 0))


def test_metrics_count_inverted_cells_of_tet_meshes(tmp_path):
    ctrl, tets = _pushed_tets(tmp_path)
    m = ctrl.metrics()
    assert m["cells"] == len(tets) and m["inverted_cells"] == _inverted(ctrl.deformed_points, tets)
    assert m["inverted_cells"] > 0
    assert "inverted_cells" not in _bar("bend-90").metrics()  # a surface has no cells to count


def test_export_of_a_folded_tet_mesh_says_how_many_cells_are_inverted(tmp_path):
    """The export writes the deformed tets as they are, and returns the line that says how
    many are inverted (what vhm-viz deform refuses without --allow-folds), counted as a
    brute force counts the written file's tets."""
    ctrl, tets = _pushed_tets(tmp_path)
    lines = ctrl.export(tmp_path / "bent.vtu")
    written = pv.read(tmp_path / "bent.vtu")
    inverted = _inverted(written.points, tets)
    assert inverted > 0 and len(lines) == 1
    assert lines[0].startswith(
        f"the deformation folds the data: {inverted} of {len(tets)} cells inverted (cell det <= 0"
    ), lines[0]
    # a bend that folds nothing: written without a line
    ctrl = _bar("bend-90")
    assert ctrl.export(tmp_path / "bend.vtp") == []
