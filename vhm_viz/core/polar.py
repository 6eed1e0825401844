"""The local step: the closest rotation (or similarity) to each 3x3 block.

A scaled Newton iteration finds the polar factor of a well-conditioned block with
``det > 0``; other blocks go through an eigen-decomposition of ``M^T M`` by cyclic Jacobi
rotations, the rotation built from the first two singular directions and their cross
product (the closest *proper* rotation, ``det = +1``, as in the paper's local step).
As-Similar-As-Possible scales the rotation by the mean signed singular value (paper
Figure 12).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.mat3 import cofactors3

__all__ = ["project_blocks", "project_stack"]


@numba.njit(cache=True, fastmath=False)
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


@numba.njit(cache=True)
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


@numba.njit(cache=True)
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
    last = False  # converged: one more unscaled step reaches rounding level
    for _it in range(31):
        c00, c01, c02, c10, c11, c12, c20, c21, c22 = cofactors3(
            x00, x01, x02, x10, x11, x12, x20, x21, x22
        )
        det = x00 * c00 + x01 * c01 + x02 * c02
        nrm2 = x00 * x00 + x01 * x01 + x02 * x02 + x10 * x10 + x11 * x11 + x12 * x12
        nrm2 += x20 * x20 + x21 * x21 + x22 * x22
        # det must be positive and not tiny relative to |X|^3 (condition number <~ 1e7)
        if not det > 1e-21 * nrm2 * math.sqrt(nrm2):
            return False
        g = 1.0
        if small_steps == 0 and not last:
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
        if last:
            out[0, 0], out[0, 1], out[0, 2] = n00, n01, n02
            out[1, 0], out[1, 1], out[1, 2] = n10, n11, n12
            out[2, 0], out[2, 1], out[2, 2] = n20, n21, n22
            return True
        ch = abs(n00 - x00) + abs(n01 - x01) + abs(n02 - x02) + abs(n10 - x10)
        ch += abs(n11 - x11) + abs(n12 - x12) + abs(n20 - x20) + abs(n21 - x21)
        ch += abs(n22 - x22)
        x00, x01, x02, x10, x11, x12, x20, x21, x22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
        if ch < 1e-3:
            small_steps += 1  # quadratic phase: no more scaling
        last = ch < 1e-8
    return False


@numba.njit(cache=True)
def _project_one(M, out, similar):  # pragma: no cover - compiled
    if not _newton_polar(M, out):
        _polar_block(M, out, False)
    if similar:
        _scale_to_similarity(M, out)


@numba.njit(cache=True)
def project_stack(G, out, similar):  # pragma: no cover - compiled
    """Local step of every 3x3 block of the ``(3d, 3)`` stack ``G`` into ``out``."""
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
    project_stack(g2, out, bool(similar))
    return out.reshape(shape)
