"""Exception types shared by every layer of vhm_viz."""

from __future__ import annotations

import numpy as np


class CageError(ValueError):
    """A cage that cannot define a harmonic map (open, non-manifold, self-intersecting, ...).

    Parameters
    ----------
    message : str
        What is wrong, naming the offending vertices/faces.
    indices : array_like of int, optional
        The offending vertex or face indices, for programmatic use.
    """

    def __init__(self, message: str, indices=None):
        super().__init__(message)
        self.indices = None if indices is None else np.asarray(indices)


class OutsideCageError(ValueError):
    """Points that lie outside the cage, where the harmonic map is meaningless.

    Parameters
    ----------
    message : str
        Human-readable description.
    indices : array_like of int
        Indices of the points that are outside.
    """

    def __init__(self, message: str, indices):
        super().__init__(message)
        self.indices = np.asarray(indices)


class ConstraintError(ValueError):
    """Constraints that make the variational problem impossible or ill posed."""


def describe_indices(indices, limit: int = 10) -> str:
    """Format an index list for an error message, eliding past ``limit`` entries.

    Parameters
    ----------
    indices : array_like of int
        Indices to show.
    limit : int
        At most this many are listed.

    Returns
    -------
    str
        For example ``"3, 17, 42"`` or ``"3, 17, ... (120 in all)"``.
    """
    idx = [int(i) for i in np.asarray(indices).ravel()]
    shown = ", ".join(str(i) for i in idx[:limit])
    if len(idx) > limit:
        shown += f", ... ({len(idx)} in all)"
    return shown


class AbortedError(RuntimeError):
    """Long work stopped because its abort callback said so (e.g. VTK's AbortExecute)."""


class SettingError(ValueError):
    """A setting of the wrong type or outside its documented range (``vhm_viz.core.limits``).

    Parameters
    ----------
    field : str
        The setting's name (``solver.max_iterations``).
    detail : str
        What is wrong, with the range (``must be an integer in [1, 1000000]; got 1e+12``);
        the message is ``f"{field} {detail}"``.
    """

    def __init__(self, field: str, detail: str):
        super().__init__(f"{field} {detail}")
        self.field = field
        self.detail = detail


class DeviceUnavailableError(SettingError):
    """A computing device was asked for (``device="cuda"``) that this machine cannot give.

    Parameters
    ----------
    detail : str
        What is missing and what to change; the message is ``f"device {detail}"``.
    """

    def __init__(self, detail: str):
        super().__init__("device", detail)


class FoldWarning(UserWarning):
    """An output made as asked that holds folds: resampled voxels with several pre-images.

    The resample filter warns with it in Python (in ParaView: its output window); the
    command line, which says so in its own fold line, ignores it.
    """
