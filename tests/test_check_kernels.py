"""The checks' compiled kernels, loaded before the checks run them.

``load_check_kernels`` calls the checks' numeric functions on tiny inputs on a second
thread, so that the checks themselves load nothing: in a fresh process (where no kernel
is loaded yet), every ``Dispatcher.compile`` the real checks make after the warm-up is
counted, for each kind of data ``deform`` checks.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

RUNNER = r"""
import json, sys
import numpy as np
import numba.core.dispatcher as dispatcher
import pyvista as pv

from vhm_viz import examples
from vhm_viz.folds import inverted_voxel_cells, load_check_kernels
from vhm_viz.cli._util import surface_metrics
from vhm_viz.filters import cell_quality

compiled = []
original = dispatcher.Dispatcher.compile


def logged(self, sig):
    before = len(self.overloads)
    out = original(self, sig)
    if len(self.overloads) > before:  # a new signature: compiled or loaded from the cache
        compiled.append(self.py_func.__name__)
    return out


dispatcher.Dispatcher.compile = logged
rng = np.random.default_rng(0)
points, tets = examples.bar_tets(4)
grid = pv.UnstructuredGrid(
    np.hstack([np.full((len(tets), 1), 4), tets]).ravel(),
    np.full(len(tets), pv.CellType.TETRA), points,
)
hexes = pv.ImageData(dimensions=(4, 3, 5)).cast_to_unstructured_grid()
surface = pv.Sphere()
image = pv.ImageData(dimensions=(6, 5, 7), spacing=(0.5, 0.4, 0.3))


def moved(ds):
    return np.asarray(ds.points) + 0.01 * rng.normal(size=(ds.n_points, 3))


def image_checks():
    inverted_voxel_cells(moved(image), image.dimensions, 0.06)


def mesh_checks(ds):
    def run():
        out = ds.copy()
        out.points = moved(ds)
        surface_metrics(ds, out, rigid=False)
        if not isinstance(ds, pv.PolyData):
            cell_quality(ds, out.points, condition=False)
    return run


def proof_checks():
    # a warped image's proof and the cells it leaves, from an engine built before the
    # warm-up (its build loads the lattice's kernels, not the checks')
    boxes = engine.unproven_cells()
    inverted_voxel_cells(warped, engine.geometry.dimensions, 1.0, unproven=boxes)


from vhm_viz import Cage, HarmonicMap
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.volume import VolumeDeformation

box = pv.Box(bounds=(-2, 25, -2, 21, -2, 21), level=2).triangulate()
cage = Cage(np.asarray(box.points), np.asarray(box.faces).reshape(-1, 4)[:, 1:])
z = np.array(HarmonicMap.identity(cage).coefficients)
z[: len(cage.vertices)] += 0.3 * rng.normal(size=(len(cage.vertices), 3))
engine = VolumeDeformation(
    HarmonicMap(cage, z), ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (24, 20, 20)),
    pre_images=False,
)
warped = engine.warp()
assert len(engine.lattice.leaf_size)  # a lattice of leaves: the proof runs its kernel

report = {}
for name, data, checks, kw in (
    ("proof", image, proof_checks, {"voxels": True, "proof": True}),
    ("image", image, image_checks, {"voxels": True}),
    ("surface", surface, mesh_checks(surface), {}),
    ("tets", grid, mesh_checks(grid), {}),
    ("hexahedra", hexes, mesh_checks(hexes), {}),
):
    compiled.clear()
    load_check_kernels(data, **kw).join()
    warmed = list(compiled)
    compiled.clear()
    checks()
    report[name] = {"warm-up": warmed, "checks": list(compiled)}
print(json.dumps(report))
"""


def test_the_checks_load_no_kernel_after_the_warm_up():
    proc = subprocess.run(
        [sys.executable, "-c", RUNNER], capture_output=True, text=True, timeout=600,
        env=dict(os.environ),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    for name, seen in report.items():
        assert seen["checks"] == [], (name, seen)
    # and the warm-up loaded each kind's own kernels
    assert {"unproven_boxes", "_hex_box_kernel", "_hex_kernel"} <= set(report["proof"]["warm-up"])
    assert "_open_edges" in report["surface"]["warm-up"]
    assert {"_tet_kernel", "_tetrahedra_volumes"} <= set(report["tets"]["warm-up"])
    assert "_reduce_cells" in report["hexahedra"]["warm-up"]


def test_with_one_thread_the_checks_load_their_own():
    # one CPU for the kernels: no core idles during the solve, so nothing is loaded early
    proc = subprocess.run(
        [sys.executable, "-c", RUNNER], capture_output=True, text=True, timeout=600,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert all(seen["warm-up"] == [] for seen in report.values()), report
    assert "unproven_boxes" in report["proof"]["checks"]
    assert "_open_edges" in report["surface"]["checks"]
