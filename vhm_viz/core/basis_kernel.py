"""The compiled evaluation of the harmonic cage basis, and the choice between kernels.

Two numba kernels evaluate the closed forms of the paper's Appendix A: the careful
per-point kernel here, which shares the per-vertex distances and per-edge logarithms
between neighbouring faces and handles every special position (next to or on an edge or
vertex, on a face), and the SIMD kernel of :mod:`vhm_viz.core.basis_lanes`, 16 points at a
time, for values and gradients of points away from the cage edges (nearly all points of a
shape). :func:`compiled_evaluation` sends each point to the one that applies.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.basis_lanes import ROWS_GRAIN, lanes_kernel
from vhm_viz.core.cage_tables import CageTables, kernel_arrays, read_only
from vhm_viz.core.exact_cross import cross_exact
from vhm_viz.core.row_threads import run_rows

__all__ = ["NEAR_EDGE", "compiled_evaluation", "lanes_evaluation", "per_point_evaluation"]

_GRAIN = 32  # points per chunk of run_rows at least (amortises the scratch allocations)
#: An edge counts as "near" when ``R - |d| < NEAR_EDGE |d|`` (``p`` within about 1% of its
#: length from the edge's interior): only then is the solid angle rewritten around it
#: (see :mod:`vhm_viz.core.basis_reference`), and the SIMD kernel leaves the point over.
NEAR_EDGE = 1e-4


@numba.njit(cache=True, nogil=True, fastmath=False, error_model="numpy")
def _basis_kernel(
    start,
    stop,
    points,
    V,
    F,
    N,
    inv_twice_area,
    D,
    NxD,
    edges,
    edge_len,
    inv_4pi_len,
    face_edges,
    face_edge_sign,
    host,
    order,
    values,
    gradients,
    hessians,
    degenerate,
):  # pragma: no cover - compiled
    """Basis values (and derivatives up to ``order``) of points ``start..stop``, one at a time.

    Run over ranges of points by :func:`vhm_viz.core.row_threads.run_rows`.

    Cage arrays as in :func:`~vhm_viz.core.cage_tables.kernel_arrays`, then
    ``face_edge_sign``; ``host[k]`` the face point ``k`` lies on (-1: none). Handles every
    special position: next to an edge (exact cross products, the solid angle written
    around the nearest edge or vertex), on a face (interior limit) and on an edge or
    vertex (``degenerate[k]`` set; the caller restores the values).
    """
    n = V.shape[0]
    m = F.shape[0]
    ne = edges.shape[0]
    if stop > start:
        e = np.empty((n, 3))
        le = np.empty(n)
        ecr = np.empty((ne, 3))  # e_i x e_j for edge (i, j)
        edot = np.empty(ne)  # e_i . e_j
        ec = np.empty(ne)
        ect = np.empty(ne)
        enear = np.empty(ne, dtype=np.bool_)  # p is next to this edge's interior
        jv = np.empty((3, 3))
        cv = np.empty(3)
        Q = np.empty((3, 3))
        gw = np.empty(3)
        M = np.empty((3, 3))
        for k in range(start, stop):
            px, py, pz = points[k, 0], points[k, 1], points[k, 2]
            for a in range(n):
                ex = V[a, 0] - px
                ey = V[a, 1] - py
                ez = V[a, 2] - pz
                e[a, 0] = ex
                e[a, 1] = ey
                e[a, 2] = ez
                le[a] = math.sqrt(ex * ex + ey * ey + ez * ez)
            degen = False
            for q in range(ne):
                i = edges[q, 0]
                j = edges[q, 1]
                ux, uy, uz = e[i, 0], e[i, 1], e[i, 2]
                wx, wy, wz = e[j, 0], e[j, 1], e[j, 2]
                cx = uy * wz - uz * wy
                cy = uz * wx - ux * wz
                cz = ux * wy - uy * wx
                ecr[q, 0] = cx
                ecr[q, 1] = cy
                ecr[q, 2] = cz
                uw = ux * wx + uy * wy + uz * wz
                edot[q] = uw
                dl = edge_len[q]
                big = le[i] + le[j] + dl
                if uw <= 0.0:
                    denom = (le[i] * le[j] - uw) * big
                    small = 2.0 * (cx * cx + cy * cy + cz * cz) / denom if denom > 0.0 else 0.0
                    if small < NEAR_EDGE * dl:
                        # next to the edge's interior the cross product cancels: exactly
                        cross_exact(V, i, j, px, py, pz, ecr[q])
                        cx, cy, cz = ecr[q, 0], ecr[q, 1], ecr[q, 2]
                        small = 2.0 * (cx * cx + cy * cy + cz * cz) / denom if denom > 0.0 else 0.0
                else:
                    small = 2.0 * (le[i] * le[j] + uw) / big
                enear[q] = small < NEAR_EDGE * dl
                if small <= 0.0:
                    degen = True
                    ec[q] = 0.0
                    ect[q] = 0.0
                else:
                    ec[q] = math.log1p(2.0 * dl / small) * inv_4pi_len[q]
                    ect[q] = 1.0 / (2.0 * math.pi * big * small)
            degenerate[k] = degen
            for t in range(m):
                i0 = F[t, 0]
                nx, ny, nz = N[t, 0], N[t, 1], N[t, 2]
                # Jv_v = e_{v+2} x e_{v+1} = -sign * (e_i x e_j) of the stored edge
                for v in range(3):
                    q = face_edges[t, v]
                    s = -face_edge_sign[t, v]
                    jv[v, 0] = s * ecr[q, 0]
                    jv[v, 1] = s * ecr[q, 1]
                    jv[v, 2] = s * ecr[q, 2]
                    cv[v] = ec[q]
                if not (
                    enear[face_edges[t, 0]] or enear[face_edges[t, 1]] or enear[face_edges[t, 2]]
                ):
                    # away from the edges the plain solid-angle formula is accurate
                    i1 = F[t, 1]
                    i2 = F[t, 2]
                    det = -(e[i0, 0] * jv[0, 0] + e[i0, 1] * jv[0, 1] + e[i0, 2] * jv[0, 2])
                    den = (
                        le[i0] * le[i1] * le[i2]
                        + edot[face_edges[t, 2]] * le[i2]
                        + edot[face_edges[t, 1]] * le[i1]
                        + edot[face_edges[t, 0]] * le[i0]
                    )
                else:
                    # Solid angle, written around the face's nearest edge (largest C) so that
                    # the denominator does not cancel next to that edge (see
                    # basis_reference._solid_angle_terms).
                    la = 0
                    if cv[1] > cv[la]:
                        la = 1
                    if cv[2] > cv[la]:
                        la = 2
                    # ... unless p is next to a vertex rather than an edge: pivot on that vertex
                    lmin = 0
                    if le[F[t, 1]] < le[F[t, lmin]]:
                        lmin = 1
                    if le[F[t, 2]] < le[F[t, lmin]]:
                        lmin = 2
                    qn = face_edges[t, la]
                    cn2 = ecr[qn, 0] ** 2 + ecr[qn, 1] ** 2 + ecr[qn, 2] ** 2
                    lm = le[F[t, lmin]]
                    if lm * lm * edge_len[qn] * edge_len[qn] <= 4.0 * cn2:
                        la = lmin
                    ia = F[t, la]
                    ib = F[t, (la + 1) % 3]
                    ic = F[t, (la + 2) % 3]
                    q = face_edges[t, la]
                    # det = e_a . (e_b x e_c) = -e_a . Jv_a
                    det = -(e[ia, 0] * jv[la, 0] + e[ia, 1] * jv[la, 1] + e[ia, 2] * jv[la, 2])
                    lb = le[ib]
                    lc = le[ic]
                    bc = edot[q]
                    if bc < 0.0:
                        c2 = ecr[q, 0] ** 2 + ecr[q, 1] ** 2 + ecr[q, 2] ** 2
                        t1 = c2 / (lb * lc - bc)
                    else:
                        t1 = lb * lc + bc
                    # l_c e_b + l_b e_c = u x cr + (l_c - t_c) e_b + (l_b - t_b) e_c, with u
                    # along the edge and cr = e_b x e_c = -Jv_a (see _solid_angle_terms)
                    crx, cry, crz = -jv[la, 0], -jv[la, 1], -jv[la, 2]
                    inv_dl = 1.0 / edge_len[q]
                    ux_ = -D[t, la, 0] * inv_dl  # x_c - x_b = -d_a
                    uy_ = -D[t, la, 1] * inv_dl
                    uz_ = -D[t, la, 2] * inv_dl
                    r2 = (crx * crx + cry * cry + crz * crz) * inv_dl * inv_dl
                    tb = -(e[ib, 0] * ux_ + e[ib, 1] * uy_ + e[ib, 2] * uz_)
                    tc = e[ic, 0] * ux_ + e[ic, 1] * uy_ + e[ic, 2] * uz_
                    gb = r2 / (lb + tb) if tb > 0.0 else lb - tb
                    gc = r2 / (lc + tc) if tc > 0.0 else lc - tc
                    vx = (uy_ * crz - uz_ * cry) + gc * e[ib, 0] + gb * e[ic, 0]
                    vy = (uz_ * crx - ux_ * crz) + gc * e[ib, 1] + gb * e[ic, 1]
                    vz = (ux_ * cry - uy_ * crx) + gc * e[ib, 2] + gb * e[ic, 2]
                    den = le[ia] * t1 + (e[ia, 0] * vx + e[ia, 1] * vy + e[ia, 2] * vz)
                hdist = e[i0, 0] * nx + e[i0, 1] * ny + e[i0, 2] * nz
                if host[k] == t:
                    w = 0.5
                    hdist = 0.0
                elif det == 0.0 and den <= 0.0:
                    w = 0.5 if den < 0.0 else 0.0
                else:
                    w = math.atan2(det, den) / (2.0 * math.pi)
                Px = -w * nx
                Py = -w * ny
                Pz = -w * nz
                psi = -w * hdist
                for v in range(3):
                    Px += cv[v] * NxD[t, v, 0]
                    Py += cv[v] * NxD[t, v, 1]
                    Pz += cv[v] * NxD[t, v, 2]
                    psi -= cv[v] * (jv[v, 0] * nx + jv[v, 1] * ny + jv[v, 2] * nz)
                values[k, n + t] = psi
                inv2a = inv_twice_area[t]
                for v in range(3):
                    col = F[t, v]
                    values[k, col] += (Px * jv[v, 0] + Py * jv[v, 1] + Pz * jv[v, 2]) * inv2a
                if order >= 1:
                    gradients[k, 0, n + t] = -Px
                    gradients[k, 1, n + t] = -Py
                    gradients[k, 2, n + t] = -Pz
                    for v in range(3):
                        col = F[t, v]
                        dx, dy, dz = D[t, v, 0], D[t, v, 1], D[t, v, 2]
                        gradients[k, 0, col] += (Py * dz - Pz * dy) * inv2a
                        gradients[k, 1, col] += (Pz * dx - Px * dz) * inv2a
                        gradients[k, 2, col] += (Px * dy - Py * dx) * inv2a
                if order >= 2:
                    # Q = sum_v Ct_v (e^_{v+1} + e^_{v+2}) d_v^T ;  grad w = sum_v Ct_v (..) Jv_v
                    Q[:, :] = 0.0
                    gw[:] = 0.0
                    for v in range(3):
                        q = face_edges[t, v]
                        ct = ect[q]
                        a1 = F[t, (v + 1) % 3]
                        a2 = F[t, (v + 2) % 3]
                        r1 = 1.0 / le[a1] if le[a1] > 0.0 else 0.0
                        r2 = 1.0 / le[a2] if le[a2] > 0.0 else 0.0
                        for r in range(3):
                            h = ct * (e[a1, r] * r1 + e[a2, r] * r2)
                            for c in range(3):
                                Q[r, c] += h * D[t, v, c]
                            gw[r] += ct * (r1 + r2) * jv[v, r]
                    # M = Q [N]_x^T + grad_w N^T ;  [N]_x^T = -[N]_x
                    for r in range(3):
                        q0, q1, q2 = Q[r, 0], Q[r, 1], Q[r, 2]
                        M[r, 0] = -(q1 * nz - q2 * ny) + gw[r] * nx
                        M[r, 1] = -(q2 * nx - q0 * nz) + gw[r] * ny
                        M[r, 2] = -(q0 * ny - q1 * nx) + gw[r] * nz
                    hessians[k, 0, n + t] = -M[0, 0]
                    hessians[k, 1, n + t] = -0.5 * (M[0, 1] + M[1, 0])
                    hessians[k, 2, n + t] = -0.5 * (M[0, 2] + M[2, 0])
                    hessians[k, 3, n + t] = -M[1, 1]
                    hessians[k, 4, n + t] = -0.5 * (M[1, 2] + M[2, 1])
                    for v in range(3):
                        col = F[t, v]
                        dx, dy, dz = D[t, v, 0], D[t, v, 1], D[t, v, 2]
                        # -[d]_x M / 2A: rows of [d]_x are (0,-dz,dy), (dz,0,-dx), (-dy,dx,0)
                        h00 = -(-dz * M[1, 0] + dy * M[2, 0])
                        h01 = -(-dz * M[1, 1] + dy * M[2, 1])
                        h02 = -(-dz * M[1, 2] + dy * M[2, 2])
                        h10 = -(dz * M[0, 0] - dx * M[2, 0])
                        h11 = -(dz * M[0, 1] - dx * M[2, 1])
                        h12 = -(dz * M[0, 2] - dx * M[2, 2])
                        h20 = -(-dy * M[0, 0] + dx * M[1, 0])
                        h21 = -(-dy * M[0, 1] + dx * M[1, 1])
                        hessians[k, 0, col] += h00 * inv2a
                        hessians[k, 1, col] += 0.5 * (h01 + h10) * inv2a
                        hessians[k, 2, col] += 0.5 * (h02 + h20) * inv2a
                        hessians[k, 3, col] += h11 * inv2a
                        hessians[k, 4, col] += 0.5 * (h12 + h21) * inv2a


def per_point_evaluation(p: np.ndarray, cd: CageTables, order: int, host: np.ndarray) -> tuple:
    """The basis at points through the per-point kernel (every special position handled).

    Parameters
    ----------
    p : (N, 3) float64
    cd : CageTables
    order : {0, 1, 2}
    host : (N,) int64
        Host face of each point on a face, -1 elsewhere.

    Returns
    -------
    values : (N, n + m) float64
    gradients : (N, 3, n + m) float64 or None
    hessians : (N, 5, n + m) float64 or None
    degenerate : (N,) bool
        Points exactly on a cage edge or vertex.
    """
    npts = p.shape[0]
    nm = cd.vertices.shape[0] + cd.faces.shape[0]
    values = np.zeros((npts, nm))
    gradients = np.zeros((npts, 3, nm)) if order >= 1 else np.zeros((0, 3, 0))
    hessians = np.zeros((npts, 5, nm)) if order >= 2 else np.zeros((0, 5, 0))
    degenerate = np.zeros(npts, dtype=np.bool_)
    if npts:
        # the per-point kernel takes face_edge_sign after face_edges
        run_rows(
            _basis_kernel,
            npts,
            read_only(p),
            *kernel_arrays(cd),
            cd.face_edge_sign,
            host,
            order,
            values,
            gradients,
            hessians,
            degenerate,
            grain=_GRAIN,
        )
    return (
        values,
        gradients if order >= 1 else None,
        hessians if order >= 2 else None,
        degenerate,
    )


def lanes_evaluation(p: np.ndarray, cd: CageTables, order: int, host: np.ndarray) -> tuple:
    """Values (and gradients) through the SIMD kernel, and the points it leaves over.

    Parameters
    ----------
    p : (N, 3) float64
    cd : CageTables
    order : {0, 1}
    host : (N,) int64
        Host face of each point on a face, -1 elsewhere (such points are left over).

    Returns
    -------
    values : (N, n + m) float64
    gradients : (N, 3, n + m) float64 or None
    flagged : (N,) bool
        Points near or on a cage edge or vertex, or with a host face: their rows hold
        placeholders, for :func:`per_point_evaluation` to redo.
    """
    npts = p.shape[0]
    nm = cd.vertices.shape[0] + cd.faces.shape[0]
    # every row is written (flagged ones with placeholders): no need to zero the output
    values = np.empty((npts, nm))
    gradients = np.empty((npts, 3, nm)) if order >= 1 else np.zeros((0, 3, 0))
    flagged = np.zeros(npts, dtype=np.bool_)
    if npts:
        run_rows(
            lanes_kernel,
            npts,
            read_only(p),
            *kernel_arrays(cd),
            host,
            NEAR_EDGE,
            order,
            values,
            gradients,
            flagged,
            grain=ROWS_GRAIN,
        )
    return values, (gradients if order >= 1 else None), flagged


def compiled_evaluation(p: np.ndarray, cd: CageTables, order: int, host: np.ndarray) -> tuple:
    """The basis through the compiled kernels: the SIMD one where it applies.

    Values and gradients of points away from the cage edges come from
    :func:`lanes_evaluation`; the points it flags, and every point when Hessians are
    asked for, go through :func:`per_point_evaluation`. Arguments and results as in
    :func:`per_point_evaluation`.
    """
    if order >= 2 or not p.shape[0]:
        return per_point_evaluation(p, cd, order, host)
    values, gradients, flagged = lanes_evaluation(p, cd, order, host)
    degenerate = np.zeros(p.shape[0], dtype=np.bool_)
    rows = np.nonzero(flagged)[0]
    if rows.size:
        sub = per_point_evaluation(p[rows], cd, order, host[rows])
        values[rows] = sub[0]
        if order >= 1:
            gradients[rows] = sub[1]
        degenerate[rows] = sub[3]
    return values, gradients, None, degenerate
