"""The one table of file formats: suffixes, what each reads and writes, and who does it.

Every question about a suffix -- can :func:`~vhm_viz.io.read_dataset` read it, what may be
written to it, does it keep a dataset's named arrays, is a volume written there resampled
onto a regular image or warped as a grid, which module checks its header -- is a query of
:data:`FORMATS`. The readers and
writers (:mod:`vhm_viz.io.datasets`, :mod:`vhm_viz.io.cages`,
:mod:`vhm_viz.io.rigidity`) dispatch through it and never list suffixes themselves.

A row names its functions as ``"module:function"`` inside :mod:`vhm_viz.io` (or a full
dotted module path), imported when first used: this module stays free of VTK and
PyVista, and a new format family plugs in as one module plus rows here -- no dispatch
code changes.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path

from vhm_viz.io.errors import ReadError

__all__ = [
    "DATASET_TYPES",
    "Format",
    "FORMATS",
    "DICOM_FOLDER",
    "suffix_of",
    "format_of",
    "dataset_type",
    "dataset_suffixes",
    "cage_suffixes",
    "output_suffixes",
    "image_suffixes",
    "is_image_format",
    "keeps_arrays",
    "array_file",
    "files_of",
]

#: The PyVista dataset types the table speaks of.
DATASET_TYPES = ("PolyData", "UnstructuredGrid", "StructuredGrid", "RectilinearGrid", "ImageData")

#: What the messages call a folder of DICOM files (the one format without a suffix).
DICOM_FOLDER = "DICOM folder"


@dataclass(frozen=True)
class Format:
    """One file format (or family of suffixes read and written the same way).

    Parameters
    ----------
    name : str
        What the format is called in messages.
    suffixes : tuple of str
        Lower-case, with the dot; ``.nii.gz`` counts as one suffix. Empty for a folder.
    reads : tuple of str
        The :data:`DATASET_TYPES` a read may give.
    writes : tuple of str
        The :data:`DATASET_TYPES` :func:`~vhm_viz.io.write_dataset` writes to it.
    image : bool
        A volume written here is resampled onto a regular image (origin, spacing,
        direction); otherwise a volume is written as a warped grid.
    read : str or None
        ``"module:function"``, ``function(path) -> pyvista.DataSet``.
    check : str or None
        ``"module:function"``, ``function(path)``: refuses (:class:`~vhm_viz.io.ReadError`)
        a file whose header promises more than it holds, before any library parses it.
    write : str or None
        ``"module:function"``, ``function(path, data)``; None: PyVista's writer for the
        suffix.
    cage : str or None
        ``"module:function"``, ``function(path) -> (points, polygons, cage_options)``:
        the file as a cage (:func:`~vhm_viz.io.read_cage`); None: not a cage format.
    lines : str or None
        ``"module:function"``, ``function(path) -> (points, edges)``: rigidity lines
        (:func:`~vhm_viz.io.read_rigidity_lines`); None: the line cells of the dataset.
    folder : bool
        The format is a folder of files (DICOM): a folder is read as it, and a file with
        one of its ``suffixes`` (or, for DICOM, its preamble) stands for its folder.
    one_array : bool
        A file holds one point array: :func:`~vhm_viz.io.write_dataset` writes the
        active one to the path and every other one beside it
        (:func:`array_file`).
    files : str or None
        ``"module:function"``, ``function(path, written) -> list of Path``: the other
        files a file of this format is made of (:func:`files_of`); None: the file alone.
    arrays : bool
        What is written keeps the dataset's named point and cell arrays (a one-array
        format in the files beside it); False: the geometry alone, every named array
        dropped (PLY, OBJ and STL as VTK's writers write them).
    """

    name: str
    suffixes: tuple[str, ...]
    reads: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()
    image: bool = False
    read: str | None = None
    check: str | None = None
    write: str | None = None
    cage: str | None = None
    lines: str | None = None
    folder: bool = False
    one_array: bool = False
    files: str | None = None
    arrays: bool = True

    def function(self, role: str):
        """The function a row names for ``role`` (``"read"``, ``"check"``, ...), or None."""
        ref = getattr(self, role)
        if ref is None:
            return None
        module, _, name = ref.partition(":")
        if "." not in module:
            module = f"{__package__}.{module}"
        return getattr(importlib.import_module(module), name)


_ALL = DATASET_TYPES
_VTK_READ = "vtk_files:read_vtk_file"
_VTK_WRITE = "vtk_files:write_vtk_file"
_VTK_CAGE = "cages:read_vtk_cage"
_VTK_XML = "vtk_files:check_vtk_xml"

#: Every format, in the order messages list them.
FORMATS: tuple[Format, ...] = (
    Format("VTK XML unstructured grid", (".vtu",), ("UnstructuredGrid",), ("UnstructuredGrid",),
           read=_VTK_READ, write=_VTK_WRITE, check=_VTK_XML, cage=_VTK_CAGE),
    Format("VTK XML polygonal data", (".vtp",), ("PolyData",), ("PolyData",),
           read=_VTK_READ, write=_VTK_WRITE, check=_VTK_XML, cage=_VTK_CAGE),
    Format("VTK XML image", (".vti",), ("ImageData",), ("ImageData",), image=True,
           read=_VTK_READ, write=_VTK_WRITE, check=_VTK_XML),
    Format("VTK XML structured grid", (".vts",), ("StructuredGrid",), ("StructuredGrid",),
           read=_VTK_READ, write=_VTK_WRITE, check=_VTK_XML),
    Format("VTK XML rectilinear grid", (".vtr",), ("RectilinearGrid",), ("RectilinearGrid",),
           read=_VTK_READ, write=_VTK_WRITE, check=_VTK_XML),
    Format("legacy VTK", (".vtk",), _ALL, _ALL, read=_VTK_READ,
           write=_VTK_WRITE, check="vtk_files:check_legacy_vtk", cage=_VTK_CAGE),
    Format("PLY", (".ply",), ("PolyData",), ("PolyData",), read=_VTK_READ,
           write=_VTK_WRITE, check="mesh_files:check_ply", cage=_VTK_CAGE, arrays=False),
    Format("Wavefront OBJ", (".obj",), ("PolyData",), ("PolyData",), read=_VTK_READ,
           write=_VTK_WRITE, cage="cages:read_obj_cage", arrays=False),
    Format("STL", (".stl",), ("PolyData",), ("PolyData",), read=_VTK_READ,
           write=_VTK_WRITE, check="mesh_files:check_stl", cage="cages:read_stl_cage",
           arrays=False),
    Format("MEDIT", (".mesh",), ("UnstructuredGrid", "PolyData"),
           read="mesh_files:read_meshio", check="mesh_files:check_medit"),
    Format("Gmsh", (".msh",), ("UnstructuredGrid", "PolyData"),
           read="mesh_files:read_meshio", check="mesh_files:check_gmsh"),
    Format("OFF", (".off",), ("PolyData",), read="mesh_files:read_off_dataset",
           cage="cages:read_off_cage", lines="rigidity:read_polylines"),
    Format("MetaImage", (".mhd", ".mha"), ("ImageData",), ("ImageData",), image=True,
           read="medical:read_metaimage", check="medical:check_metaimage",
           write="medical:write_metaimage", one_array=True, files="medical:metaimage_files"),
    Format("NIfTI", (".nii", ".nii.gz"), ("ImageData",), ("ImageData",), image=True,
           read="medical:read_nifti", check="medical:check_nifti",
           write="medical:write_nifti", one_array=True),
    Format("NRRD", (".nrrd",), ("ImageData",), ("ImageData",), image=True,
           read="nrrd:read_nrrd", check="nrrd:check_nrrd", write="nrrd:write_nrrd",
           one_array=True, files="nrrd:nrrd_files"),
    Format("NRRD detached header", (".nhdr",), ("ImageData",), read="nrrd:read_nrrd",
           check="nrrd:check_nrrd", files="nrrd:nrrd_files"),
    Format("SLC", (".slc",), ("ImageData",), read="legacy_volumes:read_slc",
           check="legacy_volumes:check_slc"),
    Format("point list", (".npy", ".xyz", ".txt", ".csv"), ("PolyData",),
           read="mesh_files:read_point_list"),
    Format("TGF skeleton", (".tgf",), lines="rigidity:read_tgf"),
    Format(DICOM_FOLDER, (".dcm",), ("ImageData",), read="dicom:read_dicom", folder=True,
           files="dicom:dicom_files"),
)  # fmt: skip


def suffix_of(path) -> str:
    """Lower-case suffix of a path, with ``.nii.gz`` kept whole."""
    name = Path(path).name.lower()
    if name.endswith(".nii.gz"):
        return ".nii.gz"
    return Path(name).suffix


def format_of(path) -> Format | None:
    """The row for ``path``: by its suffix, or the folder format for an existing folder.

    An existing file whose suffix no row lists but which starts like a DICOM file (many
    have no suffix, or a UID's last number for one) is a DICOM file. Returns None for
    other suffixes no row lists; raises :class:`ReadError` for a folder named like a file
    of a format (``bunny.ply/``).
    """
    p = Path(path)
    if p.is_dir():
        named = _format_with_suffix(suffix_of(p))
        if named is not None and not named.folder:  # "bunny.ply/": not read as a series
            raise ReadError(f"{p}: a folder, not a {suffix_of(p)} file; name the file itself")
        return next((f for f in FORMATS if f.folder), None)
    fmt = _format_with_suffix(suffix_of(p))
    if fmt is None and p.is_file():
        from vhm_viz.io.dicom import is_dicom_file

        if is_dicom_file(p):
            return next((f for f in FORMATS if f.folder), None)
    return fmt


def _format_with_suffix(suffix: str) -> Format | None:
    return next((f for f in FORMATS if suffix and suffix in f.suffixes), None)


def dataset_type(data) -> str | None:
    """The :data:`DATASET_TYPES` name of a PyVista (or VTK) dataset, None for others."""
    for cls in type(data).__mro__:
        name = cls.__name__.removeprefix("vtk")
        if name in DATASET_TYPES:
            return name
    return None


def _suffixes(keep) -> tuple[str, ...]:
    return tuple(s for f in FORMATS if keep(f) for s in f.suffixes)


def dataset_suffixes() -> tuple[str, ...]:
    """Suffixes :func:`~vhm_viz.io.read_dataset` reads (a DICOM folder has none)."""
    return _suffixes(lambda f: f.read is not None)


def cage_suffixes() -> tuple[str, ...]:
    """Suffixes :func:`~vhm_viz.io.read_cage` reads."""
    return _suffixes(lambda f: f.cage is not None)


def output_suffixes(dataset_type: str | None = None, *, arrays: bool = False) -> tuple[str, ...]:
    """Suffixes :func:`~vhm_viz.io.write_dataset` writes a ``dataset_type`` to.

    Parameters
    ----------
    dataset_type : str, optional
        One of :data:`DATASET_TYPES`; None: every suffix anything is written to.
    arrays : bool
        Only the suffixes that keep the dataset's named arrays (:attr:`Format.arrays`).
    """
    if dataset_type is not None and dataset_type not in DATASET_TYPES:
        raise ValueError(f"unknown dataset type {dataset_type!r}; use one of {DATASET_TYPES}")

    def keep(f: Format) -> bool:
        written = dataset_type in f.writes if dataset_type else bool(f.writes)
        return written and (f.arrays or not arrays)

    return _suffixes(keep)


def image_suffixes() -> tuple[str, ...]:
    """Suffixes a volume is resampled onto as a regular image (:func:`is_image_format`)."""
    return _suffixes(lambda f: f.image)


def is_image_format(path) -> bool:
    """Whether a volume written to ``path`` is a regular image (resampled onto it).

    True for ``.vti``, ``.mhd``, ``.mha``, ``.nii``, ``.nii.gz`` and ``.nrrd``; False
    otherwise (a volume written to ``.vts`` or ``.vtk`` is a warped grid, every voxel
    moved).

    Parameters
    ----------
    path : str or os.PathLike
        Only its suffix counts; the file need not exist.
    """
    return suffix_of(path) in image_suffixes()


def keeps_arrays(path) -> bool:
    """Whether a dataset written to ``path`` keeps its named point and cell arrays.

    False for ``.ply``, ``.obj`` and ``.stl`` (the geometry alone); True for the other
    suffixes written to (:attr:`Format.arrays`) and for those no format lists.

    Parameters
    ----------
    path : str or os.PathLike
        Only its suffix counts; the file need not exist.
    """
    fmt = _format_with_suffix(suffix_of(path))
    return fmt is None or fmt.arrays


def array_file(path, name: str) -> Path:
    """Where a one-array format (:attr:`Format.one_array`) puts the point array ``name``.

    Beside ``path``, its name followed by ``_`` and the array's (characters other than
    letters, digits, ``-`` and ``_`` become ``_``), with the same suffix:
    ``out.nii.gz`` and ``vhm_foldover`` give ``out_vhm_foldover.nii.gz``.

    Parameters
    ----------
    path : path-like
        The file the active array is written to.
    name : str
        A point array's name.
    """
    p = Path(path)
    suffix = suffix_of(p)
    stem = p.name[: len(p.name) - len(suffix)] if suffix else p.name
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "array"
    return p.with_name(f"{stem}_{safe}{p.name[len(stem) :]}")


def files_of(path, written: bool = False) -> list[Path]:
    """The other files that make up ``path`` in its format (:attr:`Format.files`).

    Parameters
    ----------
    path : path-like
    written : bool
        False: the files an existing ``path`` reads besides itself (a MetaImage or NRRD
        header's data files, the other files of a DICOM series' folder). True: the files
        :func:`~vhm_viz.io.write_dataset` writes beside ``path`` (a ``.mhd``'s ``.raw``);
        only the suffix counts.

    Returns
    -------
    list of Path
        Empty for a format whose files are one file, or a header that cannot be read
        (its reader says why).
    """
    p = Path(path)
    fmt = _format_with_suffix(suffix_of(p)) if written else format_of(p)
    files = fmt.function("files") if fmt is not None else None
    return list(files(p, written)) if files is not None else []
