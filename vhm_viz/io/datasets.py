"""Datasets from and to files: :func:`read_dataset` and :func:`write_dataset`.

Both dispatch through the format table (:mod:`vhm_viz.io.registry`): a format's header
check, then its reader; its writer, or PyVista's. What every read must satisfy whatever
the format -- one dataset, some points, finite points, cells whose point ids exist -- is
checked here.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from vhm_viz.atomic import atomic_directory, atomic_path
from vhm_viz.io.errors import ReadError, first_line, refuse_empty
from vhm_viz.io.guard import refuse_inputs
from vhm_viz.io.isolated import meanwhile as read_meanwhile
from vhm_viz.io.registry import (
    array_file,
    dataset_suffixes,
    dataset_type,
    format_of,
    output_suffixes,
    suffix_of,
)

__all__ = ["read_dataset", "write_dataset", "check_dataset"]


def read_dataset(path, *, meanwhile=None):
    """Read a mesh, tet mesh, point cloud or volume; never crash, never guess.

    Every file is checked before a library parses it, and a file that is truncated,
    inconsistent or not what its suffix says is refused with a :class:`ReadError` -- never
    read as a partial mesh or a point cloud:

    * PLY: the header's element counts and property types against the file size (binary)
      or the number of values (ASCII); legacy VTK: the point and cell counts against the
      bytes or values that follow; VTK XML: its closing ``</VTKFile>``; binary STL: the
      triangle count against the file size;
      MetaImage (``.mhd``/``.mha``), NIfTI (``.nii``/``.nii.gz``), NRRD (``.nrrd``, and
      ``.nhdr`` with its data file) and SLC: the voxel count against the (decompressed)
      data; MEDIT and Gmsh: each block's or section's count against the entries it holds
      (text), and every Gmsh section's end; OFF: parsed here;
    * VTK's and SimpleITK's readers then run in a forked child process, so that a crash
      of a reader on a file these checks could not fully vet becomes an error message,
      not the end of the process; an error the library reports while reading refuses the
      file too;
    * the result must have finite points and cells whose point ids exist;
    * meshio (MEDIT ``.mesh``, Gmsh ``.msh``) runs with its printed output captured and its
      ``sys.exit`` and internal errors turned into a :class:`ReadError`.

    Parameters
    ----------
    path : str or os.PathLike
        One of :data:`~vhm_viz.io.DATASET_SUFFIXES`, or a DICOM series: a folder (its
        largest series) or one DICOM file (with or without ``.dcm``: the series it
        belongs to; :mod:`~vhm_viz.io.dicom`). ``.npy``/``.xyz``/``.txt``/``.csv`` hold
        one point per row (the first three columns are x, y, z).
    meanwhile : callable(), optional
        Work for this process while a child process reads the file: run once before
        this returns, also when no child reads it (then after the read); a read that
        fails may have run it. See :func:`~vhm_viz.io.isolated.meanwhile`.

    Returns
    -------
    pyvista.DataSet
        ``PolyData`` for surfaces and point lists (an OBJ/OFF read as polygon cells becomes
        a surface again), ``UnstructuredGrid`` for volumetric meshes, ``ImageData`` for
        volumes (DICOM series included; placed in ITK's LPS world in millimetres, as
        SimpleITK reads them), and so on. A MultiBlock file with one block gives
        that block.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    ReadError
        Unknown suffix, unreadable, truncated, inconsistent or empty file, several datasets
        in one file; the message names the file and the problem.
    """
    import pyvista as pv

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no such file: {p}")
    if not (p.is_file() or p.is_dir()):
        raise ReadError(f"{p}: not a file")
    if p.is_file():
        refuse_empty(p)
    fmt = format_of(p)
    if fmt is None or fmt.read is None:
        suffix = suffix_of(p)
        raise ReadError(
            f"{p}: unsupported file type {suffix or '(none)'!r}; use one of "
            f"{', '.join(dataset_suffixes())} (or a folder of DICOM files)"
        )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            check = fmt.function("check")
            if check is not None:
                check(p)
            with read_meanwhile(meanwhile):
                data = fmt.function("read")(p)
        except ReadError:
            raise
        except MemoryError as exc:
            raise ReadError(f"{p}: cannot read (it asks for more memory than there is)") from exc
        except Exception as exc:  # noqa: BLE001 -- VTK, numpy and meshio raise many types
            raise ReadError(f"{p}: cannot read ({first_line(exc)})") from exc
    if isinstance(data, pv.MultiBlock):
        blocks = [b for b in data if b is not None]
        if len(blocks) != 1:
            raise ReadError(f"{p}: holds {len(blocks)} datasets (a MultiBlock); give one dataset")
        data = blocks[0]
    if data is None or data.n_points == 0:
        why = f" ({first_line(caught[0].message)})" if caught else ""
        kind = fmt.name if fmt.folder else suffix_of(p)
        raise ReadError(f"{p}: no points (empty, or not a valid {kind} file){why}")
    check_dataset(data, p)
    return _surface_if_polygonal(data)


def write_dataset(path, data, inputs=()) -> list[Path]:
    """Write a PyVista dataset atomically, in the format of the suffix.

    The format's row in :data:`~vhm_viz.io.registry.FORMATS` says which dataset types it
    holds and who writes it: images go to MetaImage (``.mhd`` + ``.raw``, or ``.mha``),
    NIfTI (``.nii``, ``.nii.gz``) and NRRD (``.nrrd``) with their origin, spacing and
    direction (:mod:`vhm_viz.io.medical`, :mod:`vhm_viz.io.nrrd`); the other formats
    through PyVista's writers. These image formats hold one array a file: the active
    point array (or the first) goes to ``path``, every other one to a file beside it
    (:func:`~vhm_viz.io.registry.array_file`: ``out.nii.gz`` and ``vtkValidPointMask``
    give ``out_vtkValidPointMask.nii.gz``); all of them appear together or not at all.

    Parameters
    ----------
    path : str or os.PathLike
    data : pyvista.DataSet
    inputs : iterable of path-like
        Files that must not be written (the operation's inputs): a file beside ``path``
        that would be one of them is refused before anything is written.

    Returns
    -------
    list of Path
        The files written: ``path`` first, then one per further point array (a
        MetaImage ``.mhd``'s ``.raw`` data files are not listed).

    Raises
    ------
    ValueError
        A suffix nothing is written to, or a dataset type its format does not hold; one
        line naming the suffixes that would do.
    OverwriteError
        A file beside ``path`` would be one of ``inputs``.
    """
    suffix = suffix_of(path)
    fmt = format_of(path) if suffix else None
    if fmt is None or not fmt.writes:
        raise ValueError(
            f"cannot write {suffix or 'a file without a suffix'!r} files; use one of "
            f"{', '.join(output_suffixes())}"
        )
    kind = dataset_type(data)
    if kind is not None and kind not in fmt.writes:
        raise ValueError(
            f"cannot write a {kind} to {suffix!r}; use one of {', '.join(output_suffixes(kind))}"
        )
    path = Path(path)
    write = fmt.function("write")
    if write is None:
        with atomic_path(path) as tmp:
            data.save(os.fspath(tmp))
        return [path]
    parts = _one_array_images(data) if fmt.one_array else []
    if len(parts) <= 1:
        write(path, data)
        return [path]
    paths = dataset_files(path, data)
    for other in paths[1:]:
        refuse_inputs(other, inputs)
    if len(set(paths)) < len(paths):
        raise ValueError(
            f"two point arrays would be written to one file ({', '.join(p.name for p in paths)}); "
            "rename them"
        )
    with atomic_directory(path.parent) as stage:
        for target, (_, image) in zip(paths, parts, strict=True):
            write(stage / target.name, image)
    return paths


def dataset_files(path, data) -> list[Path]:
    """The files :func:`write_dataset` writes ``data`` to, ``path`` first.

    An image in a one-array format (MetaImage, NIfTI, NRRD) has a file beside ``path``
    for each further point array, as :func:`~vhm_viz.io.registry.array_file` names it.

    Parameters
    ----------
    path : str or os.PathLike
    data : pyvista.DataSet

    Returns
    -------
    list of Path
    """
    path = Path(path)
    fmt = format_of(path) if suffix_of(path) else None
    names = _point_arrays_main_first(data) if fmt is not None and fmt.one_array else []
    return [path, *(array_file(path, name) for name in names[1:])]


def _point_arrays_main_first(data) -> list[str]:
    """An image's point array names, the main one (active scalars, else first) first.

    Empty for a dataset that is not an image.
    """
    import pyvista as pv

    data = pv.wrap(data)
    if not isinstance(data, pv.ImageData):
        return []
    names = list(data.point_data.keys())
    if not names:
        return []
    main = data.active_scalars_name if data.active_scalars_name in names else names[0]
    return [main, *(n for n in names if n != main)]


def _one_array_images(data) -> list[tuple[str, object]]:
    """``(name, image)`` for each point array of an image, the main one first.

    The main array is the active scalars (else the first); each image has ``data``'s
    grid and that one array, active. Empty for a dataset that is not an image.
    """
    import pyvista as pv

    data = pv.wrap(data)
    parts = []
    for name in _point_arrays_main_first(data):
        image = pv.ImageData()
        image.CopyStructure(data)  # extent, origin, spacing and direction
        image.point_data[name] = data.point_data[name]
        image.set_active_scalars(name)
        parts.append((name, image))
    return parts


def check_dataset(data, path) -> None:
    """Refuse what no reader should have returned: non-finite points, dangling cell ids.

    Parameters
    ----------
    data : pyvista.DataSet or vtkDataSet
    path : path-like
        The file it was read from, named in the message.

    Raises
    ------
    ReadError
    """
    import pyvista as pv
    from vtkmodules.util import numpy_support as ns

    p = path

    if data.GetNumberOfPoints() and isinstance(
        data, pv.PointSet | pv.PolyData | pv.UnstructuredGrid
    ):
        pts = np.asarray(data.points)
        if not np.isfinite(pts).all():
            bad = np.nonzero(~np.isfinite(pts).all(axis=1))[0]
            raise ReadError(
                f"{p}: {bad.size} points with non-finite coordinates (e.g. point {bad[0]})"
            )
    cells = []
    if isinstance(data, pv.PolyData):
        cells = [data.GetVerts(), data.GetLines(), data.GetPolys(), data.GetStrips()]
    elif isinstance(data, pv.UnstructuredGrid):
        cells = [data.GetCells()]
    n = data.GetNumberOfPoints()
    for arr in cells:
        if arr is None or arr.GetNumberOfCells() == 0:
            continue
        conn = ns.vtk_to_numpy(arr.GetConnectivityArray())
        if conn.size and (conn.min() < 0 or conn.max() >= n):
            raise ReadError(
                f"{p}: cells refer to points that do not exist (ids up to {int(conn.max())}, "
                f"{n} points)"
            )


def _surface_if_polygonal(data):
    """An UnstructuredGrid of triangles/quads/polygons only (OBJ/OFF via meshio) -> PolyData.

    The cells keep their order, so the point, cell and field arrays all come along.
    """
    import pyvista as pv

    if isinstance(data, pv.UnstructuredGrid) and data.n_cells:
        types = set(np.unique(np.asarray(data.celltypes)).tolist())
        polygonal = {int(pv.CellType.TRIANGLE), int(pv.CellType.QUAD), int(pv.CellType.POLYGON)}
        if types <= polygonal:
            surf = pv.PolyData(np.asarray(data.points), faces=np.asarray(data.cells))
            surf.GetPointData().ShallowCopy(data.GetPointData())
            surf.GetCellData().ShallowCopy(data.GetCellData())
            surf.GetFieldData().ShallowCopy(data.GetFieldData())
            return surf
    return data
