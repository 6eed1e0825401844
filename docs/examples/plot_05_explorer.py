"""
The explorer, in one frame
==========================

``vhm-viz explore`` opens the Qt desktop explorer: load data and a cage, click to add
constraints, drag them and watch the map and its analysis update. With ``--screenshot``
it solves the scene, renders one frame to a PNG and exits, which is how this picture is
made (Qt off screen): the bar bent by 90 degrees inside its cage (wireframe), with its
constraints, the rotation gizmo of the Jacobian constraint (magenta) and the analysis
slice (red outline) coloured by det J.
"""

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

picture = Path(tempfile.mkdtemp()) / "explorer.png"
env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
command = [sys.executable, "-m", "vhm_viz.cli", "explore", "--bar", "bend-90"]
command += ["--colour", "determinant"]
command += ["--screenshot", str(picture), "--size", "900", "600"]
subprocess.run(command, env=env, check=True)

plt.figure(figsize=(9, 6))
plt.imshow(plt.imread(picture))
plt.axis("off")
plt.show()
