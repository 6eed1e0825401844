"""Scene files: exact round trips, clear errors naming the field, building deformers."""

from __future__ import annotations

import dataclasses
import json
import os
import re

import numpy as np
import pytest
from conftest import box_cage

from vhm_viz import Cage
from vhm_viz.core.deformer import Deformer
from vhm_viz.io import write_cage
from vhm_viz.scene import SCENE_FORMAT, NotConverged, Scene, SceneError


def _deformer():
    v, f = box_cage((-0.6, -0.6, -0.6), (0.6, 0.6, 0.6), 2)
    cage = Cage(v, f)
    anchors = np.column_stack([np.zeros(4), np.zeros(4), np.linspace(-0.4, 0.4, 4)])
    dfm = Deformer(cage, anchors, mode="similar", alpha=0.02)
    pos = np.array([[0.0, 0.0, -0.5], [0.0, 0.0, 0.5]])
    tgt = pos + np.array([[0.0, 0.0, 0.0], [0.1 / 3, 0.2, -0.05]])
    rot = np.array([[np.cos(0.3), -np.sin(0.3), 0.0], [np.sin(0.3), np.cos(0.3), 0.0], [0, 0, 1]])
    dfm.set_constraints(positions=pos, targets=tgt, jacobian_points=pos[:1], jacobians=rot[None])
    return dfm


def _minimal(**changes):
    d = {
        "format": SCENE_FORMAT,
        "version": 1,
        "cage": {
            "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
            "faces": [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        },
        "anchors": [[0.2, 0.2, 0.2]],
        "constraints": {"positions": [[0.1, 0.1, 0.1]], "targets": [[0.1, 0.1, 0.15]]},
    }
    d.update(changes)
    return d


def test_round_trip_is_exact(tmp_path):
    dfm = _deformer()
    scene = Scene.from_deformer(dfm, solver={"max_iterations": 77, "steps": 2})
    path = tmp_path / "scene.json"
    scene.save(path)
    loaded = Scene.load(path)
    assert loaded == scene
    c0, c1 = scene.constraints, loaded.constraints
    for k in c0:
        np.testing.assert_array_equal(c0[k], c1[k])  # bit-exact floats (0.1/3 included)
    np.testing.assert_array_equal(loaded.cage["vertices"], dfm.cage.vertices)
    np.testing.assert_array_equal(loaded.anchors["points"], dfm.anchors)
    assert loaded.mode == "similar" and loaded.alpha == 0.02
    assert loaded.solver["max_iterations"] == 77 and loaded.solver["steps"] == 2
    # saving the loaded scene writes the identical file
    path2 = tmp_path / "again.json"
    loaded.save(path2)
    assert path2.read_text() == path.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.json", "scene.json"]


def test_minimal_file_is_normalised_and_round_trips(tmp_path):
    scene = Scene.from_dict(_minimal())
    d = scene.to_dict()
    assert d["mode"] == "rigid" and d["alpha"] == 0.01
    assert d["solver"]["init"] == "identity"
    assert d["constraints"]["jacobians"] == []
    assert Scene.from_dict(json.loads(json.dumps(d))).to_dict() == d


def test_built_deformer_reproduces_the_original(tmp_path):
    dfm = _deformer()
    dfm.solve(init="identity")
    scene = Scene.from_deformer(dfm)
    path = tmp_path / "s.json"
    scene.save(path)
    dfm2 = Scene.load(path).build()
    Scene.load(path).solve(dfm2)
    pts = np.random.default_rng(0).uniform(-0.4, 0.4, (50, 3))
    np.testing.assert_allclose(dfm2.harmonic_map.map(pts), dfm.harmonic_map.map(pts), atol=1e-8)


def test_cage_path_relative_to_scene_file(tmp_path):
    v, f = box_cage((-1, -1, -1), (1, 1, 1), 1)
    write_cage(tmp_path / "cage.obj", Cage(v, f))
    sub = tmp_path / "scenes"
    sub.mkdir()
    d = _minimal(
        cage="../cage.obj",
        anchors=[[0, 0, 0.2]],
        constraints={"positions": [[0, 0, 0]], "targets": [[0, 0, 0.1]]},
    )
    (sub / "s.json").write_text(json.dumps(d))
    scene = Scene.load(sub / "s.json")
    assert scene.to_dict()["cage"] == {"path": "../cage.obj"}
    dfm = scene.build()
    assert dfm.cage.n_vertices == 8


def test_ramped_solve_reaches_the_direct_solution():
    dfm = _deformer()
    direct = Scene.from_deformer(dfm, solver={"tolerance": 1e-9, "max_iterations": 5000})
    direct.solve(dfm)
    ref = dfm.coefficients.copy()
    dfm2 = _deformer()
    ramped = Scene.from_deformer(
        dfm2, solver={"steps": 3, "tolerance": 1e-9, "max_iterations": 5000}
    )
    reports = ramped.solve(dfm2)
    assert len(reports) == 3
    np.testing.assert_allclose(dfm2.coefficients, ref, atol=1e-5)


def test_solve_map_solves_then_reuses_the_stored_map():
    dfm = _deformer()
    scene = Scene.from_deformer(dfm, solver={"tolerance": 1e-9, "max_iterations": 5000})
    solved = scene.solve_map()
    assert not solved.reused and solved.converged and solved.reports
    probe = np.array([[0.1, -0.2, 0.3], [0.0, 0.25, -0.35]])
    # the same map as solving the deformer directly
    scene.solve(dfm)
    np.testing.assert_allclose(solved.harmonic_map.map(probe), dfm.harmonic_map.map(probe))
    assert scene.record_map(solved.deformer)
    again = Scene.loads(scene.dumps()).solve_map()
    assert again.reused and again.deformer is None and again.converged
    np.testing.assert_array_equal(again.harmonic_map.map(probe), solved.harmonic_map.map(probe))
    # solver overrides always solve anew
    assert not Scene.loads(scene.dumps()).solve_map(max_iterations=5000).reused


def test_ramped_solve_with_a_jacobian_constraint_records_its_map():
    """The last step of a ramp solves the scene's exact targets (positions and Jacobians),
    so a converged ramped solve is recorded and the recorded map is the solved one."""
    scene = Scene.from_deformer(
        _deformer(), solver={"steps": 4, "tolerance": 1e-9, "max_iterations": 5000}
    )
    assert len(scene.constraints["jacobians"]) == 1
    solved = scene.solve_map()
    assert len(solved.reports) == 4 and solved.converged
    c = solved.deformer.constraints
    for name in ("targets", "jacobians"):
        np.testing.assert_array_equal(c[name], scene.constraints[name])
    assert scene.record_map(solved.deformer)
    probe = np.random.default_rng(1).uniform(-0.4, 0.4, (20, 3))
    again = Scene.loads(scene.dumps()).solve_map()
    assert again.reused
    np.testing.assert_array_equal(again.harmonic_map.map(probe), solved.harmonic_map.map(probe))


def test_solve_map_reports_an_unconverged_solve_and_callers_decide():
    scene = Scene.from_deformer(_deformer(), solver={"tolerance": 1e-14, "max_iterations": 2})
    solved = scene.solve_map()
    assert not solved.converged and "max_iterations = 2" in solved.shortfall()
    solved.require_converged(allow=True)
    with pytest.raises(NotConverged, match="not converged: .*; raise it"):
        solved.require_converged(remedy="raise it")


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"version": 2}, "version"),
        ({"version": "1"}, "version"),
        ({"format": "something-else"}, "format"),
        ({"colour": "red"}, "colour"),
        ({"mode": "wobbly"}, "mode"),
        ({"alpha": -1}, "alpha"),
        ({"alpha": True}, "alpha"),
        ({"cage": 5}, "cage"),
        ({"cage": {"vertices": [[0, 0, 0]], "faces": []}}, "cage.vertices"),
        (
            {
                "cage": {
                    "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                    "faces": [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 9]],
                }
            },
            "cage.faces[3]",
        ),
        ({"cage": {"path": ""}}, "cage.path"),
        ({"anchors": []}, "anchors"),
        ({"anchors": [[0, 0]]}, "anchors[0]"),
        ({"anchors": {"auto": 0}}, "anchors.auto"),
        ({"anchors": {"skeleton": "x.tgf"}}, "anchors"),
        ({"constraints": {"positions": [[0, 0, 0]]}}, "constraints.targets"),
        (
            {"constraints": {"positions": [[0, 0, 0]], "targets": [[0, 0, 0], [1, 1, 1]]}},
            "constraints.targets",
        ),
        (
            {"constraints": {"positions": [[0, 0, 0], [1, 2]], "targets": [[0, 0, 0]]}},
            "constraints.positions[1]",
        ),
        (
            {"constraints": {"positions": [[0, 0, "x"]], "targets": [[0, 0, 0]]}},
            "constraints.positions[0][2]",
        ),
        (
            {
                "constraints": {
                    "positions": [[0, 0, 0]],
                    "targets": [[0, 0, 0]],
                    "jacobian_points": [[0, 0, 0]],
                    "jacobians": [[[1, 0], [0, 1]]],
                }
            },
            "constraints.jacobians[0][0]",
        ),
        (
            {
                "constraints": {
                    "positions": [[0, 0, 0]],
                    "targets": [[0, 0, 0]],
                    "jacobian_points": [[0, 0, 0]],
                }
            },
            "constraints.jacobians",
        ),
        ({"solver": {"iterations": 5}}, "solver.iterations"),
        ({"solver": {"init": "random"}}, "solver.init"),
        ({"solver": {"steps": 0}}, "solver.steps"),
        ({"map": {"coefficients": [[0, 0, 0]]}}, "map"),
        ({"map": {"coefficients": [[0, 0]], "inputs": "0" * 64}}, "map.coefficients[0]"),
        ({"map": {"coefficients": [[0, 0, 0]], "inputs": "not a digest"}}, "map.inputs"),
    ],
)
def test_malformed_scene_names_the_field(change, field):
    with pytest.raises(SceneError) as err:
        Scene.from_dict(_minimal(**change))
    assert err.value.field == field
    assert f"'{field}'" in str(err.value)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("value", [1e300, -2e15, float("nan")])
def test_an_array_edited_in_memory_is_refused_as_the_file_is(value):
    from vhm_viz.scene_fields import check_scene_values

    targets = [[0.1, 0.1, 0.15], [0.1, value, 0.1]]
    constraints = {"positions": [[0.1, 0.1, 0.1], [0.2, 0.1, 0.1]], "targets": targets}
    with pytest.raises(SceneError) as read:
        Scene.from_dict(_minimal(constraints=constraints))
    with pytest.raises(SceneError) as edited:
        check_scene_values(targets, "constraints.targets")
    assert str(edited.value) == str(read.value)
    assert edited.value.field == "constraints.targets[1][1]"
    np.testing.assert_array_equal(check_scene_values([[1e15, -1e15, 0]], "t"), [[1e15, -1e15, 0]])


def test_missing_fields_and_bad_json(tmp_path):
    d = _minimal()
    del d["constraints"]
    with pytest.raises(SceneError, match="'constraints': missing"):
        Scene.from_dict(d)
    d = _minimal()
    del d["version"]
    with pytest.raises(SceneError, match="'version': missing"):
        Scene.from_dict(d)
    p = tmp_path / "bad.json"
    p.write_text("{not json")
    with pytest.raises(SceneError, match="bad.json: scene .*not valid JSON"):
        Scene.load(p)
    p.write_text("[1, 2]")
    with pytest.raises(SceneError, match="bad.json"):
        Scene.load(p)
    with pytest.raises(FileNotFoundError):
        Scene.load(tmp_path / "missing.json")
    p.write_text(json.dumps(_minimal(version=99)))
    with pytest.raises(
        SceneError, match=r"bad.json: scene field 'version': unsupported version 99"
    ):
        Scene.load(p)


def test_an_unknown_field_is_named_with_those_that_are_known():
    import inspect

    from vhm_viz import auto_cage

    with pytest.raises(SceneError, match=r"'mdoe': unknown field; use one of alpha, anchors, "):
        Scene.from_dict(_minimal(mdoe="ARAP"))
    # an automatic cage's options are auto_cage's keywords, checked as the scene is read
    with pytest.raises(SceneError) as err:
        Scene.from_dict(_minimal(cage={"auto": {"max_face": 100}}))
    message = str(err.value)
    assert message.startswith("scene field 'cage.auto.max_face': unknown field; use one of ")
    named = message.split("use one of ")[1].split(", ")
    keywords = inspect.signature(auto_cage).parameters
    assert "max_faces" in named and "return_report" not in named
    assert all(keywords[name].kind is inspect.Parameter.KEYWORD_ONLY for name in named)
    scene = Scene.from_dict(_minimal(cage={"auto": {"max_faces": 100, "method": "voxel"}}))
    assert scene.cage == {"auto": {"max_faces": 100, "method": "voxel"}}


def _small_bar():
    """A real, small closed surface: the bundled bar (1 x 1 x 5) at a coarse resolution."""
    pv = pytest.importorskip("pyvista")
    from vhm_viz.examples import bar_surface

    v, f = bar_surface(6)
    return pv.PolyData.from_regular_faces(v, f)


def test_an_automatic_cage_option_out_of_range_is_named_as_the_scene_field():
    """A value auto_cage refuses (a face budget below a box's 12 triangles) is one error
    naming the scene's field, cage.auto.max_faces, like the other fields' errors."""
    scene = Scene.from_dict(_minimal(cage={"auto": {"max_faces": 3}}))
    with pytest.raises(SceneError) as err:
        scene.build_cage(_small_bar())
    assert err.value.field == "cage.auto.max_faces"
    assert str(err.value) == (
        "scene field 'cage.auto.max_faces': must be an integer of at least 12 (a box needs "
        "12 triangles); got 3"
    )


def test_auto_cage_and_auto_anchors_build_a_working_deformer():
    mesh = _small_bar()
    points = np.asarray(mesh.points)
    positions = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 4.9]])
    targets = np.array([[0.0, 0.0, 0.1], [1.5, 0.0, 4.5]])
    foot = [[0.0, 0.0, 0.3]]
    scene = Scene.from_dict(
        _minimal(
            cage={"auto": {"max_faces": 80}},
            anchors={"auto": 6},
            constraints={
                "positions": positions.tolist(),
                "targets": targets.tolist(),
                "jacobian_points": foot,
                "jacobians": [np.eye(3).tolist()],
            },
            solver={"max_iterations": 5000},
        )
    )
    assert scene.needs_data
    assert scene.to_dict()["cage"] == {"auto": {"max_faces": 80}}
    assert scene.to_dict()["anchors"] == {"auto": 6}
    with pytest.raises(SceneError, match="'cage'.*needs the data"):
        scene.build()
    dfm = scene.build(data=mesh)
    cage = dfm.cage
    # the automatic cage encloses the data with at most max_faces faces (the default
    # max_faces, 500, gives 500 faces on this bar: the option was passed through)
    assert 12 <= cage.n_faces <= 80
    assert cage.contains(points).all()
    # 6 anchors, inside the cage and inside the bar itself
    assert dfm.n_anchors == 6 and dfm.anchors.shape == (6, 3)
    assert cage.contains(dfm.anchors).all()
    assert (np.abs(dfm.anchors[:, :2]) < 0.5).all()
    assert ((dfm.anchors[:, 2] > 0) & (dfm.anchors[:, 2] < 5)).all()
    (report,) = scene.solve(dfm)
    assert report.converged
    hm = dfm.harmonic_map
    np.testing.assert_allclose(hm.map(positions), targets, atol=1e-8 * cage.diagonal)
    np.testing.assert_allclose(hm.jacobian(foot)[0], np.eye(3), atol=1e-8)
    moved = hm.map(points)
    assert np.abs(moved - points).max() > 0.3  # the top really moved
    assert Scene.from_dict(_minimal(cage="auto")).cage == {"auto": {}}


def test_json_the_parser_refuses_is_one_line_naming_the_file(tmp_path):
    # an integer past Python's digit limit, and nesting past its recursion limit, are
    # refused by the parser with messages of their own (or a bare RecursionError)
    from vhm_viz.io import ReadError, read_anchors
    from vhm_viz.io.markups import read_markups

    long_int = "1" + "0" * 5000
    deep = "[" * 100_000 + "]" * 100_000
    texts = {
        "long.json": (
            f'{{"format": "vhm_viz.scene", "version": {long_int}}}',
            "an integer of more than 4300 digits",
        ),
        "deep.json": (deep, "nested too deeply"),
    }
    for name, (text, why) in texts.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(SceneError) as err:
            Scene.load(tmp_path / name)
        assert str(err.value) == f"{tmp_path / name}: scene (json): not valid JSON: {why}"
        with pytest.raises(ReadError, match=f"^{re.escape(str(tmp_path / name))}: .*{why}"):
            read_anchors(tmp_path / name)
        with pytest.raises(ReadError, match=f"^{re.escape(str(tmp_path / name))}: .*{why}"):
            read_markups(tmp_path / name)


def test_a_scene_with_a_byte_order_mark_reads(tmp_path):
    # Windows editors save UTF-8 with a byte-order mark
    p = tmp_path / "bom.json"
    p.write_bytes(b"\xef\xbb\xbf" + json.dumps(_minimal()).encode())
    assert Scene.load(p).to_dict() == Scene.from_dict(_minimal()).to_dict()


def test_anchors_from_a_json_file_and_cage_from_an_obj(tmp_path):
    from vhm_viz.io import write_anchors

    dfm0 = _deformer()
    write_cage(tmp_path / "cage.obj", dfm0.cage)
    anchors = dfm0.anchors + np.array([0.1 / 3, -0.2 / 7, 0.0])  # not short decimals
    write_anchors(tmp_path / "anchors.json", anchors, resolution=96)
    written = json.loads((tmp_path / "anchors.json").read_text())
    assert written["count"] == len(anchors) and written["resolution"] == 96
    c = dfm0.constraints
    d = _minimal(
        cage="cage.obj",
        anchors="anchors.json",
        constraints={k: np.asarray(v).tolist() for k, v in c.items()},
        mode="similar",
        alpha=0.02,
    )
    (tmp_path / "s.json").write_text(json.dumps(d))
    scene = Scene.load(tmp_path / "s.json")
    assert scene.to_dict()["anchors"] == "anchors.json"
    assert scene.to_dict()["cage"] == {"path": "cage.obj"}
    assert not scene.needs_data
    assert sorted(p.name for p in scene.referenced_files()) == ["anchors.json", "cage.obj"]
    dfm = scene.build()
    # the files' values, bit for bit (OBJ written with 17 significant digits)
    np.testing.assert_array_equal(dfm.anchors, anchors)
    np.testing.assert_array_equal(dfm.cage.vertices, dfm0.cage.vertices)
    np.testing.assert_array_equal(dfm.cage.faces, dfm0.cage.faces)
    # and the deformation is the one built from the arrays directly
    ref = Deformer(dfm0.cage, anchors, mode="similar", alpha=0.02)
    ref.set_constraints(**c)
    ref.solve(init="identity")
    scene.solve(dfm)
    pts = np.random.default_rng(1).uniform(-0.4, 0.4, (30, 3))
    np.testing.assert_allclose(dfm.harmonic_map.map(pts), ref.harmonic_map.map(pts), atol=1e-12)
    # a missing file is named
    (tmp_path / "anchors.json").unlink()
    with pytest.raises(FileNotFoundError, match="anchors.json"):
        scene.build()


def test_saved_scene_is_compact_one_point_per_line(tmp_path):
    dfm = _deformer()
    scene = Scene.from_deformer(dfm)
    path = tmp_path / "s.json"
    scene.save(path)
    text = path.read_text()
    lines = text.splitlines()
    # every cage vertex, anchor and constraint point is one line "[x, y, z]" (full precision)
    for p in np.vstack([dfm.cage.vertices, dfm.anchors, dfm.constraints["targets"]]):
        row = "[" + ", ".join(json.dumps(float(x)) for x in p) + "]"
        assert any(line.strip().rstrip(",") == row for line in lines), row
    face = "[" + ", ".join(str(int(i)) for i in dfm.cage.faces[5]) + "]"
    assert any(line.strip().rstrip(",") == face for line in lines)
    # one line per point, face and matrix row; a few dozen lines of structure around them
    c = dfm.constraints
    rows = (
        dfm.cage.n_vertices
        + dfm.cage.n_faces
        + dfm.n_anchors
        + 2 * len(c["positions"])
        + len(c["jacobian_points"])
        + 3 * len(c["jacobians"])
    )
    list_lines = [line for line in lines if re.fullmatch(r"\s*\[[^\[\]{}]*\],?", line)]
    assert len(list_lines) == rows
    assert len(lines) < rows + 40
    assert 3 * len(lines) < len(json.dumps(scene.to_dict(), indent=1).splitlines())
    assert json.loads(text) == scene.to_dict()
    assert Scene.load(path) == scene


def _saved_scene(tmp_path):
    """A solved deformer, its scene saved to a file, and a sphere inside its cage."""
    pv = pytest.importorskip("pyvista")
    dfm = _deformer()
    scene = Scene.from_deformer(dfm)
    path = tmp_path / "s.json"
    scene.save(path)
    scene.solve(dfm)
    return dfm, scene, path, pv.Sphere(radius=0.45, theta_resolution=10, phi_resolution=8)


def test_filter_with_scene_file(tmp_path):
    pv = pytest.importorskip("pyvista")
    from vhm_viz.filters import HarmonicDeformationFilter, update

    dfm, scene, path, mesh = _saved_scene(tmp_path)
    flt = HarmonicDeformationFilter()
    flt.SetInputData(mesh)
    flt.SetScene(str(path))
    out = pv.wrap(update(flt))
    np.testing.assert_allclose(out.points, dfm.harmonic_map.map(mesh.points), atol=1e-8)
    assert len(flt.solve_reports) == 1


def test_paraview_mode_keeps_the_solved_map_not_the_solver(tmp_path):
    """Under ParaView (parallel reporting) nothing re-solves, so only the map is kept."""
    pv = pytest.importorskip("pyvista")
    from vhm_viz.filters import HarmonicDeformationFilter, JacobianAnalysisFilter, update

    dfm, scene, path, mesh = _saved_scene(tmp_path)
    for cls in (HarmonicDeformationFilter, JacobianAnalysisFilter):
        flt = cls()
        flt.SetParallelReporting(True)
        flt.SetInputData(mesh)
        flt.SetSceneFile(str(path))
        out = pv.wrap(update(flt))
        assert flt.GetDeformer() is None
        if cls is HarmonicDeformationFilter:
            np.testing.assert_allclose(out.points, dfm.harmonic_map.map(mesh.points), atol=1e-8)
        else:
            det = np.linalg.det(dfm.harmonic_map.jacobian(mesh.points))
            np.testing.assert_allclose(out.point_data["jacobian_determinant"], det, rtol=1e-8)
        # a setting that leaves the scene alone re-executes without solving again
        flt.SetOutsidePolicy("passthrough")
        update(flt)
        assert len(flt.solve_reports) == 1
        # a new scene file solves again
        scene2 = dataclasses.replace(scene, mode="rigid")
        path2 = tmp_path / f"{cls.__name__}.json"
        scene2.save(path2)
        flt.SetSceneFile(str(path2))
        update(flt)
        assert len(flt.solve_reports) == 2


def test_stored_map_round_trips_and_holds_only_for_its_inputs(tmp_path):
    """record_map stores a converged solve's map with the digest of its inputs; map_for
    gives it back, bit for bit, until anything the solve depended on changes."""
    dfm = _deformer()
    scene = Scene.from_deformer(dfm)
    assert not scene.record_map(dfm) and scene.stored_map is None  # not solved yet
    assert not scene.solve(dfm, max_iterations=1)[-1].converged
    assert not scene.record_map(dfm)  # an unconverged solve is not stored
    assert scene.solve(dfm)[-1].converged and scene.record_map(dfm)
    scene.save(tmp_path / "s.json")
    loaded = Scene.load(tmp_path / "s.json")
    assert loaded == scene
    cage = loaded.build_cage()
    anchors = loaded.build_anchors(cage)
    hm = loaded.map_for(cage, anchors)
    np.testing.assert_array_equal(hm.coefficients, dfm.harmonic_map.coefficients)

    def edited(**change):
        s = Scene.loads(loaded.dumps())
        for key, value in change.items():
            setattr(s, key, value)
        return s

    targets = dict(loaded.constraints, targets=loaded.constraints["targets"] + 1e-12)
    for s in (edited(constraints=targets), edited(alpha=0.03), edited(mode="rigid"),
              edited(solver=dict(loaded.solver, tolerance=1e-7))):  # fmt: skip
        assert s.map_for(cage, anchors) is None
    assert loaded.map_for(cage, anchors + [1e-12, 0, 0]) is None
    moved = Cage(np.asarray(cage.vertices) * (1 + 1e-12), cage.faces)
    assert loaded.map_for(moved, anchors) is None
    # a deformer whose constraints are not the scene's is not recorded
    other = _deformer()
    other.update_targets(targets=other.constraints["targets"] + 0.01)
    other.solve()
    assert not Scene.loads(loaded.dumps()).record_map(other)
    # nor one with another number of constraints
    fewer = _deformer()
    c = fewer.constraints
    fewer.set_constraints(positions=c["positions"][:1], targets=c["targets"][:1])
    fewer.solve()
    assert not Scene.loads(loaded.dumps()).record_map(fewer)


def test_paraview_mode_uses_the_stored_map_instead_of_solving(tmp_path):
    """With parallel reporting (ParaView) a scene's stored map is used as it is -- shown
    with a stored map that differs from what the solve gives -- and an edited scene is
    solved again."""
    pv = pytest.importorskip("pyvista")
    from vhm_viz import HarmonicMap
    from vhm_viz.filters import HarmonicDeformationFilter, update

    dfm, scene, path, mesh = _saved_scene(tmp_path)
    assert scene.record_map(dfm)
    identity = np.asarray(HarmonicMap.identity(dfm.cage).coefficients)
    half = identity + 0.5 * (np.asarray(dfm.harmonic_map.coefficients) - identity)
    scene.stored_map["coefficients"] = half  # (the digest still matches the inputs)
    scene.save(path)
    flt = HarmonicDeformationFilter()
    flt.SetParallelReporting(True)
    flt.SetInputData(mesh)
    flt.SetSceneFile(str(path))
    out = pv.wrap(update(flt))
    assert flt.solve_reports == []
    np.testing.assert_allclose(
        out.points, HarmonicMap(dfm.cage, half).map(mesh.points), rtol=0, atol=1e-12
    )
    assert np.abs(out.points - dfm.harmonic_map.map(mesh.points)).max() > 1e-3
    # the same scene with an edited constraint: the stored map no longer applies
    scene.constraints["targets"] = scene.constraints["targets"] * 1.01
    scene.save(path)
    st = path.stat()  # (a new modification time, as an editor's later save has)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    flt.Modified()
    out = pv.wrap(update(flt))
    assert len(flt.solve_reports) == 1
    assert np.abs(out.points - HarmonicMap(dfm.cage, half).map(mesh.points)).max() > 1e-3


def test_scene_file_rewritten_with_its_size_and_time_is_read_again(tmp_path):
    """A scene file rewritten with the same size and modification time (a script writing
    scenes in turn, within one tick of the file system's clock) is still read again."""
    pv = pytest.importorskip("pyvista")
    from vhm_viz.filters import HarmonicDeformationFilter, update

    dfm, scene, path, mesh = _saved_scene(tmp_path)
    flt = HarmonicDeformationFilter()
    flt.SetInputData(mesh)
    flt.SetSceneFile(str(path))
    first = np.array(pv.wrap(update(flt)).points)
    st = path.stat()
    text = path.read_text()
    assert '"alpha": 0.02' in text
    path.write_text(text.replace('"alpha": 0.02', '"alpha": 0.03'))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (st.st_size, st.st_mtime_ns)
    flt.Modified()
    second = np.array(pv.wrap(update(flt)).points)
    assert len(flt.solve_reports) == 2
    assert np.abs(second - first).max() > 1e-6
