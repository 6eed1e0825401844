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


def test_metrics_count_inverted_cells_of_tet_meshes(tmp_path):
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
    m = ctrl.metrics()
    moved = ctrl.deformed_points[tets]
    vol = np.einsum("ij,ij->i", moved[:, 1] - moved[:, 0],
                    np.cross(moved[:, 2] - moved[:, 0], moved[:, 3] - moved[:, 0]))  # fmt: skip
    assert m["cells"] == len(tets) and m["inverted_cells"] == int(np.count_nonzero(vol <= 0)) > 0
    assert "inverted_cells" not in _bar("bend-90").metrics()  # a surface has no cells to count
