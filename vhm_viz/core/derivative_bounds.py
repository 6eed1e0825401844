"""Bounds of the harmonic map's derivatives on cubes: the certificate's injectivity bound.

The map is (paper eq. 1, discrete form of Section 2.1)

    f(y) = sum_t int_t a(q) K1(q, y) dA  +  sum_t b_t int_t K0(q, y) dA,
    K0 = 1 / (4 pi |q - y|),   K1 = N_t . grad_y K0,

with ``a`` the piecewise-linear interpolation of the vertex coefficients ``a_v`` and
``b`` constant (``b_t``) on each face. Take a cube with centre ``p``, half extents ``e`` and
circumradius ``r = |e|``. For ``p + h`` in the cube, Taylor's theorem with integral
remainder gives

    J(p + h) = J(p) + H(p)[h] + R(h),    ||R(h)||_F <= 1/2 M3 |h|^2,                   (1)

where ``M3 = sqrt(sum_i M3_i^2)`` and ``M3_i`` bounds the third derivative of ``f_i`` on the
ball ``B(p, r)`` (``|D^3 f_i[., h, h]| <= M3_i |h|^2``). Weyl's inequality for singular
values, ``sigma_min(A + E) >= sigma_min(A) - ||E||_2``, bounds the whole cube:

    sigma_min(J(p + h)) >= sigma_min(J(p)) - max_corners sqrt(h^T G h) - 1/2 M3 r^2,   (2)

with ``G_kl = sum_ij H_ijk H_ijl`` (``||H[h]||_2 <= ||H[h]||_F = sqrt(h^T G h)``, a convex
function of ``h``, so its maximum over the cube is at a corner). When the right-hand side
exceeds a rounding margin and ``det J(p) > 0``, ``J`` is nonsingular on the whole cube and
``det J``, being continuous, keeps its sign: ``det J > 0`` on the cube.

*M3 from the boundary integral.* The k-th derivatives of ``1/|x|`` are bounded by
``k! / |x|^(k+1)`` in operator norm: the directional ones are ``k! P_k(cos theta) /
|x|^(k+1)`` (the generating function of the Legendre polynomials, ``|P_k| <= 1``), and a
symmetric multilinear form attains its norm on the diagonal (Banach 1938). So
``|D^3 K0| <= 6 / (4 pi d^4)`` and ``|D^3 K1| <= |D^4 K0| <= 24 / (4 pi d^5)``, ``d = |q - y|``:

    M3_i <= 1/(4 pi) sum_t [ 24 int_t |a'_i(q)| d^-5 dA  +  6 |b'_ti| int_t d^-4 dA ].  (3)

*Subtracting an affine map.* The basis reproduces ``y -> A y + T`` exactly with
``a(q) = A q + T``, ``b_t = A N_t`` (paper Section 2.1), and an affine map has no third
derivative, so (3) may use the coefficients minus any affine map:
``a'_v = a_v - A x_v - T``, ``b'_t = b_t - A N_t``. We subtract the tangent map at ``p``
(``A = J(p)``, ``T = f(p) - J(p) p``): on the faces near the cube, where the kernels are
large, the coefficients follow the tangent map closely. Without this step even the
identity map gets a useless bound.

*Face integrals.* For ``y`` in the ball and a (sub-)triangle ``s`` of area ``A`` at distance
``delta = dist(p, s) - r > 0`` from the ball, ``s`` lies outside the sphere of radius
``delta`` about ``y``; on a plane ``dA = pi d(d^2)``, so by the bathtub principle

    int_s d^-k dA <= 2 pi / (k - 2) [delta^(2-k) - (delta^2 + A / pi)^((2-k)/2)],       (4)

which is below both ``A / delta^k`` and the whole plane's ``2 pi delta^(2-k) / (k - 2)``.
``|a'_i|`` is linear on ``s``, so its maximum is at a corner. Faces closer to the ball than
their size are split into four (recursively) before (4) is applied: the bound then follows
the kernel's decay across the face.

These bounds are what :func:`~vhm_viz.core.certify.certify_injectivity` checks cube by
cube; :func:`cage_distance` gives the gap between a cube and the cage they need.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.geometry import face_normals_and_areas, triangle_distance
from vhm_viz.core.row_threads import run_rows

__all__ = [
    "cage_distance",
    "hessian_term",
    "jacobian_deviation_bounds",
    "third_derivative_bounds",
]

# Faces closer to the ball than KAPPA times their diameter are split (tightens (4)), if they
# are within NEAR times the distance of the nearest face (farther ones weigh little).
_KAPPA = 1.0
_NEAR = 3.0
# Deepest face subdivision (4^8 sub-triangles at most; reached only right next to a face).
_MAX_FACE_DEPTH = 8
_FOUR_PI = 4.0 * math.pi


@numba.njit(cache=True, nogil=True)
def _cage_distance_kernel(start, stop, points, V, F, out):  # pragma: no cover - compiled
    for k in range(start, stop):
        px, py, pz = points[k, 0], points[k, 1], points[k, 2]
        best = np.inf
        for t in range(F.shape[0]):
            a, b, c = F[t, 0], F[t, 1], F[t, 2]
            d = triangle_distance(
                px, py, pz, V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1], V[b, 2],
                V[c, 0], V[c, 1], V[c, 2],
            )  # fmt: skip
            if d < best:
                best = d
        out[k] = best


def cage_distance(points, vertices, faces) -> np.ndarray:
    """Unsigned distance from each point to the cage surface.

    Parameters
    ----------
    points : (N, 3) array_like
    vertices : (n, 3) array_like
    faces : (m, 3) array_like of int

    Returns
    -------
    (N,) float64
    """
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(p))
    if len(p):
        run_rows(
            _cage_distance_kernel,
            len(p),
            p,
            np.ascontiguousarray(vertices, dtype=np.float64),
            np.ascontiguousarray(faces, dtype=np.int64),
            out,
        )
    return out


@numba.njit(cache=True, inline="always")
def _kernel_integrals(delta, area):  # pragma: no cover - compiled
    """Bounds (4) of ``int d^-5 dA`` and ``int d^-4 dA`` over an area at distance ``delta``.

    Written with ``x = A / (pi delta^2)`` so that small pieces lose no digits:
    ``2 pi/3 delta^-3 (1 - (1 + x)^(-3/2))`` and ``pi delta^-2 x / (1 + x)``. Far pieces
    (``x < 1e-3``) take ``A / delta^k``, an upper bound of both that costs no logarithm
    and is within 0.15% of them there.
    """
    d2 = delta * delta
    x = area / (math.pi * d2)
    if x < 1e-3:
        i4 = area / (d2 * d2)
        return i4 / delta, i4
    i5 = (2.0 * math.pi / 3.0) / (d2 * delta) * (-math.expm1(-1.5 * math.log1p(x)))
    i4 = math.pi / d2 * (x / (1.0 + x))
    return i5, i4


@numba.njit(cache=True)
def _face_integrals(
    px, py, pz, r, X, D, area, diameter, dist, near, work, sx, sd, sdepth, out
):  # pragma: no cover - compiled
    """Add one face's ``int |a'_i| d^-5`` (out[0:3]) and ``int d^-4`` (out[3]).

    ``X`` (3, 3) corners, ``D`` (3, 3) signed residual densities ``a'`` at the corners
    (rows: corners), ``diameter`` its longest edge, ``dist`` a lower bound of its distance
    to ``p``. The face is
    split into four while it is closer to the ball than ``_KAPPA`` times its diameter and
    closer than ``near``; ``sx``, ``sd``, ``sdepth`` are the explicit stack and ``work``
    (4, 3, 3) scratch (nothing is allocated per piece). Returns False when a piece touches
    the ball (no bound).
    """
    top = 0
    sx[0] = X
    sd[0] = D
    sdepth[0] = 0
    while top >= 0:
        # the popped piece's slot is overwritten by its children: work on a copy
        Y, E, M, Mq = work[0], work[1], work[2], work[3]
        for i in range(3):
            for c in range(3):
                Y[i, c] = sx[top, i, c]
                E[i, c] = sd[top, i, c]
        depth = sdepth[top]
        top -= 1
        if depth == 0:
            d = dist
        else:
            d = triangle_distance(
                px, py, pz, Y[0, 0], Y[0, 1], Y[0, 2], Y[1, 0], Y[1, 1], Y[1, 2],
                Y[2, 0], Y[2, 1], Y[2, 2],
            )  # fmt: skip
        delta = d * (1.0 - 1e-12) - r
        if delta <= 0.0:
            return False
        # midpoint subdivision halves every edge: the pieces are similar to the face
        diam = diameter / (2.0**depth)
        if diam > _KAPPA * delta and delta < near and depth < _MAX_FACE_DEPTH:
            # four children: the corner triangles and the middle one
            for i in range(3):
                j = (i + 1) % 3
                for c in range(3):
                    M[i, c] = 0.5 * (Y[i, c] + Y[j, c])  # midpoint of edge (i, i+1)
                    Mq[i, c] = 0.5 * (E[i, c] + E[j, c])
            for i in range(3):
                top += 1
                k = (i + 2) % 3  # the edge (i-1, i) midpoint
                for c in range(3):
                    sx[top, 0, c] = Y[i, c]
                    sx[top, 1, c] = M[i, c]
                    sx[top, 2, c] = M[k, c]
                    sd[top, 0, c] = E[i, c]
                    sd[top, 1, c] = Mq[i, c]
                    sd[top, 2, c] = Mq[k, c]
                sdepth[top] = depth + 1
            top += 1
            sx[top] = M
            sd[top] = Mq
            sdepth[top] = depth + 1
            continue
        piece = area / (4.0**depth)
        i5, i4 = _kernel_integrals(delta, piece)
        for c in range(3):
            m = max(abs(E[0, c]), abs(E[1, c]), abs(E[2, c]))
            out[c] += m * i5
        out[3] += i4
    return True


@numba.njit(cache=True)
def _fit_affine(px, py, pz, V, F, N, areas, a, b, dist, wv, M, R, A, T):  # pragma: no cover
    """The affine map subtracted in (3) for a ball at ``p``: a weighted least-squares fit.

    Minimises ``sum_v w_v |a_v - A x_v - T|^2 + sum_t w_t |b_t - A N_t|^2`` with the weights
    of the kernels in (3) over the size of the residual each multiplies (a double-layer
    residual is a length, about ``d`` times a single-layer one, which is a ratio):
    ``w ~ area / (d^2 + area/pi)^3.5`` for the double layer (spread to the face's corners)
    and a quarter of ``area / (d^2 + area/pi)^2.5`` for the single layer (``d`` the face's
    distance to ``p``). Both scale alike with the unit of length, so the fit, and with it
    the certificate's cubes, do not depend on it. Any affine map gives a valid bound; this
    one makes the residual densities small on the faces that dominate it, where the
    tangent map at ``p`` would keep the whole curvature of the map. ``wv`` is scratch.
    """
    M[:, :] = 0.0
    R[:, :] = 0.0
    wv[:] = 0.0
    for t in range(F.shape[0]):
        s = dist[t] * dist[t] + areas[t] / math.pi
        w = areas[t] / (s * s * s * math.sqrt(s)) / 3.0
        for i in range(3):
            wv[F[t, i]] += w
        # the single layer's rows (N_t, 0)
        wb = 0.25 * areas[t] / (s * s * math.sqrt(s))
        for r in range(3):
            for c in range(3):
                M[r, c] += wb * N[t, r] * N[t, c]
                R[r, c] += wb * N[t, r] * b[t, c]
    for v in range(V.shape[0]):
        w = wv[v]
        if w == 0.0:
            continue  # an unreferenced vertex
        # rows (x_v - p, 1): coordinates relative to p keep the equations well conditioned
        x0, x1, x2 = V[v, 0] - px, V[v, 1] - py, V[v, 2] - pz
        row = (x0, x1, x2, 1.0)
        for r in range(4):
            wr = w * row[r]
            for c in range(4):
                M[r, c] += wr * row[c]
            for c in range(3):
                R[r, c] += wr * a[v, c]
    X = np.linalg.solve(M, R)  # (4, 3): rows A^T, then the value at p
    for i in range(3):
        for j in range(3):
            A[i, j] = X[j, i]
    for i in range(3):
        T[i] = X[3, i] - (A[i, 0] * px + A[i, 1] * py + A[i, 2] * pz)


@numba.njit(cache=True, nogil=True)
def _third_derivative_kernel(
    start,
    stop,
    centres,
    radii,
    fit,
    A_in,
    T_in,
    V,
    F,
    N,
    areas,
    fc,
    fr,
    diam,
    a,
    b,
    out_m3,
    out_dist,
):  # pragma: no cover - compiled
    """Bound (3) of the third derivative on each ball, and the centre's distance to the cage.

    With ``fit`` the affine map subtracted is :func:`_fit_affine`'s, else ``A_in`` (k, 3, 3),
    ``T_in`` (k, 3). ``fc``, ``fr``, ``diam``: face centroids, the radii of their
    circumscribing balls about the centroids and longest edges (faces far from ``p``
    use ``|p - centroid| - radius``, a lower bound of their distance). ``out_m3`` gets
    ``sqrt(sum_i M3_i^2)`` (inf where the ball touches the cage); ``out_dist`` a lower bound
    of the centre's distance to the cage (exact where it is below ``r`` plus four times the
    nearest faces' radius).
    """
    m = F.shape[0]
    for k in range(start, stop):
        sx = np.empty((3 * _MAX_FACE_DEPTH + 4, 3, 3))
        sd = np.empty((3 * _MAX_FACE_DEPTH + 4, 3, 3))
        sdepth = np.empty(3 * _MAX_FACE_DEPTH + 4, dtype=np.int64)
        work = np.empty((4, 3, 3))
        X = np.empty((3, 3))
        D = np.empty((3, 3))
        acc = np.zeros(4)
        sa = np.zeros(3)
        sb = np.zeros(3)
        dist = np.empty(m)
        wv = np.empty(V.shape[0])
        M = np.empty((4, 4))
        R = np.empty((4, 3))
        res = np.empty((V.shape[0], 3))
        A = np.empty((3, 3))
        T = np.empty(3)
        px, py, pz = centres[k, 0], centres[k, 1], centres[k, 2]
        r = radii[k]
        dmin = np.inf
        for t in range(m):
            cx, cy, cz = px - fc[t, 0], py - fc[t, 1], pz - fc[t, 2]
            d = math.sqrt(cx * cx + cy * cy + cz * cz) - fr[t]
            if d <= r + 4.0 * fr[t]:  # near: the exact distance
                i0, i1, i2 = F[t, 0], F[t, 1], F[t, 2]
                d = triangle_distance(
                    px, py, pz, V[i0, 0], V[i0, 1], V[i0, 2], V[i1, 0], V[i1, 1], V[i1, 2],
                    V[i2, 0], V[i2, 1], V[i2, 2],
                )  # fmt: skip
            dist[t] = d
            dmin = min(dmin, d)
        out_dist[k] = dmin
        if dmin * (1.0 - 1e-12) - r <= 0.0:
            out_m3[k] = np.inf  # the ball touches the cage: the kernels are singular there
            continue
        if fit:
            _fit_affine(px, py, pz, V, F, N, areas, a, b, dist, wv, M, R, A, T)
        else:
            # element loops: numba's array slice assignment compiles a formatted
            # shape-mismatch message, costly to compile
            for i in range(3):
                T[i] = T_in[k, i]
                for j in range(3):
                    A[i, j] = A_in[k, i, j]
        # the residual double-layer density at the vertices, once per cube
        for v in range(V.shape[0]):
            for c in range(3):
                res[v, c] = (
                    a[v, c] - (A[c, 0] * V[v, 0] + A[c, 1] * V[v, 1] + A[c, 2] * V[v, 2]) - T[c]
                )
        ok = True
        for t in range(m):
            for i in range(3):
                v = F[t, i]
                for c in range(3):
                    X[i, c] = V[v, c]
                    D[i, c] = res[v, c]
            acc[:] = 0.0
            near = _NEAR * (dmin - r)
            if not _face_integrals(
                px, py, pz, r, X, D, areas[t], diam[t], dist[t], near, work, sx, sd, sdepth, acc
            ):
                ok = False
                break
            for c in range(3):
                sa[c] += acc[c]
                bres = b[t, c] - (A[c, 0] * N[t, 0] + A[c, 1] * N[t, 1] + A[c, 2] * N[t, 2])
                sb[c] += abs(bres) * acc[3]
        if ok:
            s = 0.0
            for c in range(3):
                mi = (24.0 * sa[c] + 6.0 * sb[c]) / _FOUR_PI
                s += mi * mi
            out_m3[k] = math.sqrt(s) * (1.0 + 1e-12)
        else:
            out_m3[k] = np.inf


def _cage_arrays(hm):
    cage = hm.cage
    v = np.ascontiguousarray(cage.vertices, dtype=np.float64)
    f = np.ascontiguousarray(cage.faces, dtype=np.int64)
    normals, areas = face_normals_and_areas(v, f)
    z = np.asarray(hm.coefficients, dtype=np.float64)
    n = len(v)
    corners = v[f]
    centroids = corners.mean(axis=1)
    radii = np.linalg.norm(corners - centroids[:, None], axis=2).max(axis=1)
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    return (
        v, f, normals, areas, np.ascontiguousarray(centroids), radii, edges,
        np.ascontiguousarray(z[:n]), np.ascontiguousarray(z[n:]),
    )  # fmt: skip


def third_derivative_bounds(harmonic_map, centres, radii, values=None, jacobians=None):
    """Bound (3) of ``|D^3 f|`` on balls, after subtracting an affine map per ball.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    centres : (k, 3) array_like
        Ball centres ``p`` (inside the cage).
    radii : (k,) array_like
        Ball radii ``r``.
    values, jacobians : (k, 3), (k, 3, 3) array_like, optional
        Subtract the map ``y -> values + jacobians (y - p)`` (e.g. the tangent map, with
        ``f(p)`` and ``J(p)``). Default: the kernel-weighted least-squares fit to the
        coefficients (much tighter where the map bends; any affine map is valid).

    Returns
    -------
    m3 : (k,) float64
        ``M3 = sqrt(sum_i M3_i^2)``: ``||J(p + h) - J(p) - H(p)[h]||_F <= M3 |h|^2 / 2``
        for ``|h| <= r``; ``inf`` where the ball touches the cage.
    distance : (k,) float64
        Distance from each centre to the cage.
    """
    v, f, normals, areas, fc, fr, diam, a, b = _cage_arrays(harmonic_map)
    p = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.ascontiguousarray(np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(p),)))
    fit = jacobians is None
    if fit:
        jac, t = np.zeros((len(p), 3, 3)), np.zeros((len(p), 3))
    else:
        jac = np.ascontiguousarray(jacobians, dtype=np.float64).reshape(-1, 3, 3)
        t = np.asarray(values, dtype=np.float64).reshape(-1, 3) - np.einsum("kij,kj->ki", jac, p)
        t = np.ascontiguousarray(t)
    m3 = np.empty(len(p))
    dist = np.empty(len(p))
    if len(p):
        run_rows(
            _third_derivative_kernel, len(p), p, r, fit, jac, t, v, f, normals, areas, fc, fr,
            diam, a, b, m3, dist, grain=1,
        )  # fmt: skip
    return m3, dist


def _corner_signs() -> np.ndarray:
    # h^T G h is even in h: four of the eight corners suffice
    return np.array([[1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]], dtype=np.float64)


def hessian_term(hessians: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """``max over the cube's corners of ||H(p)[h]||_F`` (the linear term of (2)).

    Parameters
    ----------
    hessians : (k, 3, 3, 3) float64
        ``H[i, j, l] = d^2 f_i / dx_j dx_l`` at the cube centres.
    half_extents : (3,) array_like
        Half side lengths of the cubes.

    Returns
    -------
    (k,) float64
    """
    g = np.einsum("nijk,nijl->nkl", hessians, hessians)
    h = _corner_signs() * np.asarray(half_extents, dtype=np.float64)
    q = np.einsum("ck,nkl,cl->nc", h, g, h)
    return np.sqrt(np.maximum(q.max(axis=1), 0.0))


def jacobian_deviation_bounds(harmonic_map, centres, half_extents):
    """Bound of ``max ||J(x) - J(p)||_2`` over axis-aligned cubes (centre ``p``).

    The linear and remainder terms of (2): ``max_corners ||H(p)[h]||_F + M3 r^2 / 2``.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    centres : (k, 3) array_like
        Cube centres, inside the cage.
    half_extents : (3,) array_like
        Half side lengths (common to the cubes).

    Returns
    -------
    (k,) float64
        ``inf`` for cubes whose circumscribed ball touches the cage.
    """
    p = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(half_extents, dtype=np.float64).reshape(3)
    r = float(np.linalg.norm(e))
    f, jac, hess = harmonic_map.evaluate(p, order=2)
    m3, _ = third_derivative_bounds(harmonic_map, p, np.full(len(p), r))
    return hessian_term(hess, e) + 0.5 * m3 * r * r
