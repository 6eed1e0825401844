"""Time the ``vhm-viz`` commands users run, end to end, each in a fresh process.

Every case writes its scene into a scratch folder (nothing is tuned for the data: a box
cage padded around the data's bounds with anchors on its long axis, the data's automatic
cage, or a hand-made cage from ``../shared/data``; one end bent and twisted), then runs
``python -m vhm_viz.cli ...`` as a child process: read, solve, map, checks, write. A
warm-up run fills the compiled-code cache first (``--cold`` instead times runs with an
empty cache: ``--cold --only demo`` is the first run on a fresh machine). For each case
the table gives the wall time (median and spread), the process's CPU time (user + system,
``wait4``'s ``ru_utime + ru_stime``: compiling is single-threaded, so on a shared machine
it is the steadier measure of a cold run), the peak resident memory (``ru_maxrss``) and,
where the command prints ``--timings``, the stage breakdown.

    python benchmarks/bench_cli.py                     # the default set
    python benchmarks/bench_cli.py --only ct           # cases whose name contains "ct"
    python benchmarks/bench_cli.py --repo ../old -r 3  # another checkout's vhm_viz
    python benchmarks/bench_cli.py --compare ../old    # alternate two checkouts, one table
    python benchmarks/bench_cli.py --busy              # also with a busy process beside it
    python benchmarks/bench_cli.py --cold --only demo -r 2  # the first run of the demo

Needs ``../shared/data``. Prints the machine's load average before and after.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data, print_table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("read", "solve", "map", "checks", "write")
TIMINGS = re.compile(r"timings:\s*(.*)$", re.MULTILINE)


# ----------------------------------------------------------------------------------------
# scenes nobody tuned: a padded box cage, anchors on the long axis, one end bent + twisted
# ----------------------------------------------------------------------------------------
def box_cage(lo, hi, divisions: int = 4):
    """A closed, outward triangulated box with ``divisions`` squares along each edge."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    n = divisions
    verts: dict = {}
    faces = []

    def vid(ijk):
        if ijk not in verts:
            verts[ijk] = len(verts)
        return verts[ijk]

    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for side in (0, n):
            for a in range(n):
                for b in range(n):
                    q = []
                    for da, db in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        ijk = [0, 0, 0]
                        ijk[axis], ijk[u], ijk[v] = side, a + da, b + db
                        q.append(vid(tuple(ijk)))
                    if side == 0:
                        q = q[::-1]
                    faces += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    ijk = np.array(sorted(verts, key=verts.get), dtype=float)
    return lo + ijk / n * (hi - lo), np.array(faces)


def rotation(axis: int, degrees: float) -> np.ndarray:
    """Rotation by ``degrees`` about coordinate ``axis``."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def bend_twist_constraints(lo, hi, bend: float, twist: float) -> dict:
    """Hold one end of the long axis, bend the other by ``bend`` and twist it by ``twist``.

    The moving end goes where a circular arc of the axis's length and angle ``bend`` ends,
    with the Jacobian of that bend times the twist about the long axis.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    long = int(np.argmax(size))
    side = (long + 1) % 3
    centre = (lo + hi) / 2
    p0, p1 = centre.copy(), centre.copy()
    p0[long], p1[long] = lo[long] + 0.1 * size[long], hi[long] - 0.1 * size[long]
    length = float(p1[long] - p0[long])
    theta = math.radians(bend)
    target = p0.copy()
    if theta:
        target[long] += length * math.sin(theta) / theta
        target[side] += length * (1 - math.cos(theta)) / theta
    else:
        target[long] += length
    bend_axis = 3 - long - side
    jac = rotation(bend_axis, -bend if (bend_axis + 1) % 3 == long else bend)
    jac = jac @ rotation(long, twist)
    return {
        "positions": [p0.tolist(), p1.tolist()],
        "targets": [p0.tolist(), target.tolist()],
        "jacobian_points": [p0.tolist(), p1.tolist()],
        "jacobians": [np.eye(3).tolist(), jac.tolist()],
    }


def box_scene(bounds, bend=30.0, twist=20.0, pad=0.06, anchors=12) -> dict:
    """A scene with a padded 192-triangle box cage and anchors on the data's long axis."""
    lo, hi = np.asarray(bounds[0::2], float), np.asarray(bounds[1::2], float)
    grow = pad * (hi - lo)
    v, f = box_cage(lo - grow, hi + grow, 4)
    long = int(np.argmax(hi - lo))
    centre = (lo + hi) / 2
    t = np.linspace(0.1, 0.9, anchors)
    pts = np.repeat(centre[None], anchors, axis=0)
    pts[:, long] = lo[long] + t * (hi - lo)[long]
    return {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": {"vertices": v.tolist(), "faces": f.tolist()},
        "anchors": pts.tolist(),
        "constraints": bend_twist_constraints(lo, hi, bend, twist),
        "mode": "rigid",
        "alpha": 0.01,
    }


def bounds_of(path: Path) -> list:
    """The dataset's bounds as ``vhm_viz.read_dataset`` reads it (the CLI's frame)."""
    from vhm_viz.io import read_dataset

    return list(read_dataset(str(path)).bounds)


# ----------------------------------------------------------------------------------------
# cases
# ----------------------------------------------------------------------------------------
@dataclass
class Case:
    """One command line: ``args`` with ``{scene}``, ``{out}`` and ``{input}`` filled in."""

    name: str
    input: Path
    args: list
    scene: dict | None = None
    output: str = ""
    big: bool = False


def cases(big: bool) -> list[Case]:
    """The default set: volumes, tet meshes, surfaces and the certificate."""
    vol = data("volumes")
    out: list[Case] = []

    def deform(name, path, suffix, scene=None, extra=(), is_big=False):
        out.append(
            Case(
                name,
                path,
                ["deform", "{input}", "--scene", "{scene}", "-o", "{out}", "-q", *extra],
                scene=scene,
                output=suffix,
                big=is_big,
            )
        )

    for label, file in (
        ("ct head", "headsq_64x64x93.vti"),
        ("mr head", "HeadMRVolume.mhd"),
        ("avg152T1", "avg152T1_RL_nifti.nii.gz"),
    ):
        path = vol / file
        scene = box_scene(bounds_of(path))
        deform(f"{label} -> .vts (box cage)", path, ".vts", scene)
        deform(f"{label} -> .vti (box cage)", path, ".vti", scene)
    embryo = vol / "embryo.slc"
    if big:
        scene = box_scene(bounds_of(embryo))
        deform("embryo 256^3 -> .vti (box cage)", embryo, ".vti", scene, is_big=True)
        deform("embryo 256^3 -> .vts (box cage)", embryo, ".vts", scene, is_big=True)
    dragon = data("tets", "dragon.tet.vtk")
    dscene = box_scene(bounds_of(dragon), bend=40.0, twist=30.0)
    deform(
        "dragon 104k tets --arrays cells (box cage)", dragon, ".vtu", dscene, ("--arrays", "cells")
    )
    arma = data("armadillo", "armadillo_173k.ply")
    ascene = box_scene(bounds_of(arma), bend=25.0, twist=15.0)
    ascene["cage"] = str(data("armadillo", "cage_500f.obj"))
    ascene["anchors"] = {"auto": 12}  # the bounds' long axis leaves the body
    deform("armadillo 173k (hand-made cage_500f)", arma, ".vtp", ascene)
    bar = data("bar", "bar_dense.obj")
    bscene = box_scene(bounds_of(bar), bend=30.0, twist=20.0)
    bscene["cage"] = "auto"
    bscene["anchors"] = {"auto": 12}
    bscene["solver"] = {"max_iterations": 5000}
    deform("bar surface (automatic cage and anchors)", bar, ".vtp", bscene)
    hand = data("hand_tet", "hand.mesh")
    hscene = box_scene(bounds_of(hand), bend=20.0, twist=10.0)
    out.append(
        Case(
            "analyze --certify hand 30k tets (box cage)",
            hand,
            ["analyze", "{input}", "--scene", "{scene}", "-o", "{out}", "-q", "--certify"],
            scene=hscene,
            output="",
        )
    )
    out.append(
        Case(
            "demo (bundled bar: surface, tets, volume, figures)",
            Path(),
            ["demo", "-o", "{out}", "-q"],
        )
    )
    return out


# ----------------------------------------------------------------------------------------
# running
# ----------------------------------------------------------------------------------------
def run_once(cmd: list, env: dict, cwd: Path) -> tuple[float, float, float, str, int]:
    """Wall seconds, CPU seconds, peak RSS (MB), stderr text and exit status of one child."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    cpu = usage.ru_utime + usage.ru_stime
    return wall, cpu, usage.ru_maxrss / 1024.0, err, proc.returncode


def parse_timings(err: str) -> dict:
    """Stage seconds from a ``timings: read 0.1 s, solve 0.2 s, ...`` line, if any."""
    m = TIMINGS.findall(err)
    if not m:
        return {}
    found = {}
    for part in m[-1].split(","):
        bits = part.split()
        if len(bits) >= 2:
            try:
                found[bits[0]] = float(bits[1])
            except ValueError:
                pass
    return found


def busy_process():
    """A process that keeps one core busy (numpy matrix products) until killed."""
    code = (
        "import numpy as np\n"
        "a = np.random.default_rng(0).random((600, 600))\n"
        "while True:\n    a = np.tanh(a @ a.T / 600)\n"
    )
    return subprocess.Popen([sys.executable, "-c", code])


def environment(repo: Path, cache: Path | None) -> dict:
    """The child's environment: ``repo``'s vhm_viz first on the path.

    ``cache``: a compiled-code cache folder for the child (default: the caller's own, as
    a user's command would find it).
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = str(repo) + os.pathsep + env.get("PYTHONPATH", "")
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    env.setdefault("QT_QPA_PLATFORM", "offscreen")
    return env


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-r", "--repeats", type=int, default=3)
    ap.add_argument("--only", default="", help="run the cases whose name contains this")
    ap.add_argument("--big", action="store_true", help="also the 256^3 embryo")
    ap.add_argument("--repo", type=Path, default=ROOT, help="checkout whose vhm_viz runs")
    ap.add_argument("--compare", type=Path, help="a second checkout, run alternately")
    ap.add_argument("--cold", action="store_true", help="empty compiled-code cache each run")
    ap.add_argument("--busy", action="store_true", help="also time with a busy process beside")
    ap.add_argument("--json", type=Path, help="write the raw results here")
    args = ap.parse_args(argv)

    print(f"load average before: {os.getloadavg()}", flush=True)
    scratch = Path(tempfile.mkdtemp(prefix="bench_cli_"))
    repos = [args.repo.resolve()] + ([args.compare.resolve()] if args.compare else [])
    results = []
    try:
        todo = [
            c
            for c in cases(args.big or "embryo" in args.only)
            if args.only.lower() in c.name.lower()
        ]
        for k, case in enumerate(todo):
            scene_path = scratch / f"scene{k}.json"
            if case.scene is not None:
                scene_path.write_text(json.dumps(case.scene))
            loads = [False, True] if args.busy else [False]
            for loaded in loads:
                runs = {str(r): [] for r in repos}
                for rep in range(args.repeats + (0 if args.cold else 1)):
                    for repo in repos:
                        cache = None
                        if args.cold:
                            cache = scratch / f"numba-{repos.index(repo)}"
                            shutil.rmtree(cache, ignore_errors=True)
                        out = scratch / f"out{k}-{repos.index(repo)}{case.output}"
                        if out.is_dir():
                            shutil.rmtree(out)
                        elif out.exists():
                            out.unlink()
                        fill = {"input": str(case.input), "scene": str(scene_path), "out": str(out)}
                        argv_ = [a.format(**fill) for a in case.args]
                        if "--timings" not in argv_:
                            argv_.append("--timings")
                        cmd = [sys.executable, "-m", "vhm_viz.cli", *argv_]
                        busy = busy_process() if loaded else None
                        try:
                            load = os.getloadavg()[0]
                            wall, cpu, rss, err, code = run_once(
                                cmd, environment(repo, cache), scratch
                            )
                        finally:
                            if busy is not None:
                                busy.kill()
                                busy.wait()
                        if code != 0 and "unrecognized arguments: --timings" in err:
                            argv_.remove("--timings")
                            cmd = [sys.executable, "-m", "vhm_viz.cli", *argv_]
                            wall, cpu, rss, err, code = run_once(
                                cmd, environment(repo, cache), scratch
                            )
                        if code != 0:
                            print(f"{case.name}: exit {code}: {err.strip()[-400:]}", flush=True)
                        if rep == 0 and not args.cold:
                            continue  # warm-up: fills the compiled-code cache
                        runs[str(repo)].append(
                            {
                                "wall": wall,
                                "cpu": cpu,
                                "rss": rss,
                                "load": load,
                                "code": code,
                                "stages": parse_timings(err),
                            }
                        )
                for repo in repos:
                    results.append(
                        {
                            "case": case.name,
                            "busy": loaded,
                            "repo": str(repo),
                            "runs": runs[str(repo)],
                        }
                    )
                    print(
                        f"  {case.name}{' (busy)' if loaded else ''} [{repo.name}]: "
                        + ", ".join(
                            f"{r['wall']:.2f}s (cpu {r['cpu']:.1f}s, load {r['load']:.1f})"
                            for r in runs[str(repo)]
                        ),
                        flush=True,
                    )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    rows = []
    for res in results:
        w = [r["wall"] for r in res["runs"]]
        if not w:
            continue
        c = [r["cpu"] for r in res["runs"]]
        m = [r["rss"] for r in res["runs"]]
        stages = {}
        for s in STAGES:
            vals = [r["stages"][s] for r in res["runs"] if s in r["stages"]]
            if vals:
                stages[s] = statistics.median(vals)
        label = res["case"] + (" (busy)" if res["busy"] else "")
        if len(repos) > 1:
            label += f" [{Path(res['repo']).name}]"
        failed = sum(r["code"] != 0 for r in res["runs"])
        rows.append(
            [
                label,
                f"{statistics.median(w):.2f} s ({min(w):.2f}-{max(w):.2f})",
                f"{statistics.median(c):.2f} s ({min(c):.2f}-{max(c):.2f})",
                f"{statistics.median(m):.0f} MB",
                " ".join(f"{s} {stages[s]:.2f}" for s in STAGES if s in stages) or "-",
                str(failed) if failed else "",
            ]
        )
    print()
    kind = "cold (empty compiled-code cache)" if args.cold else "warm (cache filled)"
    print(f"vhm-viz commands, fresh process each, {kind}, n={args.repeats}")
    print_table(
        ["case", "wall, median (min-max)", "CPU, median (min-max)", "peak RSS", "stages (s)",
         "failed"],
        rows,
    )  # fmt: skip
    print(f"\nload average after: {os.getloadavg()}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
