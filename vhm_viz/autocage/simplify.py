"""Topology-safe quadric edge-collapse simplification (numba; numpy + heapq reference).

VTK's quadric decimation is fast but does not check the link condition, so at high
reduction it can pinch thin tubes (fingers) into non-manifold edges. :func:`simplify`
finishes the job from a moderately decimated, valid mesh: every collapse keeps the mesh a
closed 2-manifold (link condition), never flips a face, and never leaves a component with
fewer than 4 vertices.

The compiled version (default) runs the same algorithm with the same heap order as the
pure-Python reference (``backend="python"``), about 100x faster: taking a 2,000-face
offset surface to 500 faces costs ~20 ms instead of ~2 s, which makes the automatic
cage's retries cheap. The first call in a fresh environment compiles it (~15 s, cached on
disk afterwards; loading the cache costs ~0.4 s per process).
"""

from __future__ import annotations

import heapq

import numba
import numpy as np

__all__ = ["simplify"]


def _plane_quadrics(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    area = 0.5 * np.linalg.norm(n, axis=1)
    n = n / np.maximum(2 * area, 1e-300)[:, None]
    d = -np.einsum("ij,ij->i", n, V[F[:, 0]])
    p = np.concatenate([n, d[:, None]], axis=1)  # (m, 4)
    q = area[:, None, None] * p[:, :, None] * p[:, None, :]
    Q = np.zeros((len(V), 4, 4))
    for k in range(3):
        np.add.at(Q, F[:, k], q)
    return Q


def simplify(
    vertices,
    faces,
    target_faces: int,
    max_normal_turn: float = 0.2,
    outside: bool = False,
    backend: str = "numba",
):
    """Collapse edges (cheapest quadric error first) until ``target_faces`` remain.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (m, 3) int array
        A closed, consistently oriented 2-manifold.
    target_faces : int
        Stop at or below this many faces (or when no collapse is allowed).
    max_normal_turn : float
        A collapse is refused when a surrounding face's unit normal would change by a dot
        product below this value (0.2 ~ 78 degrees), or would vanish.
    outside : bool
        Only place a collapsed vertex on the outer side of the planes of all faces around
        the collapsed edge (Calderon and Boubekeur's bounding condition), so the simplified
        surface stays (locally) outside the original; moved outward along the mean normal
        when needed, refused when impossible.

    backend : {"numba", "python"}
        ``"numba"`` (compiled, default) or ``"python"`` (the reference implementation of
        the same algorithm; slow, used to test the compiled one).

    Returns
    -------
    vertices : (n', 3) float64
    faces : (m', 3) int64
    """
    if backend == "python":
        return _simplify_python(vertices, faces, target_faces, max_normal_turn, outside)
    if backend != "numba":
        raise ValueError(f"simplify: unknown backend {backend!r} (numba, python)")
    V = np.array(vertices, dtype=np.float64)
    F = np.array(faces, dtype=np.int64)
    if len(F) == 0:
        return V[:0], F.reshape(0, 3)
    Q = _plane_quadrics(V, F)
    alive = _simplify_nb(V, F, Q, int(target_faces), float(max_normal_turn), bool(outside), 16)
    F = F[alive]
    used, inv = np.unique(F, return_inverse=True)
    return V[used], inv.reshape(F.shape).astype(np.int64)


def _simplify_python(vertices, faces, target_faces, max_normal_turn, outside):
    """Reference implementation of :func:`simplify` (sets and a heap; slow)."""
    V = np.array(vertices, dtype=np.float64)
    F = np.array(faces, dtype=np.int64)
    n = len(V)
    Q = _plane_quadrics(V, F)
    alive_f = np.ones(len(F), dtype=bool)
    vf: list[set[int]] = [set() for _ in range(n)]
    for i, f in enumerate(F):
        for v in f:
            vf[int(v)].add(i)
    stamp = np.zeros(n, dtype=np.int64)
    n_faces = len(F)

    def neighbours(v):
        out = set()
        for fi in vf[v]:
            out.update(int(x) for x in F[fi])
        out.discard(v)
        return out

    def feasible(p, star, normals, offsets):
        if not outside:
            return p
        viol = offsets - normals @ p  # > 0 means p is inside that plane
        worst = viol.max()
        if worst <= 0:
            return p
        nav = normals.sum(axis=0)
        nav /= max(np.linalg.norm(nav), 1e-300)
        c = (normals @ nav).min()
        if c < 0.2:
            return None
        p2 = p + nav * (worst / c) * 1.0001
        if (offsets - normals @ p2).max() > 1e-12 * (1 + np.abs(offsets).max()):
            return None
        return p2

    def star_planes(u, v):
        star = list(vf[u] | vf[v])
        tri = V[F[star]]
        nn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nn /= np.maximum(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300)
        return star, nn, np.einsum("ij,ij->i", nn, tri[:, 0])

    def best_position(u, v):
        q = Q[u] + Q[v]
        a = q[:3, :3]
        b = -q[:3, 3]
        cands = [V[u], V[v], 0.5 * (V[u] + V[v])]
        try:
            if abs(np.linalg.det(a)) > 1e-12 * max(np.abs(a).max(), 1e-300) ** 3:
                x = np.linalg.solve(a, b)
                # keep the optimum near the edge (avoid wild positions)
                mid = 0.5 * (V[u] + V[v])
                if np.linalg.norm(x - mid) < np.linalg.norm(V[u] - V[v]):
                    cands.append(x)
        except np.linalg.LinAlgError:  # pragma: no cover
            pass
        best = None
        if outside:
            star, nn, off = star_planes(u, v)
            cands = [feasible(p, star, nn, off) for p in cands]
        for p in cands:
            if p is None:
                continue
            h = np.append(p, 1.0)
            c = float(h @ q @ h)
            if best is None or c < best[0]:
                best = (c, p)
        return best if best is not None else (np.inf, None)

    heap = []

    def push(u, v):
        if u > v:
            u, v = v, u
        c, _ = best_position(u, v)
        if np.isfinite(c):
            heapq.heappush(heap, (c, u, v, int(stamp[u]), int(stamp[v])))

    edges = set()
    for f in F:
        for k in range(3):
            a, b = int(f[k]), int(f[(k + 1) % 3])
            edges.add((min(a, b), max(a, b)))
    for a, b in edges:
        push(a, b)

    while n_faces > target_faces and heap:
        c, u, v, su, sv = heapq.heappop(heap)
        if stamp[u] != su or stamp[v] != sv:
            continue
        shared = vf[u] & vf[v]
        if len(shared) != 2:
            continue
        nu, nv = neighbours(u), neighbours(v)
        opposite = set()
        for fi in shared:
            opposite.update(int(x) for x in F[fi])
        opposite -= {u, v}
        if (nu & nv) != opposite:
            continue  # link condition
        if len(nu | nv) <= 4:
            continue  # would leave fewer than 4 vertices (a tetrahedron is the minimum)
        _, p = best_position(u, v)
        if p is None:
            continue
        # normal check on the faces that survive
        ok = True
        changed = (vf[u] | vf[v]) - shared
        for fi in changed:
            tri = F[fi]
            old = V[tri]
            new = old.copy()
            for k in range(3):
                if tri[k] == u or tri[k] == v:
                    new[k] = p
            n0 = np.cross(old[1] - old[0], old[2] - old[0])
            n1 = np.cross(new[1] - new[0], new[2] - new[0])
            l0, l1 = np.linalg.norm(n0), np.linalg.norm(n1)
            if l1 <= 1e-12 * max(l0, 1e-300) or n0 @ n1 < max_normal_turn * l0 * l1:
                ok = False
                break
        if not ok:
            continue
        # collapse v into u
        for fi in shared:
            alive_f[fi] = False
            for x in F[fi]:
                vf[int(x)].discard(fi)
        n_faces -= 2
        for fi in list(vf[v]):
            tri = F[fi]
            tri[tri == v] = u
            vf[u].add(fi)
        vf[v] = set()
        V[u] = p
        Q[u] += Q[v]
        stamp[u] += 1
        stamp[v] += 1
        for w in neighbours(u):
            push(u, w)
    F = F[alive_f]
    used, inv = np.unique(F, return_inverse=True)
    return V[used], inv.reshape(F.shape).astype(np.int64)


# ---------------------------------------------------------------------------------------
# compiled version (same algorithm, same heap order): per-vertex face lists in a growable
# table, marker arrays for the set operations, Cramer's rule for the 3x3 optimum
# ---------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _vf_remove(vf, cnt, v, f):
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
            if w != v and mark[w] != token:
                mark[w] = token
                out[k] = w
                k += 1
    return k


@numba.njit(cache=True)
def _star(vf, cnt, u, v, fmark, token, out):
    """Distinct faces around ``u`` or ``v`` (each face once); returns how many."""
    k = 0
    for x in (u, v):
        for s in range(cnt[x]):
            f = vf[x, s]
            if fmark[f] != token:
                fmark[f] = token
                out[k] = f
                k += 1
    return k


@numba.njit(cache=True)
def _cost(q, p):
    c = q[3, 3]
    for i in range(3):
        c += 2.0 * q[i, 3] * p[i]
        for j in range(3):
            c += p[i] * q[i, j] * p[j]
    return c


@numba.njit(cache=True)
def _best_position(u, v, V, F, Q, vf, cnt, outside, fmark, token, star, nn, off):
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
def _simplify_nb(V, F, Q, target_faces, max_normal_turn, outside, init_cap):
    n = V.shape[0]
    m = F.shape[0]
    cap = init_cap
    vf = np.empty((n, cap), dtype=np.int64)
    cnt = np.zeros(n, dtype=np.int64)
    for f in range(m):
        for j in range(3):
            v = F[f, j]
            if cnt[v] == cap:
                vf2 = np.empty((n, 2 * cap), dtype=np.int64)
                vf2[:, :cap] = vf
                vf = vf2
                cap *= 2
            vf[v, cnt[v]] = f
            cnt[v] += 1
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
        if k_u + k_v - common <= 4:
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
                a1 = o[1] - o[0]
                a2 = o[2] - o[0]
                b1 = w[1] - w[0]
                b2 = w[2] - w[0]
                n0 = np.array(
                    [
                        a1[1] * a2[2] - a1[2] * a2[1],
                        a1[2] * a2[0] - a1[0] * a2[2],
                        a1[0] * a2[1] - a1[1] * a2[0],
                    ]
                )
                n1 = np.array(
                    [
                        b1[1] * b2[2] - b1[2] * b2[1],
                        b1[2] * b2[0] - b1[0] * b2[2],
                        b1[0] * b2[1] - b1[1] * b2[0],
                    ]
                )
                l0 = np.sqrt((n0**2).sum())
                l1 = np.sqrt((n1**2).sum())
                if l1 <= 1e-12 * max(l0, 1e-300) or (n0 * n1).sum() < max_normal_turn * l0 * l1:
                    ok = False
                    break
        if not ok:
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
            if cnt[u] == cap:
                vf2 = np.empty((n, 2 * cap), dtype=np.int64)
                vf2[:, :cap] = vf
                vf = vf2
                cap *= 2
            vf[u, cnt[u]] = f
            cnt[u] += 1
        cnt[v] = 0
        V[u] = p
        Q[u] += Q[v]
        stamp[u] += 1
        stamp[v] += 1
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
