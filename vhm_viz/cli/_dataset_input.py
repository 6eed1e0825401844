"""What ``vhm-viz cage`` and ``vhm-viz anchors`` share: the dataset input and its grid.

INPUT, ``--resolution``, ``--threshold``, ``--quiet`` and ``-o``, the keyword options they
become for :func:`vhm_viz.auto_cage` and :func:`vhm_viz.auto_anchors`, and the line that
reports the result.
"""

from __future__ import annotations

import argparse
import contextlib
import sys

from vhm_viz.cli._util import CLIError, add_quiet_argument
from vhm_viz.core.errors import SettingError
from vhm_viz.io import DATASET_SUFFIXES

__all__ = [
    "add_dataset_arguments",
    "add_output_argument",
    "add_threshold_argument",
    "grid_options",
    "options_named",
    "report_written",
    "threshold_of",
]


#: Per command: the grid whose longest side ``--resolution`` counts voxels along, and its
#: default.
_GRIDS = {
    "cage": "the extraction grid's bounding box, at least 1 (default: 1.5 x that side / "
    "the offset, within 32-112, coarser where the clearance would take the grid past 115; --method "
    "voxel: the finest that fits --max-faces)",
    "anchors": "the grid the medial axis is computed on, at least 4 (default: 96; volumes: one per "
    "image sample, at most 96)",
}
#: Per command: what it does with a volume's region above ``--threshold``, and what it
#: works on without one.
_REGIONS = {
    "cage": ("enclose the region", "the volume's bounding box"),
    "anchors": ("place anchors in the region", "the whole volume"),
}


def add_dataset_arguments(p: argparse.ArgumentParser, command: str) -> None:
    """Add INPUT, ``--resolution``, ``--threshold`` and ``--quiet``.

    INPUT is the dataset the command builds its set-up for; the options come last in the
    command's help, worded for the command.

    Parameters
    ----------
    p : argparse.ArgumentParser
    command : {"cage", "anchors"}
    """
    p.add_argument(
        "input",
        metavar="INPUT",
        help=f"dataset: {' '.join(DATASET_SUFFIXES)}, or a DICOM folder",
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        metavar="VOXELS",
        help=f"voxels along the longest side of {_GRIDS[command]}",
    )
    add_threshold_argument(p, *_REGIONS[command])
    add_quiet_argument(p, "print nothing on success")


def add_output_argument(p: argparse.ArgumentParser, metavar: str, written: str) -> None:
    """Add the required ``-o``/``--output``; ``metavar`` names it, ``written`` says what it gets."""
    p.add_argument("-o", "--output", required=True, metavar=metavar, help=written)


def add_threshold_argument(p: argparse.ArgumentParser, purpose: str, default: str) -> None:
    """Add ``--threshold``: which region of a volume the command works on.

    Parameters
    ----------
    p : argparse.ArgumentParser
    purpose : str
        What the command does with the region, e.g. ``"enclose the region"``.
    default : str
        What it works on without a threshold.
    """
    p.add_argument(
        "--threshold",
        default=None,
        metavar="VALUE",
        help=f"volumes: {purpose} above this value, in the units of the data "
        f"('otsu' picks one; refused for other inputs) (default: {default})",
    )


def threshold_of(args: argparse.Namespace) -> float | str | None:
    """The ``--threshold`` argument as :func:`vhm_viz.auto_cage` takes it.

    Returns
    -------
    float, "otsu" or None
        A number, ``"otsu"`` (any case, as given) or None when not given.

    Raises
    ------
    ValueError
        Neither a number nor ``"otsu"``.
    """
    threshold = args.threshold
    if threshold is None or threshold.lower() == "otsu":
        return threshold
    try:
        return float(threshold)
    except ValueError as exc:
        raise ValueError(f"--threshold must be a number or 'otsu', got {threshold!r}") from exc


def grid_options(args: argparse.Namespace) -> dict:
    """The keyword options ``resolution`` and ``threshold`` of the automatic set-up.

    Returns
    -------
    dict
        ``--resolution`` (None when not given) and :func:`threshold_of`, for
        :func:`vhm_viz.auto_cage` and :func:`vhm_viz.auto_anchors`.
    """
    return {"resolution": args.resolution, "threshold": threshold_of(args)}


@contextlib.contextmanager
def options_named():
    """A setting the automatic set-up refuses, as one line naming its option.

    :func:`vhm_viz.auto_cage` and :func:`vhm_viz.auto_anchors` name their keyword
    (``offset``, ``threshold``, ``resolution``); the line names ``--offset``, ...
    """
    try:
        yield
    except SettingError as exc:
        raise CLIError(f"--{exc.field.replace('_', '-')} {exc.detail}") from exc


def report_written(args: argparse.Namespace, output, report) -> int:
    """Print ``OUTPUT: report`` on stdout unless ``--quiet``; returns the exit status 0."""
    if not args.quiet:
        print(f"{output}: {report}", file=sys.stdout)
    return 0
