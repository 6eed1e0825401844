"""Benchmark of the variational harmonic map solver (issue 3).

Prints Markdown tables:

1. time per local/global iteration (local step + global step + Anderson bookkeeping and
   energy) for d = 6, 50 and 88 anchors on the bar, plain and accelerated: each sample is
   the mean over 2000 iterations of one ``solve`` call (>= 1000 required), median and spread
   over the repeats;
2. iterations (and solve time) to converge for every bar kind, rigid and similar, from the
   identity (the twist is ramped over 6 warm-started steps, as in ``examples.bar``);
3. precompute times (anchor layout: basis rows and QR of A; constraint layout: B and C;
   binding: F) and F's memory, for the bar and for the 172,966-vertex Armadillo with
   ``cage_500f`` and 50 anchors placed on the ridge of the interior distance field
   (farthest-point sampled);
4. deformation time (the F product) for both, float64 and float32, with the float32 error
   relative to the bounding-box diagonal.

Run: ``python benchmarks/bench_solver.py [--repeats 7] [--skip-armadillo]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _common import data, print_table, summary, timed

from vhm_viz import examples
from vhm_viz.core.deformer import Deformer


def per_iteration(repeats: int) -> list[list[str]]:
    rows = []
    for d in (6, 50, 88):
        sc = examples.bar("bend-u", n_anchors=d)
        dfm = sc.deformer
        dfm.solve(max_iterations=5)  # JIT warm-up
        for window in (0, dfm.anderson_window):  # plain, and the default acceleration
            per = []
            for _ in range(repeats):
                rep = dfm.solve(
                    init="identity", tolerance=1e-300, max_iterations=2000, anderson_window=window
                )
                per.append(rep.seconds / rep.iterations)
            label = "plain" if window == 0 else f"Anderson({window})"
            target = "<= 50 us" if d == 50 else ""
            rows.append([str(d), label, summary(per), target])
    return rows


def convergence(tolerance: float) -> list[list[str]]:
    rows = []
    for kind in examples.BAR_KINDS:
        for mode in ("rigid", "similar"):
            sc = examples.bar(kind, mode=mode)
            sc.deformer.solve(max_iterations=2)  # warm-up
            reps = sc.solve(tolerance=tolerance, max_iterations=20000)
            its = [r.iterations for r in reps]
            secs = sum(r.seconds for r in reps)
            plain = sc.deformer.solve(
                init="identity", tolerance=tolerance, max_iterations=20000, anderson_window=0
            )
            rows.append(
                [
                    kind,
                    mode,
                    "+".join(map(str, its)) if len(its) > 1 else str(its[0]),
                    f"{secs * 1e3:.2f} ms",
                    str(all(r.converged for r in reps)),
                    f"{reps[-1].energy[-1]:.6g}",
                    f"{plain.iterations}{'' if plain.converged else ' (not converged)'}"
                    + (" (twist: unramped)" if kind == "twist" else ""),
                ]
            )
    return rows


def armadillo_anchors(count: int = 50, res: int = 56) -> np.ndarray:
    """Anchors on the ridge of the interior distance field of the Armadillo.

    Signed distance to the 43k surface on a ``res^3`` grid; ridge voxels (local maxima of the
    depth over their 26 neighbours, at least 2 voxels deep) are farthest-point sampled.
    """
    import pyvista as pv
    from scipy.ndimage import maximum_filter

    surf = pv.read(data("armadillo", "armadillo_43k.obj"))
    surf = surf.extract_surface(algorithm="dataset_surface").triangulate()
    lo, hi = np.array(surf.bounds[::2]), np.array(surf.bounds[1::2])
    h = (hi - lo).max() / res
    dims = np.ceil((hi - lo) / h).astype(int) + 1
    grid = pv.ImageData(dimensions=dims, spacing=(h, h, h), origin=lo)
    dist = np.asarray(grid.compute_implicit_distance(surf)["implicit_distance"])
    depth = (-dist).reshape(dims[::-1])  # VTK x-fastest -> array [z, y, x]
    ridge = (depth >= maximum_filter(depth, size=3)) & (depth > 2 * h)
    zi, yi, xi = np.nonzero(ridge)
    pts = lo + h * np.column_stack([xi, yi, zi])
    # farthest point sampling, starting from the deepest point
    chosen = [int(np.argmax(depth[ridge]))]
    dmin = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for _ in range(count - 1):
        k = int(np.argmax(dmin))
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(pts - pts[k], axis=1))
    return pts[chosen]


def precompute_and_deform(repeats: int, skip_armadillo: bool) -> tuple[list, list]:
    import pyvista as pv

    from vhm_viz.io import read_cage

    pre_rows, def_rows = [], []
    cases = [("bar (33,464 v, 208 f, d=6)", "bar")]
    if not skip_armadillo:
        cases.append(("Armadillo (172,966 v, 500 f, d=50)", "arma"))
    for label, which in cases:
        if which == "bar":
            sc = examples.bar("bend-u")
            cage, anchors, pts = sc.cage, sc.anchors, sc.points
            cons = sc.constraints
        else:
            cage = read_cage(data("armadillo", "cage_500f.obj"))
            pts = np.asarray(pv.read(data("armadillo", "armadillo_173k.ply")).points, dtype=float)
            t0 = time.perf_counter()
            anchors = armadillo_anchors(50)
            print(f"(Armadillo anchors placed in {time.perf_counter() - t0:.1f} s)")
            up = 1  # y is up in the libigl frame
            order = np.argsort(anchors[:, up])
            feet = anchors[order[:2]]
            hand = anchors[np.argmax(anchors[:, 0])]
            diag = cage.diagonal
            rot = examples.rotation("z", 30)
            cons = {
                "positions": np.vstack([feet, hand]),
                "targets": np.vstack([feet, hand + [0, 0.05 * diag, 0]]),
                "jacobian_points": hand[None],
                "jacobians": rot[None],
            }
        # warm the JIT-compiled basis kernels (numba cache) so that compilation is not timed
        from vhm_viz.core.basis import evaluate_basis

        for order in (0, 1, 2):
            evaluate_basis(pts[:4], cage.vertices, cage.faces, order=order)
        t0 = time.perf_counter()
        dfm = Deformer(cage, anchors)
        t_anchor = time.perf_counter() - t0
        t0 = time.perf_counter()
        dfm.set_constraints(**cons)
        t_cons = time.perf_counter() - t0
        t0 = time.perf_counter()
        b64 = dfm.bind(pts)
        t_bind = time.perf_counter() - t0
        t0 = time.perf_counter()
        b32 = dfm.bind(pts, dtype=np.float32)
        t_bind32 = time.perf_counter() - t0
        dfm.solve(max_iterations=2)  # JIT warm-up
        rep = dfm.solve(init="identity", tolerance=1e-6, max_iterations=20000)
        pre_rows.append(
            [
                label,
                f"{t_anchor:.2f} s",
                f"{t_cons:.3f} s",
                f"{t_bind:.2f} s",
                f"{t_anchor + t_cons + t_bind:.2f} s",
                f"{b64.F.nbytes / 1e6:.0f} MB / {b32.F.nbytes / 1e6:.0f} MB",
                f"{rep.iterations} it, {rep.seconds * 1e3:.1f} ms"
                + ("" if rep.converged else " (not converged)"),
            ]
        )
        del t_bind32
        x64 = b64.deform()
        x32 = b32.deform()
        err = np.abs(x32 - x64).max() / np.linalg.norm(pts.max(0) - pts.min(0))
        out = np.empty_like(x64)
        t64 = timed(lambda b=b64, o=out: b.deform(out=o), repeats * 3)
        t32 = timed(lambda b=b32, o=out: b.deform(out=o), repeats * 3)
        def_rows.append([label, "float64", summary(t64), "-"])
        def_rows.append([label, "float32", summary(t32), f"{err:.2e}"])
    return pre_rows, def_rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--skip-armadillo", action="store_true")
    args = ap.parse_args()

    print("## Time per local/global iteration (bar, bend-u)\n")
    print_table(
        [
            "anchors d",
            "iteration",
            "time / iteration: median (min-max) of 2000-iteration means",
            "target",
        ],
        per_iteration(args.repeats),
    )
    for tol in (1e-6, 1e-8):
        print(f"\n## Iterations to converge (tolerance {tol:g}, from identity)\n")
        print_table(
            [
                "kind",
                "mode",
                "iterations (Anderson)",
                "solve time",
                "converged",
                "energy",
                "plain iterations",
            ],
            convergence(tol),
        )
    pre, dfm_rows = precompute_and_deform(args.repeats, args.skip_armadillo)
    print("\n## Precompute (single run) and F memory\n")
    print_table(
        [
            "model",
            "anchor layout (basis rows, QR of A)",
            "constraints (B, C)",
            "bind (F)",
            "total",
            "F float64 / float32",
            "solve from identity (tol 1e-6)",
        ],
        pre,
    )
    print("\n## Deformation (F product, x = p + F dw)\n")
    print_table(["model", "F dtype", "time per frame", "float32 error / bbox diagonal"], dfm_rows)


if __name__ == "__main__":
    main()
