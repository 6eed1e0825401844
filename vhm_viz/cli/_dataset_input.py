"""The dataset input of ``vhm-viz cage`` and ``vhm-viz anchors``: INPUT and --threshold."""

from __future__ import annotations

import argparse

__all__ = ["add_dataset_argument", "add_threshold_argument", "threshold_of"]


def add_dataset_argument(p: argparse.ArgumentParser) -> None:
    """Add the positional INPUT: the dataset the command builds its set-up for."""
    p.add_argument("input", metavar="INPUT", help="dataset (any PyVista format, .mesh, .npy)")


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
        f"('otsu' picks one) (default: {default})",
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
