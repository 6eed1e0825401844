"""Memory ceilings: a volume job that cannot fit is refused before it allocates, in one line."""

from __future__ import annotations

import json
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import box_cage, data_path

from vhm_viz.resources import memory_limit

SCENE = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"
#: The address-space limit of the goal: a shared node's 1.2 GB.
LIMIT = 1_200_000_000


def _cli(*args, limit=None, timeout=600):
    def set_limit():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    return subprocess.run([sys.executable, "-m", "vhm_viz.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout,
                          preexec_fn=set_limit if limit else None)  # fmt: skip


def _bend_scene(bounds) -> dict:
    """A padded box cage around ``bounds``, its far end moved along a second axis."""
    lo, hi = np.asarray(bounds[0::2], float), np.asarray(bounds[1::2], float)
    pad = 0.06 * (hi - lo)
    vertices, faces = box_cage(lo - pad, hi + pad, 2)
    long = int(np.argmax(hi - lo))
    centre = (lo + hi) / 2
    near, far = centre.copy(), centre.copy()
    near[long], far[long] = lo[long] + 0.1 * (hi - lo)[long], hi[long] - 0.1 * (hi - lo)[long]
    moved = far.copy()
    moved[(long + 1) % 3] += 0.15 * (hi - lo)[long]
    anchors = np.repeat(centre[None], 8, axis=0)
    anchors[:, long] = np.linspace(near[long], far[long], 8)
    return {"format": "vhm_viz.scene", "version": 1,
            "cage": {"vertices": vertices.tolist(), "faces": faces.tolist()},
            "anchors": anchors.tolist(), "mode": "rigid", "alpha": 0.01,
            "constraints": {"positions": [near.tolist(), far.tolist()],
                            "targets": [near.tolist(), moved.tolist()]}}  # fmt: skip


def test_the_limit_found_is_the_address_space_limit_less_what_is_mapped():
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30)); "
            "from vhm_viz.resources import memory_limit; l = memory_limit(); "
            "print(l.available, '|', l.source)")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    available, source = out.stdout.split("|")
    # less than the limit (the interpreter maps some), at least a few hundred MiB of it left
    assert 200 << 20 < int(available) < 3 << 30
    assert "ulimit -v" in source or "cgroup" in source or "available" in source
    assert memory_limit().available is None or memory_limit().available > 0


def test_the_embryo_resampled_under_1_2_gb_completes_or_is_refused_before_mapping(tmp_path):
    from vhm_viz.io import read_dataset

    embryo = data_path("volumes", "embryo.slc")
    scene = tmp_path / "bend.json"
    scene.write_text(json.dumps(_bend_scene(read_dataset(embryo).bounds)))
    out = tmp_path / "bent.vti"
    proc = _cli("deform", embryo, "--scene", scene, "-o", out, "-q", "--timings", limit=LIMIT)
    assert "Traceback" not in proc.stderr and "MemoryError" not in proc.stderr
    assert "Unable to allocate" not in proc.stderr and proc.returncode in (0, 1), proc.stderr
    if proc.returncode == 0:
        assert read_dataset(out).n_points > 0
        return
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("vhm-viz deform")]
    assert len(errors) == 1, proc.stderr
    line = errors[0]
    # the estimate, the limit, and the options that lower it
    assert "needs about" in line and "ulimit -v" in line, line
    assert "--spacing" in line and "--memory-budget" in line, line
    timings = next(ln for ln in proc.stderr.splitlines() if "timings:" in ln)
    assert " map " not in timings, timings  # refused before the voxels were mapped
    assert not out.exists() and list(tmp_path.iterdir()) == [scene]


@pytest.mark.parametrize("kind", ["pullback", "forward"])
def test_a_displacement_field_that_cannot_fit_is_refused_before_mapping(tmp_path, kind):
    """The embryo's field (three float64 a voxel, and the writer's copies) is part of the
    estimate: under 1.6 GB the job is refused in one line before any voxel is mapped,
    where it used to fail in the map, out of memory."""
    from vhm_viz.io import read_dataset

    embryo = data_path("volumes", "embryo.slc")
    scene = tmp_path / "bend.json"
    scene.write_text(json.dumps(_bend_scene(read_dataset(embryo).bounds)))
    out, field = tmp_path / "bent.vti", tmp_path / "field.nii.gz"
    proc = _cli("deform", embryo, "--scene", scene, "-o", out, "-q", "--timings",
                "--write-field", field, "--field-kind", kind, limit=1_600_000_000)  # fmt: skip
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("vhm-viz deform")]
    assert len(errors) == 1, proc.stderr
    assert f"with its {kind} displacement field" in errors[0], errors[0]
    assert "needs about" in errors[0] and "leave out --write-field" in errors[0], errors[0]
    timings = next(ln for ln in proc.stderr.splitlines() if "timings:" in ln)
    assert " map " not in timings, timings
    assert list(tmp_path.iterdir()) == [scene]


def test_a_header_claiming_a_trillion_voxels_is_refused_before_reading(tmp_path):
    header = tmp_path / "huge.mhd"
    header.write_text("ObjectType = Image\nNDims = 3\nBinaryData = True\n"
                      "BinaryDataByteOrderMSB = False\nElementSpacing = 1 1 1\n"
                      "DimSize = 10000 10000 10000\nElementType = MET_UCHAR\n"
                      "ElementDataFile = huge.raw\n")  # fmt: skip
    with open(tmp_path / "huge.raw", "wb") as fh:  # as many bytes as it claims (sparse)
        fh.truncate(10**12)
    proc = _cli("deform", header, "--scene", SCENE, "-o", tmp_path / "out.vti", "-q")
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vhm-viz deform: error:"), proc.stderr
    assert "DimSize" in lines[0] and "needs about 931 GiB" in lines[0], lines[0]


def test_a_nifti_header_claiming_a_trillion_voxels_is_refused_before_reading(tmp_path):
    """As the MetaImage above: the header's size against the memory, before its data."""
    header = bytearray(352)
    header[0:4] = (348).to_bytes(4, "little")
    header[40:56] = np.array([3, 10000, 10000, 10000, 1, 1, 1, 1], "<i2").tobytes()
    header[70:74] = np.array([2, 8], "<i2").tobytes()  # uint8
    header[76:108] = np.array([1, 1, 1, 1, 1, 1, 1, 1], "<f4").tobytes()
    header[108:112] = np.array([352], "<f4").tobytes()
    header[344:348] = b"n+1\0"
    path = tmp_path / "huge.nii"
    with open(path, "wb") as fh:  # as many bytes as it claims (sparse)
        fh.write(header)
        fh.truncate(352 + 10**12)
    proc = _cli("deform", path, "--scene", SCENE, "-o", tmp_path / "out.vti", "-q", limit=LIMIT)
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("vhm-viz deform: error:"), proc.stderr
    assert "10000000000" in lines[0] and "needs about 931 GiB" in lines[0], lines[0]


def test_a_tolerance_wider_than_a_root_cell_is_refused_in_one_line_before_reading(tmp_path):
    """A tolerance of 1000 voxels, far wider than any cell of the lattice, is a mistake:
    refused in one line before the data is read, nothing written."""
    from vhm_viz.io import read_dataset

    head = data_path("volumes", "headsq_64x64x93.vti")
    scene = tmp_path / "bend.json"
    scene.write_text(json.dumps(_bend_scene(read_dataset(head).bounds)))
    out = tmp_path / "t.vti"
    proc = _cli("deform", head, "--scene", scene, "-o", out, "--tolerance", "1000",
                "--timings", timeout=120)  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("vhm-viz deform")]
    assert len(errors) == 1 and errors[0].startswith("vhm-viz deform: error:"), proc.stderr
    assert "--tolerance" in errors[0] and "at most 16" in errors[0], errors[0]
    assert "got 1000" in errors[0], errors[0]
    timings = next(ln for ln in proc.stderr.splitlines() if "timings:" in ln)
    assert " read " not in timings and " solve " not in timings, timings  # before any stage
    assert list(tmp_path.iterdir()) == [scene]


def test_a_resample_too_large_is_refused_for_the_grid_the_engine_would_make(tmp_path):
    """The size check before mapping sees the output grid the engine makes, whatever
    shapes it (the tolerance, the spacing): a fine --spacing is refused naming a grid that
    spans the engine's own grid of the volume, and a spacing no image can hold is refused
    in one line too."""
    from vhm_viz.io import read_dataset

    head = data_path("volumes", "headsq_64x64x93.vti")
    scene = tmp_path / "bend.json"
    scene.write_text(json.dumps(_bend_scene(read_dataset(head).bounds)))
    made = tmp_path / "made.vti"
    proc = _cli("deform", head, "--scene", scene, "-o", made, "-q", "--tolerance", "16")
    assert proc.returncode == 0, proc.stderr
    grid = read_dataset(made)
    made.unlink()
    dims, spacing = np.asarray(grid.dimensions), np.asarray(grid.spacing)
    step = 0.01
    refused = {}
    for fine, words in ((str(step), "needs about"), ("1e-9", "along an axis")):
        out = tmp_path / "fine.vti"
        proc = _cli("deform", head, "--scene", scene, "-o", out, "-q", "--tolerance", "16",
                    "--spacing", fine, "--timings")  # fmt: skip
        assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("vhm-viz deform")]
        assert len(errors) == 1 and words in errors[0], proc.stderr
        timings = next(ln for ln in proc.stderr.splitlines() if "timings:" in ln)
        assert " map " not in timings, timings  # refused before the voxels were mapped
        refused[fine] = errors[0]
    assert list(tmp_path.iterdir()) == [scene]
    # in the engine's voxels the refused grid spans its grid, give or take the estimate's
    # margin (a voxel on each side) and what its sampled points miss
    words = refused[str(step)].split(" onto a ")[1].split(" grid")[0]
    named = np.array([int(n) for n in words.split("x")])
    span = (named - 1) * step / spacing
    assert np.all(span >= dims - 2) and np.all(span <= dims + 1 + step / spacing), (named, dims)


@pytest.mark.parametrize("text", ["0", "2P"])
def test_a_memory_budget_that_is_no_size_is_refused_in_one_line(tmp_path, text):
    head = data_path("volumes", "headsq_64x64x93.vti")
    proc = _cli("deform", head, "--scene", "x.json", "-o", tmp_path / "o.vti",
                f"--memory-budget={text}")  # fmt: skip
    assert proc.returncode == 2 and "--memory-budget" in proc.stderr
    assert "expected a size" in proc.stderr and "Traceback" not in proc.stderr


def test_a_solver_of_too_many_anchors_is_refused_before_it_allocates(tmp_path):
    # the solver's dense factorisation holds (3d, 3d) matrices: 4,000 anchors need about
    # 2.3 GB, refused under 1.2 GB at once, in one line naming the anchors
    scene = _bend_scene((0.0, 1.0, 0.0, 1.0, 0.0, 4.0))
    rng = np.random.default_rng(0)
    scene["anchors"] = (rng.random((4000, 3)) * [1.0, 1.0, 4.0]).tolist()
    (tmp_path / "many.json").write_text(json.dumps(scene))
    (tmp_path / "points.csv").write_text("0.5,0.5,1\n0.5,0.5,2\n0.5,0.5,3\n")
    out = tmp_path / "bent.vtp"
    done = _cli("deform", tmp_path / "points.csv", "--scene", tmp_path / "many.json", "-o", out,
                limit=LIMIT)  # fmt: skip
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1, done.stderr
    assert "the solver for 4000 anchors needs about 2" in lines[-1], lines
    assert "use fewer anchors" in lines[-1] and not out.exists()
    assert "Traceback" not in done.stderr


@pytest.fixture()
def fine_cage_scene(tmp_path):
    """A surface given as the cage (the bar's 12,288 triangles) and two points to deform."""
    scene = _bend_scene((-0.5, 0.5, 0.0, 3.5, -0.5, 0.5))
    scene["cage"] = str(data_path("bar", "bar_dense.obj"))
    (tmp_path / "fine.json").write_text(json.dumps(scene))
    (tmp_path / "points.csv").write_text("0,1,0\n0,2,0\n")
    return tmp_path / "points.csv", tmp_path / "fine.json"


def test_a_cage_too_fine_for_its_smoothness_term_is_refused_before_it_allocates(
    fine_cage_scene, tmp_path
):
    # the basis Hessians at its 36,864 smoothness samples need some 54 GB: refused under
    # 6 GB at once, in one line that says what to change
    points, scene = fine_cage_scene
    out = tmp_path / "bent.vtp"
    done = _cli("deform", points, "--scene", scene, "-o", out, "-q", limit=6 * 10**9)
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith(
        "vhm-viz deform: error: the smoothness term of a cage of 12288 faces needs about "
    ), done.stderr
    assert "use a cage of fewer faces" in done.stderr and not out.exists()


def test_memory_running_out_where_no_estimate_refused_the_job_is_one_line(
    fine_cage_scene, tmp_path
):
    # under 1.2 GB the cage's own checks run out first: NumPy's "Unable to allocate ...
    # for an array with shape ..." is not what the user reads
    points, scene = fine_cage_scene
    out = tmp_path / "bent.vtp"
    done = _cli("deform", points, "--scene", scene, "-o", out, "-q", limit=LIMIT)
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("vhm-viz deform: error: out of memory"), done.stderr
    assert "the address-space limit" in done.stderr and "shape" not in done.stderr
    assert not out.exists()
