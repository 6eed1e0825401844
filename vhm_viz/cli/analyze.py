"""``vhm-viz analyze``: quality figures, metrics and the analysed dataset of a deformation.

Writes into the output directory the paper's Figure 4 and 12 plots, the energy curve,
``metrics.json`` and the analysed dataset (``analysis.vtu`` / ``.vtp`` / ``.vti`` / ...: the
rest shape with the point arrays of the Jacobian, the cell arrays of the deformed cells and
the point vectors ``displacement``). With ``--certify`` it also proves (or refutes) that the
map has no foldover anywhere in the shape (:func:`vhm_viz.certify_injectivity`), adding
``"injectivity"`` to the metrics and ``injectivity.png``.

PyVista and the VTK filters are imported when the command runs, so that ``vhm-viz --help``
stays quick.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vhm_viz import plotting
from vhm_viz.cli._util import (
    CLIError,
    Progress,
    add_convergence_argument,
    add_quiet_argument,
    add_scene_arguments,
    build_and_solve,
    check_input,
    check_output_directory,
    convergence_warning,
    load_scene,
    print_warning,
    quiet_vtk,
    run_filter,
    solve_summary,
    surface_metrics,
)
from vhm_viz.core.certify import certify_injectivity
from vhm_viz.core.metrics import finite_or_none
from vhm_viz.core.threads import load_compiled_runtime
from vhm_viz.io import atomic_outputs, json_text, read_dataset, write_dataset, write_text

#: Files written by ``analyze`` into the output directory.
FILES = {
    "figure4": "figure4_slices.png",
    "figure12": "figure12_condition_histogram.png",
    "energy": "energy.png",
    "metrics": "metrics.json",
    "injectivity": "injectivity.png",
}
#: Name of the analysed dataset per dataset type (VTK's XML format of that type).
ANALYSIS_FILES = {
    "PolyData": "analysis.vtp",
    "UnstructuredGrid": "analysis.vtu",
    "ImageData": "analysis.vti",
    "StructuredGrid": "analysis.vts",
    "RectilinearGrid": "analysis.vtr",
}


#: The libraries ``analyze`` imports when it runs (not for its help).
RUN_IMPORTS = ("pyvista", "vhm_viz.filters")

HELP = "figures and metrics of a deformation (Figure 4 slices, Figure 12 histogram)"

DESCRIPTION = (
    "Solve SCENE for INPUT and write into DIR: the paper's Figure 4 (a slice "
    "coloured by det J and by cond J), Figure 12 (condition-number histogram), the "
    "energy-vs-iteration plot, metrics.json (E_rigid and E_volume where the data "
    "has a surface, det/cond statistics, foldovers, and for meshes with 3D cells the "
    "inverted cells) and the analysed dataset (analysis.vtu/.vtp/.vti) with its point "
    "and cell arrays. --certify proves that the map folds nowhere in the shape, or "
    "finds where it does."
)


def add_arguments(p) -> None:
    """The ``analyze`` subcommand's arguments."""
    add_scene_arguments(p, "rest-pose dataset")
    p.add_argument(
        "-o", "--output", required=True, metavar="DIR", help="output directory (created if missing)"
    )
    p.add_argument(
        "--outside",
        choices=("error", "passthrough"),
        default="error",
        help="points outside the cage: fail or ignore them (default: error)",
    )
    p.add_argument(
        "--normal",
        default=None,
        metavar="X,Y,Z",
        help="normal of the Figure 4 slice through the data's centre, a direction (any "
        "length) (default: the coordinate axis along which the data moves least)",
    )
    add_convergence_argument(p)
    p.add_argument(
        "--certify",
        action="store_true",
        help="certify local injectivity over the shape (det J > 0 everywhere, not only at "
        "samples): adds 'injectivity' to metrics.json and injectivity.png",
    )
    p.add_argument(
        "--max-cubes",
        type=int,
        default=200_000,
        metavar="N",
        help="--certify: cubes examined at most before answering 'undecided' (default: 200000)",
    )
    add_quiet_argument(p)


def run(args: argparse.Namespace) -> int:
    """Run ``analyze``; returns the exit status."""
    quiet_vtk()
    print(analyze(args))
    return 0


def _stats(values: np.ndarray) -> dict:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {}
    return {
        "min": float(v.min()),
        "max": float(v.max()),
        "mean": float(v.mean()),
        "median": float(np.median(v)),
        "p01": float(np.percentile(v, 1)),
        "p99": float(np.percentile(v, 99)),
    }


def _parse_normal(text):
    if text is None:
        return None
    try:
        n = np.array([float(t) for t in text.split(",")])
    except ValueError:
        n = np.zeros(0)
    if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) == 0:
        raise CLIError(f"--normal must be three numbers x,y,z (not all zero); got {text!r}")
    return n


def analyze(args: argparse.Namespace) -> str:
    """Do the work; returns the summary line."""
    import pyvista as pv

    from vhm_viz.filters import HarmonicDeformationFilter, JacobianAnalysisFilter, update
    from vhm_viz.filters._vtk import displacement

    src = check_input(args.input)
    normal = _parse_normal(args.normal)
    if args.max_cubes < 1:
        raise CLIError(f"--max-cubes must be at least 1; got {args.max_cubes}")
    scene = load_scene(args.scene)
    # never write onto the data, the scene or any file the scene names
    out_dir = check_output_directory(
        args.output,
        [*FILES.values(), *ANALYSIS_FILES.values()],
        [src, args.scene, *scene.referenced_files()],
    )
    timer = args.timer
    with timer.stage("read"):
        # numba's runtime loads while a child reads the input (start-up: counted as other)
        mesh = read_dataset(src, meanwhile=timer.aside(load_compiled_runtime))

    t0 = time.perf_counter()
    with timer.stage("solve"):
        solved = build_and_solve(
            scene, mesh, quiet=args.quiet, allow_unconverged=args.allow_unconverged
        )
    dfm, reports = solved.deformer, solved.reports
    hm = dfm.harmonic_map
    ana = JacobianAnalysisFilter()
    ana.SetOutsidePolicy(args.outside)
    with timer.stage("map"):
        analysed = run_filter(
            ana,
            mesh,
            dfm,
            "analyzing",
            quiet=args.quiet,
            source=src,
            cage=scene.cage_file,
            drops=False,
        )
    # the measures of the points the map moved: the arrays themselves where it moved all
    inside = None
    if "vhm_outside" in analysed.point_data:
        moved = np.asarray(analysed.point_data["vhm_outside"]) == 0
        inside = None if moved.all() else moved
    det, cond, rot = (
        np.asarray(analysed.point_data[name]) if inside is None
        else np.asarray(analysed.point_data[name])[inside]
        for name in ("jacobian_determinant", "condition_number", "rotation_angle")
    )  # fmt: skip

    deformer_filter = HarmonicDeformationFilter()
    deformer_filter.SetInputData(mesh)
    deformer_filter.SetDeformer(dfm)
    deformer_filter.SetOutsidePolicy(args.outside)
    with timer.stage("map"):
        deformed = pv.wrap(update(deformer_filter))
    analysed.point_data["displacement"] = displacement(mesh, deformed.points)
    analysis_name = ANALYSIS_FILES.get(type(analysed).__name__, "analysis.vtk")
    surface = surface_metrics(mesh, deformed)
    if not (args.certify or isinstance(deformed, pv.PolyData)):
        # no figure draws it: a volume's moved points (three times its input) go, with the
        # filter that holds them as its output
        deformed = deformer_filter = None
    surf = deformed if isinstance(deformed, pv.PolyData) else None
    with timer.stage("checks"):
        slice_ = plotting.jacobian_slice(mesh, hm, normal=normal)
        certificate, cage_region = _certify(dfm, mesh, args) if args.certify else (None, None)

    metrics = {
        "input": str(src),
        "points": int(mesh.n_points),
        "points_outside_cage": int(ana.outside_count),
        "mode": scene.mode,
        "alpha": scene.alpha,
        "iterations": int(sum(r.iterations for r in reports)),
        "converged": bool(reports[-1].converged),
        "energy": float(reports[-1].final_energy),
        **surface,
        "jacobian_determinant": _stats(det),
        "condition_number": _stats(cond),
        "rotation_angle_degrees": _stats(rot),
        "foldovers": int(np.count_nonzero(det <= 0)),
        "analysis": analysis_name,
        "slice": {
            "normal": np.asarray(slice_.field_data["slice_normal"]).ravel().tolist(),
            "jacobian_determinant": _stats(slice_.point_data["jacobian_determinant"]),
            "condition_number": _stats(slice_.point_data["condition_number"]),
        },
    }
    if ana.cell_summary is not None:
        metrics["cells"] = {
            k: finite_or_none(v) if isinstance(v, float) else v for k, v in ana.cell_summary.items()
        }
    if certificate is not None:
        metrics["injectivity"] = certificate.to_json()
        if cage_region is not None:
            metrics["injectivity"]["points_not_covered"] = cage_region[1]
    # the report is one unit: its files appear together, or the old ones stay untouched
    with timer.stage("write"), atomic_outputs(out_dir, last=FILES["metrics"]) as stage:
        write_dataset(stage / analysis_name, analysed)
        pl = plotting.figure4(slice_, deformed_surface=surf, filename=stage / FILES["figure4"])
        pl.close()
        plotting.figure12({scene.mode: cond}, filename=stage / FILES["figure12"])
        plotting.energy_plot(reports, filename=stage / FILES["energy"])
        if certificate is not None:
            pl = plotting.injectivity_figure(
                slice_,
                certificate,
                hm,
                deformed_surface=deformed,
                filename=stage / FILES["injectivity"],
            )
            pl.close()
        write_text(stage / FILES["metrics"], json_text(metrics))
    seconds = time.perf_counter() - t0
    summary = [f"analyzed {mesh.n_points} points", solve_summary(reports)]
    if "E_rigid" in metrics:
        summary.append(f"E_rigid {metrics['E_rigid']:.4f}")
    if "E_volume" in metrics:
        summary.append(f"E_volume {metrics['E_volume']:.4f}")
    for cells in ("triangles", "tetrahedra"):
        if metrics.get(f"{cells}_left_out"):
            summary.append(
                f"{metrics[f'{cells}_left_out']} {cells} touching points outside the cage "
                "left out of E_rigid/E_volume"
            )
    summary.append(
        f"det J [{metrics['jacobian_determinant'].get('min', float('nan')):.3f}, "
        f"{metrics['jacobian_determinant'].get('max', float('nan')):.3f}]"
    )
    summary.append(f"{metrics['foldovers']} foldovers")
    if "cells" in metrics:
        c = metrics["cells"]
        summary.append(f"{c['inverted']} of {c['cells']} cells inverted")
        if c["rest_inverted"]:
            summary.append(f"{c['rest_inverted']} cells inverted at rest (not counted)")
    if certificate is not None:
        summary.append(certificate.summary())
        if cage_region is not None:
            summary[-1] += " " + cage_region[0]
    summary.append(f"{seconds:.1f} s")
    warning = convergence_warning(solved)
    if warning:
        print_warning("analyze", warning)
    return ", ".join(summary) + f" -> {out_dir}/"


def _certify(dfm, mesh, args):
    """Certify the map over the shape's region, with a progress bar.

    Returns the certificate, and where the region is the cage's interior less a margin (a
    point cloud or an open surface bounds no solid) the words saying so and how many of
    the input's points it leaves out; else None.
    """
    from vhm_viz.filters import region_of
    from vhm_viz.filters._vtk import numpy_points

    region = region_of(mesh, dfm.cage)
    bar = Progress("certify", enabled=not args.quiet)
    cert = certify_injectivity(dfm, region, max_cubes=args.max_cubes, progress=bar)
    bar.finish()
    if region.kind != "cage":
        return cert, None
    left_out = int(np.count_nonzero(~region.contains(numpy_points(mesh))))
    cert_region = (
        f"over the cage's interior at least {region.description['margin']:.4g} from the cage "
        f"({left_out} of {mesh.n_points} points nearer the cage, not covered)"
    )
    return cert, (cert_region, left_out)
