"""DICOM series: a folder of slices (or one file of it) as an image in LPS millimetres.

Read through SimpleITK's ``ImageSeriesReader`` with GDCM's series index: the slices of
one ``SeriesInstanceUID`` ordered along the normal of ``ImageOrientationPatient`` by
their ``ImagePositionPatient``, the image placed and oriented by them -- an oblique
series lands where ITK, 3D Slicer and ANTs put it. VTK's DICOM reader ignores the
orientation and turns rows and slices over.

Which series: a folder holding several is read as its largest series (most slices); to
read another, give one file of that series instead of the folder (the file's
``SeriesInstanceUID`` chooses). Two largest series of the same size are refused, the
message listing them.

SimpleITK puts the slices on one regular grid whatever their positions say: a missing
slice, uneven steps or a gantry tilt (slices shifted in their plane) would move whole
slices by up to a slice spacing or more, with only a warning. A series whose slices are
not where that grid puts them is refused instead, naming the slice.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vhm_viz.io.errors import ReadError
from vhm_viz.io.itk_images import read_with_sitk

__all__ = ["check_slices_on_grid", "dicom_files", "is_dicom_file", "read_dicom", "read_series"]

_SERIES_UID = "0020|000e"
_DESCRIPTION = "0008|103e"
_POSITION = "0020|0032"
#: How far a slice may lie from its place on the series' grid: 0.01 mm, or 1 % of the
#: slice spacing, whichever is larger (far below a voxel; above the rounding of positions
#: written with a few decimals).
SLICE_TOLERANCE_MM, SLICE_TOLERANCE_SPACING = 1e-2, 1e-2


def is_dicom_file(path) -> bool:
    """Whether ``path`` is a file with DICOM's preamble (``DICM`` at byte 128).

    Parameters
    ----------
    path : path-like
    """
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def dicom_files(path, written: bool = False) -> list[Path]:
    """The files a DICOM series given as ``path`` may read: its folder's (:func:`files_of`).

    Parameters
    ----------
    path : path-like
        A folder, or one file of the series.
    written : bool
        Nothing is written as DICOM: True gives none.

    Returns
    -------
    list of Path
    """
    if written:
        return []
    p = Path(path)
    folder = p if p.is_dir() else p.parent
    try:
        return [f for f in folder.iterdir() if f.is_file()]
    except OSError:
        return []


def read_dicom(path):
    """A DICOM series as an image, with its orientation and slice order.

    Parameters
    ----------
    path : path-like
        A folder of DICOM files (its largest series is read), or one DICOM file (the
        series it belongs to, from the files in its folder, is read).

    Returns
    -------
    pyvista.ImageData
        Origin at the first slice's ``ImagePositionPatient``, direction columns the row
        and column directions of ``ImageOrientationPatient`` and the slice normal, the
        voxels in one point array ``"DICOMImage"`` (RGB as 3 components).

    Raises
    ------
    ReadError
        No series in the folder, two largest series of one size, a slice GDCM cannot
        read, or a crash of the reader (in its child process).
    """
    p = Path(path)
    folder = p if p.is_dir() else p.parent  # sizes the child's memory cap: the series
    try:
        return read_with_sitk(
            folder, lambda _: (read_series(p), "DICOMImage"), "SimpleITK's DICOM series reader"
        )
    except ReadError as exc:
        if p == folder:
            raise
        raise ReadError(f"{p}{str(exc).removeprefix(str(folder))}") from None  # the file given


def read_series(path):
    """The series ``path`` stands for, read by SimpleITK in this process.

    The one choice of series (:func:`read_dicom` runs it in a child process; ParaView's
    reader, which has no PyVista, calls it directly).

    Parameters
    ----------
    path : path-like
        A folder (its largest series) or one DICOM file (its series).

    Returns
    -------
    SimpleITK.Image
        The series, placed and oriented by its slices' headers.

    Raises
    ------
    ValueError
        No series, a tie between the largest, a file without a series UID, or slices
        that do not lie on one regular grid (:func:`check_slices_on_grid`).
    """
    import SimpleITK as sitk

    p = Path(path)
    folder = p if p.is_dir() else p.parent
    if p.is_dir():
        uid = _largest_series(folder)
    else:
        header = sitk.ImageFileReader()
        header.SetFileName(str(p))
        header.ReadImageInformation()
        if not header.HasMetaDataKey(_SERIES_UID):
            raise ValueError(f"{p.name} names no SeriesInstanceUID (0020,000E)")
        uid = header.GetMetaData(_SERIES_UID).strip().rstrip("\0")
    files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), uid)
    if not files:
        raise ValueError(f"no readable slice of series {uid} in {folder}")
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    reader.MetaDataDictionaryArrayUpdateOn()  # each slice's header, for its position
    image = reader.Execute()
    positions = [reader.GetMetaData(k, _POSITION) if reader.HasMetaDataKey(k, _POSITION)
                 else "" for k in range(len(files))]  # fmt: skip
    check_slices_on_grid(image, positions, [Path(f).name for f in files])
    return image


def check_slices_on_grid(image, positions: list[str], names: list[str]) -> None:
    """Refuse a series whose slices do not lie where its image's regular grid puts them.

    Parameters
    ----------
    image : SimpleITK.Image
        The series as read: slice ``k`` of it is file ``k``.
    positions : list of str
        Each file's ``ImagePositionPatient`` (three numbers, backslash-separated); a
        series with one missing or unreadable is not checked (no grid to hold it to).
    names : list of str
        The files' names, for the message.

    Raises
    ------
    ValueError
        A slice farther from its grid point than :data:`SLICE_TOLERANCE_MM` or
        :data:`SLICE_TOLERANCE_SPACING` of the slice spacing; one line naming it.
    """
    if image.GetDimension() != 3 or image.GetSize()[2] != len(positions) or len(positions) < 2:
        return
    try:
        found = np.array([[float(v) for v in p.strip(" \0").split("\\")] for p in positions])
    except ValueError:
        return
    if found.shape != (len(positions), 3) or not np.isfinite(found).all():
        return
    grid = np.array([image.TransformIndexToPhysicalPoint((0, 0, k)) for k in range(len(found))])
    off = np.linalg.norm(found - grid, axis=1)
    worst = int(np.argmax(off))
    step = image.GetSpacing()[2]
    if off[worst] > max(SLICE_TOLERANCE_MM, SLICE_TOLERANCE_SPACING * step):
        raise ValueError(
            f"its slices are not evenly spaced along one axis: slice {worst} ({names[worst]}) "
            f"lies {off[worst]:.3g} mm from its place on a grid of {step:.4g} mm steps (a "
            "missing slice, uneven spacing or a gantry tilt); resample the series onto a "
            "regular grid first (dcm2niix, or 3D Slicer's acquisition geometry regularization)"
        )


def _largest_series(folder: Path) -> str:
    """The UID of the series with the most slices in ``folder``; a tie is refused."""
    import SimpleITK as sitk

    uids = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
    if not uids:
        raise ValueError("no DICOM series in this folder")
    counts = {uid: len(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), uid))
              for uid in uids}  # fmt: skip
    ranked = sorted(counts, key=counts.get, reverse=True)
    if len(ranked) > 1 and counts[ranked[0]] == counts[ranked[1]]:
        tied = [u for u in ranked if counts[u] == counts[ranked[0]]]
        names = "; ".join(f"{u} ({_description(folder, u)})" for u in tied)
        raise ValueError(
            f"holds {len(tied)} DICOM series of {counts[ranked[0]]} slices each: {names}; "
            "give one file of the series to read instead of the folder"
        )
    return ranked[0]


def _description(folder: Path, uid: str) -> str:
    """A series' ``SeriesDescription`` (or its first file's name), for messages."""
    import SimpleITK as sitk

    first = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), uid)[0]
    header = sitk.ImageFileReader()
    header.SetFileName(first)
    header.ReadImageInformation()
    if header.HasMetaDataKey(_DESCRIPTION) and header.GetMetaData(_DESCRIPTION).strip():
        return f"{header.GetMetaData(_DESCRIPTION).strip()!r}, e.g. {Path(first).name}"
    return f"e.g. {Path(first).name}"
