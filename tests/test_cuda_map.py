"""The GPU path (``device="cuda"``) against the CPU path, and its refusal without a GPU.

The map and its Jacobians, the lattice's exact evaluations and the pull-back's Newton
solves run on the GPU (:mod:`vhm_viz.core.cuda_map`,
:mod:`vhm_viz.core.lattice.cuda_pullback`).

The GPU kernels run in a child process under numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1`` must be set before numba is imported), which runs every GPU
thread in Python: the cage and the point sets are tiny. With ``VHM_TEST_REAL_GPU=1`` (set
by ``benchmarks/gpu_check.sh`` on a machine with a GPU) the child runs on the real device.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import box_cage, simple_cage

from vhm_viz.core.errors import DeviceUnavailableError, SettingError
from vhm_viz.core.harmonic_map import HarmonicMap

ROOT = Path(__file__).resolve().parents[1]

# Compares HarmonicMap.evaluate(device="cuda") with device="cpu" on a small bent box cage:
# points inside, outside (each outside policy), next to a cage edge (the CPU per-point
# kernel's points) and on a face; prints the largest relative differences as JSON.
_COMPARE = r"""
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from conftest import box_cage
from vhm_viz.core.basis import evaluate_map
from vhm_viz.core.cage import Cage
from vhm_viz.core.errors import OutsideCageError
from vhm_viz.core.harmonic_map import HarmonicMap

v, f = box_cage((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 2)
cage = Cage(v, f)
t = v.copy()
t[:, 0] += 0.3 * t[:, 2] ** 2  # a bend
t[:, 1] *= 1.0 + 0.2 * t[:, 0]
hm = HarmonicMap.from_target_cage(cage, t)
rng = np.random.default_rng(7)
inside = rng.uniform(-0.9, 0.9, (24, 3))
outside = rng.uniform(1.1, 1.6, (6, 3)) * rng.choice([-1.0, 1.0], (6, 3))
near_edge = np.array([[1.0 - 1e-9, 1.0 - 1e-9, 0.3]])  # next to the edge x = y = 1
on_face = np.array([[1.0, 0.2, -0.4]])
points = np.vstack([inside, outside, near_edge, on_face])

def rel(a, b):
    scale = np.abs(b).max()
    return float(np.abs(a - b).max() / scale)

out = {}
for order in (0, 1):
    cpu = hm.evaluate(points, order=order, outside="passthrough")
    gpu = hm.evaluate(points, order=order, outside="passthrough", device="cuda")
    out[f"values{order}"] = rel(gpu[0], cpu[0])
    if order:
        out["jacobians"] = rel(gpu[1], cpu[1])
# the fused map of the basis module, with its winding numbers
cpu = evaluate_map(points, v, f, hm.coefficients, order=1)
gpu = evaluate_map(points, v, f, hm.coefficients, order=1, device="cuda")
out["map"] = rel(gpu[0], cpu[0])
out["map_jacobians"] = rel(gpu[1], cpu[1])
out["winding"] = rel(gpu[2], cpu[2])
# the volume engine: the lattice's exact evaluations on the GPU (a tiny grid, every voxel
# exact), then the warp and the Jacobians of its voxels
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.volume import VolumeDeformation
geo = ImageGeometry((-0.8, -0.7, -0.75), (0.4, 0.35, 0.5), (5, 5, 4))
vol_cpu = VolumeDeformation(hm, geo)
vol_gpu = VolumeDeformation(hm, geo, device="cuda")
out["warp"] = rel(vol_gpu.warp(), vol_cpu.warp())
out["voxel_jacobians"] = rel(vol_gpu.jacobians(), vol_cpu.jacobians())
def refused(device):
    try:
        hm.evaluate(points, device=device)
    except OutsideCageError as exc:
        return exc.indices.tolist()
out["refused_equal"] = refused("cuda") == refused("cpu") == list(range(24, 30))
out["engine_on_gpu"] = vol_gpu.map.device == "cuda" and vol_cpu.map.device == "cpu"
out["outside_equal"] = bool(
    (np.isnan(hm.evaluate(points, outside="nan", device="cuda")[0])
     == np.isnan(hm.evaluate(points, outside="nan")[0])).all()
)
print(json.dumps(out))
"""


# Resamples two output planes of a 10^3 grid that overhangs a bent cube cage (voxels
# inside, outside left in place, leaves the cage crosses) on each device; prints how the
# masks compare and the largest pre-image and value differences as JSON.
_COMPARE_RESAMPLE = r"""
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from conftest import box_cage
from vhm_viz.core.cage import Cage
from vhm_viz.core.harmonic_map import HarmonicMap
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.volume import VolumeDeformation

v, f = box_cage((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 1)
t = v.copy()
t[:, 0] += 0.3 * (t[:, 2] + 1.0) ** 2 * (t[:, 1] > 0)  # two corners swept sideways
t[:, 1] *= 1.0 + 0.2 * t[:, 0]
hm = HarmonicMap.from_target_cage(Cage(v, f), t)
n = 10
geo = ImageGeometry((-1.2,) * 3, (2.4 / (n - 1),) * 3, (n, n, n))
img = np.random.default_rng(1).random(n ** 3).astype(np.float32)
engines = {d: VolumeDeformation(hm, geo, outside="passthrough", device=d, root=4)
           for d in ("cpu", "cuda")}
out_geo = engines["cpu"].output_geometry()
dims = out_geo.dimensions
out = {"valid_equal": True, "foldover_equal": True, "preimage": 0.0, "value": 0.0,
       "valid": 0, "identity": 0}
for box in ([0, dims[0] - 1, dims[1] // 2, dims[1] // 2, 0, dims[2] - 1],
            [0, dims[0] - 1, 0, dims[1] - 1, dims[2] // 3, dims[2] // 3]):
    res = {d: e.resample({"v": img}, out_geo, box=box, displacement=True)
           for d, e in engines.items()}
    a, b = res["cpu"], res["cuda"]
    out["valid_equal"] &= bool((a.valid == b.valid).all())
    out["foldover_equal"] &= bool((a.foldover == b.foldover).all())
    # pre-images differ as the displacements do: in input voxels
    out["preimage"] = max(out["preimage"],
                          float(np.abs(a.displacement - b.displacement).max() / geo.spacing[0]))
    out["value"] = max(out["value"], float(np.abs(a.arrays["v"] - b.arrays["v"]).max()))
    out["valid"] += a.counts["valid"]
    out["identity"] += a.counts["identity"]
print(json.dumps(out))
"""

# Compiles a real kernel (argv: module, kernel, argument types) to PTX for a Hopper GPU
# (sm_90), which needs CUDA's NVVM library but no GPU: the simulator runs the kernel as
# Python, so only this catches code that numba cannot compile for a GPU. Device functions
# take the compute capability of the current device, which a machine without a GPU lacks:
# it is given (sm_90) for this check.
_PTX = r"""
import sys
from types import SimpleNamespace
from numba import cuda, types as T
from numba.cuda.cudadrv import nvvm
try:
    nvvm.NVVM()
except Exception as exc:
    print("NO NVVM", exc)
    sys.exit(0)
if not cuda.is_available():
    import numba.cuda.dispatcher as dispatcher
    dispatcher.get_current_device = lambda: SimpleNamespace(compute_capability=(9, 0))
import importlib
f1, f2, f3 = T.float64[::1], T.float64[:, ::1], T.float64[:, :, ::1]
i1, i2, i3 = T.int64[::1], T.int64[:, ::1], T.int64[:, :, ::1]
b1, u1, u4 = T.boolean[::1], T.uint8[::1], T.uint8[:, :, :, ::1]
kernel = getattr(importlib.import_module(sys.argv[1]), sys.argv[2])
args = eval(sys.argv[3])
ptx, _ = cuda.compile_ptx(kernel.py_func, args, cc=(9, 0))
print("PTX", len(ptx), "entry" if ".entry" in ptx else "no kernel")
"""


def _child_env(simulate: bool) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    if simulate:
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    return env


def _compare_on_gpu(code: str) -> dict:
    """The JSON that ``code`` prints, run on the simulator (or a real GPU, see above)."""
    simulate = os.environ.get("VHM_TEST_REAL_GPU") != "1"
    run = subprocess.run(
        [sys.executable, "-c", code, str(Path(__file__).parent)],
        env=_child_env(simulate),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_gpu_map_equals_cpu_map():
    """Values, Jacobians, winding numbers, warped voxels equal the CPU path's (1e-12 rel.)."""
    diffs = _compare_on_gpu(_COMPARE)
    assert diffs.pop("outside_equal")
    assert diffs.pop("engine_on_gpu")
    assert diffs.pop("refused_equal")
    for name, value in diffs.items():
        assert value <= 1e-12, (name, value)


# The GPU kernels and their argument types, as their callers pass them.
_KERNELS = {
    "map": ("vhm_viz.core.cuda_map", "_map_kernel",
            "(f2, f2, i2, f2, f1, f3, f3, i2, f1, f1, i2, T.float64, T.int64, f2, f2, f3, f1, u1)"),
    "pull_back": ("vhm_viz.core.lattice.cuda_pullback", "_pull_back_kernel",
                  "(f3, i2, i2, i1, b1, b1, f2, f3, f1, f1, i3, u4, i1, i1, f1, f2, i1, T.int64,"
                  " i1, i1, i1, i1, f2, u1, u1, f1)"),
}  # fmt: skip


@pytest.mark.parametrize("kernel", sorted(_KERNELS))
def test_kernel_compiles_for_the_gpu(kernel):
    """The GPU kernels (with the shared face and cell formulas) compile to PTX for sm_90."""
    run = subprocess.run(
        [sys.executable, "-c", _PTX, *_KERNELS[kernel]],
        env=_child_env(False),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    if run.stdout.startswith("NO NVVM"):
        pytest.skip(f"CUDA's NVVM library is not installed: {run.stdout.strip()}")
    assert run.stdout.startswith("PTX ") and run.stdout.split()[2] == "entry", run.stdout


def test_cpu_path_does_not_import_numba_cuda():
    """Importing the map and the volume engine, and evaluating on the CPU, leave numba.cuda."""
    code = (
        "import sys, numpy as np\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from conftest import box_cage, simple_cage\n"
        "import vhm_viz.core.volume\n"
        "from vhm_viz.core.harmonic_map import HarmonicMap\n"
        "HarmonicMap.identity(simple_cage(*box_cage())).evaluate(np.full((1, 3), 0.5), order=1)\n"
        "print('numba.cuda' in sys.modules)\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], env=_child_env(False), capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip() == "False"


def test_gpu_resample_equals_cpu_resample():
    """Same masks; pre-images within the Newton step (1e-3 voxel), values accordingly."""
    diffs = _compare_on_gpu(_COMPARE_RESAMPLE)
    assert diffs["valid_equal"] and diffs["foldover_equal"], diffs
    assert diffs["valid"] > 50 and diffs["identity"] > 10, diffs  # both kinds were compared
    # both devices stop Newton at a step below 1e-3 voxel, where it has converged
    # quadratically: the pre-images agree far within the tolerance (0.05 voxel)
    assert diffs["preimage"] <= 1e-3, diffs
    # trilinear samples of values in [0, 1] move by at most 3 times the pre-image's move
    assert diffs["value"] <= 3e-3, diffs


def _gpu_usable() -> bool:
    from numba import cuda

    return cuda.is_available()


def test_cuda_without_gpu_is_one_clear_error():
    """Without a GPU, device="cuda" raises DeviceUnavailableError, a SettingError."""
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1" or _gpu_usable():
        pytest.skip("this process has a GPU (or the simulator)")
    v, f = box_cage()
    hm = HarmonicMap.identity(simple_cage(v, f))
    with pytest.raises(DeviceUnavailableError, match="NVIDIA GPU") as info:
        hm.evaluate(np.full((2, 3), 0.5), device="cuda")
    assert isinstance(info.value, SettingError)
    assert "device 'cpu'" in str(info.value)
    with pytest.raises(SettingError, match="must be one of cpu, cuda"):
        hm.evaluate(np.full((2, 3), 0.5), device="gpu")


def test_cli_device_cuda_without_gpu_is_one_line(tmp_path, capsys):
    """``vhm-viz deform ... --device cuda`` without a GPU: one line, before any work."""
    pytest.importorskip("pyvista")
    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1" or _gpu_usable():
        pytest.skip("this process has a GPU (or the simulator)")
    from vhm_viz.cli import main

    argv = ["deform", tmp_path / "in.vti", "--scene", tmp_path / "s.json", "-o", tmp_path / "o.vts"]
    rc = main([*map(str, argv), "--device", "cuda", "-q"])
    err = capsys.readouterr().err
    assert rc != 0
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("vhm-viz deform: error: device 'cuda' needs an NVIDIA GPU")
    assert not (tmp_path / "o.vts").exists()
