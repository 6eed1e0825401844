"""The compiled edge-collapse loop of :func:`vhm_viz.autocage.simplify.simplify`.

Cheapest quadric error first (a binary heap of ``(cost, u, v, stamp_u, stamp_v)``; an
entry whose stamps are stale is skipped), each collapse checked for the link condition,
the component's size, the normal turn of the surviving faces and, when asked, contacts
(:mod:`vhm_viz.autocage.collapse_guard`). The same algorithm, in the same heap order, as
the Python reference :mod:`vhm_viz.autocage.edge_collapse_reference`: per-vertex face
lists in a growable table, marker arrays for the set operations, Cramer's rule for the
3x3 optimum.
"""

from __future__ import annotations

import heapq

import numba
import numpy as np

from vhm_viz.autocage.collapse_guard import (
    collapse_blocked,
    make_face_grid,
    register_face,
    take_once,
    turns_too_far,
)

__all__ = ["collapse_edges"]


@numba.njit(cache=True)
def _vf_append(vf, cnt, v, f):
    """Add face ``f`` to vertex ``v``'s list; returns the table (doubled when full)."""
    cap = vf.shape[1]
    if cnt[v] == cap:
        vf2 = np.empty((vf.shape[0], 2 * cap), dtype=np.int64)
        vf2[:, :cap] = vf
        vf = vf2
    vf[v, cnt[v]] = f
    cnt[v] += 1
    return vf


@numba.njit(cache=True)
def _vf_remove(vf, cnt, v, f):
    """Remove face ``f`` from vertex ``v``'s list (order not kept)."""
    for s in range(cnt[v]):
        if vf[v, s] == f:
            cnt[v] -= 1
            vf[v, s] = vf[v, cnt[v]]
            return


@numba.njit(cache=True)
def _gather_vertices(vf, cnt, F, v, mark, token, out):
    """Neighbours of ``v`` (distinct vertices of its faces, ``v`` excluded); how many."""
    k = 0
    for s in range(cnt[v]):
        f = vf[v, s]
        for j in range(3):
            w = F[f, j]
            if w != v:
                k = take_once(w, mark, token, out, k)
    return k


@numba.njit(cache=True)
def _star(vf, cnt, u, v, fmark, token, out):
    """Distinct faces around ``u`` or ``v`` (each face once); returns how many."""
    k = 0
    for x in (u, v):
        for s in range(cnt[x]):
            k = take_once(vf[x, s], fmark, token, out, k)
    return k


@numba.njit(cache=True)
def _cost(q, p):
    """Quadric error ``[p, 1] @ q @ [p, 1]`` of position ``p``."""
    c = q[3, 3]
    for i in range(3):
        c += 2.0 * q[i, 3] * p[i]
        for j in range(3):
            c += p[i] * q[i, j] * p[j]
    return c


@numba.njit(cache=True)
def _best_position(u, v, V, F, Q, vf, cnt, outside, fmark, token, star, nn, off):
    """Cheapest allowed position of the collapsed edge ``(u, v)`` and its quadric error.

    Candidates: both ends, the midpoint and the quadric optimum (when it lies near the
    edge); with ``outside`` each is moved outside the planes around the edge or dropped.
    Returns ``(inf, any point)`` when none is allowed.
    """
    q = Q[u] + Q[v]
    a = q[:3, :3]
    det = (
        a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
        - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    )
    cands = np.empty((4, 3))
    cands[0] = V[u]
    cands[1] = V[v]
    cands[2] = 0.5 * (V[u] + V[v])
    nc = 3
    amax = max(np.abs(a).max(), 1e-300)
    if abs(det) > 1e-12 * amax**3:
        b = -q[:3, 3]
        x = np.empty(3)
        for c in range(3):
            m = a.copy()
            m[:, c] = b
            x[c] = (
                m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
                - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
                + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
            ) / det
        if np.sqrt(((x - cands[2]) ** 2).sum()) < np.sqrt(((V[u] - V[v]) ** 2).sum()):
            cands[3] = x
            nc = 4
    ok = np.ones(4, dtype=np.bool_)
    if outside:
        ns = _star(vf, cnt, u, v, fmark, token, star)
        nav = np.zeros(3)
        for s in range(ns):
            f = star[s]
            p0 = V[F[f, 0]]
            e1 = V[F[f, 1]] - p0
            e2 = V[F[f, 2]] - p0
            n0 = e1[1] * e2[2] - e1[2] * e2[1]
            n1 = e1[2] * e2[0] - e1[0] * e2[2]
            n2 = e1[0] * e2[1] - e1[1] * e2[0]
            ln = max(np.sqrt(n0 * n0 + n1 * n1 + n2 * n2), 1e-300)
            nn[s, 0], nn[s, 1], nn[s, 2] = n0 / ln, n1 / ln, n2 / ln
            off[s] = nn[s, 0] * p0[0] + nn[s, 1] * p0[1] + nn[s, 2] * p0[2]
            nav += nn[s]
        nav /= max(np.sqrt((nav**2).sum()), 1e-300)
        cmin = np.inf
        offmax = 0.0
        for s in range(ns):
            cmin = min(cmin, nn[s, 0] * nav[0] + nn[s, 1] * nav[1] + nn[s, 2] * nav[2])
            offmax = max(offmax, abs(off[s]))
        tol = 1e-12 * (1 + offmax)
        for i in range(nc):
            p = cands[i]
            worst = -np.inf
            for s in range(ns):
                worst = max(worst, off[s] - (nn[s, 0] * p[0] + nn[s, 1] * p[1] + nn[s, 2] * p[2]))
            if worst <= 0:
                continue
            if cmin < 0.2:
                ok[i] = False
                continue
            p2 = p + nav * (worst / cmin) * 1.0001
            worst2 = -np.inf
            for s in range(ns):
                worst2 = max(
                    worst2, off[s] - (nn[s, 0] * p2[0] + nn[s, 1] * p2[1] + nn[s, 2] * p2[2])
                )
            if worst2 > tol:
                ok[i] = False
            else:
                cands[i] = p2
    best = np.inf
    bi = -1
    for i in range(nc):
        if ok[i]:
            c = _cost(q, cands[i])
            if bi < 0 or c < best:
                best = c
                bi = i
    if bi < 0:
        return np.inf, cands[0]
    return best, cands[bi].copy()


@numba.njit(cache=True)
def collapse_edges(
    V, F, Q, target_faces, max_normal_turn, outside, init_cap, tol, comp, comp_size, min_verts
):
    """Collapse edges of ``(V, F)`` in place until ``target_faces`` remain or none may go.

    Parameters
    ----------
    V : (n, 3) float64
        Vertices, moved in place.
    F : (m, 3) int64
        Faces (closed, consistently oriented 2-manifold), renumbered in place.
    Q : (n, 4, 4) float64
        Plane quadrics of the vertices, summed in place.
    target_faces : int
    max_normal_turn : float
        Smallest allowed dot product of a surviving face's old and new unit normals.
    outside : bool
        Keep collapsed vertices on the outer side of the planes around the edge.
    init_cap : int
        Initial width of the per-vertex face table (it doubles when full).
    tol : float
        Contact distance of the collapse guard; negative: no guard.
    comp : (n,) int64
        Connected component of every vertex.
    comp_size : (k,) int64
        Vertices of every component, decremented in place.
    min_verts : int
        No component is collapsed below this many vertices.

    Returns
    -------
    alive : (m,) bool
        The faces that remain.
    """
    n = V.shape[0]
    m = F.shape[0]
    vf = np.empty((n, init_cap), dtype=np.int64)
    cnt = np.zeros(n, dtype=np.int64)
    for f in range(m):
        for j in range(3):
            vf = _vf_append(vf, cnt, F[f, j], f)
    alive = np.ones(m, dtype=np.bool_)
    stamp = np.zeros(n, dtype=np.int64)
    mark = np.zeros(n, dtype=np.int64)
    fmark = np.zeros(m, dtype=np.int64)
    token = 0
    nbr_u = np.empty(n, dtype=np.int64)
    nbr_v = np.empty(n, dtype=np.int64)
    star = np.empty(m, dtype=np.int64)
    nn = np.empty((m, 3))
    off = np.empty(m)
    visit = np.zeros(m + 1, dtype=np.int64)
    grid = make_face_grid(V, F, max(tol, 0.0), tol >= 0)
    heap = [(0.0, 0, 0, 0, 0)]
    heap.pop()
    # initial edges (each once: from the face where a < b is walked)
    for f in range(m):
        for j in range(3):
            a = F[f, j]
            b = F[f, (j + 1) % 3]
            if a < b:
                token += 1
                c, _p = _best_position(a, b, V, F, Q, vf, cnt, outside, fmark, token, star, nn, off)
                if np.isfinite(c):
                    heapq.heappush(heap, (c, a, b, stamp[a], stamp[b]))
    n_faces = m
    shared = np.empty(2, dtype=np.int64)
    while n_faces > target_faces and len(heap) > 0:
        c, u, v, su, sv = heapq.heappop(heap)
        if stamp[u] != su or stamp[v] != sv:
            continue
        # shared faces
        ns = 0
        for s in range(cnt[u]):
            f = vf[u, s]
            if F[f, 0] == v or F[f, 1] == v or F[f, 2] == v:
                if ns < 2:
                    shared[ns] = f
                ns += 1
        if ns != 2:
            continue
        token += 1
        k_u = _gather_vertices(vf, cnt, F, u, mark, token, nbr_u)
        token += 1
        k_v = _gather_vertices(vf, cnt, F, v, mark, token, nbr_v)
        # link condition: common neighbours == the two opposite vertices
        token += 1
        for i in range(k_u):
            mark[nbr_u[i]] = token
        common = 0
        for i in range(k_v):
            if mark[nbr_v[i]] == token:
                common += 1
        n_opp = 0
        link_ok = True
        for t in range(2):
            f = shared[t]
            for j in range(3):
                w = F[f, j]
                if w != u and w != v:
                    n_opp += 1
                    if mark[w] != token:
                        link_ok = False
        if not link_ok or common != 2 or n_opp != 2:
            continue
        # opposite vertices must differ (two shared faces with the same apex)
        o0 = -1
        o1 = -1
        for j in range(3):
            if F[shared[0], j] != u and F[shared[0], j] != v:
                o0 = F[shared[0], j]
            if F[shared[1], j] != u and F[shared[1], j] != v:
                o1 = F[shared[1], j]
        if o0 == o1:
            continue
        if k_u + k_v - common <= 4 or comp_size[comp[u]] <= min_verts:
            continue
        token += 1
        cp, p = _best_position(u, v, V, F, Q, vf, cnt, outside, fmark, token, star, nn, off)
        if not np.isfinite(cp):
            continue
        # normal check on the faces that survive
        ok = True
        for x in (u, v):
            if not ok:
                break
            for s in range(cnt[x]):
                f = vf[x, s]
                if f == shared[0] or f == shared[1]:
                    continue
                o = np.empty((3, 3))
                w = np.empty((3, 3))
                for j in range(3):
                    o[j] = V[F[f, j]]
                    w[j] = p if (F[f, j] == u or F[f, j] == v) else o[j]
                if turns_too_far(o, w, max_normal_turn):
                    ok = False
                    break
        if not ok:
            continue
        if tol >= 0 and collapse_blocked(V, F, alive, u, v, p, tol, comp, grid, visit):
            continue
        # collapse v into u
        for t in range(2):
            f = shared[t]
            alive[f] = False
            for j in range(3):
                _vf_remove(vf, cnt, F[f, j], f)
        n_faces -= 2
        for s in range(cnt[v]):
            f = vf[v, s]
            for j in range(3):
                if F[f, j] == v:
                    F[f, j] = u
            vf = _vf_append(vf, cnt, u, f)
        cnt[v] = 0
        V[u] = p
        Q[u] += Q[v]
        stamp[u] += 1
        stamp[v] += 1
        comp_size[comp[u]] -= 1
        if tol >= 0:
            for s in range(cnt[u]):  # the faces around u moved: register their new boxes
                register_face(grid, V, F, vf[u, s], tol)
        token += 1
        k = _gather_vertices(vf, cnt, F, u, mark, token, nbr_u)
        for i in range(k):
            w = nbr_u[i]
            a, b = (u, w) if u < w else (w, u)
            token += 1
            c, _p = _best_position(a, b, V, F, Q, vf, cnt, outside, fmark, token, star, nn, off)
            if np.isfinite(c):
                heapq.heappush(heap, (c, a, b, stamp[a], stamp[b]))
    return alive
