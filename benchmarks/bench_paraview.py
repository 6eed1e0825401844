"""ParaView: serial ``pvbatch`` against ``mpiexec -n 2 pvbatch`` on real volumes.

For the CT head (``docs/examples/head_scene.json``) and the 256^3 embryo (the bend of
``bench_volume.py``: automatic cage and anchors computed once here, then written into an
explicit scene, since under MPI the automatic cage is refused), each of

* ``warp``: VHM Harmonic Deformation of the image (a structured grid, each rank its piece
  of the extent, each building only its part of the lattice);
* ``resample``: VHM Resample To Image (each rank its piece of the output; the lattice is
  built whole on every rank, each rank reads only its input window)

runs in ``pvbatch`` (1 rank) and ``mpiexec -n 2 pvbatch``: the filter's update time (the
slowest rank's, between barriers) and each rank's peak resident memory (``ru_maxrss`` of
its own process, ParaView itself included), median and min-max over ``--repeats`` runs,
after one warm-up run (numba's cache). Ranks run one thread each (as the tests do); the
serial run uses both cores' threads. The load average is printed: the machine is shared.

Run: ``python benchmarks/bench_paraview.py
[--repeats 3] [--only head|embryo]`` (from the project root, with the project's venv).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from _common import data, print_table, summary

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import json, resource, sys, time
import paraview.simple as pvs
from paraview import servermanager
from vtkmodules.vtkParallelCore import vtkMultiProcessController as C

cfg = json.load(open(sys.argv[1]))
ctrl = C.GetGlobalController()
rank = 0 if ctrl is None else ctrl.GetLocalProcessId()
img = pvs.OpenDataFile(cfg["input"])
cage = pvs.OpenDataFile(cfg["cage"])
flt = getattr(pvs, cfg["filter"])(Input=img, Cage=cage)
flt.SceneFile = cfg["scene"]
pvs.UpdatePipeline(proxy=img)
pvs.UpdatePipeline(proxy=cage)
if ctrl is not None:
    ctrl.Barrier()
t0 = time.perf_counter()
pvs.UpdatePipeline(proxy=flt)
if ctrl is not None:
    ctrl.Barrier()
dt = time.perf_counter() - t0
n = flt.GetDataInformation().GetNumberOfPoints()
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print(f"bench-rank {rank} seconds {dt:.3f} rss_mb {rss:.0f} points {n}", flush=True)
"""


def embryo_scene(folder: Path) -> tuple[Path, Path]:
    """The embryo bend of bench_volume.py as an explicit scene (inline cage) + cage file."""
    scene, cage_path = folder / "embryo_scene.json", folder / "embryo_cage.obj"
    if not scene.exists() or not cage_path.exists():
        sys.path.insert(0, str(Path(__file__).parent))
        from bench_volume import bend_deformer

        from vhm_viz import auto_cage
        from vhm_viz.io import read_dataset, write_cage
        from vhm_viz.scene import Scene

        img = read_dataset(data("volumes", "embryo.slc"))
        cage = auto_cage(img, threshold="otsu")
        dfm, _ = bend_deformer(img, cage, "otsu")
        write_cage(cage_path, cage)
        Scene.from_deformer(dfm).save(scene)
    return scene, cage_path


def run_once(cfg: dict, ranks: int, env: dict, folder: Path) -> list[tuple[float, float]]:
    path = folder / "cfg.json"
    path.write_text(json.dumps(cfg))
    script = folder / "bench_pv.py"
    script.write_text(SCRIPT)
    from vhm_viz.filters._parallel import mpi_command

    cmd, env = mpi_command(["pvbatch", str(script), str(path)], ranks, env)
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    lines = [ln.split() for ln in done.stdout.splitlines() if ln.startswith("bench-rank")]
    if done.returncode != 0 or len(lines) != ranks:
        raise RuntimeError(done.stdout[-3000:] + done.stderr[-3000:])
    return [(float(ln[3]), float(ln[5])) for ln in lines]


def paraview_env() -> dict:
    out = subprocess.run(["bash", str(ROOT / "plugins" / "paraview-env.sh")],
                         capture_output=True, text=True, check=True)  # fmt: skip
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    for line in out.stdout.splitlines():
        dump = subprocess.run(["bash", "-c", f"{line}; env -0"], capture_output=True, env=env,
                              check=True)  # fmt: skip
        env = dict(kv.split("=", 1) for kv in dump.stdout.decode().split("\0") if "=" in kv)
    return env


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", choices=["head", "embryo"])
    ap.add_argument("--ops", default="warp,resample")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "vhm_bench_paraview"))
    args = ap.parse_args()
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    env = paraview_env()
    cases = {}
    if args.only in (None, "head"):
        cases["head"] = (data("volumes", "headsq_64x64x93.vti"),
                         ROOT / "docs/examples/head_scene.json",
                         ROOT / "docs/examples/head_cage.obj")  # fmt: skip
    if args.only in (None, "embryo"):
        scene, cage = embryo_scene(folder)
        cases["embryo"] = (data("volumes", "embryo.slc"), scene, cage)
    filters = {"warp": "VHMHarmonicDeformation", "resample": "VHMResampleToImage"}
    rows = []
    loads = [os.getloadavg()[0]]
    for key, (inp, scene, cage) in cases.items():
        for op in args.ops.split(","):
            cfg = {"input": str(inp), "scene": str(scene), "cage": str(cage),
                   "filter": filters[op]}  # fmt: skip
            res = {}
            for ranks in (1, 2):
                run_once(cfg, ranks, env, folder)  # warm-up: numba's cache, file cache
                runs = [run_once(cfg, ranks, env, folder) for _ in range(args.repeats)]
                loads.append(os.getloadavg()[0])
                res[ranks] = (
                    [max(t for t, _ in r) for r in runs],
                    [max(m for _, m in r) for r in runs],
                )
            t1, t2 = np.median(res[1][0]), np.median(res[2][0])
            m1, m2 = np.median(res[1][1]), np.median(res[2][1])
            rows.append([key, op, summary(res[1][0]), summary(res[2][0]), f"{t1 / t2:.2f}x",
                         f"{m1:.0f}", f"{m2:.0f}", f"{100 * m2 / m1:.0f}%"])  # fmt: skip
    print_table(["volume", "operation", "1 rank (s)", "2 ranks (s)", "speed-up",
                 "peak RSS 1 rank (MB)", "per rank, 2 ranks (MB)", "ratio"], rows)  # fmt: skip
    print(f"load average (1 min) during the runs: {min(loads):.1f}-{max(loads):.1f} "
          f"on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
