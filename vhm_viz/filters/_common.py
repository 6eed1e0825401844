"""What the VTK filters share: where the deformation comes from, VTK/numpy helpers.

A filter's deformation is set on the filter in one of three ways:

* :meth:`DeformationSource.SetDeformer` -- a :class:`~vhm_viz.Deformer` with constraints
  (solved on first use if it never was);
* :meth:`DeformationSource.SetScene` -- a :class:`~vhm_viz.scene.Scene` (or the path of a
  scene file), built and solved by the filter;
* :meth:`DeformationSource.SetHarmonicMap` -- a fixed :class:`~vhm_viz.HarmonicMap`.

Input port 1 (optional) takes the cage as ``vtkPolyData``. When it is connected it *is*
the cage: a deformer or scene whose cage differs is rebuilt on it with the same anchors,
constraints, mode and alpha (and re-solved); a fixed harmonic map cannot be moved to
another cage, so a mismatch is an error. When it is not connected, the deformation's own
cage is used. The whole cage is requested in every piece (as ``vtkProbeFilter`` does for
its source), so the filters stream and run piece-wise.
"""

from __future__ import annotations

import signal
import warnings

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonCore import vtkObject
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkPolyData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm, vtkStreamingDemandDrivenPipeline

from vhm_viz import interrupts
from vhm_viz.core.basis import DEFAULT_MEMORY_BUDGET
from vhm_viz.core.binding import bind_map, check_outside_policy
from vhm_viz.core.errors import AbortedError
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.limits import check_setting
from vhm_viz.core.memory import release_free_memory
from vhm_viz.core.volume import DEFAULT_TOLERANCE, VolumeDeformation
from vhm_viz.filters import _parallel

__all__ = [
    "DeformationSource",
    "update",
    "numpy_points",
    "geometry_key",
    "image_geometry",
    "information_geometry",
    "requested_extent",
]

_SDDP = vtkStreamingDemandDrivenPipeline
# Relative tolerance (of the cage diagonal) for "the port-1 cage is the deformer's cage".
_CAGE_TOL = 1e-9


def numpy_points(ds) -> np.ndarray:
    """Points of any vtkDataSet as a (N, 3) float64 array (a copy for implicit points)."""
    pts = ds.GetPoints() if hasattr(ds, "GetPoints") else None
    if pts is not None and pts.GetData() is not None:
        return np.asarray(ns.vtk_to_numpy(pts.GetData()), dtype=np.float64).reshape(-1, 3)
    n = ds.GetNumberOfPoints()
    out = np.empty((n, 3))
    p = [0.0, 0.0, 0.0]
    for i in range(n):  # only reached for exotic datasets; image/rectilinear are converted
        ds.GetPoint(i, p)
        out[i] = p
    return out


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
    from vtkmodules.vtkCommonDataModel import vtkImageData

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
        from vtkmodules.vtkCommonExecutionModel import vtkExtentTranslator

        piece = info.Get(_SDDP.UPDATE_PIECE_NUMBER()) or 0
        tr = vtkExtentTranslator()
        ext = [0] * 6
        tr.PieceToExtentThreadSafe(piece, n, 0, whole, ext, tr.BLOCK_MODE, 0)
    return None if ext is None else tuple(int(v) for v in ext)


def _map_key(hm) -> tuple:
    """Changes when the map (its cage or coefficients) changes."""
    cage = hm.cage
    return (
        hash(np.asarray(cage.vertices).tobytes()),
        hash(np.asarray(cage.faces).tobytes()),
        hash(np.asarray(hm.coefficients).tobytes()),
    )


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


def _cage_from_polydata(pd):
    from vhm_viz.io import cage_from_dataset

    return cage_from_dataset(pd)


def _cage_digest(pd) -> str:
    """A digest of a cage surface's points and triangles: its content, not its identity.

    A reader that re-runs gives the same digest for the same cage (no re-solve), and MPI
    ranks holding the same cage agree on it (the identity and modification time of the
    arrays differ between processes).
    """
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    h.update(ns.vtk_to_numpy(pd.GetPoints().GetData()).astype(np.float64).tobytes())
    polys = pd.GetPolys()
    if polys is not None and polys.GetNumberOfCells():
        h.update(ns.vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64).tobytes())
        h.update(ns.vtk_to_numpy(polys.GetOffsetsArray()).astype(np.int64).tobytes())
    return h.hexdigest()


def _same_cage(a, b) -> bool:
    va, vb = np.asarray(a.vertices), np.asarray(b.vertices)
    if va.shape != vb.shape or np.shape(a.faces) != np.shape(b.faces):
        return False
    if not np.array_equal(np.asarray(a.faces), np.asarray(b.faces)):
        return False
    diag = float(np.linalg.norm(va.max(0) - va.min(0))) or 1.0
    return bool(np.abs(va - vb).max() <= _CAGE_TOL * diag)


class DeformationSource(VTKPythonAlgorithmBase):
    """Base class: input port 0 any dataset, optional port 1 the cage, one output.

    Subclasses implement ``RequestData``; they call :meth:`_resolve` to obtain the current
    ``(harmonic_map, deformer_or_None)`` and wrap their work in :meth:`_guard`.
    """

    def __init__(self, input_type: str = "vtkDataSet", output_type: str = "vtkDataSet"):
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=2, inputType=input_type, nOutputPorts=1, outputType=output_type
        )
        self._input_type = input_type
        self._deformer = None
        self._user_deformer = None
        self._scene = None
        self._hmap = None
        self._solved_map = None  # a solved scene's map, when its deformer is not kept
        self._outside = "error"
        self._solver: dict = {}
        self._derived_key = None
        self._memory_budget = None
        self._tolerance = DEFAULT_TOLERANCE
        self._volume_engine = None
        self._volume_key = None
        self._binding = None
        self._binding_key = None
        self._scene_file = ""
        self._scene_stamp = None
        self._parallel_reporting = False
        self.last_error: Exception | None = None
        #: Points outside the cage in the last update (with a policy that lets them through).
        self.outside_count = 0
        #: Number of times the binding was (re)built.
        self.bind_count = 0
        #: Solve reports of solves run by the filter (scene or unsolved deformer).
        self.solve_reports: list = []
        self._allow_unconverged = False
        # the last solve this filter ran itself (for a scene, an unsolved deformer, or
        # UpdateTargets): what _check_converged looks at. A deformer its caller solved
        # comes with that caller's own report
        self._map_report = None
        #: What the last update produced that is not what was asked for (an unconverged
        #: solve let through): one line each, also shown in VTK's output window.
        self.warnings: list = []
        self._warned_report = None

    # ------------------------------------------------------------------ pipeline ports
    def FillInputPortInformation(self, port, info):
        """Port 0: ``input_type``; port 1: an optional ``vtkPolyData`` cage."""
        if port == 0:
            info.Set(vtkAlgorithm.INPUT_REQUIRED_DATA_TYPE(), self._input_type)
        else:
            info.Set(vtkAlgorithm.INPUT_REQUIRED_DATA_TYPE(), "vtkPolyData")
            info.Set(vtkAlgorithm.INPUT_IS_OPTIONAL(), 1)
        return 1

    def SetInputData(self, data) -> None:
        """Set the data to deform (port 0) directly, without a pipeline connection."""
        self.SetInputDataObject(0, data)

    def SetCageData(self, cage) -> None:
        """Connect a cage (``vtkPolyData``, PyVista PolyData or :class:`~vhm_viz.Cage`)."""
        if not isinstance(cage, vtkPolyData) and hasattr(cage, "face_normals"):
            from vhm_viz.io import cage_to_polydata

            cage = cage_to_polydata(cage)
        self.SetInputDataObject(1, cage)

    def SetCageConnection(self, port) -> None:
        """Connect the cage from another algorithm's output port."""
        self.SetInputConnection(1, port)

    def RequestInformation(self, request, in_info, out_info):
        """Structured outputs (of image and structured inputs) are made piece by piece."""
        if in_info[0].GetInformationObject(0).Has(_SDDP.WHOLE_EXTENT()):
            out_info.GetInformationObject(0).Set(vtkAlgorithm.CAN_PRODUCE_SUB_EXTENT(), 1)
        return 1

    def RequestUpdateExtent(self, request, in_info, out_info):
        """Forward the piece request on port 0; ask for the whole cage on port 1."""
        self._request_whole_cage(in_info)
        return 1

    def RequestData(self, request, in_info, out_info):
        """Run the filter's ``_execute``; errors end up in :attr:`last_error` (see ``update``).

        With :meth:`SetParallelReporting` (ParaView), the ranks first agree that the cage
        reached all of them, and afterwards that all of them succeeded; an error is shown
        once per failing rank as one line in VTK's output window and leaves an empty output
        on every rank (no stale data, no traceback).
        """
        if not self._parallel_reporting:
            return self._guard(self._execute, in_info, out_info)
        self.last_error = None
        try:
            self._check_cage_on_every_rank(in_info)
        except Exception as exc:  # noqa: BLE001 -- reported below, like any other error
            self.last_error = exc
        if self.last_error is None:
            self._guard(self._execute, in_info, out_info)
        failed_here = self.last_error is not None and not isinstance(
            self.last_error, AbortedError
        )
        everyone_ok = _parallel.all_ranks(not failed_here)
        everyone_failed = not _parallel.any_rank(not failed_here)
        # the same mistake everywhere (no scene, a bad file) is said once, by rank 0
        if failed_here and (not everyone_failed or _parallel.rank() == 0):
            self._report(self.last_error)
        if not everyone_ok:
            out = out_info.GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT())
            if out is not None:
                out.Initialize()
        return 1

    def SetParallelReporting(self, value: bool) -> None:
        """Report errors in VTK's output window and agree on them across MPI ranks.

        For ParaView (its plugin sets this), where every rank runs every update: then the
        filter may meet the other ranks in collective operations at fixed points of
        ``RequestData``. Leave it off in scripts whose ranks do not update together.
        """
        self._parallel_reporting = bool(value)
        self.Modified()

    def _report(self, error: Exception) -> None:
        from vtkmodules.vtkCommonCore import vtkOutputWindow

        text = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        where = f" (rank {_parallel.rank()})" if _parallel.process_count() > 1 else ""
        vtkOutputWindow.GetInstance().DisplayErrorText(f"{self._label()}{where}: {text}\n")

    def _label(self) -> str:
        return type(self).__name__

    def _check_cage_on_every_rank(self, in_info) -> None:
        """A cage on port 1 must reach every rank whole; never fall back silently."""
        n = 0
        if self.GetNumberOfInputConnections(1):
            pd = vtkPolyData.GetData(in_info[1])
            n = 0 if pd is None else pd.GetNumberOfPoints()
        lo, hi = _parallel.min_max_over_ranks(n)
        if self.GetNumberOfInputConnections(1) and lo != hi:
            raise RuntimeError(
                f"the Cage input reached the ranks with {lo} to {hi} points: every rank needs "
                "the whole cage (read it with a reader that every rank runs, and do not "
                "distribute it)"
            )

    def _execute(self, in_info, out_info):  # pragma: no cover - every filter defines it
        raise NotImplementedError

    def _request_whole_cage(self, in_info) -> None:
        if self.GetNumberOfInputConnections(1):
            info = in_info[1].GetInformationObject(0)
            info.Set(_SDDP.UPDATE_PIECE_NUMBER(), 0)
            info.Set(_SDDP.UPDATE_NUMBER_OF_PIECES(), 1)
            info.Set(_SDDP.UPDATE_NUMBER_OF_GHOST_LEVELS(), 0)

    # ------------------------------------------------------------------ settings
    def SetDeformer(self, deformer) -> None:
        """Use this deformer (with constraints set); solved on first use if it never was."""
        if deformer is not None and not hasattr(deformer, "bind"):
            raise TypeError(f"SetDeformer needs a vhm_viz Deformer; got {type(deformer).__name__}")
        self._user_deformer = deformer
        self._deformer = deformer
        self._scene = None
        self._scene_file, self._scene_stamp = "", None
        self._hmap = None
        self._derived_key = None
        self.Modified()

    def GetDeformer(self):
        """The deformer in use (the one set, or the one built from a scene / port-1 cage)."""
        return self._deformer

    def SetScene(self, scene) -> None:
        """Use a scene (a :class:`~vhm_viz.scene.Scene` or the path of a scene file)."""
        from vhm_viz.scene import Scene

        if scene is not None and not isinstance(scene, Scene):
            scene = Scene.load(scene)
        self._scene = scene
        self._scene_file, self._scene_stamp = "", None
        self._user_deformer = None
        self._deformer = None
        self._hmap = None
        self._derived_key = None
        self.Modified()

    def GetScene(self):
        """The scene set with :meth:`SetScene` (or None)."""
        return self._scene

    def SetSceneFile(self, path: str) -> None:
        """Use the scene in a JSON file; re-read when the file changes ("" for none).

        The ParaView property: the file is read at the next update, and again whenever its
        content changes, so editing the scene and re-applying works.
        """
        path = "" if path is None else str(path)
        if path != self._scene_file:
            # the file replaces any deformation set before (and "" leaves none: no stale
            # result from the previous scene)
            self._scene = self._user_deformer = self._deformer = self._hmap = None
            self._derived_key = None
            self._scene_file = path
            self._scene_stamp = None
            self.Modified()

    def GetSceneFile(self) -> str:
        """The scene file set with :meth:`SetSceneFile` ("" for none)."""
        return self._scene_file

    def _load_scene_file(self) -> None:
        import hashlib

        from vhm_viz.scene import Scene

        if not self._scene_file:
            return
        try:
            with open(self._scene_file, "rb") as fh:
                text = fh.read()
        except OSError:
            raise FileNotFoundError(f"no such scene file: {self._scene_file}") from None
        # by content: a rewrite of the same size within one tick of the file system's
        # clock (a script writing scenes in turn) keeps its modification time and size
        stamp = (self._scene_file, hashlib.sha256(text).hexdigest())
        if stamp != self._scene_stamp:
            self._scene = Scene.load(self._scene_file)
            self._user_deformer = self._deformer = self._hmap = None
            self._derived_key = None
            self._scene_stamp = stamp

    def SetHarmonicMap(self, harmonic_map) -> None:
        """Use a fixed harmonic map (no solver)."""
        if harmonic_map is not None and not hasattr(harmonic_map, "evaluate"):
            raise TypeError(
                f"SetHarmonicMap needs a vhm_viz HarmonicMap; got {type(harmonic_map).__name__}"
            )
        self._hmap = harmonic_map
        self._user_deformer = None
        self._deformer = None
        self._scene = None
        self._scene_file, self._scene_stamp = "", None
        self._derived_key = None
        self.Modified()

    def SetDeformation(self, deformation) -> None:
        """Set a Deformer, HarmonicMap, Scene or scene-file path, whichever it is."""
        if hasattr(deformation, "bind"):
            self.SetDeformer(deformation)
        elif hasattr(deformation, "jacobian") and hasattr(deformation, "coefficients"):
            self.SetHarmonicMap(deformation)
        else:
            self.SetScene(deformation)

    def SetOutsidePolicy(self, policy: str) -> None:
        """``"error"`` (default), ``"passthrough"`` or ``"nan"``.

        Points outside the cage make the update fail with an
        :class:`~vhm_viz.OutsideCageError` naming them; or they stay where they are
        (``"passthrough"``) or become NaN (``"nan"``), flagged by the point array
        ``vhm_outside`` and counted in :attr:`outside_count`.
        """
        policy = check_outside_policy(policy)
        if policy != self._outside:
            self._outside = policy
            self.Modified()

    def GetOutsidePolicy(self) -> str:
        """The outside policy."""
        return self._outside

    def SetAllowUnconverged(self, allow: bool) -> None:
        """Deform with a solve that stopped at its iteration cap (default: refuse).

        By default an update whose deformation comes from a solve the filter ran (a
        scene's, an unsolved deformer's, :meth:`UpdateTargets`) that did not converge
        fails, naming how far the solve stopped from its tolerance; allowed, it runs and
        says so in :attr:`warnings` (a ``UserWarning``; in ParaView, its output window).
        A deformer solved by the caller is taken as it is: its report went to the caller.
        """
        if bool(allow) != self._allow_unconverged:
            self._allow_unconverged = bool(allow)
            self.Modified()

    def GetAllowUnconverged(self) -> bool:
        """Whether an unconverged solve is let through (with a warning)."""
        return self._allow_unconverged

    def _check_converged(self, report) -> None:
        """Refuse (or, if allowed, warn about) a map from an unconverged solve."""
        if report is None or report.converged:
            self.warnings, self._warned_report = [], None
            return
        if not self._allow_unconverged:
            raise RuntimeError(
                f"not converged: {report.shortfall()}; no output (raise the scene's "
                "solver.max_iterations, or allow unconverged solves: AllowUnconverged)"
            )
        if report is not self._warned_report:  # said once per solve, not per pass
            self._warned_report = report
            text = f"deforming with an unconverged solve: {report.shortfall()}"
            self.warnings = [text]
            if not self._parallel_reporting:
                warnings.warn(text, UserWarning, stacklevel=2)
            elif _parallel.rank() == 0:  # the same solve on every rank: said once
                from vtkmodules.vtkCommonCore import vtkOutputWindow

                vtkOutputWindow.GetInstance().DisplayWarningText(f"{self._label()}: {text}\n")

    def SetMemoryBudget(self, nbytes: int | None) -> None:
        """Bytes of basis arrays per chunk while binding, in [1, 2**40] (None: the default).

        Smaller budgets mean more, smaller chunks (finer progress and abort), never a
        different result. An explicit budget is per process; the default is divided among
        the MPI ranks that share a machine.
        """
        if nbytes is not None:
            nbytes = check_setting("memory_budget", nbytes)
        if nbytes != self._memory_budget:
            self._memory_budget = nbytes
            self.Modified()

    def _budget(self) -> int | None:
        """The working-memory budget of this process.

        An explicit :meth:`SetMemoryBudget` is per process. The default is per machine:
        MPI ranks sharing one (ParaView's ``mpiexec -n N pvbatch``) divide it, so that N
        ranks work in the memory one process would.
        """
        if self._memory_budget is not None:
            return self._memory_budget
        shared = _parallel.ranks_on_this_machine() if self._parallel_reporting else 1
        return None if shared <= 1 else max(DEFAULT_MEMORY_BUDGET // shared, 1 << 20)

    def SetTolerance(self, voxels: float) -> None:
        """Volumes: largest position error of a mapped voxel, in voxels (default 0.05).

        Image inputs go through the lattice of :mod:`vhm_viz.core.lattice` (exact map at
        its nodes, tricubic Hermite in between) instead of evaluating every voxel.
        """
        voxels = float(voxels)
        if not (np.isfinite(voxels) and voxels > 0):
            raise ValueError(f"tolerance must be a positive number of voxels; got {voxels}")
        if voxels != self._tolerance:
            self._tolerance = voxels
            self.Modified()

    def GetTolerance(self) -> float:
        """The volume tolerance (voxels)."""
        return self._tolerance

    def SetSolverSettings(self, **settings) -> None:
        """Keyword arguments for :meth:`Deformer.solve` used when the filter solves."""
        self._solver = dict(settings)
        self.Modified()

    def UpdateTargets(self, targets=None, jacobians=None, *, solve: bool = True):
        """Move the constraint targets of the current deformer (and re-solve).

        Only the targets change, so the next update re-uses the cached binding.

        Returns
        -------
        SolveReport or None
        """
        dfm = self._deformer or self._user_deformer
        if dfm is None:
            raise RuntimeError("UpdateTargets needs a deformer: call SetDeformer or SetScene")
        dfm.update_targets(targets=targets, jacobians=jacobians)
        report = None
        if solve:
            report = dfm.solve(**self._solve_kwargs())
            self.solve_reports.append(report)
            self._map_report = report
        self.Modified()
        return report

    # ------------------------------------------------------------------ resolution
    def _solve_kwargs(self) -> dict:
        kw = {"init": "previous"}
        if self._scene is not None:
            kw.update(self._scene.solve_kwargs())
        kw.update(self._solver)
        kw.pop("steps", None)
        return kw

    def _port1_cage(self, in_info):
        if not self.GetNumberOfInputConnections(1):
            return None, None
        pd = vtkPolyData.GetData(in_info[1])
        if pd is None or pd.GetNumberOfPoints() == 0:
            raise ValueError(
                "the Cage input (port 1) is connected but empty: connect a closed triangle "
                "surface, or disconnect it to use the scene's own cage"
            )
        return pd, _cage_digest(pd)

    def _resolve(self, in_info, data=None):
        """Return ``(harmonic_map, deformer_or_None)`` for the current settings and inputs."""
        pd, cage_key = self._port1_cage(in_info)
        self._load_scene_file()
        if self._hmap is not None:
            if pd is not None and not _same_cage(_cage_from_polydata(pd), self._hmap.cage):
                raise ValueError(
                    "the cage on input port 1 differs from the harmonic map's cage; a fixed "
                    "harmonic map cannot be moved to another cage (use a Deformer or a scene)"
                )
            return self._hmap, None
        if self._user_deformer is not None:
            base = self._user_deformer
            key = ("deformer", id(base), cage_key)
            if key != self._derived_key:
                dfm = base
                if pd is not None:
                    cage = _cage_from_polydata(pd)
                    if not _same_cage(cage, base.cage):
                        from vhm_viz.scene import Scene

                        dfm = Scene.from_deformer(base).build(cage=cage)
                self._deformer = dfm
                self._derived_key = key
        elif self._scene is not None:
            key = (
                "scene",
                id(self._scene),
                cage_key,
                geometry_key(data) if self._scene.needs_data else None,
            )
            if key != self._derived_key:
                cage = _cage_from_polydata(pd) if pd is not None else None
                mesh = None
                if self._scene.needs_data and pd is None:
                    if _parallel.process_count() > 1:
                        raise RuntimeError(
                            "the scene's automatic cage or anchors would be computed from "
                            "each rank's own piece of the data: compute them once with "
                            "'vhm-viz cage' / 'vhm-viz anchors' and name the files in the scene"
                        )
                    import pyvista as pv

                    mesh = pv.wrap(data)
                self._deformer = self._solved_map = None  # free the old solver first
                stored = None
                if self._parallel_reporting and not self._solver:
                    # the scene's stored map, while its inputs still hold: no deformer to
                    # build and solve (ParaView keeps none anyway, having no UpdateTargets)
                    if cage is None:
                        cage = self._scene.build_cage(mesh)
                    stored = self._scene.map_for(cage, self._scene.build_anchors(cage, mesh))
                if stored is not None:
                    self._solved_map, self._map_report = stored, None
                    self._derived_key = key
                    return self._solved_map, None
                # otherwise every rank solves the same scene to the same map: tried, rank 0
                # solving alone and handing out the coefficients was no faster on the
                # embryo and 0.1 s slower on the CT head (2 ranks on this 2-core machine)
                dfm = self._scene.build(data=mesh, cage=cage)
                reports = self._scene.solve(dfm, **self._solver)
                self.solve_reports.extend(reports)
                self._map_report = reports[-1]
                if self._parallel_reporting:
                    # ParaView exposes no UpdateTargets, so nothing re-solves this deformer:
                    # keep the map only, not the solver's matrices (50 MB on the embryo's
                    # cage) through the data's own work
                    self._solved_map = dfm.harmonic_map
                else:
                    self._deformer = dfm
                del dfm
                self._derived_key = key
                # the build's transient basis matrices: before the data's own allocations
                release_free_memory()
            if self._deformer is None:
                self._check_converged(self._map_report)
                return self._solved_map, None
        elif self._parallel_reporting:
            raise RuntimeError("set SceneFile (a vhm_viz scene JSON)")
        else:
            raise RuntimeError(
                "no deformation set on the filter: call SetDeformer, SetScene, SetSceneFile "
                "or SetHarmonicMap"
            )
        dfm = self._deformer
        if dfm.last_report is None:
            self._map_report = dfm.solve(**self._solve_kwargs())
            self.solve_reports.append(self._map_report)
        # (a later solve by the caller replaces the filter's: that one is theirs)
        self._check_converged(self._map_report if dfm.last_report is self._map_report else None)
        return dfm.harmonic_map, dfm

    # ------------------------------------------------------------------ execution helpers
    def _bind(self, hm, dfm, data, points, lo: float, hi: float):
        """The binding of ``points``, kept while the deformer's layout and the geometry hold.

        With a fixed harmonic map (``dfm`` None) nothing is precomputed; with a deformer the
        binding is rebuilt only when its constraint layout (``n_factorizations``), the
        geometry of ``data``, the outside policy or the memory budget change, so moving
        targets (:meth:`UpdateTargets`) re-uses it.
        """
        if dfm is None:
            binding = bind_map(hm, points, outside=self._outside, memory_budget=self._budget())
        else:
            key = (
                id(dfm),
                dfm.n_factorizations,
                geometry_key(data),
                self._outside,
                self._budget(),
            )
            if key != self._binding_key or self._binding is None:
                self._binding = None  # free the old F before computing the new one
                self._binding = dfm.bind(
                    points,
                    outside=self._outside,
                    memory_budget=self._budget(),
                    progress=self._progress(lo, hi),
                    abort=self._aborted,
                )
                self._binding_key = key
                self.bind_count += 1
            binding = self._binding
        self.outside_count = binding.n_outside
        return binding

    def _volume(self, hm, geometry: ImageGeometry, outside: str, window=None, pre_images=True):
        """The volume engine of ``hm`` on ``geometry``, kept while nothing changes.

        ``window`` (a box of voxels): a piece's engine, whose lattice covers the piece's
        root cells only (aligned with the whole grid: its voxels get the values the whole
        lattice gives them). None: the whole lattice, shared by the pieces of an update.
        ``pre_images`` False: for warping and analysing voxels only (a faster lattice).
        """
        key = (
            _map_key(hm),
            geometry.key(),
            self._tolerance,
            self._budget(),
            None if window is None else tuple(int(v) for v in window),
            bool(pre_images),
        )
        if self._volume_engine is not None and key == self._volume_key:
            if self._volume_engine.outside != outside:
                # the lattice does not depend on the policy: ParaView pushes properties one
                # by one, each with an information pass, and would otherwise build it again
                self._volume_engine = self._volume_engine.with_outside(outside)
        else:
            self._volume_engine = None  # free the old lattice first
            release_free_memory()
            self._volume_engine = VolumeDeformation(
                hm,
                geometry,
                tolerance=self._tolerance,
                outside=outside,
                memory_budget=self._budget(),
                window=window,
                exchange=self._lattice_exchange(),
                pre_images=pre_images,
            )
            self._volume_key = key
        return self._volume_engine

    def _lattice_exchange(self):
        """A :class:`~vhm_viz.filters._parallel.LatticeExchange` under MPI, else None.

        Under MPI (ParaView) the ranks build their lattices together, each point evaluated
        once: the ranks update in step there.
        """
        if self._parallel_reporting and _parallel.process_count() > 1:
            return _parallel.LatticeExchange()
        return None

    @staticmethod
    def _add_lattice_counts(out, vol) -> None:
        """Field array ``vhm_lattice_evaluations`` of the volume's lattice build.

        The exact evaluations made by this process, and the distinct points they were
        shared among: the same two numbers without MPI; under MPI each rank's piece has
        its own share.
        """
        exchange = vol.exchange
        n = int(vol.lattice.stats["evaluations"])
        here, among = (n, n) if exchange is None else (exchange.evaluated, exchange.distinct)
        counts = ns.numpy_to_vtk(np.array([here, among], dtype=np.int64), deep=1)
        counts.SetName("vhm_lattice_evaluations")
        out.GetFieldData().RemoveArray(counts.GetName())
        out.GetFieldData().AddArray(counts)

    def _progress(self, lo: float, hi: float):
        def cb(fraction, _message=""):
            self.UpdateProgress(lo + (hi - lo) * float(fraction))

        return cb

    def _aborted(self) -> bool:
        """VTK's abort contract (``AbortExecute``), or a pending SIGINT/SIGTERM."""
        if interrupts.pending() is not None:
            return True
        check = getattr(self, "CheckAbort", None)
        if check is not None:
            return bool(check())
        return bool(self.GetAbortExecute())

    def _guard(self, fn, *args) -> int:
        """Run ``fn``; store an exception in :attr:`last_error` and report failure.

        ``BaseException`` is caught too: VTK's Python wrapper would swallow a
        ``KeyboardInterrupt`` raised in here and hand back the untouched output, which a
        caller would then take for the result. :func:`update` re-raises it.
        """
        self.last_error = None
        try:
            return int(fn(*args) or 1)
        except BaseException as exc:  # noqa: BLE001 -- handed back by update()
            self.last_error = exc
            return 1 if isinstance(exc, AbortedError) else 0
