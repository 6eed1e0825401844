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

__all__ = ["DEFAULT_ANDERSON_WINDOW", "project_blocks", "run_local_global"]

#: Anderson window used unless the caller picks one (Deformer, scenes). 10 is the smallest
#: that converged reliably on the bar scenarios: with 6, bend-u missed 1000 iterations for
#: 4 of 12 starts that differed by 1e-13.
DEFAULT_ANDERSON_WINDOW = 10


# ----------------------------------------------------------------------------- 3x3 polar
@numba.njit(cache=True, fastmath=False, inline="always")
def _jacobi_eigen3(s00, s01, s02, s11, s12, s22, V):  # pragma: no cover - compiled
    """Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations.

    Writes the eigenvectors into the columns of ``V`` (orthonormal, right-handed) sorted by
    descending eigenvalue and returns the eigenvalues.
    """
    a = np.empty((3, 3))
    a[0, 0] = s00
    a[0, 1] = s01
    a[0, 2] = s02
    a[1, 0] = s01
    a[1, 1] = s11
    a[1, 2] = s12
    a[2, 0] = s02
    a[2, 1] = s12
    a[2, 2] = s22
    for i in range(3):
        for j in range(3):
            V[i, j] = 1.0 if i == j else 0.0
    scale = abs(s00) + abs(s11) + abs(s22) + 1e-300
    for _sweep in range(12):
        off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
        if off <= 1e-18 * scale:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = a[p, q]
            if abs(apq) <= 1e-300:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
            if theta < 0.0:
                t = -t
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # A <- A J (columns p, q)
                akp = a[k, p]
                akq = a[k, q]
                a[k, p] = c * akp - s * akq
                a[k, q] = s * akp + c * akq
            for k in range(3):  # A <- J^T A (rows p, q)
                apk = a[p, k]
                aqk = a[q, k]
                a[p, k] = c * apk - s * aqk
                a[q, k] = s * apk + c * aqk
            for k in range(3):
                vkp = V[k, p]
                vkq = V[k, q]
                V[k, p] = c * vkp - s * vkq
                V[k, q] = s * vkp + c * vkq
    ev0 = a[0, 0]
    ev1 = a[1, 1]
    ev2 = a[2, 2]
    # sort descending (three compare-swaps on eigenvalues and columns)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        ei = ev0 if i == 0 else ev1
        ej = ev1 if j == 1 else ev2
        if ej > ei:
            for k in range(3):
                tmp = V[k, i]
                V[k, i] = V[k, j]
                V[k, j] = tmp
            if i == 0 and j == 1:
                ev0, ev1 = ev1, ev0
            elif i == 0:
                ev0, ev2 = ev2, ev0
            else:
                ev1, ev2 = ev2, ev1
    return ev0, ev1, ev2


@numba.njit(cache=True, fastmath=False)
def _polar_block(M, out, similar):  # pragma: no cover - compiled
    """Closest proper rotation (times the optimal scale if ``similar``) to a 3x3 matrix.

    ``R = U diag(1, 1, det(U V^T)) V^T`` from ``M = U S V^T``; built as
    ``[u1, u2, u1 x u2] V^T`` with ``V`` right-handed, which needs no small singular vector
    of ``M`` (robust for rank-deficient ``M``). With ``similar`` the result is ``s R`` with
    ``s = tr(R^T M) / 3 >= 0`` (mean of the signed singular values), the closest
    similarity to ``M`` in the Frobenius norm.
    """
    # S = M^T M
    s00 = M[0, 0] * M[0, 0] + M[1, 0] * M[1, 0] + M[2, 0] * M[2, 0]
    s01 = M[0, 0] * M[0, 1] + M[1, 0] * M[1, 1] + M[2, 0] * M[2, 1]
    s02 = M[0, 0] * M[0, 2] + M[1, 0] * M[1, 2] + M[2, 0] * M[2, 2]
    s11 = M[0, 1] * M[0, 1] + M[1, 1] * M[1, 1] + M[2, 1] * M[2, 1]
    s12 = M[0, 1] * M[0, 2] + M[1, 1] * M[1, 2] + M[2, 1] * M[2, 2]
    s22 = M[0, 2] * M[0, 2] + M[1, 2] * M[1, 2] + M[2, 2] * M[2, 2]
    V = np.empty((3, 3))
    _jacobi_eigen3(s00, s01, s02, s11, s12, s22, V)
    # make V right-handed
    det_v = (
        V[0, 0] * (V[1, 1] * V[2, 2] - V[2, 1] * V[1, 2])
        - V[0, 1] * (V[1, 0] * V[2, 2] - V[2, 0] * V[1, 2])
        + V[0, 2] * (V[1, 0] * V[2, 1] - V[2, 0] * V[1, 1])
    )
    if det_v < 0.0:
        for k in range(3):
            V[k, 2] = -V[k, 2]
    # u1 = M v1 / |M v1|
    x0 = M[0, 0] * V[0, 0] + M[0, 1] * V[1, 0] + M[0, 2] * V[2, 0]
    x1 = M[1, 0] * V[0, 0] + M[1, 1] * V[1, 0] + M[1, 2] * V[2, 0]
    x2 = M[2, 0] * V[0, 0] + M[2, 1] * V[1, 0] + M[2, 2] * V[2, 0]
    nx = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    if nx > 1e-300:
        x0 /= nx
        x1 /= nx
        x2 /= nx
    else:  # M == 0: any rotation is closest; take V V^T = I
        x0, x1, x2 = V[0, 0], V[1, 0], V[2, 0]
    # u2 = M v2 orthogonalised against u1
    y0 = M[0, 0] * V[0, 1] + M[0, 1] * V[1, 1] + M[0, 2] * V[2, 1]
    y1 = M[1, 0] * V[0, 1] + M[1, 1] * V[1, 1] + M[1, 2] * V[2, 1]
    y2 = M[2, 0] * V[0, 1] + M[2, 1] * V[1, 1] + M[2, 2] * V[2, 1]
    dot = x0 * y0 + x1 * y1 + x2 * y2
    y0 -= dot * x0
    y1 -= dot * x1
    y2 -= dot * x2
    ny = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    if ny <= 1e-12 * max(nx, 1e-300):
        # rank <= 1: any unit vector orthogonal to u1; prefer v2 (gives I for M = 0)
        y0, y1, y2 = V[0, 1], V[1, 1], V[2, 1]
        dot = x0 * y0 + x1 * y1 + x2 * y2
        y0 -= dot * x0
        y1 -= dot * x1
        y2 -= dot * x2
        ny = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    if ny <= 1e-6:
        if abs(x0) < 0.9:
            y0, y1, y2 = 0.0, -x2, x1
        else:
            y0, y1, y2 = x2, 0.0, -x0
        ny = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    y0 /= ny
    y1 /= ny
    y2 /= ny
    # one re-orthogonalisation pass for accuracy
    dot = x0 * y0 + x1 * y1 + x2 * y2
    y0 -= dot * x0
    y1 -= dot * x1
    y2 -= dot * x2
    ny = math.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    y0 /= ny
    y1 /= ny
    y2 /= ny
    w0 = x1 * y2 - x2 * y1
    w1 = x2 * y0 - x0 * y2
    w2 = x0 * y1 - x1 * y0
    # R = [x y w] V^T
    for i in range(3):
        ui0 = x0 if i == 0 else (x1 if i == 1 else x2)
        ui1 = y0 if i == 0 else (y1 if i == 1 else y2)
        ui2 = w0 if i == 0 else (w1 if i == 1 else w2)
        for j in range(3):
            out[i, j] = ui0 * V[j, 0] + ui1 * V[j, 1] + ui2 * V[j, 2]
    if similar:
        _scale_to_similarity(M, out)


@numba.njit(cache=True, inline="always")
def _scale_to_similarity(M, out):  # pragma: no cover - compiled
    """Scale the rotation ``out`` to the closest similarity ``s R`` of ``M``.

    ``s = tr(R^T M) / 3`` is the mean of the signed singular values of ``M`` (the paper's
    As-Similar-As-Possible local step), clamped at 0.
    """
    tr = 0.0
    for i in range(3):
        for j in range(3):
            tr += out[i, j] * M[i, j]
    s = max(tr / 3.0, 0.0)
    for i in range(3):
        for j in range(3):
            out[i, j] *= s


@numba.njit(cache=True, inline="always")
def _newton_polar(M, out):  # pragma: no cover - compiled
    """Orthogonal polar factor of a 3x3 matrix with ``det > 0`` by scaled Newton iteration.

    ``X <- (g X + X^{-T} / g) / 2`` with determinant scaling ``g = |det X|^{-1/3}``
    (Higham 1986) converges quadratically to the polar factor, which for ``det M > 0`` is
    the closest proper rotation. Returns False (leaving ``out`` undefined) when ``det M <= 0``,
    the matrix is badly conditioned or the iteration does not settle: the caller then uses
    the SVD path.
    """
    x00 = M[0, 0]
    x01 = M[0, 1]
    x02 = M[0, 2]
    x10 = M[1, 0]
    x11 = M[1, 1]
    x12 = M[1, 2]
    x20 = M[2, 0]
    x21 = M[2, 1]
    x22 = M[2, 2]
    fro = x00 * x00 + x01 * x01 + x02 * x02 + x10 * x10 + x11 * x11 + x12 * x12
    fro += x20 * x20 + x21 * x21 + x22 * x22
    if not fro > 1e-200:
        return False
    small_steps = 0
    for _it in range(30):
        c00 = x11 * x22 - x12 * x21
        c01 = x12 * x20 - x10 * x22
        c02 = x10 * x21 - x11 * x20
        c10 = x02 * x21 - x01 * x22
        c11 = x00 * x22 - x02 * x20
        c12 = x01 * x20 - x00 * x21
        c20 = x01 * x12 - x02 * x11
        c21 = x02 * x10 - x00 * x12
        c22 = x00 * x11 - x01 * x10
        det = x00 * c00 + x01 * c01 + x02 * c02
        nrm2 = x00 * x00 + x01 * x01 + x02 * x02 + x10 * x10 + x11 * x11 + x12 * x12
        nrm2 += x20 * x20 + x21 * x21 + x22 * x22
        # det must be positive and not tiny relative to |X|^3 (condition number <~ 1e7)
        if not det > 1e-21 * nrm2 * math.sqrt(nrm2):
            return False
        g = 1.0
        if small_steps == 0:
            g = det ** (-1.0 / 3.0)
        a = 0.5 * g
        b = 0.5 / (g * det)
        n00 = a * x00 + b * c00
        n01 = a * x01 + b * c01
        n02 = a * x02 + b * c02
        n10 = a * x10 + b * c10
        n11 = a * x11 + b * c11
        n12 = a * x12 + b * c12
        n20 = a * x20 + b * c20
        n21 = a * x21 + b * c21
        n22 = a * x22 + b * c22
        ch = abs(n00 - x00) + abs(n01 - x01) + abs(n02 - x02) + abs(n10 - x10)
        ch += abs(n11 - x11) + abs(n12 - x12) + abs(n20 - x20) + abs(n21 - x21)
        ch += abs(n22 - x22)
        x00, x01, x02, x10, x11, x12, x20, x21, x22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
        if ch < 1e-3:
            small_steps += 1  # quadratic phase: no more scaling
        if ch < 1e-8:
            # quadratic convergence: one more unscaled step reaches rounding level
            c00 = x11 * x22 - x12 * x21
            c01 = x12 * x20 - x10 * x22
            c02 = x10 * x21 - x11 * x20
            c10 = x02 * x21 - x01 * x22
            c11 = x00 * x22 - x02 * x20
            c12 = x01 * x20 - x00 * x21
            c20 = x01 * x12 - x02 * x11
            c21 = x02 * x10 - x00 * x12
            c22 = x00 * x11 - x01 * x10
            det = x00 * c00 + x01 * c01 + x02 * c02
            b = 0.5 / det
            out[0, 0] = 0.5 * x00 + b * c00
            out[0, 1] = 0.5 * x01 + b * c01
            out[0, 2] = 0.5 * x02 + b * c02
            out[1, 0] = 0.5 * x10 + b * c10
            out[1, 1] = 0.5 * x11 + b * c11
            out[1, 2] = 0.5 * x12 + b * c12
            out[2, 0] = 0.5 * x20 + b * c20
            out[2, 1] = 0.5 * x21 + b * c21
            out[2, 2] = 0.5 * x22 + b * c22
            return True
    return False


@numba.njit(cache=True)
def _project_one(M, out, similar):  # pragma: no cover - compiled
    if not _newton_polar(M, out):
        _polar_block(M, out, False)
    if similar:
        _scale_to_similarity(M, out)


@numba.njit(cache=True)
def _project_stack(G, out, similar):  # pragma: no cover - compiled
    d = G.shape[0] // 3
    for a in range(d):
        _project_one(G[3 * a : 3 * a + 3], out[3 * a : 3 * a + 3], similar)


def project_blocks(G, similar: bool = False) -> np.ndarray:
    """Local step on a ``(3d, 3)`` stack (or ``(d, 3, 3)`` array) of 3x3 blocks.

    Parameters
    ----------
    G : (3d, 3) or (d, 3, 3) array_like
        Matrices to project.
    similar : bool
        Closest similarity (rotation times a non-negative scale) instead of closest rotation.

    Returns
    -------
    ndarray, same shape as ``G``
        The closest proper rotation (``det = +1``) of each block, as in the paper's local
        step (SVD with the sign of the last singular direction flipped when ``det < 0``).
    """
    g = np.ascontiguousarray(G, dtype=np.float64)
    shape = g.shape
    g2 = g.reshape(-1, 3)
    if g2.shape[0] % 3:
        raise ValueError(f"expected a stack of 3x3 blocks; got shape {shape}")
    out = np.empty_like(g2)
    _project_stack(g2, out, bool(similar))
    return out.reshape(shape)


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
    _project_stack(G, T, similar)
    return _energy(u, G, T, jzp, l_r, const_h)


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def _dot(a, b):  # pragma: no cover - compiled
    """``a . b``; reassociation lets the reduction vectorise (Anderson's Gram rows)."""
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


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
            theta = np.linalg.solve(A, b)
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
                u[:, :] = ua
                G[:, :] = Gc
                T[:, :] = Tc
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
                u[:, :] = T
                e_tot, e_rig, e_sm, noise = _evaluate(u, C_R, g, jzp, l_r, const_h, similar, G, T)
                if ea < e_tot and math.isfinite(ea):
                    u[:, :] = ua
                    G[:, :] = Gc
                    T[:, :] = Tc
                    e_tot, e_rig, e_sm, noise = ea, ra, sa, na
                    beta = min(2.0 * beta, 64.0)
                else:
                    beta = 2.0
            else:
                u[:, :] = T
                e_tot, e_rig, e_sm, noise = _evaluate(u, C_R, g, jzp, l_r, const_h, similar, G, T)
        it += 1
    if converged and it == 0 and rho0 >= 0.0:
        # a stored solution accepted as it is: it already is a projection (the final plain
        # step of the solve that produced it), and z = B [h; u0] is its result
        return u.copy(), G.copy(), 0, converged, nrec, n_rejected, rho_last
    # final plain step, so that the returned local matrices are exact projections and the
    # last recorded energy is that of the returned solution z = B [h; u]
    u[:, :] = T
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
