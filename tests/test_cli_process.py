"""The process a command runs in: collector and OpenMP threads as the command line sets them.

A ``vhm-viz`` process imports its libraries with the garbage collector off, then freezes
what the imports made out of the collector's passes and turns it on again for the
command's own objects; the numeric core has the compiled kernels' OpenMP threads sleep
between parallel loops unless the user chose otherwise (``OMP_WAIT_POLICY``), and a
command runs VTK's parallel loops on threads (``VTK_SMP_BACKEND_IN_USE``). Each
case runs the command in a new interpreter and reads that state from its ``atexit``
handler, which runs once the command is done.
"""

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import data_path, subprocess_env

SCENE = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"


def _process_state(tmp_path: Path, policy: str | None, backend: str | None) -> list[str]:
    """The collector, OpenMP's wait policy and VTK's SMP backend after a deform.

    ``gc.isenabled()``, ``gc.get_freeze_count() > 0``, ``OMP_WAIT_POLICY`` and
    ``vtkSMPTools.GetBackend()``, with ``policy`` and ``backend`` set in the environment
    (None: unset).
    """
    head = data_path("volumes", "headsq_64x64x93.vti")
    words = ["deform", str(head), "--scene", str(SCENE), "-o", str(tmp_path / "bent.vti"), "-q"]
    code = (
        "import atexit, gc, os, sys\n"
        "from vtkmodules.vtkCommonCore import vtkSMPTools\n"
        "atexit.register(lambda: print(gc.isenabled(), gc.get_freeze_count() > 0,\n"
        "                              os.environ.get('OMP_WAIT_POLICY'),\n"
        "                              vtkSMPTools.GetBackend(), file=sys.stderr))\n"
        f"sys.argv = ['vhm-viz', *{words!r}]\n"
        "from vhm_viz.cli import main\n"
        "main()\n"
    )
    env = subprocess_env()
    for name, value in (("OMP_WAIT_POLICY", policy), ("VTK_SMP_BACKEND_IN_USE", backend)):
        env.pop(name, None)
        if value is not None:
            env[name] = value
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600
    )
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "bent.vti").is_file()
    return res.stderr.strip().splitlines()[-1].split()


@pytest.mark.parametrize(
    ("policy", "backend", "expected"),
    [(None, None, ["passive", "STDThread"]), ("active", "Sequential", ["active", "Sequential"])],
)
def test_a_command_process_collects_again_and_its_threads_fit(tmp_path, policy, backend, expected):
    enabled, frozen, *seen = _process_state(tmp_path, policy, backend)
    assert enabled == "True"  # the collector is on again for the command's objects
    assert frozen == "True"  # the start-up's objects are out of its passes
    # OpenMP's threads sleep between loops and VTK's loops run on threads, unless the user
    # chose otherwise
    assert seen == expected


def test_a_command_called_from_python_leaves_the_collector_alone(tmp_path):
    """``main(argv)`` runs inside someone else's process: the collector as it was."""
    import gc

    from vhm_viz.cli import main

    head = data_path("volumes", "headsq_64x64x93.vti")
    before = (gc.isenabled(), gc.get_freeze_count())
    words = ["deform", str(head), "--scene", str(SCENE), "-o", str(tmp_path / "bent.vts"), "-q"]
    assert main(words) == 0
    assert (gc.isenabled(), gc.get_freeze_count()) == before


@pytest.mark.parametrize(("policy", "expected"), [(None, "passive"), ("active", "active")])
def test_the_numeric_core_has_kernel_threads_sleep_unless_told(policy, expected):
    """Used from Python (a notebook, ParaView), the core sets OpenMP's policy as a command."""
    env = subprocess_env()
    env.pop("OMP_WAIT_POLICY", None)
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy
    code = "import os, vhm_viz.core.volume; print(os.environ.get('OMP_WAIT_POLICY'))"
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == [expected]
