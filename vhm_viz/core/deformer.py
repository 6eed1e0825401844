"""Variational harmonic maps: the paper's deformation solver (Sections 2.2 and 3).

:class:`Deformer` finds the harmonic map ``f(p) = D_p z`` of a cage that meets hard position
and Jacobian constraints and is As-Rigid-As-Possible (or As-Similar-As-Possible) at a few
anchor points while being smooth on the cage (problem P1 of the paper)::

    min_z,R  sum_i |J_f(m_i) - R_i|^2 + lambda^2 sum_k |H_f(w_k)|^2
    s.t.     f(q_i) = f_i,   J_f(t_i) = g_i,   R_i rotations (or similarities)

Design (all documented choices in one place):

* **Jacobian convention.** The user-facing Jacobian is ``J[i, j] = d f_i / d x_j``. The
  basis gradients ``G_p`` (3 x (n+m), ``G[j, c] = d basis_c / d x_j``) give
  ``G_p z = J^T``: the rows of the paper's eq. (4) stack hold the *transpose*. Internally
  every 3x3 block (anchor Jacobians, local matrices, Jacobian targets) is stored transposed;
  the public API converts at the boundary. The local step commutes with transposition.
* **Smoothness samples.** By default 3 per cage face, at the barycentric points
  ``(2/3, 1/6, 1/6)`` and permutations, pulled inward along the face normal by ``1e-3`` of
  the cage's bounding-box diagonal, or by half the cage's local thickness where the cage
  is thinner than twice that (k = 3 m samples, each giving 5 Hessian rows
  ``xx, xy, xz, yy, yz`` per map component, as in the paper's eq. 5). Your own samples can be
  passed instead; samples lying exactly on a face need ``smoothness_host_faces`` so that the
  interior limit of the basis is used.
* **lambda** follows the paper: ``lambda = alpha * d * ||J_anchors||_inf / ||H_samples||_inf``
  (infinity norms = largest absolute row sum of the stacked basis rows), ``alpha = 0.01``
  by default, with the norms taken in units of the cage's bounding-box diagonal so that
  lambda does not depend on the length unit
  (:func:`~vhm_viz.core.smoothness.smoothness_weight`). It depends on the
  sample layout (centroid samples roughly halve ``||H||_inf``) and grows with ``d``;
  quality is flat for alpha in [0.001, 0.01].
* **Hard constraints by elimination.** With ``K = [D_q; G_t]`` (``c = r + 3 s`` rows,
  rows normalised) and a pivoted QR ``K^T P = Q R``, every solution is
  ``z = P_h h + Q_2 y``; the rank of ``R`` detects dependent constraints and names them.
  The least-squares part uses a QR of ``A = [J_anchors; lambda H_samples]`` computed once per
  anchor layout (``A -> R_A``), then a QR of ``R_A Q_2`` per constraint layout. The result is
  ``z = B [h; R]``, ``C = J_anchors B``; :attr:`n_factorizations` counts the QR
  factorisations, and :meth:`update_targets` (same points, new targets) performs none.
* **Translation.** It lies in the null space of both the Jacobian and the Hessian rows, so
  at least one position constraint is required (:class:`ConstraintError` otherwise).
* **Cages of several shells.** Each outward shell is its own domain with its own
  coefficients (:func:`~vhm_viz.core.basis.domain_columns`). A shell without any
  constraint would leave its translation free (a singular solve): it stays put instead,
  its coefficients fixed to the identity's as extra constraint rows, listed in
  :attr:`Deformer.pinned_shells` and :attr:`Deformer.notes` and announced by a
  ``UserWarning``. A constrained shell needs a position constraint and an anchor.
* **Solver.** Local/global iteration on the anchors' local matrices, Anderson-accelerated
  (window 10) with an energy safeguard, so the energy never increases (see
  :mod:`vhm_viz.core.solver`). Stopping rule: the estimated distance to the fixed point,
  ``|T(u) - u| / (1 - rho)`` (RMS per anchor, ``rho`` the observed contraction rate), below
  ``tolerance``; the paper's "change of R_global" rule stops far too early at the slow
  contraction of alpha = 0.01 (the contraction rate approaches 1 as alpha shrinks).
* **The solution** is ``z = B [h; R_local]`` with ``R_local`` the final local matrices (the
  minimiser of the global step; energy-consistent), not the unprojected ``R_global`` of the
  paper's eq. (8); the difference vanishes at convergence.
* **A 180 degree twist from the identity** sits on a symmetric saddle; use ``init="previous"``
  while ramping the target over a few steps (see :func:`vhm_viz.examples.bar`).

Bindings (:meth:`Deformer.bind`, :mod:`vhm_viz.core.binding`) precompute ``F = D_points B``
so that deforming a shape is one matrix product (paper eq. 8).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from vhm_viz.core.basis import domain_columns, evaluate_inside
from vhm_viz.core.binding import Binding
from vhm_viz.core.constraints import (
    as_matrices,
    check_duplicate_points,
    check_jacobian_targets,
    describe_shell,
    domain_of,
    factor_constraints,
    factor_least_squares,
    shells_to_pin,
    stack_transposed,
    unstack_transposed,
)
from vhm_viz.core.errors import ConstraintError, OutsideCageError, describe_indices
from vhm_viz.core.geometry import face_normals_and_areas
from vhm_viz.core.harmonic_map import HarmonicMap
from vhm_viz.core.limits import check_setting
from vhm_viz.core.memory import smoothness_bytes, solver_bytes
from vhm_viz.core.points import as_points
from vhm_viz.core.smoothness import (
    default_smoothness_samples,
    smoothness_rows,
    smoothness_weight,
)
from vhm_viz.core.solve_report import SolveReport
from vhm_viz.core.solver import (
    DEFAULT_ANDERSON_WINDOW,
    initial_local_matrices,
    project_blocks,
    run_local_global,
)
from vhm_viz.resources import require_memory

# SolveReport and default_smoothness_samples are re-exported from their own modules
__all__ = ["Deformer", "SolveReport", "default_smoothness_samples"]

_MODES = ("rigid", "similar")


class Deformer:
    """Variational harmonic map deformer (paper Sections 2.2 and 3).

    Parameters
    ----------
    cage : Cage
        A validated cage (any object with ``vertices``, ``faces`` and ``face_normals``).
    anchors : (d, 3) array_like
        Anchor points inside the cage (samples of rigidity lines, see
        :func:`vhm_viz.anchors_from_polylines`).
    mode : {"rigid", "similar"}
        As-Rigid-As-Possible (local matrices are rotations) or As-Similar-As-Possible
        (rotations times a scalar: singular values replaced by their mean, paper Figure 12).
        Can be changed later through :attr:`mode` without refactorising.
    alpha : float
        Stiffness in [1e-4, 100] (:mod:`vhm_viz.core.limits`); ``lambda = alpha * d *
        ||J_anchors||_inf / ||H_samples||_inf``, with the norms taken in units of the cage's
        bounding-box diagonal (see the module documentation).
    smoothness_samples : (k, 3) array_like, optional
        Points where the Hessian is penalised. Default: :func:`default_smoothness_samples`.
    smoothness_host_faces : (k,) array_like of int, optional
        For samples exactly on cage faces, the face index (-1 for others): the basis then
        uses the interior limit there.
    anderson_window : int
        Anderson acceleration window in [0, 100] (0 for the plain local/global iteration of
        the paper); default :data:`~vhm_viz.core.solver.DEFAULT_ANDERSON_WINDOW` (10).

    Attributes
    ----------
    pinned_shells : tuple of int
        Cage shells (indices into :func:`~vhm_viz.core.basis.domain_columns`) that hold no
        constraint and therefore stay put; set by :meth:`set_constraints`.
    notes : list of str
        Messages for the user from the last :meth:`set_constraints` (pinned shells).

    Raises
    ------
    OutsideCageError
        Anchors (or smoothness samples) outside the cage, listed by index.
    SettingError
        ``alpha`` or ``anderson_window`` of the wrong type or out of range.
    ValueError
        Bad shapes, non-finite values, unknown mode.
    """

    def __init__(
        self,
        cage,
        anchors,
        *,
        mode: str = "rigid",
        alpha: float = 0.01,
        smoothness_samples=None,
        smoothness_host_faces=None,
        anderson_window: int = DEFAULT_ANDERSON_WINDOW,
    ):
        self.cage = cage
        self._V = np.ascontiguousarray(cage.vertices, dtype=np.float64)
        self._Fc = np.ascontiguousarray(cage.faces, dtype=np.int64)
        self._n, self._m = len(self._V), len(self._Fc)
        self._N = self._n + self._m
        normals = getattr(cage, "face_normals", None)
        if normals is None:
            normals, _ = face_normals_and_areas(self._V, self._Fc)
        self._normals = np.asarray(normals, dtype=np.float64)
        self.mode = mode
        self.alpha = check_setting("alpha", alpha)
        self.anderson_window = check_setting("anderson_window", anderson_window)
        self.n_factorizations = 0
        self._layout_version = 0

        a = as_points(anchors, "anchors", allow_empty=False)
        self._anchors = a
        d = len(a)
        require_memory(
            solver_bytes(d, self._N),
            f"the solver for {d} anchors",
            "use fewer anchors (its matrices grow with the square of their number)",
        )
        ev = self._evaluate_inside(a, 1, "anchors")
        if not np.isfinite(ev.gradients).all():
            bad = np.nonzero(~np.isfinite(ev.gradients).all(axis=(1, 2)))[0]
            raise ValueError(f"anchors {describe_indices(bad)} lie on a cage edge or vertex")
        self._Jhat = np.ascontiguousarray(ev.gradients.reshape(3 * d, self._N))
        self._domains = domain_columns(self._V, self._Fc)
        self._anchor_domain = domain_of(ev.values, self._domains, self._n)
        self.pinned_shells: tuple[int, ...] = ()
        self.notes: list[str] = []

        k = 3 * self._m if smoothness_samples is None else len(np.atleast_2d(smoothness_samples))
        require_memory(
            smoothness_bytes(k, self._N),
            f"the smoothness term of a cage of {self._m} faces",
            "use a cage of fewer faces (vhm-viz cage --max-faces N makes one)",
        )
        self._samples, self._Hhat = smoothness_rows(
            self._V, self._Fc, smoothness_samples, smoothness_host_faces
        )
        self.lambda_ = smoothness_weight(self.alpha, d, self._Jhat, self._Hhat, self._n, self._V)

        self._RA, self._W = factor_least_squares(self._Jhat, self._Hhat, self.lambda_)
        self.n_factorizations += 1
        self._z_identity = np.vstack([self._V, self._normals])
        #: Reference point of the solver's arithmetic (see :meth:`_local_h`).
        self._centre = 0.5 * (self._V.min(axis=0) + self._V.max(axis=0))

        self._u = stack_transposed(np.broadcast_to(np.eye(3), (d, 3, 3)).copy())
        self._G = None
        self._z = None
        self._has_constraints = False
        self._last_report = None

    # ------------------------------------------------------------------ properties
    @property
    def mode(self) -> str:
        """``"rigid"`` or ``"similar"`` (switching needs no refactorisation)."""
        return self._mode

    @mode.setter
    def mode(self, value: str) -> None:
        if value not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}; got {value!r}")
        self._mode = value

    @property
    def anchors(self) -> np.ndarray:
        """(d, 3) anchor points."""
        return self._anchors

    @property
    def n_anchors(self) -> int:
        """Number of anchors ``d``."""
        return len(self._anchors)

    @property
    def smoothness_samples(self) -> np.ndarray:
        """(k, 3) smoothness sample points."""
        return self._samples

    @property
    def n_constraints(self) -> int:
        """Number of scalar constraint rows ``c = r + 3 s`` (per map component).

        Rows that pin unconstrained shells (:attr:`pinned_shells`) are not counted.
        """
        return self._r + 3 * self._s if self._has_constraints else 0

    @property
    def B(self) -> np.ndarray:
        """(n+m, c+3d): ``z = B [h; R]``."""
        self._require_constraints()
        return self._B

    @property
    def C(self) -> np.ndarray:
        """(3d, c+3d): ``J_anchors B`` (transposed-Jacobian rows, as in the paper)."""
        self._require_constraints()
        return np.hstack([self._C_h, self._C_R])

    @property
    def coefficients(self) -> np.ndarray:
        """Current ``z`` (n+m, 3) for the current targets and local matrices."""
        self._require_constraints()
        if self._z is None:
            z = self._B @ np.vstack([self._local_h(self._h), self._u])
            z[: self._n] += self._centre  # back from the cage's centre (see _local_h)
            self._z = z
        return self._z

    @property
    def stacked_variables(self) -> np.ndarray:
        """Current ``w = [h; R_local]`` ((c + 3d), 3), the right factor of ``z = B w``."""
        self._require_constraints()
        return np.vstack([self._h, self._u])

    @property
    def harmonic_map(self):
        """The current map as a :class:`~vhm_viz.core.harmonic_map.HarmonicMap`."""
        return HarmonicMap(self.cage, self.coefficients)

    @property
    def jacobians_at_anchors(self) -> np.ndarray:
        """(d, 3, 3) Jacobians ``J[i, j] = d f_i / d x_j`` of the current map at the anchors."""
        self._require_constraints()
        G = self._g + self._C_R @ self._u
        return unstack_transposed(G)

    @property
    def rotations_at_anchors(self) -> np.ndarray:
        """(d, 3, 3) current local matrices (rotations, or similarities in "similar" mode)."""
        return unstack_transposed(self._u)

    @property
    def last_report(self) -> SolveReport | None:
        """The report of the last :meth:`solve`."""
        return self._last_report

    # ------------------------------------------------------------------ helpers
    def _evaluate_inside(self, points: np.ndarray, order: int, what: str):
        """The basis at points that must lie inside the cage (or on it: interior limit).

        ``what``: the points, plural (``"anchors"``), as the message names them.
        """
        ev, inside = evaluate_inside(points, self._V, self._Fc, order=order)
        if not inside.all():
            idx = np.nonzero(~inside)[0]
            noun = what if len(inside) > 1 else what.removesuffix("s")
            verb = "are" if idx.size > 1 else "is"
            raise OutsideCageError(
                f"{idx.size} of {len(inside)} {noun} {verb} outside the cage (indices "
                f"{describe_indices(idx)})",
                idx,
            )
        return ev

    def _require_constraints(self) -> None:
        if not self._has_constraints:
            raise ConstraintError(
                "no constraints set: call set_constraints(positions=..., targets=...) first "
                "(at least one position constraint fixes the translation)"
            )

    # ------------------------------------------------------------------ constraints
    def set_constraints(self, positions=None, targets=None, jacobian_points=None, jacobians=None):
        """Set the hard constraints (paper problem P1).

        Changing the constraint *points* rebuilds ``B`` and ``C`` (two QR factorisations of
        size ``n+m``); to move targets only, use :meth:`update_targets`.

        A cage shell holding none of the points stays put (identity map; see
        :attr:`pinned_shells`), with a ``UserWarning`` naming it.

        Parameters
        ----------
        positions : (r, 3) array_like
            Points ``q_i`` inside the cage whose images are prescribed (r >= 1: at least one
            position constraint is required to fix the translation).
        targets : (r, 3) array_like
            Their target positions ``f(q_i)``.
        jacobian_points : (s, 3) array_like, optional
            Points ``t_i`` inside the cage whose Jacobians are prescribed.
        jacobians : (s, 3, 3) array_like, optional
            Target Jacobians ``J[i, j] = d f_i / d x_j`` (``det > 0``).

        Raises
        ------
        OutsideCageError
            Constraint points outside the cage (indices listed).
        ConstraintError
            No position constraint; a shell with Jacobian constraints but no position
            constraint, or with constraints but no anchor (named); more constraint rows
            than degrees of freedom; duplicate constraint points; linearly dependent
            constraints (named); Jacobian targets with ``det <= 0``.
        ValueError
            Shapes, non-finite values.
        """
        if positions is None or targets is None:
            raise ConstraintError(
                "at least one position constraint is required (translation is otherwise free): "
                "pass positions and targets"
            )
        q = as_points(positions, "positions")
        f = as_points(targets, "targets")
        if len(q) == 0:
            raise ConstraintError(
                "at least one position constraint is required (translation is otherwise free)"
            )
        if f.shape != q.shape:
            raise ValueError(f"targets must have the shape of positions {q.shape}; got {f.shape}")
        if (jacobian_points is None) != (jacobians is None):
            raise ValueError("jacobian_points and jacobians must be given together")
        if jacobian_points is None:
            t = np.zeros((0, 3))
            g = np.zeros((0, 3, 3))
        else:
            t = as_points(jacobian_points, "jacobian_points")
            g = as_matrices(jacobians, "jacobians") if len(t) else np.zeros((0, 3, 3))
            if len(g) != len(t):
                raise ValueError(f"got {len(t)} jacobian_points but {len(g)} jacobians")
        check_jacobian_targets(g)
        r, s = len(q), len(t)
        c = r + 3 * s
        if c >= self._N:
            raise ConstraintError(
                f"more hard constraints than degrees of freedom: {r} position + 3 x {s} Jacobian "
                f"rows = {c} >= n + m = {self._N} coefficients per component"
            )
        diag = float(np.linalg.norm(self._V.max(0) - self._V.min(0)))
        check_duplicate_points(q, f, "position constraints", 1e-12 * diag, 1e-12 * diag)
        check_duplicate_points(t, g.reshape(-1, 9), "Jacobian constraints", 1e-12 * diag, 1e-12)

        evq = self._evaluate_inside(q, 0, "position constraints")
        rows = [evq.values]
        if s:
            evt = self._evaluate_inside(t, 1, "Jacobian constraint points")
            if not np.isfinite(evt.gradients).all():
                bad = np.nonzero(~np.isfinite(evt.gradients).all(axis=(1, 2)))[0]
                raise ValueError(
                    f"Jacobian constraint points {describe_indices(bad)} lie on a cage edge "
                    "or vertex"
                )
            rows.append(evt.gradients.reshape(3 * s, self._N))
        labels = [f"position constraint {i}" for i in range(r)] + [
            f"Jacobian constraint {i} (row {k})" for i in range(s) for k in range(3)
        ]
        # a shell nobody constrains would leave the solve singular (its translation is
        # free): it stays put instead, its coefficients fixed to the identity's
        pinned = shells_to_pin(
            self._domains,
            self._V,
            domain_of(evq.values, self._domains, self._n),
            domain_of(evt.values, self._domains, self._n) if s else np.zeros(0, dtype=np.int64),
            self._anchor_domain,
        )
        pin_cols = (
            np.concatenate([self._domains[k] for k in pinned])
            if pinned
            else np.zeros(0, dtype=np.int64)
        )
        pin_rows = np.zeros((len(pin_cols), self._N))
        pin_rows[np.arange(len(pin_cols)), pin_cols] = 1.0
        rows.append(pin_rows)
        labels += [f"pinned coefficient {j}" for j in pin_cols]
        K = np.vstack(rows)
        self._build(K, labels)
        self._q, self._t = q, t
        self._r, self._s, self._c = r, s, c + len(pin_cols)
        # pinned vertex coefficients are positions (a_v = x_v): centred like the targets
        self._pin_position_rows = c + np.flatnonzero(pin_cols < self._n)
        self._h_rest = K @ self._z_identity
        self._has_constraints = True
        self._layout_version += 1
        self.pinned_shells = tuple(pinned)
        self.notes = [
            f"{describe_shell(k, self._domains, self._V)} has no constraint: it stays put "
            "(identity map)"
            for k in pinned
        ]
        for note in self.notes:
            warnings.warn(note, UserWarning, stacklevel=2)
        h = np.vstack([f, stack_transposed(g)]) if s else f.copy()
        self._set_h(np.vstack([h, self._h_rest[c:]]))
        return self

    def _build(self, K: np.ndarray, labels: list[str]) -> None:
        """Factorise the constraint layout: B, C and the energy precomputations."""
        factors = factor_constraints(
            K, labels, self._RA, self._W, self._Jhat, self._Hhat, self.lambda_
        )
        self.n_factorizations += 2
        self._B = factors.B
        self._C_h = factors.C_h
        self._C_R = factors.C_R
        self._JP = factors.JP
        self._KH = factors.KH
        self._z = None

    def _local_h(self, h: np.ndarray) -> np.ndarray:
        """Targets relative to the cage's centre (position rows; Jacobian rows unchanged).

        The solver's energy is a quadratic form in the targets whose terms cancel to the
        energy: with targets 1e7 from the origin those terms were ~1e14 times larger than
        the energy and the rounding defeated the solver. The problem moved to the cage's
        centre is the same problem (basis rows only see differences), so everything the
        solver needs is computed from these.
        """
        local = np.array(h, dtype=np.float64)
        local[: self._r] -= self._centre
        local[getattr(self, "_pin_position_rows", np.zeros(0, dtype=np.int64))] -= self._centre
        return local

    def _set_h(self, h: np.ndarray) -> None:
        c = self._c
        self._h = np.ascontiguousarray(h, dtype=np.float64)
        local = self._local_h(self._h)
        self._g = np.ascontiguousarray(self._C_h @ local)
        self._jzp = np.ascontiguousarray(self._JP @ local)
        L = self._KH @ local
        self._l_r = np.ascontiguousarray(L[c:])
        self._const_h = float(np.sum(L[:c] * local))
        self._z = None

    def update_targets(self, targets=None, jacobians=None):
        """Change the targets of the current constraints without refactorising anything.

        Parameters
        ----------
        targets : (r, 3) array_like, optional
            New position targets (same count and order as in :meth:`set_constraints`).
        jacobians : (s, 3, 3) array_like, optional
            New Jacobian targets.
        """
        self._require_constraints()
        h = self._h.copy()
        if targets is not None:
            f = as_points(targets, "targets", allow_empty=False)
            if f.shape != (self._r, 3):
                raise ValueError(f"targets must have shape ({self._r}, 3); got {f.shape}")
            h[: self._r] = f
        if jacobians is not None:
            g = as_matrices(jacobians, "jacobians") if self._s else np.zeros((0, 3, 3))
            if len(g) != self._s:
                raise ValueError(f"expected {self._s} jacobians; got {len(g)}")
            check_jacobian_targets(g)
            h[self._r : self._r + 3 * self._s] = stack_transposed(g)
        self._set_h(h)
        return self

    @property
    def constraints(self) -> dict:
        """Current constraints: ``positions``, ``targets``, ``jacobian_points``, ``jacobians``."""
        self._require_constraints()
        return {
            "positions": self._q.copy(),
            "targets": self._h[: self._r].copy(),
            "jacobian_points": self._t.copy(),
            "jacobians": (
                unstack_transposed(self._h[self._r : self._r + 3 * self._s])
                if self._s
                else np.zeros((0, 3, 3))
            ),
        }

    # ------------------------------------------------------------------ solve
    def solve(
        self,
        max_iterations: int = 1000,
        tolerance: float = 1e-6,
        init="previous",
        seed=None,
        anderson_window: int | None = None,
        contraction: float | None = None,
    ) -> SolveReport:
        """Run the local/global iteration (Anderson-accelerated) to convergence.

        Parameters
        ----------
        max_iterations : int
            Iteration cap, in [1, 1e6]: :attr:`SolveReport.iterations` never exceeds it
            (the final plain step that makes the local matrices exact projections counts).
        tolerance : float
            In (0, 0.1]: the estimated distance of the anchors' local matrices to the fixed
            point (RMS per anchor, Frobenius norm; Jacobians are dimensionless, so this is a
            relative measure): ``|T(u) - u| / (1 - rho)``, with ``rho`` the observed
            contraction rate.
        init : {"previous", "identity", "random"} or (d, 3, 3) array_like
            Starting local matrices: the last solution (identity before the first solve),
            identities, random 3x3 matrices (paper Figure 7; entries uniform in [0, 1),
            seeded by ``seed``), or given. The problem is not convex: a random start can end
            in another local minimum (on the bar, a full turn of twist about its axis).
            On the bar's example scenes, uniform entries reach the identity-init solution
            far more often than Gaussian ones.
        seed : int or numpy Generator, optional
            For ``init="random"``.
        anderson_window : int, optional
            Overrides the deformer's window for this call (0: plain iteration), in [0, 100].
        contraction : float, optional
            With a given ``init`` that is a stored solution: the contraction rate measured
            when it was computed (:attr:`SolveReport.contraction`). The stopping rule is
            then checked on the first residual, and a solution that meets it is returned
            unchanged (0 iterations). In [0, 1).

        Returns
        -------
        SolveReport

        Raises
        ------
        SettingError
            A setting of the wrong type or outside its range (:mod:`vhm_viz.core.limits`).
        """
        self._require_constraints()
        u0, init_name = initial_local_matrices(init, self._u, seed)
        max_iterations = check_setting("max_iterations", max_iterations)
        tolerance = check_setting("tolerance", tolerance)
        window = self.anderson_window
        if anderson_window is not None:
            window = check_setting("anderson_window", anderson_window)
        rho0 = -1.0 if contraction is None else check_setting("contraction", contraction)
        hist = np.zeros((max_iterations + 2, 4))
        t0 = time.perf_counter()
        u, G, iters, converged, nrec, rejected, rho = run_local_global(
            self._C_R,
            self._g,
            self._jzp,
            self._l_r,
            self._const_h,
            np.ascontiguousarray(u0, dtype=np.float64),
            self._mode == "similar",
            max_iterations,
            tolerance,
            window,
            hist,
            rho0,
        )
        seconds = time.perf_counter() - t0
        self._u = u
        self._z = None
        hist = hist[:nrec]
        rep = SolveReport(
            iterations=int(iters),
            converged=bool(converged),
            energy=hist[:, 0].copy(),
            rigidity=hist[:, 1].copy(),
            smoothness=hist[:, 2].copy(),
            residuals=hist[:, 3].copy(),
            seconds=seconds,
            rejected_steps=int(rejected),
            init=init_name,
            contraction=float(rho) if rho >= 0 else float("nan"),
            max_iterations=int(max_iterations),
            tolerance=float(tolerance),
        )
        self._last_report = rep
        return rep

    def energy(self, z=None) -> tuple[float, float, float]:
        """Energy of a coefficient matrix evaluated directly from the basis rows (slow, exact).

        ``rigidity = sum_i |J(m_i) - proj(J(m_i))|^2``, ``smoothness = lambda^2 |H z|^2``.

        Parameters
        ----------
        z : (n+m, 3) array_like, optional
            Default: the current coefficients.

        Returns
        -------
        (total, rigidity, smoothness)
        """
        z = self.coefficients if z is None else np.asarray(z, dtype=np.float64)
        z = z.copy()
        z[: self._n] -= self._centre  # the rows sum to 0 on a translation: cancel it first
        G = self._Jhat @ z
        T = project_blocks(G, similar=self._mode == "similar")
        rig = float(np.sum((G - T) ** 2))
        sm = float(self.lambda_**2 * np.sum((self._Hhat @ z) ** 2))
        return rig + sm, rig, sm

    # ------------------------------------------------------------------ binding
    def bind(
        self,
        points,
        *,
        outside: str = "error",
        dtype=np.float64,
        memory_budget: int | None = None,
        progress=None,
        abort=None,
    ) -> Binding:
        """Precompute ``F = D_points B`` for fast repeated deformation of a point set.

        Parameters
        ----------
        points : (P, 3) array_like
            The shape's points (mesh vertices, voxel centres, ...).
        outside : {"error", "passthrough", "nan"}
            Points outside the cage: raise :class:`OutsideCageError` listing them (default),
            leave them unchanged, or make them NaN (see :mod:`vhm_viz.core.binding`).
        dtype : numpy dtype
            ``float64`` (default) or ``float32`` storage of ``F``.
        memory_budget : int, optional
            Bytes of basis arrays per chunk of the precomputation.
        progress : callable(fraction, message), optional
        abort : callable() -> bool, optional
            Checked between chunks.

        Returns
        -------
        Binding
        """
        self._require_constraints()
        return Binding(
            self,
            points,
            outside=outside,
            dtype=dtype,
            memory_budget=memory_budget,
            progress=progress,
            abort=abort,
        )

    def __repr__(self) -> str:
        return (
            f"Deformer(mode={self._mode!r}, anchors={self.n_anchors}, cage=({self._n} vertices, "
            f"{self._m} faces), samples={len(self._samples)}, lambda={self.lambda_:.4g}, "
            f"constraints={self.n_constraints})"
        )
