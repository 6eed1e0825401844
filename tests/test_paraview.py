"""The ParaView plugin in Debian's real ParaView: pvpython, pvbatch and mpiexec -n 2 pvbatch.

Each test runs ``tests/paraview/run_filter.py`` in ParaView (set up by
``plugins/paraview-env.sh``), gathers the result through ParaView's parallel XML writers
(each rank writes its piece) and compares it, point by point through the ``vhm_id`` array,
with the serial run and with the Python API (Scene -> Deformer -> Binding).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, box_cage, data_path, trilinear_corner_dets, write_folding_volume

pv = pytest.importorskip("pyvista")

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "tests" / "paraview" / "run_filter.py"
# both sides solve to this tolerance, so that BLAS differences between ParaView's numpy and
# ours cannot explain a gap (at 1e-11 the solution is still 5e-9 of the diagonal away)
TIGHT = {"tolerance": 1e-13, "max_iterations": 100000}


@pytest.fixture(scope="session")
def paraview_env():
    """Environment in which pvpython/pvbatch load the plugin (plugins/paraview-env.sh)."""
    if shutil.which("pvpython") is None and os.environ.get("CI") != "true":
        pytest.skip("ParaView is not installed (bash plugins/paraview-env.sh installs it)")
    out = subprocess.run(
        ["bash", str(ROOT / "plugins" / "paraview-env.sh")],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert out.returncode == 0, out.stderr
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)  # ParaView's Python must not see our virtual environment
    for line in out.stdout.splitlines():
        assert line.startswith("export "), line
        cmd = f"{line}; env -0"
        dump = subprocess.run(["bash", "-c", cmd], capture_output=True, env=env, check=True)
        env = dict(kv.split("=", 1) for kv in dump.stdout.decode().split("\0") if "=" in kv)
    # (the set-up has compiled the kernels into ParaView's numba cache: each pvbatch run
    # below starts from compiled code)
    return env


def _run(env, config: dict, tmp_path: Path, ranks: int = 1, name="cfg") -> str:
    path = tmp_path / f"{name}{ranks}.json"
    path.write_text(json.dumps(config))
    from vhm_viz.filters.mpi import mpi_command

    cmd, env = mpi_command(["pvbatch", str(RUN), str(path)], ranks, env)
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    log = done.stdout + done.stderr
    assert done.returncode == 0, log
    return log


def _points_by_id(path: Path, n: int) -> np.ndarray:
    """Output points ordered by the input point ids; every id must be present."""
    mesh = pv.read(path)
    ids = np.asarray(mesh.point_data["vhm_id"])
    out = np.full((n, 3), np.nan)
    out[ids] = np.asarray(mesh.points)
    assert np.isfinite(out).all(), "some input points are missing from the output"
    # a point written by two ranks (a shared boundary) must be the same on both
    np.testing.assert_array_equal(out[ids], np.asarray(mesh.points))
    return out


def _armadillo_config(scene, **extra) -> dict:
    """A pvbatch run deforming the 43k Armadillo by ``scene``, the cage on the Cage port."""
    return {"input": str(data_path("armadillo", "armadillo_43k.obj")),
            "filter": "VHMHarmonicDeformation", "scene": str(scene),
            "cage": str(data_path("armadillo", "cage_216f.obj")), "redistribute": True,
            **extra}  # fmt: skip


@pytest.fixture(scope="session")
def armadillo_scene(tmp_path_factory):
    """A bend of the 43k Armadillo with its 216-face cage and anchors from a file."""
    from vhm_viz.autocage import auto_anchors
    from vhm_viz.io import read_cage, read_dataset, write_anchors
    from vhm_viz.scene import Scene

    tmp = tmp_path_factory.mktemp("pv_armadillo")
    mesh = read_dataset(data_path("armadillo", "armadillo_43k.obj"))
    cage_path = data_path("armadillo", "cage_216f.obj")
    cage = read_cage(cage_path)
    write_anchors(tmp / "anchors.json", auto_anchors(mesh, cage, 24))
    p = np.asarray(mesh.points)
    feet = p[np.argsort(p[:, 1])[:3]]
    top = p[np.argmax(p[:, 1])]
    positions = np.vstack([feet, top])
    targets = positions.copy()
    targets[-1, 0] += 0.1 * np.ptp(p[:, 0])
    scene = {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": str(cage_path),
        "anchors": "anchors.json",
        "constraints": {"positions": positions.tolist(), "targets": targets.tolist()},
        "solver": TIGHT,
    }
    (tmp / "scene.json").write_text(json.dumps(scene))
    sc = Scene.load(tmp / "scene.json")
    dfm = sc.build()
    assert sc.solve(dfm)[-1].converged
    return tmp / "scene.json", p, dfm.bind(p).deform()


def test_pvpython_loads_the_three_filters(paraview_env, tmp_path):
    script = tmp_path / "names.py"
    script.write_text(
        "import paraview.simple as s\n"
        "print(sorted(n for n in dir(s) if n.startswith('VHM')))\n"
        "f = s.VHMHarmonicDeformation(Input=s.Sphere())\n"
        "print('SceneFile default:', repr(f.SceneFile))\n"
    )
    out = subprocess.run(
        ["pvpython", str(script)], capture_output=True, text=True, env=paraview_env, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert (
        "['VHMHarmonicDeformation', 'VHMJacobianAnalysis', 'VHMMedicalImageReader', "
        "'VHMResampleToImage']" in out.stdout
    )
    assert "SceneFile default: ''" in out.stdout


def test_numpy_points_are_vtks_points_in_pvpython(paraview_env):
    # ParaView's VTK (< 9.6) has no points array for images, and a rectilinear grid's
    # GetPoints fills an argument: the rest points of the cell measures come another way
    script = Path(__file__).parent / "paraview" / "points_check.py"
    out = subprocess.run(
        ["pvpython", str(script)], capture_output=True, text=True, env=paraview_env, timeout=300
    )
    assert out.returncode == 0, out.stderr
    assert "points ok" in out.stdout


def test_vhm_viz_paraview_runs_pvpython_with_the_plugin_loaded(paraview_env, tmp_path):
    """The installed package's route, ``vhm-viz paraview pvpython SCRIPT``, with numba for
    ParaView's Python installed as a user would (its user site-packages) and nothing else
    of the checkout's set-up: ParaView 5.11's plugin loader runs on Python 3.11 (it calls
    inspect.getargspec) and the filters are there."""
    import sys

    (site,) = [Path(p) for p in paraview_env["PYTHONPATH"].split(os.pathsep)
               if (Path(p) / "numba").is_dir()]  # fmt: skip
    version = subprocess.run(
        ["pvpython", "-c", "import sys; print('%d.%d' % sys.version_info[:2])"],
        capture_output=True, text=True, env=paraview_env, timeout=120,
    ).stdout.split()[-1]  # fmt: skip
    user_site = tmp_path / "user" / "lib" / f"python{version}" / "site-packages"
    user_site.mkdir(parents=True)
    for entry in site.iterdir():
        if entry.name.lower().startswith(("numba", "llvmlite")):
            (user_site / entry.name).symlink_to(entry)
    assert (user_site / "numba").exists() and (user_site / "llvmlite").exists()
    script = tmp_path / "names.py"
    script.write_text(
        "import paraview.simple as s\nprint(sorted(n for n in dir(s) if n.startswith('VHM')))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PV_PLUGIN_PATH")}
    env.update(
        PYTHONUSERBASE=str(tmp_path / "user"), NUMBA_CACHE_DIR=paraview_env["NUMBA_CACHE_DIR"]
    )
    for name in ("OMPI_ALLOW_RUN_AS_ROOT", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM"):
        env[name] = paraview_env.get(name, "1")
    out = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", "paraview", "--site", str(tmp_path / "pv-site"),
         "pvpython", str(script)],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    assert "getargspec" not in out.stderr, out.stderr
    assert (
        "['VHMHarmonicDeformation', 'VHMJacobianAnalysis', 'VHMMedicalImageReader', "
        "'VHMResampleToImage']" in out.stdout
    ), out.stdout + out.stderr


def test_set_up_compiles_the_kernels_and_filters_update_in_pvpython(paraview_env):
    """The set-up compiled the filters' kernels (its stamp), and the warm-up runs the
    three filter classes with ``vhm_viz.filters.update`` in pvpython, whose own SIGINT
    handler (installed outside Python) the update must leave in place."""
    stamps = list(Path(paraview_env["NUMBA_CACHE_DIR"]).glob(".compiled-numba-*"))
    assert stamps, "plugins/paraview-env.sh did not compile the kernels"
    done = subprocess.run(["pvpython", "-m", "vhm_viz.filters.warm"], capture_output=True,
                          text=True, env=paraview_env, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    lines = [ln for ln in done.stdout.splitlines() if " points" in ln]
    assert len(lines) == 2 * 12, done.stdout  # 3 + 3 x 3 runs, with and without a port cage
    for name in ("HarmonicDeformationFilter", "JacobianAnalysisFilter", "HarmonicResampleFilter"):
        assert any(ln.startswith(name) and "cage on port 1" in ln for ln in lines)
    assert "Traceback" not in done.stderr


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_surface_two_ranks_equal_serial_equal_python(paraview_env, armadillo_scene, tmp_path):
    scene, rest, expected = armadillo_scene
    config = _armadillo_config(scene)
    _run(paraview_env, {**config, "output": str(tmp_path / "serial.pvtu")}, tmp_path)
    log = _run(paraview_env, {**config, "output": str(tmp_path / "mpi.pvtu")}, tmp_path, ranks=2)
    assert "on 2 rank(s)" in log
    # each rank wrote its own piece
    assert len(list((tmp_path / "mpi").glob("*.vtu"))) == 2
    serial = _points_by_id(tmp_path / "serial.vtu", len(rest))
    mpi = _points_by_id(tmp_path / "mpi.pvtu", len(rest))
    diag = np.linalg.norm(np.ptp(expected, axis=0))
    assert np.abs(expected - rest).max() > 0.05 * diag  # a real bend was compared
    assert np.abs(mpi - serial).max() <= 1e-9 * diag
    assert np.abs(serial - expected).max() <= 1e-9 * diag


@pytest.mark.parametrize("flt", ["VHMHarmonicDeformation", "VHMResampleToImage"])
def test_no_scene_file_one_message_no_output(paraview_env, tmp_path, flt):
    """Without a scene, or with a malformed one, each filter says why in one line: the
    resample's output grid needs the map in the information pass, whose failure is that
    line too (not VTK's executive error, nor an error about the missing grid)."""
    data = tmp_path / "data.vti"
    pv.ImageData(dimensions=(4, 4, 4)).save(data)
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "vhm_viz.scene", "version": 1}')
    config = {"input": str(data), "filter": flt, "scene": None, "ids": False}
    for ranks in (1, 2):
        for scene, line in ((None, "set SceneFile (a vhm_viz scene JSON)"),
                            (str(bad), "scene field 'cage': missing")):  # fmt: skip
            log = _run(paraview_env, {**config, "scene": scene}, tmp_path, ranks=ranks,
                       name="noscene")  # fmt: skip
            assert log.count(line) == 1, log
            assert "Traceback" not in log and "returned failure" not in log, log
            assert "vhm-paraview-points: 0" in log


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_cage_missing_on_a_rank_is_an_error_not_a_seam(paraview_env, armadillo_scene, tmp_path):
    scene, _, _ = armadillo_scene
    # what a reader that runs on rank 0 only would give
    config = _armadillo_config(scene, cage_on_rank_0_only=True)
    log = _run(paraview_env, config, tmp_path, ranks=2)
    assert "the Cage input reached the ranks with 0 to 110 points" in log
    assert "vhm-paraview-points: 0" in log  # no half-deformed output
    assert "Traceback" not in log


def test_automatic_cage_is_refused_under_mpi(paraview_env, tmp_path):
    sphere = tmp_path / "sphere.vtp"
    pv.Sphere(radius=0.5).save(sphere)
    scene = {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": "auto",
        "anchors": {"auto": 4},
        "constraints": {"positions": [[0, 0, 0.45]], "targets": [[0, 0, 0.5]]},
    }
    (tmp_path / "auto.json").write_text(json.dumps(scene))
    config = {"input": str(sphere), "filter": "VHMHarmonicDeformation",
              "scene": str(tmp_path / "auto.json"), "redistribute": True}  # fmt: skip
    log = _run(paraview_env, config, tmp_path, ranks=2)
    assert "compute them once with 'vhm-viz cage' / 'vhm-viz anchors'" in log
    assert "vhm-paraview-points: 0" in log


def _by_id(values: np.ndarray, ids: np.ndarray, n: int) -> np.ndarray:
    """Rows of ``values`` ordered by ``ids``; every id present, duplicates (cells or points
    on the ranks' shared boundary) equal."""
    out = np.full((n,) + values.shape[1:], np.nan)
    out[ids] = values
    assert np.isfinite(out).all(), "some input ids are missing from the output"
    np.testing.assert_array_equal(out[ids], values)
    return out


@pytest.fixture(scope="session")
def tet_scene(tmp_path_factory):
    """The tet hand (7k points, 30k tets) as .vtu in a box cage, bent; anchors from a file."""
    from conftest import box_cage

    from vhm_viz import Cage
    from vhm_viz.autocage import auto_anchors
    from vhm_viz.io import read_dataset, write_anchors

    tmp = tmp_path_factory.mktemp("pv_tets")
    mesh = read_dataset(data_path("hand_tet", "hand.mesh"))
    mesh = pv.wrap(mesh).extract_cells_by_type(pv.CellType.TETRA)  # not its boundary triangles
    mesh.clear_data()
    assert mesh.n_cells == 29998
    mesh.save(tmp / "hand.vtu")
    p = np.asarray(mesh.points)
    lo, hi = p.min(0), p.max(0)
    pad = 0.05 * (hi - lo)
    verts, faces = box_cage(lo - pad, hi + pad, 2)
    pv.PolyData(verts, np.hstack([np.full((len(faces), 1), 3), faces]).ravel()).save(
        tmp / "cage.vtp"
    )
    write_anchors(tmp / "anchors.json", auto_anchors(mesh, Cage(verts, faces), 12))
    axis = int(np.argmax(hi - lo))
    positions = np.vstack([p[np.argmin(p[:, axis])], p[np.argmax(p[:, axis])]])
    targets = positions.copy()
    targets[1, (axis + 1) % 3] += 0.15 * (hi - lo)[axis]
    scene = {"format": "vhm_viz.scene", "version": 1, "cage": str(tmp / "cage.vtp"),
             "anchors": "anchors.json",
             "constraints": {"positions": positions.tolist(), "targets": targets.tolist()},
             "solver": TIGHT}  # fmt: skip
    (tmp / "scene.json").write_text(json.dumps(scene))
    return tmp


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_tet_mesh_two_ranks_equal_serial_equal_python(paraview_env, tet_scene, tmp_path):
    """Jacobian analysis (point and cell arrays) and the deformed points of a tet mesh."""
    from vhm_viz.core.metrics import cell_measures, jacobian_measures
    from vhm_viz.scene import Scene

    mesh = pv.read(tet_scene / "hand.vtu")
    n_pts, n_cells = mesh.n_points, mesh.n_cells
    sc = Scene.load(tet_scene / "scene.json")
    dfm = sc.build()
    assert sc.solve(dfm)[-1].converged
    ev = dfm.bind(np.asarray(mesh.points))
    deformed = ev.deform()
    m = jacobian_measures(ev.jacobians())
    tets = mesh.cells_dict[10]  # VTK_TETRA
    cm = cell_measures(mesh.points, deformed, tets)
    diag = np.linalg.norm(np.ptp(deformed, axis=0))
    assert np.abs(deformed - mesh.points).max() > 0.05 * diag  # a real bend
    base = {"input": str(tet_scene / "hand.vtu"), "scene": str(tet_scene / "scene.json"),
            "cage": str(tet_scene / "cage.vtp"), "redistribute": True}  # fmt: skip
    got = {}
    for ranks in (1, 2):
        for flt in ("VHMJacobianAnalysis", "VHMHarmonicDeformation"):
            out = tmp_path / f"{flt}{ranks}.pvtu"
            log = _run(paraview_env, {**base, "filter": flt, "output": str(out)}, tmp_path,
                       ranks=ranks, name=flt)  # fmt: skip
            assert f"on {ranks} rank(s)" in log
            path = out if ranks > 1 else out.with_suffix(".vtu")
            if ranks > 1:
                assert len(list((tmp_path / f"{flt}{ranks}").glob("*.vtu"))) == 2
            res = pv.read(path)
            pid = np.asarray(res.point_data["vhm_id"])
            cid = np.asarray(res.cell_data["vhm_cell_id"])
            if flt == "VHMHarmonicDeformation":
                got[ranks, "points"] = _by_id(np.asarray(res.points), pid, n_pts)
                continue
            for name in ("jacobian_determinant", "condition_number"):
                got[ranks, name] = _by_id(np.asarray(res.point_data[name]), pid, n_pts)
            for name in ("cell_jacobian_determinant", "cell_condition_number"):
                got[ranks, name] = _by_id(np.asarray(res.cell_data[name]), cid, n_cells)
    np.testing.assert_allclose(got[2, "points"], got[1, "points"], rtol=0, atol=1e-9 * diag)
    np.testing.assert_allclose(got[1, "points"], deformed, rtol=0, atol=1e-9 * diag)
    expected = {"jacobian_determinant": m["determinant"],
                "condition_number": m["condition_number"],
                "cell_jacobian_determinant": cm["determinant"],
                "cell_condition_number": cm["condition_number"]}  # fmt: skip
    for name, ref in expected.items():  # dimensionless: relative to their size
        np.testing.assert_allclose(got[2, name], got[1, name], rtol=1e-9, atol=0)
        np.testing.assert_allclose(got[1, name], ref, rtol=1e-9, atol=0)


@pytest.fixture(scope="session")
def head_scene(tmp_path_factory):
    """The CT head's example scene (cage and anchors from files), solved tight."""
    tmp = tmp_path_factory.mktemp("pv_head")
    examples = ROOT / "vhm_viz" / "scenes"
    scene = json.loads((examples / "head_scene.json").read_text())
    scene["cage"] = str(examples / scene["cage"])
    scene["anchors"] = str(examples / scene["anchors"])
    scene["solver"] = {**scene["solver"], **TIGHT}
    (tmp / "scene.json").write_text(json.dumps(scene))
    return tmp / "scene.json", str(examples / "head_cage.obj")


def _volume_engine(scene_path):
    from vhm_viz.core.image import ImageGeometry
    from vhm_viz.core.volume import VolumeDeformation
    from vhm_viz.scene import Scene

    img = pv.read(data_path("volumes", "headsq_64x64x93.vti"))
    sc = Scene.load(scene_path)
    dfm = sc.build()
    assert sc.solve(dfm)[-1].converged
    geo = ImageGeometry(img.origin, img.spacing, img.dimensions, img.direction_matrix)
    return img, VolumeDeformation(dfm.harmonic_map, geo)


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_volume_warp_in_pieces_equals_serial_equals_python(paraview_env, head_scene, tmp_path):
    """The head CT's forward warp, each rank a piece of the extent (.pvts)."""
    scene, cage = head_scene
    img, vol = _volume_engine(scene)
    expected = vol.warp()
    config = {"input": str(data_path("volumes", "headsq_64x64x93.vti")), "ids": False,
              "filter": "VHMHarmonicDeformation", "scene": str(scene), "cage": cage}  # fmt: skip
    _run(paraview_env, {**config, "output": str(tmp_path / "serial.pvts")}, tmp_path)
    log = _run(paraview_env, {**config, "output": str(tmp_path / "mpi.pvts")}, tmp_path, ranks=2)
    assert "on 2 rank(s)" in log
    pieces = [pv.read(f) for f in sorted((tmp_path / "mpi").glob("*.vts"))]
    assert len(pieces) == 2 and all(0 < p.n_points < img.n_points for p in pieces)
    serial = np.asarray(pv.read(tmp_path / "serial.vts").points)
    from vtkmodules.vtkIOXML import vtkXMLPStructuredGridReader  # (pyvista reads no .pvts)

    reader = vtkXMLPStructuredGridReader()
    reader.SetFileName(str(tmp_path / "mpi.pvts"))
    reader.Update()
    mpi = pv.wrap(reader.GetOutput())
    assert mpi.dimensions == img.dimensions
    diag = np.linalg.norm(np.ptp(expected, axis=0))
    assert np.abs(expected - img.points).max() > 0.05 * diag  # a real bend
    assert np.abs(np.asarray(mpi.points) - serial).max() <= 1e-9 * diag
    assert np.abs(serial - expected).max() <= 1e-9 * diag
    _assert_evaluations_shared(pieces, pv.read(tmp_path / "serial.vts"))


def _assert_evaluations_shared(pieces, serial):
    """The ranks built their lattices together: each round's points evaluated once, by
    one rank, every rank taking a share (field ``vhm_lattice_evaluations``: this rank's
    evaluations, and the distinct points they were shared among). The sizes of the shares
    follow the ranks' measured busy time; only the first round's halves are fixed."""
    counts = np.array([p.field_data["vhm_lattice_evaluations"] for p in pieces])
    alone = serial.field_data["vhm_lattice_evaluations"]
    assert alone[0] == alone[1] > 0
    assert (counts[:, 1] == counts[0, 1]).all()  # the ranks agree on the points
    assert counts[:, 0].sum() == counts[0, 1]  # each evaluated once
    assert counts[:, 0].min() > 0
    assert alone[1] <= counts[0, 1] <= 1.1 * alone[1]  # (the pieces' shared boundary)


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_volume_resample_in_pieces_equals_serial_equals_python(paraview_env, head_scene, tmp_path):
    """The head CT resampled (VHMResampleToImage), each rank a piece of the output (.pvti)."""
    scene, cage = head_scene
    img, vol = _volume_engine(scene)
    expected = vol.resample({"s": np.asarray(img.point_data.active_scalars)})
    # the cage's reader updated before the filter exists (it then re-runs on one rank
    # only): the ranks must still agree on when the scene is solved (this hung)
    config = {"input": str(data_path("volumes", "headsq_64x64x93.vti")), "ids": False,
              "filter": "VHMResampleToImage", "scene": str(scene), "cage": cage,
              "update_cage_first": True}  # fmt: skip
    _run(paraview_env, {**config, "output": str(tmp_path / "serial.pvti")}, tmp_path)
    log = _run(paraview_env, {**config, "output": str(tmp_path / "mpi.pvti")}, tmp_path, ranks=2)
    assert "on 2 rank(s)" in log
    assert len(list((tmp_path / "mpi").glob("*.vti"))) == 2
    serial = pv.read(tmp_path / "serial.vti")
    mpi = pv.read(tmp_path / "mpi.pvti")
    assert mpi.dimensions == serial.dimensions == tuple(expected.geometry.dimensions)
    np.testing.assert_allclose(serial.origin, expected.geometry.origin, rtol=0, atol=1e-9)
    name = img.point_data.active_scalars_name
    for a in (name, "vtkValidPointMask", "vhm_foldover"):
        np.testing.assert_array_equal(mpi.point_data[a], serial.point_data[a])
    ref = {name: expected.arrays["s"], "vtkValidPointMask": expected.valid,
           "vhm_foldover": expected.foldover}  # fmt: skip
    assert expected.valid.mean() > 0.3
    for a, values in ref.items():
        np.testing.assert_array_equal(serial.point_data[a], values)
    # each rank built its share of the lattice (its root cells and two voxels around),
    # evaluating a share of the points, and resampled its piece with the leaves of any
    # rank that reach it: the whole lattice's result above, bit for bit
    pieces = [pv.read(f) for f in sorted((tmp_path / "mpi").glob("*.vti"))]
    _assert_evaluations_shared(pieces, serial)
    assert serial.field_data["vhm_lattice_evaluations"][1] == vol.lattice.stats["evaluations"]
    # the ranks pulled back shares of the work, not ParaView's halves of the output: each
    # piece's voxels once (the pieces share a plane), some for the other rank's piece
    pulled = [int(p.field_data["vhm_pulled_back_voxels"][0]) for p in pieces]
    sizes = [p.n_points for p in pieces]
    assert sum(pulled) == sum(sizes) and pulled != sizes
    assert serial.field_data["vhm_pulled_back_voxels"][0] == serial.n_points


def test_resample_with_voxels_in_folds_says_so_once_for_the_whole_output(paraview_env, tmp_path):
    """A resample whose voxels lie in folds is made, with one warning in the output
    messages: the count and box of the whole output's voxels in folds, the same from two
    ranks (whose pieces share a plane) as serially; so are the field arrays' counts."""
    write_folding_volume(tmp_path, record_map=True)
    config = {"input": str(tmp_path / "image.vti"), "ids": False,
              "filter": "VHMResampleToImage", "scene": str(tmp_path / "scene.json")}  # fmt: skip
    logs = [_run(paraview_env, {**config, "output": str(tmp_path / f"out{n}.pvti")}, tmp_path,
                 ranks=n) for n in (1, 2)]  # fmt: skip
    serial, mpi = pv.read(tmp_path / "out1.vti"), pv.read(tmp_path / "out2.pvti")
    np.testing.assert_array_equal(mpi.point_data["vhm_foldover"], serial.point_data["vhm_foldover"])
    marked = np.flatnonzero(np.asarray(serial.point_data["vhm_foldover"]))
    assert marked.size > 0
    at = np.asarray(serial.points)[marked]
    lines = []
    for log in logs:
        (line,) = [ln for ln in log.splitlines() if "folds" in ln]
        assert line.startswith("VHM Resample To Image: the deformation folds the data: "), line
        assert "Traceback" not in log
        lines.append(line)
    assert lines[0] == lines[1]
    m = re.search(r": (\d+) of (\d+) output voxels in folds \(several pre-images; output "
                  r"positions within \(([^)]*)\)-\(([^)]*)\)\)$", lines[0])  # fmt: skip
    assert m, lines[0]
    assert (int(m.group(1)), int(m.group(2))) == (marked.size, serial.n_points)
    box = [[float(v) for v in m.group(g).split(",")] for g in (3, 4)]
    np.testing.assert_allclose(box, [at.min(axis=0), at.max(axis=0)], rtol=1e-3, atol=1e-3)
    # the field arrays count the whole output's voxels, in each rank's piece as serially
    valid = int(np.count_nonzero(serial.point_data["vtkValidPointMask"]))
    pieces = [pv.read(f) for f in sorted((tmp_path / "out2").glob("*.vti"))]
    assert len(pieces) == 2
    for piece in (serial, *pieces):
        assert piece.field_data["vhm_foldover_count"][0] == marked.size
        assert piece.field_data["vhm_valid_count"][0] == valid


def test_warp_with_inverted_cells_says_so_once_for_the_whole_output(paraview_env, tmp_path):
    """VHM Harmonic Deformation checks the warped cells by default: one line in the output
    messages with the whole output's inverted voxel cells, the same from two ranks (each
    warping its piece) as serially, counted as a brute-force trilinear corner Jacobian of
    the serial output counts them."""
    write_folding_volume(tmp_path, record_map=True)
    config = {"input": str(tmp_path / "image.vti"), "ids": False,
              "scene": str(tmp_path / "scene.json"),
              "filter": "VHMHarmonicDeformation"}  # fmt: skip
    logs = [_run(paraview_env, {**config, "output": str(tmp_path / f"out{n}.pvts")}, tmp_path,
                 ranks=n) for n in (1, 2)]  # fmt: skip
    image, serial = pv.read(tmp_path / "image.vti"), pv.read(tmp_path / "out1.vts")
    points = np.asarray(serial.points).reshape(tuple(image.dimensions)[::-1] + (3,))
    ratio = trilinear_corner_dets(points) / float(np.prod(image.spacing))
    inverted = int(np.count_nonzero(ratio <= 0))
    assert inverted > 0
    lines = []
    for log in logs:
        assert "Traceback" not in log
        (line,) = [ln for ln in log.splitlines() if "folds" in ln]
        lines.append(line)
    assert lines[0] == lines[1]
    assert lines[0].startswith(
        f"VHM Harmonic Deformation: the deformation folds the data: {inverted} of "
        f"{image.n_cells} cells inverted (cell det <= 0; worst "
    ), lines[0]
    assert lines[0].endswith(" (rest positions)")


def test_composite_input_on_two_ranks_is_one_error_not_a_hang(paraview_env, tmp_path):
    """A multiblock of three tet meshes: serially the warp runs block by block; on two
    ranks, which hold different numbers of blocks, it is refused in one line naming what
    to do, promptly (it waited forever in the ranks' agreement)."""
    from vhm_viz.filters.mpi import mpi_command

    write_folding_volume(tmp_path, record_map=True)
    tets = pv.read(tmp_path / "image.vti").to_tetrahedra()
    thirds = np.array_split(np.arange(tets.n_cells), 3)
    pv.MultiBlock([tets.extract_cells(part) for part in thirds]).save(tmp_path / "blocks.vtm")
    config = {"input": str(tmp_path / "blocks.vtm"), "ids": False,
              "scene": str(tmp_path / "scene.json"),
              "filter": "VHMHarmonicDeformation"}  # fmt: skip
    serial = _run(paraview_env, config, tmp_path, ranks=1)
    assert serial.count("cells inverted") == 3 and "Traceback" not in serial, serial
    path = tmp_path / "cfg2.json"
    path.write_text(json.dumps(config))
    cmd, env = mpi_command(["pvbatch", str(RUN), str(path)], 2, paraview_env)
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    except subprocess.TimeoutExpired:
        pytest.fail("composite input on two ranks hung")
    log = done.stdout + done.stderr
    assert done.returncode == 0 and "Traceback" not in log, log
    (line,) = [ln for ln in log.splitlines() if "MPI ranks" in ln]
    assert line.endswith(
        "VHM Harmonic Deformation: vtkMultiBlockDataSet input is not supported on several "
        "MPI ranks (each rank runs the filter once per block it holds): apply Merge Blocks "
        "first"
    ), line


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_analysis_cell_counts_are_the_whole_outputs_on_every_rank(paraview_env, tmp_path):
    """VHM Jacobian Analysis' field arrays vhm_cells_inverted and vhm_cells_rest_inverted
    count the whole output's cells in every rank's piece, as serially: the folding image
    (cells inverted by the map) and a tet mesh stored half inverted, redistributed."""
    write_folding_volume(tmp_path, record_map=True)
    v, f = box_cage((-11, -11, -11), (11, 11, 11))
    tet_scene = {"format": "vhm_viz.scene", "version": 1,
                 "cage": {"vertices": v.tolist(), "faces": f.tolist()},
                 "anchors": [[0, 0, 0], [4, 0, 0], [0, 4, 0], [0, 0, 4], [-4, -4, -4]],
                 "constraints": {"positions": [[0, 0, 0]], "targets": [[0.5, 0, 0]]}}  # fmt: skip
    (tmp_path / "tet_scene.json").write_text(json.dumps(tet_scene))
    runs = {
        "image": ({"input": str(tmp_path / "image.vti"), "ids": False,
                   "scene": str(tmp_path / "scene.json")}, "vti", "cell_inverted"),
        "tets": ({"input": str(data_path("tets", "tetraMesh_inverted.vtk")),
                  "redistribute": True, "scene": str(tmp_path / "tet_scene.json")},
                 "vtu", "cell_rest_inverted"),
    }  # fmt: skip
    for name, (config, ext, array) in runs.items():
        config = {**config, "filter": "VHMJacobianAnalysis"}
        for n in (1, 2):
            out = str(tmp_path / f"{name}{n}.p{ext}")
            _run(paraview_env, {**config, "output": out}, tmp_path, ranks=n, name=name)
        serial = pv.read(tmp_path / f"{name}1.{ext}")
        expected = int(np.count_nonzero(serial.cell_data[array]))
        assert expected > 0, name
        pieces = [pv.read(p) for p in sorted((tmp_path / f"{name}2").glob(f"*.{ext}"))]
        assert len(pieces) == 2 and min(p.n_cells for p in pieces) > 0
        assert sum(int(np.count_nonzero(p.cell_data[array])) for p in pieces) == expected
        for piece in (serial, *pieces):
            assert piece.field_data[f"vhm_cells_{array[5:]}"][0] == expected, name


def test_measure_colours_follow_the_one_convention(paraview_env, tmp_path):
    """det J: Cool to Warm on a log scale, symmetric about 1, folds in the below-range colour;
    cond J: viridis from 1 -- the ranges of vhm_viz.colours, as in the explorer and figures."""
    from vhm_viz import colours

    result = tmp_path / "colours.json"
    script = Path(__file__).parent / "paraview" / "colour_check.py"
    out = subprocess.run(["pvpython", str(script), str(result)], capture_output=True,
                         text=True, env=paraview_env, timeout=300)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(result.read_text())
    det, cond = got["jacobian_determinant"], got["condition_number"]
    np.testing.assert_allclose(det["range"], got["det_expected"], rtol=1e-6)
    assert det["range"][0] * det["range"][1] == pytest.approx(1.0)
    assert det["log"] == 1 and det["below"] == [1, list(colours.FOLD_COLOUR)]
    # 1 (no volume change) sits at the middle of the diverging map: near white
    assert min(det["mid_rgb"]) > 0.75
    np.testing.assert_allclose(cond["range"], got["cond_expected"], rtol=1e-6)
    assert cond["log"] == 0


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_volume_warp_with_more_ranks_than_planes_finishes(paraview_env, head_scene, tmp_path):
    """3 ranks on a 2-voxel volume: a rank with an empty piece still takes its share of
    the lattice's evaluations, so the others do not wait for it forever (they did); the
    resample of it finishes too."""
    scene, cage = head_scene
    script = tmp_path / "empty_piece.py"
    script.write_text(
        "import paraview.simple as pvs\n"
        f"img = pvs.OpenDataFile({str(data_path('volumes', 'headsq_64x64x93.vti'))!r})\n"
        "two = pvs.ExtractSubset(Input=img, VOI=[30, 30, 30, 30, 40, 41])\n"
        f"cage = pvs.OpenDataFile({str(cage)!r})\n"
        "bent = pvs.VHMHarmonicDeformation(Input=two, Cage=cage, "
        f"SceneFile={str(scene)!r}, OutsidePolicy='Pass through')\n"
        "pvs.UpdatePipeline(proxy=bent)\n"
        "print('vhm-points', bent.GetDataInformation().GetNumberOfPoints(), flush=True)\n"
        "flat = pvs.VHMResampleToImage(Input=two, Cage=cage, "
        f"SceneFile={str(scene)!r}, OutsidePolicy='Pass through')\n"
        "pvs.UpdatePipeline(proxy=flat)\n"
        "print('vhm-resampled', flat.GetDataInformation().GetNumberOfPoints(), flush=True)\n"
    )
    from vhm_viz.filters.mpi import mpi_command

    cmd, env = mpi_command(["pvbatch", str(script)], 3, paraview_env)
    cmd.insert(1, "--oversubscribe")  # 3 ranks on a 2-core machine
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "vhm-points 2" in done.stdout
    # the resample too, of the 2 x 2 x 3 output voxels that hold the deformed volume (the
    # serial filter's grid): 3 pieces along z sharing their boundary planes (20 points)
    # and 3 shares of the work, which need not match them
    assert "vhm-resampled 20" in done.stdout, done.stdout + done.stderr
    assert "Traceback" not in done.stdout + done.stderr


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_a_solve_that_fails_on_rank_0_stops_every_rank_once(paraview_env, head_scene, tmp_path):
    """Every rank solves the scene; when the solve fails on all of them, the failure is
    said once (by rank 0): one message, no output, no hang."""
    scene, cage = head_scene
    broken = json.loads(scene.read_text())
    c = broken["constraints"]
    c["positions"].append(c["positions"][0])  # the same point twice
    c["targets"].append(c["targets"][0])
    (tmp_path / "broken.json").write_text(json.dumps(broken))
    config = {"input": str(data_path("volumes", "headsq_64x64x93.vti")), "ids": False,
              "filter": "VHMHarmonicDeformation", "scene": str(tmp_path / "broken.json"),
              "cage": cage}  # fmt: skip
    for ranks in (1, 2):
        log = _run(paraview_env, config, tmp_path, ranks=ranks, name=f"broken{ranks}")
        assert log.count("position constraints 0 and 2 are at the same point") == 1, log
        assert "Traceback" not in log
        assert "vhm-paraview-points: 0" in log


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_unconverged_solve_fails_unless_allowed(paraview_env, head_scene, tmp_path):
    """A scene whose solve stops at max_iterations: by default one error line and no
    output; with AllowUnconverged the output and one warning line, on 1 and 2 ranks."""
    scene, cage = head_scene
    short = json.loads(scene.read_text())
    short["solver"] = {**short["solver"], "max_iterations": 1}
    (tmp_path / "short.json").write_text(json.dumps(short))
    config = {"input": str(data_path("volumes", "headsq_64x64x93.vti")), "ids": False,
              "filter": "VHMHarmonicDeformation", "scene": str(tmp_path / "short.json"),
              "cage": cage}  # fmt: skip
    allowed = {**config, "properties": {"AllowUnconverged": 1}}
    voxels = pv.read(config["input"]).n_points
    for ranks in (1, 2):
        log = _run(paraview_env, config, tmp_path, ranks=ranks, name=f"short{ranks}")
        assert log.count("not converged: the solver stopped at max_iterations = 1") == 1, log
        assert "Traceback" not in log
        assert "vhm-paraview-points: 0" in log
        log = _run(paraview_env, allowed, tmp_path, ranks=ranks, name=f"allowed{ranks}")
        assert log.count("deforming with an unconverged solve") == 1, log
        # every voxel (the ranks' pieces share their boundary plane)
        assert int(log.split("vhm-paraview-points: ")[1].split()[0]) >= voxels, log


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_stored_map_is_used_by_every_rank(paraview_env, head_scene, tmp_path):
    """A scene holding its solved map (Scene.record_map): serial and 2 ranks deform with
    it instead of solving -- shown with a stored map other than the solve's, whose digest
    still matches -- and with the cage on the Cage port as read by ParaView."""
    from vhm_viz import HarmonicMap
    from vhm_viz.core.image import ImageGeometry
    from vhm_viz.core.volume import VolumeDeformation
    from vhm_viz.scene import Scene

    scene_path, cage = head_scene
    sc = Scene.load(scene_path)
    dfm = sc.build()
    assert sc.solve(dfm)[-1].converged and sc.record_map(dfm)
    identity = np.asarray(HarmonicMap.identity(dfm.cage).coefficients)
    half = identity + 0.5 * (np.asarray(dfm.harmonic_map.coefficients) - identity)
    sc.stored_map["coefficients"] = half
    sc.save(tmp_path / "stored.json")
    img = pv.read(data_path("volumes", "headsq_64x64x93.vti"))
    geo = ImageGeometry(img.origin, img.spacing, img.dimensions, img.direction_matrix)
    expected = VolumeDeformation(HarmonicMap(dfm.cage, half), geo).warp()
    config = {"input": str(data_path("volumes", "headsq_64x64x93.vti")), "ids": False,
              "filter": "VHMHarmonicDeformation", "scene": str(tmp_path / "stored.json"),
              "cage": cage}  # fmt: skip
    _run(paraview_env, {**config, "output": str(tmp_path / "serial.pvts")}, tmp_path)
    _run(paraview_env, {**config, "output": str(tmp_path / "mpi.pvts")}, tmp_path, ranks=2)
    serial = np.asarray(pv.read(tmp_path / "serial.vts").points)
    from vtkmodules.vtkIOXML import vtkXMLPStructuredGridReader

    reader = vtkXMLPStructuredGridReader()
    reader.SetFileName(str(tmp_path / "mpi.pvts"))
    reader.Update()
    mpi = np.asarray(pv.wrap(reader.GetOutput()).points)
    diag = np.linalg.norm(np.ptp(expected, axis=0))
    assert np.abs(serial - expected).max() <= 1e-9 * diag
    assert np.abs(mpi - serial).max() <= 1e-9 * diag
    solved = VolumeDeformation(dfm.harmonic_map, geo).warp()
    assert np.abs(solved - expected).max() > 0.01 * diag  # (not what a solve gives)
