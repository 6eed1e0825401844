"""What a fresh process imports before any work: only what the command uses.

A command pays for every library it imports, on every run; the dispatcher imports only
the subcommand the command line names, and the heavy libraries (PyVista, VTK, SciPy's
spatial module, the automatic cage) are imported where they are used. Each case runs in
a new interpreter and reads ``sys.modules`` there.
"""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import subprocess_env

#: Libraries that no help text and no numeric-core import needs.
HEAVY = ("pyvista", "vtkmodules", "scipy.spatial", "vhm_viz.autocage")


def _imported(code: str) -> tuple[list[str], set[str]]:
    """What a new interpreter prints running ``code``, and the modules it then holds."""
    probe = code + "\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))\n"
    res = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        env=subprocess_env(),
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    *printed, modules = res.stdout.splitlines()
    return printed, set(json.loads(modules))


def _heavy(modules: set[str]) -> list[str]:
    return sorted(m for m in modules for h in HEAVY if m == h or m.startswith(h + "."))


def test_the_numeric_core_imports_no_vtk_and_no_scipy_spatial():
    _, modules = _imported(
        "import vhm_viz.core, vhm_viz.core.deformer, vhm_viz.core.volume, vhm_viz.scene"
    )
    assert "vhm_viz.core.deformer" in modules
    assert not _heavy(modules)


@pytest.mark.parametrize(
    ("words", "overview"),
    [(["--help"], True), (["-h", "deform"], True), (["deform", "--help"], False),
     (["analyze", "--help"], False)],
)  # fmt: skip
def test_help_imports_only_what_it_shows(words, overview):
    code = (
        "import contextlib, io, sys\n"
        f"sys.argv = ['vhm-viz', *{words!r}]\n"
        "from vhm_viz.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
        "    try:\n"
        "        main()\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code == 0, exc.code\n"
        "assert 'usage: vhm-viz' in out.getvalue()\n"
    )
    code += "print(all(c in out.getvalue() for c in ('demo', 'cage', 'paraview')))\n"
    printed, modules = _imported(code)
    assert not _heavy(modules)
    others = {"vhm_viz.cli.cage", "vhm_viz.cli.demo", "vhm_viz.cli.anchors"}
    if overview:  # the overview lists every subcommand
        assert printed == ["True"]
        assert others <= modules
    else:  # a named subcommand's help: the other subcommands' modules stay unimported
        assert f"vhm_viz.cli.{words[0]}" in modules
        assert not modules & others


def test_an_unknown_command_still_lists_every_command():
    res = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", "defrom", "x.vtp"],
        capture_output=True,
        text=True,
        env=subprocess_env(),
        timeout=120,
    )
    assert res.returncode == 2
    assert "invalid choice: 'defrom'" in res.stderr
    for name in ("demo", "deform", "analyze", "cage", "anchors", "explore", "paraview"):
        assert name in res.stderr.split("choose from", 1)[1]


def _cube_scene(lo: float, hi: float) -> dict:
    """A 12-triangle cube cage over ``[lo, hi]^3``, outward; two anchors, a small shift."""
    corners = [[x, y, z] for x in (lo, hi) for y in (lo, hi) for z in (lo, hi)]
    faces = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # fmt: skip
    mid, span = (lo + hi) / 2, hi - lo
    held = [[mid, mid, lo + 0.25 * span], [mid, mid, hi - 0.25 * span]]
    return {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": {"vertices": corners, "faces": faces},
        "anchors": held,
        "constraints": {"positions": held, "targets": [held[0], [mid + 0.1, mid, held[1][2]]]},
        "mode": "rigid",
        "alpha": 0.01,
    }


def test_deforming_a_volume_imports_no_scipy_linalg(tmp_path):
    """The solver's factorisations and numba's LAPACK calls load SciPy's compiled LAPACK
    alone; ``scipy.linalg``'s package (all its submodules) stays unimported."""
    import pyvista as pv

    image = pv.ImageData(dimensions=(6, 6, 6), spacing=(1.0, 1.0, 1.0))
    image.point_data["density"] = np.arange(image.n_points, dtype=np.float32)
    image.save(tmp_path / "small.vti")
    (tmp_path / "scene.json").write_text(json.dumps(_cube_scene(-1.0, 6.0)))
    words = ["deform", str(tmp_path / "small.vti"), "--scene", str(tmp_path / "scene.json"),
             "-o", str(tmp_path / "bent.vts"), "-q"]  # fmt: skip
    code = f"from vhm_viz.cli import main\nassert main({words!r}) == 0\n"
    printed, modules = _imported(code)
    assert printed and printed[0].startswith("deformed 216 voxels")
    assert (tmp_path / "bent.vts").is_file()
    assert "scipy.linalg.cython_lapack" in modules  # what the solver calls
    assert "scipy.linalg" not in modules


def test_the_command_process_ends_as_python_would_but_for_the_teardown():
    """A command line's process ends without Python's teardown, but its threads are
    joined, its ``atexit`` handlers run, its output is flushed and its status kept."""
    code = (
        "import atexit, sys, threading, time\n"
        "atexit.register(lambda: print('atexit handler ran', file=sys.stderr))\n"
        "threading.Thread(target=lambda: (time.sleep(0.2), print('thread done'))).start()\n"
        "sys.argv = ['vhm-viz']\n"  # no subcommand: the overview, exit status 2
        "from vhm_viz.cli import main\n"
        "main()\n"
        "print('not reached')\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=subprocess_env(),
        timeout=120,
    )  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert "usage: vhm-viz" in res.stdout and "thread done" in res.stdout
    assert "not reached" not in res.stdout
    assert res.stderr.strip().endswith("atexit handler ran")
