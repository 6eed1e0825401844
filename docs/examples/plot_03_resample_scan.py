"""
Resample a CT scan through the map
==================================

A volume is deformed on a regular grid: each output voxel is pulled back to its
pre-image through the inverse map and the input is sampled there. The example scene
``head_scene.json`` (shipped in the package, with its cage and anchors) bends the top of
the head CT ``headsq_64x64x93.vti`` sideways, its base held in place; the picture shows
the isosurface at 1100 before (left) and after (right), with each volume's box.
"""

from importlib import resources

import pyvista as pv

import vhm_viz
from vhm_viz import examples

# scans open with vhm_viz.read_dataset, in ITK's physical (LPS) frame
head = vhm_viz.read_dataset(examples.data_dir() / "volumes" / "headsq_64x64x93.vti")
scene = resources.files("vhm_viz") / "scenes" / "head_scene.json"
print(head)

# %%
# ``image.vhm.resample`` takes a deformer, a map, a :class:`~vhm_viz.scene.Scene` or a
# scene file; the output grid keeps the input's spacing and holds the whole deformed
# volume.
bent = head.vhm.resample(str(scene))
print(bent.dimensions, "voxels; without a pre-image:", int((bent["vtkValidPointMask"] == 0).sum()))

# %%
plotter = pv.Plotter(shape=(1, 2), window_size=(1000, 500))
for column, (volume, title) in enumerate([(head, "rest"), (bent, "resampled bend")]):
    plotter.subplot(0, column)
    plotter.add_mesh(volume.contour([1100.0]), color="wheat")
    plotter.add_mesh(volume.outline(), color="grey")
    plotter.add_text(title, font_size=12, color="black")
    plotter.view_xz()
    plotter.camera.Elevation(20)
    plotter.reset_camera()
plotter.show()
