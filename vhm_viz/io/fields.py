"""Displacement fields written as ITK reads them, for SimpleITK/ITK, ANTs and 3D Slicer.

A :class:`~vhm_viz.core.displacement.DisplacementField` is written through SimpleITK, the
reference of what these tools read: a 3-component float64 vector image on the field's
grid (origin, spacing, direction in ITK's physical LPS frame), its vectors in that frame
too. NIfTI (``.nii``, ``.nii.gz``) gets ITK's vector intent (``intent_code`` 1007, the
vectors along the fifth dimension: ``dim = (5, nx, ny, nz, 1, 3)``); MetaImage (``.mha``)
and NRRD (``.nrrd``, ``space: left-posterior-superior``, ``kinds: vector domain domain
domain``) hold the same image. As in every ITK and ANTs warp file the vectors are LPS even
in NIfTI, whose own world is RAS: SimpleITK's ``DisplacementFieldTransform`` and
``antsApplyTransforms`` read them unchanged, nibabel users negate x and y for RAS.

The pull-back field is what resamples a moving image onto the field's grid::

    field = sitk.ReadImage("field.nii.gz")             # vector of 64-bit float
    transform = sitk.DisplacementFieldTransform(sitk.Image(field))  # takes a copy's pixels
    moved = sitk.Resample(image, field, transform)     # onto the field's grid
    # antsApplyTransforms -d 3 -i image.nii.gz -r field.nii.gz -t field.nii.gz -o moved.nii.gz

Beside each field goes its mask (:attr:`DisplacementField.mask
<vhm_viz.core.displacement.DisplacementField.mask>`), a ``uint8`` image on the same grid
named ``<field>_mask<suffix>``: 0 where the field is not the map's (no pre-image, no
image), 1 where it is, 2 where it is in a fold. Both files appear together, atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vhm_viz.atomic import atomic_directory
from vhm_viz.core.displacement import DisplacementField
from vhm_viz.core.image import ImageGeometry
from vhm_viz.io.itk_images import write_sitk_image
from vhm_viz.io.registry import suffix_of

__all__ = ["FIELD_SUFFIXES", "check_field_path", "mask_path_of", "write_displacement_field"]

#: Suffixes a displacement field is written to.
FIELD_SUFFIXES = (".nii", ".nii.gz", ".mha", ".nrrd")


def check_field_path(path) -> Path:
    """The path of a field to write, refused (one-line ValueError) for another suffix."""
    path = Path(path)
    if suffix_of(path) not in FIELD_SUFFIXES:
        raise ValueError(
            f"a displacement field is written to {', '.join(FIELD_SUFFIXES)}; got "
            f"{suffix_of(path) or 'no suffix'!r} ({path})"
        )
    return path


def mask_path_of(path) -> Path:
    """The mask written beside the field ``path``: ``field.nii.gz`` -> ``field_mask.nii.gz``."""
    path = check_field_path(path)
    suffix = suffix_of(path)
    stem = path.name[: len(path.name) - len(suffix)]
    return path.with_name(f"{stem}_mask{suffix}")


def _itk_image(values, geometry: ImageGeometry, vector: bool):
    import SimpleITK as sitk

    nx, ny, nz = geometry.dimensions
    shape = (nz, ny, nx, 3) if vector else (nz, ny, nx)
    image = sitk.GetImageFromArray(np.asarray(values).reshape(shape), isVector=vector)
    image.SetOrigin(tuple(float(v) for v in geometry.origin))
    image.SetSpacing(tuple(float(v) for v in geometry.spacing))
    image.SetDirection(tuple(float(v) for v in geometry.direction.ravel()))
    return image


def write_displacement_field(path, field: DisplacementField) -> tuple[Path, Path]:
    """Write a displacement field and its mask beside it (both or neither, atomically).

    Parameters
    ----------
    path : str or os.PathLike
        ``.nii``, ``.nii.gz``, ``.mha`` or ``.nrrd`` (:data:`FIELD_SUFFIXES`).
    field : DisplacementField

    Returns
    -------
    field_path, mask_path : Path
        The mask is :func:`mask_path_of` ``path``.

    Raises
    ------
    ValueError
        Another suffix, or a NIfTI file for a sheared grid.
    OSError
        SimpleITK could not write a file, or a NIfTI file it wrote ends early (a full
        disk, a file-size limit): :func:`~vhm_viz.io.itk_images.write_sitk_image`.
    """
    path = check_field_path(path)
    mask = mask_path_of(path)
    vectors = np.asarray(field.vectors, dtype=np.float64)
    if vectors.shape != (field.geometry.n_points, 3):
        raise ValueError(
            f"the field has {vectors.shape[0]} vectors for {field.geometry.n_points} grid points"
        )
    direction = field.geometry.direction
    if suffix_of(path) in (".nii", ".nii.gz") and not np.allclose(
        direction.T @ direction, np.eye(3), rtol=0, atol=1e-6
    ):  # ITK's NIfTI writer would turn the grid into the nearest rotation of it
        raise ValueError(
            f"{path}: the field's grid is sheared (its direction is no rotation), which a "
            "NIfTI field cannot hold; write it as .mha or .nrrd"
        )
    images = {path.name: _itk_image(vectors, field.geometry, True),
              mask.name: _itk_image(field.mask, field.geometry, False)}  # fmt: skip
    with atomic_directory(path.parent) as stage:
        for name, image in images.items():
            write_sitk_image(image, stage / name, path.parent / name)
    return path, mask
