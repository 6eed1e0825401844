"""numpy_points and displacement against VTK's GetPoint on every lattice kind.

Run by test_filters, and in pvpython by test_paraview: VTK < 9.6 has no points array for
images, and its rectilinear grid's GetPoints fills an argument.
"""

import numpy as np
from vtkmodules.util import numpy_support as ns
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkImageData, vtkRectilinearGrid, vtkStructuredGrid

from vhm_viz.filters._vtk import displacement, numpy_points


def _by_point(ds):
    return np.array([ds.GetPoint(i) for i in range(ds.GetNumberOfPoints())])


def lattices():
    """An image piece, a turned and mirrored image, a rectilinear and a structured grid."""
    image = vtkImageData()
    image.SetExtent(3, 9, -2, 2, 5, 8)  # a piece of a larger image: 7 x 5 x 4 points
    image.SetSpacing(0.3, 1.1, 2.0)
    image.SetOrigin(1.1, -2.0, 3.0)
    turned = vtkImageData()
    turned.DeepCopy(image)
    turned.SetExtent(2, 8, -1, 3, 0, 3)
    turned.SetDirectionMatrix(0, 1, 0, -1, 0, 0, 0, 0, -1)
    rect = vtkRectilinearGrid()
    rect.SetDimensions(3, 2, 4)
    for axis, values in zip("XYZ", ([0, 1, 3.5], [0, 2.0], [1, 5, 6, 9.0]), strict=True):
        getattr(rect, f"Set{axis}Coordinates")(ns.numpy_to_vtk(np.array(values)))
    grid = vtkStructuredGrid()
    grid.SetDimensions(3, 2, 2)
    points = vtkPoints()
    points.SetData(ns.numpy_to_vtk(np.random.default_rng(4).normal(size=(12, 3)), deep=1))
    grid.SetPoints(points)
    return {"image": image, "turned image": turned, "rectilinear": rect, "structured": grid}


def check():
    for name, ds in lattices().items():
        got, want = numpy_points(ds), _by_point(ds)
        assert got.dtype == np.float64 and got.shape == want.shape, name
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12, err_msg=name)
        moved = want * 1.5 + 0.25
        step = displacement(ds, moved)
        assert step.dtype == np.float64 and step.shape == want.shape, name
        np.testing.assert_allclose(step, moved - want, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_array_equal(moved, want * 1.5 + 0.25)  # its input is left alone
    return "points ok"


if __name__ == "__main__":
    print(check())
