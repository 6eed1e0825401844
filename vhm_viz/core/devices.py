"""Where the closed-form map is evaluated: the CPU (always) or an NVIDIA GPU (optional).

The CPU kernels are the default and the reference. ``device="cuda"`` evaluates the map and
its Jacobians with the numba-cuda kernels of :mod:`vhm_viz.core.cuda_map`; this module
only checks names and availability, and imports ``numba.cuda`` only when a GPU is asked
for, so that the CPU path never pays for it.
"""

from __future__ import annotations

from vhm_viz.core.errors import DeviceUnavailableError, SettingError

__all__ = ["DEVICES", "DEVICE_SETTINGS", "check_device", "require_device", "resolve_device"]

#: The devices the map can be evaluated on.
DEVICES = ("cpu", "cuda")
#: What a user may ask for where a fallback is better than an error (the explorer):
#: a device, or ``"auto"`` (the GPU when one is usable, else the CPU).
DEVICE_SETTINGS = ("auto", *DEVICES)


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


def resolve_device(setting: str) -> tuple[str, str | None]:
    """The device to use for a setting, falling back to the CPU instead of failing.

    Parameters
    ----------
    setting : {"auto", "cpu", "cuda"}
        ``"auto"``: the GPU when one is usable, else the CPU, silently.

    Returns
    -------
    device : {"cpu", "cuda"}
    reason : str or None
        Why the CPU is used instead of what was asked for (``"cuda"`` without a usable
        GPU, or a setting that names no device), one line; None when the setting is met.
    """
    if setting not in DEVICE_SETTINGS:
        return "cpu", f"device must be one of {', '.join(DEVICE_SETTINGS)}; got {setting!r}"
    if setting == "cpu":
        return "cpu", None
    try:
        return require_device("cuda"), None
    except DeviceUnavailableError as exc:
        return "cpu", (None if setting == "auto" else str(exc).split(";")[0])
