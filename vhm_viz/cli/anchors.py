"""``vhm-viz anchors``: place automatic anchors inside a dataset and its cage (JSON)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vhm_viz.cli.cage import check_paths, write_text_atomic


def add_parser(subparsers) -> None:
    """Register the ``anchors`` subcommand."""
    p = subparsers.add_parser(
        "anchors",
        help="place anchors on the medial axis/surface of a dataset, inside its cage",
        description="Place --count anchors on an approximation of the medial axis/surface "
        "of INPUT, strictly inside INPUT and CAGE, and write them as JSON: "
        '{"anchors": [[x, y, z], ...], "count": d, "min_pairwise_distance": ...}.',
    )
    p.add_argument("input", metavar="INPUT", help="dataset (any PyVista format, .mesh, .npy)")
    p.add_argument("--cage", "-c", required=True, metavar="CAGE", help="cage file (OBJ, ...)")
    p.add_argument("-o", "--output", required=True, metavar="ANCHORS.json", help="output JSON")
    p.add_argument("--count", "-n", type=int, default=24, help="number of anchors (default 24)")
    p.add_argument("--resolution", type=int, default=None, help="voxels along the longest side")
    p.add_argument(
        "--threshold", default=None, help="volumes: the region above this value ('otsu' picks one)"
    )
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``anchors``; returns the exit status."""
    from vhm_viz.autoanchors import auto_anchors
    from vhm_viz.cage import Cage

    src, dst = check_paths(args.input, args.output, (".json",))
    cage_path = Path(args.cage)
    if not cage_path.exists():
        raise ValueError(f"cage file not found: {cage_path}")
    if dst.resolve() == cage_path.resolve():
        raise ValueError(f"output {dst} is the cage file; refusing to overwrite it")
    threshold = args.threshold
    if threshold is not None and threshold.lower() != "otsu":
        threshold = float(threshold)
    cage = Cage.from_file(cage_path)
    anchors, report = auto_anchors(
        src,
        cage,
        args.count,
        resolution=args.resolution,
        threshold=threshold,
        return_report=True,
    )
    payload = {
        "anchors": anchors.tolist(),
        "count": int(report.count),
        "min_pairwise_distance": report.min_pairwise_distance,
        "min_depth": report.min_depth,
        "input": str(src),
        "cage": str(cage_path),
    }
    write_text_atomic(json.dumps(payload, indent=1) + "\n", dst)
    if not args.quiet:
        print(f"{dst}: {report}", file=sys.stdout)
    return 0
