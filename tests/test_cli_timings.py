"""--timings, --threads and the fold check of a warped or resampled volume, through the
command line."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import pyvista as pv
from conftest import (
    FOLDING_DIMS,
    box_cage,
    data_path,
    trilinear_corner_dets,
    write_folding_volume,
)

from vhm_viz.cli.timings import StageTimer


def _cli(*args, env=None):
    return subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", *args],
        capture_output=True, text=True, timeout=600, env={**os.environ, **(env or {})},
    )  # fmt: skip


DIMS = FOLDING_DIMS


@pytest.fixture(scope="module")
def folding_volume(tmp_path_factory):
    """An image filling the bar, and the bar's push scene, which folds it."""
    folder = tmp_path_factory.mktemp("fold")
    write_folding_volume(folder)
    return folder


def test_warped_volume_fold_count_matches_brute_force(folding_volume):
    out = folding_volume / "warped.vts"
    proc = _cli(
        "deform", str(folding_volume / "image.vti"), "--scene", str(folding_volume / "scene.json"),
        "-o", str(out), "-q", "--timings", "--allow-folds",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    warped = pv.read(out)
    grid = np.asarray(warped.points).reshape(*DIMS[::-1], 3)
    expected = int((trilinear_corner_dets(grid) <= 0).sum())
    assert expected > 0  # the scene folds
    m = re.search(r"(\d+) of (\d+) cells inverted", proc.stderr)
    assert m, proc.stderr
    assert int(m.group(1)) == expected and int(m.group(2)) == np.prod(np.array(DIMS) - 1)
    line = [ln for ln in proc.stderr.splitlines() if "timings:" in ln]
    assert len(line) == 1
    stages = dict(re.findall(r"(\w+) ([0-9.]+) s", line[0]))
    assert {"read", "solve", "map", "checks", "write", "other", "total"} <= set(stages)
    parts = sum(float(v) for k, v in stages.items() if k != "total")
    # each printed value is rounded to 0.01 s: the sum is within half of that per value
    assert parts == pytest.approx(float(stages["total"]), abs=0.005 * len(stages) + 1e-9)


def _box(text):
    """The two corners of ``(x, y, z)-(x, y, z)``."""
    return [[float(v) for v in corner.split(",")] for corner in re.findall(r"\(([^)]*)\)", text)]


def test_resampled_volume_in_folds_is_refused_unless_allowed(folding_volume, tmp_path):
    args = ["deform", str(folding_volume / "image.vti"), "--scene",
            str(folding_volume / "scene.json"), "-q"]  # fmt: skip
    # an earlier output stays as it was: the refusal writes nothing, not even beside it
    out = tmp_path / "out.vti"
    out.write_bytes((folding_volume / "image.vti").read_bytes())
    before = out.read_bytes()
    refused = _cli(*args, "-o", str(out))
    assert refused.returncode == 4 and refused.stdout.strip() == ""
    assert out.read_bytes() == before
    nifti = _cli(*args, "-o", str(tmp_path / "out.nii.gz"))
    assert nifti.returncode == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.vti"]
    error = refused.stderr.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("vhm-viz deform: error: the deformation folds")
    assert error[0].endswith("pass --allow-folds to write it anyway)")
    # --allow-folds writes it; the line, now a warning, counts the voxels it marks in folds
    # and gives the box of their positions
    allowed = _cli(*args, "-o", str(out), "--allow-folds")
    assert allowed.returncode == 0, allowed.stderr
    (line,) = allowed.stderr.strip().splitlines()
    warned = "vhm-viz deform: warning: "
    assert line.startswith(warned) and line.removeprefix(warned) in error[0]
    m = re.search(
        r"(\d+) of (\d+) output voxels in folds \(several pre-images; output positions "
        r"within (\([^)]*\)-\([^)]*\))\)",
        line,
    )
    assert m, line
    image = pv.read(out)
    marked = np.flatnonzero(np.asarray(image.point_data["vhm_foldover"]))
    assert int(m.group(1)) == marked.size > 0 and int(m.group(2)) == image.n_points
    at = np.asarray(image.points)[marked]
    np.testing.assert_allclose(_box(m.group(3)), [at.min(axis=0), at.max(axis=0)], atol=1e-3)


def test_a_resample_refuses_voxels_in_folds_that_the_spot_check_misses(tmp_path):
    # the CT head twisted by 45 degrees in a box cage: the 256 points of the spot check
    # have det J > 0, yet output voxels lie in folds (the warp's cells are inverted there)
    head = data_path("volumes", "headsq_64x64x93.vti")
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    held = [[100.8, 100.8, 0], [0, 0, 0], [201.6, 0, 0], [201.6, 201.6, 0], [0, 201.6, 0],
            [100.8, 100.8, 138]]  # fmt: skip
    v, f = box_cage((-10, -10, -10), (211.6, 211.6, 148))
    scene = {
        "format": "vhm_viz.scene", "version": 1,
        "cage": {"vertices": v.tolist(), "faces": f.tolist()},
        "anchors": {"auto": 24},
        "constraints": {
            "positions": held, "targets": held,
            "jacobian_points": [[100.8, 100.8, 0], [100.8, 100.8, 138]],
            "jacobians": [np.eye(3).tolist(), [[c, -s, 0], [s, c, 0], [0, 0, 1]]],
        },
        "solver": {"steps": 3},
    }  # fmt: skip
    (tmp_path / "twist.json").write_text(json.dumps(scene))
    out = tmp_path / "twist.vti"
    proc = _cli("deform", str(head), "--scene", str(tmp_path / "twist.json"), "-o", str(out),
                "-q")  # fmt: skip
    assert proc.returncode == 4 and not out.exists()
    (line,) = proc.stderr.strip().splitlines()
    assert re.search(r": \d+ of \d+ output voxels in folds \(several pre-images; output ", line)
    assert "sampled points" not in line, line


class _Clock:
    """A clock that moves only when told: stage times are then exact."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_work_set_aside_inside_a_stage_counts_as_other():
    clock = _Clock()
    timer = StageTimer(clock=clock)
    clock.now += 1.0  # start-up before the first stage

    def load():
        clock.now += 6.0
        return "loaded"

    with timer.stage("read"):
        clock.now += 0.5
        assert timer.aside(load)() == "loaded"
        clock.now += 1.5  # the wait beyond the work set aside
    with timer.stage("solve"):
        clock.now += 3.0
        # a process ended inside a stage reports the stage so far, without work set aside
        timer.aside(lambda: setattr(clock, "now", clock.now + 4.0))()
        clock.now += 1.0
        assert timer.line() == "timings: read 2.00 s, solve 4.00 s, other 11.00 s, total 17.00 s"
    assert timer.seconds == {"read": 2.0, "solve": 4.0}
    assert timer.aside(None) is None
    # a command that is its process counts from the command line's start (its imports)
    begun = StageTimer(clock=clock, start=clock.now - 0.25)
    with begun.stage("read"):
        clock.now += 1.0
    assert begun.line() == "timings: read 1.00 s, other 0.25 s, total 1.25 s"


def _stages(stderr: str) -> list[tuple[str, float]]:
    line = [ln for ln in stderr.splitlines() if "timings:" in ln]
    assert len(line) == 1, stderr
    return [(name, float(v)) for name, v in re.findall(r"(\w+) ([0-9.]+) s", line[0])]


def test_cage_and_anchors_time_their_stages(folding_volume, tmp_path):
    image, cage = folding_volume / "image.vti", tmp_path / "cage.obj"
    runs = {
        "cage": _cli("cage", str(image), "-o", str(cage), "-q", "--timings"),
        "anchors": _cli("anchors", str(image), "--cage", str(cage), "-n", "4",
                        "-o", str(tmp_path / "a.json"), "-q", "--timings"),
    }  # fmt: skip
    for command, proc in runs.items():
        assert proc.returncode == 0, proc.stderr
        stages = _stages(proc.stderr)
        assert [n for n, _ in stages] == ["read", command, "write", "other", "total"]
        parts = sum(v for n, v in stages if n != "total")
        assert parts == pytest.approx(dict(stages)["total"], abs=0.005 * len(stages) + 1e-9)
        assert _help_stages(command) == ["read", command, "write"]


def _help_stages(command: str) -> list[str]:
    """The stages ``COMMAND --help`` says ``--timings`` prints (before "and other")."""
    text = " ".join(_cli(command, "--help").stdout.split())
    listed = re.search(r"--timings print where the time went on stderr: (.*?),? and other", text)
    assert listed, text
    return [part.split()[0] for part in listed.group(1).split(", ")]


def test_the_demos_timings_name_its_work(tmp_path):
    """The demo's work is its own stage, as its --help says, not start-up ("other")."""
    proc = _cli("demo", "-o", str(tmp_path), "-q", "--resolution", "6", "--voxel", "0.25",
                "--timings")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    stages = dict(_stages(proc.stderr))
    assert list(stages) == ["demo", "other", "total"]
    assert _help_stages("demo") == ["demo"]
    assert _help_stages("deform") == ["read", "solve", "map", "checks", "write"]


def test_fold_count_is_the_same_in_small_slabs(folding_volume):
    # a memory budget of a layer of cells: the check goes through every layer on its own
    out = folding_volume / "small.vts"
    proc = _cli(
        "deform", str(folding_volume / "image.vti"), "--scene", str(folding_volume / "scene.json"),
        "-o", str(out), "-q", "--memory-budget", "1K", "--allow-folds",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    grid = np.asarray(pv.read(out).points).reshape(*DIMS[::-1], 3)
    dets = trilinear_corner_dets(grid)  # VTK's cell order
    expected = np.flatnonzero(dets <= 0)
    m = re.search(
        r"(\d+) of (\d+) cells inverted \(cell det <= 0; worst (\S+) at \(([^)]*)\)", proc.stderr
    )
    assert m, proc.stderr
    assert int(m.group(1)) == expected.size > 0
    assert int(m.group(2)) == np.prod(np.array(DIMS) - 1)
    image = pv.read(folding_volume / "image.vti")
    assert float(m.group(3)) == pytest.approx(dets.min() / np.prod(image.spacing), rel=5e-3)
    # the worst cell's rest centre, printed to 4 digits
    i, j, k = np.unravel_index(np.argmin(dets), np.array(DIMS) - 1, order="F")
    centre = np.asarray(image.origin) + (np.array([i, j, k]) + 0.5) * np.asarray(image.spacing)
    shown = [float(v) for v in m.group(4).split(",")]
    np.testing.assert_allclose(shown, centre, rtol=1e-3, atol=1e-3)
    # the box of every inverted cell's rest centre
    box = re.search(r"cell det <= 0; [^;]*within \(([^)]*)\)-\(([^)]*)\)", proc.stderr)
    assert box, proc.stderr
    ijk = np.column_stack(np.unravel_index(expected, np.array(DIMS) - 1, order="F"))
    centres = np.asarray(image.origin) + (ijk + 0.5) * np.asarray(image.spacing)
    lo, hi = ([float(v) for v in text.split(",")] for text in box.groups())
    np.testing.assert_allclose(lo, centres.min(axis=0), rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(hi, centres.max(axis=0), rtol=1e-3, atol=1e-3)


def test_threads_option_and_variable(folding_volume):
    d = folding_volume
    args = ["deform", str(d / "image.vti"), "--scene", str(d / "scene.json"),
            "-o", str(d / "t.vti"), "-q", "--allow-folds"]  # fmt: skip
    ok = _cli(*args, "--threads", "1")
    assert ok.returncode == 0, ok.stderr
    bad = _cli(*args, "--threads", "0")
    assert bad.returncode == 2 and "--threads: expected a positive integer" in bad.stderr
    env = _cli(*args, env={"VHM_THREADS": "many"})
    assert env.returncode == 1
    assert env.stderr.strip().splitlines() == [
        "vhm-viz deform: error: VHM_THREADS must be a positive integer; got 'many'"
    ]


def test_first_run_says_it_compiles_once(folding_volume, tmp_path):
    """An empty compiled-code cache (a fresh process, as on a new machine): the first run
    says it compiles, once, before the work (the progress lines); a run ended by an input
    error, or one that finds its kernels cached, says nothing of it."""
    d = folding_volume
    pv.PolyData(pv.read(d / "image.vti").points).save(tmp_path / "points.vtp")
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    args = ["deform", str(tmp_path / "points.vtp"), "--scene", str(d / "scene.json"),
            "-o", str(tmp_path / "out.vtp"), "--allow-folds"]  # fmt: skip
    missing = _cli(*args[:1], str(d / "missing.vtp"), *args[2:], env=env)
    assert missing.returncode == 1 and "compiling" not in missing.stderr  # nothing compiled
    first = _cli(*args, env=env)
    assert first.returncode == 0, first.stderr
    assert first.stderr.count("compiling numeric kernels once") == 1
    assert first.stderr.index("compiling numeric kernels once") < first.stderr.index("solving")
    again = _cli(*args, env=env)
    assert again.returncode == 0 and "compiling" not in again.stderr


def test_the_lattices_proof_leaves_the_fold_warning_as_it_was(folding_volume, tmp_path,
                                                               monkeypatch, capsys):  # fmt: skip
    # the cells proven unfolded are not measured: the same warning as measuring them all
    from vhm_viz import folds
    from vhm_viz.cli import main

    d = folding_volume
    args = ["deform", str(d / "image.vti"), "--scene", str(d / "scene.json"), "-q"]
    args.append("--allow-folds")
    assert main([*args, "-o", str(tmp_path / "all.vts")]) == 0
    every = capsys.readouterr().err
    monkeypatch.setattr(folds, "PROOF_MIN_CELLS", 0)
    assert main([*args, "-o", str(tmp_path / "proven.vts")]) == 0
    proven = capsys.readouterr().err
    assert "cells inverted" in every
    assert proven.splitlines()[0] == every.splitlines()[0]
