"""ParaView plugin loader for a checkout: runs vhm_viz's plugin file in this module.

The plugin has one home, ``vhm_viz/paraview_plugin/vhm_viz_paraview.py``, which the wheel
ships (``vhm-viz paraview`` prints where an installed copy is). This file lets ParaView load
it from the checkout's ``plugins/`` folder (``eval "$(bash plugins/paraview-env.sh)"`` puts
that folder on ``PV_PLUGIN_PATH``; or Tools > Manage Plugins > Load New): the plugin's code
is executed here, so its filters are declared by this module exactly as by the file itself.
"""

from pathlib import Path

_PLUGIN = Path(__file__).resolve().parents[1] / "vhm_viz/paraview_plugin/vhm_viz_paraview.py"
exec(compile(_PLUGIN.read_text(), str(_PLUGIN), "exec"))
