"""The VTK edge of the filters: VTK data as numpy arrays and grids, and ``update``.

What the filters read from VTK objects (points, image geometry, the extent a pipeline
asks for, a key that changes with a dataset's geometry) as plain arrays and
:class:`~vhm_viz.core.image.ImageGeometry`, and :func:`update`, which runs a filter and
raises the Python error its execution stored.
"""

from __future__ import annotations

import hashlib
import signal

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonCore import VTK_LONG_LONG, vtkObject
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonExecutionModel import vtkExtentTranslator, vtkStreamingDemandDrivenPipeline

from vhm_viz import interrupts
from vhm_viz.core.image import ImageGeometry

__all__ = [
    "update",
    "numpy_points",
    "geometry_key",
    "image_geometry",
    "information_geometry",
    "requested_extent",
    "cage_digest",
    "add_lattice_counts",
    "set_field_counts",
]

_SDDP = vtkStreamingDemandDrivenPipeline


def numpy_points(ds) -> np.ndarray:
    """Points of any vtkDataSet as a (N, 3) float64 array (a copy for implicit points)."""
    axes = _axes(ds)
    if axes is not None:
        x, y, z = axes
        out = np.empty((len(z), len(y), len(x), 3))
        out[..., 0] = x
        out[..., 1] = y[:, None]
        out[..., 2] = z[:, None, None]
        return out.reshape(-1, 3)
    pts = ds.GetPoints() if hasattr(ds, "GetPoints") else None
    if pts is not None and pts.GetData() is not None:
        return np.asarray(ns.vtk_to_numpy(pts.GetData()), dtype=np.float64).reshape(-1, 3)
    if ds.IsA("vtkImageData"):  # VTK < 9.6 (ParaView's) makes no points array for images
        return image_geometry(ds).points()
    n = ds.GetNumberOfPoints()
    out = np.empty((n, 3))
    p = [0.0, 0.0, 0.0]
    for i in range(n):  # only reached for exotic datasets
        ds.GetPoint(i, p)
        out[i] = p
    return out


def displacement(ds, moved_points) -> np.ndarray:
    """``moved_points - numpy_points(ds)`` as a new (N, 3) float64 array.

    An axis-aligned lattice's points are subtracted axis by axis, never made: the same
    values without a second array of the output's size.
    """
    out = np.array(moved_points, dtype=np.float64).reshape(-1, 3)
    axes = _axes(ds)
    if axes is None:
        out -= numpy_points(ds)
        return out
    x, y, z = axes
    grid = out.reshape(len(z), len(y), len(x), 3)
    grid[..., 0] -= x
    grid[..., 1] -= y[:, None]
    grid[..., 2] -= z[:, None, None]
    return out


def _axes(ds):
    """The x, y and z coordinates of an axis-aligned lattice's points, else None.

    A rectilinear grid's (VTK < 9.6's ``GetPoints`` fills an argument), or the implicit
    points (VTK's ``vtkStructuredPointArray``) of an image without a direction matrix,
    whose own conversion to numpy builds three meshgrids and a column stack, several
    times the output's memory and time.
    """
    data = None
    if ds.IsA("vtkRectilinearGrid"):
        data = ds
    elif ds.IsA("vtkImageData") and hasattr(ds, "GetPoints"):
        pts = ds.GetPoints()
        implicit = None if pts is None else pts.GetData()
        if hasattr(implicit, "GetXCoordinates") and not implicit.GetUsesDirectionMatrix():
            data = implicit
    if data is None:
        return None
    return tuple(
        ns.vtk_to_numpy(c).astype(np.float64, copy=False)
        for c in (data.GetXCoordinates(), data.GetYCoordinates(), data.GetZCoordinates())
    )


def image_geometry(img, extent=None) -> ImageGeometry:
    """:class:`~vhm_viz.core.image.ImageGeometry` of a ``vtkImageData`` (or of an extent).

    ``extent`` (default: the image's own) may be any extent of the same grid, such as the
    whole extent of a pipeline whose data holds one piece.
    """
    ext = img.GetExtent() if extent is None else extent
    origin = np.asarray(img.GetOrigin(), dtype=np.float64)
    spacing = np.asarray(img.GetSpacing(), dtype=np.float64)
    m = img.GetDirectionMatrix()
    direction = np.array([[m.GetElement(i, j) for j in range(3)] for i in range(3)])
    start = np.array(ext[0::2], dtype=np.float64)
    dims = [ext[2 * a + 1] - ext[2 * a] + 1 for a in range(3)]
    return ImageGeometry(origin + direction @ (start * spacing), spacing, dims, direction)


def information_geometry(info) -> ImageGeometry | None:
    """The whole grid an image pipeline announces (WHOLE_EXTENT, ORIGIN, SPACING, DIRECTION).

    Known in the information pass, before any data is read: what a filter needs to plan
    which extent of its input to request. None without a whole extent.
    """
    whole = info.Get(_SDDP.WHOLE_EXTENT())
    if whole is None:
        return None
    origin = info.Get(vtkImageData.ORIGIN()) or (0.0, 0.0, 0.0)
    spacing = info.Get(vtkImageData.SPACING()) or (1.0, 1.0, 1.0)
    direction = info.Get(vtkImageData.DIRECTION()) if info.Has(vtkImageData.DIRECTION()) else None
    direction = np.eye(3) if direction is None else np.asarray(direction).reshape(3, 3)
    start = np.array(whole[0::2], dtype=np.float64)
    dims = [whole[2 * a + 1] - whole[2 * a] + 1 for a in range(3)]
    origin = np.asarray(origin, dtype=np.float64) + direction @ (start * np.asarray(spacing))
    return ImageGeometry(origin, spacing, dims, direction)


def requested_extent(info, whole=None):
    """The extent a structured output is asked for: its piece's (block mode) or UPDATE_EXTENT.

    When a piece is requested (``UpdatePiece``, MPI ranks), VTK turns it into an extent
    with ``vtkExtentTranslator`` only after the update-extent pass; a filter that plans
    what to read from its input (the resampling's window) needs the piece's extent then.
    """
    whole = info.Get(_SDDP.WHOLE_EXTENT()) if whole is None else whole
    ext = info.Get(_SDDP.UPDATE_EXTENT()) or whole
    n = info.Get(_SDDP.UPDATE_NUMBER_OF_PIECES()) or 1
    if n > 1 and whole is not None and (ext is None or tuple(ext) == tuple(whole)):
        piece = info.Get(_SDDP.UPDATE_PIECE_NUMBER()) or 0
        tr = vtkExtentTranslator()
        ext = [0] * 6
        tr.PieceToExtentThreadSafe(piece, n, 0, whole, ext, tr.BLOCK_MODE, 0)
    return None if ext is None else tuple(int(v) for v in ext)


def own_extent(info, whole=None):
    """A piece's own extent, without the ghost levels it is requested with; else None.

    None when the request has no ghost levels (the requested extent is the piece's own)
    or no pieces. The extent of the piece that ``vtkExtentTranslator`` assigns in block
    mode, as :func:`requested_extent`: the cells between it and the requested extent are
    the neighbours' (ghost cells).
    """
    whole = info.Get(_SDDP.WHOLE_EXTENT()) if whole is None else whole
    ghosts = info.Get(_SDDP.UPDATE_NUMBER_OF_GHOST_LEVELS()) or 0
    n = info.Get(_SDDP.UPDATE_NUMBER_OF_PIECES()) or 1
    if ghosts <= 0 or n <= 1 or whole is None:
        return None
    piece = info.Get(_SDDP.UPDATE_PIECE_NUMBER()) or 0
    tr = vtkExtentTranslator()
    ext = [0] * 6
    tr.PieceToExtentThreadSafe(piece, n, 0, whole, ext, tr.BLOCK_MODE, 0)
    return tuple(int(v) for v in ext)


def geometry_key(ds) -> tuple:
    """A hashable key that changes when the geometry (point positions) of ``ds`` changes.

    Point sets: identity and modification time of their points. Images: extent, origin,
    spacing, direction. Rectilinear grids: extent and the coordinate arrays' times.
    """
    if ds is None:
        return (None,)
    if ds.IsA("vtkImageData"):
        d = ds.GetDirectionMatrix()
        direction = tuple(d.GetElement(i, j) for i in range(3) for j in range(3))
        return ("image", ds.GetExtent(), ds.GetOrigin(), ds.GetSpacing(), direction)
    if ds.IsA("vtkRectilinearGrid"):
        coords = (ds.GetXCoordinates(), ds.GetYCoordinates(), ds.GetZCoordinates())
        return ("rect", ds.GetExtent(), *((id(c), c.GetMTime()) for c in coords))
    pts = ds.GetPoints()
    if pts is None:
        return ("empty", ds.GetNumberOfPoints())
    return ("points", pts.GetAddressAsString("vtkPoints"), pts.GetMTime(), pts.GetNumberOfPoints())


def update(algorithm, piece: int | None = None, n_pieces: int = 1):
    """Update a vhm_viz filter and re-raise the Python error its execution stored.

    VTK reports exceptions raised inside ``RequestData`` only as log messages; the
    vhm_viz filters keep the exception in ``last_error``. This helper silences VTK's
    duplicate messages and raises that exception.

    Parameters
    ----------
    algorithm : a vhm_viz filter
    piece, n_pieces : int, optional
        Update only this piece (``UpdatePiece(piece, n_pieces, 0)``).

    Returns
    -------
    vtkDataObject
        The filter's output.
    """
    previous = vtkObject.GetGlobalWarningDisplay()
    vtkObject.GlobalWarningDisplayOff()
    # Ctrl-C inside VTK's pipeline: the filters stop between chunks and the interrupt is
    # raised here, even when VTK's wrapper swallowed it inside a callback
    with interrupts.handled(signals=(signal.SIGINT,)):
        try:
            algorithm.last_error = None
            if piece is None:
                algorithm.Update()
            else:
                algorithm.UpdatePiece(int(piece), int(n_pieces), 0)
        finally:
            vtkObject.SetGlobalWarningDisplay(previous)
            if algorithm.last_error is not None or interrupts.pending() is not None:
                algorithm.Modified()  # what it produced is no result: execute next time
        try:
            interrupts.check()
        except interrupts.Interrupted as exc:
            if exc.signum == signal.SIGINT:  # Ctrl-C: what Python callers expect
                raise KeyboardInterrupt(str(exc)) from None
            raise
    if algorithm.last_error is not None:
        raise algorithm.last_error
    return algorithm.GetOutputDataObject(0)


def cage_digest(pd) -> str:
    """A digest of a cage surface's points and triangles: its content, not its identity.

    A reader that re-runs gives the same digest for the same cage (no re-solve), and MPI
    ranks holding the same cage agree on it (the identity and modification time of the
    arrays differ between processes).
    """
    h = hashlib.blake2b(digest_size=16)
    h.update(ns.vtk_to_numpy(pd.GetPoints().GetData()).astype(np.float64).tobytes())
    polys = pd.GetPolys()
    if polys is not None and polys.GetNumberOfCells():
        h.update(ns.vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64).tobytes())
        h.update(ns.vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64).tobytes())
    return h.hexdigest()


def set_field_counts(data, name: str, values) -> None:
    """The field array ``name`` of ``data``: counts, as 64-bit integers of a fixed width.

    A ``vtkTypeInt64Array``, which legacy ``.vtk`` files call ``vtktypeint64``: numpy's
    int64 would become a ``vtkLongArray``, which they call ``long``, a type as wide as the
    platform's C ``long`` (4 bytes on Windows, so the rest of the file is misread there)
    and one that other readers of the format (meshio) refuse.
    """
    counts = ns.numpy_to_vtk(
        np.asarray(values, dtype=np.int64).reshape(-1), deep=1, array_type=VTK_LONG_LONG
    )
    counts.SetName(name)
    data.GetFieldData().RemoveArray(name)
    data.GetFieldData().AddArray(counts)


def add_lattice_counts(out, vol) -> None:
    """Field array ``vhm_lattice_evaluations`` of the volume's lattice build.

    The exact evaluations made by this process, and the distinct points they were
    shared among: the same two numbers without MPI; under MPI each rank's piece has
    its own share.
    """
    exchange = vol.exchange
    n = int(vol.lattice.stats["evaluations"])
    here, among = (n, n) if exchange is None else (exchange.evaluated, exchange.distinct)
    set_field_counts(out, "vhm_lattice_evaluations", [here, among])
