"""``vhm-viz anchors``: place automatic anchors inside a dataset and its cage (JSON)."""

from __future__ import annotations

import argparse
import sys

from vhm_viz.cli._dataset_input import add_dataset_argument, add_threshold_argument, threshold_of
from vhm_viz.cli._util import add_quiet_argument, check_input, check_output
from vhm_viz.io import CAGE_SUFFIXES, read_cage, read_dataset, write_anchors

HELP = "place anchors on the medial axis/surface of a dataset, inside its cage"

DESCRIPTION = (
    "Place --count anchors on an approximation of the medial axis/surface "
    "of INPUT, strictly inside INPUT and CAGE, and write them as JSON: "
    '{"anchors": [[x, y, z], ...], "count": d, "min_pairwise_distance": ...}, '
    "or, to an OUTPUT ending in .mrk.json, a 3D Slicer point list (LPS)."
)


def add_arguments(p) -> None:
    """The ``anchors`` subcommand's arguments."""
    add_dataset_argument(p)
    p.add_argument("--cage", "-c", required=True, metavar="CAGE", help="cage file (OBJ, ...)")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="ANCHORS.json",
        help="output JSON, or a 3D Slicer point list (*.mrk.json)",
    )
    p.add_argument(
        "--count", "-n", type=int, default=24, metavar="N", help="number of anchors (default: 24)"
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        metavar="VOXELS",
        help="voxels along the longest side of the grid the medial axis is computed on "
        "(default: 96; volumes: one per image sample, at most 96)",
    )
    add_threshold_argument(p, "place anchors in the region", "the whole volume")
    add_quiet_argument(p, "print nothing on success")


def run(args: argparse.Namespace) -> int:
    """Run ``anchors``; returns the exit status."""
    # loaded when the command runs, so that the other commands start without it
    from vhm_viz.autocage import auto_anchors

    src = check_input(args.input)
    cage_path = check_input(args.cage, CAGE_SUFFIXES)
    dst = check_output(args.output, (".json",), inputs=[src, cage_path])
    anchors, report = auto_anchors(
        read_dataset(src),
        read_cage(cage_path),
        args.count,
        resolution=args.resolution,
        threshold=threshold_of(args),
        return_report=True,
    )
    write_anchors(
        dst,
        anchors,
        min_pairwise_distance=report.min_pairwise_distance,
        min_depth=report.min_depth,
        input=str(src),
        cage=str(cage_path),
    )
    if not args.quiet:
        print(f"{dst}: {report}", file=sys.stdout)
    return 0
