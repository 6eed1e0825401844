"""Automatic cages: time, faces, clearance and enclosure per model; Beast quality check.

Run: ``python benchmarks/bench_autocage.py [--quick] [--repeat N]`` (N timed runs per model,
default 3; the table gives the median and the min-max). The quality check follows the
paper's Figure 13: the Beast deformed with the same constraints and anchors using its
hand-made cage and the automatic cage; reported are the mean and max distance between the
two deformed shapes relative to the bounding-box diagonal (goal: mean <= 2%).
"""

from __future__ import annotations

import sys
import time

import numpy as np
from _common import data, print_table, summary, timed


def load(kind, path):
    import pyvista as pv

    if kind == "tet":
        import meshio

        return pv.from_meshio(meshio.read(path))
    return pv.read(path)


MODELS = [
    ("Armadillo 43k", "surface", ("armadillo", "armadillo_43k.obj"), {}),
    ("Armadillo 173k", "surface", ("armadillo", "armadillo_173k.ply"), {}),
    ("Beast", "surface", ("beast", "beast.obj"), {}),
    ("hand", "surface", ("hand", "hand.obj"), {}),
    ("horse", "surface", ("horse", "horse.obj"), {}),
    ("hand tet mesh", "tet", ("hand_tet", "hand.mesh"), {}),
    ("CT head (Otsu region)", "volume", ("volumes", "headsq_64x64x93.vti"), {"threshold": "otsu"}),
]


def cage_table(quick: bool, repeat: int) -> None:
    from vhm_viz.autocage import auto_cage

    rows = []
    for name, kind, parts, kw in MODELS:
        if quick and "173k" in name:
            continue
        mesh = load(kind, data(*parts))
        result = []

        def run(mesh=mesh, kw=kw, result=result):
            result.append(auto_cage(mesh, return_report=True, **kw))

        times = timed(run, repeat)
        cage, rep = result[-1]
        rows.append(
            [
                name,
                f"{rep.n_points}",
                summary(times),
                rep.method,
                f"{rep.n_faces}",
                f"{rep.n_components}",
                f"{rep.clearance:.4g}",
                f"{100 * rep.clearance_relative:.2f}%",
                f"{rep.min_winding_number:.6f}",
                "yes" if rep.enclosed else "NO",
            ]
        )
        print(f"  {name}: {rep}" + (f"  notes: {rep.notes}" if rep.notes else ""), flush=True)
    print_table(
        [
            "model",
            "points",
            "seconds (target <= 5 s)",
            "method",
            "faces",
            "parts",
            "clearance",
            "% diag",
            "min winding",
            "enclosed",
        ],
        rows,
    )


def beast_quality() -> None:
    import pyvista as pv

    from vhm_viz.autocage import auto_cage
    from vhm_viz.autocage.anchors import auto_anchors
    from vhm_viz.core.deformer import Deformer
    from vhm_viz.io import read_cage

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
    cage_table(quick, repeat)
    beast_quality()


if __name__ == "__main__":
    main()
