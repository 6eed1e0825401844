"""``vhm-viz cage``: build an automatic cage for a dataset and write it as OBJ."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from vhm_viz import atomic


def write_text_atomic(text: str, path: Path) -> None:
    """Write ``text`` to ``path`` atomically (see :mod:`vhm_viz.atomic`)."""
    atomic.write_text_atomic(path, text)


def obj_text(vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> str:
    """Wavefront OBJ text of a triangle mesh (1-based indices)."""
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in np.asarray(vertices)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces)]
    return "\n".join(lines) + "\n"


def check_paths(input_path: str, output: str, suffixes: tuple[str, ...]) -> tuple[Path, Path]:
    """Validate the input (exists) and output (suffix, not the input) paths."""
    src = Path(input_path)
    dst = Path(output)
    if not src.exists():
        raise ValueError(f"input file not found: {src}")
    if dst.suffix.lower() not in suffixes:
        raise ValueError(f"output {dst} must end with one of {', '.join(suffixes)}")
    if dst.exists() and src.exists() and os.path.samefile(src, dst):
        raise ValueError(f"output {dst} is the input file; refusing to overwrite it")
    if dst.resolve() == src.resolve():
        raise ValueError(f"output {dst} is the input file; refusing to overwrite it")
    if not dst.resolve().parent.is_dir():
        raise ValueError(f"output directory does not exist: {dst.parent}")
    return src, dst


def add_parser(subparsers) -> None:
    """Register the ``cage`` subcommand."""
    p = subparsers.add_parser(
        "cage",
        help="build an automatic cage (closed, manifold, enclosing) for a dataset",
        description="Build a cage that strictly encloses INPUT (surface, point cloud, tet "
        "mesh or volume) and follows its shape, with at most --max-faces triangles; write "
        "it as OBJ. Prints the face count, clearance and enclosure check.",
    )
    p.add_argument("input", metavar="INPUT", help="dataset (any PyVista format, .mesh, .npy)")
    p.add_argument("-o", "--output", required=True, metavar="CAGE.obj", help="output OBJ")
    p.add_argument(
        "--max-faces",
        type=int,
        default=500,
        metavar="N",
        help="largest number of triangles (default 500)",
    )
    p.add_argument(
        "--offset",
        type=float,
        default=None,
        help="clearance in world units (default 1%% of the bounding-box diagonal)",
    )
    p.add_argument("--resolution", type=int, default=None, help="voxels along the longest side")
    p.add_argument("--method", choices=("auto", "offset", "voxel"), default="auto")
    p.add_argument(
        "--threshold",
        default=None,
        help="volumes: enclose the region above this value ('otsu' picks one); "
        "default: the bounding box",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cage``; returns the exit status."""
    from vhm_viz.autocage import auto_cage

    src, dst = check_paths(args.input, args.output, (".obj",))
    threshold = args.threshold
    if threshold is not None and threshold.lower() != "otsu":
        try:
            threshold = float(threshold)
        except ValueError as exc:
            raise ValueError(f"--threshold must be a number or 'otsu', got {threshold!r}") from exc
    cage, report = auto_cage(
        src,
        offset=args.offset,
        max_faces=args.max_faces,
        resolution=args.resolution,
        method=args.method,
        threshold=threshold,
        return_report=True,
    )
    write_text_atomic(
        obj_text(cage.vertices, cage.faces, f"vhm-viz cage of {src.name}\n{report}"), dst
    )
    if not args.quiet:
        print(f"{dst}: {report}", file=sys.stdout)
    return 0
