"""Helpers shared by the subcommands (options, input and output checks, solving, reports).

VTK and PyVista are imported where they are used: ``vhm-viz --help`` imports every
subcommand's module and stays quick.
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from vhm_viz import interrupts
from vhm_viz.atomic import require_writable
from vhm_viz.cli import one_line
from vhm_viz.core.errors import FoldWarning, OutsideCageError, describe_indices
from vhm_viz.core.metrics import rigidity_distortion, volume_change
from vhm_viz.io import DATASET_SUFFIXES, OverwriteError, refuse_inputs, suffix_of
from vhm_viz.io.dicom import is_dicom_file
from vhm_viz.scene import Scene, SolvedMap


class CLIError(ValueError):
    """An error reported as one line (the message) with a non-zero exit status."""


class FoldedOutput(CLIError):
    """The output folds the data and folds were not allowed: nothing was written."""

    #: The exit status (see :mod:`vhm_viz.cli`).
    exit_status = 4


class Progress:
    """Progress on stderr: a bar on a terminal, plain lines elsewhere.

    On a terminal, one line redrawn in place (``label [#####.....]  50%``, carriage
    returns). When the stream is not a terminal (a pipe, a log file, CI), a plain line
    every :attr:`LOG_STEP` percent (``label:  50%``) and never a carriage return, so logs
    stay readable. Both end with the elapsed time.

    Parameters
    ----------
    label : str
    enabled : bool
        Print nothing when False.
    stream : file, optional
        Default ``sys.stderr``.
    tty : bool, optional
        Draw the in-place bar; default: whether ``stream`` is a terminal.
    """

    #: Percent between the lines written when the stream is not a terminal.
    LOG_STEP = 10

    def __init__(self, label: str, *, enabled: bool = True, stream=None, width: int = 30, tty=None):
        self.label = label
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.tty = _is_terminal(self.stream) if tty is None else bool(tty)
        self._step = 2 if self.tty else self.LOG_STEP
        self._last = -1
        self._t0 = time.perf_counter()
        self._done = False

    def __call__(self, fraction: float, _message: str = "") -> None:
        if not self.enabled or self._done or interrupts.pending() is not None:
            return
        pct = int(round(100 * min(max(float(fraction), 0.0), 1.0)))
        if pct <= self._last or (pct < 100 and pct // self._step == self._last // self._step):
            return
        self._last = pct
        if self.tty:
            filled = int(self.width * pct / 100)
            bar = "#" * filled + "." * (self.width - filled)
            self.stream.write(f"\r{self.label:<9} [{bar}] {pct:3d}%")
        else:
            self.stream.write(f"{self.label}: {pct:3d}%" + ("" if pct >= 100 else "\n"))
        self.stream.flush()
        if pct >= 100:
            self.finish()

    def finish(self) -> None:
        """End the line (with the elapsed time)."""
        if not self.enabled or self._done or interrupts.pending() is not None:
            return
        if self._last < 100:
            self(1.0)  # draws 100% and comes back here
            return
        self._done = True
        self.stream.write(f" {time.perf_counter() - self._t0:.1f} s\n")
        self.stream.flush()


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):  # no isatty, or a closed stream
        return False


def quiet_vtk() -> None:
    """Silence VTK's own log and warning output (the CLI reports errors itself, one line)."""
    from vtkmodules.vtkCommonCore import vtkLogger, vtkObject

    vtkObject.GlobalWarningDisplayOff()
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    warnings.filterwarnings("ignore", module="pyvista")
    warnings.filterwarnings("ignore", module="pytetwild")
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    # the resample filter's: the command's own fold line says it, or refuses the output
    warnings.filterwarnings("ignore", category=FoldWarning)


def use_vtk_threads(threads: int) -> None:
    """Run VTK's own parallel loops on ``threads`` threads, unless the user chose a backend.

    VTK's wheels run them (the value ranges an XML writer computes for every array, among
    others) on one thread unless told otherwise; its ``VTK_SMP_BACKEND_IN_USE`` variable,
    when set, is the user's choice and is kept. Process-wide: only for a process that is
    wholly a command.
    """
    from vtkmodules.vtkCommonCore import vtkSMPTools

    if os.environ.get("VTK_SMP_BACKEND_IN_USE"):
        return
    if vtkSMPTools.SetBackend("STDThread"):
        vtkSMPTools.Initialize(int(threads))


def observe_progress(algorithm, progress: Progress) -> None:
    """Forward a VTK algorithm's ``ProgressEvent`` to a :class:`Progress`.

    An interrupt arriving meanwhile is only recorded: raised inside VTK's callback it would
    be printed and lost; the filter stops at its next chunk and ``update`` raises it.
    """

    def forward(obj, _event) -> None:
        with interrupts.deferred(raise_at_end=False):
            progress(obj.GetProgress())

    algorithm.AddObserver("ProgressEvent", forward)


def run_filter(
    algorithm,
    data,
    deformer,
    label: str,
    *,
    quiet: bool,
    source=None,
    cage=None,
    drops: bool = True,
):
    """Run one of the VTK filters on ``data`` with ``deformer``, its progress on stderr.

    Parameters
    ----------
    algorithm : vtkAlgorithm
        A :mod:`vhm_viz.filters` filter, set up apart from its input and deformer.
    data : pyvista.DataSet
    deformer : Deformer
    label : str
        The progress bar's label.
    quiet : bool
        No progress bar.
    source : path-like, optional
        The file ``data`` came from: with it, points outside the cage are one
        :class:`CLIError` naming the file (else the filter's error is raised).
    cage : path-like, optional
        The file the cage came from (:attr:`~vhm_viz.scene.Scene.cage_file`), named in
        that line too.
    drops : bool
        The command has ``--outside nan`` (the message suggests it).

    Returns
    -------
    pyvista.DataSet
        The filter's output.
    """
    import pyvista as pv

    from vhm_viz.filters import update

    algorithm.SetInputData(data)
    algorithm.SetDeformer(deformer)
    bar = Progress(label, enabled=not quiet)
    observe_progress(algorithm, bar)
    try:
        result = pv.wrap(update(algorithm))
    except OutsideCageError as exc:
        if source is None:
            raise
        raise CLIError(outside_message(exc, data.n_points, source, cage=cage, drops=drops)) from exc
    bar.finish()
    return result


def check_input(path: str, suffixes=DATASET_SUFFIXES) -> Path:
    """The input path; :class:`CLIError` when missing or of an unknown type.

    With the dataset suffixes, a folder or a DICOM file of any name is accepted too (a
    DICOM series, read by :func:`vhm_viz.io.read_dataset`).
    """
    p = Path(path)
    if not p.exists():
        raise CLIError(f"input file not found: {p}")
    if suffixes is DATASET_SUFFIXES and (p.is_dir() or is_dicom_file(p)):
        return p  # a DICOM series: its folder, or one file of it (any name)
    if not p.is_file():
        raise CLIError(f"input is not a file: {p}")
    if suffix_of(p) not in suffixes:
        raise CLIError(
            f"unsupported input type {suffix_of(p) or '(none)'!r} ({p}); use one of "
            f"{', '.join(suffixes)}"
        )
    return p


def check_output(output: str, suffixes, inputs=(), option: str = "-o") -> Path:
    """The output path: a known suffix, an existing directory, and none of ``inputs``.

    Parameters
    ----------
    output : str
        The ``-o`` argument.
    suffixes : sequence of str
        Accepted suffixes (``.nii.gz`` counts as one).
    inputs : iterable of path-like
        Every file the command reads (data, scene, cage, ...): the output must be none of
        them, whatever path or hard link names it.
    option : str
        The option that named ``output``, which a refusal says to change.
    """
    out = Path(output)
    if out.is_dir():
        raise CLIError(f"output {out} is a directory; give a file name")
    _refuse_inputs(out, inputs, option)
    if suffix_of(out) not in suffixes:
        raise CLIError(f"output {out} must end with one of {', '.join(suffixes)}")
    if not out.resolve().parent.is_dir():
        raise CLIError(f"output directory does not exist: {out.parent}")
    require_writable(out.resolve().parent)
    return out


def check_output_directory(output: str, names, inputs=()) -> Path:
    """The ``-o`` directory (created later if missing), refused if it is an input.

    Neither it nor any of the files ``names`` that the command writes into it may be one
    of ``inputs`` (see :func:`check_output`).
    """
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise CLIError(f"output {out} must be a directory (it is a file)")
    for path in (out, *(out / name for name in names)):
        _refuse_inputs(path, inputs)
    require_writable(out)
    return out


def _refuse_inputs(path: Path, inputs, option: str = "-o") -> None:
    try:
        refuse_inputs(path, inputs)
    except OverwriteError as exc:
        raise CLIError(f"{exc} ({option})") from None


def outside_message(exc, n_points: int, source, *, cage=None, drops: bool = True) -> str:
    """One line for an :class:`OutsideCageError` raised on the input's points.

    ``cage``: the file the cage came from, named after "the cage" (None: not a file).
    ``drops``: the command has ``--outside nan``, which the line then suggests too.
    """
    idx = getattr(exc, "indices", None)
    if idx is None or len(idx) == 0:
        return one_line(exc)
    which = "the cage" if cage is None else f"the cage {cage}"
    return (
        f"{len(idx)} of {n_points} points of {source} are outside {which} (indices "
        f"{describe_indices(np.asarray(idx))}): the cage must enclose the data, or pass "
        "--outside passthrough to leave them in place"
        + (" (or --outside nan to drop them)" if drops else "")
    )


def load_scene(path: str):
    """Load a scene file; errors as :class:`CLIError`."""
    p = Path(path)
    if not p.is_file():
        raise CLIError(f"scene file not found: {p}")
    return Scene.load(p)


def add_scene_arguments(parser, input_help: str) -> None:
    """The positional INPUT and the required ``--scene``: a dataset and the scene that moves it.

    Parameters
    ----------
    parser : argparse.ArgumentParser
    input_help : str
        What INPUT is to the command, e.g. ``"dataset to deform"``.
    """
    parser.add_argument("input", metavar="INPUT", help=input_help)
    parser.add_argument("--scene", "-s", required=True, metavar="SCENE", help="scene file (JSON)")


def add_quiet_argument(parser, silenced: str = "no progress bars") -> None:
    """``--quiet``/``-q``; ``silenced`` says what it turns off."""
    parser.add_argument("--quiet", "-q", action="store_true", help=silenced)


def add_convergence_argument(parser) -> None:
    """``--allow-unconverged`` (see :func:`build_and_solve`)."""
    parser.add_argument(
        "--allow-unconverged",
        action="store_true",
        help="write the result even when the solver stops at solver.max_iterations "
        "before converging (otherwise: exit status 3, nothing written)",
    )


def add_fold_argument(parser) -> None:
    """``--allow-folds`` (see :class:`FoldedOutput`)."""
    parser.add_argument(
        "--allow-folds",
        action="store_true",
        help="write the result even when it folds the data (inverted cells, resampled "
        "voxels in folds, or det J <= 0 at sampled points: the warning says how many and "
        "where); otherwise exit status 4, nothing written",
    )


def build_and_solve(scene, mesh, *, quiet: bool, allow_unconverged: bool = False) -> SolvedMap:
    """Solve the scene's map for ``mesh`` (auto cage/anchors from it), saying its notes.

    Always solves (the command line reports the solve), through
    :meth:`~vhm_viz.scene.Scene.solve_map`; what loading had to change is printed on stderr,
    one line each (old scene format, cage repairs, thin cage faces).

    Returns
    -------
    SolvedMap
        With its deformer and the reports of each solve step.

    Raises
    ------
    NotConverged
        The (last) solve stopped at ``solver.max_iterations`` and ``allow_unconverged``
        is false.
    CLIError
        Anchors or constraints outside a cage read from a file: the line names it.
    """
    bar = Progress("solving", enabled=not quiet)
    try:
        solved = scene.solve_map(mesh, progress=bar, reuse_stored=False, on_note=_print_note)
    except OutsideCageError as exc:  # anchors or constraints: which cage, of several at hand
        if scene.cage_file is None:
            raise
        # worded as the line for the data's points (outside_message): "the cage PATH"
        text = one_line(exc).replace("outside the cage", f"outside the cage {scene.cage_file}", 1)
        raise CLIError(text) from exc
    bar.finish()
    solved.require_converged(
        allow_unconverged,
        remedy="nothing written (raise max_iterations, or pass --allow-unconverged)",
    )
    return solved


def solve_summary(reports) -> str:
    """The summary line's part on the solve, ``N iterations`` (all steps together).

    ``in S steps`` follows for a ramp (each step has its own ``solver.max_iterations``, so
    ``N`` may exceed it), and ``(not converged)`` when the last step stopped short.
    """
    text = f"{sum(r.iterations for r in reports)} iterations"
    if len(reports) > 1:
        text += f" in {len(reports)} steps"
    return text + ("" if reports[-1].converged else " (not converged)")


def print_warning(command: str, warning: str) -> None:
    """A result written although it is not what was asked for: one line on stderr."""
    print(f"vhm-viz {command}: warning: {warning}", file=sys.stderr)


def convergence_warning(solved: SolvedMap) -> str:
    """The warning of a result written from an unconverged solve (empty if it converged)."""
    return "" if solved.converged else f"not converged: {solved.shortfall()}"


def _print_note(note: str) -> None:
    print(f"vhm-viz: note: {note}", file=sys.stderr)


def surface_metrics(rest, deformed, rigid: bool = True) -> dict:
    """``E_rigid`` (with ``rigid``) and ``E_volume`` where defined.

    ``E_rigid`` of triangle surfaces, ``E_volume`` of closed triangle surfaces and solid
    meshes. A measure the data does not allow (all triangles degenerate, zero volume) is
    left out. They measure the map: triangles and cells with a point the map left in
    place (outside the cage, flagged ``vhm_outside``) are left out, counted in
    ``triangles_left_out`` or ``tetrahedra_left_out`` (a 3D cell's), and a surface's
    ``E_volume`` with them (it is no longer closed).
    """
    try:
        return _surface_metrics(rest, deformed, rigid)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return {}


def _surface_metrics(rest, deformed, rigid: bool) -> dict:
    import pyvista as pv

    from vhm_viz.core.geometry import moved_tetrahedra_volume, open_edge_count
    from vhm_viz.filters.cells import cell_tetrahedra

    out: dict = {}
    flags = deformed.point_data.get("vhm_outside")
    # the points the map left in place, if any
    left = None if flags is None else np.asarray(flags).astype(bool)
    left = left if left is not None and left.any() else None
    if isinstance(rest, pv.PolyData) and rest.n_cells and rest.GetNumberOfPolys():
        surf = rest if rest.is_all_triangles else rest.triangulate()
        dsurf = deformed if deformed.is_all_triangles else deformed.triangulate()
        tris = np.asarray(surf.faces).reshape(-1, 4)[:, 1:]
        closed = open_edge_count(tris, surf.n_points) == 0
        touching = np.zeros(len(tris), bool) if left is None else left[tris].any(axis=1)
        if touching.any():
            out["triangles_left_out"] = int(touching.sum())
            tris, closed = tris[~touching], False
        if rigid and len(tris):
            out["E_rigid"] = float(rigidity_distortion(surf.points, dsurf.points, tris))
        if closed:
            out["E_volume"] = float(volume_change(surf.points, dsurf.points, tris))
    elif isinstance(rest, pv.UnstructuredGrid) and rest.n_cells:
        # the 3D cells as tets, each counted with its rest orientation: VTK's cell sizes
        # take a voxel for the axis-aligned box it no longer is once its points move
        v0 = v1 = 0.0
        dropped = 0
        for tets, _ in cell_tetrahedra(rest):
            if left is not None:
                touching = left[tets].any(axis=1)
                dropped += int(touching.sum())
                tets = tets[~touching]
            a, b = moved_tetrahedra_volume(rest.points, deformed.points, tets)
            v0, v1 = v0 + a, v1 + b
        if dropped:
            out["tetrahedra_left_out"] = dropped
        if v0 > 0 and np.isfinite(v1):  # not with points dropped (--outside nan)
            out["E_volume"] = abs(v1 - v0) / v0
    return out


#: ``--memory-budget`` suffixes: powers of 1024.
_SIZE_UNITS = {"": 1, "B": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def memory_size(text: str) -> int:
    """``--memory-budget``: bytes, or a number with K, M, G or T (powers of 1024)."""
    import argparse

    from vhm_viz.core.limits import RANGES

    t = text.strip().upper().removesuffix("IB").removesuffix("B")
    unit = t[-1:] if t[-1:] in _SIZE_UNITS else ""
    try:
        value = float(t[: len(t) - len(unit)]) * _SIZE_UNITS[unit]
    except ValueError:
        value = -1.0
    rng = RANGES["memory_budget"]
    if not (value == value and rng.low <= value <= rng.high):
        raise argparse.ArgumentTypeError(
            f"expected a size such as 256M or 2G, at least 1 byte and at most 1T; got {text!r}"
        )
    return int(value)


def add_memory_argument(parser) -> None:
    """``--memory-budget`` (see :func:`check_volume_memory`)."""
    parser.add_argument(
        "--memory-budget",
        type=memory_size,
        default=None,
        metavar="SIZE",
        help="volumes: working memory per slab and per evaluation chunk (bytes, or with "
        "K, M, G); smaller slabs need less memory and are never a different result "
        "(default: 64M)",
    )


#: Whole copies of the output data a writer makes, by output suffix (the rest: none).
_WRITER_COPIES = {".mhd": 1, ".mha": 2, ".nii": 2, ".nii.gz": 2}
#: Input points per axis mapped to estimate the extent of a resampled volume.
_EXTENT_SAMPLES = 9


def check_volume_memory(image, harmonic_map, *, resample: bool, output, memory_budget=None,
                        spacing=None, reference=None, outside: str = "error",
                        field: str | None = None) -> None:  # fmt: skip
    """Refuse a volume job that cannot fit in this process's memory, before it allocates.

    The estimate is :func:`vhm_viz.core.memory.volume_job_bytes`; the limit is
    :func:`vhm_viz.resources.memory_limit` (address-space limit, cgroup, free memory).

    Parameters
    ----------
    image : pyvista.ImageData
        The input volume.
    harmonic_map : HarmonicMap
        The solved map (a few of the input's points are mapped to size a resample's grid).
    resample : bool
        Resampled to an image (else warped: every voxel moved).
    output : path-like
        The output file (its format decides the writer's copies).
    memory_budget : int, optional
        ``--memory-budget`` (default the engine's).
    spacing : (3,) float, optional
        ``--spacing`` of a resample.
    reference : pyvista.ImageData, optional
        ``--reference`` grid of a resample.
    outside : str
        ``--outside`` (passthrough keeps the input's own box in a resample's grid).
    field : {"pullback", "forward"} or None
        ``--field-kind`` of a ``--write-field``; None without one.

    Raises
    ------
    CLIError
        One line: the estimate, the limit, and the options that lower it.
    """
    from vhm_viz.core.basis import DEFAULT_MEMORY_BUDGET
    from vhm_viz.core.memory import volume_job_bytes
    from vhm_viz.io import suffix_of
    from vhm_viz.resources import format_bytes, require_memory

    dims = tuple(int(d) for d in image.dimensions)
    n_in = int(np.prod(dims, dtype=np.int64))
    value_bytes = sum(image.point_data[name].nbytes // max(n_in, 1)
                      for name in image.point_data.keys())  # fmt: skip
    if resample:
        try:
            out_dims = _resampled_dimensions(image, harmonic_map, spacing, reference, outside)
        except ValueError as exc:  # a grid no image can hold
            raise CLIError(f"resampling {'x'.join(map(str, dims))} voxels: {exc}") from None
    else:
        out_dims = dims
    budget = DEFAULT_MEMORY_BUDGET if memory_budget is None else int(memory_budget)
    parts = volume_job_bytes(
        n_in, math.prod(out_dims), value_bytes,
        kind="resample" if resample else "warp", memory_budget=budget,
        writer_copies=_WRITER_COPIES.get(suffix_of(output), 0), field=field,
    )  # fmt: skip
    grid = "x".join(str(d) for d in out_dims)
    what = (f"resampling {'x'.join(map(str, dims))} voxels onto a {grid} grid" if resample
            else f"warping {'x'.join(map(str, dims))} voxels")  # fmt: skip
    if resample:
        remedy = "give a coarser --spacing (or a smaller --reference grid)"
    else:
        remedy = "resample to an image (.vti, .mhd, .nii) with a coarser --spacing"
    if parts["slab"] > 2 * 2**20:
        remedy += f", or a smaller --memory-budget (now {format_bytes(budget)})"
    if field is not None:
        what += f" with its {field} displacement field ({format_bytes(parts['field'])})"
        remedy += ", or leave out --write-field"
    try:
        require_memory(parts["total"], what, remedy)
    except MemoryError as exc:
        raise CLIError(str(exc)) from None


def _resampled_dimensions(image, harmonic_map, spacing, reference, outside) -> tuple:
    """The dimensions of a resample's output grid, from the images of a few input points.

    The engine's own rule (:func:`~vhm_viz.core.volume.output_grid`) over the points'
    images, widened by a voxel on each side for the images between them, so that every
    option that shapes the grid shapes the estimate the same way.
    """
    if reference is not None:
        return tuple(int(d) for d in reference.dimensions)
    from vhm_viz.core.volume import output_grid
    from vhm_viz.filters._vtk import image_geometry

    geo = image_geometry(image)
    dims = np.asarray(geo.dimensions, dtype=np.int64)
    axes = [np.linspace(0, d - 1, min(int(d), _EXTENT_SAMPLES)) for d in dims]
    ijk = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    mapped = harmonic_map.evaluate(geo.points(ijk), outside="nan")[0]
    mapped = mapped[np.isfinite(mapped).all(axis=1)]
    if len(mapped) == 0:
        return tuple(int(d) for d in dims)
    index = geo.continuous_index(mapped)
    grid = output_grid(geo, index.min(axis=0) - 1.0, index.max(axis=0) + 1.0, spacing=spacing,
                       keep_input=outside == "passthrough")  # fmt: skip
    return tuple(int(d) for d in grid.dimensions)
