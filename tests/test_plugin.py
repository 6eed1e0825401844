"""The ParaView plugin, run for real on VTK with ParaView's decorators stubbed out.

ParaView is not installable here; its ``paraview.util.vtkAlgorithm`` module provides VTK's own
``VTKPythonAlgorithmBase`` plus ``smproxy``/``smproperty``/``smdomain``/``smhint`` decorators
that only attach XML for the proxy. Stubbing the decorators as no-ops runs the plugin's
pipeline code unchanged: the plugin file is loaded as a module and its filter class is driven
through a real VTK pipeline (a ``vtkOBJReader`` on a real model), then compared with the
Python API on the same scene file.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from conftest import data_path

pv = pytest.importorskip("pyvista")

from vtkmodules.util import numpy_support as ns  # noqa: E402
from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringOutputWindow  # noqa: E402
from vtkmodules.vtkIOGeometry import vtkOBJReader  # noqa: E402

# the checkout's loader, which runs the plugin shipped in the package
PLUGIN = Path(__file__).resolve().parents[1] / "plugins" / "vhm_viz_paraview.py"
FILTERS = ("VHMHarmonicDeformation", "VHMJacobianAnalysis", "VHMResampleToImage")


class _NoOpDecorators:
    def __getattr__(self, name):
        def factory(*args, **kwargs):
            return lambda obj: obj

        return factory


@pytest.fixture
def plugin(monkeypatch):
    return _load_plugin(PLUGIN, monkeypatch)


def _load_plugin(path, monkeypatch):
    """The plugin file loaded as ParaView does (a module named after the file)."""
    from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase

    algorithm = types.ModuleType("paraview.util.vtkAlgorithm")
    algorithm.VTKPythonAlgorithmBase = VTKPythonAlgorithmBase
    for name in ("smproxy", "smproperty", "smdomain", "smhint"):
        setattr(algorithm, name, _NoOpDecorators())
    monkeypatch.setitem(sys.modules, "paraview", types.ModuleType("paraview"))
    monkeypatch.setitem(sys.modules, "paraview.util", types.ModuleType("paraview.util"))
    monkeypatch.setitem(sys.modules, "paraview.util.vtkAlgorithm", algorithm)
    spec = importlib.util.spec_from_file_location("vhm_viz_paraview", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_checkout_loader_declares_the_installed_plugins_filters(monkeypatch):
    """plugins/vhm_viz_paraview.py and the package's plugin (what ``vhm-viz paraview``
    names) declare the same filters, in a module named after the file as ParaView's loader
    names it."""
    from vhm_viz.cli.paraview import plugin_path

    loader = _load_plugin(PLUGIN, monkeypatch)
    packaged = _load_plugin(plugin_path(), monkeypatch)
    for name in FILTERS:
        assert getattr(loader, name).__module__ == "vhm_viz_paraview"
        assert getattr(packaged, name).__module__ == "vhm_viz_paraview"
        assert getattr(loader, name).__doc__ == getattr(packaged, name).__doc__


@contextlib.contextmanager
def _messages(monkeypatch):
    """Collect what the plugin shows in VTK's output window (ParaView's Output Messages).

    The plugin reports an error as one line there and leaves an empty output; an exception
    escaping RequestData would instead reach ``sys.excepthook`` (VTK's ``PyErr_Print``), so
    those are collected too: there must be none.
    """
    escaped: list[BaseException] = []
    monkeypatch.setattr(sys, "excepthook", lambda tp, value, tb: escaped.append(value))
    previous = vtkOutputWindow.GetInstance()
    window = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(window)
    lines: list[str] = []
    try:
        yield lines
    finally:
        vtkOutputWindow.SetInstance(previous)
        lines.extend(line for line in window.GetOutput().splitlines() if line.strip())
        assert escaped == [], f"an exception escaped RequestData: {escaped}"


# ------------------------------------------------------------------------------- real data


def _hand_scene(tmp_path) -> Path:
    """A scene file for the hand: its cage and rigidity polylines next to it (relative
    paths), the wrist held, the index tip moved and the palm's Jacobian fixed."""
    from vhm_viz.io import read_polylines

    for name in ("cage.obj", "polylines.off"):
        shutil.copy(data_path("hand", name), tmp_path / name)
    pts, _ = read_polylines(tmp_path / "polylines.off")
    low = pts[np.argsort(pts[:, 2])[:3]]  # the wrist end of the medial axis
    tip = pts[np.argmax(pts[:, 2])]
    positions = np.vstack([low, tip])
    targets = np.vstack([low, tip + [1.5, -0.5, -2.0]])
    scene = {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": "cage.obj",
        "anchors": {"polylines": "polylines.off", "count": 24},
        "constraints": {
            "positions": positions.tolist(),
            "targets": targets.tolist(),
            "jacobian_points": [low[0].tolist()],
            "jacobians": [np.eye(3).tolist()],
        },
        "solver": {"tolerance": 1e-9, "max_iterations": 3000},
    }
    path = tmp_path / "hand.json"
    path.write_text(json.dumps(scene))
    return path


def _obj_reader(path):
    reader = vtkOBJReader()
    reader.SetFileName(str(path))
    reader.Update()
    return reader


def test_plugin_deforms_real_data_like_the_python_api(plugin, tmp_path):
    from vhm_viz.scene import Scene

    scene_path = _hand_scene(tmp_path)
    reader = _obj_reader(data_path("hand", "hand.obj"))
    rest = ns.vtk_to_numpy(reader.GetOutput().GetPoints().GetData()).astype(np.float64)
    assert len(rest) > 3000

    flt = plugin.VHMHarmonicDeformation()
    flt.SetSceneFile(str(scene_path))
    for name in ("displacement", "jacobian_determinant", "condition_number"):
        flt.GetOutputArrays().EnableArray(name)  # the OutputArrays checklist
    flt.SetInputConnection(0, reader.GetOutputPort())
    flt.Update()
    out = pv.wrap(flt.GetOutputDataObject(0))

    # the reference: the Python API on the same file, evaluated at the reader's points
    scene = Scene.load(scene_path)
    dfm = scene.build()
    (report,) = scene.solve(dfm)
    assert report.converged
    binding = dfm.bind(rest)
    expected = binding.deform()
    jac = binding.jacobians()
    diag = float(np.linalg.norm(rest.max(0) - rest.min(0)))

    assert isinstance(out, pv.PolyData)
    assert out.n_points == len(rest) and out.n_cells == reader.GetOutput().GetNumberOfCells()
    np.testing.assert_allclose(out.points, expected, rtol=0, atol=1e-9 * diag)
    # a real deformation, not the identity: the tip moved by about its target offset
    assert np.abs(expected - rest).max() > 0.05 * diag
    np.testing.assert_allclose(
        out.point_data["displacement"], expected - rest, rtol=0, atol=1e-9 * diag
    )
    np.testing.assert_allclose(
        out.point_data["jacobian_determinant"], np.linalg.det(jac), rtol=1e-8
    )
    sv = np.linalg.svd(jac, compute_uv=False)
    np.testing.assert_allclose(out.point_data["condition_number"], sv[:, 0] / sv[:, 2], rtol=1e-8)
    # the constraint is met through the plugin too
    c = scene.constraints
    moved = dfm.harmonic_map.map(c["positions"])
    np.testing.assert_allclose(moved, c["targets"], atol=1e-6 * diag)


@pytest.mark.qt_no_exception_capture
def test_plugin_outside_points_fail_or_pass_through(plugin, tmp_path, monkeypatch):
    from vhm_viz.io import read_cage

    scene_path = _hand_scene(tmp_path)
    cage = read_cage(tmp_path / "cage.obj")
    hand = _obj_reader(data_path("hand", "hand.obj")).GetOutput()
    rest = ns.vtk_to_numpy(hand.GetPoints().GetData()).astype(np.float64)
    far = cage.bounds[1] + 1.0  # outside the cage's bounding box
    cloud = pv.PolyData(np.vstack([rest[:200], far]))
    flt = plugin.VHMHarmonicDeformation()
    flt.SetSceneFile(str(scene_path))
    flt.SetInputDataObject(0, cloud)
    with _messages(monkeypatch) as lines:
        flt.Update()
    assert len(lines) == 1 and "VHM Harmonic Deformation: " in lines[0], lines
    assert "outside the cage" in lines[0] and "200" in lines[0]  # names the point
    assert flt.GetOutputDataObject(0).GetNumberOfPoints() == 0

    flt.SetOutsidePolicyIndex(1)  # "Pass through"
    flt.Update()
    out = pv.wrap(flt.GetOutputDataObject(0))
    flags = np.asarray(out.point_data["vhm_outside"])
    assert flags.dtype == np.uint8
    np.testing.assert_array_equal(flags, (~cage.contains(cloud.points)).astype(np.uint8))
    np.testing.assert_array_equal(out.points[200], far)


def test_plugin_deforms_a_point_cloud_with_a_scene_file(plugin, tmp_path):
    from vhm_viz import examples
    from vhm_viz.scene import Scene

    scenario = examples.bar("bend-90")
    scene_path = tmp_path / "bend90.json"
    Scene.from_deformer(scenario.deformer).save(scene_path)
    # the reference: the same scene built and solved directly
    scene = Scene.load(scene_path)
    dfm = scene.build()
    scene.solve(dfm)
    surface = pv.PolyData(scenario.points[::7].copy())  # a point cloud inside the cage
    expected, jac, _ = dfm.harmonic_map.evaluate(surface.points, order=1)

    flt = plugin.VHMHarmonicDeformation()
    flt.SetSceneFile(str(scene_path))
    flt.GetOutputArrays().EnableArray("displacement")
    flt.GetOutputArrays().EnableArray("jacobian_determinant")
    flt.SetInputDataObject(0, surface)
    flt.Update()
    out = pv.wrap(flt.GetOutputDataObject(0))
    assert isinstance(out, pv.PolyData) and out.n_points == surface.n_points
    np.testing.assert_allclose(out.points, expected, atol=1e-9)
    np.testing.assert_allclose(out.point_data["displacement"], expected - surface.points, atol=1e-9)
    det = np.asarray(out.point_data["jacobian_determinant"])
    np.testing.assert_allclose(det, np.linalg.det(jac), rtol=1e-9)
    assert "condition_number" not in out.point_data  # not asked for


# pytest-qt (loaded for the explorer's tests) would otherwise turn the exception VTK prints
# through sys.excepthook into a test error
@pytest.mark.qt_no_exception_capture
def test_plugin_without_scene_fails_clearly_and_leaves_no_stale_output(
    plugin, tmp_path, monkeypatch
):
    from vhm_viz import examples
    from vhm_viz.scene import Scene

    scenario = examples.bar("bend-90")
    scene_path = tmp_path / "bend90.json"
    Scene.from_deformer(scenario.deformer).save(scene_path)
    cloud = pv.PolyData(scenario.points[::25].copy())

    flt = plugin.VHMHarmonicDeformation()
    flt.SetInputDataObject(0, cloud)
    with _messages(monkeypatch) as lines:
        flt.Update()
    assert lines == ["VHM Harmonic Deformation: set SceneFile (a vhm_viz scene JSON)"]
    assert flt.GetOutputDataObject(0).GetNumberOfPoints() == 0

    # a successful update, then the scene is cleared: the old result must not linger
    flt.SetSceneFile(str(scene_path))
    flt.Update()
    assert flt.GetOutputDataObject(0).GetNumberOfPoints() == cloud.n_points
    assert not np.allclose(pv.wrap(flt.GetOutputDataObject(0)).points, cloud.points, atol=1e-3)
    flt.SetSceneFile("")
    with _messages(monkeypatch) as lines:
        flt.Update()
    assert lines == ["VHM Harmonic Deformation: set SceneFile (a vhm_viz scene JSON)"]
    assert flt.GetOutputDataObject(0).GetNumberOfPoints() == 0

    # a missing scene file names the file
    flt.SetSceneFile(str(tmp_path / "missing.json"))
    with _messages(monkeypatch) as lines:
        flt.Update()
    assert len(lines) == 1 and "no such scene file" in lines[0] and "missing.json" in lines[0]
    assert flt.GetOutputDataObject(0).GetNumberOfPoints() == 0
