"""``vhm-viz deform --write-field``: the deformation as a displacement field for ITK tools.

The pull-back field comes from the resampling itself (the same pre-images, one pass:
:meth:`HarmonicResampleFilter.SetComputeDisplacementField
<vhm_viz.filters.HarmonicResampleFilter.SetComputeDisplacementField>`); a forward field,
or a pull-back field beside a warped grid, from ``mesh.vhm.displacement_field``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vhm_viz.core.displacement import FIELD_KINDS

__all__ = [
    "add_field_arguments",
    "check_field_output",
    "check_field_apart",
    "field_of",
    "write_field",
]


def add_field_arguments(p: argparse.ArgumentParser) -> None:
    """``--write-field`` and ``--field-kind``."""
    p.add_argument(
        "--write-field",
        metavar="FIELD",
        default=None,
        help="volumes: also write the deformation as an ITK displacement field "
        "(.nii, .nii.gz, .mha, .nrrd: 3 float64 components, vectors in LPS world units, "
        "NIfTI intent 1007 as ITK writes it), which SimpleITK's "
        "DisplacementFieldTransform, antsApplyTransforms (-t FIELD) and 3D Slicer (as a "
        "grid transform) apply; and its mask beside it, FIELD_mask with the same suffix "
        "(uint8: 0 no pre-image, 1 the map's, 2 in a fold) (default: none)",
    )
    p.add_argument(
        "--field-kind",
        choices=FIELD_KINDS,
        default="pullback",
        help="--write-field: pullback, f^-1(y) - y on the output grid (resamples the input "
        "as vhm-viz does: what ITK and ANTs apply to images); forward, f(x) - x on the "
        "input grid (moves points and meshes: x -> x + u(x)) (default: pullback)",
    )


def check_field_output(args: argparse.Namespace, volume: bool, inputs) -> tuple | None:
    """The field and mask paths, checked as outputs before any work; None without one.

    Raises :class:`~vhm_viz.cli._util.CLIError` for another suffix, an input that is not
    a volume, or a path that is an input or the output.
    """
    if args.write_field is None:
        return None
    from vhm_viz.cli._util import CLIError, check_output
    from vhm_viz.io import suffix_of
    from vhm_viz.io.fields import FIELD_SUFFIXES, mask_path_of

    field = Path(args.write_field)
    if suffix_of(field) not in FIELD_SUFFIXES:
        raise CLIError(
            f"--write-field {field} must end with one of {', '.join(FIELD_SUFFIXES)} "
            "(an ITK displacement field)"
        )
    if not volume:
        raise CLIError("--write-field needs a volume INPUT (an image): a field lives on a grid")
    check_output(field, FIELD_SUFFIXES, inputs, "--write-field")
    mask = mask_path_of(field)
    check_output(mask, FIELD_SUFFIXES, inputs, "--write-field")
    outputs = [Path(args.output), field, mask]
    if len({p.resolve() for p in outputs}) < 3:
        raise CLIError(
            f"--write-field {field} (or its mask {mask.name}) is the output {args.output}; "
            "give another name"
        )
    return field, mask


def check_field_apart(paths, written) -> None:
    """Refuse a field (or its mask) named as a file the output puts beside itself.

    ``paths``: the field and mask (:func:`check_field_output`), or None; ``written``: the
    output's files (:func:`vhm_viz.io.dataset_files`: ``out_vtkValidPointMask.nii`` ...),
    known once the result's arrays are.
    """
    if paths is None:
        return
    from vhm_viz.cli._util import CLIError

    taken = {p.resolve() for p in written}
    for path in paths:
        if path.resolve() in taken:
            raise CLIError(
                f"--write-field {paths[0]} (or its mask {paths[1].name}): {path.name} is "
                f"also a file of the output {written[0]}, which writes "
                f"{', '.join(p.name for p in written)}; give another name"
            )


def field_of(args: argparse.Namespace, mesh, result, deformer, tolerance: float):
    """The field to write: from the resampled ``result`` when it holds it, else computed.

    Removes the field's array from ``result`` (it is written apart, not into the output).
    """
    from vhm_viz.accessor import VHMAccessor
    from vhm_viz.filters.resample import FIELD_ARRAY, displacement_field_of

    if FIELD_ARRAY in result.point_data:
        field = displacement_field_of(result)
        result.point_data.remove(FIELD_ARRAY)
        return field
    image = VHMAccessor(mesh).displacement_field(
        deformer, kind=args.field_kind, outside=args.outside, tolerance=tolerance
    )
    return displacement_field_of(image, args.field_kind)


def write_field(field, paths) -> str:
    """Write the field and its mask; the summary's words for them."""
    from vhm_viz.io.fields import write_displacement_field

    path, mask = write_displacement_field(paths[0], field)
    kind = "pull-back" if field.kind == "pullback" else "forward"
    return f"{kind} field -> {path} (mask {mask})"
