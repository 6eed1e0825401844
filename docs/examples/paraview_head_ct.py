"""
ParaView: the head CT bent by the plugin
========================================

A ParaView state script (shown, not run here: it needs ParaView's ``pvpython`` or GUI).
The plugin's *VHM Harmonic Deformation* filter bends the head CT with the example scene
``head_scene.json``; the skin isosurface is coloured by det J with
:func:`vhm_viz.paraview.color_by_measure`, the same convention as the explorer and the
figures.

Set up ParaView's Python and open the state, from the repository root::

    eval "$(bash plugins/paraview-env.sh)"       # from a checkout
    eval "$(vhm-viz paraview --shell)"           # or from an installed vhm_viz
    paraview --script=docs/examples/paraview_head_ct.py

.. image:: /images/paraview_head_ct.png
   :alt: ParaView with the VHM Harmonic Deformation panel and the head CT bent, coloured by det J
"""


import paraview.simple as pvs

from vhm_viz.paraview import color_by_measure

head = pvs.XMLImageDataReader(
    registrationName="headsq_64x64x93.vti",
    FileName=["../shared/data/volumes/headsq_64x64x93.vti"],
)
cage = pvs.WavefrontOBJReader(
    registrationName="head_cage.obj", FileName="vhm_viz/scenes/head_cage.obj"
)
bent = pvs.VHMHarmonicDeformation(registrationName="VHMHarmonicDeformation1", Input=head, Cage=cage)
bent.SceneFile = "vhm_viz/scenes/head_scene.json"
bent.OutputArrays = ["jacobian_determinant"]
skin = pvs.Contour(registrationName="Contour1", Input=bent)
skin.ContourBy = ["POINTS", "ImageScalars"]
skin.Isosurfaces = [1100.0]
skin.ComputeScalars = 1
view = pvs.GetActiveViewOrCreate("RenderView")
# the one convention of the explorer and the figures: Cool to Warm on a log scale,
# symmetric about det J = 1 (no volume change), folds below the range
shown, lut = color_by_measure(skin, "jacobian_determinant", view)
shown.SetScalarBarVisibility(view, True)
pvs.Show(head, view).SetRepresentationType("Outline")
pvs.Hide(bent, view)
view.CameraPosition = [-250, -500, 300]
view.CameraFocalPoint = [100, 100, 69]
view.CameraViewUp = [0, 0, 1]
view.ResetCamera()
pvs.SetActiveSource(bent)
pvs.Render()
