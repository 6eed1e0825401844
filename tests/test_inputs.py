"""Inputs are never written, malformed files never crash, every volume format is read.

Three parts: outputs that name an input, malformed files, and volume formats (read in the
frame their headers state). The crash cases run real processes: the command line, or the
forked reader.
"""

from __future__ import annotations

import base64
import gzip
import json
import os
import re
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from conftest import box_cage, data_path, subprocess_env  # noqa: E402

from vhm_viz import examples  # noqa: E402
from vhm_viz.cli import main  # noqa: E402
from vhm_viz.io import ReadError, read_dataset, write_cage  # noqa: E402


def run_cli(*args) -> subprocess.CompletedProcess:
    """``python -m vhm_viz.cli ARGS`` in a real process (a crash shows as its status)."""
    env = subprocess_env()
    return subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", *map(str, args)],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )


def box_scene(folder: Path, lo, hi, name="scene.json", **extra) -> Path:
    """A scene with a box cage around [lo, hi] (12 % margin) and the identity as target."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pad = 0.12 * (hi - lo)
    v, f = box_cage(lo - pad, hi + pad, divisions=2)
    centre = 0.5 * (lo + hi)
    anchors = centre + 0.2 * (hi - lo) * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    scene = {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": {"vertices": v.tolist(), "faces": f.tolist()},
        "anchors": anchors.tolist(),
        "constraints": {"positions": [centre.tolist()], "targets": [(centre + 0.01).tolist()]},
        **extra,
    }
    path = folder / name
    path.write_text(json.dumps(scene))
    return path


@pytest.fixture(scope="module")
def bar_case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("guard")
    sc = examples.bar("bend-u", resolution=8)
    sc.surface.save(folder / "bar.vtp")
    write_cage(folder / "cage.obj", sc.cage)
    (folder / "anchors.json").write_text(json.dumps({"anchors": sc.anchors.tolist()}))
    d = sc.scene.to_dict()
    d["cage"] = "cage.obj"
    d["anchors"] = "anchors.json"
    (folder / "scene.json").write_text(json.dumps(d))
    return folder


def _bytes(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


# ------------------------------------------------------------------ outputs onto inputs
def test_outputs_naming_an_input_are_refused(bar_case, tmp_path, capsys):
    f = bar_case
    before = _bytes(f)
    deform = ["deform", str(f / "bar.vtp"), "-s", str(f / "scene.json"), "-q", "-o"]
    # the cage the scene references, through a plain path and through a symbolic link
    os.symlink(f / "cage.obj", tmp_path / "link.obj")
    # the data through a hard link
    os.link(f / "bar.vtp", tmp_path / "hard.vtp")
    for target in (f / "cage.obj", tmp_path / "link.obj", tmp_path / "hard.vtp", f / "bar.vtp"):
        assert main([*deform, str(target)]) == 1
        err = capsys.readouterr().err
        assert "refusing to overwrite the input file" in err and err.count("\n") == 1
    # the scene file itself, under a VTK suffix
    (tmp_path / "scene.vtk").write_bytes((f / "scene.json").read_bytes())
    kept = (tmp_path / "scene.vtk").read_bytes()
    assert main(["deform", str(f / "bar.vtp"), "-s", str(tmp_path / "scene.vtk"), "-q",
                 "-o", str(tmp_path / "scene.vtk")]) == 1  # fmt: skip
    assert "refusing to overwrite" in capsys.readouterr().err
    assert (tmp_path / "scene.vtk").read_bytes() == kept
    assert _bytes(f) == before


def test_polylines_file_of_the_scene_is_refused(bar_case, tmp_path, capsys):
    sc = examples.bar("bend-u", resolution=8)
    centre = np.column_stack([np.zeros(11), np.zeros(11), np.linspace(0.3, 4.7, 11)])
    lines = "OFF\n11 0 10\n" + "".join(f"{x} {y} {z}\n" for x, y, z in centre)
    lines += "".join(f"2 {i} {i + 1}\n" for i in range(10))
    (tmp_path / "lines.vtk").write_text(lines)  # an OFF file named .vtk: read by suffix? no
    (tmp_path / "lines.off").write_text(lines)
    d = sc.scene.to_dict()
    d["anchors"] = {"polylines": "lines.off", "count": 6}
    (tmp_path / "scene.json").write_text(json.dumps(d))
    assert main(["deform", str(bar_case / "bar.vtp"), "-s", str(tmp_path / "scene.json"), "-q",
                 "-o", str(tmp_path / "lines.off")]) == 1  # fmt: skip
    assert "refusing to overwrite the input file" in capsys.readouterr().err
    assert (tmp_path / "lines.off").read_text() == lines


def test_analyze_never_writes_a_report_file_over_an_input(bar_case, tmp_path, capsys):
    """The scene's anchors file sits in the report folder under a report file's name."""
    report = tmp_path / "report"
    report.mkdir()
    sc = examples.bar("bend-u", resolution=8)
    anchors = report / "metrics.json"
    anchors.write_text(json.dumps({"anchors": sc.anchors.tolist()}))
    kept = anchors.read_bytes()
    d = sc.scene.to_dict()
    d["anchors"] = "report/metrics.json"
    (tmp_path / "scene.json").write_text(json.dumps(d))
    rc = main(["analyze", str(bar_case / "bar.vtp"), "-s", str(tmp_path / "scene.json"), "-q",
               "-o", str(report)])  # fmt: skip
    assert rc == 1
    assert "refusing to overwrite the input file" in capsys.readouterr().err
    assert anchors.read_bytes() == kept and sorted(os.listdir(report)) == ["metrics.json"]


def test_explorer_export_never_overwrites_what_it_read(bar_case, tmp_path):
    from vhm_viz.app.controller import ExplorerController
    from vhm_viz.io import OverwriteError

    data = tmp_path / "bar.vtp"
    data.write_bytes((bar_case / "bar.vtp").read_bytes())
    kept = data.read_bytes()
    ctrl = ExplorerController()
    ctrl.load_file(data)
    ctrl.load_cage(bar_case / "cage.obj")
    with pytest.raises(OverwriteError, match="refusing to overwrite"):
        ctrl.export(data)
    with pytest.raises(OverwriteError):
        ctrl.export(bar_case / "cage.obj")
    assert data.read_bytes() == kept


# ------------------------------------------------------------------ malformed files
@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """The bar surface in PLY (binary, ASCII) and legacy VTK (binary, ASCII), and a scene."""
    folder = tmp_path_factory.mktemp("malformed")
    mesh = pv.read(data_path("bar", "bar_dense.obj"))
    mesh.point_data["s"] = np.arange(mesh.n_points, dtype=float)
    mesh.save(folder / "bin.ply", binary=True)
    mesh.save(folder / "ascii.ply", binary=False)
    mesh.save(folder / "bin.vtk", binary=True)
    mesh.save(folder / "ascii.vtk", binary=False)
    box_scene(folder, mesh.bounds[0::2], mesh.bounds[1::2])
    return folder


def _truncate(src: Path, dst: Path, fraction: float) -> Path:
    blob = src.read_bytes()
    dst.write_bytes(blob[: int(len(blob) * fraction)])
    return dst


def test_truncated_binary_ply_is_an_error_not_a_crash(models, tmp_path):
    bad = _truncate(models / "bin.ply", tmp_path / "cut.ply", 0.5)
    res = run_cli("deform", bad, "-s", models / "scene.json", "-o", tmp_path / "o.vtp", "-q")
    # VTK's PLY reader dereferences the header's counts: the checks must come first
    assert res.returncode == 1, res.stderr
    assert res.stderr.count("\n") == 1 and "truncated" in res.stderr
    assert not (tmp_path / "o.vtp").exists()


@pytest.mark.parametrize("name", ["bin.ply", "ascii.ply", "bin.vtk", "ascii.vtk"])
@pytest.mark.parametrize("fraction", [0.01, 0.2, 0.5, 0.9, 0.999])
def test_truncated_files_are_refused_never_read_as_point_clouds(models, tmp_path, name, fraction):
    bad = _truncate(models / name, tmp_path / f"cut{Path(name).suffix}", fraction)
    # VTK's legacy reader returns what it got from a truncated file (points with garbage
    # past the cut, some cells) without an error
    with pytest.raises(ReadError, match="truncated|corrupt|cannot read"):
        read_dataset(bad)


def test_truncated_legacy_vtk_exits_1_through_the_command_line(models, tmp_path):
    bad = _truncate(models / "ascii.vtk", tmp_path / "cut.vtk", 0.5)
    res = run_cli("deform", bad, "-s", models / "scene.json", "-o", tmp_path / "o.vtp", "-q")
    assert res.returncode == 1 and "truncated" in res.stderr, res.stderr
    assert not (tmp_path / "o.vtp").exists()


@pytest.mark.parametrize(
    ("name", "said"),
    [
        ("ascii.ply", r"element 'face' lists 12288 rows, the file ends after \d+"),
        ("ascii.vtk", r"[A-Z]+ \w+ lists \d+ values, the file ends after \d+"),
        ("points.off", r"the header lists 6146 points, the file ends after \d+"),
        ("faces.off", r"the header lists 12288 faces, the file ends after \d+"),
    ],
)
def test_text_files_cut_short_say_what_they_list_and_hold(models, tmp_path, name, said):
    """One wording for a count the file does not hold, whatever the text format."""
    if name.endswith(".off"):
        mesh = pv.read(models / "ascii.ply")
        faces = mesh.faces.reshape(-1, 4)[:, 1:]
        text = (f"OFF\n{mesh.n_points} {len(faces)} 0\n"
                + "".join(f"{x} {y} {z}\n" for x, y, z in mesh.points)
                + "".join(f"3 {a} {b} {c}\n" for a, b, c in faces))  # fmt: skip
        (tmp_path / "whole.off").write_text(text)
        bad = _truncate(
            tmp_path / "whole.off", tmp_path / "cut.off", 0.3 if "points" in name else 0.9
        )
    else:
        bad = _truncate(models / name, tmp_path / f"cut{Path(name).suffix}", 0.7)
    with pytest.raises(ReadError) as err:
        read_dataset(bad)
    assert re.fullmatch(re.escape(f"{bad}: truncated: ") + said + "; copy or export it again",
                        str(err.value)), err.value  # fmt: skip


def test_an_error_vtk_reports_is_the_same_line_in_every_command(models, tmp_path):
    """VTK's reader refusing a file (an OBJ cut inside a face line) is one line of ours --
    not VTK's source file, line and object address, nor 'no points' where the command
    line had silenced VTK's messages."""
    mesh = pv.read(models / "ascii.ply")
    faces = mesh.faces.reshape(-1, 4)[:, 1:]
    text = ("".join(f"v {x} {y} {z}\n" for x, y, z in mesh.points)
            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))  # fmt: skip
    bad = tmp_path / "cut.obj"
    bad.write_text(text[: len(text) - 5])  # inside the last face line
    said = f"{bad}: not a valid .obj file (Definition of a face needs at least 3 vertices"
    with pytest.raises(ReadError) as err:
        read_dataset(bad)
    assert str(err.value).startswith(said), err.value
    for argv in (("deform", bad, "-s", models / "scene.json", "-o", tmp_path / "o.vtp"),
                 ("cage", bad, "-o", tmp_path / "c.obj")):  # fmt: skip
        res = run_cli(*argv, "-q")
        assert res.returncode == 1 and res.stderr.count("\n") == 1, res.stderr
        assert said in res.stderr and "0x" not in res.stderr and ".cxx" not in res.stderr


@pytest.mark.parametrize("suffix", [".vtp", ".vtu"])
def test_a_vtk_xml_file_cut_short_says_so(models, tmp_path, suffix):
    mesh = pv.read(models / "bin.vtk")
    whole = tmp_path / f"whole{suffix}"
    (mesh if suffix == ".vtp" else mesh.cast_to_unstructured_grid()).save(whole)
    bad = _truncate(whole, tmp_path / f"cut{suffix}", 0.6)
    said = f"{bad}: truncated: the file ends inside its VTKFile element; copy or export it again"
    with pytest.raises(ReadError) as err:
        read_dataset(bad)
    assert str(err.value) == said
    res = run_cli("cage", bad, "-o", tmp_path / "c.obj", "-q")
    assert res.returncode == 1 and res.stderr == f"vhm-viz cage: error: {said}\n", res.stderr


def test_an_ascii_stl_or_gzip_cut_short_says_to_copy_it_again(tmp_path):
    # the remedy every other file cut short gives
    pv.Sphere().save(tmp_path / "whole.stl", binary=False)
    nii = data_path("volumes", "avg152T1_RL_nifti.nii.gz")
    for whole, said in (
        (tmp_path / "whole.stl", "truncated ASCII STL (no 'endsolid' at the end)"),
        (nii, "truncated or corrupt gzip data ("),
    ):
        bad = _truncate(whole, tmp_path / f"cut{''.join(whole.suffixes)}", 0.5)
        with pytest.raises(ReadError) as err:
            read_dataset(bad)
        assert str(err.value).startswith(f"{bad}: {said}"), err.value
        assert str(err.value).endswith("; copy or export it again"), err.value


def test_a_vtk_xml_file_of_broken_xml_is_one_line_of_ours(models, tmp_path):
    pv.read(models / "bin.vtk").save(tmp_path / "whole.vtp")
    blob = (tmp_path / "whole.vtp").read_bytes()
    bad = tmp_path / "broken.vtp"
    bad.write_bytes(blob.replace(b"<Piece", b"<Pie<ce", 1))
    with pytest.raises(ReadError) as err:
        read_dataset(bad)
    assert str(err.value).startswith(f"{bad}: not a valid .vtp file (Error parsing"), err.value
    assert ".cxx" not in str(err.value)


def test_ply_with_a_corrupt_vertex_index_is_refused(models, tmp_path):
    mesh = pv.read(models / "bin.ply")
    blob = bytearray((models / "bin.ply").read_bytes())
    # last face's last index (int32, little endian) set to a vertex that does not exist
    struct.pack_into("<i", blob, len(blob) - 4, mesh.n_points + 1000)
    (tmp_path / "bad.ply").write_bytes(bytes(blob))
    with pytest.raises(ReadError, match="refers to vertex"):
        read_dataset(tmp_path / "bad.ply")


def test_empty_off_is_one_clear_line_and_nothing_else(models, tmp_path):
    (tmp_path / "empty.off").write_text("")
    res = run_cli("deform", tmp_path / "empty.off", "-s", models / "scene.json",
                  "-o", tmp_path / "o.vtp", "-q")  # fmt: skip
    # meshio prints its complaint and calls sys.exit: neither may reach the user
    assert res.returncode == 1
    assert res.stdout == ""
    assert res.stderr.count("\n") == 1 and "empty.off: empty file (0 bytes)" in res.stderr


def test_meshio_sys_exit_and_prints_become_one_error(tmp_path, capsys):
    (tmp_path / "bad.mesh").write_text("MeshVersionFormatted 1\nDimension 3\nVertices\n12\n1 2")
    with pytest.raises(ReadError, match="bad.mesh"):
        read_dataset(tmp_path / "bad.mesh")
    out, err = capsys.readouterr()
    assert out == "" and err == ""


def _hand_mesh_cut(folder: Path, name: str, lines: int, tail: str = "") -> Path:
    """The first ``lines`` lines of the tet hand (MEDIT), then ``tail``."""
    text = data_path("hand_tet", "hand.mesh").read_text().splitlines(keepends=True)
    (folder / name).write_text("".join(text[:lines]) + tail)
    return folder / name


# hand.mesh: Vertices (7234) on lines 5-7238, Tetrahedra (29998) from line 16799
@pytest.mark.parametrize(
    ("lines", "tail", "block", "announced", "held"),
    [
        (3000, "", "Vertices", 7234, 2996),  # cut at a line's end
        (20000, "", "Tetrahedra", 29998, 3202),
        (20000, "6612 5385 70", "Tetrahedra", 29998, 3202),  # cut inside a line
        (16798, "", "Tetrahedra", 29998, 0),
    ],
)
def test_a_medit_file_cut_short_says_which_block_lacks_entries(
    tmp_path, lines, tail, block, announced, held
):
    cut = _hand_mesh_cut(tmp_path, "cut.mesh", lines, tail)
    with pytest.raises(ReadError) as err:
        read_dataset(cut)
    msg = str(err.value)
    assert msg.startswith(f"{cut}: truncated: ") and "\n" not in msg, msg
    assert f"its {block} block lists {announced} entries, the file ends after {held}" in msg
    assert "export it again" in msg and "reshape" not in msg


def test_a_medit_count_larger_than_its_entries_is_one_line_through_the_command_line(tmp_path):
    text = data_path("hand_tet", "hand.mesh").read_text().splitlines(keepends=True)
    text[3] = "9000\n"  # the Vertices count; 7234 follow
    (tmp_path / "count.mesh").write_text("".join(text))
    cut = _hand_mesh_cut(tmp_path, "cut.mesh", 20000)
    for bad, said in ((tmp_path / "count.mesh", "corrupt: its Vertices block lists 9000 "
                       "entries but holds 7234"),
                      (cut, "truncated: its Tetrahedra block lists 29998 entries")):  # fmt: skip
        res = run_cli("cage", bad, "-o", tmp_path / "cage.obj", "-q")
        assert res.returncode == 1 and res.stdout == "", res.stderr
        assert res.stderr.count("\n") == 1 and f"{bad}: {said}" in res.stderr, res.stderr
    assert not (tmp_path / "cage.obj").exists()


@pytest.mark.parametrize("kind", ["gmsh22", "gmsh"])
@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("fraction", [0.05, 0.3, 0.6, 0.999])
def test_a_gmsh_file_cut_short_says_so(tmp_path, kind, binary, fraction):
    meshio = pytest.importorskip("meshio")
    grid = pv.ImageData(dimensions=(6, 6, 9), spacing=(0.3, 0.3, 0.3)).to_tetrahedra()
    tets = grid.cells_dict[pv.CellType.TETRA]
    whole = tmp_path / "whole.msh"
    meshio.Mesh(np.asarray(grid.points), [("tetra", tets)]).write(
        whole, file_format=kind, binary=binary
    )
    cut = _truncate(whole, tmp_path / "cut.msh", fraction)
    with pytest.raises(ReadError) as err:
        read_dataset(cut)
    msg = str(err.value)
    assert re.fullmatch(
        re.escape(f"{cut}: truncated: the file ends inside its ")
        + r"\$(Nodes|Elements) section; copy or export it again",
        msg,
    ), msg


def test_a_gmsh_count_larger_than_its_entries_is_refused(tmp_path):
    meshio = pytest.importorskip("meshio")
    grid = pv.ImageData(dimensions=(3, 3, 3)).to_tetrahedra()
    tets = grid.cells_dict[pv.CellType.TETRA]
    for kind, line in (("gmsh22", 4), ("gmsh", 4)):
        path = tmp_path / f"{kind}.msh"
        meshio.Mesh(np.asarray(grid.points), [("tetra", tets)]).write(
            path, file_format=kind, binary=False
        )
        text = path.read_text().splitlines(keepends=True)
        assert text[line - 1].startswith("$Nodes")
        head = text[line].split()
        head[-3 if kind == "gmsh" else 0] = "40"  # the node count
        text[line] = " ".join(head) + "\n"
        path.write_text("".join(text))
        with pytest.raises(ReadError) as err:
            read_dataset(path)
        assert str(err.value) == (
            f"{path}: corrupt: its $Nodes section lists 40 entries but holds 27; correct the "
            "count or export the file again"
        )


def test_a_cage_leaving_points_out_is_named_in_the_one_line(tmp_path):
    """With several cages about, the line says which one leaves the data's points out."""
    from vhm_viz import read_cage

    data = data_path("bad_cages", "armadillo_252v_for_partial_cage.obj")
    (tmp_path / "cages").mkdir()
    (tmp_path / "cages" / "partial.obj").symlink_to(
        data_path("bad_cages", "partial_armadillo_cage.obj")
    )
    points = np.asarray(pv.read(data).points)
    inside = points[read_cage(tmp_path / "cages" / "partial.obj").contains(points)]
    scene = {"format": "vhm_viz.scene", "version": 1, "cage": "cages/partial.obj",
             "anchors": inside[::25].tolist(),
             "constraints": {"positions": [inside[0].tolist()],
                             "targets": [(inside[0] + 0.01).tolist()]}}  # fmt: skip
    (tmp_path / "scene.json").write_text(json.dumps(scene))
    said = (f"{len(points) - len(inside)} of {len(points)} points of {data} are outside the "
            f"cage {tmp_path / 'cages' / 'partial.obj'} (indices ")  # fmt: skip
    for command, out in (("deform", tmp_path / "o.vtp"), ("analyze", tmp_path / "report")):
        res = run_cli(command, data, "-s", tmp_path / "scene.json", "-o", out, "-q")
        assert res.returncode == 1 and res.stderr.count("\n") == 1, res.stderr
        assert said in res.stderr and "--outside passthrough" in res.stderr, res.stderr
        assert not out.exists()


def test_a_vtu_of_triangles_keeps_its_cell_and_field_arrays(tmp_path):
    """A .vtu holding only triangles is read as the surface it is: its cell and field
    arrays come along with the point arrays, into the deformed output."""
    surf = pv.Box(bounds=(0, 1, 0, 1, 0, 2), level=2).triangulate()
    grid = surf.cast_to_unstructured_grid()
    grid.clear_data()
    grid.point_data["temperature"] = np.linspace(0.0, 1.0, grid.n_points)
    grid.cell_data["label"] = np.arange(grid.n_cells, dtype=np.int32) % 7
    grid.field_data["units"] = ["mm"]
    grid.save(tmp_path / "tris.vtu")
    read = read_dataset(tmp_path / "tris.vtu")
    assert isinstance(read, pv.PolyData) and read.n_cells == grid.n_cells
    assert np.array_equal(read.cell_data["label"], grid.cell_data["label"])
    assert np.array_equal(read.point_data["temperature"], grid.point_data["temperature"])
    assert list(read.field_data["units"]) == ["mm"]
    box_scene(tmp_path, grid.bounds[0::2], grid.bounds[1::2])
    res = run_cli("deform", tmp_path / "tris.vtu", "-s", tmp_path / "scene.json",
                  "-o", tmp_path / "bent.vtp", "-q")  # fmt: skip
    assert res.returncode == 0, res.stderr
    bent = pv.read(tmp_path / "bent.vtp")
    assert np.array_equal(bent.cell_data["label"], grid.cell_data["label"])
    assert list(bent.field_data["units"]) == ["mm"]


def test_gmsh_tet_mesh_deforms_like_its_vtu(tmp_path):
    """A Gmsh ``.msh`` tet mesh (meshio writes it) deforms to the same points and cell
    arrays as the same mesh in ``.vtu``; a malformed one is one line."""
    meshio = pytest.importorskip("meshio")
    grid = pv.ImageData(dimensions=(4, 4, 7), spacing=(0.3, 0.3, 0.3)).to_tetrahedra()
    tets = grid.cells_dict[pv.CellType.TETRA]
    meshio.Mesh(np.asarray(grid.points), [("tetra", tets)]).write(
        tmp_path / "m.msh", file_format="gmsh22", binary=False
    )
    pv.UnstructuredGrid({pv.CellType.TETRA: tets}, np.asarray(grid.points)).save(tmp_path / "m.vtu")
    box_scene(tmp_path, grid.bounds[0::2], grid.bounds[1::2])
    out = {}
    for name in ("m.msh", "m.vtu"):
        res = run_cli("deform", tmp_path / name, "-s", tmp_path / "scene.json",
                      "-o", tmp_path / f"{name}.out.vtu", "-q", "--arrays", "cells")  # fmt: skip
        assert res.returncode == 0, res.stderr
        out[name] = pv.read(tmp_path / f"{name}.out.vtu")
    assert np.allclose(out["m.msh"].points, out["m.vtu"].points, rtol=0, atol=1e-12)
    got, want = (out[n].cell_data["cell_jacobian_determinant"] for n in ("m.msh", "m.vtu"))
    assert np.allclose(got, want, rtol=1e-12)
    (tmp_path / "bad.msh").write_text("$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n3\n1 0 0\n")
    res = run_cli("deform", tmp_path / "bad.msh", "-s", tmp_path / "scene.json",
                  "-o", tmp_path / "o.vtu", "-q")  # fmt: skip
    assert res.returncode == 1 and res.stderr.count("\n") == 1 and "bad.msh" in res.stderr
    assert not (tmp_path / "o.vtu").exists()


def test_a_reader_that_crashes_takes_only_its_child_process(models):
    """If VTK crashes on a file the checks could not vet, that is an error message."""
    import ctypes

    from vhm_viz.io.isolated import read_isolated

    with pytest.raises(ReadError, match="crashed on this file .signal SIGSEGV."):
        read_isolated(models / "bin.ply", lambda p: ctypes.string_at(0), "a reader")


def test_an_image_read_in_a_child_is_the_image_vtk_reads(tmp_path):
    """The child hands an image back as its grid and arrays: all of them, where they were."""
    rng = np.random.default_rng(3)
    image = pv.ImageData()
    image.extent = (2, 9, -3, 4, 5, 10)  # an extent that does not start at 0
    image.origin = (1.5, -2.0, 0.25)
    image.spacing = (0.5, 0.75, 1.25)
    image.direction_matrix = examples.rotation("z", 30.0) @ examples.rotation("x", 10.0)
    n, c = image.n_points, image.n_cells
    image.point_data["density"] = rng.integers(-500, 3000, n).astype(np.int16)
    image.point_data["flow"] = rng.normal(size=(n, 3)).astype(np.float32)
    image.cell_data["label"] = rng.integers(0, 4, c).astype(np.uint8)
    image.point_data.active_scalars_name = "density"
    path = tmp_path / "offset.vti"
    image.save(path)
    got, vtk = read_dataset(path), pv.read(path)  # ours went through a child
    assert tuple(got.extent) == tuple(vtk.extent) == (2, 9, -3, 4, 5, 10)
    np.testing.assert_array_equal(got.points, vtk.points)  # the same physical points
    np.testing.assert_array_equal(got.direction_matrix, vtk.direction_matrix)
    assert got.active_scalars_name == "density"
    for part, ref in ((got.point_data, vtk.point_data), (got.cell_data, vtk.cell_data)):
        assert list(part.keys()) == list(ref.keys())
        for name in ref.keys():
            assert part[name].dtype == ref[name].dtype
            np.testing.assert_array_equal(part[name], ref[name])


def test_work_handed_to_a_read_runs_once_while_the_child_reads(tmp_path):
    children = Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children")
    if not children.exists():
        pytest.skip("no /proc/.../children here")
    seen = []

    def work():
        seen.append(set(children.read_text().split()))  # this process's children, now

    before = set(children.read_text().split())  # (earlier tests may have left some)
    read_dataset(data_path("volumes", "headsq_64x64x93.vti"), meanwhile=work)
    assert len(seen) == 1 and seen[0] - before  # once, while the reading child was there
    np.save(tmp_path / "points.npy", np.zeros((4, 3)))
    before = set(children.read_text().split())
    read_dataset(tmp_path / "points.npy", meanwhile=work)  # read here: the work runs after
    assert len(seen) == 2 and seen[1] == before  # no child of the read


def test_volume_with_missing_voxels_is_refused(tmp_path):
    raw = data_path("volumes", "HeadMRVolume.raw")
    (tmp_path / "head.mhd").write_text(data_path("volumes", "HeadMRVolume.mhd").read_text())
    (tmp_path / "HeadMRVolume.raw").write_bytes(raw.read_bytes()[:-100])
    with pytest.raises(ReadError, match="truncated"):
        read_dataset(tmp_path / "head.mhd")
    nii = data_path("volumes", "avg152T1_RL_nifti.nii.gz").read_bytes()
    (tmp_path / "cut.nii.gz").write_bytes(nii[: len(nii) // 2])
    with pytest.raises(ReadError, match="truncated"):
        read_dataset(tmp_path / "cut.nii.gz")


# ------------------------------------------------------------------ volumes
def _write_mha(path: Path, vol: np.ndarray, spacing) -> None:
    header = (
        f"ObjectType = Image\nNDims = 3\nDimSize = {vol.shape[2]} {vol.shape[1]} {vol.shape[0]}\n"
        f"ElementSpacing = {spacing[0]} {spacing[1]} {spacing[2]}\nElementType = MET_UCHAR\n"
        "ElementByteOrderMSB = False\nElementDataFile = LOCAL\n"
    )
    path.write_bytes(header.encode() + vol.astype(np.uint8).tobytes())


def _write_mhd(path: Path, vol: np.ndarray, spacing) -> None:
    _write_mha(path.with_suffix(".mha"), vol, spacing)
    text = path.with_suffix(".mha").read_bytes().split(b"ElementDataFile")[0].decode()
    path.write_text(text + f"ElementDataFile = {path.stem}.raw\n")
    path.with_suffix(".raw").write_bytes(vol.astype(np.uint8).tobytes())
    path.with_suffix(".mha").unlink()


def _write_nrrd(path: Path, vol: np.ndarray, spacing) -> None:
    header = (
        "NRRD0004\ntype: uint8\ndimension: 3\nkinds: domain domain domain\n"
        f"sizes: {vol.shape[2]} {vol.shape[1]} {vol.shape[0]}\n"
        f"spacings: {spacing[0]} {spacing[1]} {spacing[2]}\nencoding: raw\n\n"
    )
    path.write_bytes(header.encode() + vol.astype(np.uint8).tobytes())


def _write_slc(path: Path, vol: np.ndarray, spacing) -> None:
    nz, ny, nx = vol.shape
    header = f"11111\n{nx} {ny} {nz} 8\n{spacing[0]} {spacing[1]} {spacing[2]}\n0 0 0 0\n1 1 X"
    path.write_bytes(header.encode() + b"\0\0\0" + vol.astype(np.uint8).tobytes())


def _write_nifti(path: Path, vol: np.ndarray, spacing) -> None:
    img = pv.ImageData(dimensions=vol.shape[::-1], spacing=spacing)
    img.point_data["v"] = vol.astype(np.uint8).ravel()
    img.save(path)


def _write_dicom(folder: Path, vol: np.ndarray, spacing) -> None:
    """A DICOM series, one file per slice (implicit VR little endian, 16-bit pixels)."""
    folder.mkdir()

    def element(group, elem, value: bytes) -> bytes:
        value += b" " * (len(value) % 2)
        return struct.pack("<HHI", group, elem, len(value)) + value

    syntax = b"1.2.840.10008.1.2\0"
    meta = struct.pack("<HH2sH", 2, 0x10, b"UI", len(syntax)) + syntax
    meta = struct.pack("<HH2sHI", 2, 0, b"UL", 4, len(meta)) + meta
    ny, nx = vol.shape[1:]
    for z, plane in enumerate(vol):
        us = lambda v: struct.pack("<H", v)  # noqa: E731
        body = b"".join([
            element(0x08, 0x18, f"1.2.3.{z + 1}".encode()),
            element(0x18, 0x50, str(spacing[2]).encode()),
            element(0x20, 0x0E, b"1.2.3"),
            element(0x20, 0x13, str(z + 1).encode()),
            element(0x20, 0x32, f"0\\0\\{z * spacing[2]}".encode()),
            element(0x20, 0x37, b"1\\0\\0\\0\\1\\0"),
            element(0x28, 0x02, us(1)),
            element(0x28, 0x10, us(ny)),
            element(0x28, 0x11, us(nx)),
            element(0x28, 0x30, f"{spacing[1]}\\{spacing[0]}".encode()),
            element(0x28, 0x100, us(16)),
            element(0x28, 0x101, us(16)),
            element(0x28, 0x102, us(15)),
            element(0x28, 0x103, us(0)),
            element(0x7FE0, 0x10, plane.astype("<u2").tobytes()),
        ])  # fmt: skip
        (folder / f"slice{z:03d}.dcm").write_bytes(b"\0" * 128 + b"DICM" + meta + body)


WRITERS = {
    ".vti": lambda p, v, s: _write_nifti(p, v, s),
    ".vtk": lambda p, v, s: _write_nifti(p, v, s),
    ".mhd": _write_mhd,
    ".mha": _write_mha,
    ".nii": _write_nifti,
    ".nii.gz": _write_nifti,
    ".nrrd": _write_nrrd,
    ".slc": _write_slc,
    "dicom": _write_dicom,
}


@pytest.fixture(scope="module")
def volume():
    z, y, x = np.mgrid[0:9, 0:8, 0:7]
    return ((x + 2 * y + 3 * z) % 256).astype(np.uint8), (0.5, 0.5, 0.7)


@pytest.mark.parametrize("kind", list(WRITERS))
def test_every_volume_format_is_deformed_by_the_command_line(volume, kind, tmp_path, capsys):
    vol, spacing = volume
    path = tmp_path / ("series" if kind == "dicom" else f"vol{kind}")
    WRITERS[kind](path, vol, spacing)
    img = read_dataset(path)
    assert isinstance(img, pv.ImageData) and img.n_points == vol.size
    values = np.asarray(img.point_data[img.array_names[0]]).ravel()
    np.testing.assert_array_equal(values, vol.ravel())  # every voxel in its place
    if kind in ("dicom", ".nrrd"):  # placed as the headers say: no flipped rows or slices
        np.testing.assert_allclose(img.origin, 0.0, atol=1e-9)
        np.testing.assert_allclose(img.spacing, spacing, rtol=1e-9)
        np.testing.assert_allclose(img.direction_matrix, np.eye(3), atol=1e-12)
    scene = box_scene(tmp_path, img.bounds[0::2], img.bounds[1::2])
    assert main(["deform", str(path), "-s", str(scene), "-o", str(tmp_path / "o.vts"), "-q"]) == 0
    out = pv.read(tmp_path / "o.vts")
    assert out.n_points == vol.size
    assert "deformed" in capsys.readouterr().out


# ------------------------------------------------------------------ files an input reads
def _metaimage_naming(path: Path, vol, spacing, spec: str, after: str = "") -> None:
    """A MetaImage header at ``path`` whose ``ElementDataFile`` is ``spec``, then ``after``."""
    _write_mhd(path, vol, spacing)
    path.with_suffix(".raw").unlink()
    text = path.read_text().split("ElementDataFile")[0]
    path.write_text(f"{text}ElementDataFile = {spec}\n{after}")


def _slices(folder: Path, vol) -> None:
    for z, plane in enumerate(vol):
        (folder / f"s{z}.raw").write_bytes(plane.astype(np.uint8).tobytes())


@pytest.mark.parametrize("case", ["one file", "list", "pattern", "nrrd detached", "dicom"])
def test_no_output_writes_a_file_an_input_reads(volume, case, tmp_path, capsys):
    """``-o`` whose file, or the data file written beside it, is a data file of the input."""
    vol, spacing = volume
    hi = (np.array(vol.shape[::-1]) - 1) * np.array(spacing)
    scene = box_scene(tmp_path, np.zeros(3), hi)
    folder = tmp_path / "data"
    folder.mkdir()
    if case == "one file":  # in.mhd's voxels are in voxels.raw; -o voxels.mhd writes that
        src, out = folder / "in.mhd", folder / "voxels.mhd"
        _metaimage_naming(src, vol, spacing, "voxels.raw")
        (folder / "voxels.raw").write_bytes(vol.astype(np.uint8).tobytes())
    elif case == "list":  # one file per slice, listed after the header
        src, out = folder / "in.mhd", folder / "s4.mhd"
        _metaimage_naming(src, vol, spacing, "LIST 2D", "".join(f"s{z}.raw\n" for z in range(9)))
        _slices(folder, vol)
    elif case == "pattern":  # one file per slice, named by a printf pattern
        src, out = folder / "in.mhd", folder / "s4.mhd"
        _metaimage_naming(src, vol, spacing, "s%d.raw 0 8 1")
        _slices(folder, vol)
    elif case == "nrrd detached":
        src, out = folder / "in.nhdr", folder / "voxels.mhd"
        _write_nrrd(tmp_path / "whole.nrrd", vol, spacing)
        header = (tmp_path / "whole.nrrd").read_bytes().split(b"\n\n")[0].decode()
        src.write_text(header + "\ndata file: voxels.raw\n")
        (folder / "voxels.raw").write_bytes(vol.astype(np.uint8).tobytes())
    else:  # a DICOM series reads every file of its folder, whatever its name
        folder.rmdir()
        _write_dicom(folder, vol, spacing)
        (folder / "slice004.dcm").rename(folder / "slice004.mha")
        src, out = folder, folder / "slice004.mha"
    before = _bytes(folder)
    assert main(["deform", str(src), "-s", str(scene), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err
    assert "refusing to overwrite" in err and err.count("\n") == 1, err
    assert _bytes(folder) == before
    if case in ("one file", "nrrd detached", "dicom"):  # another output is written
        assert (
            main(["deform", str(src), "-s", str(scene), "-o", str(tmp_path / "o.mhd"), "-q"]) == 0
        )
        assert _bytes(folder) == before
        assert pv.read(tmp_path / "o.mhd").n_points > 0


def test_the_files_each_format_writes_beside_its_own():
    from vhm_viz.io.registry import files_of

    assert files_of("a/out.mhd", written=True) == [Path("a/out.raw")]
    for name in ("out.mha", "out.nii.gz", "out.nrrd", "out.vti", "out.vts"):
        assert files_of(name, written=True) == []


@pytest.mark.parametrize("kind", [".slc", "dicom", ".nii.gz"])
def test_cage_and_anchors_commands_read_volumes_too(volume, kind, tmp_path):
    vol, spacing = volume
    path = tmp_path / ("series" if kind == "dicom" else f"vol{kind}")
    WRITERS[kind](path, vol, spacing)
    assert main(["cage", str(path), "-o", str(tmp_path / "cage.obj"), "-q"]) == 0
    assert main(["anchors", str(path), "--cage", str(tmp_path / "cage.obj"), "-n", "4",
                 "-o", str(tmp_path / "a.json"), "-q"]) == 0  # fmt: skip


# Each bundled volume's frame and voxels from its own header, parsed here with plain Python
# and NumPy: (nx, ny, nz), origin, spacing, direction (columns: the image axes in the
# world), and the voxels as an (nz, ny, nx) array in file order.
def _metaimage_reference(path: Path):
    fields = dict(
        (key.strip(), value.strip())
        for key, _, value in (line.partition("=") for line in path.read_text().splitlines())
    )
    dims = [int(v) for v in fields["DimSize"].split()]
    assert fields["ElementType"] == "MET_UCHAR" and fields["ElementByteOrderMSB"] == "False"
    origin = [float(v) for v in fields.get("Offset", "0 0 0").split()]
    direction = np.eye(3)  # no TransformMatrix in the file
    assert "TransformMatrix" not in fields
    spacing = [float(v) for v in fields["ElementSpacing"].split()]
    raw = (path.parent / fields["ElementDataFile"]).read_bytes()
    return dims, origin, spacing, direction, np.frombuffer(raw, np.uint8).reshape(dims[::-1])


def _nifti_reference(path: Path):
    blob = gzip.open(path).read()
    order = "<" if struct.unpack_from("<i", blob, 0)[0] == 348 else ">"
    dim = struct.unpack_from(order + "8h", blob, 40)
    datatype = struct.unpack_from(order + "h", blob, 70)[0]
    sform_code = struct.unpack_from(order + "h", blob, 254)[0]
    offset = int(struct.unpack_from(order + "f", blob, 108)[0])
    assert datatype == 2 and sform_code > 0  # uint8, placed by its sform
    srow = np.array([struct.unpack_from(order + "4f", blob, 280 + 16 * r) for r in range(3)])
    lps = np.diag([-1.0, -1.0, 1.0])  # NIfTI's world is RAS, vhm_viz's is LPS
    spacing = np.linalg.norm(srow[:, :3], axis=0)
    dims = list(dim[1:4])
    voxels = np.frombuffer(blob, np.uint8, int(np.prod(dims)), offset).reshape(dims[::-1])
    return dims, lps @ srow[:, 3], spacing, lps @ srow[:, :3] / spacing, voxels


def _slc_reference(path: Path, slices):
    """SLC (run-length encoded 8-bit slices); only ``slices`` decoded, the others zero."""
    blob = path.read_bytes()
    head = blob.split(b"X", 1)[0].split()
    nx, ny, nz, bits = (int(v) for v in head[1:5])
    spacing = [float(v) for v in head[5:8]]
    compression, icon_w, icon_h = (int(v) for v in head[11:14])
    assert bits == 8 and compression == 1
    pos = blob.index(b"X") + 1 + 3 * icon_w * icon_h
    voxels = np.zeros((nz, ny, nx), np.uint8)
    for z in range(nz):
        size_text, pos = blob[pos:].split(b"X", 1)[0], pos + blob[pos:].index(b"X") + 1
        code = blob[pos : pos + int(size_text)]
        pos += int(size_text)
        if z not in slices:
            continue
        values, i = bytearray(), 0
        while i < len(code) and code[i] & 0x7F:
            count = code[i] & 0x7F
            if code[i] & 0x80:  # literal bytes
                values += code[i + 1 : i + 1 + count]
                i += 1 + count
            else:  # one byte repeated
                values += code[i + 1 : i + 2] * count
                i += 2
        voxels[z].ravel()[: len(values)] = np.frombuffer(bytes(values[: nx * ny]), np.uint8)
    return [nx, ny, nz], [0.0, 0.0, 0.0], spacing, np.eye(3), voxels


def _vti_reference(path: Path):
    """VTK XML image, one zlib-compressed inline array (UInt32 block headers)."""
    text = path.read_bytes()

    def attr(name: bytes) -> list[float]:
        return [float(v) for v in re.search(b' %s="([^"]*)"' % name, text).group(1).split()]

    extent = attr(b"WholeExtent")
    dims = [int(extent[2 * a + 1] - extent[2 * a]) + 1 for a in range(3)]
    data = re.search(rb'type="UInt16"[^>]*format="binary"[^>]*>\s*([A-Za-z0-9+/=]+)', text).group(1)
    n_blocks = int(np.frombuffer(base64.b64decode(data[:8]), "<u4", 1)[0])
    head_chars = 4 * ((4 * (3 + n_blocks) + 2) // 3)
    sizes = np.frombuffer(base64.b64decode(data[:head_chars]), "<u4")[3 : 3 + n_blocks]
    blob, raw, pos = base64.b64decode(data[head_chars:]), b"", 0
    for size in sizes:
        raw += zlib.decompress(blob[pos : pos + size])
        pos += size
    direction = np.array(attr(b"Direction")).reshape(3, 3)
    voxels = np.frombuffer(raw, "<u2").reshape(dims[::-1])
    return dims, attr(b"Origin"), attr(b"Spacing"), direction, voxels


@pytest.mark.data
@pytest.mark.parametrize(
    "name", ["HeadMRVolume.mhd", "avg152T1_RL_nifti.nii.gz", "embryo.slc", "headsq_64x64x93.vti"]
)
def test_bundled_volumes_are_read_in_the_frame_their_headers_state(name):
    path = data_path("volumes", name)
    rng = np.random.default_rng(7)
    if name.endswith(".slc"):
        slices = {0, 100, 128, 200, 255}
        dims, origin, spacing, direction, voxels = _slc_reference(path, slices)
        ks = sorted(slices)
    else:
        reference = {".mhd": _metaimage_reference, ".gz": _nifti_reference,
                     ".vti": _vti_reference}[Path(name).suffix]  # fmt: skip
        dims, origin, spacing, direction, voxels = reference(path)
        ks = list(range(voxels.shape[0]))
    img = read_dataset(path)
    assert isinstance(img, pv.ImageData)
    assert list(img.dimensions) == list(dims)
    np.testing.assert_allclose(img.origin, origin, atol=1e-9)
    np.testing.assert_allclose(img.spacing, spacing, rtol=1e-12)
    np.testing.assert_allclose(img.direction_matrix, direction, atol=1e-12)
    values = np.asarray(img.point_data[img.array_names[0]])
    assert values.dtype == voxels.dtype
    # chosen voxels: the corners of the decoded slices, the brightest voxel, random ones
    k_bright, j_bright, i_bright = np.unravel_index(np.argmax(voxels), voxels.shape)
    chosen = [
        (i, j, k) for k in (ks[0], ks[-1]) for j in (0, dims[1] - 1) for i in (0, dims[0] - 1)
    ]
    chosen.append((i_bright, j_bright, k_bright))
    chosen += [(rng.integers(dims[0]), rng.integers(dims[1]), rng.choice(ks)) for _ in range(40)]
    assert voxels[k_bright, j_bright, i_bright] > 0
    for i, j, k in chosen:
        # where the header puts voxel (i, j, k): origin + direction @ (spacing * index)
        x = np.asarray(origin) + np.asarray(direction) @ (np.asarray(spacing) * [i, j, k])
        found = img.FindPoint(x)
        np.testing.assert_allclose(img.points[found], x, atol=1e-9)
        assert values[found] == voxels[k, j, i], (i, j, k)


def test_a_tet_mesh_written_to_legacy_vtk_reads_in_meshio(tmp_path, capsys):
    """A deformed tet mesh written to legacy ``.vtk`` reads in meshio, an independent
    reader: the tets exactly as given, the points as the same run's ``.vtu`` holds them.
    The count of points outside the cage, a field array, is written as 64-bit integers
    of a fixed width: a ``long`` one (as wide as the platform's C long) meshio refuses."""
    meshio = pytest.importorskip("meshio")
    points, tets = examples.bar_tets(12)
    pv.UnstructuredGrid({pv.CellType.TETRA: tets}, points).save(tmp_path / "bar.vtu")
    box_scene(tmp_path, points.min(axis=0), points.max(axis=0))
    for name in ("bent.vtk", "bent.vtu"):
        rc = main(["deform", str(tmp_path / "bar.vtu"), "-s", str(tmp_path / "scene.json"),
                   "-o", str(tmp_path / name), "-q"])  # fmt: skip
        assert rc == 0, capsys.readouterr().err
    got, want = meshio.read(tmp_path / "bent.vtk"), pv.read(tmp_path / "bent.vtu")
    assert [c.type for c in got.cells] == ["tetra"]
    assert np.array_equal(got.cells[0].data, tets)
    assert np.array_equal(got.points, want.points)
    assert not np.array_equal(got.points, points)
    back = pv.read(tmp_path / "bent.vtk").field_data["vhm_outside_count"]
    assert back.dtype == np.int64 and back.tolist() == [0]


def test_a_deformed_tet_mesh_written_to_vtu_reads_in_meshio(tmp_path, capsys):
    """``.vtu`` is how tet meshes go on to finite-element tools, whose Python reader is
    meshio: it reads a deformed mesh with its point and cell arrays (an outside flag,
    uint8, among them) as VTK's reader does, value for value."""
    meshio = pytest.importorskip("meshio")
    points, tets = examples.bar_tets(12)
    longer = points * [1.0, 1.0, 1.5]  # its far end outside the cage: flagged, left in place
    pv.UnstructuredGrid({pv.CellType.TETRA: tets}, longer).save(tmp_path / "bar.vtu")
    box_scene(tmp_path, points.min(axis=0), points.max(axis=0))
    rc = main(["deform", str(tmp_path / "bar.vtu"), "-s", str(tmp_path / "scene.json"),
               "-o", str(tmp_path / "bent.vtu"), "-q", "--outside", "passthrough",
               "--allow-folds", "--arrays", "displacement,det,cells"])  # fmt: skip
    assert rc == 0, capsys.readouterr().err
    got, want = meshio.read(tmp_path / "bent.vtu"), pv.read(tmp_path / "bent.vtu")
    assert [c.type for c in got.cells] == ["tetra"]
    assert np.array_equal(got.cells[0].data, tets)
    assert np.array_equal(got.points, want.points)
    assert 0 < want.point_data["vhm_outside"].sum() < want.n_points
    assert set(want.point_data) <= set(got.point_data)
    for name in want.point_data:
        np.testing.assert_array_equal(got.point_data[name], want.point_data[name], err_msg=name)
    assert set(want.cell_data) - {"vtkOriginalCellIds"} <= set(got.cell_data)
    for name in set(want.cell_data) & set(got.cell_data):
        np.testing.assert_array_equal(got.cell_data[name][0], want.cell_data[name], err_msg=name)


def test_a_folder_named_like_a_file_is_said_to_be_a_folder(bar_case, tmp_path):
    # "bunny.ply/" as the data, a cage or an anchors file: one line saying it is a folder
    # and to name the file itself, not "no DICOM series", "no such cage file" or a reader's
    folder = bar_case
    for name in ("bar.ply", "cage.obj", "anchors.json"):
        (tmp_path / name).mkdir()
    scene = json.loads((folder / "scene.json").read_text())
    cases = {
        "bar.ply": ("deform", tmp_path / "bar.ply", folder / "scene.json"),
        "cage.obj": ("deform", folder / "bar.vtp", dict(scene, cage=str(tmp_path / "cage.obj"))),
        "anchors.json": (
            "deform", folder / "bar.vtp", dict(scene, cage=str(folder / "cage.obj"),
                                               anchors=str(tmp_path / "anchors.json")),
        ),
    }  # fmt: skip
    for name, (command, data, sc) in cases.items():
        if isinstance(sc, dict):
            (tmp_path / "s.json").write_text(json.dumps(sc))
            sc = tmp_path / "s.json"
        done = run_cli(command, data, "--scene", sc, "-o", tmp_path / "out.vtp", "-q")
        assert done.returncode == 1, (name, done.stderr)
        assert done.stderr.count("\n") == 1, (name, done.stderr)
        suffix = name[name.index(".") :]
        said = f"{tmp_path / name}: a folder, not a"
        assert said in done.stderr and "name the file itself" in done.stderr, (name, done.stderr)
        assert suffix in done.stderr or "file" in done.stderr
        assert not (tmp_path / "out.vtp").exists()


def test_anchors_outside_a_cage_file_name_it(bar_case, tmp_path):
    # a user with several cages at hand reads which one the anchors fall outside of
    folder = bar_case
    anchors = json.loads((folder / "anchors.json").read_text())["anchors"]
    anchors.append([40.0, 0.0, 0.0])
    (tmp_path / "anchors.json").write_text(json.dumps({"anchors": anchors}))
    scene = json.loads((folder / "scene.json").read_text())
    scene.update(cage=str(folder / "cage.obj"), anchors=str(tmp_path / "anchors.json"))
    (tmp_path / "s.json").write_text(json.dumps(scene))
    done = run_cli("deform", folder / "bar.vtp", "--scene", tmp_path / "s.json", "-o",
                   tmp_path / "out.vtp", "-q")  # fmt: skip
    n = len(anchors)
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.strip() == (
        f"vhm-viz deform: error: 1 of {n} anchors is outside the cage {folder / 'cage.obj'} "
        f"(indices {n - 1})"
    )
    assert not (tmp_path / "out.vtp").exists()
