"""Fuzz: mutated models and scenes through ``vhm-viz deform``.

Several hundred versions of the bundled models, the formats derived from them, the scenes
and the files the scenes reference -- truncated, bit-flipped, or under the wrong suffix --
go through ``vhm_viz.cli.main(["deform", ...])``, the path the command line uses, in one
separate process (so that a crash shows as that process's exit status and names the case
it was in). Every case must end with a readable output and exit 0, or with exactly one
line on stderr and a non-zero exit and no output; the process must survive all of them;
no input may change (checksums before and after).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from conftest import box_cage, data_path, subprocess_env  # noqa: E402

RUNNER = r'''
import contextlib, io, json, sys
from pathlib import Path

from vhm_viz.cli import main
from vhm_viz.io import read_dataset

cases = json.loads(Path(sys.argv[1]).read_text())
with open(sys.argv[2], "w") as log:
    for case in cases:
        log.write(json.dumps({"started": case["name"]}) + "\n")
        log.flush()
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            status = main(case["argv"])
        out = Path(case["output"])
        points = None
        if out.exists():
            with contextlib.redirect_stderr(io.StringIO()):
                points = read_dataset(out).n_points
        log.write(json.dumps({"name": case["name"], "status": status, "stderr": err.getvalue(),
                              "output_points": points}) + "\n")
        log.flush()
'''


def _digest(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _bases(folder: Path) -> list[dict]:
    """The unmutated cases: a scene, its data, and the files the scene references."""
    bar = pv.read(data_path("bar", "bar_dense.obj"))
    shutil.copy(data_path("bar", "bar_dense.obj"), folder / "bar.obj")
    shutil.copy(data_path("bar", "bar_cage_3d.obj"), folder / "bar_cage.obj")
    bar.save(folder / "bar.ply", binary=True)
    bar.save(folder / "bar_ascii.ply", binary=False)
    bar.save(folder / "bar.vtk", binary=True)
    bar.save(folder / "bar.vtp")
    bar.save(folder / "bar.stl")
    axis = np.column_stack([np.zeros(5), np.linspace(0.0, 3.7, 5), np.zeros(5)])
    (folder / "bar_scene.json").write_text(json.dumps({
        "format": "vhm_viz.scene", "version": 1, "cage": "bar_cage.obj",
        "anchors": axis.tolist(),
        "constraints": {"positions": [[0, -0.9, 0], [0, 4.6, 0]],
                        "targets": [[0, -0.9, 0], [0.3, 4.5, 0]]},
    }))  # fmt: skip

    for name in ("hand.obj", "cage.obj", "polylines.off"):
        shutil.copy(data_path("hand", name), folder / name)
    (folder / "hand_scene.json").write_text(json.dumps({
        "format": "vhm_viz.scene", "version": 1, "cage": "cage.obj",
        "anchors": {"polylines": "polylines.off", "count": 10},
        "constraints": {"positions": [[3.0, 0.9, 18.4], [2.7, 1.9, 12.5]],
                        "targets": [[3.3, 1.0, 18.3], [2.7, 1.9, 12.5]]},
        "solver": {"max_iterations": 20000},
    }))  # fmt: skip

    shutil.copy(data_path("tets", "tetraMesh_inverted.vtk"), folder / "tets.vtk")
    shutil.copy(data_path("volumes", "HeadMRVolume.mhd"), folder / "head.mhd")
    shutil.copy(data_path("volumes", "HeadMRVolume.raw"), folder / "HeadMRVolume.raw")
    for name, path in (("tets", folder / "tets.vtk"), ("head", folder / "head.mhd")):
        b = np.array(pv.read(path).bounds)
        lo, hi = b[0::2], b[1::2]
        v, f = box_cage(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo))
        c = 0.5 * (lo + hi)
        (folder / f"{name}_scene.json").write_text(json.dumps({
            "format": "vhm_viz.scene", "version": 1,
            "cage": {"vertices": v.tolist(), "faces": f.tolist()},
            "anchors": (c + 0.1 * (hi - lo) * np.eye(3)).tolist(),
            "constraints": {"positions": [c.tolist()],
                            "targets": [(c + 0.01 * (hi - lo)).tolist()]},
        }))  # fmt: skip
    return [
        *({"scene": "bar_scene.json", "data": d, "out": ".vtp", "files": ["bar_cage.obj"]}
          for d in ("bar.obj", "bar.ply", "bar_ascii.ply", "bar.vtk", "bar.vtp", "bar.stl")),
        {"scene": "hand_scene.json", "data": "hand.obj", "out": ".vtp",
         "files": ["cage.obj", "polylines.off"]},
        {"scene": "tets_scene.json", "data": "tets.vtk", "out": ".vtu", "files": []},
        {"scene": "head_scene.json", "data": "head.mhd", "out": ".vts",
         "files": ["HeadMRVolume.raw"]},
    ]  # fmt: skip


def _mutations(blob: bytes, rng) -> list[tuple[str, bytes]]:
    """Truncations at four places and bit flips of one to 64 bits (text and binary)."""
    out = []
    for frac in (0.0, 0.1, 0.5, 0.97):
        out.append((f"cut{frac}", blob[: int(len(blob) * frac)]))
    for k, flips in enumerate((1, 1, 2, 2, 4, 8, 16, 64)):
        b = bytearray(blob)
        # half of the flips in the first KiB, where the headers (and their counts) are
        pos = rng.integers(0, min(len(b), 1024) if k % 2 else len(b), flips)
        for p, bit in zip(pos, rng.integers(0, 8, flips), strict=True):
            b[p] ^= 1 << int(bit)
        out.append((f"flip{flips}.{k}", bytes(b)))
    return out


def _cases(folder: Path) -> list[dict]:
    rng = np.random.default_rng(12)
    cases = []

    def add(name, case_dir: Path, scene, data, out_suffix):
        cases.append({
            "name": name,
            "argv": ["deform", str(case_dir / data), "--scene", str(case_dir / scene),
                     "-o", str(case_dir / f"out{out_suffix}"), "-q"],
            "output": str(case_dir / f"out{out_suffix}"),
            "dir": str(case_dir),
        })  # fmt: skip

    bases = _bases(folder / "base")

    def case_dir(name: str, base: dict) -> Path:
        """A folder with the files of one base case (scene, data, what the scene reads)."""
        d = folder / "cases" / name
        d.mkdir(parents=True)
        for f in (base["scene"], base["data"], *base["files"]):
            shutil.copy(folder / "base" / f, d / f)
        return d

    for base in bases:
        scene, data, suffix = base["scene"], base["data"], base["out"]
        add(f"pristine {data}", case_dir(f"pristine_{data}", base), scene, data, suffix)
        targets = [data, "HeadMRVolume.raw"] if data == "head.mhd" else [data]
        for target in targets:
            blob = (folder / "base" / target).read_bytes()
            for tag, mutated in _mutations(blob, rng):
                d = case_dir(f"{target}_{tag}", base)
                (d / target).write_bytes(mutated)
                add(f"{target} {tag}", d, scene, data, suffix)
        # the right bytes under the wrong suffix, and the wrong kind of file for the scene
        wrong = {".obj": ".ply", ".ply": ".vtk", ".vtk": ".stl", ".vtp": ".obj",
                 ".stl": ".vtp", ".mhd": ".nii"}[Path(data).suffix]  # fmt: skip
        d = case_dir(f"{data}_as{wrong}", base)
        shutil.copy(d / data, d / f"renamed{wrong}")
        add(f"{data} as {wrong}", d, scene, f"renamed{wrong}", suffix)
    for scene in ("bar_scene.json", "hand_scene.json", "tets_scene.json", "head_scene.json"):
        base = next(b for b in bases if b["scene"] == scene)
        referenced = [f for f in base["files"] if not f.endswith(".raw")]
        for target in [scene, *referenced]:
            blob = (folder / "base" / target).read_bytes()
            for tag, mutated in _mutations(blob, rng):
                d = case_dir(f"{target}_{tag}_{scene}", base)
                (d / target).write_bytes(mutated)
                add(f"{target} {tag}", d, scene, base["data"], base["out"])
        d = case_dir(f"{scene}_swapped", base)
        add(f"{scene} given as the data", d, base["data"], scene, base["out"])
    return cases


def test_fuzz_deform_never_crashes_never_writes_inputs(tmp_path):
    (tmp_path / "base").mkdir()
    cases = _cases(tmp_path)
    assert len(cases) >= 200
    before = {c["name"]: _digest(Path(c["dir"])) for c in cases}
    (tmp_path / "cases.json").write_text(json.dumps(cases))
    env = subprocess_env()
    t0 = time.perf_counter()
    res = subprocess.run(
        [sys.executable, "-c", RUNNER, str(tmp_path / "cases.json"), str(tmp_path / "log.jsonl")],
        capture_output=True, text=True, env=env, timeout=900,
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    results = {r["name"]: r for r in log if "status" in r}
    crashed = [r["started"] for r in log if "started" in r and r["started"] not in results]
    assert res.returncode == 0 and not crashed, (
        f"the process ended with status {res.returncode} in case {crashed}: {res.stderr[-2000:]}"
    )
    assert len(results) == len(cases)
    outcomes = {"written": 0, "refused": 0}
    for case in cases:
        r = results[case["name"]]
        lines = [ln for ln in r["stderr"].splitlines() if not ln.startswith("vhm-viz: note: ")]
        if r["status"] == 0:
            assert r["output_points"], case["name"]  # a valid output, readable again
            assert not lines, (case["name"], lines)
            outcomes["written"] += 1
        else:
            one_line = len(lines) == 1 and lines[0].startswith("vhm-viz deform: ")
            assert one_line, (case["name"], lines)
            assert r["output_points"] is None, case["name"]  # nothing written
            outcomes["refused"] += 1
        after = _digest(Path(case["dir"]))
        after.pop(Path(case["output"]).name, None)
        assert after == before[case["name"]], f"{case['name']}: an input changed"
        assert not [n for n in after if Path(n).name.startswith(".")], case["name"]
    assert all(results[c["name"]]["status"] == 0 for c in cases if c["name"].startswith("pristine"))
    print(f"\nfuzz: {len(cases)} cases, {outcomes}, {seconds:.1f} s")
