"""The filters' base class: VTK ports and reporting around a deformation's map.

:class:`DeformationSource` is what every vhm_viz filter is: input port 0 the data, an
optional port 1 the cage (``vtkPolyData``), one output. It converts at the VTK edge --
the port-1 cage into a :class:`~vhm_viz.Cage`, the data into point arrays or an image
grid (:mod:`vhm_viz.filters._vtk`) -- and takes its map from a
:class:`~vhm_viz.filters._map_source.MapSource`, set in one of three ways:

* :meth:`DeformationSource.SetDeformer` -- a :class:`~vhm_viz.Deformer` with constraints
  (solved on first use if it never was);
* :meth:`DeformationSource.SetScene` -- a :class:`~vhm_viz.scene.Scene` (or the path of a
  scene file), or :meth:`DeformationSource.SetSceneFile`, solved by the filter through
  :meth:`Scene.solve_map <vhm_viz.scene.Scene.solve_map>`;
* :meth:`DeformationSource.SetHarmonicMap` -- a fixed :class:`~vhm_viz.HarmonicMap`.

Input port 1, when connected, *is* the cage (see :mod:`vhm_viz.filters._map_source`).
The whole cage is requested in every piece (as ``vtkProbeFilter`` does for its source),
so the filters stream and run piece-wise. The binding of the points and the volume engine
are kept between updates (:mod:`vhm_viz.filters._engines`).
"""

from __future__ import annotations

import warnings

import numpy as np
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonCore import vtkOutputWindow
from vtkmodules.vtkCommonDataModel import vtkDataObject, vtkPolyData
from vtkmodules.vtkCommonExecutionModel import vtkAlgorithm

from vhm_viz import interrupts
from vhm_viz.core.basis import DEFAULT_MEMORY_BUDGET
from vhm_viz.core.binding import check_outside_policy
from vhm_viz.core.devices import require_device
from vhm_viz.core.errors import AbortedError
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.limits import check_setting
from vhm_viz.core.volume import DEFAULT_TOLERANCE, check_tolerance
from vhm_viz.filters import mpi
from vhm_viz.filters._engines import BindingCache, VolumeEngineCache
from vhm_viz.filters._map_source import MapSource
from vhm_viz.filters._vtk import _SDDP, cage_digest, geometry_key
from vhm_viz.filters._vtk import image_geometry as image_geometry  # re-exported (explorer)
from vhm_viz.io import cage_from_dataset, cage_to_polydata

__all__ = ["DeformationSource"]


class DeformationSource(VTKPythonAlgorithmBase):
    """Base class: input port 0 any dataset, optional port 1 the cage, one output.

    Subclasses implement ``_execute(in_info, out_info)``; they call :meth:`_resolve` to
    obtain the current ``(harmonic_map, deformer_or_None)`` and :meth:`_bind` /
    :meth:`_volume` for the kept binding or volume engine.
    """

    def __init__(self, input_type: str = "vtkDataSet", output_type: str = "vtkDataSet"):
        VTKPythonAlgorithmBase.__init__(
            self, nInputPorts=2, inputType=input_type, nOutputPorts=1, outputType=output_type
        )
        self._input_type = input_type
        self._source = MapSource()
        self._bindings = BindingCache()
        self._volumes = VolumeEngineCache()
        self._port_cage = None  # (digest, Cage) of the last cage on port 1
        self._outside = "error"
        self._memory_budget = None
        self._tolerance = DEFAULT_TOLERANCE
        self._device = "cpu"
        self._parallel_reporting = False
        self._allow_unconverged = False
        self._warned_report = None
        self.last_error: Exception | None = None
        #: Points outside the cage in the last update (with a policy that lets them through).
        self.outside_count = 0
        self._solve_warnings: list = []  # an unconverged solve let through
        self._output_warnings: list = []  # what the last update's output holds (folds)
        self._composite = None  # (class, block addresses, address, MTime) of a composite input
        self._composite_said = None  # the composite input last refused (said once)

    @property
    def warnings(self) -> list:
        """What the last update produced that is not what was asked for: one line each.

        An unconverged solve let through (:meth:`SetAllowUnconverged`), a resampled
        volume with voxels in folds. Each is also said once as a Python warning or, in
        ParaView, in VTK's output window.
        """
        return [*self._solve_warnings, *self._output_warnings]

    @property
    def bind_count(self) -> int:
        """Number of times the binding was (re)built."""
        return self._bindings.count

    @property
    def solve_reports(self) -> list:
        """Solve reports of the solves run by the filter (scene or unsolved deformer)."""
        return self._source.solve_reports

    @property
    def volume_engine(self):
        """The volume engine of the last update of an image, or None.

        A :class:`~vhm_viz.core.volume.VolumeDeformation`.
        """
        return self._volumes.engine

    # ------------------------------------------------------------------ pipeline ports
    def ProcessRequest(self, request, in_info, out_info):
        """VTK's dispatch of a request to the ``Request*`` methods, which keep their errors.

        An exception raised between them -- a signal's :class:`~vhm_viz.interrupts.
        Interrupted` arrives at any instruction -- is kept in :attr:`last_error` as theirs
        are (``update`` raises it), not printed by VTK as a traceback.
        """
        try:
            self._note_composite(in_info)
            return VTKPythonAlgorithmBase.ProcessRequest(self, request, in_info, out_info)
        except BaseException as exc:  # noqa: BLE001 -- handed back by update()
            self.last_error = exc
            return 0

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
        reached all of them, and afterwards that all of them succeeded; an error on any
        rank becomes every rank's :attr:`last_error` (the first failing rank's line), is
        shown once as one line in VTK's output window and leaves an empty output on every
        rank (no stale data, no traceback, no rank left waiting).
        """
        self._forget_output()
        if not self._parallel_reporting:
            return self._guard(self._execute, in_info, out_info)
        if self._mpi() and self._composite_input() is not None:
            return self._refuse_composite(out_info)
        self.last_error = None
        try:
            self._check_cage_on_every_rank(in_info)
        except Exception as exc:  # noqa: BLE001 -- reported below, like any other error
            self.last_error = exc
        if self.last_error is None:
            self._guard(self._execute, in_info, out_info)
        failed_here = self.last_error is not None and not isinstance(self.last_error, AbortedError)
        everyone_ok = mpi.all_ranks(not failed_here)
        if not everyone_ok:
            self._agree_on_error(failed_here)
            out = out_info.GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT())
            if out is not None:
                out.Initialize()
        elif mpi.process_count() > 1:
            self._guard(self._agree_on_output, out_info)
        return 1

    def _forget_output(self) -> None:
        """Drop what described the last update's output (its warnings).

        An update that fails, on any rank, before or during its work, leaves no output
        to describe.
        """
        self._output_warnings = []

    def _note_composite(self, in_info) -> None:
        """Keep which composite data set (multiblock, AMR ...) feeds port 0, if one does.

        VTK's pipeline passes a composite input's blocks to a filter of data sets one at a
        time: every request then sees a block, and only the requests before them the
        composite. Its blocks are kept (their addresses) until a request sees data that
        is neither it nor one of them.
        """
        port = in_info[0] if in_info else None
        if port is None or not port.GetNumberOfInformationObjects():
            return
        data = port.GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT())
        if data is None:
            return
        if data.IsA("vtkCompositeDataSet"):
            blocks, it = set(), data.NewIterator()
            it.InitTraversal()
            while not it.IsDoneWithTraversal():
                if it.GetCurrentDataObject() is not None:
                    blocks.add(it.GetCurrentDataObject().__this__)
                it.GoToNextItem()
            self._composite = (data.GetClassName(), blocks, data.__this__, data.GetMTime())
        elif self._composite is not None and data.__this__ not in self._composite[1]:
            self._composite = None

    def _composite_input(self) -> str | None:
        """The class of the composite data set whose blocks port 0 now gets, else None.

        VTK's pipeline runs ``RequestData`` once per block, and MPI ranks hold different
        numbers of blocks.
        """
        return None if self._composite is None else self._composite[0]

    def _refuse_composite(self, out_info) -> int:
        """Under MPI, composite input: an error, said once, with no collective operation.

        Every rank runs one request per block it holds, and the numbers differ between
        ranks: the ranks' agreement (collective) would pair different blocks or wait for a
        rank that has none left. Every rank takes the same decision from the input's type
        alone, so none waits for another.
        """
        self.last_error = ValueError(
            f"{self._composite_input()} input is not supported on several MPI ranks (each "
            "rank runs the filter once per block it holds): apply Merge Blocks first"
        )
        key = self._composite[2:]
        if mpi.rank() == 0 and self._composite_said != key:
            self._composite_said = key
            vtkOutputWindow.GetInstance().DisplayErrorText(
                f"{self._label()}: {_one_line(self.last_error)}\n"
            )
        out = out_info.GetInformationObject(0).Get(vtkDataObject.DATA_OBJECT())
        if out is not None:
            out.Initialize()
        return 1

    def _agree_on_output(self, out_info) -> None:
        """Under MPI, once every rank succeeded: what describes the whole output, agreed.

        Collective (every rank calls it). Filters whose field arrays count the whole
        output (not a rank's piece) gather the ranks' counts here.
        """

    def _agree_on_error(self, failed_here: bool) -> None:
        """Give every rank the same error: the first failing rank's, said once (collective).

        Every rank ends the request with that one line in :attr:`last_error` (the
        failing rank its own exception, the others a RuntimeError of the same text);
        rank 0 shows it in VTK's output window, naming the failing rank unless every rank
        failed (the same mistake everywhere: no scene, a bad file).
        """
        everyone_failed = not mpi.any_rank(not failed_here)
        text = _one_line(self.last_error) if failed_here else ""
        codes = np.frombuffer(text.encode("utf-8", "replace")[:2000], dtype=np.uint8)
        rows = np.column_stack([np.full(len(codes), mpi.rank()), codes])
        got = mpi.gather_rows(rows, 2) if mpi.process_count() > 1 else rows
        first = int(got[:, 0].min())
        agreed = bytes(got[got[:, 0] == first, 1].astype(np.uint8)).decode("utf-8", "replace")
        if text != agreed:
            self.last_error = RuntimeError(agreed)
        if mpi.rank() == 0:
            where = "" if everyone_failed else f" (rank {first})"
            vtkOutputWindow.GetInstance().DisplayErrorText(f"{self._label()}{where}: {agreed}\n")

    def SetParallelReporting(self, value: bool) -> None:
        """Report errors in VTK's output window and agree on them across MPI ranks.

        For ParaView (its plugin sets this), where every rank runs every update: then the
        filter may meet the other ranks in collective operations at fixed points of
        ``RequestData``. Leave it off in scripts whose ranks do not update together.
        """
        self._set_option("_parallel_reporting", bool(value))

    def _set_option(self, name: str, value) -> None:
        """Set the attribute ``name`` to ``value``, marking the filter modified if it changed.

        VTK's ``vtkSetMacro`` convention: setting the value a filter already has leaves
        its next update a no-op.
        """
        if getattr(self, name) != value:
            setattr(self, name, value)
            self.Modified()

    def _label(self) -> str:
        return type(self).__name__

    def _check_cage_on_every_rank(self, in_info) -> None:
        """A cage on port 1 must reach every rank whole; never fall back silently."""
        connected = bool(self.GetNumberOfInputConnections(1))
        pd = vtkPolyData.GetData(in_info[1]) if connected else None
        mpi.check_whole_cage(connected, 0 if pd is None else pd.GetNumberOfPoints())

    def _execute(self, in_info, out_info):  # pragma: no cover - every filter defines it
        raise NotImplementedError

    def _request_whole_cage(self, in_info) -> None:
        if self.GetNumberOfInputConnections(1):
            info = in_info[1].GetInformationObject(0)
            info.Set(_SDDP.UPDATE_PIECE_NUMBER(), 0)
            info.Set(_SDDP.UPDATE_NUMBER_OF_PIECES(), 1)
            info.Set(_SDDP.UPDATE_NUMBER_OF_GHOST_LEVELS(), 0)

    # ------------------------------------------------------------------ the deformation
    def SetDeformer(self, deformer) -> None:
        """Use this deformer (with constraints set); solved on first use if it never was."""
        self._source.set_deformer(deformer)
        self.Modified()

    def GetDeformer(self):
        """The deformer in use (the one set, or the one built from a scene / port-1 cage)."""
        return self._source.deformer

    def SetScene(self, scene) -> None:
        """Use a scene (a :class:`~vhm_viz.scene.Scene` or the path of a scene file)."""
        self._source.set_scene(scene)
        self.Modified()

    def GetScene(self):
        """The scene set with :meth:`SetScene` or read from the scene file (or None)."""
        return self._source.scene

    def SetSceneFile(self, path: str) -> None:
        """Use the scene in a JSON file; re-read when the file changes ("" for none).

        The ParaView property: the file is read at the next update, and again whenever its
        content changes, so editing the scene and re-applying works. It replaces any
        deformation set before.
        """
        if self._source.set_scene_file(path):
            self.Modified()

    def GetSceneFile(self) -> str:
        """The scene file set with :meth:`SetSceneFile` ("" for none)."""
        return self._source.scene_file

    def SetHarmonicMap(self, harmonic_map) -> None:
        """Use a fixed harmonic map (no solver)."""
        self._source.set_harmonic_map(harmonic_map)
        self.Modified()

    def SetDeformation(self, deformation) -> None:
        """Set a Deformer, HarmonicMap, Scene or scene-file path, whichever it is."""
        if hasattr(deformation, "bind"):
            self.SetDeformer(deformation)
        elif hasattr(deformation, "jacobian") and hasattr(deformation, "coefficients"):
            self.SetHarmonicMap(deformation)
        else:
            self.SetScene(deformation)

    def SetSolverSettings(self, **settings) -> None:
        """Keyword arguments for :meth:`Deformer.solve` used when the filter solves."""
        self._source.solver = dict(settings)
        self.Modified()

    def UpdateTargets(self, targets=None, jacobians=None, *, solve: bool = True):
        """Move the constraint targets of the current deformer (and re-solve).

        Only the targets change, so the next update re-uses the kept binding.

        Returns
        -------
        SolveReport or None
        """
        report = self._source.update_targets(targets, jacobians, solve=solve)
        self.Modified()
        return report

    # ------------------------------------------------------------------ settings
    def SetOutsidePolicy(self, policy: str) -> None:
        """``"error"`` (default), ``"passthrough"`` or ``"nan"``.

        Points outside the cage make the update fail with an
        :class:`~vhm_viz.OutsideCageError` naming them; or they stay where they are
        (``"passthrough"``) or become NaN (``"nan"``), flagged by the point array
        ``vhm_outside`` and counted in :attr:`outside_count`.
        """
        self._set_option("_outside", check_outside_policy(policy))

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
        self._set_option("_allow_unconverged", bool(allow))

    def GetAllowUnconverged(self) -> bool:
        """Whether an unconverged solve is let through (with a warning)."""
        return self._allow_unconverged

    def _check_converged(self, report) -> None:
        """Refuse (or, if allowed, warn about) a map from an unconverged solve."""
        if report is None or report.converged:
            self._solve_warnings, self._warned_report = [], None
            return
        if not self._allow_unconverged:
            raise RuntimeError(
                f"not converged: {report.shortfall()}; no output (raise the scene's "
                "solver.max_iterations, or allow unconverged solves: AllowUnconverged)"
            )
        if report is not self._warned_report:  # said once per solve, not per pass
            self._warned_report = report
            text = f"deforming with an unconverged solve: {report.shortfall()}"
            self._solve_warnings = [text]
            self._say_warning(text, UserWarning)

    def _say_warning(self, text: str, category) -> None:
        """Say a warning once: a Python warning, or in ParaView VTK's output window.

        Under MPI, on rank 0 only: the ranks call it with the same (agreed) text.
        """
        if not self._parallel_reporting:
            warnings.warn(text, category, stacklevel=3)
        elif mpi.rank() == 0:
            vtkOutputWindow.GetInstance().DisplayWarningText(f"{self._label()}: {text}\n")

    def SetDevice(self, device: str) -> None:
        """Where a volume's exact map evaluations run: ``"cpu"`` (default) or ``"cuda"``.

        ``"cuda"`` needs an NVIDIA GPU (see :mod:`vhm_viz.core.devices`); the results are
        the same to rounding.
        """
        self._set_option("_device", require_device(device))

    def SetMemoryBudget(self, nbytes: int | None) -> None:
        """Bytes of basis arrays per chunk while binding, in [1, 2**40] (None: the default).

        Smaller budgets mean more, smaller chunks (finer progress and abort), never a
        different result. An explicit budget is per process; the default is divided among
        the MPI ranks that share a machine.
        """
        if nbytes is not None:
            nbytes = check_setting("memory_budget", nbytes)
        self._set_option("_memory_budget", nbytes)

    def _budget(self) -> int | None:
        """The working-memory budget of this process.

        An explicit :meth:`SetMemoryBudget` is per process. The default is per machine:
        MPI ranks sharing one (ParaView's ``mpiexec -n N pvbatch``) divide it, so that N
        ranks work in the memory one process would.
        """
        if self._memory_budget is not None:
            return self._memory_budget
        shared = mpi.ranks_on_this_machine() if self._parallel_reporting else 1
        return None if shared <= 1 else max(DEFAULT_MEMORY_BUDGET // shared, 1 << 20)

    def SetTolerance(self, voxels: float) -> None:
        """Volumes: largest position error of a mapped voxel, in voxels.

        Default :data:`vhm_viz.core.volume.DEFAULT_TOLERANCE`. Image inputs go through the
        lattice of :mod:`vhm_viz.core.lattice` (exact map at its nodes, tricubic Hermite
        in between) instead of evaluating every voxel.
        """
        self._set_option("_tolerance", check_tolerance(voxels))

    def GetTolerance(self) -> float:
        """The volume tolerance (voxels)."""
        return self._tolerance

    # ------------------------------------------------------------------ execution helpers
    def _port1_cage(self, in_info):
        """The port-1 cage as ``(Cage, digest)``, or ``(None, None)`` when unconnected."""
        if not self.GetNumberOfInputConnections(1):
            return None, None
        pd = vtkPolyData.GetData(in_info[1])
        if pd is None or pd.GetNumberOfPoints() == 0:
            raise ValueError(
                "the Cage input (port 1) is connected but empty: connect a closed triangle "
                "surface, or disconnect it to use the scene's own cage"
            )
        key = cage_digest(pd)
        if self._port_cage is None or self._port_cage[0] != key:
            self._port_cage = (key, cage_from_dataset(pd))
        return self._port_cage[1], key

    def _resolve(self, in_info, data=None):
        """Return ``(harmonic_map, deformer_or_None)`` for the current settings and inputs."""
        cage, cage_key = self._port1_cage(in_info)
        hm, dfm, report = self._source.resolve(
            cage,
            cage_key,
            data,
            geometry_key(data),
            mpi=mpi.process_count() > 1,
            keep_deformer=not self._parallel_reporting,
        )
        if hm is None:
            if self._parallel_reporting:
                raise RuntimeError("set SceneFile (a vhm_viz scene JSON)")
            raise RuntimeError(
                "no deformation set on the filter: call SetDeformer, SetScene, SetSceneFile "
                "or SetHarmonicMap"
            )
        self._check_converged(report)
        return hm, dfm

    def _bind(self, hm, dfm, data, points, lo: float, hi: float):
        """The binding of ``points`` (N, 3), kept while the deformer and geometry hold.

        With a fixed harmonic map (``dfm`` None) nothing is precomputed; with a deformer the
        binding is rebuilt only when its constraint layout (``n_factorizations``), the
        geometry of ``data``, the outside policy or the memory budget change, so moving
        targets (:meth:`UpdateTargets`) re-uses it.
        """
        binding = self._bindings.get(
            hm,
            dfm,
            points,
            data_key=geometry_key(data),
            outside=self._outside,
            budget=self._budget(),
            progress=self._progress(lo, hi),
            abort=self._aborted,
        )
        self.outside_count = binding.n_outside
        return binding

    def _volume(self, hm, geometry: ImageGeometry, outside: str, window=None, pre_images=True):
        """The volume engine of ``hm`` on ``geometry``, kept while nothing changes.

        ``window``: a piece's box of voxels (None: the whole lattice); ``pre_images``
        False: for warping and analysing voxels only (see
        :meth:`~vhm_viz.filters._engines.VolumeEngineCache.get`).
        """
        return self._volumes.get(
            hm,
            geometry,
            tolerance=self._tolerance,
            outside=outside,
            budget=self._budget(),
            window=window,
            pre_images=pre_images,
            exchange=self._lattice_exchange(),
            device=self._device,
        )

    def _mpi(self) -> bool:
        """Whether this update runs on several MPI ranks that agree (ParaView)."""
        return self._parallel_reporting and mpi.process_count() > 1

    def _lattice_exchange(self):
        """A :class:`~vhm_viz.filters.mpi.LatticeExchange` under MPI, else None.

        Under MPI (ParaView) the ranks build their lattices together, each point evaluated
        once: the ranks update in step there.
        """
        if self._mpi():
            return mpi.LatticeExchange()
        return None

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


def _one_line(error: BaseException) -> str:
    """An error's first line (its type's name when it has no message)."""
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__
