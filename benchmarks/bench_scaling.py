"""How the volume engine scales with threads: warp and resample of the 256^3 embryo.

The numeric core alone (no VTK): :class:`~vhm_viz.core.volume.VolumeDeformation` on the
embryo (``../shared/data/volumes/embryo.slc``) with the padded box cage bent and twisted
that ``bench_cli.py`` makes (:func:`bench_cli.box_scene` on the volume's bounds), at the
default tolerance (0.05 voxel). The map is solved once and saved; then each thread count
runs in a fresh process (numba's thread pool is sized when it starts), its count set
through ``VHM_THREADS``, the variable that :func:`vhm_viz.core.threads.use_threads`
reads as the command line does. Each process loads the compiled kernels on a small
volume first, then times ``-r`` runs of each operation, every one with a fresh engine:

* **warp**: a lattice without pre-images (``pre_images=False``, as the warp filter
  builds it) and the forward warp of every voxel;
* **resample**: the lattice with pre-images and the pull-back of every output voxel
  (trilinear sampling).

Each is split into the lattice build (its ``stats["seconds"]``) and the rest (the warp
kernel; the pull-back, its checks and the sampling). The table gives the median and the
spread (min-max) of the wall times, the speed-up over one thread and the efficiency
(speed-up / threads), for 1, 2, 4, ... threads up to the CPUs this process may use
(``os.sched_getaffinity``) and that count itself. The load average is printed before and
after each thread count: on a shared machine, compare runs made at a low load.

``--compare DIR`` also runs another checkout's vhm_viz (say, the main branch's) for each
thread count, alternating with this one's, and gives its rows beside (an A/B in one run,
under the same load).

    python benchmarks/bench_scaling.py              # -r 3, 1, 2, 4, ... threads
    python benchmarks/bench_scaling.py -r 5 --threads 1 2
    python benchmarks/bench_scaling.py --only warp
    python benchmarks/bench_scaling.py --threads 1 2 --only resample --compare ../main
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data, print_table  # noqa: E402
from bench_cli import bounds_of, box_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OPERATIONS = ("warp", "resample")


def solve(embryo: Path, path: Path) -> None:
    """Solve the box-cage bend of the embryo and save its cage and coefficients."""
    from vhm_viz.io import read_dataset
    from vhm_viz.scene import Scene

    img = read_dataset(str(embryo))
    scene = Scene.from_dict(box_scene(bounds_of(embryo)))
    solved = scene.solve_map(img, reuse_stored=False)
    hm = solved.harmonic_map
    np.savez(path, vertices=hm.cage.vertices, faces=hm.cage.faces, z=hm.coefficients)


def child(embryo: Path, saved: Path, repeats: int, operations) -> dict:
    """Time the operations in this process (its thread count from ``VHM_THREADS``)."""
    from vhm_viz import Cage, HarmonicMap
    from vhm_viz.core.image import ImageGeometry
    from vhm_viz.core.threads import use_threads
    from vhm_viz.core.volume import VolumeDeformation
    from vhm_viz.io import read_dataset

    threads = use_threads()
    img = read_dataset(str(embryo))
    z = np.load(saved)
    hm = HarmonicMap(Cage(z["vertices"], z["faces"]), z["z"])
    geo = ImageGeometry(img.origin, img.spacing, img.dimensions, img.direction_matrix)
    values = {"scalars": np.asarray(img.active_scalars)}
    # the compiled kernels loaded from the cache on a coarse copy of the grid first
    coarse = ImageGeometry(img.origin, np.asarray(img.spacing) * 4,
                           -(-np.asarray(img.dimensions) // 4), img.direction_matrix)  # fmt: skip
    VolumeDeformation(hm, coarse, pre_images=False).warp()
    small = np.zeros(int(np.prod(coarse.dimensions)), dtype=np.asarray(img.active_scalars).dtype)
    VolumeDeformation(hm, coarse).resample({"scalars": small})
    out: dict = {"threads": threads, "load": [os.getloadavg()[0]]}
    for op in operations:
        runs = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            if op == "warp":
                vol = VolumeDeformation(hm, geo, pre_images=False)
                vol.warp()
            else:
                vol = VolumeDeformation(hm, geo)
                vol.resample(values)
            total = time.perf_counter() - t0
            build = float(vol.lattice.stats["seconds"])
            runs.append({"total": total, "build": build, "rest": total - build})
            out[f"{op} evaluations"] = int(vol.lattice.stats["evaluations"])
            del vol
        out[op] = runs
        out["load"].append(os.getloadavg()[0])
    return out


def thread_counts(limit: int) -> list[int]:
    """1, 2, 4, ... below ``limit``, and ``limit`` itself."""
    counts, n = [], 1
    while n < limit:
        counts.append(n)
        n *= 2
    return counts + [limit]


def spread(times: list[float]) -> str:
    """``median (min-max)`` in seconds."""
    return f"{statistics.median(times):.3g} s ({min(times):.3g}-{max(times):.3g})"


def main(argv=None) -> int:
    """Run the thread counts in fresh processes and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-r", "--repeats", type=int, default=3, help="timed runs per operation")
    ap.add_argument("--threads", type=int, nargs="+", help="thread counts (default 1, 2, 4, ...)")
    ap.add_argument("--only", choices=OPERATIONS, help="one operation only")
    ap.add_argument("--json", type=Path, help="write the raw results here")
    ap.add_argument("--compare", type=Path, help="another checkout, run alternately")
    ap.add_argument("--child", nargs=2, metavar=("MAP", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    embryo = data("volumes", "embryo.slc")
    operations = OPERATIONS if args.only is None else (args.only,)
    if args.child:
        result = child(embryo, Path(args.child[0]), args.repeats, operations)
        Path(args.child[1]).write_text(json.dumps(result))
        return 0
    counts = args.threads or thread_counts(len(os.sched_getaffinity(0)))
    repos = [ROOT] + ([args.compare.resolve()] if args.compare else [])
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_scaling_") as scratch:
        saved = Path(scratch) / "map.npz"
        solve(embryo, saved)
        for n in counts:
            for repo in repos:
                print(f"{n} threads [{repo.name}], load average before: {os.getloadavg()}",
                      flush=True)  # fmt: skip
                out = Path(scratch) / f"{n}-{repos.index(repo)}.json"
                env = {**os.environ, "VHM_THREADS": str(n), "PYTHONPATH": str(repo)}
                cmd = [sys.executable, __file__, "-r", str(args.repeats), "--child", str(saved),
                       str(out)] + (["--only", args.only] if args.only else [])  # fmt: skip
                subprocess.run(cmd, env=env, check=True)
                results.append({**json.loads(out.read_text()), "repo": repo.name})
                print(f"  load average after: {os.getloadavg()}", flush=True)
    rows = []
    for repo in repos:
        mine = [res for res in results if res["repo"] == repo.name]
        base = {op: statistics.median(r["total"] for r in mine[0][op]) for op in operations}
        base_threads = mine[0]["threads"]
        for res in mine:
            row = [str(res["threads"]) + (f" [{repo.name}]" if len(repos) > 1 else "")]
            for op in operations:
                totals = [r["total"] for r in res[op]]
                speed = base[op] / statistics.median(totals)
                row += [
                    spread(totals),
                    f"{statistics.median(r['build'] for r in res[op]):.3g} s",
                    f"{statistics.median(r['rest'] for r in res[op]):.3g} s",
                    f"{speed:.2f}x",
                    f"{100 * speed * base_threads / res['threads']:.0f}%",
                ]
            row.append(" ".join(f"{x:.2f}" for x in res["load"]))
            rows.append(row)
    headers = ["threads"]
    for op in operations:
        headers += [f"{op}, median (min-max)", "lattice", "rest", "speed-up", "efficiency"]
    headers.append("load (1 min) start, after each")
    evaluations = ", ".join(f"{op} {results[0][f'{op} evaluations']}" for op in operations)
    print(f"\nembryo 256^3, box-cage bend, tolerance 0.05 voxel, n={args.repeats}; "
          f"exact evaluations: {evaluations}")  # fmt: skip
    print_table(headers, rows)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
