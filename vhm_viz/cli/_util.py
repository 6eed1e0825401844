"""Helpers shared by the ``deform``, ``analyze`` and ``demo`` subcommands."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from vhm_viz.cli import one_line
from vhm_viz.io import DATASET_SUFFIXES, suffix_of

#: Output formats per output dataset type.
OUTPUT_SUFFIXES = {
    "PolyData": (".vtp", ".vtk", ".ply", ".obj", ".stl"),
    "UnstructuredGrid": (".vtu", ".vtk"),
    "StructuredGrid": (".vts", ".vtk"),
    "ImageData": (".vti", ".vtk", ".mhd", ".mha", ".nii", ".nii.gz"),
}


class CLIError(ValueError):
    """An error reported as one line (the message) with a non-zero exit status."""


class Progress:
    """A one-line text progress bar on stderr (``label [#####.....]  50%``).

    Parameters
    ----------
    label : str
    enabled : bool
        Print nothing when False.
    stream : file, optional
        Default ``sys.stderr``.
    """

    def __init__(self, label: str, *, enabled: bool = True, stream=None, width: int = 30):
        self.label = label
        self.enabled = enabled
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self._last = -1
        self._t0 = time.perf_counter()
        self._done = False

    def __call__(self, fraction: float, _message: str = "") -> None:
        if not self.enabled or self._done:
            return
        pct = int(round(100 * min(max(float(fraction), 0.0), 1.0)))
        if pct == self._last or (pct < 100 and pct - self._last < 2):
            return
        self._last = pct
        filled = int(self.width * pct / 100)
        bar = "#" * filled + "." * (self.width - filled)
        self.stream.write(f"\r{self.label:<9} [{bar}] {pct:3d}%")
        self.stream.flush()
        if pct >= 100:
            self.finish()

    def finish(self) -> None:
        """End the line (with the elapsed time)."""
        if not self.enabled or self._done:
            return
        self._done = True
        if self._last < 100:
            self._last = 99
            self(1.0)
            return
        self.stream.write(f" {time.perf_counter() - self._t0:.1f} s\n")
        self.stream.flush()


def quiet_vtk() -> None:
    """Silence VTK's own log and warning output (the CLI reports errors itself, one line)."""
    import warnings

    from vtkmodules.vtkCommonCore import vtkLogger, vtkObject

    vtkObject.GlobalWarningDisplayOff()
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    warnings.filterwarnings("ignore", module="pyvista")
    warnings.filterwarnings("ignore", module="pytetwild")
    warnings.filterwarnings("ignore", category=DeprecationWarning)


def observe_progress(algorithm, progress: Progress) -> None:
    """Forward a VTK algorithm's ``ProgressEvent`` to a :class:`Progress`."""
    algorithm.AddObserver("ProgressEvent", lambda obj, _ev: progress(obj.GetProgress()))


def check_input(path: str, suffixes=DATASET_SUFFIXES) -> Path:
    """The input path; :class:`CLIError` when missing or of an unknown type."""
    p = Path(path)
    if not p.exists():
        raise CLIError(f"input file not found: {p}")
    if not p.is_file():
        raise CLIError(f"input is not a file: {p}")
    if suffix_of(p) not in suffixes:
        raise CLIError(
            f"unsupported input type {suffix_of(p) or '(none)'!r} ({p}); use one of "
            f"{', '.join(suffixes)}"
        )
    return p


def same_file(a: Path, b: Path) -> bool:
    """Whether two paths name the same file: same inode (hard links), or same real path."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


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
    if suffix_of(out) not in suffixes:
        raise CLIError(f"output {out} must end with one of {', '.join(suffixes)}")
    for src in inputs:
        if src is not None and same_file(Path(src), out):
            raise CLIError(f"refusing to overwrite the input file {src}; choose another -o")
    if not out.resolve().parent.is_dir():
        raise CLIError(f"output directory does not exist: {out.parent}")
    return out


def outside_message(exc, n_points: int, source) -> str:
    """One line for an :class:`OutsideCageError` raised on the input's points."""
    from vhm_viz.core.errors import describe_indices

    idx = getattr(exc, "indices", None)
    if idx is None or len(idx) == 0:
        return one_line(exc)
    return (
        f"{len(idx)} of {n_points} points of {source} are outside the cage (indices "
        f"{describe_indices(np.asarray(idx))}): the cage must enclose the data, or pass "
        "--outside passthrough to leave them in place (or --outside nan to drop them)"
    )


def load_scene(path: str):
    """Load a scene file; errors as :class:`CLIError`."""
    from vhm_viz.scene import Scene

    p = Path(path)
    if not p.is_file():
        raise CLIError(f"scene file not found: {p}")
    return Scene.load(p)


def build_and_solve(scene, mesh, *, quiet: bool):
    """Build the scene's deformer (auto cage/anchors from ``mesh``) and solve it."""
    dfm = scene.build(data=mesh)
    bar = Progress("solving", enabled=not quiet)
    reports = scene.solve(dfm, progress=bar)
    bar.finish()
    return dfm, reports


def surface_metrics(rest, deformed) -> dict:
    """``E_rigid`` and ``E_volume`` where defined (triangle surfaces / solid meshes)."""
    import pyvista as pv

    from vhm_viz.core.metrics import rigidity_distortion, volume_change

    out: dict = {}
    if isinstance(rest, pv.PolyData) and rest.n_cells and rest.GetNumberOfPolys():
        surf = rest if rest.is_all_triangles else rest.triangulate()
        dsurf = deformed if deformed.is_all_triangles else deformed.triangulate()
        tris = np.asarray(surf.faces).reshape(-1, 4)[:, 1:]
        out["E_rigid"] = float(rigidity_distortion(surf.points, dsurf.points, tris))
        if rest.n_open_edges == 0:
            out["E_volume"] = float(volume_change(surf.points, dsurf.points, tris))
    elif isinstance(rest, pv.UnstructuredGrid) and rest.n_cells:
        v0 = float(rest.volume)
        if v0 > 0:
            out["E_volume"] = abs(float(deformed.volume) - v0) / v0
    return out
