"""``vhm-viz cage``: build an automatic cage for a dataset and write it as OBJ."""

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
from vhm_viz.io import read_dataset, write_cage

#: The libraries ``cage`` imports when it runs (not for its help).
RUN_IMPORTS = ("vhm_viz.autocage",)

#: What ``--timings`` reports, besides "other".
TIMING_STAGES = "read, cage, write"

HELP = "build an automatic cage (closed, manifold, enclosing) for a dataset"

DESCRIPTION = (
    "Build a cage that strictly encloses INPUT (surface, point cloud, tet "
    "mesh or volume) and follows its shape, with at most --max-faces triangles; write "
    "it as OBJ. Prints the face count, clearance and enclosure check."
)


def add_arguments(p) -> None:
    """The ``cage`` subcommand's arguments."""
    add_output_argument(p, "CAGE.obj", "output OBJ")
    p.add_argument(
        "--max-faces",
        type=int,
        default=500,
        metavar="N",
        help="largest number of triangles (default: 500)",
    )
    p.add_argument(
        "--offset",
        type=float,
        default=None,
        metavar="DISTANCE",
        help="clearance between the data and the cage, in world units (the data's units) "
        "(default: 1%% of the bounding-box diagonal; at most the diagonal)",
    )
    p.add_argument(
        "--method",
        choices=("auto", "offset", "voxel"),
        default="auto",
        help="offset: a surface at the clearance, simplified; voxel: boxes of voxels; auto: "
        "offset, retried at 2 and 4 times the clearance, then voxel (default: auto)",
    )
    add_dataset_arguments(p, "cage")


def run(args: argparse.Namespace) -> int:
    """Run ``cage``; returns the exit status."""
    from vhm_viz.autocage import auto_cage  # here: ``vhm-viz --help`` skips its libraries

    src = check_input(args.input)
    dst = check_output(args.output, (".obj",), inputs=[src])
    timer = args.timer
    with timer.stage("read"):
        data = read_dataset(src)
    with timer.stage("cage"), options_named():
        cage, report = auto_cage(
            data,
            offset=args.offset,
            max_faces=args.max_faces,
            method=args.method,
            return_report=True,
            **grid_options(args),
        )
    with timer.stage("write"):
        write_cage(dst, cage, comment=f"vhm-viz cage of {src.name}\n{report}")
    return report_written(args, dst, report)
