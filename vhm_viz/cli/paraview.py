"""``vhm-viz paraview [--shell] [PROGRAM ARGS...]``: where the ParaView plugin is, and its set-up.

The plugin and the example scenes ship inside the package, so an installed ``vhm_viz``
(a wheel, no checkout) finds them here. Without arguments the command prints the plugin's
file, the example scenes' folder and the shell lines that make ParaView load the plugin;
``--shell`` prints only those lines (``eval "$(vhm-viz paraview --shell)"``); with a
``PROGRAM`` (``paraview``, ``pvpython``, ``pvbatch`` and its arguments) it runs it in that
environment and returns its exit status.

ParaView's Python must import ``vhm_viz`` but not this environment's own VTK (two VTKs in
one process crash): when the package sits next to a pip-installed VTK, ``PYTHONPATH`` names
a folder that holds only a link to the package (``--site``, made on demand). A folder in
it holds a ``sitecustomize.py`` with which ParaView 5.11's plugin loader runs on Python
3.11. ParaView's Python also needs numba built for its own Python and numpy; from a
checkout, ``eval "$(bash plugins/paraview-env.sh)"`` installs it and does all of this.
"""

from __future__ import annotations

import argparse
import os
import subprocess
from importlib import resources
from pathlib import Path

PLUGIN_FILE = "vhm_viz_paraview.py"


#: What ``--timings`` reports, besides "other".
TIMING_STAGES = "program (the ParaView program run, if any)"

HELP = "print the ParaView plugin's path and set-up lines, or run ParaView with it"

DESCRIPTION = (
    "Print where the installed ParaView plugin and example scenes are and "
    "the shell lines that make ParaView load the plugin; with PROGRAM (paraview, "
    "pvpython, pvbatch ...), run it with those settings."
)


def add_arguments(p) -> None:
    """The ``paraview`` subcommand's arguments."""
    p.add_argument(
        "--shell",
        action="store_true",
        help='print only the export lines, for eval "$(vhm-viz paraview --shell)"',
    )
    p.add_argument(
        "--site",
        metavar="DIR",
        default=None,
        help="folder for the link to the package when its own folder also holds a pip VTK "
        "(default: $XDG_CACHE_HOME/vhm_viz/paraview-site, or ~/.cache/...)",
    )
    p.add_argument(
        "program",
        nargs=argparse.REMAINDER,
        metavar="PROGRAM ARGS",
        help="run this program (e.g. paraview, pvpython script.py) with the plugin loaded",
    )


def package_folder() -> Path:
    """The installed ``vhm_viz`` package's folder."""
    return Path(str(resources.files("vhm_viz")))


def plugin_path() -> Path:
    """The ParaView plugin file shipped in the package (its folder goes on PV_PLUGIN_PATH)."""
    return package_folder() / "paraview_plugin" / PLUGIN_FILE


def scenes_folder() -> Path:
    """The folder of the example scenes shipped in the package (scene, cage, anchors)."""
    return package_folder() / "scenes"


def python_path(site: str | None = None) -> Path:
    """A folder from which ParaView's Python imports this ``vhm_viz`` and no other package.

    The package's parent folder when it holds no VTK of its own (a checkout); otherwise
    ``site``, made with a link named ``vhm_viz`` to the package.
    """
    package = package_folder()
    parent = package.parent
    if not (parent / "vtkmodules").exists() and not (parent / "vtk.py").exists():
        return parent
    folder = Path(site) if site is not None else _cache_site()
    folder.mkdir(parents=True, exist_ok=True)
    link = folder / "vhm_viz"
    if link.is_symlink() and link.resolve() != package.resolve():
        link.unlink()
    if not link.exists():
        link.symlink_to(package, target_is_directory=True)
    return folder


#: ``sitecustomize.py`` of :func:`shim_folder`: ParaView 5.11's Python plugin loader calls
#: ``inspect.getargspec``, which Python 3.11 removed (``getfullargspec`` has its ``.args``).
SHIM = """\
# Written by vhm-viz paraview: ParaView 5.11's Python plugin loader calls
# inspect.getargspec, removed in Python 3.11; getfullargspec has the same .args.
import inspect

if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec
"""


def _cache_site() -> Path:
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "vhm_viz" / "paraview-site"


def shim_folder(site: str | None = None) -> Path:
    """A folder whose ``sitecustomize.py`` lets ParaView 5.11 load Python plugins on 3.11.

    The folder ``startup`` in ``site`` (default: the user's cache), holding that file
    alone (no package: it comes first on ``PYTHONPATH``); the file is written when
    missing or different.
    """
    folder = (Path(site) if site is not None else _cache_site()) / "startup"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "sitecustomize.py"
    if not path.is_file() or path.read_text() != SHIM:
        tmp = folder / f".sitecustomize.{os.getpid()}.tmp"
        tmp.write_text(SHIM)
        os.replace(tmp, path)
    return folder


def environment(site: str | None = None) -> dict[str, str]:
    """The variables that make ParaView load the plugin and import ``vhm_viz``."""
    folders = [str(shim_folder(site)), str(python_path(site))]
    return {
        "PV_PLUGIN_PATH": str(plugin_path().parent),
        "PYTHONPATH": os.pathsep.join(dict.fromkeys(folders)),
    }


def _prepend(name: str, value: str) -> str:
    return f'export {name}="{value}${{{name}:+:${name}}}"'


def run(args: argparse.Namespace) -> int:
    """Print the plugin's set-up, or run a ParaView program with it; returns the status."""
    settings = environment(args.site)
    program = [a for a in args.program if a != "--"] if args.program else []
    if program:
        env = dict(os.environ)
        for name, value in settings.items():
            env[name] = value + (os.pathsep + env[name] if env.get(name) else "")
        with args.timer.stage("program"):
            return subprocess.call(program, env=env)
    lines = [_prepend(name, value) for name, value in settings.items()]
    if not args.shell:
        print(f"ParaView plugin: {plugin_path()}")
        print(f"example scenes:  {scenes_folder()}")
        print('set-up (or: eval "$(vhm-viz paraview --shell)"; ParaView\'s Python also needs')
        print("numba for its own numpy: from a checkout, plugins/paraview-env.sh installs it):")
    print("\n".join(lines))
    return 0
