"""Point-vectorised kernel for basis values and gradients (the common, far-from-cage case).

:mod:`vhm_viz.core.basis_kernel` evaluates one point at a time, with branches for every
way a point can sit next to the cage. Most points of a shape are not next to any cage edge,
and for them the plain formulas are exact to rounding. This kernel evaluates such points in
groups of ``LANES``: every loop runs over the lanes of a group, without branches, so LLVM
turns it into SIMD code, and the transcendental functions come from
:mod:`vhm_viz.core.vecmath` instead of the C library (which would stop vectorisation).

A point is *flagged* (and left for the careful per-point kernel) when it is near a cage
edge, in the sense of the per-point kernel's pivot rule (``R - |d| < near_edge * |d|``), on
it, or has a host face. A point exactly in a face's plane and inside the triangle gets the
interior limit with a select, as in the per-point kernel, so the two kernels agree to a few
ulp wherever both apply; the tests check it.

Making LLVM vectorise these loops took some care, and the rules are easy to break:

* Scratch arrays are flat, ``LANES`` per row, indexed with **unsigned** offsets
  (``np.uint64``): numba adds a negative-index fix-up to signed indices, which turns
  ``base + j`` into a gather instead of a contiguous load.
* Row offsets are compile-time multiples of ``LANES`` from a common base, so that LLVM sees
  the rows read from one cage vertex as a single block: the loop then needs few enough
  run-time alias checks (at most 8) to be vectorised at all.
* Loop trip counts are run-time values: a constant 16 gets a loop fully unrolled, and the
  unrolled body is not vectorised.
* A loop writes into one array at one base only (several rows of one array, at unrelated
  offsets, count as a possible dependence), so results go through a small buffer.
* Only a face's values (called once per face of every group) are inlined at numba level.
  The other helpers are plain compiled functions: LLVM inlines the small ones into their
  loops, and the large ones (a group's basis, every face's terms) are compiled once and
  shared by the kernels here. numba's inlining copies and re-analyses the callee at every
  call site, which made these kernels the slowest part of a first run; a call per group
  of 16 points costs nothing measurable.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core import face_formulas, vecmath

# Points per group. LLVM vectorises the lane loops 4 wide (AVX2), so 16 lanes are four
# vector iterations: fewer lanes leave the loop overhead in charge, more gain nothing. The
# scratch per group is (4 n + n_edges + n + m) * 16 * 8 bytes: it grows with the cage,
# never with the number of points.
LANES = 16
#: Rows per chunk of :func:`vhm_viz.core.row_threads.run_rows` (whole groups, and enough
#: of them to amortise a chunk's scratch allocation).
ROWS_GRAIN = 16 * LANES
_INV_TWO_PI = 1.0 / (2.0 * math.pi)


_JIT = dict(cache=True, error_model="numpy", boundscheck=False)
_INLINE = dict(_JIT, inline="always")
# The kernels over ranges of points: serial, run on threads by run_rows (see its module).
_ROWS = dict(_JIT, nogil=True)
_U = np.uint64
_S = _U(LANES)  # row length of the flat scratch arrays, as an unsigned offset

# One face's closed form (paper Appendix A), shared with the GPU kernels of
# vhm_viz.core.cuda_map: inlined into the lane loops, which stay vectorisable because
# the transcendental functions (vecmath's) are applied here, outside the shared formulas.
_edge_log_argument = numba.njit(**_INLINE)(face_formulas.edge_log_argument)
_solid_angle_parts = numba.njit(**_INLINE)(face_formulas.solid_angle_parts)
_one_face = numba.njit(**_INLINE)(face_formulas.face_terms)


@numba.njit(**_JIT)
def _vectors_to_vertices(pts, V, E, L):  # pragma: no cover - compiled
    """Rows ``x, y, z, |e|`` of ``e = x_a - p`` for every cage vertex ``a``: ``E[4a + c]``."""
    S = _S
    for a in range(V.shape[0]):
        vx = V[a, 0]
        vy = V[a, 1]
        vz = V[a, 2]
        base = _U(a) * _U(4) * S
        for j in range(_U(L)):
            x = vx - pts[j]
            y = vy - pts[S + j]
            z = vz - pts[_U(2) * S + j]
            E[base + j] = x
            E[base + S + j] = y
            E[base + _U(2) * S + j] = z
            E[base + _U(3) * S + j] = math.sqrt(x * x + y * y + z * z)


@numba.njit(**_JIT)
def _corner(E, base, j):  # pragma: no cover - compiled
    """Lane ``j`` of the rows ``x, y, z, |e|`` of one cage vertex starting at ``base``."""
    S = _S
    return E[base + j], E[base + S + j], E[base + _U(2) * S + j], E[base + _U(3) * S + j]


@numba.njit(**_JIT)
def _edge_logs(E, edges, edge_len, inv_4pi_len, near_edge, ce, near, L):  # pragma: no cover
    """Per edge and lane: ``C = log(1 + 2|d| / (R - |d|)) / (4 pi |d|)``; flags near edges.

    ``near[j]`` becomes nonzero when lane ``j`` is near (or on) some edge; its ``C`` values
    are then placeholders.
    """
    S = _S
    for q in range(edges.shape[0]):
        bi = _U(edges[q, 0]) * _U(4) * S
        bj = _U(edges[q, 1]) * _U(4) * S
        dl = edge_len[q]
        c4 = inv_4pi_len[q]
        limit = near_edge * dl
        out = _U(q) * S
        for j in range(_U(L)):
            ux, uy, uz, li = _corner(E, bi, j)
            wx, wy, wz, lj = _corner(E, bj, j)
            arg, is_near = _edge_log_argument(ux, uy, uz, li, wx, wy, wz, lj, dl, limit)
            near[j] += 1.0 if is_near else 0.0
            ce[out + j] = vecmath.log1p(arg) * c4


@numba.njit(**_INLINE)
def _face_values(E, ce, b0, b1, b2, q0, q1, q2, n_t, NxD_t, ia, buf, L):  # pragma: no cover
    """One face, every lane: ``psi_t``, the three ``phi`` increments and ``P`` into ``buf``.

    ``b*`` are the flat offsets of the face's corners in ``E``, ``q*`` those of the edges
    opposite them in ``ce``; ``buf`` rows: psi, phi increments of corners 0-2, P (x, y, z).
    """
    S = _S
    nx, ny, nz = n_t[0], n_t[1], n_t[2]
    m0x, m0y, m0z = NxD_t[0, 0], NxD_t[0, 1], NxD_t[0, 2]
    m1x, m1y, m1z = NxD_t[1, 0], NxD_t[1, 1], NxD_t[1, 2]
    m2x, m2y, m2z = NxD_t[2, 0], NxD_t[2, 1], NxD_t[2, 2]
    for j in range(_U(L)):
        x0, y0, z0, l0 = _corner(E, b0, j)
        x1, y1, z1, l1 = _corner(E, b1, j)
        x2, y2, z2, l2 = _corner(E, b2, j)
        det, den = _solid_angle_parts(x0, y0, z0, l0, x1, y1, z1, l1, x2, y2, z2, l2)
        w = vecmath.atan2(det, den) * _INV_TWO_PI
        # exactly in the plane, inside the triangle: the interior limit
        w = 0.5 if (det == 0.0) & (den < 0.0) else w
        psi, f0, f1, f2, qx, qy, qz = _one_face(
            x0, y0, z0, x1, y1, z1, x2, y2, z2, w, ce[q0 + j], ce[q1 + j], ce[q2 + j],
            nx, ny, nz, m0x, m0y, m0z, m1x, m1y, m1z, m2x, m2y, m2z, ia,
        )  # fmt: skip
        buf[j] = psi
        buf[S + j] = f0
        buf[_U(2) * S + j] = f1
        buf[_U(3) * S + j] = f2
        buf[_U(4) * S + j] = qx
        buf[_U(5) * S + j] = qy
        buf[_U(6) * S + j] = qz


@numba.njit(**_JIT)
def _scatter(dst, dst_off, buf, buf_row, scale, add, L):  # pragma: no cover - compiled
    """``dst[dst_off + j] (+)= scale * buf[buf_row * LANES + j]``."""
    src = _U(buf_row) * _S
    if add:
        for j in range(_U(L)):
            dst[dst_off + j] += scale * buf[src + j]
    else:
        for j in range(_U(L)):
            dst[dst_off + j] = scale * buf[src + j]


@numba.njit(**_JIT)
def _face_terms(E, ce, F, N, inv_twice_area, D, NxD, face_edges, order, acc, accg, buf, L):
    """Add every face's contribution to the basis values (and gradients), lane by lane.

    ``acc`` holds ``n + m`` rows (vertex functions, then faces) and ``accg`` three such
    blocks (x, y, z derivatives). Each face's results go to ``buf`` first and are then added
    to ``acc`` one row at a time (see the module notes).
    """  # pragma: no cover - compiled
    S = _S
    n = _U(E.shape[0]) // (_U(4) * S)
    nm = n + _U(F.shape[0])
    for t in range(F.shape[0]):
        ia = inv_twice_area[t]
        col = (n + _U(t)) * S
        r0 = _U(F[t, 0])
        r1 = _U(F[t, 1])
        r2 = _U(F[t, 2])
        _face_values(
            E,
            ce,
            r0 * _U(4) * S,
            r1 * _U(4) * S,
            r2 * _U(4) * S,
            _U(face_edges[t, 0]) * S,
            _U(face_edges[t, 1]) * S,
            _U(face_edges[t, 2]) * S,
            N[t],
            NxD[t],
            ia,
            buf,
            L,
        )
        _scatter(acc, col, buf, 0, 1.0, False, L)
        # buffer rows 1-3 to the corners (a loop index, not constants: numba compiles a
        # helper once per combination of constant arguments)
        for v in range(3):
            _scatter(acc, _U(F[t, v]) * S, buf, v + 1, 1.0, True, L)
        if order >= 1:
            # grad psi_t = -P ;  grad phi_v += (P x d_v) / 2A, one axis per loop
            for c in range(3):
                block = _U(c) * nm * S
                _scatter(accg, block + col, buf, 4 + c, -1.0, False, L)
                for v in range(3):
                    row = _U(F[t, v]) * S + block
                    c1 = (c + 1) % 3
                    c2 = (c + 2) % 3
                    # (P x d)_c = P_{c+1} d_{c+2} - P_{c+2} d_{c+1}
                    _scatter(accg, row, buf, 4 + c1, D[t, v, c2] * ia, True, L)
                    _scatter(accg, row, buf, 4 + c2, -D[t, v, c1] * ia, True, L)


@numba.njit(**_JIT)
def _group_basis(
    points, k0, host, V, F, N, inv_twice_area, D, NxD, edges, edge_len, inv_4pi_len,
    face_edges, near_edge, order, pts, near, E, ce, acc, accg, buf, L,
):  # pragma: no cover - compiled  # fmt: skip
    """Basis values (and gradients) of the group of points starting at ``k0``.

    Into ``acc`` (and ``accg``); ``near[j]`` flags the lanes the per-point kernel must redo.
    """
    npts = points.shape[0]
    n = V.shape[0]
    nm = n + F.shape[0]
    for j in range(L):
        k = min(k0 + j, npts - 1)  # the last group repeats its last point
        pts[j] = points[k, 0]
        pts[L + j] = points[k, 1]
        pts[2 * L + j] = points[k, 2]
        near[j] = 0.0 if host[min(k, host.shape[0] - 1)] < 0 else 1.0
    # the vertex rows accumulate over faces: start them at zero
    acc[: n * L] = 0.0
    if order >= 1:
        for c in range(3):
            accg[c * nm * L : c * nm * L + n * L] = 0.0
    _vectors_to_vertices(pts, V, E, L)
    _edge_logs(E, edges, edge_len, inv_4pi_len, near_edge, ce, near, L)
    _face_terms(E, ce, F, N, inv_twice_area, D, NxD, face_edges, order, acc, accg, buf, L)


@numba.njit(**_INLINE)
def _group_scratch(n, n_edges, nm, order, L):  # pragma: no cover - compiled
    """Scratch of one chunk of rows: ``pts, near, E, ce, acc, accg, buf`` (see _group_basis)."""
    return (
        np.empty(3 * L),
        np.empty(L),
        np.empty(4 * n * L),
        np.empty(n_edges * L),
        np.empty(nm * L),
        np.empty(3 * nm * L if order >= 1 else 0),
        np.empty(7 * L),
    )


@numba.njit(**_ROWS)
def lanes_kernel(
    start, stop, points, V, F, N, inv_twice_area, D, NxD, edges, edge_len, inv_4pi_len,
    face_edges, host, near_edge, order, values, gradients, flagged,
):  # pragma: no cover - compiled  # fmt: skip
    """Values (``order`` 0) or values and gradients (``order`` 1) of the basis.

    Of the points ``start <= k < stop`` (``start`` a multiple of ``LANES``; see
    :func:`vhm_viz.core.row_threads.run_rows`). Cage arrays as in
    :func:`vhm_viz.core.cage_tables.kernel_arrays`; ``flagged[k]`` is set for points this
    kernel does not handle (near or on a cage edge or vertex, or with a host face): their
    rows of ``values``/``gradients`` hold placeholders and must be recomputed by the
    per-point kernel.
    """
    L = LANES
    n = V.shape[0]
    nm = n + F.shape[0]
    pts, near, E, ce, acc, accg, buf = _group_scratch(n, edges.shape[0], nm, order, L)
    for k0 in range(start, stop, L):
        _group_basis(
            points, k0, host, V, F, N, inv_twice_area, D, NxD, edges, edge_len,
            inv_4pi_len, face_edges, near_edge, order, pts, near, E, ce, acc, accg, buf, L,
        )  # fmt: skip
        for j in range(min(L, stop - k0)):
            k = k0 + j
            flagged[k] = near[j] > 0.0
            for c in range(nm):
                values[k, c] = acc[c * L + j]
            if order >= 1:
                for r in range(3):
                    for c in range(nm):
                        gradients[k, r, c] = accg[(r * nm + c) * L + j]


@numba.njit(**_INLINE)
def _add_solid_angles(E, b0, b1, b2, wsum, L):  # pragma: no cover - compiled
    """``wsum[j] +=`` the signed solid angle / 4 pi of one face seen from lane ``j``."""
    for j in range(_U(L)):
        x0, y0, z0, l0 = _corner(E, b0, j)
        x1, y1, z1, l1 = _corner(E, b1, j)
        x2, y2, z2, l2 = _corner(E, b2, j)
        det, den = _solid_angle_parts(x0, y0, z0, l0, x1, y1, z1, l1, x2, y2, z2, l2)
        w = vecmath.atan2(det, den) * _INV_TWO_PI
        # exactly in the plane: 1/2 inside the triangle, 0 on its edges and corners
        in_plane = (det == 0.0) & (den <= 0.0)
        wsum[j] += (0.5 if den < 0.0 else 0.0) if in_plane else w


@numba.njit(**_ROWS)
def winding_kernel(start, stop, points, V, F, out):  # pragma: no cover - compiled
    """Generalised winding number (sum of face solid angles / 4 pi) at points ``start..stop``.

    ``start`` a multiple of ``LANES`` (see :func:`vhm_viz.core.row_threads.run_rows`).
    """
    L = LANES
    npts = points.shape[0]
    n = V.shape[0]
    S = _S
    pts = np.empty(3 * L)
    E = np.empty(4 * n * L)
    wsum = np.empty(L)
    for k0 in range(start, stop, L):
        for j in range(L):
            k = min(k0 + j, npts - 1)
            pts[j] = points[k, 0]
            pts[L + j] = points[k, 1]
            pts[2 * L + j] = points[k, 2]
            wsum[j] = 0.0
        _vectors_to_vertices(pts, V, E, L)
        for t in range(F.shape[0]):
            b0 = _U(F[t, 0]) * _U(4) * S
            b1 = _U(F[t, 1]) * _U(4) * S
            b2 = _U(F[t, 2]) * _U(4) * S
            _add_solid_angles(E, b0, b1, b2, wsum, L)
        for j in range(min(L, stop - k0)):
            out[k0 + j] = wsum[j]


@numba.njit(**_ROWS)
def lanes_map_kernel(
    start, stop, points, V, F, N, inv_twice_area, D, NxD, edges, edge_len, inv_4pi_len,
    face_edges, near_edge, order, z, values, jacobians, winding, flagged,
):  # pragma: no cover - compiled  # fmt: skip
    """A map ``f = sum_c z_c b_c`` (and its Jacobian) without storing the basis.

    At the points ``start <= k < stop`` (``start`` a multiple of ``LANES``; see
    :func:`vhm_viz.core.row_threads.run_rows`). The basis values and gradients of a group
    of points are contracted with the coefficients ``z`` (``n + m`` rows, 3 columns) as
    soon as they are complete, so no ``(N, n + m)`` matrices are written or read back (for
    a large cage that memory traffic costs more than the kernel's arithmetic).
    ``values[k]`` is ``f``, ``jacobians[k, i, j]`` is ``d f_i / d x_j`` (``order`` 1),
    ``winding[k]`` the sum of the vertex functions. Flagged points as in
    :func:`lanes_kernel`.
    """
    L = LANES
    n = V.shape[0]
    nm = n + F.shape[0]
    S = _S
    host = np.empty(1, dtype=np.int64)  # (np.full compiles a function of its own)
    host[0] = -1
    pts, near, E, ce, acc, accg, buf = _group_scratch(n, edges.shape[0], nm, order, L)
    fz = np.empty(3 * L)
    jz = np.empty(9 * L)
    wz = np.empty(L)
    for k0 in range(start, stop, L):
        _group_basis(
            points, k0, host, V, F, N, inv_twice_area, D, NxD, edges, edge_len,
            inv_4pi_len, face_edges, near_edge, order, pts, near, E, ce, acc, accg, buf, L,
        )  # fmt: skip
        fz[:] = 0.0
        jz[:] = 0.0
        wz[:] = 0.0
        for c in range(nm):
            cb = _U(c) * S
            for i in range(3):
                zi = z[c, i]
                ob = _U(i) * S
                for j in range(_U(L)):
                    fz[ob + j] += acc[cb + j] * zi
            if c < n:
                for j in range(_U(L)):
                    wz[j] += acc[cb + j]
            if order >= 1:
                for r in range(3):
                    gb = (_U(r) * _U(nm) + _U(c)) * S
                    for i in range(3):
                        zi = z[c, i]
                        ob = _U(3 * i + r) * S
                        for j in range(_U(L)):
                            jz[ob + j] += accg[gb + j] * zi
        for j in range(min(L, stop - k0)):
            k = k0 + j
            flagged[k] = near[j] > 0.0
            winding[k] = wz[j]
            for i in range(3):
                values[k, i] = fz[i * L + j]
            if order >= 1:
                for i in range(3):
                    for r in range(3):
                        jacobians[k, i, r] = jz[(3 * i + r) * L + j]
