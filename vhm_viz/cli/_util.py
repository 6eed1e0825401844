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
from vhm_viz.core.errors import OutsideCageError, describe_indices
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
    algorithm, data, deformer, label: str, *, quiet: bool, source=None, drops: bool = True
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
        raise CLIError(outside_message(exc, data.n_points, source, drops=drops)) from exc
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


def check_output(output: str, suffixes, inputs=()) -> Path:
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
    """
    out = Path(output)
    if out.is_dir():
        raise CLIError(f"output {out} is a directory; give a file name")
    _refuse_inputs(out, inputs)
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


def _refuse_inputs(path: Path, inputs) -> None:
    try:
        refuse_inputs(path, inputs)
    except OverwriteError as exc:
        raise CLIError(f"{exc} (-o)") from None


def outside_message(exc, n_points: int, source, *, drops: bool = True) -> str:
    """One line for an :class:`OutsideCageError` raised on the input's points.

    ``drops``: the command has ``--outside nan``, which the line then suggests too.
    """
    idx = getattr(exc, "indices", None)
    if idx is None or len(idx) == 0:
        return one_line(exc)
    return (
        f"{len(idx)} of {n_points} points of {source} are outside the cage (indices "
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
    """
    bar = Progress("solving", enabled=not quiet)
    solved = scene.solve_map(mesh, progress=bar, reuse_stored=False, on_note=_print_note)
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
    left out.
    """
    try:
        return _surface_metrics(rest, deformed, rigid)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return {}


def _surface_metrics(rest, deformed, rigid: bool) -> dict:
    import pyvista as pv

    from vhm_viz.core.geometry import open_edge_count, tetrahedra_volume
    from vhm_viz.filters.cells import tetra_cells

    out: dict = {}
    if isinstance(rest, pv.PolyData) and rest.n_cells and rest.GetNumberOfPolys():
        surf = rest if rest.is_all_triangles else rest.triangulate()
        dsurf = deformed if deformed.is_all_triangles else deformed.triangulate()
        tris = np.asarray(surf.faces).reshape(-1, 4)[:, 1:]
        if rigid:
            out["E_rigid"] = float(rigidity_distortion(surf.points, dsurf.points, tris))
        if open_edge_count(tris, surf.n_points) == 0:
            out["E_volume"] = float(volume_change(surf.points, dsurf.points, tris))
    elif isinstance(rest, pv.UnstructuredGrid) and rest.n_cells:
        tets = tetra_cells(rest)  # a tet mesh: its volumes without VTK's cell sizes
        if tets is None:
            v0, v1 = float(rest.volume), float(deformed.volume)
        else:
            v0, v1 = (tetrahedra_volume(d.points, tets[0]) for d in (rest, deformed))
        if v0 > 0:
            out["E_volume"] = abs(v1 - v0) / v0
    return out


#: Points at which ``vhm-viz deform`` samples ``det J`` for its fold warning (evenly spread)
#: when nothing else checks the whole output (a surface, a point cloud): at most this many,
#: and at most one in :data:`FOLD_SAMPLE_SPREAD` of the data's (:func:`fold_samples`).
FOLD_SAMPLES = 20000
#: The exact Jacobian at a point costs about twice the map's value there (both sum over
#: the cage's faces; the Jacobian three gradients besides the value): one point in this
#: many holds the samples to about a sixteenth of the map's work, so that with the
#: summary's measures (``E_volume``) the checks stay a small part of the map.
FOLD_SAMPLE_SPREAD = 32
#: Points of the spot check beside a check of the whole output -- every cell of a warped
#: volume or tet mesh, every resampled voxel's pre-image -- at most (evenly spread): there
#: the output's own check finds its folds, and this one samples the exact ``det J`` of the
#: continuous map itself, at a cost that stays a small part of even a fast map's (a
#: volume engine's map is far cheaper per voxel than the exact Jacobian). Also the fewest
#: points of :func:`fold_samples`.
FOLD_SPOT_SAMPLES = 256


def fold_samples(n_points: int) -> int:
    """Points of the fold warning's ``det J`` samples of an output of ``n_points`` points."""
    return min(FOLD_SAMPLES, max(FOLD_SPOT_SAMPLES, int(n_points) // FOLD_SAMPLE_SPREAD))


def _position(p) -> str:
    """``(x, y, z)`` to 4 digits."""
    return "(" + ", ".join(f"{c:.4g}" for c in p) + ")"


def _where(points: np.ndarray, values: np.ndarray) -> str:
    """``worst -0.12 at (x, y, z), within [lo]-[hi]`` for the bad points (rest positions)."""
    k = int(np.argmin(values))
    text = f"worst {values[k]:.3g} at {_position(points[k])}"
    if len(points) > 1:  # column by column: numpy's axis-0 reduction of (K, 3) is slow
        lo = [points[:, c].min() for c in range(points.shape[1])]
        hi = [points[:, c].max() for c in range(points.shape[1])]
        text += f", within {_position(lo)}-{_position(hi)}"
    return text


def _points_of(data, index) -> np.ndarray:
    """Positions of the points ``index`` of ``data``; an image's without making them all."""
    import pyvista as pv

    index = np.asarray(index, dtype=np.int64)
    if isinstance(data, pv.ImageData):
        ijk = np.column_stack(np.unravel_index(index, tuple(data.dimensions), order="F"))
        return image_positions(data, ijk)
    return np.asarray(data.points, dtype=np.float64)[index]


def image_positions(image, ijk) -> np.ndarray:
    """World positions of (fractional) index coordinates ``ijk`` (K, 3) of an image."""
    frame = np.asarray(image.direction_matrix, dtype=np.float64) * np.asarray(image.spacing)
    return np.asarray(image.origin, dtype=np.float64) + np.asarray(ijk, dtype=np.float64) @ frame.T


#: Cells per slab of :func:`inverted_voxel_cells` at most: a slab takes a small fraction
#: of a second, and an interrupt is acted on between slabs.
FOLD_SLAB_CELLS = 1 << 22
#: Share of a grid's cells above which :func:`inverted_voxel_cells` sweeps every cell
#: rather than measuring the unproven ones alone: the sweep shares each plane's work
#: between the layers of cells and runs along whole rows, several times faster per cell.
_SWEEP_FRACTION = 0.2
#: Working memory of :func:`inverted_voxel_cells` per cell of a slab at most (bytes): an
#: inverted cell's index and determinant (no memory per cell that is not inverted).
_FOLD_CELL_BYTES = 16


def inverted_voxel_cells(
    points, dimensions, rest_det: float, progress=None, memory_budget=None, unproven=None
) -> dict:
    """The inverted cells of a warped voxel grid, slab by slab, in bounded memory.

    :func:`~vhm_viz.core.cell_kernels.inverted_hexahedra` of a slab of voxel layers at a
    time (or of a group of ``unproven`` boxes): only the inverted cells are held, and an
    interrupt is acted on between slabs, so that Ctrl-C or SIGTERM stops the fold check of
    a large warped volume promptly.

    Parameters
    ----------
    points : (nx * ny * nz, 3) array_like
        Deformed positions in VTK's point order.
    dimensions : (3,) int
    rest_det : float
    progress : callable, optional
        ``progress(fraction)`` after each slab.
    memory_budget : int, optional
        Bytes of working memory per slab (default: slabs of :data:`FOLD_SLAB_CELLS`
        cells; a slab is at least one layer of cells).
    unproven : (K, 6) int array_like, optional
        The only cells to measure (inclusive cell ranges,
        :meth:`~vhm_viz.core.volume.VolumeDeformation.unproven_cells`): the others are
        proven not inverted, and counted as measured cells. Where they are more than
        :data:`_SWEEP_FRACTION` of the cells, every cell is measured.

    Returns
    -------
    dict
        :func:`fold_warning`'s ``cells``: ``summary`` (``cells``: cells with finite
        corners, ``inverted``: of them with a corner determinant ``<= 0``, ``proven``:
        of them proven not inverted without being measured), ``inverted`` (K,) int64 (the
        inverted cells in VTK's cell order) and ``inverted_determinant`` (K,) float64
        (their smallest corner determinant relative to the rest voxel's).
    """
    from vhm_viz.core.cell_kernels import inverted_hexahedra

    nx, ny, nz = (int(d) for d in dimensions)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    plane, cell_plane = nx * ny, max(nx - 1, 0) * max(ny - 1, 0)
    slab_cells = FOLD_SLAB_CELLS
    if memory_budget is not None:
        slab_cells = min(slab_cells, int(memory_budget) // _FOLD_CELL_BYTES)
    checked, proven, inverted, worst = 0, 0, [np.zeros(0, np.int64)], [np.zeros(0)]
    boxes = np.asarray([] if unproven is None else unproven, dtype=np.int64).reshape(-1, 6)
    ends = np.cumsum(np.prod(boxes[:, 1::2] - boxes[:, 0::2] + 1, axis=1))
    n_unproven, all_cells = int(ends[-1]) if ends.size else 0, cell_plane * max(nz - 1, 0)
    if unproven is not None and n_unproven <= _SWEEP_FRACTION * all_cells:
        proven = all_cells - n_unproven
        # groups of boxes of about slab_cells cells
        group_of = (ends - 1) // max(slab_cells, 1)
        groups = np.split(boxes, np.flatnonzero(np.diff(group_of)) + 1)
        for g, group in enumerate(groups):
            part = inverted_hexahedra(points, dimensions, rest_det, group)
            checked += part["cells"]
            inverted.append(part["inverted"])
            worst.append(part["determinant"])
            interrupts.check()
            if progress is not None:
                progress((g + 1) / len(groups))
        bad = np.concatenate(inverted)
        order = np.argsort(bad, kind="stable")
        bad, worst = bad[order], np.concatenate(worst)[order]
    else:
        layers = max(1, slab_cells // max(cell_plane, 1))
        for k0 in range(0, nz - 1, layers):
            k1 = min(k0 + layers, nz - 1)
            slab = inverted_hexahedra(
                points[k0 * plane : (k1 + 1) * plane], (nx, ny, k1 - k0 + 1), rest_det
            )
            checked += slab["cells"]
            inverted.append(slab["inverted"] + k0 * cell_plane)
            worst.append(slab["determinant"])
            interrupts.check()
            if progress is not None:
                progress(k1 / (nz - 1))
        bad, worst = np.concatenate(inverted), np.concatenate(worst)
    return {
        "summary": {"cells": checked + proven, "inverted": int(bad.size), "proven": proven},
        "inverted": bad,
        "inverted_determinant": worst,
    }


def _spot_jacobian_determinants(harmonic_map, points) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``det J`` at points inside the cage: (which points, their ``det J``).

    Through :meth:`~vhm_viz.core.harmonic_map.HarmonicMap.jacobian`, the basis kernel that
    solving the scene has already run (a sample of points needs no kernel of its own).
    Points outside the cage, or on a cage edge (no Jacobian), are left out.
    """
    from vhm_viz.core.metrics import jacobian_determinant

    jac = harmonic_map.jacobian(points, outside="nan")
    ok = np.isfinite(jac).all(axis=(1, 2))
    return ok, jacobian_determinant(jac[ok])


def fold_warning(
    rest, harmonic_map, cells=None, point_det=None, samples: int = FOLD_SAMPLES, voxels=None
) -> str | None:
    """One warning line when a deformation folds the data, naming how many and where.

    Parameters
    ----------
    rest : pyvista.DataSet
        The rest data (positions in the message are rest positions).
    harmonic_map : HarmonicMap
    cells : dict, optional
        The output's cells (3D cells only): :func:`vhm_viz.filters.cell_quality` of the
        output (``determinant`` per cell), or :func:`inverted_voxel_cells` (``inverted``
        cells and their ``inverted_determinant``); either with its ``summary``, and
        optionally ``centres(cells)``, the rest centres of cells given by index.
    point_det : (N,) array_like, optional
        ``det J`` at every point, when already computed; else it is sampled exactly at up
        to ``samples`` points.
    samples : int
        :func:`fold_samples`, or :data:`FOLD_SPOT_SAMPLES` beside a check of the whole
        output.
    voxels : dict, optional
        A resampled output's voxels in folds (several pre-images): ``count`` of them,
        of ``voxels`` in all, and ``lo``, ``hi``, the box of their output positions.

    Returns
    -------
    str or None
        None when no cell is inverted, no output voxel lies in a fold and no sampled
        ``det J`` is ``<= 0``.
    """
    voxel_part = []
    if voxels is not None and voxels["count"]:
        lo, hi = voxels["lo"], voxels["hi"]
        where = f"output position {_position(lo)}"
        if not np.array_equal(lo, hi):
            where = f"output positions within {_position(lo)}-{_position(hi)}"
        voxel_part.append(
            f"{voxels['count']} of {voxels['voxels']} output voxels in folds "
            f"(several pre-images; {where})"
        )
    parts = list(voxel_part)
    if cells is not None and cells["summary"]["inverted"]:
        if "inverted" in cells:
            bad, worst = np.asarray(cells["inverted"]), np.asarray(cells["inverted_determinant"])
        else:
            det = np.asarray(cells["determinant"])
            bad = np.nonzero(det <= 0)[0]
            worst = det[bad]
        if "centres" in cells:
            centres = np.asarray(cells["centres"](bad))
        else:
            from vhm_viz.filters.cells import cell_centres

            centres = cell_centres(rest, bad)
        parts.append(
            f"{bad.size} of {cells['summary']['cells']} cells inverted "
            f"(cell det <= 0; {_where(centres, worst)})"
        )
    n_points = rest.GetNumberOfPoints()
    if point_det is None:
        idx = np.unique(np.linspace(0, n_points - 1, min(n_points, samples)).astype(int))
        ok, det = _spot_jacobian_determinants(harmonic_map, _points_of(rest, idx))
        idx = idx[ok]
        what = f"{idx.size} sampled points"
    else:
        det = np.asarray(point_det, dtype=np.float64)
        idx = np.nonzero(np.isfinite(det))[0]
        det = det[idx]
        what = f"{idx.size} points"
    bad = det <= 0
    if bad.any():
        parts.append(
            f"det J <= 0 at {int(bad.sum())} of {what} "
            f"({_where(_points_of(rest, idx[bad]), det[bad])})"
        )
    if not parts:
        return None
    # the cells' and the sampled points' positions are rest positions; the voxels' say theirs
    rest = "rest positions; " if len(parts) > len(voxel_part) else ""
    return (
        "the deformation folds the data: "
        + "; ".join(parts)
        + f" ({rest}vhm-viz analyze --certify checks every point)"
    )


def load_check_kernels(data, *, cells: bool = True, voxels: bool = False, proof: bool = False):
    """Start loading the compiled kernels of ``data``'s checks, on a second thread.

    The checks after the map -- the summary's ``E_volume`` (:func:`surface_metrics`) and
    the fold check's cells (:func:`~vhm_viz.filters.cell_quality`,
    :func:`inverted_voxel_cells`) -- run compiled kernels that a process loads from
    numba's cache before their first call: a fixed cost that a small map cannot amortise.
    Started before the solve, which leaves a core idle, the thread calls the same numeric
    functions on a tiny input of the same types, so it loads what they will load; it
    touches no VTK object. With one thread for the kernels (``--threads 1``, one CPU) it
    does nothing. Join it before the checks (a check that finds its kernel still
    loading waits for it).

    Parameters
    ----------
    data : pyvista.DataSet
        The input.
    cells : bool
        The fold check measures the cells of an unstructured grid (not when the filter
        measured them itself: ``--arrays cells``).
    voxels : bool
        The fold check measures a warped image's voxel cells (a forward warp).
    proof : bool
        Those of them that the volume engine's lattice does not prove unfolded (a large
        image: :data:`~vhm_viz.cli.deform.PROOF_MIN_CELLS`).

    Returns
    -------
    threading.Thread
    """
    import threading

    import numba
    import pyvista as pv

    from vhm_viz.core.geometry import open_edge_count, tetrahedra_volume
    from vhm_viz.core.metrics import cell_measures
    from vhm_viz.filters.cells import tetra_cells

    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    tet = np.array([[0, 1, 2, 3]])
    work = []
    if isinstance(data, pv.ImageData) and voxels:
        cube = np.stack(np.meshgrid([0.0, 1], [0.0, 1], [0.0, 1], indexing="ij"), -1)
        cube = cube.reshape(-1, 3)
        if proof:  # the proof, then the cells it leaves (boxes of them, or every cell)
            from vhm_viz.core.cell_kernels import inverted_hexahedra
            from vhm_viz.core.lattice import HermiteLattice

            work.append(HermiteLattice.load_proof_kernel)
            work.append(lambda: inverted_hexahedra(cube, (2, 2, 2), 1.0, [[0] * 6]))
        work.append(lambda: inverted_voxel_cells(cube, (2, 2, 2), 1.0))
    elif isinstance(data, pv.UnstructuredGrid):
        found = tetra_cells(data)
        if found is None:  # other 3D cells: split into tets, reduced per cell
            if cells:
                work.append(lambda: cell_measures(corners, corners, tet, [0], 1, condition=False))
        elif len(found[0]):  # a tet mesh: its volumes (E_volume) and a cell per tet
            work.append(lambda: tetrahedra_volume(corners, tet))
            if cells:
                work.append(lambda: cell_measures(corners, corners, tet, condition=False))
    elif isinstance(data, pv.PolyData):
        faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        work.append(lambda: open_edge_count(faces, 4))  # E_volume of a closed surface

    if numba.get_num_threads() < 2:  # one CPU: nothing idles; the checks load their own
        work.clear()

    def run():
        for step in work:
            try:
                step()
            except Exception:  # noqa: BLE001 - the checks themselves meet it and say so
                pass

    thread = threading.Thread(target=run, name="vhm-check-kernels", daemon=True)
    thread.start()
    return thread


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
