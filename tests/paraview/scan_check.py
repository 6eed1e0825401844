"""Open scans with the VHM Medical Image Reader and resample one through a scene, in pvpython.

Usage: ``pvpython scan_check.py CONFIG.json`` where CONFIG holds ``scans`` (a list of
``[input, output.vti]``: each scan as the reader gives it) and ``resample`` (``[input,
scene, output.vti]``: the reader's output through "VHM Resample To Image").
"""

import json
import sys

from paraview.simple import SaveData, UpdatePipeline, VHMMedicalImageReader, VHMResampleToImage

config = json.load(open(sys.argv[1]))
for path, output in config["scans"]:
    reader = VHMMedicalImageReader(FileName=path)
    UpdatePipeline(proxy=reader)
    SaveData(output, proxy=reader)
path, scene, output = config["resample"]
flt = VHMResampleToImage(
    Input=VHMMedicalImageReader(FileName=path), SceneFile=scene, DisplacementField=1
)
UpdatePipeline(proxy=flt)
SaveData(output, proxy=flt)
print("vhm-scan-check: done")
