"""``vhm-viz deform``: deform a mesh, tet mesh, point cloud or volume with a scene."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from vhm_viz.cli._util import (
    OUTPUT_SUFFIXES,
    CLIError,
    Progress,
    add_convergence_argument,
    build_and_solve,
    check_input,
    check_output,
    fold_warning,
    load_scene,
    observe_progress,
    outside_message,
    quiet_vtk,
    surface_metrics,
)
from vhm_viz.core.errors import OutsideCageError
from vhm_viz.io import DATASET_SUFFIXES, read_dataset, write_dataset

ALL_OUTPUT_SUFFIXES = tuple(sorted({s for v in OUTPUT_SUFFIXES.values() for s in v}))


def add_parser(subparsers) -> None:
    """Register the ``deform`` subcommand."""
    p = subparsers.add_parser(
        "deform",
        help="deform a dataset with a scene (cage, anchors, constraints)",
        description="Deform INPUT with the variational harmonic map described by SCENE and "
        "write OUTPUT. Surfaces stay surfaces, tet meshes stay tet meshes; a volume (.vti) "
        "written to .vti is resampled onto a regular grid (pull-back through the inverse "
        "map), to .vts it becomes a warped structured grid. Prints one summary line, and a "
        "warning line (stderr) when the output has inverted cells or det J <= 0 at sampled "
        "points.",
        epilog=f"input types: {' '.join(DATASET_SUFFIXES)}, or a DICOM folder. Example: "
        "vhm-viz deform bar.vtp "
        "--scene bar.json -o bent.vtp",
    )
    p.add_argument("input", metavar="INPUT", help="dataset to deform")
    p.add_argument("--scene", "-s", required=True, metavar="SCENE", help="scene file (JSON)")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUTPUT",
        help="output file (never the input; written atomically)",
    )
    p.add_argument(
        "--outside",
        choices=("error", "passthrough"),
        default="error",
        help="points outside the cage: fail (default) or leave them in place, "
        "flagged by the point array vhm_outside",
    )
    p.add_argument(
        "--arrays",
        default="",
        help="comma-separated extra arrays: displacement, det, cond (point arrays), cells "
        "(cell_jacobian_determinant, cell_condition_number, cell_inverted of 3D cells)",
    )
    p.add_argument(
        "--fill-value",
        type=float,
        default=0.0,
        help="volume resampling: value of voxels without a pre-image (default 0)",
    )
    add_convergence_argument(p)
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``deform``; returns the exit status."""
    quiet_vtk()
    print(deform(args))
    return 0


def _parse_arrays(text: str) -> set[str]:
    names = {t.strip() for t in text.split(",") if t.strip()}
    known = {"displacement", "det", "cond", "cells"}
    bad = sorted(names - known)
    if bad:
        raise CLIError(f"unknown --arrays entry {bad[0]!r}; use displacement, det, cond, cells")
    return names


def deform(args: argparse.Namespace) -> str:
    """Do the work; returns the summary line."""
    import pyvista as pv

    from vhm_viz.filters import HarmonicDeformationFilter, HarmonicResampleFilter, update

    src = check_input(args.input)
    arrays = _parse_arrays(args.arrays)
    scene = load_scene(args.scene)
    # never write onto the data, the scene or any file the scene names
    check_output(args.output, ALL_OUTPUT_SUFFIXES, [src, args.scene, *scene.referenced_files()])
    out = Path(args.output)
    mesh = read_dataset(src)
    resample = isinstance(mesh, pv.ImageData) and out.suffix.lower() == ".vti"
    out_type = "ImageData" if resample else _output_type(mesh)
    if out.suffix.lower() not in OUTPUT_SUFFIXES[out_type]:
        raise CLIError(
            f"cannot write a {out_type} to {out.suffix!r}; use "
            f"{', '.join(OUTPUT_SUFFIXES[out_type])}"
        )

    t0 = time.perf_counter()
    dfm, reports = build_and_solve(
        scene, mesh, quiet=args.quiet, allow_unconverged=args.allow_unconverged
    )
    if resample:
        flt = HarmonicResampleFilter()
        flt.SetFillValue(args.fill_value)
        label = "resampling"
    else:
        flt = HarmonicDeformationFilter()
        flt.SetOutsidePolicy(args.outside)
        flt.SetComputeDisplacement("displacement" in arrays)
        flt.SetComputeJacobianDeterminant("det" in arrays)
        flt.SetComputeConditionNumber("cond" in arrays)
        flt.SetComputeCellQuality("cells" in arrays)
        label = "binding"
    flt.SetInputData(mesh)
    flt.SetDeformer(dfm)
    bar = Progress(label, enabled=not args.quiet)
    observe_progress(flt, bar)
    try:
        result = pv.wrap(update(flt))
    except OutsideCageError as exc:
        raise CLIError(outside_message(exc, mesh.n_points, src)) from exc
    bar.finish()
    # everything that can fail happens before the write: an error never follows an output
    summary = _summary(mesh, result, reports, flt, resample)
    warning = _check_folds(mesh, result, dfm, flt, resample)
    write_dataset(out, result)
    seconds = time.perf_counter() - t0
    if warning:
        print(warning, file=sys.stderr)
    return ", ".join([*summary, f"{seconds:.1f} s"]) + f" -> {out}"


def _summary(mesh, result, reports, flt, resample: bool) -> list[str]:
    iterations = sum(r.iterations for r in reports)
    parts = [f"deformed {mesh.n_points} points ({type(mesh).__name__})"]
    parts.append(f"{iterations} iterations" + ("" if reports[-1].converged else " (not converged)"))
    if resample:
        stats = flt.stats
        parts.append(f"{stats['valid']}/{stats['voxels']} voxels with a pre-image")
    else:
        metrics = surface_metrics(mesh, result)
        if "E_volume" in metrics:
            parts.append(f"E_volume {metrics['E_volume']:.4f}")
        parts.append(f"{flt.outside_count} points outside the cage")
    return parts


def _output_type(mesh) -> str:
    import pyvista as pv

    if isinstance(mesh, pv.PolyData):
        return "PolyData"
    if isinstance(mesh, pv.UnstructuredGrid):
        return "UnstructuredGrid"
    return "StructuredGrid"


def _check_folds(mesh, result, dfm, flt, resample: bool) -> str | None:
    """The fold warning of the output: inverted cells and sampled det J <= 0."""
    from vhm_viz.filters import cell_quality

    cells = None
    point_det = None
    if not resample:
        cells = cell_quality(mesh, result.points)
        if "jacobian_determinant" in result.point_data:
            point_det = np.asarray(result.point_data["jacobian_determinant"])
            if "vhm_outside" in result.point_data:  # passthrough points are not the map's
                point_det = np.where(result.point_data["vhm_outside"] == 0, point_det, np.nan)
    return fold_warning(mesh, dfm.harmonic_map, cells=cells, point_det=point_det)
