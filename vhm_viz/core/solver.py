"""Local/global iteration of the variational harmonic map, with Anderson acceleration.

This module holds the small dense kernels behind :class:`vhm_viz.Deformer` (paper Section 3,
eq. 7). Everything is independent of the cage size and of the shape: with ``d`` anchors the
state is a ``(3d, 3)`` stack ``u`` of 3x3 blocks, one per anchor, and one iteration costs one
``(3d x 3d) @ (3d x 3)`` product, ``d`` 3x3 polar decompositions and O(d) bookkeeping.

Notation (see ``deformer.py`` for how the matrices are built):

* ``u``: the "local" matrices ``R_local`` (one 3x3 block per anchor, stored as the
  *transposed* Jacobian, i.e. the rows of the paper's eq. (4) stack).
* ``G(u) = g + C_R u``: the Jacobians (transposed) at the anchors of the global-step
  minimiser ``z(u) = B [h; u]``; ``g = C_h h`` is fixed for given targets ``h``.
* ``T(u) = proj(G(u))``: the local step -- per block the closest rotation (``"rigid"``) or
  closest rotation times a scalar (``"similar"``, paper Figure 12).
* Energy of ``u``: ``E(u) = min_R E(z(u), R) = |G - T(u)|^2 + lambda^2 |H z(u)|^2``. The
  smoothness part is evaluated in O(d) from precomputed quantities (``deformer.py``), never
  from the ``O(n+m)`` coefficients.

The plain local/global step ``u <- T(u)`` never increases ``E``. Anderson acceleration
(window ``m``, Walker & Ni 2011; with the energy safeguard of Peng et al. 2018) extrapolates
``u`` from the last ``m`` steps; an extrapolated iterate that would raise the energy is
rejected in favour of the plain step and the history is cleared, so the recorded energy is
monotone whichever path is taken.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.core import types
from numba.np.linalg import F_INT_nbtype, F_INT_nptype

from vhm_viz.core.constraints import as_matrices, stack_transposed
from vhm_viz.core.lapack import register_cython_linalg
from vhm_viz.core.polar import project_blocks, project_stack

__all__ = [
    "DEFAULT_ANDERSON_WINDOW",
    "INITS",
    "initial_local_matrices",
    "project_blocks",  # re-exported from vhm_viz.core.polar
    "run_local_global",
]

#: Anderson window used unless the caller picks one (Deformer, scenes): the smallest that
#: converges reliably on the bar scenarios, where smaller windows miss the iteration cap
#: for some starts that differ only by rounding.
DEFAULT_ANDERSON_WINDOW = 10


# ----------------------------------------------------------------------------- energies
@numba.njit(cache=True)
def _energy(u, G, T, jzp, l_r, const_h):  # pragma: no cover - compiled
    """Return (total, rigidity, smoothness) energy of iterate ``u``.

    ``E(z(u), u) = <u - J z_p, u - G> + const_h + <L_R, u>`` (the optimum of a linear
    least-squares problem equals ``<t, r>``, rhs times residual), hence
    ``smooth = E(z(u), u) - |G - u|^2`` and ``rigid = |G - T|^2``.
    """
    e_at_u = const_h
    mag = abs(const_h)
    gu2 = 0.0
    rig = 0.0
    rows = u.shape[0]
    for i in range(rows):
        for j in range(3):
            uij = u[i, j]
            diff = uij - G[i, j]
            t1 = (uij - jzp[i, j]) * diff
            t2 = l_r[i, j] * uij
            e_at_u += t1 + t2
            mag += abs(t1) + abs(t2)
            gu2 += diff * diff
            dt = G[i, j] - T[i, j]
            rig += dt * dt
    smooth = e_at_u - gu2
    if smooth < 0.0:
        smooth = 0.0
    # rounding level of the total (the sum above cancels terms of size ``mag``)
    noise = 1e-14 * (mag + gu2 + rig)
    return rig + smooth, rig, smooth, noise


@numba.njit(cache=True, fastmath=True)
def _global_step(C_R, u, g, G):  # pragma: no cover - compiled
    """G = g + C_R u, single-threaded.

    A BLAS call costs more in threading and dispatch than it saves at these sizes;
    ``fastmath`` lets the row dot products vectorise.
    """
    rows = C_R.shape[0]
    ut = np.empty((3, rows))
    for k in range(rows):
        ut[0, k] = u[k, 0]
        ut[1, k] = u[k, 1]
        ut[2, k] = u[k, 2]
    for i in range(rows):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for k in range(rows):
            c = C_R[i, k]
            s0 += c * ut[0, k]
            s1 += c * ut[1, k]
            s2 += c * ut[2, k]
        G[i, 0] = g[i, 0] + s0
        G[i, 1] = g[i, 1] + s1
        G[i, 2] = g[i, 2] + s2


@numba.njit(cache=True)
def _evaluate(u, C_R, g, jzp, l_r, const_h, similar, G, T):  # pragma: no cover - compiled
    """G = g + C_R u; T = proj(G); return the energies of ``u`` and their rounding level."""
    _global_step(C_R, u, g, G)
    project_stack(G, T, similar)
    return _energy(u, G, T, jzp, l_r, const_h)


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _dot(a, b):  # pragma: no cover - compiled
    """``a . b``; reassociation lets the reduction vectorise (Anderson's Gram rows)."""
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


#: LAPACK's ``gesv`` as numba's own ``np.linalg.solve`` calls it (its C helper).
_gesv = types.ExternalFunction(
    "numba_xgesv",
    types.intc(
        types.char,
        types.intp,
        types.intp,
        types.CPointer(types.float64),
        types.intp,
        types.CPointer(F_INT_nbtype),
        types.CPointer(types.float64),
        types.intp,
    ),
)
_GESV_DOUBLE = ord("d")
register_cython_linalg()  # the BLAS and LAPACK numba calls, found by name


@numba.njit(cache=True)
def _solve_symmetric(A, b, pivots):  # pragma: no cover - compiled
    """``b <- A^-1 b`` for a symmetric ``(k, k)`` ``A`` (overwritten), ``pivots`` (k,) scratch.

    The LAPACK call of ``np.linalg.solve`` (same inputs, same result, bit for bit: a
    symmetric matrix is its own Fortran-order copy) without the wrapper's generic
    copies and checks (their compile is much of this module's first-run cost).
    """
    k = b.shape[0]
    for i in range(k):
        if not math.isfinite(b[i]):
            raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
        for j in range(k):
            if not math.isfinite(A[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    info = _gesv(_GESV_DOUBLE, k, 1, A.ctypes, k, pivots.ctypes, b.ctypes, k)
    if info != 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")


@numba.njit(cache=True)
def _assign(dst, src):  # pragma: no cover - compiled
    """``dst[:, :] = src`` for two arrays of one shape, as a plain loop.

    numba's array slice assignment compiles a run-time formatted shape-mismatch message
    (string formatting machinery) into the kernel, a large part of its first compile.
    """
    for i in range(dst.shape[0]):
        for j in range(dst.shape[1]):
            dst[i, j] = src[i, j]


@numba.njit(cache=True)
def run_local_global(
    C_R,
    g,
    jzp,
    l_r,
    const_h,
    u0,
    similar,
    max_iterations,
    tolerance,
    window,
    hist,
    rho0=-1.0,
):  # pragma: no cover - compiled
    """Iterate the local/global map from ``u0`` (Anderson-accelerated when ``window > 0``).

    Parameters
    ----------
    C_R : (3d, 3d) ; g, jzp, l_r : (3d, 3) ; const_h : float
        Precomputed solver quantities (see ``deformer.py``), C-contiguous float64.
    u0 : (3d, 3)
        Initial local matrices.
    similar : bool
    max_iterations : int
        At least 1; the returned count (final plain step included) never exceeds it.
    tolerance : float
        Stop when the estimated distance to the fixed point (RMS per anchor, Frobenius),
        ``|T(u) - u| / (1 - rho)`` with ``rho`` the observed contraction rate, is below it.
    window : int
        Anderson window (0: plain local/global).
    hist : (max_iterations + 2, 4) float64
        Receives ``(total, rigid, smooth, residual)`` per recorded iterate.
    rho0 : float
        Contraction rate measured when ``u0`` was computed (a stored solution), or negative
        when unknown. The stopping rule needs a rate, which the residual history gives only
        from the third iterate on; with ``rho0`` a stored solution that meets the rule is
        accepted as it is (no iteration, ``u0`` returned unchanged), so re-solving a saved
        scene reproduces its result to rounding.

    Returns
    -------
    u : (3d, 3)  final local matrices (exact rotations / similarities)
    G : (3d, 3)  transposed Jacobians at the anchors of ``z(u)``
    n_iter : int  iterations performed (including the final plain step)
    converged : bool
    n_records : int  rows of ``hist`` filled
    n_rejected : int  rejected accelerated steps
    rho : float  the last contraction-rate estimate (``rho0`` if none was measured)
    """
    rows = u0.shape[0]
    n9 = rows * 3
    d = rows // 3
    u = u0.copy()
    G = np.empty_like(u)
    T = np.empty_like(u)
    Gc = np.empty_like(u)
    Tc = np.empty_like(u)
    ua = np.empty_like(u)
    uf = u.reshape(n9)
    Tf = T.reshape(n9)
    uaf = ua.reshape(n9)
    f = np.empty(n9)
    f_prev = np.empty(n9)
    t_prev = np.empty(n9)
    e_tot, e_rig, e_sm, noise = _evaluate(u, C_R, g, jzp, l_r, const_h, similar, G, T)
    m = max(window, 1)
    dF = np.zeros((m, n9))
    dG = np.zeros((m, n9))
    gram = np.zeros((m, m))
    pivots = np.empty(m, dtype=F_INT_nptype)
    n_hist = 0
    head = 0
    have_prev = False
    res_hist = np.zeros(max_iterations + 2)
    converged = False
    n_rejected = 0
    beta = 2.0
    it = 0
    nrec = 0
    scale = math.sqrt(max(d, 1))
    rho_last = rho0
    while True:
        ss = 0.0
        for i in range(n9):
            fi = Tf[i] - uf[i]
            f[i] = fi
            ss += fi * fi
        res = math.sqrt(ss) / scale
        hist[nrec, 0] = e_tot
        hist[nrec, 1] = e_rig
        hist[nrec, 2] = e_sm
        hist[nrec, 3] = res
        nrec += 1
        res_hist[it] = res
        # contraction estimate from the residual history (geometric mean over <= 8 steps)
        if it >= 2:
            back = min(it, 8)
            r0 = res_hist[it - back]
            if r0 > 0.0 and res > 0.0:
                rho = (res / r0) ** (1.0 / back)
            else:
                rho = 0.0
            rho = min(max(rho, 0.0), 0.9999)
            rho_last = rho
            if res / (1.0 - rho) <= tolerance:
                converged = True
        elif rho0 >= 0.0:
            if res / (1.0 - min(rho0, 0.9999)) <= tolerance:
                converged = True
        elif res <= 1e-3 * tolerance:
            converged = True
        # the final plain step below is an iteration too: stop one early so that the
        # count never exceeds the cap
        if converged or it + 1 >= max_iterations:
            break
        # --- Anderson history update (ring buffer of differences, Gram matrix kept current)
        if window > 0:
            if have_prev:
                for i in range(n9):
                    dF[head, i] = f[i] - f_prev[i]
                    dG[head, i] = Tf[i] - t_prev[i]
                if n_hist < m:
                    n_hist += 1
                for j in range(n_hist):
                    v = _dot(dF[head], dF[j])
                    gram[head, j] = v
                    gram[j, head] = v
                head = (head + 1) % m
            for i in range(n9):
                f_prev[i] = f[i]
                t_prev[i] = Tf[i]
            have_prev = True
        accepted = False
        if window > 0 and n_hist > 0:
            k = n_hist
            A = np.empty((k, k))
            b = np.empty(k)
            tr = 0.0
            for i in range(k):
                tr += gram[i, i]
            for i in range(k):
                for j in range(k):
                    A[i, j] = gram[i, j]
                A[i, i] += 1e-10 * tr + 1e-300
                b[i] = _dot(dF[i], f)
            _solve_symmetric(A, b, pivots[:k])
            theta = b
            for i in range(n9):
                uaf[i] = Tf[i]
            for j in range(k):
                tj = theta[j]
                for i in range(n9):
                    uaf[i] -= tj * dG[j, i]
            ea, ra, sa, na = _evaluate(ua, C_R, g, jzp, l_r, const_h, similar, Gc, Tc)
            # energy safeguard (an increase below the rounding level of E is not one)
            if ea <= e_tot + max(noise, na) and math.isfinite(ea):
                accepted = True
                _assign(u, ua)
                _assign(G, Gc)
                _assign(T, Tc)
                e_tot, e_rig, e_sm, noise = ea, ra, sa, na
            else:
                n_rejected += 1
                n_hist = 0
                head = 0
        if not accepted:
            if window > 0 and n_rejected > 0:
                # After a rejection the iterate is often drifting slowly away from a saddle
                # (the secant model then points back to it). Try an over-relaxed plain step
                # u + beta (T - u); keep it only if it beats the plain step.
                for i in range(n9):
                    uaf[i] = uf[i] + beta * f[i]
                ea, ra, sa, na = _evaluate(ua, C_R, g, jzp, l_r, const_h, similar, Gc, Tc)
                _assign(u, T)
                e_tot, e_rig, e_sm, noise = _evaluate(u, C_R, g, jzp, l_r, const_h, similar, G, T)
                if ea < e_tot and math.isfinite(ea):
                    _assign(u, ua)
                    _assign(G, Gc)
                    _assign(T, Tc)
                    e_tot, e_rig, e_sm, noise = ea, ra, sa, na
                    beta = min(2.0 * beta, 64.0)
                else:
                    beta = 2.0
            else:
                _assign(u, T)
                e_tot, e_rig, e_sm, noise = _evaluate(u, C_R, g, jzp, l_r, const_h, similar, G, T)
        it += 1
    if converged and it == 0 and rho0 >= 0.0:
        # a stored solution accepted as it is: it already is a projection (the final plain
        # step of the solve that produced it), and z = B [h; u0] is its result
        return u.copy(), G.copy(), 0, converged, nrec, n_rejected, rho_last
    # final plain step, so that the returned local matrices are exact projections and the
    # last recorded energy is that of the returned solution z = B [h; u]
    _assign(u, T)
    e_tot, e_rig, e_sm, noise = _evaluate(u, C_R, g, jzp, l_r, const_h, similar, G, T)
    ss = 0.0
    for i in range(n9):
        fi = Tf[i] - uf[i]
        ss += fi * fi
    hist[nrec, 0] = e_tot
    hist[nrec, 1] = e_rig
    hist[nrec, 2] = e_sm
    hist[nrec, 3] = math.sqrt(ss) / scale
    nrec += 1
    return u.copy(), G.copy(), it + 1, converged, nrec, n_rejected, rho_last


#: Named starting points of the local/global iteration (see :func:`initial_local_matrices`).
INITS = ("previous", "identity", "random")


def initial_local_matrices(init, previous: np.ndarray, seed=None) -> tuple[np.ndarray, str]:
    """The anchors' starting local matrices, as a stack of transposed blocks.

    Parameters
    ----------
    init : {"previous", "identity", "random"} or (d, 3, 3) array_like
        The last solution, identities, random matrices (entries uniform in [0, 1), seeded
        by ``seed``), or given matrices ``J[i, j]``.
    previous : (3d, 3) float64
        The last solution's stack.
    seed : int or numpy Generator, optional

    Returns
    -------
    u0 : (3d, 3) float64
    name : str
        ``init``, or ``"given"`` for matrices.
    """
    d = len(previous) // 3
    if isinstance(init, str):
        if init not in INITS:
            raise ValueError(f"init must be one of {INITS} or an array; got {init!r}")
        if init == "previous":
            return previous.copy(), init
        if init == "identity":
            return stack_transposed(np.broadcast_to(np.eye(3), (d, 3, 3)).copy()), init
        return np.random.default_rng(seed).random((3 * d, 3)), init
    u0 = stack_transposed(as_matrices(init, "init"))
    if u0.shape != (3 * d, 3):
        raise ValueError(f"init must have shape ({d}, 3, 3)")
    return u0, "given"
