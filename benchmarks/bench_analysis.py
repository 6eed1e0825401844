"""Benchmark of the analysis (issue 14): the injectivity certificate and per-cell quality.

Prints Markdown tables (median, min-max and count of the repeats; the compiled code is
cached by a warm-up call first):

1. the issue's goals on the paper's bar (``examples.bar``): bend-u certified over the bar's
   solid (goal <= 2 s); a clear fold, the top pushed down to 2.5 (``examples.bar("push")``),
   answered with a witness (<= 0.5 s); a subtle fold, top at 3.582 (min det J about -0.01,
   no tet of ``examples.bar_tets(10)`` inverts), found over that tet mesh (<= 5 s); a
   near-fold, top at 3.666 (min det J about +0.014), still certified. Each row also gives
   the minimum of det J over 250,000 exact samples of the solid (after a local
   refinement), the cubes examined and the time per cube.
2. the cost against the region's distance to the cage: bend-u certified over the cage's
   interior minus margins from 0.2 down to 0.075 (the bar is 0.15 from its cage).
3. per-cell quality (determinant and condition number of every tet) of the dragon tet
   mesh (104,261 tets, ``../shared/data``), given the deformed points.

Run: ``python benchmarks/bench_analysis.py [--repeats 3] [--margins 0.2 0.15 0.1 0.075]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
from _common import DATA, print_table, summary, timed
from scipy.optimize import minimize

from vhm_viz import examples
from vhm_viz.core.certify import Region, certify_injectivity
from vhm_viz.core.metrics import cell_measures

BAR_LO, BAR_HI = np.array([-0.5, -0.5, 0.0]), np.array([0.5, 0.5, 5.0])


def min_det(hm, samples: int = 250_000) -> float:
    """Minimum of det J over the bar's solid: a dense grid, then L-BFGS from its lowest points."""
    n = round((samples / 5) ** (1 / 3))
    axes = [np.linspace(BAR_LO[a], BAR_HI[a], n * (5 if a == 2 else 1)) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    det = np.linalg.det(hm.jacobian(grid))
    best = float(det.min())
    for i in np.argsort(det)[:5]:
        res = minimize(
            lambda x: np.linalg.det(hm.jacobian(x[None])[0]),
            grid[i],
            bounds=list(zip(BAR_LO, BAR_HI, strict=True)),
            method="L-BFGS-B",
        )
        best = min(best, float(res.fun))
    return best


def timed_certify(hm, region, repeats: int, **kw):
    """Wall times of ``repeats`` certifications, their median CPU time, the last answer.

    The CPU time (all threads) does not depend on what else runs on the machine: on an idle
    2-core machine the wall time is at least half of it.
    """
    answers, cpu = [], []

    def run():
        c0 = time.process_time()
        answers.append(certify_injectivity(hm, region, **kw))
        cpu.append(time.process_time() - c0)

    times = timed(run, repeats)
    return times, statistics.median(cpu), answers[-1]


def solved(kind: str, **kw):
    sc = examples.bar(kind, **kw)
    sc.solve()
    return sc.deformer.harmonic_map


def goals(repeats: int) -> list[list[str]]:
    box = Region.box(BAR_LO, BAR_HI)
    points, tets = examples.bar_tets(10)
    tet_region = Region.tetrahedra(points, tets)
    fold = "not injective"
    cases = [
        ("bend-u, over the bar's solid", solved("bend-u"), box, "certified", "<= 2 s"),
        ("clear fold (top at 2.5)", solved("push", top_height=2.5), box, fold, "<= 0.5 s"),
        ("subtle fold (top at 3.582), over the bar's 30,000 tets",
         solved("push", top_height=3.582), tet_region, fold, "<= 5 s"),
        ("near-fold (top at 3.666)", solved("push", top_height=3.666), box, "certified", ""),
    ]  # fmt: skip
    certify_injectivity(cases[0][1], box, max_cubes=50)  # warm-up: compiled code cached
    rows = []
    for label, hm, region, expected, goal in cases:
        times, cpu, cert = timed_certify(hm, region, repeats)
        assert cert.status == expected, f"{label}: {cert.summary()}"
        moved = hm.map(points)[tets]
        vol = np.einsum("ij,ij->i", moved[:, 1] - moved[:, 0],
                        np.cross(moved[:, 2] - moved[:, 0], moved[:, 3] - moved[:, 0]))  # fmt: skip
        answer = cert.status
        if len(cert.witnesses):
            answer += f" (witness det J {cert.witness_determinants[0]:.3g})"
        per_cube = statistics.median(times) / cert.cubes
        rows.append([
            label, answer, summary(times), f"{cpu:.2f} s", goal, str(cert.cubes),
            f"{per_cube * 1e6:.0f} us", f"{min_det(hm):.4f}", str(int(np.count_nonzero(vol <= 0))),
        ])  # fmt: skip
    return rows


def distance(repeats: int, margins) -> list[list[str]]:
    sc = examples.bar("bend-u")
    sc.solve()
    hm = sc.deformer.harmonic_map
    rows = []
    for margin in margins:
        region = Region.cage_interior(sc.cage, margin)
        certify_injectivity(hm, region, max_cubes=50)  # warm-up of the region's own tests
        times, cpu, cert = timed_certify(hm, region, repeats, max_cubes=400_000)
        rows.append([
            f"{margin:g}", cert.status, str(cert.cubes), summary(times), f"{cpu:.2f} s",
            f"{statistics.median(times) / cert.cubes * 1e6:.0f} us", f"{cert.smallest_cube:.3g}",
        ])  # fmt: skip
    return rows


def dragon_cells(repeats: int) -> list[list[str]]:
    path = DATA / "tets" / "dragon.tet.vtk"
    if not path.exists():
        return [["dragon (data missing)", "", "", ""]]
    import pyvista as pv

    mesh = pv.read(path)
    points = np.asarray(mesh.points, dtype=np.float64)
    tets = np.asarray(mesh.cells_dict[pv.CellType.TETRA])
    rng = np.random.default_rng(0)
    moved = points + 0.01 * rng.normal(size=points.shape)
    cell_measures(points, moved, tets[:10])
    times = timed(lambda: cell_measures(points, moved, tets), repeats)
    return [
        [
            "dragon",
            f"{len(tets):,}",
            summary(times),
            f"{statistics.median(times) / len(tets) * 1e9:.0f} ns",
        ]
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--margins", type=float, nargs="*", default=[0.2, 0.15, 0.1, 0.075])
    args = parser.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f} (2 cores)\n")
    print("Certificate goals (bar, 208-face cage; times: median (min-max, n); min det J over")
    print("250,000 samples refined locally; inverted tets of examples.bar_tets(10), 30,000):\n")
    print_table(
        ["scenario", "answer", "time", "CPU", "goal", "cubes", "per cube", "min det J",
         "inverted tets"],
        goals(args.repeats),
    )  # fmt: skip
    print(
        "\nCost against the distance to the cage (bend-u over the cage interior minus a margin):\n"
    )
    print_table(
        ["margin", "answer", "cubes", "time", "CPU", "per cube", "smallest cube side"],
        distance(args.repeats, args.margins),
    )
    print("\nPer-cell quality (det and cond of every tet, given the deformed points):\n")
    print_table(["mesh", "tets", "time", "per tet"], dragon_cells(args.repeats))
    print(f"\nload average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
