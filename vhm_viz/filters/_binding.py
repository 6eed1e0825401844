"""Chunked evaluation of a deformation over many points, with progress and abort.

Pure numpy (no VTK): used by the VTK filters and the command line. A
:class:`ChunkedBinding` binds a point set to a :class:`~vhm_viz.Deformer` in chunks (one
:class:`~vhm_viz.core.deformer.Binding` per chunk) so that long precomputations can report
progress and be aborted between chunks; :class:`MapEvaluator` does the same for a fixed
:class:`~vhm_viz.HarmonicMap` (no precomputation to keep).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from vhm_viz.core.basis import winding_number
from vhm_viz.core.errors import OutsideCageError, describe_indices

__all__ = ["ChunkedBinding", "MapEvaluator", "AbortedError", "OUTSIDE_POLICIES", "outside_mask"]

# Policies for points outside the cage, as the filters and the CLI name them.
OUTSIDE_POLICIES = ("error", "passthrough")
# Winding-number threshold for "inside" (the solver's: points on the cage count as inside).
_WN_TOL = 1e-8
DEFAULT_CHUNK = 16384

ProgressCallback = Callable[[float, str], None]
AbortCallback = Callable[[], bool]


class AbortedError(RuntimeError):
    """The work was aborted through the abort callback (e.g. VTK's AbortExecute)."""


def normalize_outside(policy: str) -> str:
    """Map ``"raise"`` to ``"error"`` and check the policy name."""
    policy = "error" if policy == "raise" else policy
    if policy not in OUTSIDE_POLICIES:
        raise ValueError(f"outside policy must be one of {OUTSIDE_POLICIES}; got {policy!r}")
    return policy


def outside_mask(points: np.ndarray, cage, policy: str) -> np.ndarray:
    """Boolean mask of the points outside ``cage``; raises for policy ``"error"``.

    Parameters
    ----------
    points : (P, 3) float64
    cage : Cage
    policy : {"error", "passthrough"}

    Returns
    -------
    (P,) bool
        True where the point is outside the cage (winding number below 1/2).

    Raises
    ------
    OutsideCageError
        With policy ``"error"`` when any point is outside (indices listed).
    """
    policy = normalize_outside(policy)
    if len(points) == 0:
        return np.zeros(0, bool)
    wn = winding_number(points, cage.vertices, cage.faces)
    out = ~(wn >= 0.5 - _WN_TOL)
    if out.any() and policy == "error":
        bad = np.nonzero(out)[0]
        raise OutsideCageError(
            f"{bad.size} of {len(points)} points are outside the cage (indices "
            f"{describe_indices(bad)}); use the 'passthrough' outside policy to leave them "
            "unchanged",
            bad,
        )
    return out


def _chunks(n: int, size: int):
    for s in range(0, n, size):
        yield s, min(n, s + size)


class ChunkedBinding:
    """A point set bound to a deformer in chunks (progress and abort between chunks).

    Parameters
    ----------
    deformer : Deformer
        With constraints set.
    points : (P, 3) array_like
    outside : {"error", "passthrough"}
        Points outside the cage raise :class:`OutsideCageError` (global indices) or stay
        where they are.
    chunk_size : int
        Points per chunk.
    progress : callable(fraction, message), optional
    abort : callable() -> bool, optional
        Checked between chunks; :class:`AbortedError` when it returns True.

    Attributes
    ----------
    outside : (P,) bool
        Points outside the cage.
    n_outside : int
    """

    def __init__(
        self,
        deformer,
        points,
        *,
        outside: str = "error",
        chunk_size: int = DEFAULT_CHUNK,
        progress: ProgressCallback | None = None,
        abort: AbortCallback | None = None,
    ):
        self.deformer = deformer
        self.points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.chunk_size = max(1, int(chunk_size))
        self.outside = outside_mask(self.points, deformer.cage, outside)
        self.n_outside = int(self.outside.sum())
        self._bindings = []
        n = len(self.points)
        for s, e in _chunks(n, self.chunk_size):
            _check_abort(abort)
            self._bindings.append((s, e, deformer.bind(self.points[s:e], outside="passthrough")))
            if progress is not None:
                progress(e / max(n, 1), "binding")

    def deform(self) -> np.ndarray:
        """Deformed positions (P, 3) for the deformer's current solution."""
        out = self.points.copy()
        for s, e, b in self._bindings:
            b.deform(out=out[s:e])
        return out

    def jacobians(self, progress: ProgressCallback | None = None, abort=None) -> np.ndarray:
        """Jacobians ``J[k, i, j] = d f_i / d x_j`` (P, 3, 3); identity outside the cage."""
        out = np.empty((len(self.points), 3, 3))
        n = len(self.points)
        for s, e, b in self._bindings:
            _check_abort(abort)
            out[s:e] = b.jacobians()
            if progress is not None:
                progress(e / max(n, 1), "jacobians")
        return out


class MapEvaluator:
    """Values (and Jacobians) of a fixed :class:`HarmonicMap` over many points, chunked.

    Same interface as :class:`ChunkedBinding` (``outside``, ``n_outside``, ``deform``,
    ``jacobians``); nothing is precomputed.
    """

    def __init__(
        self,
        harmonic_map,
        points,
        *,
        outside: str = "error",
        chunk_size: int = DEFAULT_CHUNK,
        progress: ProgressCallback | None = None,
        abort: AbortCallback | None = None,
    ):
        self.map = harmonic_map
        self.points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.chunk_size = max(1, int(chunk_size))
        self.outside = outside_mask(self.points, harmonic_map.cage, outside)
        self.n_outside = int(self.outside.sum())
        self._progress, self._abort = progress, abort

    def _run(self, order: int, progress=None, abort=None):
        progress = progress or self._progress
        abort = abort or self._abort
        n = len(self.points)
        f = self.points.copy()
        jac = np.broadcast_to(np.eye(3), (n, 3, 3)).copy() if order else None
        idx = np.nonzero(~self.outside)[0]
        for s, e in _chunks(idx.size, self.chunk_size):
            _check_abort(abort)
            rows = idx[s:e]
            fv, jv, _ = self.map.evaluate(self.points[rows], order=order, outside="passthrough")
            f[rows] = fv
            if order:
                jac[rows] = jv
            if progress is not None:
                progress(e / max(idx.size, 1), "jacobians" if order else "mapping")
        return f, jac

    def deform(self) -> np.ndarray:
        """Deformed positions (P, 3)."""
        return self._run(0)[0]

    def jacobians(self, progress: ProgressCallback | None = None, abort=None) -> np.ndarray:
        """Jacobians (P, 3, 3); identity outside the cage."""
        return self._run(1, progress, abort)[1]


def _check_abort(abort) -> None:
    if abort is not None and abort():
        raise AbortedError("aborted")


def cofactor_normals(jacobians: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Unit normals deformed through the Jacobian: ``n' = cof(J) n / |cof(J) n|`` (eq. 6).

    Parameters
    ----------
    jacobians : (P, 3, 3) float64
        ``J[k, i, j] = d f_i / d x_j``.
    normals : (P, 3) array_like

    Returns
    -------
    (P, 3) float64
        Zero where ``cof(J) n`` vanishes.
    """
    n = np.asarray(normals, dtype=np.float64)
    c0, c1, c2 = jacobians[:, :, 0], jacobians[:, :, 1], jacobians[:, :, 2]
    out = n[:, 0:1] * np.cross(c1, c2) + n[:, 1:2] * np.cross(c2, c0) + n[:, 2:3] * np.cross(c0, c1)
    ln = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, ln, out=np.zeros_like(out), where=ln > 0)
