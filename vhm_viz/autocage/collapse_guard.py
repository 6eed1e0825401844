"""Compiled guards that refuse a collapse making faces touch or swallowing a shell.

:func:`collapse_blocked` answers for one collapse of edge ``(u, v)`` to a point ``p``:
a moved face touching another face (the contact test of
:func:`vhm_viz.core.cage.self_intersections`: separating axes, with a tolerance), or the
region the moving faces sweep holding a vertex of another connected component (a shell
swallowed whole, which no contact reveals). Candidate faces come from a uniform grid of
face boxes (:func:`make_face_grid`), updated as faces move (:func:`register_face`).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "collapse_blocked",
    "empty_face_grid",
    "make_face_grid",
    "register_face",
    "take_once",
    "turns_too_far",
]


@numba.njit(cache=True)
def take_once(item, mark, token, out, n):
    """Append ``item`` as ``out[n]`` unless ``mark[item]`` already holds ``token``.

    The set operations of the compiled loops: a marker array (one int per item) and a
    running token make "distinct items" a pass with no clearing. Returns the new count.
    """
    if mark[item] == token:
        return n
    mark[item] = token
    out[n] = item
    return n + 1


@numba.njit(cache=True)
def _face_normal(t):
    """Unnormalized normal ``(t1 - t0) x (t2 - t0)`` of the triangle ``t`` (3, 3)."""
    a1 = t[1] - t[0]
    a2 = t[2] - t[0]
    return np.array(
        [
            a1[1] * a2[2] - a1[2] * a2[1],
            a1[2] * a2[0] - a1[0] * a2[2],
            a1[0] * a2[1] - a1[1] * a2[0],
        ]
    )


@numba.njit(cache=True)
def turns_too_far(old, new, max_normal_turn):
    """Whether a face moved from corners ``old`` to ``new`` ((3, 3) each) turns too far.

    It does when the moved face degenerates (its normal shrinks below ``1e-12`` of the
    old one) or the cosine of the angle between the two normals falls below
    ``max_normal_turn``.
    """
    n0 = _face_normal(old)
    n1 = _face_normal(new)
    l0 = np.sqrt((n0**2).sum())
    l1 = np.sqrt((n1**2).sum())
    return l1 <= 1e-12 * max(l0, 1e-300) or (n0 * n1).sum() < max_normal_turn * l0 * l1


@numba.njit(cache=True)
def _tri_touch(t1, t2, tol):
    """Whether triangles ``t1``, ``t2`` ((3, 3) each) intersect or come within ``tol``.

    The separating-axis test of :func:`vhm_viz.core.self_intersection.self_intersections`
    (normals, edge cross products, in-plane edge normals); a segment is the triangle
    ``(a, b, b)``.
    """
    o = t1[0].copy()
    a = t1 - o
    b = t2 - o
    ea = np.empty((3, 3))
    eb = np.empty((3, 3))
    for i in range(3):
        ea[i] = a[(i + 1) % 3] - a[i]
        eb[i] = b[(i + 1) % 3] - b[i]
    na = np.cross(ea[0], ea[1])
    nb = np.cross(eb[0], eb[1])
    # quick rejection (most candidates): one triangle strictly on one side of the other's
    # plane
    for n_, x, y in ((na, b, a), (nb, a, b)):
        ln = np.sqrt((n_**2).sum())
        if ln == 0.0:
            continue
        d0 = ((x[0] - y[0]) * n_).sum() / ln
        d1 = ((x[1] - y[0]) * n_).sum() / ln
        d2 = ((x[2] - y[0]) * n_).sum() / ln
        if (d0 > tol and d1 > tol and d2 > tol) or (d0 < -tol and d1 < -tol and d2 < -tol):
            return False
    axes = np.empty((23, 3))
    axes[0] = na
    axes[1] = nb
    k = 2
    for i in range(3):
        for j in range(3):
            axes[k] = np.cross(ea[i], eb[j])
            k += 1
    for i in range(3):
        axes[k] = np.cross(na, ea[i])
        axes[k + 1] = np.cross(na, eb[i])
        axes[k + 2] = np.cross(nb, ea[i])
        axes[k + 3] = np.cross(nb, eb[i])
        k += 4
    for i in range(23):
        ln = np.sqrt((axes[i] ** 2).sum())
        if ln == 0.0:
            continue
        ax = axes[i] / ln
        pa0 = np.inf
        pa1 = -np.inf
        pb0 = np.inf
        pb1 = -np.inf
        for v in range(3):
            x = (a[v] * ax).sum()
            pa0 = min(pa0, x)
            pa1 = max(pa1, x)
            y = (b[v] * ax).sum()
            pb0 = min(pb0, y)
            pb1 = max(pb1, y)
        if pa1 < pb0 - tol or pb1 < pa0 - tol:
            return False
    return True


@numba.njit(cache=True)
def _faces_clash(ta, ia, tb, ib, tol):
    """Improper contact of two faces (corners ``ta``/``tb``, vertex ids ``ia``/``ib``).

    As :func:`vhm_viz.core.cage.self_intersections`: no shared vertex -- any contact; one
    shared vertex -- the edge opposite it in either face meets the other face; a shared
    edge -- the faces fold onto each other (coplanar, on the same side of the edge).
    """
    shared = 0
    sa = -1
    sb = -1
    for i in range(3):
        for j in range(3):
            if ia[i] == ib[j]:
                shared += 1
                sa = i
                sb = j
    if shared == 0:
        return _tri_touch(ta, tb, tol)
    if shared == 1:
        seg = np.empty((3, 3))
        seg[0] = ta[(sa + 1) % 3]
        seg[1] = ta[(sa + 2) % 3]
        seg[2] = ta[(sa + 2) % 3]
        if _tri_touch(seg, tb, tol):
            return True
        seg[0] = tb[(sb + 1) % 3]
        seg[1] = tb[(sb + 2) % 3]
        seg[2] = tb[(sb + 2) % 3]
        return _tri_touch(seg, ta, tol)
    if shared == 2:
        na = np.cross(ta[1] - ta[0], ta[2] - ta[0])
        nb = np.cross(tb[1] - tb[0], tb[2] - tb[0])
        la = np.sqrt((na**2).sum())
        lb = np.sqrt((nb**2).sum())
        if la == 0.0 or lb == 0.0:
            return True
        na /= la
        nb /= lb
        if (na * nb).sum() >= 0.0:
            return False
        for j in range(3):
            if ib[j] != ia[0] and ib[j] != ia[1] and ib[j] != ia[2]:
                if abs(((tb[j] - ta[0]) * na).sum()) <= tol:
                    return True
        for i in range(3):
            if ia[i] != ib[0] and ia[i] != ib[1] and ia[i] != ib[2]:
                if abs(((ta[i] - tb[0]) * nb).sum()) <= tol:
                    return True
        return False
    return True


@numba.njit(cache=True)
def _clashes_with(V, F, alive, u, v, ta, ia, lo, hi, g, tol):
    """Whether moved face ``ta`` (ids ``ia``, box ``lo``-``hi``) touches live face ``g``."""
    if not alive[g]:
        return False
    for j in range(3):
        if F[g, j] == u or F[g, j] == v:
            return False  # moves too: the normal check's job
    tb = np.empty((3, 3))
    for j in range(3):
        tb[j] = V[F[g, j]]
    for k in range(3):
        if max(tb[0, k], tb[1, k], tb[2, k]) < lo[k] or min(tb[0, k], tb[1, k], tb[2, k]) > hi[k]:
            return False
    return _faces_clash(ta, ia, tb, F[g], tol)


@numba.njit(cache=True)
def _grid_cells(origin, cs, dims, lo, hi):
    """Index ranges (i0, i1, j0, j1, k0, k1) of the grid cells a box overlaps."""
    r = np.empty(6, dtype=np.int64)
    for k in range(3):
        r[2 * k] = min(max(int(np.floor((lo[k] - origin[k]) / cs)), 0), dims[k] - 1)
        r[2 * k + 1] = min(max(int(np.floor((hi[k] - origin[k]) / cs)), 0), dims[k] - 1)
    return r


@numba.njit(cache=True)
def _face_box(V, F, f, tol):
    lo = np.empty(3)
    hi = np.empty(3)
    for k in range(3):
        a, b, c = V[F[f, 0], k], V[F[f, 1], k], V[F[f, 2], k]
        lo[k] = min(a, b, c) - tol
        hi[k] = max(a, b, c) + tol
    return lo, hi


@numba.njit(cache=True)
def _grid_insert(grid, f, lo, hi):
    """Register face ``f`` in the cells its box overlaps (append-only cell lists).

    ``grid = (head, nxt, entry_face, state, origin, cs, dims)``; ``state[0]`` counts the
    entries, ``state[1]`` becomes 1 when they run out (callers then go brute force).
    """
    head, nxt, entry_face, state, origin, cs, dims = grid
    r = _grid_cells(origin, cs, dims, lo, hi)
    for i in range(r[0], r[1] + 1):
        for j in range(r[2], r[3] + 1):
            for k in range(r[4], r[5] + 1):
                e = state[0]
                if e >= len(nxt):
                    state[1] = 1
                    return
                c = (i * dims[1] + j) * dims[2] + k
                entry_face[e] = f
                nxt[e] = head[c]
                head[c] = e
                state[0] = e + 1


@numba.njit(cache=True)
def register_face(grid, V, F, f, tol):
    """Register face ``f`` at its current position (its box grown by ``tol``) in ``grid``."""
    flo, fhi = _face_box(V, F, f, tol)
    _grid_insert(grid, f, flo, fhi)


@numba.njit(cache=True)
def make_face_grid(V, F, tol, enabled):
    """A uniform grid over the mesh (about 32 cells along its longest side), faces in.

    Empty (no cells) unless ``enabled``.
    """
    lo = np.empty(3)
    hi = np.empty(3)
    for k in range(3):
        lo[k] = V[:, k].min() - tol
        hi[k] = V[:, k].max() + tol
    cs = max((hi - lo).max() / 32.0, 1e-300)
    dims = np.empty(3, dtype=np.int64)
    for k in range(3):
        dims[k] = max(1, int(np.ceil((hi[k] - lo[k]) / cs)) + 1)
    m = F.shape[0] if enabled else 0
    cap = 256 * m + 4096 if enabled else 0
    grid = (
        np.full(dims[0] * dims[1] * dims[2] if enabled else 0, -1, dtype=np.int64),
        np.empty(cap, dtype=np.int64),
        np.empty(cap, dtype=np.int64),
        np.zeros(2, dtype=np.int64),
        lo,
        cs,
        dims,
    )
    for f in range(m):
        register_face(grid, V, F, f, tol)
    return grid


@numba.njit(cache=True)
def _candidates(grid, visit, m, lo, hi, out):
    """Faces whose registered boxes meet the box ``lo``-``hi``, each once, into ``out``.

    All ``m`` faces when the grid is empty or ran out of entries. Returns how many.
    ``visit`` (one int per face, ``visit[-1]`` the running token) marks the faces taken.
    """
    head, nxt, entry_face, state, origin, cs, dims = grid
    if head.size == 0 or state[1] != 0:
        for g in range(m):
            out[g] = g
        return m
    visit[-1] += 1
    token = visit[-1]
    n = 0
    r = _grid_cells(origin, cs, dims, lo, hi)
    for i in range(r[0], r[1] + 1):
        for j in range(r[2], r[3] + 1):
            for k in range(r[4], r[5] + 1):
                e = head[(i * dims[1] + j) * dims[2] + k]
                while e >= 0:
                    g = entry_face[e]
                    e = nxt[e]
                    n = take_once(g, visit, token, out, n)
    return n


@numba.njit(cache=True)
def _collapse_clashes(V, F, alive, u, v, p, tol, grid, visit):
    """Whether collapsing edge ``(u, v)`` to ``p`` makes a moved face touch another face.

    Candidates come from :func:`_candidates` (the face grid of :func:`make_face_grid`); a
    bounding-box test comes first. Faces around ``u`` or ``v`` are compared with the
    others only (their mutual folds are the normal check's job).
    """
    m = F.shape[0]
    cand = np.empty(m, dtype=np.int64)
    ta = np.empty((3, 3))
    ia = np.empty(3, dtype=np.int64)
    lo = np.empty(3)
    hi = np.empty(3)
    for f in range(m):
        if not alive[f]:
            continue
        collapsed = 0
        for j in range(3):
            w = F[f, j]
            if w == u or w == v:
                ta[j] = p
                ia[j] = u
                collapsed += 1
            else:
                ta[j] = V[w]
                ia[j] = w
        if collapsed != 1:
            continue  # untouched, or one of the two faces that disappear
        for k in range(3):
            lo[k] = min(ta[0, k], ta[1, k], ta[2, k]) - tol
            hi[k] = max(ta[0, k], ta[1, k], ta[2, k]) + tol
        n = _candidates(grid, visit, m, lo, hi, cand)
        for c in range(n):
            g = cand[c]
            if g != f and _clashes_with(V, F, alive, u, v, ta, ia, lo, hi, g, tol):
                return True
    return False


@numba.njit(cache=True)
def _in_tet(x, a, b, c, d):
    """Whether point ``x`` lies strictly inside tetrahedron ``abcd`` (any orientation)."""
    vol = np.dot(np.cross(b - a, c - a), d - a)
    if vol == 0.0:
        return False
    s = 1.0 if vol > 0 else -1.0
    for p, q, r, t in ((a, b, c, x), (a, b, x, d), (a, x, c, d), (x, b, c, d)):
        if s * np.dot(np.cross(q - p, r - p), t - p) <= 0.0:
            return False
    return True


@numba.njit(cache=True)
def _collapse_swallows(V, F, alive, u, v, p, comp, grid, visit):
    """Whether collapsing ``(u, v)`` to ``p`` sweeps the surface over another shell.

    The region the moving faces sweep is the union of the tetrahedra (old face, ``p``);
    a vertex of another connected component inside it would end up enclosed (a small
    shell swallowed whole, which no face-face contact reveals).
    """
    m = F.shape[0]
    tets = np.empty((2 * m, 4, 3))
    nt = 0
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for f in range(m):
        if not alive[f]:
            continue
        has_u = F[f, 0] == u or F[f, 1] == u or F[f, 2] == u
        has_v = F[f, 0] == v or F[f, 1] == v or F[f, 2] == v
        if not (has_u or has_v):
            continue
        for j in range(3):
            tets[nt, j] = V[F[f, j]]
        tets[nt, 3] = p
        for j in range(4):
            for k in range(3):
                lo[k] = min(lo[k], tets[nt, j, k])
                hi[k] = max(hi[k], tets[nt, j, k])
        nt += 1
    own = comp[u]

    def hit(g):
        if not alive[g] or comp[F[g, 0]] == own:
            return False
        for j in range(3):
            x = V[F[g, j]]
            if x[0] < lo[0] or x[0] > hi[0] or x[1] < lo[1] or x[1] > hi[1]:
                continue
            if x[2] < lo[2] or x[2] > hi[2]:
                continue
            for t in range(nt):
                if _in_tet(x, tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]):
                    return True
        return False

    cand = np.empty(m, dtype=np.int64)
    n = _candidates(grid, visit, m, lo, hi, cand)
    for c in range(n):
        if hit(cand[c]):
            return True
    return False


def empty_face_grid():
    """An empty face grid: :func:`collapse_blocked` then compares with every face."""
    e = np.zeros(0, dtype=np.int64)
    return (e, e, e, np.zeros(2, dtype=np.int64), np.zeros(3), 1.0, np.ones(3, np.int64))


@numba.njit(cache=True)
def collapse_blocked(V, F, alive, u, v, p, tol, comp, grid, visit):
    """Whether collapsing edge ``(u, v)`` to ``p`` makes faces touch or swallows a shell.

    Parameters
    ----------
    V : (n, 3) float64
    F : (m, 3) int64
    alive : (m,) bool
        Faces still in the mesh.
    u, v : int
        The edge's vertices.
    p : (3,) float64
        Where the collapsed vertex goes.
    tol : float
        Contact distance (world units).
    comp : (n,) int64
        Connected component of every vertex.
    grid : tuple
        A face grid (:func:`make_face_grid`, or :func:`empty_face_grid`).
    visit : (m + 1,) int64
        Scratch marks for the grid's candidate lists.

    Returns
    -------
    bool
    """
    return _collapse_clashes(V, F, alive, u, v, p, tol, grid, visit) or _collapse_swallows(
        V, F, alive, u, v, p, comp, grid, visit
    )
