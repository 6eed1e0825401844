"""Benchmark of the closed-form basis kernels.

Prints a Markdown table: point-face pairs per second for values, values+gradients and
values+gradients+Hessians, and the wall time to evaluate basis values at all 172,966
vertices of the 173k Armadillo with its 216- and 500-face cages (first call including JIT
compilation, measured in a fresh process with an empty numba cache, and warm calls).

Run: ``python benchmarks/bench_basis.py [--repeats 5]``
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np
from _common import data, print_table, summary, timed

FIRST_CALL = """
import time, numpy as np, pyvista as pv, sys
sys.path.insert(0, {bench!r})
from _common import data
from vhm_viz.io import read_cage
cage = read_cage(data('armadillo', {cage!r}))
pts = np.asarray(pv.read(data('armadillo', 'armadillo_173k.ply')).points, dtype=float)
t0 = time.perf_counter()
from vhm_viz.core.basis import evaluate_basis
evaluate_basis(pts, cage.vertices, cage.faces, order=0)
print(time.perf_counter() - t0)
"""


def first_call_seconds(cage_name: str) -> float:
    """Import + JIT compile + evaluate, in a fresh process with an empty numba cache."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        code = FIRST_CALL.format(bench=os.path.dirname(os.path.abspath(__file__)), cage=cage_name)
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
        )
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    import numba
    import pyvista as pv

    from vhm_viz.core.basis import evaluate_basis
    from vhm_viz.io import read_cage

    pts = np.asarray(pv.read(data("armadillo", "armadillo_173k.ply")).points, dtype=np.float64)
    print(f"numba threads: {numba.get_num_threads()}, points: {len(pts)}\n")
    rows = []
    cage500 = read_cage(data("armadillo", "cage_500f.obj"))
    sub = pts[:: max(1, len(pts) // 20000)]
    for order, label, subset in (
        (0, "values", sub),
        (1, "values+gradients", sub),
        (2, "values+gradients+Hessians", sub[:8000]),
    ):
        evaluate_basis(subset[:16], cage500.vertices, cage500.faces, order=order)  # compile
        times = timed(
            lambda o=order, s=subset: evaluate_basis(s, cage500.vertices, cage500.faces, order=o),
            args.repeats,
        )
        pairs = len(subset) * cage500.n_faces
        rates = sorted(pairs / t / 1e6 for t in times)
        rows.append(
            [
                f"{label} (cage_500f, {len(subset)} pts)",
                f"{np.median(rates):.1f} M pairs/s ({rates[0]:.1f}-{rates[-1]:.1f})",
                summary(times),
            ]
        )
    for cage_name in ("cage_216f.obj", "cage_500f.obj"):
        cage = read_cage(data("armadillo", cage_name))
        first = first_call_seconds(cage_name)
        evaluate_basis(pts[:16], cage.vertices, cage.faces)
        times = timed(
            lambda c=cage: evaluate_basis(pts, c.vertices, c.faces, order=0), args.repeats
        )
        rows.append(
            [
                f"Armadillo 173k x {cage_name[:-4]} values, first call (JIT compile)",
                "",
                f"{first:.2f} s",
            ]
        )
        rows.append(
            [
                f"Armadillo 173k x {cage_name[:-4]} values, warm",
                f"{len(pts) * cage.n_faces / np.median(times) / 1e6:.1f} M pairs/s",
                summary(times),
            ]
        )
    print_table(["what", "throughput", "wall time median (min-max)"], rows)


if __name__ == "__main__":
    main()
