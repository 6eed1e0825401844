"""
The det J and cond J analysis view
==================================

Two measures of the map's Jacobian ``J`` tell where a deformation distorts: ``det J``,
the local volume ratio (1: no change of volume, below 0: a fold), and ``cond J``, the
ratio of its largest to smallest singular value (1: no shear). Both are exact, from the
closed-form Jacobian. :func:`vhm_viz.plotting.jacobian_slice` takes a slice of the rest
shape, maps it and attaches both, as in the paper's Figure 4.
"""

import pyvista as pv

from vhm_viz import examples
from vhm_viz.plotting import jacobian_slice, measure_mesh_kwargs

scenario = examples.bar("bend-u", resolution=16)
scenario.solve()
section = jacobian_slice(scenario.surface, scenario.deformer.harmonic_map, resolution=120)
print(section)

# %%
plotter = pv.Plotter(shape=(1, 2), window_size=(1000, 600))
for column, (array, measure) in enumerate(
    [("jacobian_determinant", "determinant"), ("condition_number", "condition_number")]
):
    plotter.subplot(0, column)
    values = section[array]
    plotter.add_mesh(section, scalars=array, **measure_mesh_kwargs(measure, values))
    plotter.view_xz()
plotter.link_views()
plotter.show()
