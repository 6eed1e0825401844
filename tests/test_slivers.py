"""Near-degenerate cage triangles are repaired or refused, never silently used.

Issue 12, defect 5: one sliver in an otherwise good cage gave exit 0, "converged", and a
result far from the clean cage's (the smoothness weight collapses on the sliver).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from vhm_viz import examples
from vhm_viz.core import metrics
from vhm_viz.core.cage import MIN_FACE_ANGLE, Cage, SliverError, face_angles
from vhm_viz.core.deformer import Deformer
from vhm_viz.io import write_cage


def with_needle(vertices, faces, t: float, face: int = 0):
    """Split the first edge of ``face`` (and its neighbour) at ``t`` of its length."""
    v, f = np.asarray(vertices, float), np.asarray(faces)
    a, b = f[face, 0], f[face, 1]
    nb = next(i for i, g in enumerate(f) if i != face and a in g and b in g)
    k = len(v)
    out = []
    for i, g in enumerate(f):
        if i in (face, nb):
            j = next(q for q in range(3) if {g[q], g[(q + 1) % 3]} == {a, b})
            u, w, o = g[j], g[(j + 1) % 3], g[(j + 2) % 3]
            out += [[u, k, o], [k, w, o]]
        else:
            out.append(list(g))
    return np.vstack([v, v[a] + t * (v[b] - v[a])]), np.array(out)


@pytest.fixture(scope="module")
def bar():
    sc = examples.bar("bend-u", resolution=10)
    return sc, _solve(sc, sc.cage)


def _solve(sc, cage):
    dfm = Deformer(cage, sc.anchors)
    dfm.set_constraints(**sc.scene.constraint_arguments())
    report = dfm.solve(max_iterations=20000)
    return dfm.bind(sc.points).deform(), report


@pytest.mark.parametrize("t", [0.1, 1e-3, 1e-6])
def test_a_needle_is_collapsed_and_the_result_is_the_clean_cages(bar, t):
    sc, (ref, _) = bar
    v, f = with_needle(sc.cage.vertices, sc.cage.faces, t)
    assert face_angles(v, f).min() < MIN_FACE_ANGLE
    cage = Cage(v, f)
    assert len(cage.repairs) == 1 and cage.repairs[0].startswith("collapsed edge")
    assert face_angles(cage.vertices, cage.faces).min() >= MIN_FACE_ANGLE
    out, report = _solve(sc, cage)
    diag = float(np.linalg.norm(np.ptp(sc.points, axis=0)))
    # before: converged, E_rigid 0.33-0.71 instead of 0.067, 0.37 diagonals away
    assert report.converged
    assert np.abs(out - ref).max() <= 1e-5 * diag
    assert metrics.rigidity_distortion(sc.points, out, sc.triangles) < 0.07


def test_refused_naming_the_faces_and_the_threshold_when_repair_is_off(bar):
    sc, _ = bar
    v, f = with_needle(sc.cage.vertices, sc.cage.faces, 1e-6)
    with pytest.raises(SliverError, match=r"faces \d+ \(.* deg\).* below the 3 degree minimum"):
        Cage(v, f, repair=False)


def test_a_cap_is_flipped():
    # a flat 3 x 3 grid on each side of a box, one vertex pushed next to an edge
    from conftest import box_cage

    v, f = box_cage((0, 0, 0), (1, 1, 1), divisions=3)
    # a vertex inside the z = 1 side, moved almost onto the segment between two others
    on_top = np.flatnonzero((np.abs(v[:, 2] - 1) < 1e-12) & (v[:, 0] > 0) & (v[:, 0] < 1)
                            & (v[:, 1] > 0) & (v[:, 1] < 1))  # fmt: skip
    p = on_top[0]
    v = v.copy()
    v[p, 0] += 0.32  # (1/3, 1/3) -> (0.653, 1/3): next to the grid edge x = 2/3
    assert face_angles(v, f).min() < MIN_FACE_ANGLE
    cage = Cage(v, f)
    assert cage.repairs and all(r.startswith(("flipped", "collapsed")) for r in cage.repairs)
    assert face_angles(cage.vertices, cage.faces).min() >= MIN_FACE_ANGLE
    assert cage.volume == pytest.approx(1.0, rel=1e-9)  # a flat side stays flat


def _surface_depths(v_new, f_new, v_old, f_old) -> np.ndarray:
    """How far inside the old surface the new one goes, at points over its faces.

    VTK's signed distance to the old surface (negative inside), at the new faces'
    corners, edge midpoints and centroids: minus that, so positive is inward.
    """
    pv = pytest.importorskip("pyvista")
    from vtkmodules.vtkFiltersCore import vtkImplicitPolyDataDistance

    old = pv.PolyData(v_old, np.column_stack([np.full(len(f_old), 3), f_old]))
    x = v_new[f_new]
    pts = np.concatenate([x.reshape(-1, 3), 0.5 * (x + x[:, [1, 2, 0]]).reshape(-1, 3),
                          x.mean(axis=1)])  # fmt: skip
    dist = vtkImplicitPolyDataDistance()
    dist.SetInput(old)
    return -np.array([dist.EvaluateFunction(p) for p in pts])


@pytest.mark.parametrize("inward", [0.0, 0.01, 0.05])
def test_reducing_slivers_moves_the_surface_inward_no_farther_than_allowed(inward):
    # a capped cylinder of 48 strips, 8 long and 1 round: its sides are needles (0.4
    # degrees) that only collapses along the circle remove, and those cut the chords in
    pv = pytest.importorskip("pyvista")
    from vhm_viz.core.slivers import reduce_slivers

    cyl = pv.Cylinder(radius=0.5, height=8.0, resolution=48, capping=True)
    cyl = cyl.triangulate().clean()
    v, f = np.asarray(cyl.points, float), cyl.regular_faces.astype(np.int64)
    assert (face_angles(v, f).min(axis=1) < 1.0).sum() == 96
    v1, f1, notes = reduce_slivers(v, f, MIN_FACE_ANGLE, inward=inward)
    # a closed, consistently oriented manifold: every directed edge once, its twin once
    edges = np.concatenate([f1[:, [0, 1]], f1[:, [1, 2]], f1[:, [2, 0]]])
    assert len({tuple(e) for e in edges}) == len(edges)
    assert {tuple(e) for e in edges} == {tuple(e) for e in edges[:, ::-1]}
    depth = _surface_depths(v1, f1, v, f)
    assert depth.max() <= inward + 1e-9
    thin = (face_angles(v1, f1).min(axis=1) < MIN_FACE_ANGLE).sum()
    if inward == 0.0:
        assert not notes and thin == 96  # every step would cut a chord in
    else:  # collapses along the circle, each cutting in by a chord's sagitta
        assert notes and thin < 96


def test_an_unrepairable_sliver_is_refused_with_its_face():
    # a tetrahedron with one edge 1e-4 long: no flip (every edge exists), no collapse
    v = np.array([[0, 0, 0], [1e-4, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    with pytest.raises(SliverError, match=r"face \d+ has an angle of .* below the 3 degree"):
        Cage(v, f)


def test_the_command_line_says_what_it_repaired(bar, tmp_path, capsys):
    from vhm_viz.cli import main

    sc, _ = bar
    v, f = with_needle(sc.cage.vertices, sc.cage.faces, 1e-6)
    write_cage(tmp_path / "cage.obj", _raw_cage(v, f))
    d = sc.scene.to_dict()
    d["cage"] = "cage.obj"
    (tmp_path / "scene.json").write_text(json.dumps(d))
    sc.surface.save(tmp_path / "bar.vtp")
    assert main(["deform", str(tmp_path / "bar.vtp"), "-s", str(tmp_path / "scene.json"),
                 "-o", str(tmp_path / "out.vtp"), "-q"]) == 0  # fmt: skip
    err = capsys.readouterr().err
    assert "vhm-viz: note: cage repaired: collapsed edge" in err


def _raw_cage(v, f):
    """Something write_cage can write without validating (an OBJ of the raw arrays)."""
    from types import SimpleNamespace

    return SimpleNamespace(vertices=v, faces=f)


def test_automatic_cages_keep_their_thin_faces_and_say_so(tmp_path, capsys):
    from vhm_viz.autocage import auto_cage
    from vhm_viz.cli import main
    from vhm_viz.io import read_cage

    sc = examples.bar("bend-u", resolution=6)
    auto = auto_cage(sc.surface, max_faces=80)
    assert len(auto.thin_faces)  # this bar's automatic cages have some (0.5 degrees)
    write_cage(tmp_path / "auto.obj", auto)  # marks them as accepted ...
    back = read_cage(tmp_path / "auto.obj")  # ... so the cage reads back as it was
    np.testing.assert_array_equal(back.faces, auto.faces)
    assert len(back.thin_faces) == len(auto.thin_faces) and not back.repairs
    d = sc.scene.to_dict()
    d["cage"] = "auto.obj"
    (tmp_path / "scene.json").write_text(json.dumps(d))
    sc.surface.save(tmp_path / "bar.vtp")
    main(["deform", str(tmp_path / "bar.vtp"), "-s", str(tmp_path / "scene.json"),
          "-o", str(tmp_path / "out.vtp"), "-q", "--allow-unconverged"])  # fmt: skip
    err = capsys.readouterr().err
    assert f"faces with an angle below {MIN_FACE_ANGLE:g} degrees" in err
