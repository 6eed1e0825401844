"""The command line: demo end to end, deform and analyze, and every kind of bad input."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from vhm_viz.cli import main  # noqa: E402
from vhm_viz.scene import Scene  # noqa: E402


def _run(capsys, *argv):
    rc = main(list(map(str, argv)))
    out, err = capsys.readouterr()
    return rc, out, err


def _with_scene(capsys, command, data, scene, output):
    """``vhm-viz <command> <data> --scene <scene> -o <output> -q``: rc, stdout, stderr."""
    return _run(capsys, command, data, "--scene", scene, "-o", output, "-q")


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    rc = main(["demo", "-o", str(out), "-q", "--resolution", "12", "--voxel", "0.12"])
    assert rc == 0
    return out


def test_demo_writes_everything(demo_dir):
    names = {p.name for p in demo_dir.iterdir()}
    expected = {
        "scene.json",
        "bar_rest.vtp",
        "bar_bent.vtp",
        "bar_tets_rest.vtu",
        "bar_tets_bent.vtu",
        "bar_volume_rest.vti",
        "bar_volume_bent.vts",
        "bar_volume_bent.vti",
        "figure4_slices.png",
        "figure12_condition_histogram.png",
        "energy.png",
        "bar_bent.png",
        "metrics.json",
    }
    assert expected <= names
    assert not [n for n in names if n.startswith(".")]  # no temporary files left
    metrics = json.loads((demo_dir / "metrics.json").read_text())
    assert metrics["converged"] and metrics["foldovers"] == 0
    assert 0.02 < metrics["E_rigid"] < 0.12  # paper Table 1 range / math notes: 0.068
    assert 0.01 < metrics["E_volume"] < 0.1
    bent = pv.read(demo_dir / "bar_bent.vtp")
    rest = pv.read(demo_dir / "bar_rest.vtp")
    assert bent.n_points == rest.n_points
    assert bent.bounds[1] > 3.0  # the top went over to x = 3.18
    assert isinstance(pv.read(demo_dir / "bar_tets_bent.vtu"), pv.UnstructuredGrid)
    vol = pv.read(demo_dir / "bar_volume_bent.vti")
    assert isinstance(vol, pv.ImageData) and "density" in vol.point_data
    assert 0.9 < metrics["volume_voxel_sum_ratio"] < 1.15


def test_demo_writes_relative_to_the_current_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, out, err = _run(
        capsys,
        "demo",
        "-o",
        "d",
        "-q",
        "--resolution",
        "6",
        "--voxel",
        "0.2",
        "--no-tets",
    )
    assert rc == 0, err
    assert str((tmp_path / "d").resolve()) in out
    assert "figure4_slices.png" in out and "bar_bent.png" in out
    assert (tmp_path / "d" / "bar_bent.png").is_file()
    _check_bar_picture(tmp_path / "d" / "bar_bent.png")


def _check_bar_picture(path):
    """The demo's 3D view: the rest bar in grey and the bent bar in colour, seen along y.

    The rest bar spans x in [-0.5, 0.5] and z in [0, 5]; bent into a U (the bottom held)
    its top goes over to x = 3.18, so the U is 4.2 wide and about 2.1 high. Left of the
    colour bar (the right quarter) and below the title, the coloured pixels span about 4.2
    times the width of the grey ones above the U, and about 2.1 / 5 of the rest bar's height.
    """
    from matplotlib.image import imread

    img = imread(str(path))[..., :3]
    assert img.shape[:2] == (700, 1000)
    view = img[60:, :750]
    spread = view.max(axis=2) - view.min(axis=2)
    coloured = spread > 0.12
    rows_c, cols_c = np.nonzero(coloured)
    assert coloured.sum() > 10_000
    # grey above the U: only the rest bar is there (det J near 1 is greyish on the U too)
    grey = (spread < 0.03) & (view.mean(axis=2) > 0.6) & (view.mean(axis=2) < 0.9)
    grey[rows_c.min() - 5 :] = False
    rows_g, cols_g = np.nonzero(grey)
    assert grey.sum() > 5_000
    assert 3.2 < np.ptp(cols_c) / np.ptp(cols_g) < 5.0
    assert 0.3 < np.ptp(rows_c) / (rows_c.max() - rows_g.min()) < 0.55


def test_deform_matches_the_scene(demo_dir, tmp_path, capsys):
    out_path = tmp_path / "bent.vtp"
    rc, out, err = _run(
        capsys,
        "deform",
        demo_dir / "bar_rest.vtp",
        "--scene",
        demo_dir / "scene.json",
        "-o",
        out_path,
        "--arrays",
        "det,displacement",
    )
    assert rc == 0, err
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 1
    assert "iterations" in lines[0] and "E_volume" in lines[0]
    assert "0 points outside the cage" in lines[0] and str(out_path) in lines[0]
    assert "binding" in err and "solving" in err  # progress bars
    result = pv.read(out_path)
    rest = pv.read(demo_dir / "bar_rest.vtp")
    scene = Scene.load(demo_dir / "scene.json")
    dfm = scene.build()
    scene.solve(dfm)
    np.testing.assert_allclose(result.points, dfm.harmonic_map.map(rest.points), atol=1e-6)
    assert "jacobian_determinant" in result.point_data
    assert "displacement" in result.point_data
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_deform_refuses_arrays_the_output_format_drops(demo_dir, tmp_path, capsys):
    # PLY, OBJ and STL keep only the geometry: asked-for arrays are refused before any
    # work, in one line naming them, the format and the suffixes that keep them
    args = ["deform", demo_dir / "bar_rest.vtp", "--scene", demo_dir / "scene.json", "-q",
            "--arrays", "det,displacement"]  # fmt: skip
    named = set()
    for suffix in (".ply", ".obj", ".stl"):
        out_path = tmp_path / f"bent{suffix}"
        rc, out, err = _run(capsys, *args, "-o", out_path)
        assert rc == 1 and out == "" and not out_path.exists()
        (line,) = err.strip().splitlines()
        m = re.fullmatch(
            rf"vhm-viz deform: error: --arrays det,displacement: .+ \({re.escape(suffix)}\) "
            r"keeps no point or cell arrays, only the geometry; write to (.+) to keep them",
            line,
        )
        assert m, line
        named.add(m.group(1))
    assert named == {".vtp or .vtk"}
    assert list(tmp_path.iterdir()) == []
    # the suffixes named keep them
    for suffix in (".vtp", ".vtk"):
        rc, _, err = _run(capsys, *args, "-o", tmp_path / f"bent{suffix}")
        assert rc == 0, err
        kept = pv.read(tmp_path / f"bent{suffix}").point_data
        assert {"jacobian_determinant", "displacement"} <= set(kept.keys()), suffix


def test_deform_refuses_options_the_input_leaves_without_effect(demo_dir, tmp_path, capsys):
    # cell arrays of data without 3D cells, and volume options given for other data or
    # resampling options for a warped volume, would be dropped: refused in one line
    # naming the option and why, before any work
    scene = demo_dir / "scene.json"
    surface, tets = demo_dir / "bar_rest.vtp", demo_dir / "bar_tets_rest.vtu"
    volume = demo_dir / "bar_volume_rest.vti"
    cloud = tmp_path / "cloud.vtp"
    pv.PolyData(pv.read(surface).points).save(cloud)
    resampled = "a volume resampled to an image (.vti, .mhd, .mha, .nii, .nii.gz, .nrrd)"
    cases = [
        (surface, "out.vtp", ["--arrays", "cells"],
         "--arrays cells: bar_rest.vtp has no 3D cells (a surface)"),
        (surface, "out.vtp", ["--arrays", "det,cells"],
         "--arrays cells: bar_rest.vtp has no 3D cells (a surface)"),
        (cloud, "out.vtp", ["--arrays", "cells"],
         "--arrays cells: cloud.vtp has no 3D cells (a point cloud)"),
        (surface, "out.vtp", ["--fill-value", "3"],
         f"--fill-value: applies to {resampled}; bar_rest.vtp is a surface"),
        (surface, "out.vtp", ["--fill-value", "0"],  # given, even at the default value
         f"--fill-value: applies to {resampled}; bar_rest.vtp is a surface"),
        (tets, "out.vtu", ["--interpolation", "nearest"],
         f"--interpolation: applies to {resampled}; bar_tets_rest.vtu is an UnstructuredGrid"),
        (surface, "out.vtp", ["--tolerance", "0.5"],
         "--tolerance: applies to volumes; bar_rest.vtp is a surface"),
        (volume, "out.vts", ["--fill-value", "3"],
         f"--fill-value: applies to {resampled}; written to .vts, the volume is warped "
         "(every voxel moved)"),
        (volume, "out.vti", ["--spacing", "0.1", "--reference", volume],
         "--spacing: applies to the grid that holds the deformed volume; --reference gives "
         "the grid, its spacing included"),
    ]  # fmt: skip
    for data, output, extra, message in cases:
        rc, out, err = _run(
            capsys, "deform", data, "--scene", scene, "-o", tmp_path / output, "-q", *extra
        )
        assert (rc, out, err) == (1, "", f"vhm-viz deform: error: {message}\n"), extra
    assert list(tmp_path.iterdir()) == [cloud]
    # where they apply, the same options are taken
    rc, _, err = _run(capsys, "deform", tets, "--scene", scene, "-o", tmp_path / "t.vtu", "-q",
                      "--arrays", "cells")  # fmt: skip
    assert rc == 0, err
    assert "cell_jacobian_determinant" in pv.read(tmp_path / "t.vtu").cell_data
    rc, _, err = _run(capsys, "deform", volume, "--scene", scene, "-o", tmp_path / "w.vts", "-q",
                      "--arrays", "cells", "--allow-folds")  # fmt: skip
    assert rc == 0, err
    warped = pv.read(tmp_path / "w.vts")  # a volume's cells are 3D cells too
    assert warped.cell_data["cell_jacobian_determinant"].size == warped.n_cells > 0
    rc, _, err = _run(capsys, "deform", volume, "--scene", scene, "-o", tmp_path / "v.vti", "-q",
                      "--fill-value", "3", "--tolerance", "0.5")  # fmt: skip
    assert rc == 0, err


def test_deform_volume_resampled_and_warped(demo_dir, tmp_path, capsys):
    scene = demo_dir / "scene.json"
    rc, out, err = _with_scene(
        capsys, "deform", demo_dir / "bar_volume_rest.vti", scene, tmp_path / "v.vti"
    )
    assert rc == 0, err
    assert "voxels with a pre-image" in out
    assert isinstance(pv.read(tmp_path / "v.vti"), pv.ImageData)
    rc, out, err = _with_scene(
        capsys, "deform", demo_dir / "bar_volume_rest.vti", scene, tmp_path / "v.vts"
    )
    assert rc == 0, err
    assert isinstance(pv.read(tmp_path / "v.vts"), pv.StructuredGrid)
    rc, out, err = _with_scene(
        capsys, "deform", demo_dir / "bar_tets_rest.vtu", scene, tmp_path / "t.vtp"
    )
    assert rc == 1 and "cannot write a UnstructuredGrid" in err


def test_deform_refuses_arrays_for_a_resampled_volume(demo_dir, tmp_path, capsys):
    # a resample pulls voxels back: it has none of the map's arrays to give, and says
    # where they are written instead
    args = ["deform", demo_dir / "bar_volume_rest.vti", "--scene", demo_dir / "scene.json",
            "-q", "--arrays", "det,displacement"]  # fmt: skip
    for suffix in (".vti", ".nii.gz"):
        rc, out, err = _run(capsys, *args, "-o", tmp_path / f"v{suffix}")
        (line,) = err.strip().splitlines()
        assert rc == 1 and out == "", err
        assert line == (
            f"vhm-viz deform: error: --arrays det,displacement: a volume resampled to {suffix} "
            "gets no arrays of the map (its voxels are pulled back, not moved); write the "
            "warped grid to .vts or .vtk to have them, or --write-field for a displacement field"
        )
    assert list(tmp_path.iterdir()) == []
    rc, _, err = _run(capsys, *args, "-o", tmp_path / "v.vts")
    assert rc == 0, err
    kept = pv.read(tmp_path / "v.vts").point_data
    assert {"jacobian_determinant", "displacement"} <= set(kept.keys())


def test_warped_volume_gets_the_cell_arrays_asked_for(demo_dir, tmp_path, capsys):
    """``--arrays cells`` on a warped image: each voxel's smallest det F over the six tets
    around its main diagonal, computed here from the rest and warped corners."""
    rest = pv.read(demo_dir / "bar_volume_rest.vti")
    rc, _, err = _run(capsys, "deform", demo_dir / "bar_volume_rest.vti", "--scene",
                      demo_dir / "scene.json", "-o", tmp_path / "v.vts", "-q", "--arrays",
                      "cells")  # fmt: skip
    assert rc == 0, err
    bent = pv.read(tmp_path / "v.vts")
    nx, ny, nz = rest.dimensions
    x = np.asarray(rest.points).reshape(nz, ny, nx, 3)
    y = np.asarray(bent.points).reshape(nz, ny, nx, 3)

    def corner(a, offset):  # the corner (i, j, k) + offset of every voxel, k slowest
        i, j, k = offset
        return a[k : nz - 1 + k, j : ny - 1 + j, i : nx - 1 + i].reshape(-1, 3)

    def volume(a, path):
        steps = np.eye(3, dtype=int)[list(path)]
        v = [corner(a, (0, 0, 0)), corner(a, steps[0]), corner(a, steps[0] + steps[1])]
        v.append(corner(a, (1, 1, 1)))
        return np.einsum("ij,ij->i", v[1] - v[0], np.cross(v[2] - v[0], v[3] - v[0]))

    paths = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    want = np.min([volume(y, p) / volume(x, p) for p in paths], axis=0)
    got = np.asarray(bent.cell_data["cell_jacobian_determinant"])
    np.testing.assert_allclose(got, want, rtol=1e-9)
    assert want.min() < 0.95 and want.max() > 1.05  # a bend: cells squeezed and stretched
    assert np.array_equal(bent.cell_data["cell_inverted"], (want <= 0).astype(np.uint8))


def test_analyze_writes_figures_and_metrics(demo_dir, tmp_path, capsys):
    scene = demo_dir / "scene.json"
    out_dir = tmp_path / "analysis"
    rc, out, err = _with_scene(capsys, "analyze", demo_dir / "bar_rest.vtp", scene, out_dir)
    assert rc == 0, err
    assert len(out.strip().splitlines()) == 1 and "E_rigid" in out
    for name in ("figure4_slices.png", "figure12_condition_histogram.png", "energy.png"):
        assert (out_dir / name).stat().st_size > 5000
    m = json.loads((out_dir / "metrics.json").read_text())
    for key in (
        "E_rigid",
        "E_volume",
        "jacobian_determinant",
        "condition_number",
        "foldovers",
        "iterations",
        "points_outside_cage",
    ):
        assert key in m
    assert m["foldovers"] == 0 and m["condition_number"]["min"] >= 1.0
    # tets: E_volume from the cell volumes, no E_rigid
    rc, out, err = _with_scene(
        capsys, "analyze", demo_dir / "bar_tets_rest.vtu", scene, tmp_path / "a2"
    )
    assert rc == 0, err
    m = json.loads((tmp_path / "a2" / "metrics.json").read_text())
    assert "E_volume" in m and "E_rigid" not in m


def _one_line_error(rc, err):
    assert rc != 0
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("vhm-viz ")
    return lines[0]


def test_bad_inputs(demo_dir, tmp_path, capsys):
    scene = demo_dir / "scene.json"
    rest = demo_dir / "bar_rest.vtp"
    # missing input
    line = _one_line_error(
        *_with_scene(capsys, "deform", tmp_path / "nope.vtp", scene, tmp_path / "o.vtp")[::2]
    )
    assert "not found" in line
    # missing scene
    line = _one_line_error(
        *_with_scene(capsys, "deform", rest, tmp_path / "nope.json", tmp_path / "o.vtp")[::2]
    )
    assert "scene file not found" in line
    # malformed scene: wrong version, bad field
    bad = json.loads(scene.read_text())
    bad["version"] = 7
    (tmp_path / "v7.json").write_text(json.dumps(bad))
    line = _one_line_error(
        *_with_scene(capsys, "deform", rest, tmp_path / "v7.json", tmp_path / "o.vtp")[::2]
    )
    assert "'version'" in line and "unsupported version 7" in line
    bad = json.loads(scene.read_text())
    bad["constraints"]["targets"][1] = [1, 2]
    (tmp_path / "b.json").write_text(json.dumps(bad))
    line = _one_line_error(
        *_with_scene(capsys, "analyze", rest, tmp_path / "b.json", tmp_path / "a")[::2]
    )
    assert "'constraints.targets[1]'" in line
    (tmp_path / "j.json").write_text("{oops")
    line = _one_line_error(
        *_with_scene(capsys, "deform", rest, tmp_path / "j.json", tmp_path / "o.vtp")[::2]
    )
    assert "not valid JSON" in line
    # output = input (also through another spelling of the path)
    copy = tmp_path / "in.vtp"
    copy.write_bytes(rest.read_bytes())
    before = copy.read_bytes()
    for target in (copy, tmp_path / "." / "in.vtp"):
        line = _one_line_error(*_with_scene(capsys, "deform", copy, scene, target)[::2])
        assert "refusing to overwrite the input" in line
    assert copy.read_bytes() == before
    # unreadable input
    (tmp_path / "junk.vtp").write_text("not a vtk file")
    line = _one_line_error(
        *_with_scene(capsys, "deform", tmp_path / "junk.vtp", scene, tmp_path / "o.vtp")[::2]
    )
    assert "junk.vtp" in line
    assert not (tmp_path / "o.vtp").exists()


@pytest.fixture()
def poking_out(demo_dir, tmp_path):
    """The demo's bar stretched out of the top of its cage (a file), and the demo's scene."""
    mesh = pv.read(demo_dir / "bar_rest.vtp")
    mesh.points = mesh.points * np.array([1.0, 1.0, 1.2])
    big = tmp_path / "long.vtp"
    mesh.save(big)
    return big, demo_dir / "scene.json"


def test_cage_not_enclosing_the_data(poking_out, tmp_path, capsys):
    big, scene = poking_out
    mesh = pv.read(big)
    line = _one_line_error(*_with_scene(capsys, "deform", big, scene, tmp_path / "o.vtp")[::2])
    assert "outside the cage" in line and "--outside passthrough" in line
    assert not (tmp_path / "o.vtp").exists()
    rc, out, err = _run(
        capsys,
        "deform",
        big,
        "--scene",
        scene,
        "-o",
        tmp_path / "o.vtp",
        "-q",
        "--outside",
        "passthrough",
    )
    assert rc == 0, err
    n_out = int((np.asarray(mesh.points)[:, 2] > 5.2).sum())
    assert n_out > 0 and f"{n_out} points outside the cage" in out
    res = pv.read(tmp_path / "o.vtp")
    assert int(np.asarray(res.point_data["vhm_outside"]).sum()) == n_out


def test_dropped_points_of_a_tet_mesh_say_nothing_false(demo_dir, tmp_path, capsys):
    """--outside nan on a tet mesh poking out of its cage: the dropped points' det J is NaN
    and the others' the map's, with no numpy warning as a note, and the line gives no
    E_volume (the dropped points' tets have no volume) rather than 'E_volume nan'."""
    from vhm_viz.io import read_dataset

    tets = read_dataset(demo_dir / "bar_tets_rest.vtu")
    tets.points = tets.points * np.array([1.0, 1.0, 1.2])
    tets.save(tmp_path / "long.vtu")
    rc, out, err = _run(
        capsys, "deform", tmp_path / "long.vtu", "--scene", demo_dir / "scene.json",
        "-o", tmp_path / "o.vtu", "-q", "--outside", "nan", "--arrays", "det",
    )  # fmt: skip
    assert rc == 0, err
    assert err.strip() == "" and "nan" not in out.lower()
    res = pv.read(tmp_path / "o.vtu")
    dropped = np.asarray(res.point_data["vhm_outside"]) == 1
    assert dropped.any() and np.isnan(res.points[dropped]).all()
    det = np.asarray(res.point_data["jacobian_determinant"])
    assert np.isnan(det[dropped]).all()
    scene = Scene.load(demo_dir / "scene.json")
    hm = scene.solve_map(tets).harmonic_map
    kept = np.asarray(tets.points)[~dropped]
    assert det[~dropped] == pytest.approx(np.linalg.det(hm.jacobian(kept)), rel=1e-9)


def test_points_on_the_cage_edges_and_vertices_deform(tmp_path, capsys):
    """A point cloud that touches its cage at vertices and edges (the cage made from the
    data's own box): every point deforms, with the Jacobian the map takes just inside,
    whichever side of the surface rounding put it."""
    from conftest import box_cage

    v, f = box_cage((0, 0, 0), (1, 1, 2), 2)
    points = np.vstack([v, (v[f] + v[np.roll(f, 1, axis=1)]).reshape(-1, 3) / 2])
    pv.PolyData(points).save(tmp_path / "touching.vtp")
    scene = {
        "format": "vhm_viz.scene", "version": 1,
        "cage": {"vertices": v.tolist(), "faces": f.tolist()},
        "anchors": [[0.5, 0.5, z] for z in (0.4, 0.8, 1.2, 1.6)],
        "constraints": {
            "positions": [[0.5, 0.5, 0.4], [0.5, 0.5, 1.6]],
            "targets": [[0.5, 0.5, 0.4], [0.6, 0.5, 1.6]],
            "jacobian_points": [[0.5, 0.5, 1.6]],
            "jacobians": [[[0.98, 0, 0.2], [0, 1, 0], [-0.2, 0, 0.98]]],
        },
    }  # fmt: skip
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    rc, out, err = _run(
        capsys, "deform", tmp_path / "touching.vtp", "--scene", tmp_path / "scene.json",
        "-o", tmp_path / "o.vtp", "-q", "--arrays", "det", "--allow-folds",
    )  # fmt: skip
    assert rc == 0, err
    res = pv.read(tmp_path / "o.vtp")
    hm = Scene.load(tmp_path / "scene.json").solve_map(None).harmonic_map
    value, jac = hm.evaluate(points, order=1)[:2]
    det = np.asarray(res.point_data["jacobian_determinant"])
    assert np.isfinite(det).all() and np.isfinite(jac).all()
    assert np.allclose(res.points, value, rtol=0, atol=1e-8)
    assert np.allclose(det, np.linalg.det(jac), rtol=1e-6)


def test_the_outside_options_a_refusal_suggests_are_the_commands_own(poking_out, tmp_path, capsys):
    big, scene = poking_out
    for command, target in (("deform", tmp_path / "o.vtp"), ("analyze", tmp_path / "report")):
        line = _one_line_error(*_with_scene(capsys, command, big, scene, target)[::2])
        suggested = re.findall(r"--outside (\w+)", line)
        assert "passthrough" in suggested and ("nan" in suggested) == (command == "deform")
        for policy in suggested:  # each one the command takes
            rc, _, err = _run(capsys, command, big, "--scene", scene, "-o", target, "-q",
                              "--outside", policy)  # fmt: skip
            assert rc == 0, err


def test_a_warning_during_a_command_is_one_note_line(demo_dir, tmp_path, capsys):
    scene = json.loads((demo_dir / "scene.json").read_text())
    scene["cage"]["faces"] = [face[::-1] for face in scene["cage"]["faces"]]  # turned inward
    (tmp_path / "inward.json").write_text(json.dumps(scene))
    rc, out, err = _with_scene(
        capsys, "deform", demo_dir / "bar_rest.vtp", tmp_path / "inward.json", tmp_path / "o.vtp"
    )
    assert rc == 0, err
    assert err.splitlines() == [
        "vhm-viz: note: cage faces are oriented inward (negative signed volume); flipped them "
        "to point outward"
    ]
    assert (tmp_path / "o.vtp").exists()


def test_help_is_useful(capsys):
    for cmd in ("deform", "analyze", "demo"):
        with pytest.raises(SystemExit) as ex:
            main([cmd, "--help"])
        assert ex.value.code == 0
        out = capsys.readouterr().out
        assert "--output" in out or "-o" in out
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "deform" in out and "analyze" in out and "demo" in out


def test_console_script_runs():
    exe = Path(sys.executable).with_name("vhm-viz")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "vhm_viz.cli"]
    res = subprocess.run(
        [*cmd, "deform", "/nonexistent/x.vtp", "--scene", "s.json", "-o", "y.vtp"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 1
    assert res.stderr.strip().count("\n") == 0
    assert "input file not found" in res.stderr
