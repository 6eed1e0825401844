"""``vhm-viz anchors``: place automatic anchors inside a dataset and its cage (JSON)."""

from __future__ import annotations

import argparse

from vhm_viz.cli._dataset_input import (
    add_dataset_arguments,
    add_output_argument,
    grid_options,
    options_named,
    report_written,
)
from vhm_viz.cli._util import check_input, check_output
from vhm_viz.io import CAGE_SUFFIXES, read_cage, read_dataset, write_anchors

#: The libraries ``anchors`` imports when it runs (not for its help).
RUN_IMPORTS = ("vhm_viz.autocage",)

#: What ``--timings`` reports, besides "other".
TIMING_STAGES = "read, anchors, write"

HELP = "place anchors on the medial axis/surface of a dataset, inside its cage"

DESCRIPTION = (
    "Place --count anchors on an approximation of the medial axis/surface "
    "of INPUT, strictly inside INPUT and CAGE (which must enclose INPUT), and write them "
    "as JSON: "
    '{"anchors": [[x, y, z], ...], "count": d, "min_pairwise_distance": ...}, '
    "or, to an OUTPUT ending in .mrk.json, a 3D Slicer point list (LPS)."
)


def add_arguments(p) -> None:
    """The ``anchors`` subcommand's arguments."""
    p.add_argument(
        "--cage", "-c", required=True, metavar="CAGE", help=f"cage file: {' '.join(CAGE_SUFFIXES)}"
    )
    add_output_argument(p, "ANCHORS.json", "output JSON, or a 3D Slicer point list (*.mrk.json)")
    p.add_argument(
        "--count",
        "-n",
        type=int,
        default=24,
        metavar="N",
        help="number of anchors, 1 to 10000 (default: 24)",
    )
    add_dataset_arguments(p, "anchors")


def run(args: argparse.Namespace) -> int:
    """Run ``anchors``; returns the exit status."""
    from vhm_viz.autocage import auto_anchors  # here: ``vhm-viz --help`` skips its libraries

    src = check_input(args.input)
    cage_path = check_input(args.cage, CAGE_SUFFIXES)
    dst = check_output(args.output, (".json",), inputs=[src, cage_path])
    timer = args.timer
    with timer.stage("read"):
        data, cage = read_dataset(src), read_cage(cage_path)
    with timer.stage("anchors"), options_named():
        anchors, report = auto_anchors(
            data, cage, args.count, return_report=True, **grid_options(args)
        )
    with timer.stage("write"):
        write_anchors(
            dst,
            anchors,
            min_pairwise_distance=report.min_pairwise_distance,
            min_depth=report.min_depth,
            input=str(src),
            cage=str(cage_path),
        )
    return report_written(args, dst, report)
