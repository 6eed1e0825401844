"""Device settings with a fallback (the explorer's volume views): auto, cpu, cuda.

Without a GPU (this machine, and CI), ``cuda`` falls back to the CPU with one line that
says why, ``auto`` silently; the volume view's deformed volume is then the CPU's.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage

from vhm_viz.core.cage import Cage
from vhm_viz.core.devices import require_device, resolve_device
from vhm_viz.core.errors import DeviceUnavailableError
from vhm_viz.core.harmonic_map import HarmonicMap


def _gpu_usable() -> bool:
    try:
        require_device("cuda")
    except DeviceUnavailableError:
        return False
    return True


def test_settings_that_need_no_gpu():
    """``cpu`` is met; a setting naming no device falls back with a line naming the choices."""
    assert resolve_device("cpu") == ("cpu", None)
    device, reason = resolve_device("gpu")
    assert device == "cpu"
    assert reason == "device must be one of auto, cpu, cuda; got 'gpu'"


def test_without_gpu_auto_is_silent_and_cuda_says_why():
    """No GPU: ``auto`` gives the CPU silently, ``cuda`` the CPU and one line of why."""
    if _gpu_usable():
        pytest.skip("this process has a GPU (or the simulator)")
    assert resolve_device("auto") == ("cpu", None)
    device, reason = resolve_device("cuda")
    assert device == "cpu"
    assert reason == "device 'cuda' needs an NVIDIA GPU with its driver, and none is usable here"


def test_volume_view_falls_back_to_the_cpu(monkeypatch):
    """``VHM_DEVICE=cuda`` without a GPU: one status line, and the CPU's deformed volume."""
    pv = pytest.importorskip("pyvista")
    if _gpu_usable():
        pytest.skip("this process has a GPU (or the simulator)")
    from vhm_viz.app.volume import VolumeView

    n = 10
    image = pv.ImageData(dimensions=(n, n, n), spacing=(0.2, 0.2, 0.2), origin=(-0.9,) * 3)
    image.point_data["density"] = np.random.default_rng(3).random(n**3).astype(np.float32)
    v, f = box_cage((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 1)
    t = v.copy()
    t[:, 0] += 0.2 * (t[:, 2] + 1.0) * (t[:, 1] > 0)
    hm = HarmonicMap.from_target_cage(Cage(v, f), t)

    monkeypatch.setenv("VHM_DEVICE", "cuda")
    asked = VolumeView(image)
    device, reason = asked.device()
    assert device == "cpu"
    assert reason.splitlines() == [reason]
    assert reason.startswith("volume views run on the CPU (VHM_DEVICE=cuda: device 'cuda' needs")
    monkeypatch.setenv("VHM_DEVICE", "auto")
    assert VolumeView(image).device() == ("cpu", None)
    on_cpu = VolumeView(image, device="cpu")
    assert on_cpu.device() == ("cpu", None)
    got, want = asked.deformed_image(hm), on_cpu.deformed_image(hm)
    np.testing.assert_array_equal(got.point_data["values"], want.point_data["values"])
    np.testing.assert_array_equal(
        got.point_data["vtkValidPointMask"], want.point_data["vtkValidPointMask"]
    )
    assert np.asarray(got.point_data["vtkValidPointMask"]).sum() > 0
