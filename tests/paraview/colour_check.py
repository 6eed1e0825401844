"""pvpython: vhm_viz.paraview.color_by_measure follows vhm_viz.colours (run by test_paraview)."""

import json
import sys

import numpy as np
import paraview.simple as pvs

from vhm_viz import colours
from vhm_viz.paraview import color_by_measure


def _colour(lut, value):
    rgb = [0.0, 0.0, 0.0]
    lut.GetClientSideObject().GetColor(value, rgb)
    return rgb


# a sphere with det J values spread over two orders of magnitude, some folded
sphere = pvs.Sphere(ThetaResolution=64, PhiResolution=64)
calc = pvs.Calculator(Input=sphere, ResultArrayName="jacobian_determinant")
calc.Function = "exp(4*coordsX) - 0.2"
calc2 = pvs.Calculator(Input=calc, ResultArrayName="condition_number")
calc2.Function = "1 + 9*abs(coordsY)"
pvs.UpdatePipeline(proxy=calc2)
out = {}
for name in ("jacobian_determinant", "condition_number"):
    _, lut = color_by_measure(calc2, name)
    rgb = np.asarray(lut.RGBPoints).reshape(-1, 4)
    out[name] = {
        "range": [float(rgb[0, 0]), float(rgb[-1, 0])],
        "log": int(lut.UseLogScale),
        "below": [int(lut.UseBelowRangeColor), list(lut.BelowRangeColor)],
        "mid_rgb": _colour(lut, 1.0) if name == "jacobian_determinant" else None,
    }
# the values, computed independently of ParaView's pipeline
pts = np.asarray(pvs.servermanager.Fetch(sphere).GetPoints().GetData())
out["det_expected"] = list(colours.det_range(np.exp(4 * pts[:, 0]) - 0.2))
out["cond_expected"] = list(colours.cond_range(1 + 9 * np.abs(pts[:, 1])))
json.dump(out, open(sys.argv[1], "w"))
