"""Compile the filters' numba kernels ahead of their first use (a set-up step).

numba compiles a kernel on its first call and keeps it in its cache (``NUMBA_CACHE_DIR``);
in a fresh installation the first filter run spends about a minute compiling instead of
seconds, and under MPI every rank compiles at once. :func:`compile_kernels` runs the three filters
once on tiny data -- two images, a tet mesh and a surface in the bundled bar's cage, the
same calls as the ParaView plugin makes -- so that ``plugins/paraview-env.sh`` can fill
the cache when it installs numba.

Run: ``python -m vhm_viz.filters.warm`` (pvpython: the same).
"""

from __future__ import annotations

import time

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import (
    VTK_TETRA,
    VTK_TRIANGLE,
    vtkCellArray,
    vtkImageData,
    vtkPolyData,
    vtkUnstructuredGrid,
)

from vhm_viz.core.volume import EXACT_VOXELS
from vhm_viz.examples import bar, bar_surface, bar_tets
from vhm_viz.filters import (
    HarmonicDeformationFilter,
    HarmonicResampleFilter,
    JacobianAnalysisFilter,
    update,
)
from vhm_viz.io import cage_to_polydata

__all__ = ["compile_kernels"]

#: Value types of the image whose resampling kernels are compiled ahead.
_VALUE_TYPES = (np.uint8, np.int16, np.uint16, np.float32, np.float64)


def _cells(kind: int, conn: np.ndarray, points: np.ndarray, dataset):
    pts = vtkPoints()
    pts.SetData(ns.numpy_to_vtk(np.ascontiguousarray(points, dtype=np.float64), deep=1))
    dataset.SetPoints(pts)
    cells = vtkCellArray()
    n = conn.shape[1]
    offsets = np.arange(0, conn.size + 1, n, dtype=np.int64)
    cells.SetData(ns.numpy_to_vtkIdTypeArray(offsets, deep=1),
                  ns.numpy_to_vtkIdTypeArray(conn.astype(np.int64).ravel(), deep=1))  # fmt: skip
    if isinstance(dataset, vtkPolyData):
        dataset.SetPolys(cells)
    else:
        dataset.SetCells(kind, cells)
    return dataset


def _image(dims, spacing: float, start=(0, 0, 0)) -> vtkImageData:
    """An image across the bar's cage, with an array of each of :data:`_VALUE_TYPES`.

    Its corner lies outside the cage (x, y in [-0.65, 0.65], z in [-0.2, 5.2]): the
    voxels there go through the outside policy's kernels.
    """
    image = vtkImageData()
    image.SetOrigin(-0.8, -0.8, -0.4)
    image.SetSpacing(spacing, spacing, spacing)
    image.SetExtent(*[v for a in range(3) for v in (start[a], start[a] + dims[a] - 1)])
    # the sampling kernels are compiled for each value type: the volumes' usual ones
    # (8-bit CT/EM, 16-bit CT and MR, float); another type compiles on first use
    ramp = np.linspace(0.0, 200.0, int(np.prod(dims)))
    for dtype in _VALUE_TYPES:
        array = ns.numpy_to_vtk(ramp.astype(dtype), deep=1)
        array.SetName(np.dtype(dtype).name)
        image.GetPointData().AddArray(array)
    image.GetPointData().SetActiveScalars("float32")
    return image


def _inputs():
    """Images, a tet mesh and a surface inside the bar's cage (VTK objects)."""
    # more voxels than EXACT_VOXELS (the volume engine builds its lattice), and fewer
    # (every voxel evaluated exactly); and an extent not starting at 0 (a piece of a
    # volume, an extracted subset: its masks and boxes are views, compiled apart)
    # (30: not a multiple of the lattice's root cells plus one, which would make the
    # lattice's masks exactly the image's and their slices contiguous, unlike a real one)
    images = [_image((30, 30, 60), 0.05), _image((9, 9, 20), 0.2),
              _image((30, 30, 60), 0.05, start=(3, 2, 5))]  # fmt: skip
    if not images[0].GetNumberOfPoints() > EXACT_VOXELS >= images[1].GetNumberOfPoints():
        raise RuntimeError("the warm-up's images no longer straddle EXACT_VOXELS")
    tet_points, tets = bar_tets(4)
    surf_points, tris = bar_surface(9)
    return (images, _cells(VTK_TETRA, tets, tet_points, vtkUnstructuredGrid()),
            _cells(VTK_TRIANGLE, tris, surf_points, vtkPolyData()))  # fmt: skip


def compile_kernels(report=None) -> float:
    """Run the three filters once on tiny data, compiling (or loading) their kernels.

    Parameters
    ----------
    report : callable(str), optional
        Called with a line after each filter.

    Returns
    -------
    float
        Seconds taken.
    """
    t0 = time.perf_counter()
    scenario = bar(resolution=5)  # (its own surface is not used)
    scene = scenario.scene  # solved by each filter: the solver's kernels too
    images, tets, surface = _inputs()
    cage = cage_to_polydata(scenario.cage)
    runs = [(HarmonicDeformationFilter, tets), (HarmonicDeformationFilter, surface),
            (JacobianAnalysisFilter, tets)]  # fmt: skip
    for image in images:
        runs += [(HarmonicDeformationFilter, image), (JacobianAnalysisFilter, image),
                 (HarmonicResampleFilter, image)]  # fmt: skip
    # with the scene's cage and with one on the Cage port (the plugin's usual way): two
    # paths to the same kernels, which must both find them compiled
    for port_cage in (None, cage):
        for cls, data in runs:
            flt = cls()
            flt.SetScene(scene)
            flt.SetOutsidePolicy("passthrough")
            flt.SetInputData(data)
            if port_cage is not None:
                flt.SetCageData(port_cage)
            update(flt)
            if report is not None:
                report(f"{cls.__name__} on a {data.GetClassName()} of "
                       f"{data.GetNumberOfPoints()} points"
                       f"{'' if port_cage is None else ', cage on port 1'}: "
                       f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    return time.perf_counter() - t0


if __name__ == "__main__":
    seconds = compile_kernels(report=print)
    print(f"vhm_viz kernels compiled (or loaded) in {seconds:.0f} s")
