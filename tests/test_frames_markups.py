"""One physical frame: scans where nibabel puts them, scenes in LPS or RAS, Slicer markups.

References are independent of vhm_viz's readers: nibabel's affine (RAS) for the
radiological NIfTI, the half turn RAS = diag(-1, -1, 1) LPS written out by hand, and the
raw JSON of the markups files.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import box_cage, data_path

from vhm_viz.cli import main
from vhm_viz.io import read_anchors, read_dataset, write_anchors
from vhm_viz.io.markups import read_markups, write_markups
from vhm_viz.scene import Scene, SceneError

nib = pytest.importorskip("nibabel")

NIFTI = data_path("volumes", "avg152T1_RL_nifti.nii.gz")
FLIP = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS, written out independently


def _ras(points):
    return np.asarray(points, dtype=np.float64) * FLIP


def test_radiological_nifti_lies_at_nibabels_physical_points():
    image = read_dataset(NIFTI)
    ref = nib.load(NIFTI)
    dims = np.array(ref.shape[:3])
    np.testing.assert_array_equal(image.dimensions, dims)
    rng = np.random.default_rng(35)
    ijk = np.vstack([rng.integers(0, dims, size=(200, 3)), [0, 0, 0], dims - 1])
    ras = ijk @ ref.affine[:3, :3].T + ref.affine[:3, 3]
    flat = ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2])  # VTK: x fastest
    np.testing.assert_allclose(np.asarray(image.points)[flat], _ras(ras), atol=1e-4)
    values = np.asarray(ref.get_fdata())[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    np.testing.assert_allclose(np.asarray(image.active_scalars)[flat], values)


def _lps_scene(anchors="inline") -> dict:
    """A bend of a box cage with position and Jacobian constraints, in LPS."""
    v, f = box_cage((-60.0, -80.0, -40.0), (40.0, 70.0, 90.0), divisions=2)
    c = v.mean(axis=0)
    positions = np.array([c + [-30, -50, -20], c + [20, 40, 50], c + [25, -45, 30]])
    targets = positions + [[0, 0, 0], [12, -6, 4], [-3, 5, 8]]
    turn = np.array([[np.cos(0.2), -np.sin(0.2), 0], [np.sin(0.2), np.cos(0.2), 0], [0, 0, 1]])
    a = np.array([c + [x, y, z] for x in (-25, 25) for y in (-40, 40) for z in (-30, 30)])
    return {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": {"vertices": v.tolist(), "faces": f.tolist()},
        "anchors": a.tolist() if anchors == "inline" else anchors,
        "constraints": {
            "positions": positions.tolist(),
            "targets": targets.tolist(),
            "jacobian_points": [c.tolist()],
            "jacobians": [(1.1 * turn).tolist()],
        },
        "solver": {"tolerance": 1e-12, "max_iterations": 20000},
    }


def _as_ras(scene: dict) -> dict:
    """The same scene with its coordinates written in RAS (by hand)."""
    ras = json.loads(json.dumps(scene))
    ras["space"] = "RAS"
    cage = ras["cage"]
    cage["vertices"] = _ras(cage["vertices"]).tolist()
    if isinstance(ras["anchors"], list):
        ras["anchors"] = _ras(ras["anchors"]).tolist()
    c = ras["constraints"]
    for name in ("positions", "targets", "jacobian_points"):
        if isinstance(c[name], list):  # (markups say their frame themselves)
            c[name] = _ras(c[name]).tolist()
    c["jacobians"] = [
        (np.diag(FLIP) @ np.array(j) @ np.diag(FLIP)).tolist() for j in c["jacobians"]
    ]
    return ras


def _deformed(scene: Scene, points) -> np.ndarray:
    solved = scene.solve_map()
    solved.require_converged()
    return solved.deformer.bind(points).deform()


@pytest.fixture(scope="module")
def lps_result():
    scene = _lps_scene()
    v = np.array(scene["cage"]["vertices"])
    rng = np.random.default_rng(7)
    points = v.min(axis=0) + (0.1 + 0.8 * rng.random((300, 3))) * np.ptp(v, axis=0)
    return points, _deformed(Scene.from_dict(scene), points)


def test_a_ras_scene_deforms_like_the_same_scene_in_lps(tmp_path, lps_result):
    points, expected = lps_result
    ras = Scene.from_dict(_as_ras(_lps_scene()))
    assert any("from RAS to LPS" in note for note in ras.notes)
    lps = Scene.from_dict(_lps_scene())
    for name, values in lps.constraints.items():
        np.testing.assert_allclose(ras.constraints[name], values, atol=1e-12, err_msg=name)
    np.testing.assert_allclose(_deformed(ras, points), expected, atol=1e-8)
    # written back in LPS, the one frame every scene writer uses
    ras.save(tmp_path / "scene.json")
    saved = json.loads((tmp_path / "scene.json").read_text())
    assert saved["space"] == "LPS"
    assert Scene.load(tmp_path / "scene.json") == lps


def test_a_scene_in_another_frame_is_refused_naming_the_field():
    with pytest.raises(SceneError, match=r"scene field 'space': expected \"LPS\" or \"RAS\""):
        Scene.from_dict({**_lps_scene(), "space": "RAI"})


@pytest.mark.parametrize("space", ["LPS", "RAS"])
def test_markups_round_trip_in_their_coordinate_system(tmp_path, space):
    points = np.random.default_rng(3).normal(scale=50.0, size=(7, 3))
    path = tmp_path / "points.mrk.json"
    write_markups(path, points, space=space)
    raw = json.loads(path.read_text())
    (markup,) = raw["markups"]
    assert markup["type"] == "Fiducial" and markup["coordinateSystem"] == space
    stored = np.array([cp["position"] for cp in markup["controlPoints"]])
    np.testing.assert_array_equal(stored, _ras(points) if space == "RAS" else points)
    np.testing.assert_array_equal(read_markups(path), points)
    # Slicer's default when coordinateSystem is absent is LPS
    del markup["coordinateSystem"]
    path.write_text(json.dumps(raw))
    np.testing.assert_array_equal(read_markups(path), stored)


def test_markups_anchor_and_constrain_a_deformation_like_json_points(tmp_path, lps_result):
    points, expected = lps_result
    scene = _lps_scene()
    write_markups(tmp_path / "anchors.mrk.json", scene["anchors"], space="RAS")
    write_markups(tmp_path / "targets.mrk.json", scene["constraints"]["targets"], space="RAS")
    write_markups(tmp_path / "sources.mrk.json", scene["constraints"]["positions"])
    marked = _lps_scene(anchors={"markups": "anchors.mrk.json"})
    marked["constraints"]["positions"] = {"markups": "sources.mrk.json"}
    marked["constraints"]["targets"] = {"markups": "targets.mrk.json"}
    (tmp_path / "scene.json").write_text(json.dumps(_as_ras(marked)))
    loaded = Scene.load(tmp_path / "scene.json")
    assert tmp_path / "anchors.mrk.json" in loaded.referenced_files()
    np.testing.assert_allclose(_deformed(loaded, points), expected, atol=1e-8)


def test_bad_markups_are_refused_with_one_line(tmp_path):
    path = tmp_path / "bad.mrk.json"
    path.write_text(json.dumps({"markups": [{"type": "Fiducial", "coordinateSystem": "XYZ"}]}))
    with pytest.raises(ValueError, match="coordinateSystem 'XYZ' is not one of LPS, RAS"):
        read_markups(path)
    scene = _lps_scene()
    scene["constraints"]["targets"] = {"markups": str(path)}
    with pytest.raises(SceneError, match=r"constraints.targets.markups.*coordinateSystem"):
        Scene.from_dict(scene)


def test_cli_anchors_writes_a_slicer_point_list(tmp_path, capsys):
    import pyvista as pv

    from vhm_viz.core.cage import Cage
    from vhm_viz.io import write_cage

    pv.Sphere(radius=20.0, center=(-5.0, 10.0, 3.0)).save(tmp_path / "ball.vtp")
    v, f = box_cage((-30.0, -15.0, -22.0), (20.0, 35.0, 28.0))
    write_cage(tmp_path / "cage.obj", Cage(v, f))
    args = ["anchors", str(tmp_path / "ball.vtp"), "-c", str(tmp_path / "cage.obj"), "-n", "6"]
    assert main([*args, "-o", str(tmp_path / "a.mrk.json"), "-q"]) == 0
    assert main([*args, "-o", str(tmp_path / "a.json"), "-q"]) == 0
    np.testing.assert_array_equal(
        read_anchors(tmp_path / "a.mrk.json"), read_anchors(tmp_path / "a.json")
    )
    raw = json.loads((tmp_path / "a.mrk.json").read_text())
    assert raw["markups"][0]["coordinateSystem"] == "LPS"
    assert len(raw["markups"][0]["controlPoints"]) == 6
    # the same anchors as a bare JSON file, for the round trip through write_anchors
    write_anchors(tmp_path / "b.mrk.json", read_anchors(tmp_path / "a.json"))
    np.testing.assert_array_equal(
        read_markups(tmp_path / "b.mrk.json"), read_anchors(tmp_path / "a.json")
    )


def test_the_working_with_scans_example_runs(tmp_path, monkeypatch):
    """docs/working-with-scans.md's example: Slicer point lists in RAS bend the template."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "working-with-scans.md").read_text(
        encoding="utf-8"
    )
    (block,) = re.findall(r"```python\n(.*?)```", text, re.S)
    monkeypatch.chdir(tmp_path)
    space: dict = {}
    exec(compile(block, "working-with-scans.md", "exec"), space)
    assert space["solved"].converged
    np.testing.assert_allclose(space["moved"], space["targets"], atol=1e-6 * 180)
    assert space["size"][0] == pytest.approx(180.0)
