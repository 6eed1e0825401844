"""Hard constraints of the deformer: checks, shells, and their elimination (paper P1).

The deformer's hard constraints ``f(q_i) = f_i`` and ``J_f(t_i) = g_i`` are rows ``K`` of
basis values and gradients. They are eliminated exactly: with a pivoted QR
``K^T P = Q R``, every solution is ``z = P_h h + Q_2 y``, and the least-squares part
(rigidity at the anchors, smoothness at the samples) is solved on ``Q_2`` only
(:func:`factor_constraints`). This module also holds the checks of the constraint data and
the rules for cages of several shells (each outward shell is its own domain, see
:func:`~vhm_viz.core.basis.domain_columns`).

Every 3x3 block is stored transposed inside the solver (the rows of the paper's eq. (4)
stack hold ``J^T``); :func:`stack_transposed` and :func:`unstack_transposed` convert at
the boundary.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vhm_viz.core import lapack
from vhm_viz.core.errors import ConstraintError, describe_indices

__all__ = [
    "ConstraintFactors",
    "as_matrices",
    "check_duplicate_points",
    "check_jacobian_targets",
    "describe_shell",
    "domain_of",
    "factor_constraints",
    "factor_least_squares",
    "shells_to_pin",
    "stack_transposed",
    "unstack_transposed",
]

# Relative rank tolerance of the constraint and least-squares factorisations.
_RANK_TOL = 1e-10


def unstack_transposed(a: np.ndarray) -> np.ndarray:
    """(3d, 3) stack of transposed blocks -> (d, 3, 3) user-facing matrices."""
    return np.ascontiguousarray(np.swapaxes(a.reshape(-1, 3, 3), 1, 2))


def stack_transposed(j: np.ndarray) -> np.ndarray:
    """(d, 3, 3) user-facing matrices -> (3d, 3) stack of their transposes."""
    return np.ascontiguousarray(np.swapaxes(j, 1, 2).reshape(-1, 3))


def as_matrices(a, name: str) -> np.ndarray:
    """Validate a stack of 3x3 matrices.

    Parameters
    ----------
    a : (s, 3, 3) or (3, 3) array_like
    name : str
        What the matrices are, for the error messages.

    Returns
    -------
    (s, 3, 3) float64

    Raises
    ------
    ValueError
        Wrong shape, or non-finite entries (the offending matrices are listed).
    """
    j = np.asarray(a, dtype=np.float64)
    if j.shape == (3, 3):
        j = j[None]
    if j.ndim != 3 or j.shape[1:] != (3, 3):
        raise ValueError(f"{name} must have shape (s, 3, 3); got {np.shape(a)}")
    bad = ~np.isfinite(j).all(axis=(1, 2))
    if bad.any():
        raise ValueError(
            f"{name} has non-finite values at indices {describe_indices(np.nonzero(bad)[0])}"
        )
    return j


def check_jacobian_targets(g: np.ndarray) -> None:
    """Refuse Jacobian targets that fold or flatten space (``det <= 0``).

    Parameters
    ----------
    g : (s, 3, 3) float64

    Raises
    ------
    ConstraintError
        Naming the targets and their determinants.
    """
    if len(g):
        det = np.linalg.det(g)
        bad = np.nonzero(~(det > 0))[0]
        if bad.size:
            raise ConstraintError(
                f"Jacobian targets {describe_indices(bad)} have non-positive determinant "
                f"({', '.join(f'{det[i]:.3g}' for i in bad[:5])}): a harmonic deformation "
                "cannot fold or flatten space there"
            )


def check_duplicate_points(
    points: np.ndarray, targets: np.ndarray, what: str, tol: float, target_tol: float
) -> None:
    """Refuse constraint points closer than ``tol`` to each other.

    Parameters
    ----------
    points : (r, 3) float64
    targets : (r, k) float64
        Their targets (positions, or flattened Jacobians).
    what : str
        The kind of constraint, for the message.
    tol, target_tol : float
        Distance under which two points coincide (length units), and two targets.

    Raises
    ------
    ConstraintError
        A duplicate (same targets) or a contradiction (different targets).
    """
    if len(points) < 2 or not _may_have_close_pair(points, tol):
        return
    from vhm_viz.core.scipy_extensions import kd_tree

    pairs = kd_tree(points).query_pairs(tol, output_type="ndarray")
    if len(pairs):
        i, j = (int(v) for v in pairs[0])
        differ = not np.allclose(targets[i], targets[j], rtol=0, atol=target_tol)
        raise ConstraintError(
            f"{what} {i} and {j} are at the same point "
            + ("with different targets (contradictory)" if differ else "(duplicate: remove one)")
        )


#: Up to this many points, :func:`check_duplicate_points` first compares all pairs directly.
_DIRECT_PAIRS_MAX = 1024


def _may_have_close_pair(points: np.ndarray, tol: float) -> bool:
    """Whether two of ``points`` may lie within ``tol``: False only when surely none do.

    A direct comparison of every pair, in blocks of rows, with twice the distance (the
    KD-tree that names the pair decides near the threshold); True for many points.
    """
    n = len(points)
    if n > _DIRECT_PAIRS_MAX:
        return True
    p = np.asarray(points, dtype=np.float64)
    limit = (2.0 * tol) ** 2
    later = np.arange(n)
    for start in range(0, n, 128):
        block = p[start : start + 128]
        d2 = ((block[:, None, :] - p[None, :, :]) ** 2).sum(axis=-1)  # (b, n)
        rows = np.arange(start, start + len(block))[:, None]
        if np.any((d2 <= limit) & (later[None, :] > rows)):
            return True
    return False


def domain_of(values: np.ndarray, domains: tuple, n: int) -> np.ndarray:
    """Index of the domain (outward shell) holding each point, from its basis values.

    Parameters
    ----------
    values : (N, n + m) float64
        Basis values at the points.
    domains : tuple of int arrays
        :func:`~vhm_viz.core.basis.domain_columns` of the cage.
    n : int
        Number of cage vertices.

    Returns
    -------
    (N,) int64
    """
    if len(domains) == 1:
        return np.zeros(len(values), dtype=np.int64)
    # the basis zeroes the other shells' columns, so only the own shell sums to ~1
    own = np.stack([values[:, cols[cols < n]].sum(axis=1) for cols in domains], axis=1)
    return np.argmax(own, axis=1)


def describe_shell(k: int, domains: tuple, vertices: np.ndarray) -> str:
    """Shell ``k`` in words: its face count and the centre of its box."""
    n = len(vertices)
    cols = domains[k]
    verts = vertices[cols[cols < n]]
    centre = ", ".join(f"{x:.4g}" for x in 0.5 * (verts.min(0) + verts.max(0)))
    return f"cage shell {k} ({int((cols >= n).sum())} faces, centred at ({centre}))"


def shells_to_pin(
    domains: tuple,
    vertices: np.ndarray,
    position_domain: np.ndarray,
    jacobian_domain: np.ndarray,
    anchor_domain: np.ndarray,
) -> list[int]:
    """Shells without constraints, to be pinned to the identity.

    Parameters
    ----------
    domains : tuple of int arrays
        :func:`~vhm_viz.core.basis.domain_columns` of the cage.
    vertices : (n, 3) float64
    position_domain, jacobian_domain, anchor_domain : int arrays
        The shell of each position constraint, Jacobian constraint and anchor.

    Returns
    -------
    list of int

    Raises
    ------
    ConstraintError
        A shell whose solve would be singular: Jacobian constraints without a position
        constraint, or constraints without an anchor.
    """
    pinned = []
    for k in range(len(domains)):
        has_pos = bool((position_domain == k).any())
        has_jac = bool((jacobian_domain == k).any())
        if not has_pos and not has_jac:
            pinned.append(k)
        elif not has_pos:
            raise ConstraintError(
                f"{describe_shell(k, domains, vertices)} has Jacobian constraints but no "
                "position constraint: its translation is free; add a position constraint "
                "inside it"
            )
        elif not (anchor_domain == k).any():
            raise ConstraintError(
                f"{describe_shell(k, domains, vertices)} has constraints but no anchor: "
                "nothing determines its rotation; add anchors inside it (auto_anchors gives "
                "every shell at least one)"
            )
    return pinned


def factor_least_squares(Jhat: np.ndarray, Hhat: np.ndarray, lambda_: float) -> tuple:
    """QR of the least-squares rows ``A = [J_anchors; lambda H_samples]``.

    Done once per anchor layout, in place: in Fortran order LAPACK's ``geqrf`` and
    ``orgqr`` overwrite ``A`` with ``Q``, where scipy would copy a C-ordered ``A`` and
    return ``Q`` apart (three arrays of ``A``'s size instead of one; the same factors).

    Parameters
    ----------
    Jhat : (3d, n + m) float64
        Basis gradient rows at the anchors.
    Hhat : (5k, n + m) float64
        Basis Hessian rows at the smoothness samples.
    lambda_ : float
        The smoothness weight.

    Returns
    -------
    RA : (n + m, n + m) float64
        The R factor.
    W : (n + m, 3d) float64
        ``Q_A^T [I; 0]``: the anchors' rows of ``Q``, transposed.
    """
    d3 = len(Jhat)
    A = np.empty((d3 + len(Hhat), Jhat.shape[1]), order="F")
    A[:d3] = Jhat
    np.multiply(Hhat, lambda_, out=A[d3:])
    q, r = lapack.qr(A, economic=True, overwrite_a=True)
    del A
    return r, np.ascontiguousarray(q[:d3].T)


class ConstraintFactors(NamedTuple):
    """The factors of one constraint layout (see :func:`factor_constraints`).

    Attributes
    ----------
    B : (n + m, c + 3d) float64
        ``z = B [h; R]``.
    C_h, C_R : (3d, c), (3d, 3d) float64
        ``J_anchors B``, split into its target and local-matrix columns.
    JP : (3d, c) float64
        ``J_anchors P_h``, the anchors' Jacobian rows of the particular solution.
    KH : (c + 3d, c) float64
        ``lambda^2 (H B)^T (H P_h)``, the smoothness energy's coupling to the targets.
    """

    B: np.ndarray
    C_h: np.ndarray
    C_R: np.ndarray
    JP: np.ndarray
    KH: np.ndarray


def factor_constraints(
    K: np.ndarray,
    labels: list[str],
    RA: np.ndarray,
    W: np.ndarray,
    Jhat: np.ndarray,
    Hhat: np.ndarray,
    lambda_: float,
) -> ConstraintFactors:
    """Eliminate the hard constraints ``K z = h`` from the least-squares problem.

    Two QR factorisations: a pivoted one of the (row-normalised) ``K^T``, whose rank names
    dependent constraints, and one of ``R_A Q_2``, the least-squares factor restricted to
    the constraints' null space.

    Parameters
    ----------
    K : (c, n + m) float64
        Constraint rows.
    labels : list of str
        A name for each row, for the error message.
    RA, W : (n + m, n + m), (n + m, 3d) float64
        The factors of :func:`factor_least_squares` for ``Jhat``, ``Hhat``, ``lambda_``.
    Jhat, Hhat, lambda_
        The least-squares rows and weight, as for :func:`factor_least_squares`.

    Returns
    -------
    ConstraintFactors

    Raises
    ------
    ConstraintError
        Linearly dependent constraints (named), or a map the data do not determine.
    """
    c = K.shape[0]
    scale = 1.0 / np.linalg.norm(K, axis=1)
    Ks = K * scale[:, None]
    Q, R, piv = lapack.qr(Ks.T, pivoting=True)
    diag = np.abs(np.diag(R))
    rank = int(np.count_nonzero(diag > _RANK_TOL * diag[0]))
    if rank < c:
        dep = sorted(piv[rank:])
        raise ConstraintError(
            "rank-deficient constraints: "
            + ", ".join(labels[i] for i in dep[:8])
            + (f" (and {len(dep) - 8} more)" if len(dep) > 8 else "")
            + " linearly depend on the others (duplicate or redundant constraints)"
        )
    Q1, Q2 = Q[:, :c], Q[:, c:]
    E = np.zeros((c, c))
    E[np.arange(c), piv] = scale[piv]
    P = Q1 @ lapack.solve_triangular(R[:c, :c], E, transpose=True)  # (N, c)
    M2 = RA @ Q2
    U2, T2 = lapack.qr(M2, economic=True)
    d2 = np.abs(np.diag(T2))
    if d2.min() <= 1e-12 * d2.max():
        raise ConstraintError(
            "the constraints, anchors and smoothness samples do not determine the map "
            "(a free direction remains, e.g. the translation): add position constraints"
        )
    X = lapack.solve_triangular(T2, U2.T @ np.hstack([W, RA @ P]))
    d3 = W.shape[1]
    B_R = Q2 @ X[:, :d3]
    B_h = P - Q2 @ X[:, d3:]
    B = np.ascontiguousarray(np.hstack([B_h, B_R]))
    HP = Hhat @ P
    HB = Hhat @ B
    return ConstraintFactors(
        B=B,
        C_h=np.ascontiguousarray(Jhat @ B_h),
        C_R=np.ascontiguousarray(Jhat @ B_R),
        JP=Jhat @ P,
        KH=(lambda_**2) * (HB.T @ HP),
    )
