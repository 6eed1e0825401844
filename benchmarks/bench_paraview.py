"""ParaView: serial ``pvbatch`` against ``mpiexec -n 2 pvbatch`` on real volumes.

For the CT head (``vhm_viz/scenes/head_scene.json``) and the 256^3 embryo (the bend of
``bench_volume.py``: automatic cage and anchors computed once here, then written into an
explicit scene, since under MPI the automatic cage is refused), each scene holding its
solved map as a scene saved after a solve does (``--solve``: without it, so that every
process builds and solves the scene), each of

* ``warp``: VHM Harmonic Deformation of the image (a structured grid, each rank its piece
  of the extent, each building only its part of the lattice, the ranks sharing the exact
  evaluations);
* ``resample``: VHM Resample To Image (each rank its piece of the output; each rank
  builds the lattice of its share of the input's layers, the ranks sharing the exact
  evaluations, then gathers from the others the leaves that reach its share of the
  output planes -- shares of the pull-back work and of the leaves it needs, whichever
  pieces they belong to --
  reads only its input window, and sends the other ranks their voxels among its planes)

runs in ``pvbatch --symmetric`` (1 rank) and ``mpiexec -n 2 pvbatch --symmetric`` (every
rank runs the script): the filter's update time (the
slowest rank's, between barriers, from the filter's creation: the resample's information
pass builds the lattice) and each rank's peak resident memory (``VmHWM`` of its own
process, ParaView itself included, and the part of it above the resident memory before
the filter ran: what the filter needs), median and min-max over ``--repeats`` runs,
after one warm-up run (numba's cache). Ranks run one thread each (as the tests do); the
serial run is timed with one thread (the MPI scaling) and with every core's threads
(numba's default, what a user of serial pvbatch gets). The load average is printed: the
machine is shared.

Run: ``python benchmarks/bench_paraview.py [--repeats 3] [--only head|embryo]
[--ops warp,resample] [--solve] [--env NAME=VALUE]`` (from the project root, with the
project's venv). ``--env MALLOC_MMAP_THRESHOLD_=262144`` fixes glibc's mmap threshold: its
default rises to 32 MB once a large block is freed, after which mid-sized arrays come from
the heap, and what the heap keeps then depends on the order of earlier allocations (the
serial embryo's peak varies by tens of MB between otherwise equal runs).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from _common import data, print_table, summary

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import json, sys, time
import paraview.simple as pvs
from vtkmodules.vtkParallelCore import vtkMultiProcessController as C

def status(key):
    with open("/proc/self/status") as fh:
        return [int(ln.split()[1]) / 1024.0 for ln in fh if ln.startswith(key + ":")][0]

cfg = json.load(open(sys.argv[1]))
ctrl = C.GetGlobalController()
rank = 0 if ctrl is None else ctrl.GetLocalProcessId()
img = pvs.OpenDataFile(cfg["input"])
cage = pvs.OpenDataFile(cfg["cage"])
pvs.UpdatePipeline(proxy=img)
pvs.UpdatePipeline(proxy=cage)
before = status("VmRSS")
if ctrl is not None:
    ctrl.Barrier()
t0 = time.perf_counter()
# the filter is made inside the timed span: its information pass (the resample's output
# grid, which needs the lattice) runs when its properties are set
# every property at creation, as the GUI's Apply does (set one by one, each would run
# the information pass). The embryo's cage holds its body only: the voxels around it stay
# in place (as in bench_volume.py); with the default (Error) the update would stop
flt = getattr(pvs, cfg["filter"])(Input=img, Cage=cage, SceneFile=cfg["scene"],
                                  OutsidePolicy="Pass through")
pvs.UpdatePipeline(proxy=flt)
if ctrl is not None:
    ctrl.Barrier()
dt = time.perf_counter() - t0
n = flt.GetDataInformation().GetNumberOfPoints()  # every rank's, gathered
print(f"bench-rank {rank} seconds {dt:.3f} rss_mb {status('VmHWM'):.0f} "
      f"before_mb {before:.0f} points {n}", flush=True)
"""

def embryo_scene(folder: Path) -> tuple[Path, Path]:
    """The embryo bend of bench_volume.py as an explicit scene (inline cage) + cage file.

    The scene holds its solved map (:meth:`Scene.record_map`), as one saved after a solve
    does; :func:`without_map` makes the copy without it.
    """
    scene, cage_path = folder / "embryo_scene_map.json", folder / "embryo_cage.obj"
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
        sc = Scene.from_deformer(dfm)
        assert sc.record_map(dfm), "the embryo's bend did not converge"
        sc.save(scene)
    return scene, cage_path


def with_map(scene: Path, folder: Path) -> Path:
    """A copy of ``scene`` (cage and anchors made absolute) holding its solved map."""
    from vhm_viz.scene import Scene

    path = folder / f"{scene.stem}_map.json"
    if not path.exists():
        sc = Scene.load(scene)
        for field in (sc.cage, sc.anchors):
            if "path" in field:
                field["path"] = str(sc._resolve_path(field["path"]))
        dfm = sc.build()
        assert sc.solve(dfm)[-1].converged and sc.record_map(dfm)
        sc.save(path)
    return path


def without_map(scene: Path, folder: Path) -> Path:
    """A copy of ``scene`` without its stored map: the filter builds and solves the scene."""
    from vhm_viz.scene import Scene

    path = folder / f"{scene.stem}_solve.json"
    sc = Scene.load(scene)
    sc.stored_map = None
    sc.save(path)
    return path


def embryo_vti(folder: Path) -> Path:
    """The embryo as .vti: ParaView 5.11 has no reader registered for .slc."""
    path = folder / "embryo.vti"
    if not path.exists():
        from vhm_viz.io import read_dataset, write_dataset

        write_dataset(path, read_dataset(data("volumes", "embryo.slc")))
    return path


def voxel_count(path: Path) -> int:
    from vhm_viz.io import read_dataset

    return int(read_dataset(path).n_points)


def run_once(cfg: dict, ranks: int, env: dict, folder: Path, threads: int | None = None):
    """Each rank's ``(seconds, peak RSS MB)`` of one pvbatch run.

    ``threads``: numba/BLAS threads of a single process (default: all cores); MPI ranks
    always run one thread each (:func:`~vhm_viz.filters.mpi.mpi_command`).
    """
    path = folder / "cfg.json"
    path.write_text(json.dumps(cfg))
    script = folder / "bench_pv.py"
    script.write_text(SCRIPT)
    from vhm_viz.filters.mpi import mpi_command

    # --symmetric: every rank runs the script (without it only rank 0 does, and its
    # barriers wait forever for the satellites, which serve the pipeline instead)
    cmd, env = mpi_command(["pvbatch", "--symmetric", str(script), str(path)], ranks, env)
    if ranks == 1 and threads is not None:
        env = {**env, "NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads),
               "OPENBLAS_NUM_THREADS": str(threads)}  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    # ranks print at once: their lines may run into each other
    found = re.findall(
        r"bench-rank (\d+) seconds ([\d.]+) rss_mb (\d+) before_mb (\d+) points (\d+)",
        done.stdout,
    )
    # a filter error leaves an empty output and pvbatch still exits 0: time only runs
    # that made the whole output, the same in every run (each rank reports its own
    # piece's points in symmetric mode); a serial warp deforms every voxel
    points = tuple(int(n) for _, n in sorted((int(r), n) for r, *_, n in found))
    if done.returncode != 0 or len(found) != ranks or 0 in points:
        raise RuntimeError(done.stdout[-3000:] + done.stderr[-3000:])
    first = (cfg["voxels"],) if ranks == 1 and "voxels" in cfg else points
    expected = tuple(cfg.setdefault(f"points_{ranks}", list(first)))
    if points != expected:
        raise RuntimeError(f"{cfg['filter']} made {points} points, not {expected}")
    return [(float(t), float(m), float(m) - float(b)) for _, t, m, b, _ in found]


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
    ap.add_argument("--solve", action="store_true",
                    help="scenes without their stored map: every process solves the scene")
    ap.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                    help="extra environment of the pvbatch runs (e.g. "
                         "MALLOC_MMAP_THRESHOLD_=262144: glibc's fixed mmap threshold)")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "vhm_bench_paraview"))
    args = ap.parse_args()
    folder = Path(args.cache)
    folder.mkdir(parents=True, exist_ok=True)
    env = paraview_env()
    env.update(kv.split("=", 1) for kv in args.env)
    cases = {}
    if args.only in (None, "head"):
        cases["head"] = (data("volumes", "headsq_64x64x93.vti"),
                         with_map(ROOT / "vhm_viz/scenes/head_scene.json", folder),
                         ROOT / "vhm_viz/scenes/head_cage.obj")  # fmt: skip
    if args.only in (None, "embryo"):
        scene, cage = embryo_scene(folder)
        cases["embryo"] = (embryo_vti(folder), scene, cage)
    if args.solve:
        cases = {k: (i, without_map(s, folder), c) for k, (i, s, c) in cases.items()}
    filters = {"warp": "VHMHarmonicDeformation", "resample": "VHMResampleToImage"}
    rows = []
    loads = [os.getloadavg()[0]]
    for key, (inp, scene, cage) in cases.items():
        for op in args.ops.split(","):
            cfg = {"input": str(inp), "scene": str(scene), "cage": str(cage),
                   "filter": filters[op]}  # fmt: skip
            if op == "warp":  # one deformed point per voxel
                cfg["voxels"] = voxel_count(inp)
            res = {}
            # serial with one thread (what each MPI rank gets), serial with every core's
            # threads (numba's default), and 2 ranks of one thread each
            for label, ranks, threads in (("1x1", 1, 1), ("1xN", 1, None), ("2x1", 2, 1)):
                run_once(cfg, ranks, env, folder, threads)  # warm-up: numba's cache, files
                runs = [run_once(cfg, ranks, env, folder, threads) for _ in range(args.repeats)]
                loads.append(os.getloadavg()[0])
                res[label] = (
                    [max(t for t, *_ in r) for r in runs],
                    [max(m for _, m, _ in r) for r in runs],
                    [max(g for *_, g in r) for r in runs],
                    [[round(t, 2) for t, *_ in r] for r in runs],
                )
            t11, t1n, t2 = (np.median(res[k][0]) for k in ("1x1", "1xN", "2x1"))
            m1, m2 = np.median(res["1x1"][1]), np.median(res["2x1"][1])
            g1, g2 = np.median(res["1x1"][2]), np.median(res["2x1"][2])
            rows.append([key, op, summary(res["1x1"][0]), summary(res["1xN"][0]),
                         summary(res["2x1"][0]), f"{t11 / t2:.2f}x / {t1n / t2:.2f}x",
                         f"{m1:.0f} / {m2:.0f} ({100 * m2 / m1:.0f}%)",
                         f"{g1:.0f} / {g2:.0f} ({100 * g2 / g1:.0f}%)"])  # fmt: skip
            print(f"{key} {op}: seconds per rank of the 2-rank runs {res['2x1'][3]}; "
                  f"the filter's MB per run, 1 rank {res['1x1'][2]}, largest rank of 2 "
                  f"{res['2x1'][2]}", flush=True)  # fmt: skip
    print_table(["volume", "operation", "1 rank, 1 thread (s)",
                 f"1 rank, {os.cpu_count()} threads (s)", "2 ranks, 1 thread each (s)",
                 "speed-up vs 1 thread / vs all threads",
                 "peak RSS (MB): 1 rank / per rank of 2",
                 "of which the filter (MB): 1 rank / per rank of 2"], rows)  # fmt: skip
    scenes = "solved by every process" if args.solve else "with their stored map"
    print(f"load average (1 min) during the runs: {min(loads):.1f}-{max(loads):.1f} "
          f"on {os.cpu_count()} cores; scenes {scenes}; extra environment "
          f"{args.env or 'none'}")


if __name__ == "__main__":
    main()
