"""The package stands alone: a wheel built from the project carries what a user without a
checkout needs (the ParaView plugin, the example scenes, the type marker, the licence),
and its ``vhm-viz`` runs from the installed copy, outside the repository."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

REPO = Path(__file__).resolve().parents[1]
SCENES = {"bar_scene.json", "bar_cage.obj", "bar_anchors.json"}
SCENES |= {"head_scene.json", "head_cage.obj", "head_anchors.json"}


def test_licence_is_the_declared_bsd_3_clause():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert project["license"] == "BSD-3-Clause"
    text = (REPO / "LICENSE").read_text()
    assert text.startswith("BSD 3-Clause License")
    assert "vhm_viz developers" in text
    assert "Neither the name of the copyright holder" in text


def test_version_has_one_source():
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert "version" not in pyproject["project"]
    assert "version" in pyproject["project"]["dynamic"]
    assert pyproject["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "vhm_viz.__version__"}
    init = (REPO / "vhm_viz" / "__init__.py").read_text()
    (version,) = re.findall(r'^__version__ = "([^"]+)"$', init, flags=re.M)
    out = _vhm_viz("--version", cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert out.stdout.strip() == f"vhm-viz {version}"


def _vhm_viz(*args, cwd, env):
    """``vhm-viz ARGS`` of the copy that ``env``'s PYTHONPATH finds, run in ``cwd``."""
    run = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    return run


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """A wheel built (``pip wheel --no-deps``) from a copy of the project's sources."""
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(REPO / name, src / name)
    shutil.copytree(REPO / "vhm_viz", src / "vhm_viz", ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path_factory.mktemp("wheel")
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(src)],
        capture_output=True,
        text=True,
    )
    assert build.returncode == 0, build.stderr[-2000:]
    (whl,) = out.glob("vhm_viz-*.whl")
    return whl


def test_wheel_carries_plugin_scenes_type_marker_and_licence(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "vhm_viz/py.typed" in names
    assert "vhm_viz/paraview_plugin/vhm_viz_paraview.py" in names
    assert {f"vhm_viz/scenes/{s}" for s in SCENES} <= names
    assert any(re.search(r"\.dist-info/(licenses/)?LICENSE$", n) for n in names)
    metadata = next(n for n in names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(wheel).read(metadata).decode()
    init = (REPO / "vhm_viz" / "__init__.py").read_text()
    (version,) = re.findall(r'^__version__ = "([^"]+)"$', init, flags=re.M)
    assert f"\nVersion: {version}\n" in text
    assert "Requires-Dist: pyvista>=0.48" in text
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert "vhm-viz = vhm_viz.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()


def test_installed_copy_prints_its_plugin_and_scenes_outside_the_checkout(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    run = _vhm_viz("paraview", cwd=elsewhere, env=env)
    plugin = site / "vhm_viz" / "paraview_plugin" / "vhm_viz_paraview.py"
    assert f"ParaView plugin: {plugin}" in run.stdout
    assert f"example scenes:  {site / 'vhm_viz' / 'scenes'}" in run.stdout
    assert f'export PV_PLUGIN_PATH="{plugin.parent}' in run.stdout
    # PV_PLUGIN_PATH's folder holds the plugin only: ParaView loads every plugin there
    assert [p.name for p in plugin.parent.iterdir()] == ["vhm_viz_paraview.py"]

    # --shell: only export lines, and a program run with them sees the same settings
    shell = _vhm_viz("paraview", "--shell", cwd=elsewhere, env=env)
    assert all(line.startswith("export ") for line in shell.stdout.splitlines())
    probe = "import os, vhm_viz; print(os.environ['PV_PLUGIN_PATH']); print(vhm_viz.__file__)"
    bare = {k: v for k, v in env.items() if k != "PV_PLUGIN_PATH"}
    ran = _vhm_viz("paraview", sys.executable, "-c", probe, cwd=elsewhere, env=bare)
    plugin_path, module = ran.stdout.splitlines()
    assert plugin_path == str(plugin.parent)
    assert Path(module).resolve() == (site / "vhm_viz" / "__init__.py").resolve()

    # the installed copy's command line knows the demo, and its scenes are complete
    demo = _vhm_viz("demo", "--help", cwd=elsewhere, env=env)
    assert "--output" in demo.stdout
    assert SCENES <= {p.name for p in (site / "vhm_viz" / "scenes").iterdir()}


def test_scenes_are_found_through_the_package():
    from vhm_viz.cli.paraview import plugin_path, scenes_folder

    assert plugin_path().is_file()
    assert SCENES <= {p.name for p in scenes_folder().iterdir()}


def test_paraview_python_path_leaves_a_pip_vtk_out(wheel, tmp_path):
    """Next to a pip-installed VTK, PYTHONPATH names a folder holding only the package."""
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    (site / "vtkmodules").mkdir()  # as in a virtual environment's site-packages
    link_site = tmp_path / "pv-site"
    env = {**os.environ, "PYTHONPATH": str(site)}
    run = _vhm_viz("paraview", "--shell", "--site", str(link_site), cwd=tmp_path, env=env)
    assert f'export PYTHONPATH="{link_site / "startup"}:{link_site}$' in run.stdout
    assert sorted(p.name for p in link_site.iterdir()) == ["startup", "vhm_viz"]
    assert [p.name for p in (link_site / "startup").iterdir()] == ["sitecustomize.py"]
    assert (link_site / "vhm_viz").resolve() == (site / "vhm_viz").resolve()
