"""``vhm-viz deform``: deform a mesh, tet mesh, point cloud or volume with a scene.

PyVista and the VTK filters are imported when the command runs, so that ``vhm-viz --help``
stays quick.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from vhm_viz.cli._field_output import (
    add_field_arguments,
    check_field_apart,
    check_field_output,
    field_of,
    write_field,
)
from vhm_viz.cli._util import (
    CLIError,
    FoldedOutput,
    Progress,
    add_convergence_argument,
    add_fold_argument,
    add_memory_argument,
    add_quiet_argument,
    add_scene_arguments,
    build_and_solve,
    check_input,
    check_output,
    check_volume_memory,
    convergence_warning,
    load_scene,
    print_warning,
    quiet_vtk,
    run_filter,
    solve_summary,
    surface_metrics,
)
from vhm_viz.core.devices import DEVICES, require_device
from vhm_viz.core.image import INTERPOLATIONS
from vhm_viz.core.threads import load_compiled_runtime
from vhm_viz.core.volume import DEFAULT_TOLERANCE, MAX_TOLERANCE
from vhm_viz.folds import load_check_kernels, output_folds, proof_sized
from vhm_viz.io import (
    DATASET_SUFFIXES,
    atomic_outputs,
    dataset_files,
    format_of,
    image_suffixes,
    is_image_format,
    keeps_arrays,
    output_suffixes,
    read_dataset,
    suffix_of,
    write_dataset,
)

#: The libraries ``deform`` imports when it runs (not for its help).
RUN_IMPORTS = ("pyvista", "vhm_viz.filters")
#: What ``deform`` writes: the input's type, or an image a volume is resampled onto.
OUTPUT_TYPES = ("PolyData", "UnstructuredGrid", "StructuredGrid", "ImageData")
ALL_OUTPUT_SUFFIXES = tuple(sorted({s for t in OUTPUT_TYPES for s in output_suffixes(t)}))
#: Output suffixes that keep no named arrays (``--arrays`` is refused there).
GEOMETRY_ONLY_SUFFIXES = tuple(s for s in output_suffixes() if not keeps_arrays(f"x{s}"))


HELP = "deform a dataset with a scene (cage, anchors, constraints)"

DESCRIPTION = (
    "Deform INPUT with the variational harmonic map described by SCENE and "
    "write OUTPUT. Surfaces stay surfaces, tet meshes stay tet meshes. A volume (any "
    "image format read) written to .vts or .vtk becomes a warped structured grid "
    f"(every voxel moved); written to {', '.join(image_suffixes())} it is resampled "
    "onto a regular grid that holds the whole deformed volume (each output voxel pulled "
    "back through the inverse map), keeping origin, spacing and direction. Volumes go "
    "through an adaptive lattice of exact map values (--tolerance). Prints one summary "
    "line. A result that folds the data (inverted cells, resampled voxels in folds, or "
    "det J <= 0 at sampled points) is one line on stderr and exit status 4, nothing "
    "written (--allow-folds). Options for volumes, or for resampling, given for other "
    "data are refused."
)

EPILOG = (
    f"input types: {' '.join(DATASET_SUFFIXES)}, or a DICOM folder. Example: "
    "vhm-viz deform vhm_viz_demo/bar_rest.vtp "
    "--scene vhm_viz_demo/scene.json -o bent.vtp (after vhm-viz demo)"
)


def add_arguments(p) -> None:
    """The ``deform`` subcommand's arguments."""
    add_scene_arguments(p, "dataset to deform")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUTPUT",
        help="output file (never the input; written atomically)",
    )
    p.add_argument(
        "--outside",
        choices=("error", "passthrough", "nan"),
        default="error",
        help="points (voxels) outside the cage: fail, leave them in place (flagged by the "
        "point array vhm_outside), or drop them (NaN positions; no data in a resampled "
        "volume) (default: error)",
    )
    p.add_argument(
        "--arrays",
        default="",
        metavar="LIST",
        help="comma-separated extra arrays: displacement, det, cond (point arrays), cells "
        "(cell_jacobian_determinant, cell_condition_number, cell_inverted of 3D cells; "
        "refused for data without them); "
        f"refused for {', '.join(GEOMETRY_ONLY_SUFFIXES)}, which keep only the geometry, "
        "and for a resampled volume (default: none)",
    )
    p.add_argument(
        "--fill-value",
        type=float,
        default=None,
        metavar="VALUE",
        help="volume resampling: value of voxels without a pre-image, in the units of the "
        "data and held exactly by its type: an integer in the type's range for integer "
        "data, any number (nan, inf) for floating-point data (default: 0; they also get 0 "
        "in the array vtkValidPointMask)",
    )
    p.add_argument(
        "--tolerance",
        type=float,
        default=None,
        metavar="VOXELS",
        help="volumes: largest position error of a mapped voxel, in voxels of the input "
        f"spacing, at most {MAX_TOLERANCE:g} (default: {DEFAULT_TOLERANCE} voxels)",
    )
    p.add_argument(
        "--interpolation",
        choices=INTERPOLATIONS,
        default=None,
        help="volume resampling: sampling of the input at the pre-images: linear "
        "(trilinear), nearest (label maps: values copied, integer type kept) or cubic "
        "(Catmull-Rom) (default: linear)",
    )
    p.add_argument(
        "--spacing",
        type=_spacing,
        default=None,
        metavar="SX,SY,SZ",
        help="volume resampling: output voxel size in world units (the data's units); one "
        "number for cubic voxels (default: the input spacing)",
    )
    p.add_argument(
        "--reference",
        metavar="IMAGE",
        default=None,
        help="volume resampling: resample onto this image's grid (origin, spacing, "
        "dimensions, direction) instead (default: a grid holding the whole deformed volume)",
    )
    p.add_argument(
        "--device",
        choices=DEVICES,
        default=None,
        help="volumes: where the lattice's exact map evaluations run: cpu, or cuda (an "
        "NVIDIA GPU, with numba-cuda; the same result to rounding) (default: cpu)",
    )
    add_field_arguments(p)
    add_convergence_argument(p)
    add_fold_argument(p)
    add_memory_argument(p)
    add_quiet_argument(p)


#: The options of volumes (``VOLUME_OPTIONS``) and of a volume resampled to an image
#: (``RESAMPLE_OPTIONS``), with the values they take when left out: their argparse default
#: is None, so that an option given, which another input leaves without effect, is refused.
VOLUME_OPTIONS = {"--tolerance": DEFAULT_TOLERANCE, "--device": "cpu"}
RESAMPLE_OPTIONS = {"--fill-value": 0.0, "--interpolation": "linear", "--spacing": None,
                    "--reference": None}  # fmt: skip


def _given_options(args: argparse.Namespace) -> list[str]:
    """The volume options given on the command line; the others get their values."""
    given = []
    for option, default in {**VOLUME_OPTIONS, **RESAMPLE_OPTIONS}.items():
        name = option[2:].replace("-", "_")
        if getattr(args, name) is None:
            setattr(args, name, default)
        else:
            given.append(option)
    return given


def _check_options_apply(given, arrays, mesh, src, out, volume: bool, resample: bool) -> None:
    """Refuse, before the solve, options this input (or output) would leave without effect.

    Volume options for other data, resampling options for a volume written as a warped
    grid, and ``--arrays cells`` for data without 3D cells: one line, the option and why.
    """
    from vhm_viz.filters.cells import has_3d_cells

    resampled = f"a volume resampled to an image ({', '.join(image_suffixes())})"
    for option in given:
        if not volume:
            scope = "volumes" if option in VOLUME_OPTIONS else resampled
            raise CLIError(f"{option}: applies to {scope}; {src.name} is {_kind(mesh)}")
        if option in RESAMPLE_OPTIONS and not resample:
            raise CLIError(
                f"{option}: applies to {resampled}; written to {suffix_of(out)}, the volume "
                "is warped (every voxel moved)"
            )
    if "--spacing" in given and "--reference" in given:
        raise CLIError(
            "--spacing: applies to the grid that holds the deformed volume; --reference gives "
            "the grid, its spacing included"
        )
    if "cells" in arrays and not has_3d_cells(mesh):
        raise CLIError(f"--arrays cells: {src.name} has no 3D cells ({_kind(mesh)})")


def _kind(mesh) -> str:
    """What ``mesh`` is, in words, for the messages of options that do not apply to it."""
    import pyvista as pv

    if isinstance(mesh, pv.PolyData):
        if mesh.GetNumberOfPolys() or mesh.GetNumberOfStrips():
            return "a surface"
        return "lines" if mesh.GetNumberOfLines() else "a point cloud"
    if isinstance(mesh, pv.ImageData):
        return "a volume" if min(mesh.dimensions) > 1 else "a flat image"
    name = type(mesh).__name__
    return f"{'an' if name[0] in 'AEIOU' else 'a'} {name}"


def run(args: argparse.Namespace) -> int:
    """Run ``deform``; returns the exit status."""
    quiet_vtk()
    print(deform(args))
    return 0


def _spacing(text: str) -> tuple[float, float, float]:
    """``--spacing``: one number or three, comma- or space-separated, all positive."""
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not numbers: {text!r}") from None
    if len(values) == 1:
        values *= 3
    if len(values) != 3 or not all(v > 0 and v < float("inf") for v in values):
        raise argparse.ArgumentTypeError(f"expected 1 or 3 positive numbers; got {text!r}")
    return tuple(values)


def _parse_arrays(text: str) -> tuple[str, ...]:
    """``--arrays``: its entries, each once, in the order given."""
    names = tuple(dict.fromkeys(t.strip() for t in text.split(",") if t.strip()))
    known = ("displacement", "det", "cond", "cells")
    bad = [n for n in names if n not in known]
    if bad:
        raise CLIError(f"unknown --arrays entry {bad[0]!r}; use displacement, det, cond, cells")
    return names


def _check_arrays_kept(arrays: tuple[str, ...], output) -> None:
    """Refuse ``--arrays`` for an output format that would drop them, before any work."""
    if not arrays or keeps_arrays(output):
        return
    fmt = format_of(output)
    keep = dict.fromkeys(s for t in fmt.writes for s in output_suffixes(t, arrays=True))
    raise CLIError(
        f"--arrays {','.join(arrays)}: {fmt.name} ({suffix_of(output)}) keeps no point or "
        f"cell arrays, only the geometry; write to {' or '.join(keep)} to keep them"
    )


def deform(args: argparse.Namespace) -> str:
    """Do the work; returns the summary line."""
    import pyvista as pv

    from vhm_viz.core.image import check_fill_value
    from vhm_viz.core.volume import check_tolerance
    from vhm_viz.filters import HarmonicDeformationFilter, HarmonicResampleFilter
    from vhm_viz.filters.resample import resampled_arrays

    given = _given_options(args)
    require_device(args.device)  # no GPU: one line, before any work
    src = check_input(args.input)
    arrays = _parse_arrays(args.arrays)
    _check_arrays_kept(arrays, args.output)
    try:
        tolerance = check_tolerance(args.tolerance)
    except ValueError as exc:
        raise CLIError(f"--{exc}") from None
    scene = load_scene(args.scene)
    reference = check_input(args.reference) if args.reference else None
    # never write onto the data, the scene or any file the scene names
    inputs = [src, args.scene, *scene.referenced_files(), *([reference] if reference else [])]
    check_output(args.output, ALL_OUTPUT_SUFFIXES, inputs)
    out = Path(args.output)
    timer = args.timer
    with timer.stage("read"):
        # numba's runtime loads while a child reads the input (start-up: counted as other)
        mesh = read_dataset(src, meanwhile=timer.aside(load_compiled_runtime))
    volume = isinstance(mesh, pv.ImageData)
    resample = volume and is_image_format(out)
    out_type = "ImageData" if resample else _output_type(mesh)
    if suffix_of(out) not in output_suffixes(out_type):
        raise CLIError(
            f"cannot write a {out_type} to {suffix_of(out)!r}; use "
            f"{', '.join(output_suffixes(out_type))}"
        )
    ref_image = None
    if reference is not None:
        with timer.stage("read"):
            ref_image = read_dataset(reference)
        if not isinstance(ref_image, pv.ImageData):
            raise CLIError(f"--reference {reference} is not an image")
    _check_options_apply(given, arrays, mesh, src, out, volume, resample)
    if resample and arrays:  # the resample filter computes none of them
        field = ", or --write-field for a displacement field" if "displacement" in arrays else ""
        raise CLIError(
            f"--arrays {','.join(arrays)}: a volume resampled to {suffix_of(out)} gets no "
            "arrays of the map (its voxels are pulled back, not moved); write the warped "
            f"grid to {' or '.join(output_suffixes('StructuredGrid', arrays=True))} to have "
            f"them{field}"
        )
    field_paths = check_field_output(args, volume, inputs)
    if resample:  # a fill value the output's types cannot hold: before the solve
        dtypes = {name: mesh.point_data[name].dtype for name in resampled_arrays(mesh)}
        try:
            check_fill_value(args.fill_value, dtypes, name="--fill-value")
        except ValueError as exc:
            raise CLIError(str(exc)) from None

    t0 = time.perf_counter()
    # the checks' kernels load on a second thread while the solve leaves a core idle (a
    # daemon: should the solve fail, it ends on its own)
    voxels = volume and not resample
    check_kernels = load_check_kernels(
        mesh,
        cells="cells" not in arrays,
        voxels=voxels,
        proof=voxels and proof_sized(mesh.dimensions),
    )
    with timer.stage("solve"):
        solved = build_and_solve(
            scene, mesh, quiet=args.quiet, allow_unconverged=args.allow_unconverged
        )
    dfm, reports = solved.deformer, solved.reports
    if resample:
        flt = HarmonicResampleFilter()
        flt.SetFillValue(args.fill_value)
        flt.SetInterpolation(args.interpolation)
        if args.spacing:
            flt.SetOutputSpacing(args.spacing)
        if ref_image is not None:
            flt.SetReferenceImage(ref_image)
        flt.SetComputeDisplacementField(field_paths is not None and args.field_kind == "pullback")
        label = "resampling"
    else:
        flt = HarmonicDeformationFilter()
        flt.SetComputeDisplacement("displacement" in arrays)
        flt.SetComputeJacobianDeterminant("det" in arrays)
        flt.SetComputeConditionNumber("cond" in arrays)
        flt.SetComputeCellQuality("cells" in arrays)
        label = "warping" if volume else "binding"
    flt.SetOutsidePolicy(args.outside)
    flt.SetTolerance(tolerance)
    flt.SetMemoryBudget(args.memory_budget)
    flt.SetDevice(args.device)
    if volume:  # a job that cannot fit is refused before it allocates
        check_volume_memory(mesh, dfm.harmonic_map, resample=resample, output=out,
                            memory_budget=args.memory_budget, spacing=args.spacing,
                            reference=ref_image, outside=args.outside,
                            field=None if field_paths is None else args.field_kind)  # fmt: skip
    with timer.stage("map"):
        result = run_filter(
            flt, mesh, dfm, label, quiet=args.quiet, source=src, cage=scene.cage_file
        )
        field = None if field_paths is None else field_of(args, mesh, result, dfm, tolerance)
    # everything that can fail happens before the write: an error never follows an output
    with timer.stage("checks"):
        if ref_image is not None:
            _require_overlap(flt.stats, reference)
        check_kernels.join()
        summary = _summary(mesh, result, reports, flt, resample, volume, tolerance)
        bar = Progress("checking", enabled=not (args.quiet or resample))
        bar(0.0)
        warning = output_folds(
            mesh, result, dfm.harmonic_map, resampled=flt.fold_voxels if resample else None,
            engine=flt.volume_engine, progress=bar, memory_budget=args.memory_budget,
        )  # fmt: skip
        bar.finish()
    if warning and not args.allow_folds:
        raise FoldedOutput(
            warning
            + "; nothing written (change the scene, or pass --allow-folds to write it anyway)"
        )
    check_field_apart(field_paths, dataset_files(out, result))
    # the output, the arrays beside it and a field in the same folder appear as one set
    with timer.stage("write"), atomic_outputs(out.parent):
        written = write_dataset(out, result, inputs=inputs)
        field_written = "" if field is None else "; " + write_field(field, field_paths)
    seconds = time.perf_counter() - t0
    for text in (convergence_warning(solved), warning):
        if text:
            print_warning("deform", text)
    outputs = ", ".join(map(str, written))
    return ", ".join([*summary, f"{seconds:.1f} s"]) + f" -> {outputs}" + field_written


def _require_overlap(stats: dict, reference) -> None:
    """Refuse a resample onto a ``--reference`` grid that the deformed volume misses.

    Every voxel of such an output would be the fill value: not what anyone asked for.
    """
    if stats["valid"] == 0 and stats["identity"] == 0:
        raise CLIError(
            f"--reference {reference}: none of its {stats['voxels']} voxels lies in the "
            "deformed volume, so every one would be the fill value; nothing written (give a "
            "reference grid that overlaps the deformed volume, in the same world frame)"
        )


def _summary(mesh, result, reports, flt, resample: bool, volume: bool, tolerance) -> list[str]:
    kind = "voxels" if volume else "points"
    parts = [f"deformed {mesh.n_points} {kind} ({type(mesh).__name__})"]
    parts.append(solve_summary(reports))
    if resample:
        stats = flt.stats
        kept = f" ({stats['identity']} left in place outside the cage)" if stats["identity"] else ""
        parts.append(f"{stats['valid']}/{stats['voxels']} voxels with a pre-image{kept}")
        parts.append(f"{stats['foldover']} in folds")
        parts.append(f"grid {'x'.join(str(d) for d in result.dimensions)}")
    else:
        metrics = surface_metrics(mesh, result, rigid=False)  # the line shows E_volume
        if "E_volume" in metrics:
            parts.append(f"E_volume {metrics['E_volume']:.4f}")
        parts.append(f"{flt.outside_count} {kind} outside the cage")
    if volume:
        parts.append(f"tolerance {tolerance:g} voxel")
    return parts


def _output_type(mesh) -> str:
    import pyvista as pv

    if isinstance(mesh, pv.PolyData):
        return "PolyData"
    if isinstance(mesh, pv.UnstructuredGrid):
        return "UnstructuredGrid"
    return "StructuredGrid"
