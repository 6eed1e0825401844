"""``vhm-viz demo``: the bundled end-to-end demonstration on generated data."""

from __future__ import annotations

import argparse
import time

import numpy as np


def add_parser(subparsers) -> None:
    """Register the ``demo`` subcommand."""
    p = subparsers.add_parser(
        "demo",
        help="run the bundled demo on generated data",
        description="Deform a generated bar with a cage-driven harmonic map and print what "
        "happened (points, timing, Jacobian quality).",
    )
    p.add_argument("--points", type=int, default=20000, help="surface points of the bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the demo; returns the exit status."""
    from vhm_viz.core.basis import winding_number
    from vhm_viz.core.cage import Cage
    from vhm_viz.core.harmonic_map import HarmonicMap

    rng = np.random.default_rng(0)
    # a 1 x 1 x 5 bar sampled on its surface, inside a 1.3 x 1.3 x 5.4 box cage
    pts = rng.uniform([-0.5, -0.5, 0.0], [0.5, 0.5, 5.0], (args.points, 3))
    axis = rng.integers(0, 2, args.points)
    pts[np.arange(args.points), axis] = np.sign(pts[np.arange(args.points), axis]) * 0.5
    lo, hi = np.array([-0.65, -0.65, -0.2]), np.array([0.65, 0.65, 5.2])
    corners = np.array(
        [[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])]
    )
    faces = np.array(
        [
            [0, 2, 1],
            [1, 2, 3],
            [4, 5, 6],
            [5, 7, 6],
            [0, 1, 4],
            [1, 5, 4],
            [2, 6, 3],
            [3, 6, 7],
            [0, 4, 2],
            [2, 4, 6],
            [1, 3, 5],
            [3, 7, 5],
        ]
    )
    cage = Cage(corners, faces)
    # twist the top of the cage by 90 degrees about the bar's axis
    target = cage.vertices.copy()
    top = target[:, 2] > 2.5
    c, s = np.cos(np.pi / 2), np.sin(np.pi / 2)
    target[top, :2] = target[top, :2] @ np.array([[c, s], [-s, c]])
    t0 = time.perf_counter()
    hm = HarmonicMap.from_target_cage(cage, target)
    deformed, jac, _ = hm.evaluate(pts, order=1)
    dt = time.perf_counter() - t0
    det = np.linalg.det(jac)
    print(
        f"cage: {cage.n_vertices} vertices, {cage.n_faces} faces; "
        f"points inside: {(winding_number(pts, cage.vertices, cage.faces) > 0.5).sum()}/{len(pts)}"
    )
    print(f"deformed {len(pts)} points with a Green-coordinates twist in {dt:.3f} s")
    print(
        f"Jacobian determinant: min {det.min():.3f}, median {np.median(det):.3f}, "
        f"max {det.max():.3f}; foldovers: {(det <= 0).sum()}"
    )
    print(f"mean displacement: {np.linalg.norm(deformed - pts, axis=1).mean():.3f}")
    return 0
