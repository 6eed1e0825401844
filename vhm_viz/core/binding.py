"""Point sets bound to a deformation: deforming many points is one matrix product.

The one place where many points meet the cage basis. Every front end -- the VTK filters,
the command line, the explorer, ParaView -- binds through here, so they share one outside
policy, one inside test (:func:`~vhm_viz.core.basis.classify_inside`), one memory bound and
one way to report progress and to stop.

* :class:`Binding` (made by :meth:`Deformer.bind <vhm_viz.core.deformer.Deformer.bind>`)
  precomputes ``F = D_points B`` for a deformer, so that each new solution deforms the
  points with one product (paper eq. 8). ``F`` acts on the change from the rest pose,
  ``x = p + F ([h; R] - [h_rest; I])``, which keeps float32 storage accurate.
* :class:`MapBinding` (made by :func:`bind_map`) evaluates a fixed
  :class:`~vhm_viz.core.harmonic_map.HarmonicMap` at the points; nothing is precomputed.

Both evaluate the basis in chunks whose arrays fit in a memory budget
(:func:`~vhm_viz.core.basis.chunk_rows`), call ``progress(fraction, message)`` after each
chunk and ``abort()`` before it: a true return raises :class:`~vhm_viz.core.errors.AbortedError`
(the VTK filters pass their ``AbortExecute`` flag).

Outside policies (:data:`OUTSIDE_POLICIES`), for points outside the cage:

* ``"error"`` -- raise :class:`~vhm_viz.core.errors.OutsideCageError` naming them;
* ``"passthrough"`` -- leave them where they are (Jacobian ``I``);
* ``"nan"`` -- NaN positions and Jacobians.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from vhm_viz.core.basis import (
    chunk_rows,
    classify_inside,
    evaluate_basis,
    surface_hosts,
    surface_points_inside,
)
from vhm_viz.core.errors import AbortedError, OutsideCageError, describe_indices
from vhm_viz.core.limits import check_setting
from vhm_viz.core.points import as_points

__all__ = [
    "OUTSIDE_POLICIES",
    "Binding",
    "MapBinding",
    "bind_map",
    "check_outside_policy",
    "cofactor_normals",
    "outside_mask",
]

#: What to do with points outside the cage (see the module documentation).
OUTSIDE_POLICIES = ("error", "passthrough", "nan")
# Bindings with fewer F entries than this deform with numpy instead of the parallel kernel.
_SMALL_F = 2_000_000

ProgressCallback = Callable[[float, str], None]
AbortCallback = Callable[[], bool]


def check_outside_policy(policy: str) -> str:
    """Return ``policy`` if it is one of :data:`OUTSIDE_POLICIES`, else raise ValueError."""
    if policy not in OUTSIDE_POLICIES:
        raise ValueError(f"outside policy must be one of {OUTSIDE_POLICIES}; got {policy!r}")
    return policy


def _check_abort(abort: AbortCallback | None) -> None:
    if abort is not None and abort():
        raise AbortedError("aborted")


def outside_mask(points, vertices, faces, policy: str = "error") -> np.ndarray:
    """Which points lie outside the cage; raise for policy ``"error"``.

    Parameters
    ----------
    points : (P, 3) float64
    vertices : (n, 3) float64
        Cage vertices.
    faces : (m, 3) int
        Cage faces (outward).
    policy : {"error", "passthrough", "nan"}

    Returns
    -------
    (P,) bool
        True where the point is outside (:func:`~vhm_viz.core.basis.classify_inside`:
        points on the cage surface, on either side within rounding, are inside).

    Raises
    ------
    OutsideCageError
        With policy ``"error"`` when any point is outside (their indices listed).
    """
    return _classify(points, vertices, faces, policy)[0]


def _classify(points, vertices, faces, policy: str) -> tuple[np.ndarray, np.ndarray]:
    """``outside`` mask and host faces (:func:`~vhm_viz.core.basis.classify_inside`)."""
    check_outside_policy(policy)
    p = as_points(points)
    if len(p) == 0:
        return np.zeros(0, bool), np.zeros(0, np.int64)
    inside, hosts = classify_inside(p, vertices, faces)
    out = ~inside
    if out.any() and policy == "error":
        bad = np.nonzero(out)[0]
        raise OutsideCageError(
            f"{bad.size} of {len(p)} points are outside the cage (indices "
            f"{describe_indices(bad)}); use the 'passthrough' outside policy to leave them "
            "unchanged",
            bad,
        )
    return out, hosts


def cofactor_normals(jacobians: np.ndarray, normals, *, normalize: bool = True) -> np.ndarray:
    """Normals deformed through the Jacobian: ``n' = cof(J) n`` (paper eq. 6).

    ``cof(J) n = (J t1) x (J t2)`` for any tangent pair with ``t1 x t2 = n``: the normal of
    the deformed tangent plane.

    Parameters
    ----------
    jacobians : (P, 3, 3) float64
        ``J[k, i, j] = d f_i / d x_j``.
    normals : (P, 3) array_like
    normalize : bool
        Unit normals (default; zero where ``cof(J) n`` vanishes) or the raw ``cof(J) n``
        (scaled by the area change).

    Returns
    -------
    (P, 3) float64
    """
    n = np.asarray(normals, dtype=np.float64)
    if n.shape != (len(jacobians), 3):
        raise ValueError(f"normals must have shape ({len(jacobians)}, 3); got {n.shape}")
    c0, c1, c2 = jacobians[:, :, 0], jacobians[:, :, 1], jacobians[:, :, 2]
    out = n[:, 0:1] * np.cross(c1, c2) + n[:, 1:2] * np.cross(c2, c0) + n[:, 2:3] * np.cross(c0, c1)
    if normalize:
        ln = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.divide(out, ln, out=np.zeros_like(out), where=ln > 0)
    return out


@numba.njit(parallel=True, fastmath=True, cache=True)
def _apply_rows(F, dwt, p, rows, out):  # pragma: no cover - compiled
    """out[rows[i]] = p[rows[i]] + F[i] @ dw, with float64 accumulation.

    A dedicated kernel: numpy's matmul of a tall (P, K) by a (K, 3) matrix runs at a
    fraction of the memory bandwidth, while this product is purely bandwidth-bound.
    """
    for i in numba.prange(F.shape[0]):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for k in range(F.shape[1]):
            f = F[i, k]
            s0 += f * dwt[0, k]
            s1 += f * dwt[1, k]
            s2 += f * dwt[2, k]
        r = rows[i]
        out[r, 0] = p[r, 0] + s0
        out[r, 1] = p[r, 1] + s1
        out[r, 2] = p[r, 2] + s2


class _BoundPoints:
    """What both bindings share: the points, the outside mask, chunking, normals."""

    def __init__(self, points, vertices, faces, outside, memory_budget):
        self.outside_policy = check_outside_policy(outside)
        self.points = as_points(points).copy()
        self.points.flags.writeable = False
        if memory_budget is not None:
            memory_budget = check_setting("memory_budget", memory_budget)
        self.memory_budget = memory_budget
        #: (P,) bool: points outside the cage.
        self.outside, hosts = _classify(self.points, vertices, faces, self.outside_policy)
        self.outside.flags.writeable = False
        self._idx = np.nonzero(~self.outside)[0]
        # points on the cage surface that rounding put outside are evaluated just inside
        self._eval = surface_points_inside(self.points, hosts, vertices, faces)[self._idx]
        self._cage = (vertices, faces)

    @property
    def n_outside(self) -> int:
        """Number of points outside the cage."""
        return int(self.outside.sum())

    @property
    def inside(self) -> np.ndarray:
        """(P,) bool: points inside the cage (deformed by the map)."""
        return ~self.outside

    def _fill_outside(self, out: np.ndarray) -> None:
        """Outside rows of a (P, 3) or (P, 3, 3) result: identity or NaN by policy."""
        if not self.outside.any():
            return
        if self.outside_policy == "nan":
            out[self.outside] = np.nan
        elif out.ndim == 2:
            out[self.outside] = self.points[self.outside]
        else:
            out[self.outside] = np.eye(3)

    def _move_undefined(self, undefined: np.ndarray) -> np.ndarray:
        """Evaluate the points whose derivatives came out undefined just inside.

        ``undefined`` (bool, one per inside point): rows with non-finite derivatives. Those
        on a cage edge or at a vertex (within rounding of the surface) are moved as
        :func:`~vhm_viz.core.basis.surface_points_inside` moves points that rounding put
        outside. Returns the moved rows, for the caller to evaluate again.
        """
        rows = np.nonzero(undefined)[0]
        if rows.size:
            vertices, faces = self._cage
            hosts = surface_hosts(self._eval[rows], vertices, faces)
            rows, hosts = rows[hosts >= 0], hosts[hosts >= 0]
            self._eval[rows] = surface_points_inside(self._eval[rows], hosts, vertices, faces)
        return rows

    def _chunks(self, order: int, n_columns: int):
        rows = chunk_rows(n_columns, order, self.memory_budget)
        n = self._idx.size
        for s in range(0, n, rows):
            yield s, min(n, s + rows)

    def deform_normals(self, normals, *, normalize: bool = True) -> np.ndarray:
        """Normals at the bound points deformed through the Jacobian (paper eq. 6).

        Parameters
        ----------
        normals : (P, 3) array_like
            One normal per bound point.
        normalize : bool
            Unit normals (default) or the raw ``cof(J) n``.

        Returns
        -------
        (P, 3) float64
        """
        return cofactor_normals(self.jacobians(), normals, normalize=normalize)

    def jacobians(self, progress=None, abort=None) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError


class Binding(_BoundPoints):
    """A point set bound to a :class:`~vhm_viz.core.deformer.Deformer`.

    Made by :meth:`Deformer.bind <vhm_viz.core.deformer.Deformer.bind>`. :meth:`deform`
    returns ``p + F (w - w_rest)`` with ``w = [h; R_local]`` the deformer's current
    variables (paper eq. 8, relative to the rest pose ``w_rest = [h_rest; I]``, whose image
    is the identity). When the deformer's constraint *points* change, ``F`` is recomputed
    on the next call (:meth:`refresh`).

    Parameters
    ----------
    deformer : Deformer
        With constraints set.
    points : (P, 3) array_like
    outside : {"error", "passthrough", "nan"}
    dtype : numpy dtype
        ``float64`` (default) or ``float32`` storage of ``F`` (half the memory and bandwidth;
        the rounding error stays far below 1e-6 of the bounding-box diagonal because ``F``
        acts on the change from the rest pose -- ``benchmarks/bench_solver.py`` measures it).
    memory_budget : int, optional
        Bytes of basis arrays per chunk (:func:`~vhm_viz.core.basis.chunk_rows`), in
        [1, 2**40].
    progress : callable(fraction, message), optional
        Called after each chunk of the precomputation.
    abort : callable() -> bool, optional
        Checked before each chunk; :class:`~vhm_viz.core.errors.AbortedError` when true.

    Attributes
    ----------
    points : (P, 3) float64, read-only
    outside : (P,) bool, read-only
    """

    def __init__(
        self,
        deformer,
        points,
        *,
        outside: str = "error",
        dtype=np.float64,
        memory_budget: int | None = None,
        progress: ProgressCallback | None = None,
        abort: AbortCallback | None = None,
    ):
        dtype = np.dtype(dtype)
        if dtype not in (np.float32, np.float64):
            raise ValueError(f"dtype must be float32 or float64; got {dtype}")
        super().__init__(points, deformer._V, deformer._Fc, outside, memory_budget)
        self.deformer = deformer
        self.dtype = dtype
        self._F = None
        self._FG = None
        self._version = None
        self.refresh(progress, abort)

    # -- precomputation
    def refresh(self, progress: ProgressCallback | None = None, abort=None) -> None:
        """Recompute ``F`` if the deformer's constraint layout changed since the last call."""
        if self._version == self.deformer._layout_version and self._F is not None:
            return
        self._F = self._basis_times_B(0, progress, abort, "binding")
        self._FG = None
        self._version = self.deformer._layout_version

    def _basis_times_B(self, order: int, progress, abort, message: str) -> np.ndarray:
        """``D B`` (order 0, (P, K)) or ``G B`` (order 1, (P, 3, K)) at the inside points."""
        dfm = self.deformer
        B = dfm._B
        pts = self._eval
        shape = (len(pts), B.shape[1]) if order == 0 else (len(pts), 3, B.shape[1])
        out = np.empty(shape, dtype=self.dtype)
        for s, e in self._chunks(order, B.shape[0]):
            _check_abort(abort)
            b = evaluate_basis(pts[s:e], dfm._V, dfm._Fc, order=order)
            out[s:e] = (b.gradients if order else b.values) @ B
            if progress is not None:
                progress(e / max(len(pts), 1), message)
        return out

    def _compute_FG(self, progress, abort) -> None:
        FG = self._basis_times_B(1, progress, abort, "jacobians")
        bad = ~np.isfinite(FG).all(axis=(1, 2))
        moved = self._move_undefined(bad)
        if moved.size:  # on a cage edge or at a vertex: values and Jacobians just inside
            dfm = self.deformer
            b = evaluate_basis(self._eval[moved], dfm._V, dfm._Fc, order=1)
            self._F[moved] = b.values @ dfm._B
            FG[moved] = b.gradients @ dfm._B
            bad = ~np.isfinite(FG).all(axis=(1, 2))
        if bad.any():
            raise ValueError(
                f"bound points {describe_indices(self._idx[bad])} lie on a cage edge or vertex: "
                "the Jacobian is undefined there"
            )
        self._FG = FG.reshape(3 * FG.shape[0], FG.shape[2])

    def _delta_w(self) -> np.ndarray:
        dfm = self.deformer
        w_rest = np.vstack([dfm._h_rest, np.tile(np.eye(3), (dfm.n_anchors, 1))])
        return dfm.stacked_variables - w_rest

    @property
    def nbytes(self) -> int:
        """Memory of the stored ``F`` (and of the Jacobian binding, once computed)."""
        return int(self._F.nbytes + (0 if self._FG is None else self._FG.nbytes))

    @property
    def F(self) -> np.ndarray:
        """(P_inside, c + 3d) ``D_points B`` (read-only view)."""
        self.refresh()
        v = self._F.view()
        v.flags.writeable = False
        return v

    # -- evaluation
    def deform(self, out=None) -> np.ndarray:
        """Deformed positions of the bound points, (P, 3) float64.

        Parameters
        ----------
        out : (P, 3) float64 ndarray, optional
            Written in place and returned.
        """
        self.refresh()
        dwt = np.ascontiguousarray(self._delta_w().T, dtype=np.float64)
        if out is None:
            out = np.empty((len(self.points), 3))
        elif out.shape != self.points.shape or out.dtype != np.float64:
            raise ValueError(f"out must be a float64 array of shape {self.points.shape}")
        all_inside = self._idx.size == len(self.points)
        if self._F.size < _SMALL_F:
            # small products: numpy avoids waking the kernel's thread pool
            delta = self._F @ dwt.T.astype(self.dtype)
            if all_inside:
                np.add(self.points, delta, out=out)
            else:
                out[self._idx] = self.points[self._idx] + delta
        elif self._idx.size:
            _apply_rows(self._F, dwt, self.points, self._idx, out)
        self._fill_outside(out)
        return out

    def jacobians(self, progress=None, abort=None) -> np.ndarray:
        """Jacobians ``J[k, i, j] = d f_i / d x_j`` at the bound points, (P, 3, 3).

        The first call precomputes the gradient binding (three times the memory of ``F``),
        in chunks with ``progress`` and ``abort``. Outside points get ``I`` (passthrough)
        or NaN.
        """
        self.refresh()
        if self._FG is None:
            self._compute_FG(progress, abort)
        dw = self._delta_w().astype(self.dtype)
        jt = np.empty((len(self.points), 3, 3))
        jt[self._idx] = np.eye(3) + (self._FG @ dw).reshape(-1, 3, 3)
        jac = np.ascontiguousarray(np.swapaxes(jt, 1, 2))
        self._fill_outside(jac)
        return jac

    def __repr__(self) -> str:
        return (
            f"Binding(points={len(self.points)}, inside={self._idx.size}, dtype={self.dtype}, "
            f"F={self.nbytes / 1e6:.1f} MB)"
        )


class MapBinding(_BoundPoints):
    """A point set evaluated under a fixed :class:`~vhm_viz.core.harmonic_map.HarmonicMap`.

    Made by :func:`bind_map`; the same interface as :class:`Binding` (``outside``,
    ``deform``, ``jacobians``, ``deform_normals``), nothing precomputed.
    """

    def __init__(self, harmonic_map, points, *, outside="error", memory_budget=None):
        cage = harmonic_map.cage
        super().__init__(points, cage.vertices, cage.faces, outside, memory_budget)
        self.map = harmonic_map

    def _run(self, order: int, progress, abort) -> np.ndarray:
        cage, z = self.map.cage, self.map._z_local  # origin-free (see HarmonicMap)
        n_cols = len(cage.vertices) + len(cage.faces)
        shape = (len(self.points), 3, 3) if order else (len(self.points), 3)
        out = np.empty(shape)
        pts = self._eval
        total = max(pts.shape[0], 1)
        for s, e in self._chunks(order, n_cols):
            _check_abort(abort)
            b = evaluate_basis(pts[s:e], cage.vertices, cage.faces, order=order)
            rows = self._idx[s:e]
            if order:
                out[rows] = np.swapaxes(b.gradients @ z, 1, 2)
            else:
                out[rows] = self.map._offset + b.values @ z
            if progress is not None:
                progress(e / total, "jacobians" if order else "mapping")
        if order:
            moved = self._move_undefined(~np.isfinite(out[self._idx]).all(axis=(1, 2)))
            if moved.size:  # on a cage edge or at a vertex: the Jacobians just inside
                b = evaluate_basis(self._eval[moved], cage.vertices, cage.faces, order=1)
                out[self._idx[moved]] = np.swapaxes(b.gradients @ z, 1, 2)
        self._fill_outside(out)
        return out

    def deform(self, progress=None, abort=None) -> np.ndarray:
        """Mapped positions (P, 3)."""
        return self._run(0, progress, abort)

    def jacobians(self, progress=None, abort=None) -> np.ndarray:
        """Jacobians (P, 3, 3); identity (passthrough) or NaN outside the cage."""
        return self._run(1, progress, abort)

    def __repr__(self) -> str:
        return f"MapBinding(points={len(self.points)}, inside={self._idx.size})"


def bind_map(harmonic_map, points, *, outside: str = "error", memory_budget=None) -> MapBinding:
    """Bind points to a fixed harmonic map (see :class:`MapBinding`)."""
    return MapBinding(harmonic_map, points, outside=outside, memory_budget=memory_budget)
