"""``vhm-viz cage`` and ``vhm-viz anchors`` end to end, and their bad-input paths."""

from __future__ import annotations

import json

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from vhm_viz.cli import main  # noqa: E402
from vhm_viz.io import cage_from_dataset, read_cage, write_cage  # noqa: E402


@pytest.fixture(scope="module")
def capsule(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "capsule.vtp"
    pv.Capsule(radius=0.4, cylinder_length=2.0, resolution=24).triangulate().save(path)
    return path


def test_cage_then_anchors(capsule, tmp_path, capsys):
    cage_path = tmp_path / "cage.obj"
    assert main(["cage", str(capsule), "-o", str(cage_path), "--max-faces", "200"]) == 0
    cage = read_cage(cage_path)  # validates: closed, manifold, outward, no intersections
    assert cage.n_faces <= 200
    pts = np.asarray(pv.read(capsule).points)
    assert cage.contains(pts).all()
    out = tmp_path / "anchors.json"
    assert main(["anchors", str(capsule), "--cage", str(cage_path), "-o", str(out), "-n", "6"]) == 0
    anchors = np.asarray(json.loads(out.read_text())["anchors"])
    assert anchors.shape == (6, 3) and cage.contains(anchors).all()
    # on the capsule's axis (the x axis of pv.Capsule), i.e. on its medial axis
    assert np.abs(anchors[:, 1:]).max() < 0.15
    assert "faces" in capsys.readouterr().out


def test_cage_line_counts_the_thin_faces_it_kept(tmp_path, capsys):
    """A cage with faces thinner than MIN_FACE_ANGLE (the bar's long flat sides) says how
    many, counted from the written cage's angles; one without (a sphere's) says nothing."""
    from vhm_viz import examples
    from vhm_viz.core.cage import MIN_FACE_ANGLE

    bar = tmp_path / "bar.vtp"
    examples.bar("bend-u", resolution=12).surface.save(bar)
    sphere = tmp_path / "sphere.vtp"
    pv.Sphere().save(sphere)
    for data, thin in ((bar, True), (sphere, False)):
        cage_path = tmp_path / f"{data.stem}.obj"
        assert main(["cage", str(data), "-o", str(cage_path), "--max-faces", "300"]) == 0
        line = capsys.readouterr().out
        cage = read_cage(cage_path)
        x = np.asarray(cage.vertices)[np.asarray(cage.faces)]
        cosines = []
        for i in range(3):
            a, b = x[:, (i + 1) % 3] - x[:, i], x[:, (i + 2) % 3] - x[:, i]
            cosines.append(np.einsum("ij,ij->i", a, b) / np.linalg.norm(a, axis=1)
                           / np.linalg.norm(b, axis=1))  # fmt: skip
        angles = np.degrees(np.arccos(np.clip(np.max(cosines, axis=0), -1, 1)))
        count = int((angles < MIN_FACE_ANGLE).sum())
        assert (count > 0) == thin
        assert (f"{count} faces thinner than" in line) == thin, line
        assert ("thinner" in line) == thin


@pytest.mark.parametrize(
    "argv,message",
    [
        (["cage", "{missing}", "-o", "{tmp}/c.obj"], "not found"),
        (["cage", "{capsule_obj}", "-o", "{capsule_obj}"], "refusing to overwrite"),
        (["cage", "{capsule}", "-o", "{tmp}/c.txt"], "must end with"),
        (["anchors", "{capsule}", "--cage", "{missing}", "-o", "{tmp}/a.json"], "not found"),
        # the capsule's diagonal is about 3: a clearance past it is refused, not gridded
        (["cage", "{capsule}", "-o", "{tmp}/c.obj", "--offset", "1e9"], "--offset must be"),
        (["cage", "{capsule}", "-o", "{tmp}/c.obj", "--offset", "4"], "diagonal, 3.02"),
        (["cage", "{capsule}", "-o", "{tmp}/c.obj", "--threshold", "5"], "--threshold applies"),
        (["cage", "{cloud}", "-o", "{tmp}/c.obj", "--threshold", "5"], "is a point cloud"),
        # settings bounded below, named as the options the user typed
        (["cage", "{capsule}", "-o", "{tmp}/c.obj", "--max-faces", "3"],
         "--max-faces must be an integer of at least 12"),
        (["cage", "{capsule}", "-o", "{tmp}/c.obj", "--resolution", "0"],
         "--resolution must be an integer of at least 1; got 0"),
        (["anchors", "{capsule}", "--cage", "{box}", "-o", "{tmp}/a.json", "--resolution", "0"],
         "--resolution must be an integer of at least 4; got 0"),
        (["anchors", "{capsule}", "--cage", "{box}", "-o", "{tmp}/a.json", "--resolution", "3"],
         "--resolution must be an integer of at least 4; got 3"),
    ],
)  # fmt: skip
def test_bad_input_is_one_line_and_nonzero(argv, message, capsule, tmp_path, capsys):
    capsule_obj = tmp_path / "capsule.obj"
    pv.read(capsule).save(capsule_obj)
    fill = {"missing": tmp_path / "nope.obj", "tmp": tmp_path, "capsule": capsule}
    fill["capsule_obj"] = capsule_obj
    fill["cloud"] = tmp_path / "cloud.npy"
    np.save(fill["cloud"], np.asarray(pv.read(capsule).points))
    fill["box"] = tmp_path / "box.obj"  # encloses the capsule (x in [-1.4, 1.4], radius 0.4)
    write_cage(fill["box"], cage_from_dataset(pv.Box((-2, 2, -1, 1, -1, 1), quads=False)))
    before = capsule.read_bytes(), capsule_obj.read_bytes()
    rc = main([a.format(**fill) for a in argv])
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert message in err and len(err.splitlines()) == 1
    assert (capsule.read_bytes(), capsule_obj.read_bytes()) == before  # inputs untouched


@pytest.mark.data
@pytest.mark.parametrize(
    "data,cage,count",
    [
        # 12 of the 252 armadillo points stick out of this cage
        (("bad_cages", "armadillo_252v_for_partial_cage.obj"), "partial_armadillo_cage", 12),
        # the bar's cage holds a corner of the hand only (24 points)
        (("hand", "hand.obj"), "bar_cage_3d", 3320),
    ],
)
def test_anchors_refuse_a_cage_that_does_not_enclose_the_data(data, cage, count, tmp_path, capsys):
    from conftest import data_path

    cages = {
        "partial_armadillo_cage": data_path("bad_cages", "partial_armadillo_cage.obj"),
        "bar_cage_3d": data_path("bar", "bar_cage_3d.obj"),
    }
    src, out = data_path(*data), tmp_path / "a.json"
    n = pv.read(src).n_points
    outside = ~read_cage(cages[cage]).contains(np.asarray(pv.read(src).points))
    assert outside.sum() == count  # the cage's own inside test, independently
    rc = main(["anchors", str(src), "--cage", str(cages[cage]), "-o", str(out), "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and not out.exists()
    assert len(err) == 1 and f"{count} of {n} points" in err[0] and "outside the cage" in err[0]
    # the step that failed in words, not the library function's name
    assert err[0].startswith(f"vhm-viz anchors: error: automatic anchors: {count} of {n} points")


def test_anchors_are_distinct_where_the_skeleton_is_one_voxel(tmp_path, capsys):
    # a cube at a 6-voxel grid: its skeleton is the centre voxel, the anchors 4 places
    from conftest import box_cage

    src, cage_path, out = tmp_path / "cube.vtp", tmp_path / "box.obj", tmp_path / "a.json"
    pv.Cube().triangulate().save(src)
    v, f = box_cage((-2, -2, -2), (2, 2, 2))
    cage_path.write_text(
        "".join(f"v {x} {y} {z}\n" for x, y, z in v)
        + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f)
    )
    argv = ["anchors", str(src), "--cage", str(cage_path), "-o", str(out), "-n", "4"]
    assert main([*argv, "--resolution", "6"]) == 0, capsys.readouterr().err
    anchors = np.asarray(json.loads(out.read_text())["anchors"])
    assert len(np.unique(anchors, axis=0)) == 4 and np.abs(anchors).max() < 0.5


def test_a_scenes_automatic_anchors_cover_the_part_its_cage_holds(capsule, tmp_path, capsys):
    """``deform --outside passthrough`` moves the part of the data a cage holds: a scene's
    automatic anchors go there (the map, not the anchors, checks the data against the
    cage), and without passthrough the map refuses the points outside."""
    from conftest import box_cage

    surface = pv.read(capsule)  # z from -1.4 to 1.4
    v, f = box_cage((-1, -1, -1.6), (1, 1, 0.5))  # holds the lower part only
    held = np.asarray(surface.points)[:, 2] < 0.5
    scene = {"format": "vhm_viz.scene", "version": 1,
             "cage": {"vertices": v.tolist(), "faces": f.tolist()}, "anchors": {"auto": 6},
             "constraints": {"positions": [[0, 0, -1.2], [0, 0, 0.2]],
                             "targets": [[0, 0, -1.2], [0.1, 0, 0.2]]}}  # fmt: skip
    (tmp_path / "part.json").write_text(json.dumps(scene))
    argv = ["deform", str(capsule), "-s", str(tmp_path / "part.json"), "-q", "-o"]
    assert main([*argv, str(tmp_path / "o.vtp"), "--outside", "passthrough"]) == 0
    out = capsys.readouterr().out
    assert f"{int((~held).sum())} points outside the cage" in out
    moved = pv.read(tmp_path / "o.vtp")
    np.testing.assert_array_equal(moved.points[~held], surface.points[~held])
    assert main([*argv, str(tmp_path / "e.vtp")]) == 1
    err = capsys.readouterr().err
    assert "outside the cage" in err and "--outside passthrough" in err
    assert not (tmp_path / "e.vtp").exists()
