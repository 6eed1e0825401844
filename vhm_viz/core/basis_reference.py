"""Reference evaluation of the harmonic cage basis in plain numpy, face by face.

It follows the closed forms of the paper's Appendix A (Urago 2000) one face at a time,
with no sharing between neighbouring faces: readable, and the yardstick the tests hold
the compiled kernels (:mod:`vhm_viz.core.basis_kernel`, :mod:`vhm_viz.core.basis_lanes`)
to. Its temporaries are ``O(chunk * m)``, so points go through in chunks.
"""

from __future__ import annotations

import math

import numpy as np

from vhm_viz.core.cage_tables import CageTables
from vhm_viz.core.exact_cross import cross_exact_np

__all__ = ["NUMPY_CHUNK", "evaluate_reference"]

#: Default number of points per chunk of the reference evaluation (bounds its temporaries).
NUMPY_CHUNK = 256
_FOUR_PI = 4.0 * math.pi
_TWO_PI = 2.0 * math.pi


def evaluate_reference(p: np.ndarray, cd: CageTables, order: int, host, chunk: int) -> tuple:
    """The basis at points, chunk by chunk, in plain numpy.

    Parameters
    ----------
    p : (N, 3) float64
        Validated points.
    cd : CageTables
    order : {0, 1, 2}
    host : (N,) int64
        Host face of each point on a face, -1 elsewhere.
    chunk : int
        Points per chunk.

    Returns
    -------
    values, gradients, hessians, degenerate
        As :func:`~vhm_viz.core.basis_kernel.per_point_evaluation` returns them; the
        degenerate rows need the fix-up of :func:`vhm_viz.core.basis.evaluate_basis`.
    """
    npts = p.shape[0]
    parts = [
        _evaluate_chunk(p[s : s + chunk], cd, order, None if host is None else host[s : s + chunk])
        for s in range(0, npts, chunk)
    ] or [_evaluate_chunk(p, cd, order, None)]
    values = np.concatenate([q[0] for q in parts])
    gradients = np.concatenate([q[1] for q in parts]) if order >= 1 else None
    hessians = np.concatenate([q[2] for q in parts]) if order >= 2 else None
    degenerate = np.concatenate([q[3] for q in parts])
    return values, gradients, hessians, degenerate


def _edge_terms_numpy(u, q, lu, lq, dlen, cr):
    """``C`` and ``Ct`` of an edge with end vectors ``u``, ``q`` (cancellation-free).

    ``cr`` is ``u x q``, computed exactly (:func:`cross_exact_np`).
    """
    uq = np.einsum("...i,...i->...", u, q)
    cr2 = np.einsum("...i,...i->...", cr, cr)
    big = lu + lq + dlen
    with np.errstate(divide="ignore", invalid="ignore"):
        # when u.q <= 0 (p next to the segment) R - |d| cancels: use the exact rewrite
        # R - |d| = 2 (l_u l_q + u.q) / (R + |d|), and when u.q <= 0 the bracket itself
        # cancels: l_u l_q + u.q = |u x q|^2 / (l_u l_q - u.q). Both branches are exact.
        small = np.where(uq <= 0.0, 2.0 * cr2 / ((lu * lq - uq) * big), 2.0 * (lu * lq + uq) / big)
        on_edge = small <= 0.0
        c = np.where(on_edge, 0.0, np.log1p(2.0 * dlen / small) / (_FOUR_PI * dlen))
        ct = np.where(on_edge, 0.0, 1.0 / (_TWO_PI * big * small))
    return c, ct, on_edge


def _evaluate_chunk(p, cd: CageTables, order: int, host):
    """Values, gradients, Hessians (up to ``order``) and the degenerate mask of one chunk."""
    npts = p.shape[0]
    n, m = cd.vertices.shape[0], cd.faces.shape[0]
    x = cd.vertices[cd.faces]  # (m, 3, 3)
    e = x[None, :, :, :] - p[:, None, None, :]  # (N, m, 3, 3)
    le = np.linalg.norm(e, axis=-1)  # (N, m, 3)
    e0 = e[:, :, 0]
    dot = lambda a, b: np.einsum("...i,...i->...", a, b)  # noqa: E731
    C, Ct, Jv = [], [], []
    degenerate = np.zeros(npts, dtype=bool)
    pp = np.broadcast_to(p[:, None, :], e[:, :, 0].shape)
    for v in range(3):
        u, q = e[:, :, (v + 1) % 3], e[:, :, (v + 2) % 3]
        lu, lq = le[:, :, (v + 1) % 3], le[:, :, (v + 2) % 3]
        cr = cross_exact_np(x[None, :, (v + 1) % 3], x[None, :, (v + 2) % 3], pp)
        dlen = np.linalg.norm(cd.d[:, v], axis=-1)[None]
        c, ct, on_edge = _edge_terms_numpy(u, q, lu, lq, dlen, cr)
        degenerate |= on_edge.any(axis=1)
        C.append(c)
        Ct.append(ct)
        Jv.append(-cr)  # e_{v+2} x e_{v+1}
    near = _solid_angle_pivot(e, le, np.argmax(np.stack(C, -1), axis=-1), cd.d)
    det, denom = _solid_angle_terms(e, le, near, cd.d, np.stack(Jv, axis=2))
    w = np.arctan2(det, denom) / _TWO_PI
    in_plane = det == 0.0
    w = np.where(in_plane & (denom < 0.0), 0.5, w)  # exactly on the face: interior limit
    w = np.where(in_plane & (denom == 0.0), 0.0, w)  # on an edge/vertex: see fix-up
    h_dist = dot(e0, cd.normals[None])  # signed distance to the plane (inside > 0)
    if host is not None:
        rows = np.nonzero(host >= 0)[0]
        w[rows, host[rows]] = 0.5
        h_dist[rows, host[rows]] = 0.0

    N = cd.normals[None]  # (1, m, 3)
    P = -w[..., None] * N
    for v in range(3):
        P = P + C[v][..., None] * cd.n_cross_d[None, :, v]
    psi = -w * h_dist - sum(C[v] * dot(Jv[v], N) for v in range(3))

    import scipy.sparse as sp  # here: importing it is slow, the compiled path skips it

    nm = n + m
    values = np.zeros((npts, nm))
    values[:, n:] = psi
    incid = [
        sp.csr_matrix((np.ones(m), (np.arange(m), cd.faces[:, v])), shape=(m, n)) for v in range(3)
    ]
    inv2a = 1.0 / cd.twice_area[None]
    for v in range(3):
        values[:, :n] += (incid[v].T @ (dot(P, Jv[v]) * inv2a).T).T
    gradients = hessians = None
    if order >= 1:
        gradients = np.zeros((npts, 3, nm))
        gradients[:, :, n:] = -np.moveaxis(P, 2, 1)
        for v in range(3):
            g = np.cross(P, cd.d[None, :, v]) * inv2a[..., None]  # (N, m, 3)
            for j in range(3):
                gradients[:, j, :n] += (incid[v].T @ g[:, :, j].T).T
    if order >= 2:
        with np.errstate(divide="ignore", invalid="ignore"):
            ehat = np.where(le[..., None] > 0, e / le[..., None], 0.0)
            inv_le = np.where(le > 0, 1.0 / le, 0.0)
        grad_w = sum(
            (Ct[v] * (inv_le[:, :, (v + 1) % 3] + inv_le[:, :, (v + 2) % 3]))[..., None] * Jv[v]
            for v in range(3)
        )
        Q = sum(
            (Ct[v][..., None] * (ehat[:, :, (v + 1) % 3] + ehat[:, :, (v + 2) % 3]))[..., :, None]
            * cd.d[None, :, v][..., None, :]
            for v in range(3)
        )
        nx = _cross_matrix(cd.normals)  # (m, 3, 3)
        M = Q @ np.swapaxes(nx, -1, -2)[None] + grad_w[..., :, None] * N[..., None, :]
        hessians = np.zeros((npts, 5, nm))
        hessians[:, :, n:] = np.moveaxis(_sym5(-M), -1, 1)
        dx = _cross_matrix(cd.d.reshape(-1, 3)).reshape(m, 3, 3, 3)
        for v in range(3):
            hv = -(dx[None, :, v] @ M) * inv2a[..., None, None]
            h5 = _sym5(hv)  # (N, m, 5)
            for j in range(5):
                hessians[:, j, :n] += (incid[v].T @ h5[:, :, j].T).T
    return values, gradients, hessians, degenerate


def _solid_angle_pivot(e, le, opposite_nearest_edge, d):
    """Local vertex to write the solid angle around (see :func:`_solid_angle_terms`).

    Next to an edge's interior, pivot on the vertex opposite that edge; next to a vertex
    (closer to it than twice the distance to the nearest edge's line), pivot on the vertex
    itself, where the plain formula has no cancellation but the edge rewrite would.
    """
    a = opposite_nearest_edge
    take = lambda arr, k: np.take_along_axis(arr, k[..., None, None], axis=2)[:, :, 0]  # noqa: E731
    eb, ec = take(e, (a + 1) % 3), take(e, (a + 2) % 3)
    dlen = np.linalg.norm(take(np.broadcast_to(d[None], e.shape), a), axis=-1)
    to_line = np.linalg.norm(np.cross(eb, ec), axis=-1) / dlen
    return np.where(le.min(-1) <= 2.0 * to_line, le.argmin(-1), a)


def _solid_angle_terms(e, le, a, d, jv):
    """Numerator and denominator of the solid-angle ``atan2``, written around edge (b, c).

    ``det = e_a . (e_b x e_c)``, ``den = l_a (l_b l_c + e_b.e_c) + e_a.(l_c e_b + l_b e_c)``.
    Next to edge (b, c) both brackets cancel catastrophically; with the exact
    ``cr = e_b x e_c`` they are rewritten exactly as
    ``l_b l_c + e_b.e_c = |cr|^2 / (l_b l_c - e_b.e_c)`` and, with ``u`` the unit vector
    along the edge, ``t_b = -e_b.u``, ``t_c = e_c.u`` (the foot of ``p`` along it),
    ``l_c e_b + l_b e_c = u x cr + (l_c - t_c) e_b + (l_b - t_b) e_c`` (the triple product
    ``u x (e_b x e_c) = (u.e_c) e_b - (u.e_b) e_c``), where ``l - t = r^2 / (l + t)`` with
    ``r = |cr| / |d|`` the distance to the edge's line when ``t > 0``.
    ``a`` holds, per (point, face), the local vertex opposite the edge to write around;
    ``jv[..., v, :] = e_{v+2} x e_{v+1}`` (exact), so ``cr = -jv[..., a, :]``.
    """
    take = lambda arr, k: np.take_along_axis(arr, k[..., None, None], axis=2)[:, :, 0]  # noqa: E731
    ea, eb, ec = take(e, a), take(e, (a + 1) % 3), take(e, (a + 2) % 3)
    la = np.take_along_axis(le, a[..., None], axis=2)[..., 0]
    lb = np.take_along_axis(le, ((a + 1) % 3)[..., None], axis=2)[..., 0]
    lc = np.take_along_axis(le, ((a + 2) % 3)[..., None], axis=2)[..., 0]
    dot = lambda x, y: np.einsum("...i,...i->...", x, y)  # noqa: E731
    cr = -take(jv, a)
    det = dot(ea, cr)
    bc = dot(eb, ec)
    dv = -take(np.broadcast_to(d[None], e.shape), a)  # x_c - x_b
    with np.errstate(divide="ignore", invalid="ignore"):
        cr2 = dot(cr, cr)
        t1 = np.where(bc < 0.0, cr2 / (lb * lc - bc), lb * lc + bc)
        dl = np.sqrt(dot(dv, dv))
        u = dv / dl[..., None]
        r2 = cr2 / (dl * dl)
        tb, tc = -dot(eb, u), dot(ec, u)
        gap_b = np.where(tb > 0.0, r2 / (lb + tb), lb - tb)
        gap_c = np.where(tc > 0.0, r2 / (lc + tc), lc - tc)
    vec = np.cross(u, cr) + gap_c[..., None] * eb + gap_b[..., None] * ec
    return det, la * t1 + dot(ea, vec)


def _cross_matrix(a: np.ndarray) -> np.ndarray:
    """``[a]_x`` for a stack of vectors ``(..., 3)`` -> ``(..., 3, 3)``."""
    z = np.zeros(a.shape[:-1])
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    return np.stack(
        [np.stack([z, -az, ay], -1), np.stack([az, z, -ax], -1), np.stack([-ay, ax, z], -1)], -2
    )


def _sym5(h: np.ndarray) -> np.ndarray:
    """Five entries of the symmetric part of ``(..., 3, 3)`` matrices."""
    return np.stack(
        [
            h[..., 0, 0],
            0.5 * (h[..., 0, 1] + h[..., 1, 0]),
            0.5 * (h[..., 0, 2] + h[..., 2, 0]),
            h[..., 1, 1],
            0.5 * (h[..., 1, 2] + h[..., 2, 1]),
        ],
        axis=-1,
    )
