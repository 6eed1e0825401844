"""The pure-Python reference of the edge-collapse loop (sets and a heap; slow).

The same algorithm as the compiled :func:`vhm_viz.autocage.edge_collapse.collapse_edges`,
written with Python sets and :mod:`heapq` so that it can be read and used to test the
compiled loop (``simplify(..., backend="python")``): the same heap order gives the same
mesh.
"""

from __future__ import annotations

import heapq

import numpy as np

from vhm_viz.autocage.collapse_guard import collapse_blocked, empty_face_grid, turns_too_far

__all__ = ["collapse_edges_reference"]


def collapse_edges_reference(
    V, F, Q, target_faces, max_normal_turn, outside, tol, comp, comp_size, min_verts
):
    """Collapse edges of ``(V, F)`` in place, as the compiled loop does.

    The arguments and result of :func:`vhm_viz.autocage.edge_collapse.collapse_edges`,
    without ``init_cap``.

    Returns
    -------
    alive : (m,) bool
        The faces that remain.
    """
    no_grid = empty_face_grid()
    visit = np.zeros(len(F) + 1, dtype=np.int64)
    n = len(V)
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
        if len(nu | nv) <= 4 or comp_size[comp[u]] <= min_verts:
            continue  # would leave fewer than 4 vertices (a tetrahedron is the minimum)
        _, p = best_position(u, v)
        if p is None:
            continue
        # normal check on the faces that survive
        changed = (vf[u] | vf[v]) - shared
        if any(
            turns_too_far(V[F[fi]], _moved_corners(V, F[fi], u, v, p), max_normal_turn)
            for fi in changed
        ):
            continue
        if tol >= 0 and collapse_blocked(V, F, alive_f, u, v, p, tol, comp, no_grid, visit):
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
        comp_size[comp[u]] -= 1
        for w in neighbours(u):
            push(u, w)
    return alive_f


def _moved_corners(V, tri, u, v, p):
    """(3, 3) corners of triangle ``tri`` with its corners ``u`` and ``v`` moved to ``p``."""
    corners = V[tri]
    corners[(tri == u) | (tri == v)] = p
    return corners
