"""ParaView GUI state of the README's screenshot: the head CT bent by VHM Harmonic Deformation.

Run from the project root, after ``eval "$(bash plugins/paraview-env.sh)"``:
``paraview --script=docs/paraview_head_ct.py``. The scene in docs/examples/ names its cage and
anchors, computed once with ``vhm-viz cage`` / ``vhm-viz anchors``.
"""

import paraview.simple as pvs

from vhm_viz.paraview import color_by_measure

head = pvs.XMLImageDataReader(
    registrationName="headsq_64x64x93.vti",
    FileName=["../shared/data/volumes/headsq_64x64x93.vti"],
)
cage = pvs.WavefrontOBJReader(
    registrationName="head_cage.obj", FileName="docs/examples/head_cage.obj"
)
bent = pvs.VHMHarmonicDeformation(registrationName="VHMHarmonicDeformation1", Input=head, Cage=cage)
bent.SceneFile = "docs/examples/head_scene.json"
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
