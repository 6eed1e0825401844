"""Medical volumes: MetaImage and NIfTI, read and written in ITK's frame.

vhm_viz's world follows ITK and DICOM (LPS, millimetres). Both MetaImage and NIfTI are
read through VTK (:mod:`vhm_viz.io.vtk_files`) after a check of the header's voxel count
against the data, and their orientation is then taken from the header as ITK reads it:
VTK's MetaImage reader takes ``TransformMatrix`` row by row (the transpose of what ITK
writes) and drops a negative spacing's sign, and its NIfTI reader keeps the qform/sform,
the spatial unit and the intensity scaling (``scl_slope``, ``scl_inter``) apart from the
image and reverses the slices of a left-handed grid (qfac -1), which are put back in the
file's order. MetaImages of long integers, which VTK misreads, go through SimpleITK; 4-D
images are refused (VTK keeps a part of them), and so are complex NIfTI images (VTK
takes their voxels for 2-component vectors). The writers keep origin,
spacing and direction, so SimpleITK and ITK-based tools read the same geometry. DICOM
series and NRRD, which VTK reads without their frame, go through SimpleITK
(:mod:`vhm_viz.io.dicom`, :mod:`vhm_viz.io.nrrd`).
"""

from __future__ import annotations

import gzip
import math
import os
import struct
from pathlib import Path

import numpy as np

from vhm_viz.atomic import atomic_output_set, atomic_path
from vhm_viz.io.errors import (
    AGAIN,
    ReadError,
    TruncatedError,
    complex_voxels,
    first_line,
    need,
)
from vhm_viz.io.itk_images import grid_origin, read_with_sitk
from vhm_viz.io.registry import suffix_of
from vhm_viz.io.vtk_files import read_vtk_file
from vhm_viz.resources import require_memory

__all__ = [
    "check_metaimage",
    "check_nifti",
    "data_files_named",
    "metaimage_files",
    "read_metaimage",
    "read_nifti",
    "volume_array",
    "write_metaimage",
    "write_nifti",
]

# NIfTI's world is RAS; vhm_viz's is LPS: x and y flip.
_RAS_LPS = np.diag([-1.0, -1.0, 1.0])
# NIfTI's spatial units (the low 3 bits of xyzt_units) in millimetres; unknown counts as mm
_NIFTI_UNIT_MM = {1: 1000.0, 2: 1.0, 3: 1e-3}
_NIFTI_MM = 2
_META_TYPES = {
    "uint8": "MET_UCHAR", "int8": "MET_CHAR", "uint16": "MET_USHORT", "int16": "MET_SHORT",
    "uint32": "MET_UINT", "int32": "MET_INT", "uint64": "MET_ULONG_LONG",
    "int64": "MET_LONG_LONG", "float32": "MET_FLOAT", "float64": "MET_DOUBLE",
}  # fmt: skip
_NIFTI_TYPES = {  # NIfTI-1 datatype code, bits per voxel
    "uint8": (2, 8), "int16": (4, 16), "int32": (8, 32), "float32": (16, 32),
    "float64": (64, 64), "int8": (256, 8), "uint16": (512, 16), "uint32": (768, 32),
    "int64": (1024, 64), "uint64": (1280, 64),
}  # fmt: skip
#: NIfTI's complex datatype codes, the voxel type as SimpleITK names it: refused on reading
_NIFTI_COMPLEX = {
    32: "complex of 32-bit float", 1792: "complex of 64-bit float",
    2048: "complex of 128-bit float",
}  # fmt: skip


_MET_TYPES = {
    "MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4,
    "MET_UINT": 4, "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8,
    "MET_ULONG_LONG": 8, "MET_FLOAT": 4, "MET_DOUBLE": 8,
}  # fmt: skip


#: Element types VTK's MetaImage reader misreads: they go through SimpleITK.
_SITK_MET_TYPES = ("MET_LONG", "MET_ULONG", "MET_LONG_LONG", "MET_ULONG_LONG")


def check_metaimage(p: Path) -> None:
    """MetaImage: DimSize x ElementType x channels against the (uncompressed) data file."""
    blob = p.read_bytes()[: 1 << 16] if p.stat().st_size > 1 << 16 else p.read_bytes()
    fields, header_end = {}, 0
    for line in blob.split(b"\n"):
        header_end += len(line) + 1
        key, _, value = line.decode("latin-1").partition("=")
        key = key.strip()
        if key:
            fields[key] = value.strip()
        if key == "ElementDataFile":
            break
    try:
        dims = [int(v) for v in fields["DimSize"].split()]
        item = _MET_TYPES[fields["ElementType"].upper()]
        channels = int(fields.get("ElementNumberOfChannels", "1"))
        data_file = fields["ElementDataFile"]
    except (KeyError, ValueError):
        raise ReadError(
            f"{p}: malformed MetaImage header (DimSize, ElementType, ElementDataFile)"
        ) from None
    if min(dims, default=0) <= 0 or channels <= 0:
        raise ReadError(f"{p}: corrupt MetaImage header: DimSize {dims}")
    if len(dims) > 3:  # VTK's reader keeps one voxel of a 4-D image, or aborts
        raise ReadError(f"{p}: cannot read (a {len(dims)}-D image; give a 2-D or 3-D one)")
    # VTK reads what it can of a header that contradicts itself (a 1-voxel image, no turn)
    if fields.get("NDims", str(len(dims))) != str(len(dims)):
        raise ReadError(
            f"{p}: corrupt MetaImage header: NDims {fields['NDims']} but DimSize "
            f"{fields['DimSize']}"
        )
    for key in ("TransformMatrix", "Rotation", "Orientation"):
        if key in fields and len(fields[key].split()) != len(dims) ** 2:
            raise ReadError(
                f"{p}: corrupt MetaImage header: {key} has {len(fields[key].split())} "
                f"values, not {len(dims) ** 2} (DimSize {fields['DimSize']})"
            )
    # refused before a reader allocates it (a header claiming 10**12 voxels)
    what = f"{p}: reading its DimSize {fields['DimSize']}"
    remedy = "check its DimSize, or read it where more memory is allowed"
    require_memory(math.prod(dims) * item * channels, what, remedy, ReadError)
    if fields.get("CompressedData", "False").lower() == "true" or data_file.upper() == "LIST":
        return
    needed = int(np.prod(dims, dtype=np.int64)) * item * channels
    if data_file.upper() == "LOCAL":
        need(p, "the voxels", needed, p.stat().st_size - header_end)
        return
    raw = (p.parent / data_file) if not Path(data_file).is_absolute() else Path(data_file)
    if not raw.is_file():
        raise ReadError(f"{p}: its data file {raw.name} is missing")
    skip = int(fields.get("HeaderSize", "0") or 0)
    need(raw, "the voxels of " + p.name, needed, raw.stat().st_size - max(skip, 0))


#: The most of a header read to find its data files (a detached header with a long list).
HEADER_SCAN_LIMIT = 1 << 24


def data_files_named(folder: Path, spec: str, following: list[str]) -> list[Path]:
    """The data files a MetaImage ``ElementDataFile`` or a NRRD ``data file`` names.

    Parameters
    ----------
    folder : Path
        The header's folder: relative names are relative to it.
    spec : str
        The field's value: one file name; ``LIST`` (then ``following`` holds one name a
        line); or a pattern ``name%03d.raw first last step`` (NRRD may add a
        sub-dimension); ``LOCAL`` (MetaImage: in the header file) names none.
    following : list of str
        The header's lines after the field.

    Returns
    -------
    list of Path
    """
    words = spec.split()
    if not words or words[0].upper() == "LOCAL":
        return []
    if words[0].upper() == "LIST":
        names = [line.strip() for line in following if line.strip()]
    elif len(words) >= 4 and "%" in words[0]:
        try:
            first, last, step = (int(w) for w in words[1:4])
            stop = last + (1 if step > 0 else -1)
            names = [words[0] % i for i in range(first, stop, step)] if step else []
        except (TypeError, ValueError):
            names = []
    else:
        names = [spec.strip()]
    return [Path(n) if Path(n).is_absolute() else folder / n for n in names]


def metaimage_files(path, written: bool = False) -> list[Path]:
    """The files that hold a MetaImage's voxels, besides the header (:func:`files_of`).

    Parameters
    ----------
    path : path-like
        ``.mhd`` or ``.mha``.
    written : bool
        True: what :func:`write_metaimage` puts beside ``path`` (a ``.mhd``'s ``.raw``).
        False: what an existing header's ``ElementDataFile`` names (none for ``LOCAL``,
        or for a header that cannot be read).

    Returns
    -------
    list of Path
    """
    p = Path(path)
    if written:
        return [] if suffix_of(p) == ".mha" else [p.with_suffix(".raw")]
    try:
        with open(p, "rb") as fh:
            while fh.tell() < HEADER_SCAN_LIMIT:
                line = fh.readline(1 << 16)
                if not line:
                    return []
                key, _, value = line.decode("latin-1").partition("=")
                if key.strip() == "ElementDataFile":  # the header's last field
                    value = value.strip()
                    rest = fh.read(HEADER_SCAN_LIMIT) if value.upper().startswith("LIST") else b""
                    return data_files_named(p.parent, value, rest.decode("latin-1").splitlines())
    except OSError:
        pass
    return []


def check_nifti(p: Path) -> None:
    """NIfTI-1/2: the voxel count of the header against the (decompressed) data.

    A header asking for more memory than there is is refused before anything more is
    read; the data are counted, not kept.
    """
    gz = suffix_of(p) == ".nii.gz"
    try:
        with gzip.open(p, "rb") if gz else open(p, "rb") as fh:
            head = fh.read(540)
            voxels, bits, offset = _nifti_sizes(p, head)
            needed = offset + voxels * bits // 8
            what = f"{p}: reading its {voxels} voxels"
            remedy = "check its dim, or read it where more memory is allowed"
            require_memory(voxels * bits // 8, what, remedy, ReadError)
            if gz:
                available = len(head)
                while available < needed and (chunk := fh.read(min(needed - available, 1 << 24))):
                    available += len(chunk)
            else:
                available = p.stat().st_size
    except (OSError, EOFError) as exc:
        raise TruncatedError(
            f"{p}: truncated or corrupt gzip data ({first_line(exc)}); {AGAIN}"
        ) from None
    need(p, f"{voxels} voxels of {bits} bits", needed, available)


def _nifti_sizes(p: Path, head: bytes) -> tuple[int, int, int]:
    """A NIfTI-1/2 header's voxel count, bits per voxel and data offset, checked."""
    need(p, "a NIfTI header", 348, len(head))
    for order in "<>":
        size = struct.unpack_from(order + "i", head, 0)[0]
        if size in (348, 540):
            break
    else:
        raise ReadError(f"{p}: not a NIfTI file (header size field is not 348 or 540)")
    if size == 348:
        dim = struct.unpack_from(order + "8h", head, 40)
        datatype = struct.unpack_from(order + "h", head, 70)[0]
        bitpix = struct.unpack_from(order + "h", head, 72)[0]
        pixdim = struct.unpack_from(order + "8f", head, 76)
        offset = struct.unpack_from(order + "f", head, 108)[0]
    else:
        need(p, "a NIfTI-2 header", 540, len(head))
        datatype = struct.unpack_from(order + "h", head, 12)[0]
        bitpix = struct.unpack_from(order + "h", head, 14)[0]
        dim = struct.unpack_from(order + "8q", head, 16)
        pixdim = struct.unpack_from(order + "8d", head, 104)
        offset = struct.unpack_from(order + "q", head, 168)[0]
    ndim = dim[0]
    if not 1 <= ndim <= 7 or any(d <= 0 for d in dim[1 : ndim + 1]) or bitpix <= 0:
        raise ReadError(f"{p}: corrupt NIfTI header (dim {list(dim)}, bitpix {bitpix})")
    if not (np.isfinite(offset) and offset >= 0):
        raise ReadError(f"{p}: corrupt NIfTI header (vox_offset {offset})")
    negative = [i for i in (1, 2, 3) if pixdim[i] < 0]
    if negative:
        # the standard wants voxel sizes positive; ITK flips such an axis, nibabel does not
        i = negative[0]
        raise ReadError(
            f"{p}: its voxel size pixdim[{i}] is {pixdim[i]:g}; NIfTI voxel sizes are "
            "positive, and tools place such a file differently (SimpleITK flips the axis, "
            "nibabel does not): set pixdim[1:4] to their absolute values, with the qform "
            "or sform saying which way each axis runs"
        )
    # dim[4] counts time points (VTK's reader keeps the first), dim[5] a voxel's components
    if any(dim[i] > 1 for i in (4, 6, 7) if i <= ndim):
        sizes = " x ".join(str(d) for d in dim[1 : ndim + 1])
        raise ReadError(f"{p}: cannot read (a {ndim}-D image, {sizes}; give a 2-D or 3-D one)")
    if datatype in _NIFTI_COMPLEX:  # VTK's reader takes them for 2-component vectors
        raise ReadError(f"{p}: cannot read ({complex_voxels(_NIFTI_COMPLEX[datatype])})")
    return int(np.prod(dim[1 : ndim + 1], dtype=np.int64)), int(bitpix), int(offset)


def read_metaimage(path):
    """A MetaImage (``.mhd`` + data file, or ``.mha``), its direction as ITK reads it.

    ``MET_LONG_LONG``/``MET_ULONG_LONG`` voxels (64 bits), which VTK's reader takes for
    16-bit ones (or aborts on), and ``MET_LONG``/``MET_ULONG`` voxels (32 bits in
    MetaIO), which it takes for 64-bit ones, are read by SimpleITK.
    """
    p = Path(path)
    fields = {}
    with open(p, "rb") as fh:
        for raw in fh:
            line = raw.decode("latin-1").strip()
            key, _, value = line.partition("=")
            fields[key.strip()] = value.strip()
            if key.strip() == "ElementDataFile":
                break
    if fields.get("ElementType", "").upper() in _SITK_MET_TYPES:

        def read(q):
            import SimpleITK as sitk

            return sitk.ReadImage(str(q)), "MetaImage"

        return read_with_sitk(p, read, "SimpleITK's MetaImage reader")
    image = read_vtk_file(p)
    if not hasattr(image, "direction_matrix"):
        return image
    direction = np.array(image.direction_matrix, dtype=np.float64)
    text = fields.get("TransformMatrix") or fields.get("Rotation") or fields.get("Orientation")
    m = np.array(text.split() if text else [], dtype=np.float64)
    if m.size == 9:
        direction = m.reshape(3, 3).T
    elif m.size == 4:
        direction[:2, :2] = m.reshape(2, 2).T
    # VTK keeps a negative spacing's size; ITK turns the axis over, as here
    spacing = np.array(fields.get("ElementSpacing", "").split()[:3], dtype=np.float64)
    direction[:, : spacing.size] *= np.where(spacing < 0, -1.0, 1.0)
    if m.size == 4 or spacing.size == 2:
        # a 2-D image: its plane's axes, the third the normal to them
        direction[:, 2] = np.cross(direction[:, 0], direction[:, 1])
    image.direction_matrix = direction
    return image


def read_nifti(path):
    """A NIfTI image (``.nii``, ``.nii.gz``) in LPS millimetres, its intensities scaled.

    Placed by its sform or qform as ITK chooses (:func:`_nifti_placement`), negated in x
    and y (NIfTI's world is RAS); an sform whose voxel size differs from ``pixdim`` places
    the voxels by its own (as nibabel does; ITK keeps ``pixdim`` and warns); metres and
    micrometres (``xyzt_units``) are converted to millimetres; a ``scl_slope`` other than
    0 or 1, or a ``scl_inter`` other than 0, is applied (``slope * value + inter``, as
    float32, or float64 for float64 data), as ITK and nibabel read the file.
    """
    from vtkmodules.vtkIOImage import vtkNIFTIImageReader

    p = Path(path)
    image = read_vtk_file(p)
    if not hasattr(image, "direction_matrix"):
        return image
    reader = vtkNIFTIImageReader()
    reader.SetFileName(os.fspath(p))
    reader.UpdateInformation()
    unit = _NIFTI_UNIT_MM.get(reader.GetNIFTIHeader().GetXYZTUnits() & 7, 1.0)
    _scale_intensities(image, reader.GetRescaleSlope(), reader.GetRescaleIntercept())
    header = reader.GetNIFTIHeader()
    m = _nifti_placement(
        _matrix(reader.GetQFormMatrix()) if header.GetQFormCode() > 0 else None,
        _matrix(reader.GetSFormMatrix()) if header.GetSFormCode() > 0 else None,
        header.GetSFormCode(),
    )
    if m is not None:
        # VTK divides the sform by pixdim: a voxel size of the sform's own stays in its
        # columns, and goes to the spacing here (the direction's columns are unit vectors)
        scale = np.linalg.norm(m[:3, :3], axis=0)
        scale[~(scale > 0)] = 1.0
        image.origin = tuple(_RAS_LPS @ m[:3, 3])
        image.direction_matrix = _RAS_LPS @ m[:3, :3] / scale
        image.spacing = tuple(np.asarray(image.spacing, dtype=np.float64) * scale)
        if reader.GetQFac() < 0:
            _unflip_slices(image)
    if unit != 1.0:
        image.origin = tuple(unit * np.asarray(image.origin, dtype=np.float64))
        image.spacing = tuple(unit * np.asarray(image.spacing, dtype=np.float64))
    return image


def _unflip_slices(image) -> None:
    """Put back the slice order of the file, which VTK's NIfTI reader reverses for qfac -1.

    VTK makes a left-handed voxel grid right-handed by reading the slices last to first;
    ITK and nibabel keep the file's order. Same voxels at the same points either way, but
    only the file's order keeps an output written on this grid (or on it as a
    ``--reference``) voxel for voxel on the file's grid, as other tools index it.
    """
    nx, ny, nz = (int(d) for d in image.dimensions)
    direction = np.array(image.direction_matrix, dtype=np.float64)
    origin = np.asarray(image.origin, dtype=np.float64)
    image.origin = tuple(origin + direction[:, 2] * image.spacing[2] * (nz - 1))
    direction[:, 2] *= -1.0
    image.direction_matrix = direction
    for name in list(image.point_data.keys()):
        values = np.asarray(image.point_data[name])
        if not (values.flags.c_contiguous and values.flags.writeable):
            values = np.ascontiguousarray(values).copy()
            image.point_data[name] = values
        layers = values.reshape(nz, -1)  # a view: the slices swap in place, two at a time
        for k in range(nz // 2):
            layers[[k, nz - 1 - k]] = layers[[nz - 1 - k, k]]


def _matrix(matrix) -> np.ndarray | None:
    """A ``vtkMatrix4x4`` (or None) as a (4, 4) array."""
    if matrix is None:
        return None
    return np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])


def _nifti_placement(qform, sform, sform_code: int) -> np.ndarray | None:
    """The voxel-to-RAS matrix ITK places a NIfTI image by: its sform or its qform.

    ITK's choice is that of SimpleITK, ANTs and 3D Slicer.

    Parameters
    ----------
    qform, sform : numpy.ndarray or None
        VTK's (4, 4) matrices, the voxel spacing divided out; None where the header's code
        is 0 (unknown).
    sform_code : int
        1 (scanner) makes an sform without shear win over a differing qform.

    Returns
    -------
    numpy.ndarray or None
        The sform where ITK takes it: free of shear, and either the only one, labelled
        scanner, or the qform's twin (an sform labelled aligned, Talairach or MNI that
        differs from the qform is another space than the scanner's, and ITK reads the
        qform). Else the qform, else an sform with shear (ITK refuses that file; nibabel
        reads it so), else None (neither: the image lies on its index grid).
    """
    if sform is not None:
        columns = sform[:3, :3] / np.linalg.norm(sform[:3, :3], axis=0)
        unsheared = np.allclose(columns.T @ columns, np.eye(3), rtol=0, atol=1e-4)
        twins = qform is not None and np.allclose(sform[:3], qform[:3], rtol=0, atol=1e-4)
        if unsheared and (qform is None or sform_code == 1 or twins):
            return sform
    return qform if qform is not None else sform


def _scale_intensities(image, slope: float, inter: float) -> None:
    """Apply NIfTI's ``scl_slope``/``scl_inter`` to every point array, where they scale."""
    if not np.isfinite(slope) or slope == 0.0:
        slope = 1.0
    if not np.isfinite(inter):
        inter = 0.0
    if slope == 1.0 and inter == 0.0:
        return
    for name in list(image.point_data.keys()):
        values = np.asarray(image.point_data[name])
        dtype = np.float64 if values.dtype == np.float64 else np.float32
        image.point_data[name] = (values.astype(np.float64) * slope + inter).astype(dtype)


def volume_array(image) -> np.ndarray:
    """The array a one-array format stores: the active scalars, else the first one.

    Parameters
    ----------
    image : pyvista.ImageData

    Returns
    -------
    numpy.ndarray
        ``(n_points,)`` or ``(n_points, components)``, contiguous; a dtype no format
        stores (bool, float16, ...) as float64.

    Raises
    ------
    ValueError
        The image has no point array.
    """
    name = image.active_scalars_name or (image.point_data.keys() or [None])[0]
    if name is None:
        raise ValueError("the image has no point array to write")
    values = np.ascontiguousarray(image.point_data[name])
    if values.dtype.name not in _META_TYPES:
        values = values.astype(np.float64)
    return values


def write_metaimage(path, image) -> None:
    """Write an image as MetaImage (atomically), keeping origin, spacing and direction.

    The active scalars (or the first point array) are written; a multi-component array
    becomes channels. The direction matrix is listed column by column
    (``TransformMatrix``, each image axis's direction in turn), as ITK writes it.
    ``.mhd`` puts the voxels in a ``.raw`` file beside it; ``.mha`` holds them.

    Parameters
    ----------
    path : str or os.PathLike
        ``.mhd`` or ``.mha``.
    image : pyvista.ImageData
    """
    path = Path(path)
    values = volume_array(image)
    direction = np.asarray(image.direction_matrix, dtype=np.float64)
    comps = 1 if values.ndim == 1 else values.shape[1]
    fmt = lambda v: " ".join(f"{x:.17g}" for x in v)  # noqa: E731
    beside = metaimage_files(path, written=True)
    data_file = beside[0].name if beside else "LOCAL"
    header = [
        "ObjectType = Image",
        "NDims = 3",
        "BinaryData = True",
        "BinaryDataByteOrderMSB = False",
        "CompressedData = False",
        f"TransformMatrix = {fmt(direction.T.ravel())}",  # ITK: one image axis after another
        f"Offset = {fmt(grid_origin(image))}",
        "CenterOfRotation = 0 0 0",
        f"ElementSpacing = {fmt(image.spacing)}",
        f"DimSize = {' '.join(str(int(d)) for d in image.dimensions)}",
        *([f"ElementNumberOfChannels = {comps}"] if comps > 1 else []),
        f"ElementType = {_META_TYPES[values.dtype.name]}",
        f"ElementDataFile = {data_file}",
    ]
    text = ("\n".join(header) + "\n").encode("ascii")
    raw = values.astype(values.dtype.newbyteorder("<"), copy=False).tobytes()
    if data_file == "LOCAL":
        with atomic_path(path) as tmp:
            tmp.write_bytes(text + raw)
        return
    # one set: the voxels appear with their header, never beside another header
    with atomic_output_set([*beside, path]) as (raw_tmp, header_tmp):
        raw_tmp.write_bytes(raw)
        header_tmp.write_bytes(text)


def write_nifti(path, image) -> None:
    """Write an image as NIfTI-1 (atomically), keeping origin, spacing and direction.

    One file, a 352-byte header with matching qform and sform (a sheared grid, which no
    qform holds, has the sform alone); the active scalars (or the first point array), a
    multi-component array as a vector. NIfTI's world is RAS, so x and y are negated from
    vhm_viz's (LPS) world, as ITK does.

    Parameters
    ----------
    path : str or os.PathLike
        ``.nii`` or ``.nii.gz`` (gzip-compressed).
    image : pyvista.ImageData
    """
    from scipy.spatial.transform import Rotation  # here: importing it is slow, rarely used

    path = Path(path)
    values = volume_array(image)
    if values.dtype.name not in _NIFTI_TYPES:
        values = values.astype(np.float64)
    code, bits = _NIFTI_TYPES[values.dtype.name]
    comps = 1 if values.ndim == 1 else values.shape[1]
    # the voxel axes in the RAS world, one a column, as long as a voxel
    affine = _RAS_LPS @ np.asarray(image.direction_matrix, dtype=np.float64) * image.spacing
    spacing = np.linalg.norm(affine, axis=0)
    rot = affine / np.where(spacing > 0, spacing, 1.0)
    offset = _RAS_LPS @ grid_origin(image)
    # the quaternion holds a proper rotation; a reflection flips the third axis (qfac = -1)
    qfac = 1.0 if np.linalg.det(rot) > 0 else -1.0
    quat = Rotation.from_matrix(rot * [1.0, 1.0, qfac]).as_quat()  # x, y, z, w
    if quat[3] < 0:
        quat = -quat
    # a sheared grid is the sform's alone: a qform would hold a rotation near it
    qform_code = 1 if np.allclose(rot.T @ rot, np.eye(3), rtol=0, atol=1e-6) else 0
    dims = [5 if comps > 1 else 3, *image.dimensions, 1, comps, 1, 1]
    header = bytearray(352)
    struct.pack_into("<i", header, 0, 348)
    struct.pack_into("<8h", header, 40, *dims)
    if comps > 1:
        struct.pack_into("<h", header, 68, 1007)  # intent: vector
    struct.pack_into("<2h", header, 70, code, bits)
    struct.pack_into("<8f", header, 76, qfac, *spacing, 1.0, 1.0, 1.0, 1.0)
    struct.pack_into("<f", header, 108, 352.0)  # vox_offset
    struct.pack_into("<f", header, 112, 1.0)  # scl_slope
    header[123] = _NIFTI_MM  # xyzt_units: vhm_viz's world is in mm; no time axis
    struct.pack_into("<2h", header, 252, qform_code, 1)  # qform_code, sform_code: scanner
    struct.pack_into("<6f", header, 256, *quat[:3], *offset)
    for r in range(3):
        struct.pack_into("<4f", header, 280 + 16 * r, *affine[r], offset[r])
    header[344:348] = b"n+1\0"
    raw = values.astype(values.dtype.newbyteorder("<"), copy=False)
    # NIfTI orders a vector's components slowest: (c, z, y, x)
    blob = bytes(header) + (raw.T if comps > 1 else raw).tobytes()
    with atomic_path(path) as tmp:
        if suffix_of(path) == ".nii.gz":
            with gzip.open(tmp, "wb", compresslevel=6) as fh:
                fh.write(blob)
        else:
            tmp.write_bytes(blob)
