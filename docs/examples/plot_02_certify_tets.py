"""
Certify a tet mesh: does the map fold anywhere?
===============================================

Sampling ``det J`` at the vertices cannot prove that a map folds nowhere: it can fold
between the samples. :func:`vhm_viz.certify_injectivity` covers the region with cubes and
bounds ``det J`` on each whole cube from the map's closed-form derivatives; the answer is
*certified*, *not injective* (with a witness point) or *undecided*.

Here the bar is a tetrahedral mesh bent by 90 degrees. Its cells are coloured by the
``det F`` of their linear deformation (``cell_jacobian_determinant``), and the title
gives the certificate's answer for the whole solid.
"""

import numpy as np
import pyvista as pv

from vhm_viz import examples
from vhm_viz.plotting import measure_mesh_kwargs

scenario = examples.bar("bend-90", resolution=12)
scenario.solve()
points, tets = examples.bar_tets(6)
cells = np.column_stack([np.full(len(tets), 4), tets]).ravel()
mesh = pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA), points)
print(mesh)

# %%
# The certificate, over the tetrahedra of the mesh (not the cage's whole interior).
certificate = mesh.vhm.certify(scenario.deformer)
print(certificate.status, f"after {certificate.cubes} cubes, min det J {certificate.min_det:.3f}")

# %%
# The cell analysis of the deformed mesh, drawn on the deformed cells.
analysed = mesh.vhm.analyze(scenario.deformer)
bent = mesh.vhm.deform(scenario.deformer)
bent.cell_data["cell_jacobian_determinant"] = analysed["cell_jacobian_determinant"]
det = bent["cell_jacobian_determinant"]
print(f"{int(analysed['cell_inverted'].sum())} inverted cells of {mesh.n_cells}")

plotter = pv.Plotter(window_size=(800, 600))
plotter.add_mesh(
    bent,
    scalars="cell_jacobian_determinant",
    show_edges=True,
    **measure_mesh_kwargs("determinant", det, scalar_bar_args={"title": "cell det F"}),
)
plotter.add_text(f"certificate: {certificate.status}", font_size=14, color="black")
plotter.view_xz()
plotter.show()
