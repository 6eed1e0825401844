"""SimpleITK's readers and writers, for the formats VTK reads without their frame.

VTK's NRRD reader keeps the spacing only (no ``space directions``, no ``space origin``,
no RAS-to-LPS conversion), its DICOM reader ignores ``ImageOrientationPatient`` and turns
rows and slices over, and VTK writes no NRRD. SimpleITK reads and writes all of them in
ITK's physical (LPS) frame -- the frame of vhm_viz's world and of the users' other tools
(ITK, ANTs, 3D Slicer) -- so these formats go through it. This module converts between
SimpleITK images and PyVista images (origin, spacing, direction and voxels, exactly),
runs SimpleITK's readers in a forked child (:func:`~vhm_viz.io.isolated.read_isolated`)
and writes atomically.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from vhm_viz.atomic import atomic_path
from vhm_viz.core.image import ImageGeometry
from vhm_viz.io.errors import ReadError, complex_voxels
from vhm_viz.io.isolated import native_stderr_silenced, read_isolated
from vhm_viz.io.registry import suffix_of

__all__ = [
    "grid_origin",
    "image_from_sitk",
    "sitk_from_image",
    "read_with_sitk",
    "write_with_sitk",
    "write_sitk_image",
    "sitk_message",
]


def image_from_sitk(image, name: str = "ImageFile"):
    """A PyVista image with a SimpleITK image's geometry and voxels.

    Parameters
    ----------
    image : SimpleITK.Image
        2-D or 3-D, scalar or vector pixels. A 2-D image becomes one slice (``nz = 1``),
        its third axis the normal of its plane.
    name : str
        The point array's name.

    Returns
    -------
    pyvista.ImageData
        ``origin`` and ``spacing`` in mm, ``direction_matrix`` (3, 3) whose columns are the
        image axes in the (LPS) world, the voxels as one point array of shape
        ``(nx * ny * nz,)`` or ``(nx * ny * nz, components)``, x fastest.

    Raises
    ------
    ValueError
        A 4-D (or higher) image, or one of complex voxels
        (:func:`~vhm_viz.io.errors.complex_voxels`).
    """
    import pyvista as pv
    import SimpleITK as sitk

    dim = image.GetDimension()
    if dim not in (2, 3):
        raise ValueError(f"a {dim}-D image; give a 2-D or 3-D one")
    if image.GetPixelID() in (sitk.sitkComplexFloat32, sitk.sitkComplexFloat64):
        raise ValueError(complex_voxels(image.GetPixelIDTypeAsString()))
    size = [*image.GetSize(), 1][:3]
    spacing = [*image.GetSpacing(), 1.0][:3]
    origin = [*image.GetOrigin(), 0.0][:3]
    direction = np.eye(3)
    direction[:dim, :dim] = np.reshape(image.GetDirection(), (dim, dim))
    if dim == 2:
        direction[:, 2] = np.cross(direction[:, 0], direction[:, 1])
    comps = image.GetNumberOfComponentsPerPixel()
    values = sitk.GetArrayViewFromImage(image).reshape((-1, comps) if comps > 1 else -1)
    out = pv.ImageData(dimensions=size, spacing=spacing, origin=origin)
    out.direction_matrix = direction
    out.point_data[name] = np.array(values)  # a copy: the view dies with the image
    return out


def grid_origin(image) -> np.ndarray:
    """Where an image's first voxel lies: the origin a file holding its voxels is given.

    A ``vtkImageData``'s origin is the point of index (0, 0, 0), which lies outside a grid
    whose extent does not start at 0 (a piece, ``extract_subset``); a file's origin is
    its first voxel's point, ``origin + direction @ (extent start * spacing)``.

    Parameters
    ----------
    image : pyvista.ImageData

    Returns
    -------
    numpy.ndarray
        (3,) in the image's world.
    """
    grid = ImageGeometry(image.origin, image.spacing, image.dimensions, image.direction_matrix)
    return grid.points(np.asarray(image.extent, dtype=np.float64)[None, ::2])[0]


def sitk_from_image(image, values: np.ndarray):
    """A 3-D SimpleITK image on a PyVista image's grid, holding ``values``.

    Parameters
    ----------
    image : pyvista.ImageData
        Its dimensions, origin, spacing, direction and extent place the voxels.
    values : numpy.ndarray
        ``(n_points,)`` or ``(n_points, components)``, x fastest.

    Returns
    -------
    SimpleITK.Image
    """
    import SimpleITK as sitk

    nx, ny, nz = (int(d) for d in image.dimensions)
    comps = 1 if values.ndim == 1 else values.shape[1]
    shape = (nz, ny, nx, comps) if comps > 1 else (nz, ny, nx)
    out = sitk.GetImageFromArray(np.ascontiguousarray(values).reshape(shape), isVector=comps > 1)
    out.SetOrigin([float(v) for v in grid_origin(image)])
    out.SetSpacing([float(v) for v in image.spacing])
    direction = np.asarray(image.direction_matrix, dtype=np.float64)
    out.SetDirection([float(v) for v in direction.ravel()])
    return out


def read_with_sitk(path, read, what: str):
    """``read(path)`` -> SimpleITK image, in a forked child, returned as a PyVista image.

    Parameters
    ----------
    path : path-like
        The file or folder; named in messages.
    read : callable
        ``read(path) -> (SimpleITK.Image, name)``, run in the child with one thread.
    what : str
        The reader, as messages name it (``"SimpleITK's NRRD reader"``).

    Returns
    -------
    pyvista.ImageData
        :func:`image_from_sitk` of what ``read`` returned.

    Raises
    ------
    ReadError
        ``read`` raised (its first line) or the child crashed.
    """

    def child(p):
        import SimpleITK as sitk

        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
        sitk.ProcessObject.GlobalWarningDisplayOff()
        try:
            image, name = read(p)
        except RuntimeError as exc:
            raise ValueError(sitk_message(exc)) from None
        return image_from_sitk(image, name)

    return read_isolated(path, child, what)


_ITK_PREFIX = re.compile(
    r"^(\[\w+\]\s*|(sitk|itk)::ERROR:\s*|\w+\(0x[0-9a-fA-F]+\):\s*|Reason:\s*)+"
)


def sitk_message(exc) -> str:
    """The line of a SimpleITK exception that says what is wrong, without ITK's prefixes.

    SimpleITK's first line names its own source file; the last non-empty line is the
    innermost cause (``Unable to determine ImageIO reader for "x"``, teem's
    ``_nrrdReadNrrdParse_sizes: ...``, MetaIO's ``Reason: File too large``).
    """
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    if len(lines) > 1:
        lines = lines[1:]
    return _ITK_PREFIX.sub("", lines[-1]) if lines else type(exc).__name__


def write_with_sitk(path, image, values: np.ndarray, compress: bool = True) -> None:
    """Write ``values`` on ``image``'s grid with SimpleITK, atomically.

    Parameters
    ----------
    path : path-like
        SimpleITK picks the format from the suffix (the temporary keeps it).
    image : pyvista.ImageData
    values : numpy.ndarray
        ``(n_points,)`` or ``(n_points, components)``.
    compress : bool
        Compress the voxels where the format allows (gzip for NRRD).
    """
    out = sitk_from_image(image, values)
    with atomic_path(Path(path)) as tmp:
        write_sitk_image(out, tmp, path, compress)


def write_sitk_image(image, written, final, compress: bool = True) -> None:
    """Write a SimpleITK image to ``written``, a temporary renamed to ``final`` after.

    Every write through SimpleITK goes here. ITK's writers print their own complaints on
    stderr (NIfTI's ``** ERROR: NWAD: ...``, MetaIO's ``file stream is fail after
    write``), which are kept from the user: a failure is one OSError naming ``final``.
    ITK's NIfTI writer reports a short write (a full disk or quota, a file-size limit)
    only there, so a NIfTI file's voxels are counted before it is renamed into place.

    Parameters
    ----------
    image : SimpleITK.Image
    written : path-like
        The file written; SimpleITK picks the format from its suffix.
    final : path-like
        Where it goes: named in messages.
    compress : bool
        Compress the voxels where the format allows (gzip for NRRD, MetaImage).

    Raises
    ------
    OSError
        ``could not write FINAL: REASON``.
    """
    import SimpleITK as sitk

    from vhm_viz.io.medical import check_nifti  # here: medical imports this module

    with native_stderr_silenced():
        try:
            sitk.WriteImage(image, os.fspath(written), useCompression=compress)
        except RuntimeError as exc:  # a full disk, a file-size limit
            raise OSError(f"could not write {final}: {sitk_message(exc)}") from None
    if suffix_of(written) in (".nii", ".nii.gz"):
        try:
            check_nifti(Path(written))
        except ReadError as exc:
            reason = str(exc).removeprefix(f"{written}: ")
            raise OSError(
                f"could not write {final}: the file ends early ({reason}); the disk is full "
                "or a file-size limit was reached"
            ) from None
