"""Automatic cages and anchors: time, faces, clearance, enclosure, anchor coverage per model.

Run: ``python benchmarks/bench_autocage.py [--quick] [--repeat N]`` (N timed runs of
``auto_cage`` per model, default 3; the table gives the median and the min-max of the wall
time, the median process (CPU) time -- on a shared machine the wall time depends on what
else runs, so the load average is printed before and after). Every cage is checked here,
independently of the builder's report: winding number of every point (or every voxel above
the threshold), and, for the two bars, of points on the mid-plane of their gap. Anchor
coverage: the largest distance from a point to the nearest of 24 ``auto_anchors``, over
the bounding-box diagonal (goal: <= 15%).

The quality check follows the paper's Figure 13: the Beast deformed with the same
constraints and anchors using its hand-made cage and the automatic cage; reported are the
mean and max distance between the two deformed shapes relative to the bounding-box
diagonal (goal: mean <= 2%).
"""

from __future__ import annotations

import os
import statistics
import sys
import time

import numpy as np
import pyvista as pv
from _common import data, print_table, summary
from scipy.spatial import cKDTree

from vhm_viz.autocage import auto_anchors, auto_cage, otsu_threshold
from vhm_viz.core.basis import winding_number
from vhm_viz.core.deformer import Deformer
from vhm_viz.io import read_cage, read_dataset


def load(path):
    return read_dataset(path)


def two_bars(fraction: float):
    """Two 1 x 1 x 5 boxes (8 x 8 x 40 quads a side) ``fraction`` of the diagonal apart."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
    from conftest import box_cage

    gap = fraction * np.sqrt(30.0)
    for _ in range(50):
        gap = fraction * np.sqrt((2 + gap) ** 2 + 26.0)
    v1, f1 = box_cage((0, 0, 0), (1, 1, 5), 8)
    v2, f2 = box_cage((1 + gap, 0, 0), (2 + gap, 1, 5), 8)
    return (np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])), gap


MODELS = [
    ("two bars 3% apart", "bars", 0.03, {}),
    ("two bars 2% apart", "bars", 0.02, {}),
    ("two bars 1% apart", "bars", 0.01, {}),
    ("two bars 0.5% apart", "bars", 0.005, {}),
    ("Armadillo 43k", "file", ("armadillo", "armadillo_43k.obj"), {}),
    ("Armadillo 173k", "file", ("armadillo", "armadillo_173k.ply"), {}),
    ("Beast", "file", ("beast", "beast.obj"), {}),
    ("hand", "file", ("hand", "hand.obj"), {}),
    ("horse", "file", ("horse", "horse.obj"), {}),
    ("bar", "file", ("bar", "bar_dense.obj"), {}),
    ("hand tet mesh", "file", ("hand_tet", "hand.mesh"), {}),
    ("dragon tet mesh", "file", ("tets", "dragon.tet.vtk"), {}),
    ("tetraMesh_inverted", "file", ("tets", "tetraMesh_inverted.vtk"), {}),
    ("CT head (Otsu region)", "file", ("volumes", "headsq_64x64x93.vti"), {"threshold": "otsu"}),
    ("embryo (Otsu region)", "file", ("volumes", "embryo.slc"), {"threshold": "otsu"}),
]


def _points(dataset, kw) -> np.ndarray:
    """What the cage must enclose, computed here: every point, or every voxel above."""
    if isinstance(dataset, tuple):
        return dataset[0]
    pts = np.asarray(dataset.points, dtype=np.float64)
    if "threshold" in kw:
        vals = np.asarray(dataset.active_scalars)
        pts = pts[vals > otsu_threshold(vals)]
    return pts


def cage_table(quick: bool, repeat: int) -> None:
    rows = []
    for name, kind, what, kw in MODELS:
        if quick and ("173k" in name or "0.5%" in name or "2%" in name):
            continue
        if kind == "bars":
            dataset, gap = two_bars(what)
        else:
            dataset, gap = load(data(*what)), None
        result = []
        walls, cpus = [], []
        for _ in range(repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            result.append(auto_cage(dataset, return_report=True, **kw))
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        cage, rep = result[-1]
        pts = _points(dataset, kw)
        diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
        w = winding_number(pts, cage.vertices, cage.faces)
        gap_cell = "-"
        if gap is not None:
            gy, gz = np.meshgrid(np.linspace(0, 1, 11), np.linspace(0, 5, 41))
            mid = np.stack([np.full(gy.size, 1 + 0.5 * gap), gy.ravel(), gz.ravel()], axis=1)
            open_ = winding_number(mid, cage.vertices, cage.faces).max() < 0.5
            gap_cell = "open" if open_ else "bridged"
        t1 = time.perf_counter()
        anchors = auto_anchors(dataset, cage, 24, **kw)
        t_anchor = time.perf_counter() - t1
        cover = float(cKDTree(anchors).query(pts)[0].max()) / diag
        rows.append(
            [
                name,
                f"{len(pts)}",
                summary(walls),
                f"{statistics.median(cpus):.2f} s",
                f"{rep.method} x{rep.offset_used / rep.offset:g}",
                f"{rep.n_faces}",
                f"{rep.n_components}",
                f"{100 * rep.clearance_relative:.2f}%",
                f"{w.min():.6f}",
                "yes" if w.min() > 0.5 else "NO",
                gap_cell,
                f"{100 * cover:.1f}%",
                f"{t_anchor:.2f} s",
            ]
        )
        print(f"  {name}: {rep}" + (f"  notes: {rep.notes}" if rep.notes else ""), flush=True)
    print_table(
        [
            "model",
            "points",
            "seconds, wall (target <= 5 s)",
            "CPU",
            "method",
            "faces",
            "shells",
            "clearance % diag",
            "min winding",
            "encloses all",
            "gap mid-plane",
            "24 anchors: max dist % diag",
            "anchors s",
        ],
        rows,
    )


def beast_quality() -> None:
    mesh = pv.read(data("beast", "beast.obj"))
    pts = np.asarray(mesh.points, dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    hand_cage = read_cage(data("beast", "cage.obj"))
    auto = auto_cage(mesh)
    anchors = auto_anchors(mesh, hand_cage, 40)
    anchors = anchors[auto.contains(anchors) & hand_cage.contains(anchors)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)

    # constraints: the two feet held, the right hand raised, the head turned a little
    def pick(where):
        return pts[np.argmin(np.linalg.norm(pts - where, axis=1))]

    feet_l = pick([lo[0] * 0.4, lo[1], 0.0])
    feet_r = pick([hi[0] * 0.4, lo[1], 0.0])
    hand_r = pick([hi[0], 0.5 * (lo[1] + hi[1]) + 0.1, 0.0])
    hand_l = pick([lo[0], 0.5 * (lo[1] + hi[1]) + 0.1, 0.0])
    head = pick([0.0, hi[1], 0.0])
    positions = np.array([feet_l, feet_r, hand_r, hand_l, head])
    targets = positions.copy()
    targets[2] += np.array([-0.15, 0.35, 0.1])  # raise the right hand
    targets[4] += np.array([0.05, -0.02, 0.03])
    results = {}
    for label, cage in (("hand-made", hand_cage), ("automatic", auto)):
        inside = cage.contains(pts)
        t0 = time.perf_counter()
        d = Deformer(cage, anchors)
        d.set_constraints(positions=positions, targets=targets)
        rep = d.solve(max_iterations=5000, tolerance=1e-8)
        out = d.bind(pts[inside]).deform()
        full = pts.copy()
        full[inside] = out
        results[label] = (full, inside, time.perf_counter() - t0, rep)
        print(
            f"  {label} cage: {cage.n_faces} faces, {rep.iterations} iterations, "
            f"{results[label][2]:.2f} s, {int((~inside).sum())} points outside"
        )
    a, ia = results["hand-made"][0], results["hand-made"][1]
    b, ib = results["automatic"][0], results["automatic"][1]
    both = ia & ib
    dist = np.linalg.norm(a[both] - b[both], axis=1) / diag
    moved = np.linalg.norm(a[both] - pts[both], axis=1) / diag
    print_table(
        [
            "Beast (Fig. 13)",
            "anchors",
            "mean dist / diag",
            "max dist / diag",
            "mean displacement / diag",
            "goal",
        ],
        [
            [
                "hand-made vs automatic cage",
                f"{len(anchors)}",
                f"{100 * dist.mean():.2f}%",
                f"{100 * dist.max():.2f}%",
                f"{100 * moved.mean():.2f}%",
                "mean <= 2%",
            ]
        ],
    )


def main() -> None:
    quick = "--quick" in sys.argv
    repeat = int(sys.argv[sys.argv.index("--repeat") + 1]) if "--repeat" in sys.argv else 3
    print("load average before: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()), flush=True)
    cage_table(quick, repeat)
    beast_quality()
    print("load average after: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))


if __name__ == "__main__":
    main()
