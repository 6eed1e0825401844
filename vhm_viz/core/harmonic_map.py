"""The harmonic map ``f(p) = sum_v a_v phi_v(p) + sum_t b_t psi_t(p)`` of a cage."""

from __future__ import annotations

import numpy as np

from vhm_viz.core.basis import (
    chunk_rows,
    classify_inside,
    evaluate_inside,
    evaluate_map,
    hessian5_to_full,
    surface_points_inside,
)
from vhm_viz.core.binding import check_outside_policy
from vhm_viz.core.devices import require_device
from vhm_viz.core.errors import OutsideCageError, SettingError, describe_indices
from vhm_viz.core.geometry import face_normals_and_areas
from vhm_viz.core.points import as_points


class HarmonicMap:
    """A harmonic map of the space inside a cage, in closed form.

    Parameters
    ----------
    cage : Cage
        Any object with ``vertices`` (n, 3), ``faces`` (m, 3) and ``face_normals`` (m, 3)
        (normally a validated :class:`vhm_viz.Cage`).
    coefficients : (n + m, 3) array_like
        ``z = [a; b]``: vertex coefficients ``a_v`` first, then face coefficients ``b_t``.
    device : {"cpu", "cuda"}
        Where :meth:`evaluate` and the volume engine's exact evaluations run by default:
        the CPU, or an NVIDIA GPU (:mod:`vhm_viz.core.cuda_map`; refused with
        :class:`~vhm_viz.core.errors.DeviceUnavailableError` where there is none).

    Notes
    -----
    Jacobians follow ``J[k, i, j] = d f_i / d x_j`` and Hessians
    ``H[k, i, j, l] = d^2 f_i / d x_j d x_l``. Points outside the cage (winding number
    below 1/2) are refused by default, because the formulas there give a harmonic
    function unrelated to the deformation the user set up.
    """

    def __init__(self, cage, coefficients, *, device: str = "cpu"):
        self.cage = cage
        self.device = require_device(device)
        z = np.array(coefficients, dtype=np.float64)
        n, m = len(cage.vertices), len(cage.faces)
        if z.shape != (n + m, 3):
            raise ValueError(
                f"coefficients must have shape (n_vertices + n_faces, 3) = ({n + m}, 3); "
                f"got {z.shape}"
            )
        if not np.isfinite(z).all():
            rows = np.nonzero(~np.isfinite(z).all(axis=1))[0]
            raise ValueError(f"coefficients are not finite in rows {describe_indices(rows)}")
        z.flags.writeable = False
        self._z = z
        # Inside the cage sum_v phi_v = 1 and sum_v grad phi_v = 0, so the map is also
        # c + sum_v phi_v (a_v - c) + sum_t psi_t b_t: with c the image of the cage's
        # centre, a cage far from the origin (coefficients ~1e7) is evaluated without the
        # cancellation of sum_v phi_v a_v, which cost 1e-8 of the coefficients' size.
        self._offset = 0.5 * (z[:n].min(axis=0) + z[:n].max(axis=0)) if n else np.zeros(3)
        local = z.copy()
        local[:n] -= self._offset
        local.flags.writeable = False
        self._z_local = local

    # ---------------------------------------------------------------- constructors
    @classmethod
    def identity(cls, cage) -> HarmonicMap:
        """The identity map: ``a_v = x_v``, ``b_t = N_t``."""
        return cls.affine(cage, np.eye(3), np.zeros(3))

    @classmethod
    def affine(cls, cage, matrix, translation=(0.0, 0.0, 0.0)) -> HarmonicMap:
        """The affine map ``p -> A p + T``, reproduced exactly inside the cage.

        Parameters
        ----------
        cage : Cage
        matrix : (3, 3) array_like
            ``A``.
        translation : (3,) array_like
            ``T``.
        """
        a = np.asarray(matrix, dtype=np.float64).reshape(3, 3)
        t = np.asarray(translation, dtype=np.float64).reshape(3)
        v = np.asarray(cage.vertices, dtype=np.float64)
        return cls(cage, np.vstack([v @ a.T + t, np.asarray(cage.face_normals) @ a.T]))

    @classmethod
    def from_target_cage(cls, cage, target_vertices) -> HarmonicMap:
        """Cage-driven 3D Green Coordinates deformation (Lipman, Levin, Cohen-Or 2008).

        ``a = target vertices``, ``b_t = s_t * N'_t`` with ``N'_t`` the unit normal of the
        deformed face and ``s_t`` Green Coordinates' stretch factor, which makes the map
        reproduce similarities of the cage exactly.

        Parameters
        ----------
        cage : Cage
            Source cage.
        target_vertices : (n, 3) array_like
            Deformed cage vertices (same connectivity).
        """
        src = np.asarray(cage.vertices, dtype=np.float64)
        tgt = np.asarray(target_vertices, dtype=np.float64)
        if tgt.shape != src.shape:
            raise ValueError(f"target_vertices must have shape {src.shape}; got {tgt.shape}")
        if not np.isfinite(tgt).all():
            raise ValueError("target_vertices contain non-finite coordinates")
        f = np.asarray(cage.faces)
        return cls(
            cage,
            np.vstack(
                [tgt, green_stretch(src, tgt, f)[:, None] * face_normals_and_areas(tgt, f)[0]]
            ),
        )

    def on(self, device: str) -> HarmonicMap:
        """The same map, evaluated on ``device`` by default (itself if already so)."""
        if require_device(device) == self.device:
            return self
        other = HarmonicMap.__new__(HarmonicMap)
        other.__dict__.update(self.__dict__, device=device)
        return other

    # ---------------------------------------------------------------- properties
    @property
    def coefficients(self) -> np.ndarray:
        """``z`` (n + m, 3), read-only."""
        return self._z

    @property
    def vertex_coefficients(self) -> np.ndarray:
        """``a`` (n, 3): the vertex rows of ``z``."""
        return self._z[: len(self.cage.vertices)]

    @property
    def face_coefficients(self) -> np.ndarray:
        """``b`` (m, 3): the face rows of ``z``."""
        return self._z[len(self.cage.vertices) :]

    # ---------------------------------------------------------------- evaluation
    def inside(self, points) -> np.ndarray:
        """Mask of the points inside the cage or on it.

        The one inside test, :func:`~vhm_viz.core.basis.classify_inside`.
        """
        return classify_inside(points, self.cage.vertices, self.cage.faces)[0]

    def evaluate(
        self,
        points,
        *,
        order: int = 0,
        outside: str = "error",
        memory_budget: int | None = None,
        device: str | None = None,
    ):
        """Map values and, on request, Jacobians and Hessians, in one pass over the basis.

        Parameters
        ----------
        points : (N, 3) array_like
        order : {0, 1, 2}
            Highest derivative wanted.
        outside : {"error", "passthrough", "nan"}
            Points outside the cage: raise :class:`OutsideCageError` naming them; leave
            them where they are (identity value, Jacobian I, Hessian 0); or fill with NaN.
        memory_budget : int, optional
            Bytes of basis arrays per chunk (:func:`~vhm_viz.core.basis.chunk_rows`).
        device : {"cpu", "cuda"}, optional
            Where the closed forms are evaluated: the CPU or an NVIDIA GPU
            (:mod:`vhm_viz.core.cuda_map`, values and Jacobians only, equal to the CPU's to
            rounding); :class:`~vhm_viz.core.errors.DeviceUnavailableError` when this
            machine has no usable GPU. Default: the map's :attr:`device` ("cpu" unless
            made otherwise).

        Returns
        -------
        f : (N, 3) ndarray
        J : (N, 3, 3) ndarray or None
        H : (N, 3, 3, 3) ndarray or None
        """
        check_outside_policy(outside)
        device = self.device if device is None else require_device(device)
        if device == "cuda":
            return self._evaluate_fused(points, order, outside, device)
        p = as_points(points)
        npts = len(p)
        f = p.copy()
        jac = np.broadcast_to(np.eye(3), (npts, 3, 3)).copy() if order >= 1 else None
        hess = np.zeros((npts, 3, 3, 3)) if order >= 2 else None
        inside = np.ones(npts, dtype=bool)
        z = self._z_local  # relative to the offset (see __init__)
        chunk_size = chunk_rows(len(z), order, memory_budget)
        for s in range(0, npts, chunk_size):
            rows = slice(s, s + chunk_size)
            b, ins = evaluate_inside(p[rows], self.cage.vertices, self.cage.faces, order=order)
            inside[rows] = ins
            if not ins.all() and outside == "error":
                self._raise_outside(p, s, ins)
            f[rows] = np.where(ins[:, None], self._offset + b.values @ z, p[rows])
            # all inside (the usual case): no copies of the basis arrays, one matrix product
            sel = slice(None) if ins.all() else ins
            if order >= 1:
                # gradients[k, j, c] z[c, i] = d f_i / d x_j  ->  J[k, i, j]
                jac[rows][sel] = np.swapaxes(_times(b.gradients[sel], z), 1, 2)
            if order >= 2:
                hess[rows][sel] = hessian5_to_full(np.swapaxes(_times(b.hessians[sel], z), 1, 2))
        return _outside_nan(outside, inside, f, jac, hess)

    def _evaluate_fused(self, points, order: int, outside: str, device: str):
        """:meth:`evaluate` through the fused map kernels (no basis arrays), on ``device``.

        The same inside test and surface rule as the basis path: points on the surface
        that the winding number puts outside are evaluated just inside.
        """
        if order not in (0, 1):
            raise SettingError(
                "order", f"must be 0 or 1 on device {device!r} (Hessians: device 'cpu'); "
                f"got {order!r}"
            )  # fmt: skip
        p = as_points(points)
        V, F = self.cage.vertices, self.cage.faces
        z = self._z_local  # relative to the offset (see __init__)
        f, jac, winding = evaluate_map(p, V, F, z, order=order, device=device)
        undefined = None if jac is None else ~np.isfinite(jac).all(axis=(1, 2))
        inside, hosts = classify_inside(p, V, F, winding, undefined)
        if not inside.all() and outside == "error":
            self._raise_outside(p, 0, inside)
        on = np.nonzero(hosts >= 0)[0]
        if on.size:
            q = surface_points_inside(p[on], hosts[on], V, F)
            f[on], j_on, _ = evaluate_map(q, V, F, z, order=order, device=device)
            if order:
                jac[on] = j_on
        f = np.where(inside[:, None], self._offset + f, p)
        if order:
            jac[~inside] = np.eye(3)
        return _outside_nan(outside, inside, f, jac, None)

    def _raise_outside(self, p, start, inside_chunk):
        """Raise OutsideCageError naming every outside point (scans the rest cheaply)."""
        bad = [start + np.nonzero(~inside_chunk)[0]]
        rest = p[start + len(inside_chunk) :]
        if len(rest):
            bad.append(start + len(inside_chunk) + np.nonzero(~self.inside(rest))[0])
        if start:
            bad.insert(0, np.nonzero(~self.inside(p[:start]))[0])
        bad = np.concatenate(bad)
        raise OutsideCageError(
            f"{bad.size} of {len(p)} points are outside the cage (indices "
            f"{describe_indices(bad)}); pass outside='passthrough' to leave them unchanged",
            bad,
        )

    def map(self, points, *, outside: str = "error") -> np.ndarray:
        """Deformed positions ``f(p)``, shape (N, 3). See :meth:`evaluate` for ``outside``."""
        return self.evaluate(points, order=0, outside=outside)[0]

    def jacobian(self, points, *, outside: str = "error") -> np.ndarray:
        """Jacobians ``J[k, i, j] = d f_i / d x_j``, shape (N, 3, 3)."""
        return self.evaluate(points, order=1, outside=outside)[1]

    def hessian(self, points, *, outside: str = "error") -> np.ndarray:
        """Hessians ``H[k, i, j, l] = d^2 f_i / d x_j d x_l``, shape (N, 3, 3, 3)."""
        return self.evaluate(points, order=2, outside=outside)[2]

    def __call__(self, points, **kwargs) -> np.ndarray:
        """Same as :meth:`map`."""
        return self.map(points, **kwargs)

    def __repr__(self) -> str:
        return f"HarmonicMap(n_vertices={len(self.cage.vertices)}, n_faces={len(self.cage.faces)})"


def _outside_nan(outside: str, inside: np.ndarray, f, jac, hess) -> tuple:
    """``(f, jac, hess)``, with NaN at the outside points under the ``"nan"`` policy."""
    if outside == "nan" and not inside.all():
        out = ~inside
        for arr in (f, jac, hess):
            if arr is not None:
                arr[out] = np.nan
    return f, jac, hess


def _times(basis: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``basis @ z`` for an (N, k, n + m) stack, as one (N k, n + m) matrix product."""
    n, k, c = basis.shape
    return (basis.reshape(n * k, c) @ z).reshape(n, k, z.shape[1])


def green_stretch(source_vertices, target_vertices, faces) -> np.ndarray:
    """Green Coordinates' per-face stretch factor ``s_t``.

    ``s_t = sqrt(|u'|^2 |v|^2 - 2 (u'.v')(u.v) + |v'|^2 |u|^2) / (sqrt(8) A_t)`` with
    ``u, v`` the source edge vectors of face ``t``, ``u', v'`` the target ones and
    ``A_t`` the source area (Lipman, Levin, Cohen-Or 2008, Section 3.1). It is 1 for
    rigid motions and ``c`` for a uniform scale by ``c``.

    Parameters
    ----------
    source_vertices, target_vertices : (n, 3) array_like
    faces : (m, 3) array_like of int
        The triangles, the same for both vertex sets.

    Returns
    -------
    (m,) ndarray
    """
    s = np.asarray(source_vertices, dtype=np.float64)
    t = np.asarray(target_vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    u, v = s[f[:, 1]] - s[f[:, 0]], s[f[:, 2]] - s[f[:, 0]]
    u2, v2 = t[f[:, 1]] - t[f[:, 0]], t[f[:, 2]] - t[f[:, 0]]
    dot = lambda a, b: np.einsum("ij,ij->i", a, b)  # noqa: E731
    num = dot(u2, u2) * dot(v, v) - 2.0 * dot(u2, v2) * dot(u, v) + dot(v2, v2) * dot(u, u)
    area = 0.5 * np.linalg.norm(np.cross(u, v), axis=1)
    return np.sqrt(np.maximum(num, 0.0)) / (np.sqrt(8.0) * area)
