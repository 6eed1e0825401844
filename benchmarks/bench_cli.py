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
    python benchmarks/bench_cli.py --python ENV/bin/python  # also an installed vhm_viz
    python benchmarks/bench_cli.py --busy              # also with a busy process beside it
    python benchmarks/bench_cli.py --cold --only demo -r 2  # the first run of the demo
    python benchmarks/bench_cli.py --anchors           # also the machine anchors, scaled goals
    python benchmarks/bench_cli.py --anchors only      # the anchors alone
    python benchmarks/bench_cli.py --huge --only "^3 -> .vti" -r 1  # 512^3 embryo vs 256^3

``--python`` also runs, alternately, the vhm_viz installed for an interpreter as a user
installs it (``python -m venv ENV && ENV/bin/pip install .``: the runtime dependencies
only, no editable-install hook, no test or docs packages): a process's start-up grows with
the packages beside it (numba scans every installed distribution's entry points).

``--anchors`` times two jobs of other tools (:mod:`machine_anchors`) and prints issue
#34's goals scaled by this machine's ratio to the machine they were set on. The embryo's
``.vti`` case always times SimpleITK's ``Resample`` of it in the same run (its goal is a
multiple of that). ``--huge`` makes the embryo upsampled to 512^3 in the scratch folder
(each voxel repeated 2x2x2: half the spacing, the same physical extent, uint8) and
compares its ``.vti`` run with the 256^3 one: time ratio and peak RSS against input +
output + 1 GB.

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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data, print_table  # noqa: E402
from machine_anchors import ISSUE_SECONDS, LABELS, time_anchors  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("read", "solve", "map", "checks", "write")
TIMINGS = re.compile(r"timings:\s*(.*)$", re.MULTILINE)
EMBRYO_VTI = "embryo 256^3 -> .vti (box cage)"
HUGE_VTI = "embryo 512^3 -> .vti (box cage, upsampled)"

#: Issue #34's goals where it was measured: case -> (wall seconds, peak RSS in MB or None).
GOALS = {
    "embryo 256^3 -> .vts (box cage)": (8.0, 1500),
    EMBRYO_VTI: (10.0, 1200),
    "ct head -> .vts (box cage)": (1.5, None),
    "ct head -> .vts (automatic cage and anchors)": (1.5, None),
    "ct head -> .vti (box cage)": (2.0, None),
    "dragon 104k tets --arrays cells (box cage)": (3.0, None),
}
#: A deform case's command line. The scenes are not tuned and some fold: the output is
#: written and timed all the same.
DEFORM = ("deform", "{input}", "--scene", "{scene}", "-o", "{out}", "-q", "--allow-folds")
#: Options of newer ``vhm-viz`` versions, left out for a checkout that does not know them.
NEWER_OPTIONS = ("--timings", "--allow-folds")
#: The cold demo's goal (seconds, empty compiled-code cache).
COLD_DEMO_GOAL = 40.0
#: Embryo .vti: at most this multiple of SimpleITK's Resample timed in the same run.
SIMPLEITK_MULTIPLE = 15.0
#: The 512^3 embryo: at most this multiple of the 256^3 time, 8x the voxels.
HUGE_MULTIPLE = 9.0


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


def bend_twist_constraints(lo, hi, bend: float, twist: float, points=None) -> dict:
    """Hold one end of the long axis, bend the other by ``bend`` and twist it by ``twist``.

    The moving end goes where a circular arc of the axis's length and angle ``bend`` ends,
    with the Jacobian of that bend times the twist about the long axis. With ``points``
    (the data's points, ``(N, 3)``), both ends move to the nearest of them, so that they
    lie inside a cage that hugs the data (on the long axis they may lie outside it); the
    moving end's offset from the axis turns with the bend.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    long = int(np.argmax(size))
    side = (long + 1) % 3
    centre = (lo + hi) / 2
    p0, p1 = centre.copy(), centre.copy()
    p0[long], p1[long] = lo[long] + 0.1 * size[long], hi[long] - 0.1 * size[long]
    if points is not None:
        points = np.asarray(points, float)
        p0, p1 = (points[np.argmin(((points - p) ** 2).sum(axis=1))] for p in (p0, p1))
    length = float(p1[long] - p0[long])
    off_axis = p1 - p0
    off_axis[long] = 0.0
    theta = math.radians(bend)
    target = p0.copy()
    if theta:
        target[long] += length * math.sin(theta) / theta
        target[side] += length * (1 - math.cos(theta)) / theta
    else:
        target[long] += length
    bend_axis = 3 - long - side
    jac = rotation(bend_axis, -bend if (bend_axis + 1) % 3 == long else bend)
    target = target + jac @ off_axis
    jac = jac @ rotation(long, twist)
    return {
        "positions": [p0.tolist(), p1.tolist()],
        "targets": [p0.tolist(), target.tolist()],
        "jacobian_points": [p0.tolist(), p1.tolist()],
        "jacobians": [np.eye(3).tolist(), jac.tolist()],
    }


def box_scene(bounds, bend=30.0, twist=20.0, pad=0.06, anchors=12, points=None) -> dict:
    """A scene with a padded 192-triangle box cage and anchors on the data's long axis.

    ``points``: the data's points, for constraints on them
    (:func:`bend_twist_constraints`).
    """
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
        "constraints": bend_twist_constraints(lo, hi, bend, twist, points),
        "mode": "rigid",
        "alpha": 0.01,
    }


def bounds_of(path: Path) -> list:
    """The dataset's bounds as ``vhm_viz.read_dataset`` reads it (the CLI's frame)."""
    from vhm_viz.io import read_dataset

    return list(read_dataset(str(path)).bounds)


def points_of(path: Path) -> np.ndarray:
    """The dataset's points ``(N, 3)`` as ``vhm_viz.read_dataset`` reads it."""
    from vhm_viz.io import read_dataset

    return np.asarray(read_dataset(str(path)).points, dtype=float)


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
    #: Makes the input in the scratch folder and gives its path (``input`` unused).
    prepare: Callable[[Path], Path] | None = None
    #: Run once untimed first (a long case whose compiled code an earlier case cached
    #: needs none).
    warmup: bool = True


def upsampled_embryo(scratch: Path) -> Path:
    """The embryo with each voxel repeated 2x2x2 (512^3, uint8), as ``.vti`` in ``scratch``.

    Half the spacing, the origin a quarter voxel back: the voxels cover the same physical
    extent (numpy ``repeat``, nearest neighbour: no interpolation).
    """
    import pyvista as pv

    from vhm_viz.io import read_dataset

    path = scratch / "embryo_512.vti"
    if path.exists():
        return path
    img = read_dataset(str(data("volumes", "embryo.slc")))
    nx, ny, nz = img.dimensions
    values = np.asarray(img.active_scalars).reshape(nz, ny, nx)
    big = values.repeat(2, axis=0).repeat(2, axis=1).repeat(2, axis=2)
    spacing = np.asarray(img.spacing, float)
    direction = np.asarray(img.direction_matrix, float)
    out = pv.ImageData(
        dimensions=(2 * nx, 2 * ny, 2 * nz),
        spacing=tuple(spacing / 2),
        origin=tuple(np.asarray(img.origin, float) - direction @ (spacing / 4)),
    )
    out.direction_matrix = direction
    out.point_data[img.active_scalars_name] = big.ravel()
    out.save(str(path))
    return path


def cases(big: bool, huge: bool = False) -> list[Case]:
    """The default set: volumes, tet meshes, surfaces and the certificate."""
    vol = data("volumes")
    out: list[Case] = []

    def deform(name, path, suffix, scene=None, extra=(), is_big=False):
        out.append(
            Case(
                name,
                path,
                [*DEFORM, *extra],
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
        if label == "ct head":  # the issue's CT row, with the cage and anchors automatic
            auto = dict(scene, cage="auto", anchors={"auto": 12})
            deform(f"{label} -> .vts (automatic cage and anchors)", path, ".vts", auto)
    embryo = vol / "embryo.slc"
    if big or huge:
        scene = box_scene(bounds_of(embryo))
        deform(EMBRYO_VTI, embryo, ".vti", scene, is_big=True)
    if big:
        deform("embryo 256^3 -> .vts (box cage)", embryo, ".vts", scene, is_big=True)
        deform(
            "embryo 256^3 -> .vts --arrays cells (box cage)", embryo, ".vts", scene,
            ("--arrays", "cells"), is_big=True,
        )  # fmt: skip
        out.append(
            Case(
                "analyze embryo 256^3 (box cage)",
                embryo,
                ["analyze", "{input}", "--scene", "{scene}", "-o", "{out}", "-q"],
                scene=scene,
                output="",
                big=True,
            )
        )
    if huge:
        deform(HUGE_VTI, Path(), ".vti", None, is_big=True)
        out[-1].prepare, out[-1].warmup = upsampled_embryo, False
    dragon = data("tets", "dragon.tet.vtk")
    dscene = box_scene(bounds_of(dragon), bend=40.0, twist=30.0)
    deform(
        "dragon 104k tets --arrays cells (box cage)", dragon, ".vtu", dscene, ("--arrays", "cells")
    )
    arma = data("armadillo", "armadillo_173k.ply")
    # the hand-made cage hugs the body: constraints on it, not on the bounds' long axis
    ascene = box_scene(bounds_of(arma), bend=25.0, twist=15.0, points=points_of(arma))
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


class Runner(NamedTuple):
    """Where a case's command runs: a checkout's vhm_viz, or an interpreter's installed one."""

    python: str
    repo: Path | None

    @property
    def label(self) -> str:
        return self.repo.name if self.repo is not None else f"installed: {self.python}"


def environment(repo: Path | None, cache: Path | None) -> dict:
    """The child's environment: ``repo``'s vhm_viz first on the path (None: as installed).

    ``cache``: a compiled-code cache folder for the child (default: the caller's own, as
    a user's command would find it). Python's bytecode is cached as an installed
    package's is (``pip`` compiles it at install): a ``PYTHONDONTWRITEBYTECODE`` in the
    caller's environment would make every child compile vhm_viz's modules from source.
    """
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    if repo is not None:
        env["PYTHONPATH"] = str(repo) + os.pathsep + env.get("PYTHONPATH", "")
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    env.setdefault("QT_QPA_PLATFORM", "offscreen")
    return env


def run_case(case: Case, k: int, scratch: Path, repos: list[Runner], args) -> list[dict]:
    """Run one case ``args.repeats`` times per runner (quiet, then busy with ``--busy``)."""
    input_path = case.prepare(scratch) if case.prepare is not None else case.input
    scene = case.scene
    if case.prepare is not None and scene is None:
        scene = box_scene(bounds_of(input_path))
    scene_path = scratch / f"scene{k}.json"
    if scene is not None:
        scene_path.write_text(json.dumps(scene))
    results = []
    warmup = 0 if args.cold or not case.warmup else 1
    for loaded in [False, True] if args.busy else [False]:
        runs = {r.label: [] for r in repos}
        for rep in range(args.repeats + warmup):
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
                fill = {"input": str(input_path), "scene": str(scene_path), "out": str(out)}
                argv_ = [a.format(**fill) for a in case.args]
                if "--timings" not in argv_:
                    argv_.append("--timings")
                cmd = [repo.python, "-m", "vhm_viz.cli", *argv_]
                busy = busy_process() if loaded else None
                try:
                    load = os.getloadavg()[0]
                    env = environment(repo.repo, cache)
                    wall, cpu, rss, err, code = run_once(cmd, env, scratch)
                finally:
                    if busy is not None:
                        busy.kill()
                        busy.wait()
                unknown = re.search(r"unrecognized arguments: (.*)", err) if code else None
                newer = [a for a in NEWER_OPTIONS if unknown and a in unknown[1].split()]
                if newer:  # an older checkout (--compare, --repo): without what it lacks
                    argv_ = [a for a in argv_ if a not in newer]
                    cmd = [repo.python, "-m", "vhm_viz.cli", *argv_]
                    wall, cpu, rss, err, code = run_once(cmd, env, scratch)
                if code != 0:
                    print(f"{case.name}: exit {code}: {err.strip()[-400:]}", flush=True)
                if rep < warmup:
                    continue  # warm-up: fills the compiled-code cache
                run = {"wall": wall, "cpu": cpu, "rss": rss, "load": load, "code": code,
                       "stages": parse_timings(err)}  # fmt: skip
                if case.prepare is not None and code == 0:
                    run["input_mb"], run["output_mb"] = voxel_mb(input_path), voxel_mb(out)
                runs[repo.label].append(run)
        for repo in repos:
            results.append(
                {"case": case.name, "busy": loaded, "repo": repo.label, "runs": runs[repo.label]}
            )
            print(
                f"  {case.name}{' (busy)' if loaded else ''} [{repo.label}]: "
                + ", ".join(
                    f"{r['wall']:.2f}s (cpu {r['cpu']:.1f}s, load {r['load']:.1f})"
                    for r in runs[repo.label]
                ),
                flush=True,
            )
    return results


#: Bytes of each VTK XML ``DataArray`` type.
VTK_TYPE_BYTES = {"Int8": 1, "UInt8": 1, "Int16": 2, "UInt16": 2, "Int32": 4, "UInt32": 4,
                  "Int64": 8, "UInt64": 8, "Float32": 4, "Float64": 8}  # fmt: skip


def voxel_mb(path: Path) -> float:
    """Megabytes of a ``.vti``'s point arrays in memory, from its XML header alone."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16).decode("latin-1").split("<AppendedData")[0]
    extent = [int(v) for v in re.search(r'WholeExtent="([^"]+)"', head).group(1).split()]
    voxels = math.prod(extent[2 * a + 1] - extent[2 * a] + 1 for a in range(3))
    points = head[head.index("<PointData") :].split("</PointData>")[0]
    per_voxel = 0
    for tag in re.findall(r"<DataArray[^>]*>", points):
        kind = re.search(r'type="(\w+)"', tag).group(1)
        comps = re.search(r'NumberOfComponents="(\d+)"', tag)
        per_voxel += VTK_TYPE_BYTES[kind] * (int(comps.group(1)) if comps else 1)
    return voxels * per_voxel / 2**20


def median_of(results: list, name: str, key: str = "wall", runner=None) -> float | None:
    """Median of ``key`` over the quiet runs of case ``name`` (``runner``'s, else the first's)."""
    for res in results:
        if res["case"] == name and not res["busy"] and runner in (None, res["repo"]):
            vals = [r[key] for r in res["runs"] if r["code"] == 0 and key in r]
            return statistics.median(vals) if vals else None
    return None


def print_anchors(anchors: dict) -> None:
    """The anchors' table: this machine's time, the issue machine's and their ratio."""
    rows = []
    for name, a in anchors.items():
        t = a["times"]
        cpu = statistics.median(r["cpu"] for r in a["runs"])
        rows.append([LABELS[name], f"{a['median']:.2f} s ({min(t):.2f}-{max(t):.2f})",
                     f"{cpu:.2f} s", a["detail"]["threads"], f"{ISSUE_SECONDS[name]:.2f} s",
                     f"{a['ratio']:.2f}"])  # fmt: skip
    print("\nmachine anchors, fresh process each (ratio = this machine / the goals' machine)")
    print_table(
        ["anchor", "wall, median (min-max)", "CPU, median", "threads", "issue machine", "ratio"],
        rows,
    )


def yes(ok: bool) -> str:
    """``yes`` or ``no``."""
    return "yes" if ok else "no"


def print_goals(results: list, anchors: dict, cold: bool, runner: str | None = None) -> None:
    """Issue #34's goals beside what was measured, time goals scaled by each anchor ratio.

    ``runner``: whose runs (a :attr:`Runner.label`; default: the first runner's).
    """
    results = [r for r in results if runner in (None, r["repo"])]
    ratios = {name: a["ratio"] for name, a in anchors.items()}
    order = [n for n in ("vtk", "simpleitk") if n in ratios]
    goals = dict(GOALS)
    if cold:
        goals = {n: (COLD_DEMO_GOAL, None) for n in (r["case"] for r in results) if "demo" in n}
    rows = []
    for name, (seconds, mb) in goals.items():
        wall, rss = median_of(results, name), median_of(results, name, "rss")
        if wall is None:
            continue
        scaled = [seconds * ratios[n] for n in order] or [seconds]
        met = " / ".join(yes(wall <= g) for g in scaled)
        goal, measured = f"<= {seconds:g} s", f"{wall:.2f} s"
        if mb:
            goal += f", <= {mb} MB"
            measured += f", {rss:.0f} MB"
            met += f"; RSS {yes(rss <= mb)}"
        rows.append([name, goal, " / ".join(f"{g:.2f} s" for g in scaled), measured, met])
    vti, itk = median_of(results, EMBRYO_VTI), anchors.get("simpleitk")
    if vti is not None and itk is not None:
        times = vti / itk["median"]
        cpu = median_of(results, EMBRYO_VTI, "cpu") / statistics.median(
            r["cpu"] for r in itk["runs"]
        )
        rows.append([f"{EMBRYO_VTI} / SimpleITK Resample", f"<= {SIMPLEITK_MULTIPLE:g}x", "-",
                     f"{times:.1f}x (CPU time {cpu:.1f}x)",
                     yes(times <= SIMPLEITK_MULTIPLE)])  # fmt: skip
    huge = median_of(results, HUGE_VTI)
    if vti is not None and huge is not None:
        times = huge / vti
        cpu = median_of(results, HUGE_VTI, "cpu") / median_of(results, EMBRYO_VTI, "cpu")
        rows.append([f"{HUGE_VTI} / 256^3", f"<= {HUGE_MULTIPLE:g}x", "-",
                     f"{times:.2f}x (CPU time {cpu:.2f}x)",
                     yes(times <= HUGE_MULTIPLE)])  # fmt: skip
        rss = median_of(results, HUGE_VTI, "rss")
        inp, out = (median_of(results, HUGE_VTI, k) for k in ("input_mb", "output_mb"))
        bound = inp + out + 1024
        rows.append([f"{HUGE_VTI} peak RSS", "<= input + output + 1 GB", f"{bound:.0f} MB",
                     f"{rss:.0f} MB (input {inp:.0f}, output {out:.0f} MB)",
                     yes(rss <= bound)])  # fmt: skip
    if not rows:
        return
    scale = ", ".join(f"x {ratios[n]:.2f} ({n})" for n in order) or "no anchors timed: unscaled"
    whose = f" [{runner}]" if runner is not None else ""
    print(f"\nissue #34's goals{whose}; times scaled by this machine's ratio {scale}")
    print_table(["goal", "issue machine", "scaled here", "measured (median)", "met"], rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("-r", "--repeats", type=int, default=3)
    ap.add_argument("--only", default="", help="run the cases whose name contains this")
    ap.add_argument("--big", action="store_true", help="also the 256^3 embryo")
    ap.add_argument("--huge", action="store_true", help="also the embryo upsampled to 512^3")
    ap.add_argument(
        "--anchors",
        nargs="?",
        const="also",
        choices=("also", "only"),
        help="also time the machine anchors (--anchors only: them alone)",
    )
    ap.add_argument("--repo", type=Path, default=ROOT, help="checkout whose vhm_viz runs")
    ap.add_argument("--compare", type=Path, help="a second checkout, run alternately")
    ap.add_argument("--python", help="also the vhm_viz installed for this interpreter")
    ap.add_argument("--cold", action="store_true", help="empty compiled-code cache each run")
    ap.add_argument("--busy", action="store_true", help="also time with a busy process beside")
    ap.add_argument("--json", type=Path, help="write the raw results here")
    args = ap.parse_args(argv)

    print(f"load average before: {os.getloadavg()}", flush=True)
    scratch = Path(tempfile.mkdtemp(prefix="bench_cli_"))
    repos = [Runner(sys.executable, args.repo.resolve())]
    if args.compare:
        repos.append(Runner(sys.executable, args.compare.resolve()))
    if args.python:
        repos.append(Runner(args.python, None))
    results, anchors = [], {}
    try:
        pair = (EMBRYO_VTI, HUGE_VTI) if args.huge else ()  # --huge compares the two
        todo = [
            c
            for c in cases(args.big or "embryo" in args.only, args.huge)
            if args.only.lower() in c.name.lower() or c.name in pair
        ]
        if args.anchors == "only":
            todo = []
        which = ["vtk", "simpleitk"] if args.anchors else []
        if any(c.name == EMBRYO_VTI for c in todo) and "simpleitk" not in which:
            which.append("simpleitk")  # the embryo's goal is a multiple of it, same run
        if which:
            anchors = time_anchors(which, args.repeats, scratch, environment(repos[0].repo, None),
                                   lambda path: box_scene(bounds_of(path)))  # fmt: skip
            print_anchors(anchors)
        for k, case in enumerate(todo):
            results += run_case(case, k, scratch, repos, args)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)

    rows = []
    itk = anchors.get("simpleitk")
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
            label += f" [{res['repo']}]"
        failed = sum(r["code"] != 0 for r in res["runs"])
        versus = "-"
        if itk is not None and res["case"] == EMBRYO_VTI:
            versus = f"{statistics.median(w) / itk['median']:.1f}x SimpleITK"
        rows.append(
            [
                label,
                f"{statistics.median(w):.2f} s ({min(w):.2f}-{max(w):.2f})",
                f"{statistics.median(c):.2f} s ({min(c):.2f}-{max(c):.2f})",
                f"{statistics.median(m):.0f} MB",
                " ".join(f"{s} {stages[s]:.2f}" for s in STAGES if s in stages) or "-",
                versus,
                str(failed) if failed else "",
            ]
        )
    if rows:
        print()
        kind = "cold (empty compiled-code cache)" if args.cold else "warm (cache filled)"
        print(f"vhm-viz commands, fresh process each, {kind}, n={args.repeats}")
        print_table(
            ["case", "wall, median (min-max)", "CPU, median (min-max)", "peak RSS", "stages (s)",
             "vs anchor", "failed"],
            rows,
        )  # fmt: skip
    for runner in repos if len(repos) > 1 else [None]:
        print_goals(results, anchors, args.cold, runner and runner.label)
    print(f"\nload average after: {os.getloadavg()}")
    if args.json:
        args.json.write_text(json.dumps({"anchors": anchors, "cases": results}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
