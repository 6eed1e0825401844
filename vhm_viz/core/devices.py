"""Where the closed-form map is evaluated: the CPU (always) or an NVIDIA GPU (optional).

The CPU kernels are the default and the reference. ``device="cuda"`` evaluates the map and
its Jacobians with the numba-cuda kernels of :mod:`vhm_viz.core.cuda_map`; this module
only checks names and availability, and imports ``numba.cuda`` only when a GPU is asked
for, so that the CPU path never pays for it.
"""

from __future__ import annotations

from vhm_viz.core.errors import DeviceUnavailableError, SettingError

__all__ = ["DEVICES", "check_device", "require_device"]

#: The devices the map can be evaluated on.
DEVICES = ("cpu", "cuda")


def check_device(device: str) -> str:
    """``device`` if it names a known device (availability is not checked).

    Raises
    ------
    SettingError
        For any other name.
    """
    if device not in DEVICES:
        raise SettingError("device", f"must be one of {', '.join(DEVICES)}; got {device!r}")
    return device


def require_device(device: str) -> str:
    """``device``, after checking that this machine can evaluate on it.

    Parameters
    ----------
    device : {"cpu", "cuda"}

    Returns
    -------
    str

    Raises
    ------
    DeviceUnavailableError
        ``"cuda"`` without numba's CUDA support or without a usable NVIDIA GPU and driver
        (numba's CUDA simulator, ``NUMBA_ENABLE_CUDASIM=1``, counts as a GPU).
    """
    if check_device(device) == "cpu":
        return device
    try:
        from numba import cuda
    except ImportError as exc:  # pragma: no cover - numba ships numba.cuda
        raise DeviceUnavailableError(
            f"'cuda' needs numba's CUDA support ({exc}); install numba-cuda or use device 'cpu'"
        ) from None
    if not cuda.is_available():
        raise DeviceUnavailableError(
            "'cuda' needs an NVIDIA GPU with its driver, and none is usable here; "
            "use device 'cpu' (the default)"
        )
    return device
