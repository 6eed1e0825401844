"""``vhm-viz analyze`` and ``deform`` on cells and folds: the analysed dataset, the cell
counts, the certificate, the fold warning; checked against brute-force signed volumes and
exact re-evaluation of the witnesses.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import box_cage, data_path

pv = pytest.importorskip("pyvista")

from vhm_viz import examples  # noqa: E402
from vhm_viz.cli import main  # noqa: E402
from vhm_viz.folds import FOLD_SPOT_SAMPLES  # noqa: E402
from vhm_viz.scene import Scene  # noqa: E402


def _run(capsys, *argv):
    rc = main(list(map(str, argv)))
    out, err = capsys.readouterr()
    return rc, out, err


def _signed_volumes(points, tets):
    x = np.asarray(points, dtype=np.float64)[tets]
    return np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]))


def _analyze(capsys, data, scene, out_dir, *extra):
    """Run ``vhm-viz analyze -q``; returns the output line, metrics.json and the dataset."""
    rc, out, err = _run(capsys, "analyze", data, "--scene", scene, "-o", out_dir, "-q", *extra)
    assert rc == 0, err
    m = json.loads((out_dir / "metrics.json").read_text())
    return out, m, pv.read(out_dir / m["analysis"])


def _moved(analysed):
    """Deformed positions of an analysed dataset (rest points + displacement)."""
    return np.asarray(analysed.points, dtype=np.float64) + analysed.point_data["displacement"]


def _scene(kind, path, **kw):
    sc = examples.bar(kind, resolution=12, **kw)
    scene = sc.scene
    if kind == "push":
        scene.solver["steps"] = 8  # the continuation of BarScenario.solve
    scene.save(path)
    return scene


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bar")
    _scene("bend-u", d / "bend.json")
    _scene("push", d / "push.json", top_height=2.5)
    points, tets = examples.bar_tets(5)
    cells = np.hstack([np.full((len(tets), 1), 4), tets]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA), points)
    grid.save(d / "bar_tets.vtu")
    examples.bar("bend-u", resolution=12).surface.save(d / "bar.vtp")
    img = pv.ImageData(dimensions=(6, 6, 26), spacing=(0.2, 0.2, 0.2), origin=(-0.5, -0.5, 0))
    img.point_data["density"] = np.arange(img.n_points, dtype=np.float32)
    img.save(d / "bar.vti")
    return d, points, tets


@pytest.mark.parametrize(
    ("data", "written", "cells"),
    [
        ("bar.vtp", "analysis.vtp", 0),
        ("bar_tets.vtu", "analysis.vtu", 3750),
        ("bar.vti", "analysis.vti", 625),
    ],
)
def test_analyze_writes_the_analysed_dataset(files, tmp_path, capsys, data, written, cells):
    d, _, _ = files
    out_dir = tmp_path / "report"
    rc, out, err = _run(
        capsys, "analyze", d / data, "--scene", d / "bend.json", "-o", out_dir, "-q"
    )
    assert rc == 0, err
    m = json.loads((out_dir / "metrics.json").read_text())
    assert m["analysis"] == written
    analysed = pv.read(out_dir / written)
    rest = pv.read(d / data)
    assert type(analysed) is type(rest) and analysed.n_points == rest.n_points
    for name in ("jacobian_determinant", "condition_number", "rotation_angle", "displacement"):
        assert name in analysed.point_data
    if cells:
        assert m["cells"]["cells"] == cells and m["cells"]["inverted"] == 0
        for name in ("cell_jacobian_determinant", "cell_condition_number", "cell_inverted"):
            assert len(analysed.cell_data[name]) == analysed.n_cells
        assert f"0 of {cells} cells inverted" in out
    else:
        assert "cells" not in m
    assert not [p for p in out_dir.iterdir() if p.name.startswith(".")]  # atomic writes


def test_e_volume_of_a_solid_mesh_is_the_volume_it_fills(files, tmp_path, capsys):
    """E_volume of a tet mesh counts each tet with its rest orientation (a mesh stored with
    the other corner order fills the same volume), and of voxel cells their deformed
    volume, not the axis-aligned box a voxel cell stands for: both against numpy's volumes
    of the deformed Kuhn tets."""
    d, points, tets = files
    analysed = _analyze(capsys, d / "bar_tets.vtu", d / "bend.json", tmp_path / "a")[2]
    moved = _moved(analysed)
    v0, v1 = _signed_volumes(points, tets).sum(), _signed_volumes(moved, tets).sum()
    expected = abs(v1 - v0) / v0
    assert expected > 0.01
    flipped = tets[:, [1, 0, 2, 3]]
    cells = np.hstack([np.full((len(tets), 1), 4), flipped]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA), points)
    grid.save(tmp_path / "flipped.vtu")
    img = pv.ImageData(dimensions=(6, 6, 26), spacing=(0.2, 0.2, 0.2), origin=(-0.5, -0.5, 0))
    voxels = img.cast_to_unstructured_grid()
    assert set(voxels.celltypes) == {pv.CellType.VOXEL}
    voxels.save(tmp_path / "voxels.vtu")
    for name, rel in (("flipped.vtu", 1e-9), ("voxels.vtu", 0.02)):
        out, m, _ = _analyze(capsys, tmp_path / name, d / "bend.json", tmp_path / name[:-4])
        assert m["E_volume"] == pytest.approx(expected, rel=rel), name
        assert "E_volume" in out


def test_deformed_voxel_cells_become_hexahedra(files, tmp_path, capsys):
    """A voxel (pixel) cell stands for an axis-aligned box (rectangle); moved, it is written
    as the hexahedron (quad) with the same corners, which VTK measures as what it is:
    the deformed grid's volume against numpy's volumes of the deformed Kuhn tets, and a
    slab of pixels' area against numpy's areas of its triangles."""
    d, points, tets = files
    img = pv.ImageData(dimensions=(6, 6, 26), spacing=(0.2, 0.2, 0.2), origin=(-0.5, -0.5, 0))
    voxels = img.cast_to_unstructured_grid()
    sheet = pv.ImageData(dimensions=(6, 1, 26), spacing=(0.2, 0.2, 0.2), origin=(-0.5, 0, 0))
    pixels = sheet.cast_to_unstructured_grid()
    assert set(pixels.celltypes) == {pv.CellType.PIXEL}
    for name, grid in (("voxels", voxels), ("pixels", pixels)):
        grid.save(tmp_path / f"{name}.vtu")
        rc, _, err = _run(
            capsys, "deform", tmp_path / f"{name}.vtu", "--scene", d / "bend.json",
            "-o", tmp_path / f"{name}_bent.vtu", "-q", "--arrays", "displacement",
        )  # fmt: skip
        assert rc == 0, err
    bent = pv.read(tmp_path / "voxels_bent.vtu")
    assert set(bent.celltypes) == {pv.CellType.HEXAHEDRON}
    assert set(pv.read(tmp_path / "voxels.vtu").celltypes) == {pv.CellType.VOXEL}  # input kept
    # the same lattice's points as the bar's tets: map them through the written points
    key = {tuple(np.round(p, 9)): i for i, p in enumerate(np.asarray(voxels.points))}
    moved = np.asarray(bent.points)[[key[tuple(np.round(p, 9))] for p in points]]
    expected = _signed_volumes(moved, tets).sum() / 6.0
    assert bent.volume == pytest.approx(expected, rel=0.01)
    flat = pv.read(tmp_path / "pixels_bent.vtu")
    assert set(flat.celltypes) == {pv.CellType.QUAD}
    q = flat.cells_dict[pv.CellType.QUAD]
    x = np.asarray(flat.points)
    # a quad's corners run around it: its two triangles (0, 1, 2), (0, 2, 3) cover it
    tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    e = x[tri]
    area = 0.5 * np.linalg.norm(np.cross(e[:, 1] - e[:, 0], e[:, 2] - e[:, 0]), axis=1).sum()
    assert flat.area == pytest.approx(area, rel=0.01)
    assert area == pytest.approx(1.0 * 5.0, rel=0.1)


def test_analyze_certifies_the_bend(files, tmp_path, capsys):
    d, _, _ = files
    out_dir = tmp_path / "cert"
    rc, out, err = _run(
        capsys,
        "analyze",
        d / "bar_tets.vtu",
        "--scene",
        d / "bend.json",
        "-o",
        out_dir,
        "-q",
        "--certify",
    )
    assert rc == 0, err
    inj = json.loads((out_dir / "metrics.json").read_text())["injectivity"]
    assert inj["certified"] is True and inj["status"] == "certified"
    assert inj["witnesses"] == [] and inj["undecided"] == 0 and inj["cubes"] > 0
    assert inj["region"]["kind"] == "tetrahedra"
    assert (out_dir / "injectivity.png").stat().st_size > 5000
    assert "certified injective" in out


def test_a_point_clouds_certificate_says_which_points_it_leaves_out(files, tmp_path, capsys):
    """A point cloud bounds no solid: the certificate covers the cage's interior less a
    margin, and the line and metrics.json say how many points lie nearer the cage."""
    from vhm_viz.core.certify import default_margin
    from vhm_viz.scene import Scene

    d, points, _ = files
    cage = Scene.load(d / "bend.json").build_cage()
    faces = np.hstack([np.full((len(cage.faces), 1), 3), cage.faces]).ravel()
    surface = pv.PolyData(cage.vertices, faces).compute_normals(cell_normals=True)
    # the bar's points, and points a third of the margin inside the cage's faces
    near = surface.cell_centers().points - surface.cell_data["Normals"] * default_margin(cage) / 3
    points = np.vstack([points, near])
    cloud = tmp_path / "bar.xyz"
    np.savetxt(cloud, points)
    out, m, _ = _analyze(capsys, cloud, d / "bend.json", tmp_path / "cloud", "--certify")
    inj = m["injectivity"]
    assert inj["region"]["kind"] == "cage"
    # the independent count: VTK's signed distance to the cage (negative inside)
    distance = pv.PolyData(points).compute_implicit_distance(surface)
    deep = np.asarray(distance["implicit_distance"]) <= -inj["region"]["margin"]
    left_out = int(np.count_nonzero(~deep))
    assert inj["points_not_covered"] == left_out > 0
    assert f"({left_out} of {len(points)} points nearer the cage, not covered)" in out


def test_analyze_finds_the_fold_and_counts_its_cells(files, tmp_path, capsys):
    d, points, tets = files
    out, m, analysed = _analyze(
        capsys, d / "bar_tets.vtu", d / "push.json", tmp_path / "fold", "--certify"
    )
    moved = _moved(analysed)
    brute = int(np.count_nonzero(_signed_volumes(moved, tets) <= 0))
    assert m["cells"]["inverted"] == brute > 0
    assert int(np.asarray(analysed.cell_data["cell_inverted"]).sum()) == brute
    inj = m["injectivity"]
    assert inj["status"] == "not injective" and inj["certified"] is False
    dfm = Scene.load(d / "push.json").build()
    Scene.load(d / "push.json").solve(dfm)
    det = np.linalg.det(dfm.harmonic_map.jacobian(np.array(inj["witnesses"])))
    assert np.all(det <= 0)
    assert np.allclose(det, inj["witness_determinants"], atol=1e-9)
    assert f"{brute} of {len(tets)} cells inverted" in out and "not injective" in out


def test_analyze_out_of_budget_is_undecided(files, tmp_path, capsys):
    d, _, _ = files
    out_dir = tmp_path / "budget"
    rc, out, err = _run(
        capsys, "analyze", d / "bar.vti", "--scene", d / "bend.json", "-o", out_dir, "-q",
        "--certify", "--max-cubes", "40",
    )  # fmt: skip
    assert rc == 0, err
    inj = json.loads((out_dir / "metrics.json").read_text())["injectivity"]
    assert inj["status"] == "undecided" and inj["certified"] is False
    assert inj["cubes"] == 40 and inj["undecided"] > 0 and inj["region"]["kind"] == "box"
    rc, _, err = _run(
        capsys, "analyze", d / "bar.vti", "--scene", d / "bend.json", "-o", out_dir, "-q",
        "--certify", "--max-cubes", "0",
    )  # fmt: skip
    assert rc != 0 and "--max-cubes" in err


@pytest.mark.parametrize("far", [1e20, 1e300])
def test_analyze_slices_inside_the_cage_past_a_far_stray_point(files, tmp_path, far):
    # a scan's stray point far outside the cage, left in place: the Figure 4 slice is
    # taken inside the cage, not on a grid stretched to the stray point (an empty slice,
    # or VTK's implicit distance crashing the process)
    d = files[0]
    surface = pv.read(d / "bar.vtp")
    surface.points[0] = [far, 0.0, 0.0]
    surface.save(tmp_path / "stray.vtp")
    out_dir = tmp_path / "report"
    proc = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", "analyze", str(tmp_path / "stray.vtp"), "--scene",
         str(d / "bend.json"), "-o", str(out_dir), "-q", "--outside", "passthrough"],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    m = json.loads((out_dir / "metrics.json").read_text())
    assert m["points_outside_cage"] == 1
    det = m["slice"]["jacobian_determinant"]
    assert 0 < det["min"] <= det["max"] < 10


def test_rigidity_leaves_out_triangles_touching_a_point_left_outside_the_cage(files, tmp_path):
    # the stray point's triangles are stretched by the distance to it, not by the map: the
    # measure is that of the same surface without them
    d = files[0]
    surface = pv.read(d / "bar.vtp")
    surface.points[0] = [1e20, 0.0, 0.0]
    surface.save(tmp_path / "stray.vtp")
    tris = surface.faces.reshape(-1, 4)[:, 1:]
    touching = (tris == 0).any(axis=1)
    surface.remove_cells(np.flatnonzero(touching)).save(tmp_path / "cut.vtp")
    metrics, lines = {}, {}
    for name in ("stray", "cut"):
        proc = subprocess.run(
            [sys.executable, "-m", "vhm_viz.cli", "analyze", str(tmp_path / f"{name}.vtp"),
             "--scene", str(d / "bend.json"), "-o", str(tmp_path / name), "--outside",
             "passthrough"],
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        assert "overflow" not in proc.stderr
        metrics[name] = json.loads((tmp_path / name / "metrics.json").read_text())
        lines[name] = proc.stdout
    stray, cut = metrics["stray"], metrics["cut"]
    assert stray["triangles_left_out"] == int(touching.sum()) and "triangles_left_out" not in cut
    assert stray["E_rigid"] == pytest.approx(cut["E_rigid"], rel=1e-9)
    assert "E_volume" not in stray  # the surface without them is not closed
    said = f"{int(touching.sum())} triangles touching points outside the cage left out"
    assert said in lines["stray"] and "left out" not in lines["cut"]


def test_analyze_never_overwrites_its_input(files, tmp_path, capsys):
    d, _, _ = files
    out_dir = tmp_path / "same"
    out_dir.mkdir()
    data = out_dir / "analysis.vtu"
    data.write_bytes((d / "bar_tets.vtu").read_bytes())
    before = data.read_bytes()
    rc, _, err = _run(capsys, "analyze", data, "--scene", d / "bend.json", "-o", out_dir, "-q")
    assert rc != 0 and "refusing to overwrite" in err
    assert data.read_bytes() == before


def test_deform_refuses_a_folded_output_unless_allowed(files, tmp_path, capsys):
    d, points, tets = files
    # by default a folded result is an error: one line saying how much, exit status 4,
    # nothing written
    refused = _run(capsys, "deform", d / "bar_tets.vtu", "--scene", d / "push.json",
                   "-o", tmp_path / "f.vtu", "-q")  # fmt: skip
    assert refused[0] == 4 and refused[1].strip() == "" and not (tmp_path / "f.vtu").exists()
    error = [ln for ln in refused[2].splitlines() if ln.strip()]
    assert len(error) == 1 and error[0].startswith("vhm-viz deform: error: the deformation folds")
    assert error[0].endswith("pass --allow-folds to write it anyway)")
    # --allow-folds writes it, with the same counts as a warning
    rc, out, err = _run(
        capsys,
        "deform",
        d / "bar_tets.vtu",
        "--scene",
        d / "push.json",
        "-o",
        tmp_path / "f.vtu",
        "-q",
        "--allow-folds",
    )
    assert rc == 0, err
    assert len(out.strip().splitlines()) == 1
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("vhm-viz deform: warning: the deformation folds")
    bent = pv.read(tmp_path / "f.vtu")
    brute = int(np.count_nonzero(_signed_volumes(bent.points, tets) <= 0))
    assert f"{brute} of {len(tets)} cells inverted" in lines[0]
    assert lines[0].removeprefix("vhm-viz deform: warning: ") in error[0]
    # beside the check of every cell, a spot check of the exact map at evenly spread points
    spot = re.search(r"det J <= 0 at (\d+) of (\d+) sampled points \(worst \S+ at \(", lines[0])
    assert spot, lines[0]
    assert 0 < int(spot[1]) < int(spot[2]) == min(FOLD_SPOT_SAMPLES, len(points))
    rc, out, err = _run(
        capsys, "deform", d / "bar_tets.vtu", "--scene", d / "bend.json", "-o", tmp_path / "b.vtu",
        "-q", "--arrays", "cells",
    )  # fmt: skip
    assert rc == 0 and err.strip() == ""  # no fold, no warning
    assert "cell_jacobian_determinant" in pv.read(tmp_path / "b.vtu").cell_data


@pytest.mark.parametrize(("scene", "which"), [("bend", "all"), ("push", "some")])
def test_fold_line_counts_the_inverted_cells_that_straddle_the_cage(files, tmp_path, capsys,
                                                                    scene, which):  # fmt: skip
    # a tet mesh longer than the cage, its far end left in place (--outside passthrough):
    # the tets across the cage's end span the map and the identity, and the line says how
    # many of the inverted cells those are, as the output's signed volumes and outside
    # flags count them
    d, points, tets = files
    longer = np.asarray(points, dtype=np.float64) * [1.0, 1.0, 1.3]
    cells = np.hstack([np.full((len(tets), 1), 4), tets]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA), longer)
    grid.save(tmp_path / "longer.vtu")
    argv = ["deform", tmp_path / "longer.vtu", "--scene", d / f"{scene}.json", "-o",
            tmp_path / "o.vtu", "-q", "--outside", "passthrough"]  # fmt: skip
    rc, _, refused = _run(capsys, *argv)
    assert rc == 4
    rc, _, err = _run(capsys, *argv, "--allow-folds")
    assert rc == 0, err
    out = pv.read(tmp_path / "o.vtu")
    inverted = _signed_volumes(out.points, tets) <= 0
    straddling = inverted & (np.asarray(out.point_data["vhm_outside"])[tets] != 0).any(axis=1)
    every = straddling.sum() == inverted.sum()
    assert straddling.any() and every == (which == "all")
    count = "all" if every else int(straddling.sum())
    said = f"{int(inverted.sum())} of {len(tets)} cells inverted ("
    assert said in err and said in refused
    said = f", {count} of them straddling the cage (their points outside it left in place"
    assert said in err and said in refused
    # without points left outside, the line says nothing of straddling
    rc, _, err = _run(capsys, "deform", d / "bar_tets.vtu", "--scene", d / "push.json",
                      "-o", tmp_path / "p.vtu", "-q", "--allow-folds")  # fmt: skip
    assert rc == 0 and "cells inverted" in err and "straddling" not in err


def test_surface_fold_warning_samples_the_exact_det(files, tmp_path, capsys):
    # a surface has no cells to measure: det J is sampled at points; the worst sample
    # named is det J there, as central differences of the solved map give it
    from vhm_viz.folds import fold_samples

    d, _, _ = files
    rc, out, err = _run(
        capsys, "deform", d / "bar.vtp", "--scene", d / "push.json", "-o", tmp_path / "s.vtp", "-q",
        "--allow-folds",
    )  # fmt: skip
    assert rc == 0, err
    found = re.search(
        r"det J <= 0 at (\d+) of (\d+) sampled points \(worst (\S+) at \((\S+), (\S+), (\S+)\)",
        err,
    )
    assert found, err
    bad, sampled = int(found[1]), int(found[2])
    assert 0 < bad < sampled == fold_samples(pv.read(d / "bar.vtp").n_points)
    worst, at = float(found[3]), np.array([float(found[k]) for k in (4, 5, 6)])
    dfm = Scene.load(d / "push.json").build()
    Scene.load(d / "push.json").solve(dfm)
    h = 1e-5
    steps = np.vstack([at + h * np.eye(3), at - h * np.eye(3)])
    f = dfm.harmonic_map.map(steps)
    jac = (f[:3] - f[3:]).T / (2 * h)  # column j: d f / d x_j
    # printed to 3 significant digits, at a position printed to 4
    assert np.linalg.det(jac) == pytest.approx(worst, rel=5e-3, abs=1e-4)


def _dragon_scene(path, degrees=66.0):
    """The dragon held at one end, the other end swung by ``degrees`` about y (box cage)."""
    mesh = pv.read(data_path("tets", "dragon.tet.vtk"))
    p = np.asarray(mesh.points)
    lo, hi = p.min(0), p.max(0)
    c = (lo + hi) / 2

    def nearest(q):
        return p[np.argmin(np.linalg.norm(p - q, axis=1))]

    held = [nearest([lo[0] + 0.05, c[1], c[2]]), nearest([lo[0] + 0.25, c[1] + 0.1, c[2]]),
            nearest([lo[0] + 0.25, c[1] - 0.1, c[2]])]  # fmt: skip
    moved = nearest([hi[0] - 0.08, c[1], c[2] + 0.1])
    rot = examples.rotation("y", -degrees)
    v, f = box_cage(lo - 0.1, hi + 0.1, 3)
    along = np.linspace(0.15, 0.85, 8)[:, None] * [1, 0, 0] + [0, 0.5, 0.5]
    scene = Scene(
        cage={"vertices": v, "faces": f},
        anchors={"points": np.array([nearest(lo + (hi - lo) * t) for t in along])},
        constraints={
            "positions": np.vstack([held, moved]),
            "targets": np.vstack([held, c + rot @ (moved - c)]),
            "jacobian_points": moved[None],
            "jacobians": rot[None],
        },
    )
    scene.solver["steps"] = 4
    scene.save(path)


def test_analyze_dragon_tet_mesh_reports_inverted_cells(tmp_path, capsys):
    src = data_path("tets", "dragon.tet.vtk")
    _dragon_scene(tmp_path / "dragon.json")
    out, m, analysed = _analyze(capsys, src, tmp_path / "dragon.json", tmp_path / "d", "--certify")
    rest = pv.read(src)
    tets = np.asarray(rest.cells_dict[pv.CellType.TETRA])
    ratio = _signed_volumes(_moved(analysed), tets) / _signed_volumes(rest.points, tets)
    assert m["cells"]["cells"] == rest.n_cells == 104261
    assert m["cells"]["inverted"] == int(np.count_nonzero(ratio <= 0)) > 0
    assert m["cells"]["rest_inverted"] == 0
    assert np.allclose(
        analysed.cell_data["cell_jacobian_determinant"], ratio, rtol=1e-8, atol=1e-10
    )
    assert int(np.asarray(analysed.cell_data["cell_inverted"]).sum()) == m["cells"]["inverted"]
    assert m["injectivity"]["status"] == "not injective"
    assert f"{m['cells']['inverted']} of 104261 cells inverted" in out
