"""Small triangle-mesh geometry helpers shared by the cage, basis, metrics and readers."""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.row_threads import run_rows


def face_normals_and_areas(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals and areas of triangles.

    Parameters
    ----------
    vertices : (n, 3) float array
        Vertex positions.
    faces : (m, 3) int array
        Triangles, counter-clockwise about the normal returned.

    Returns
    -------
    normals : (m, 3) float64
        Unit normals ``(x1 - x0) x (x2 - x0)`` normalised; zero rows for degenerate faces.
    areas : (m,) float64
        Triangle areas (same length unit squared as ``vertices``).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    twice_area = np.linalg.norm(cross, axis=1)
    normals = np.zeros_like(cross)
    nz = twice_area > 0
    normals[nz] = cross[nz] / twice_area[nz, None]
    return normals, 0.5 * twice_area


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by a closed triangle mesh (positive for outward orientation).

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (m, 3) int array

    Returns
    -------
    float
        Volume in length units cubed, by the divergence theorem.

    Notes
    -----
    The cones are taken from the vertices' centroid, not from the origin: for a mesh far
    from the origin the per-face terms would otherwise be huge and cancel, leaving nothing
    of a small volume, not even its sign.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(f):
        return 0.0
    # coordinate by coordinate: contiguous columns, no (m, 3) temporaries
    x, y, z = (v[:, k] - v[:, k].mean() for k in range(3))
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    return float(_triple_products(x, y, z, a, b, c).sum() / 6.0)


def tetrahedra_volume(vertices: np.ndarray, tets: np.ndarray) -> float:
    """Sum of the signed volumes of tetrahedra.

    Parameters
    ----------
    vertices : (n, 3) float array
    tets : (m, 4) int array
        Corners ``p0, p1, p2, p3``; a tetrahedron's volume is
        ``det(p1 - p0, p2 - p0, p3 - p0) / 6``, positive when the three edges from ``p0``
        are right-handed (VTK's orientation of its tetra cells).

    Returns
    -------
    float
        Volume in length units cubed; inverted tetrahedra count negative.
    """
    v, t = _tet_arrays(vertices, tets)
    return float(_tetrahedra_volumes(v, v, t)[2] / 6.0)


def moved_tetrahedra_volume(rest: np.ndarray, moved: np.ndarray, tets: np.ndarray) -> tuple:
    """The volume a tet mesh fills at rest and after its points moved.

    Each tetrahedron counts with the orientation it has at rest, so the answer does not
    depend on the order its corners are stored in (mesh generators differ: a mesh stored
    all inverted, or a mix, fills the same volume): at rest ``|V_t|``, moved
    ``sign(V_t) V'_t`` (negative where the motion inverts it).

    Parameters
    ----------
    rest, moved : (n, 3) float arrays
        The points before and after.
    tets : (m, 4) int array

    Returns
    -------
    (float, float)
        Rest and moved volumes, in length units cubed.
    """
    v, t = _tet_arrays(rest, tets)
    w = np.ascontiguousarray(moved, dtype=np.float64).reshape(-1, 3)
    if len(w) != len(v):
        raise ValueError(f"moved has {len(w)} points; rest has {len(v)}")
    at_rest, now, _ = _tetrahedra_volumes(v, w, t)
    return float(at_rest / 6.0), float(now / 6.0)


def _tet_arrays(vertices, tets):
    v = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    t = np.ascontiguousarray(tets, dtype=np.int64).reshape(-1, 4)
    if t.size and (t.min() < 0 or t.max() >= len(v)):
        raise ValueError(f"tets must index the {len(v)} vertices")
    return v, t


@numba.njit(cache=True, nogil=True, inline="always")
def _tet_det(v, p0, p1, p2, p3):  # pragma: no cover - compiled
    ax, ay, az = v[p1, 0] - v[p0, 0], v[p1, 1] - v[p0, 1], v[p1, 2] - v[p0, 2]
    bx, by, bz = v[p2, 0] - v[p0, 0], v[p2, 1] - v[p0, 1], v[p2, 2] - v[p0, 2]
    cx, cy, cz = v[p3, 0] - v[p0, 0], v[p3, 1] - v[p0, 1], v[p3, 2] - v[p0, 2]
    return ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)


@numba.njit(cache=True, nogil=True)
def _tetrahedra_volumes(v, w, t):  # pragma: no cover - compiled
    """Sums over ``t`` of ``|d_v|``, ``sign(d_v) d_w`` and ``d_v``, ``d = det(p1 - p0, ...)``."""
    at_rest = 0.0
    moved = 0.0
    signed = 0.0
    for i in range(t.shape[0]):
        p0, p1, p2, p3 = t[i, 0], t[i, 1], t[i, 2], t[i, 3]
        d = _tet_det(v, p0, p1, p2, p3)
        signed += d
        if d > 0.0:
            at_rest += d
            moved += _tet_det(w, p0, p1, p2, p3)
        elif d < 0.0:
            at_rest -= d
            moved -= _tet_det(w, p0, p1, p2, p3)
    return at_rest, moved, signed


def _triple_products(x, y, z, a, b, c) -> np.ndarray:
    """``p_a . (p_b x p_c)`` per row of index arrays, from coordinate columns."""
    ax, ay, az = x[a], y[a], z[a]
    bx, by, bz = x[b], y[b], z[b]
    cx, cy, cz = x[c], y[c], z[c]
    return ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)


def open_edge_count(faces: np.ndarray, n_points: int) -> int:
    """Edges of a triangle mesh that do not join exactly two triangles: none where closed.

    Boundary edges (of one triangle) and non-manifold ones (of three or more): the count of
    PyVista's ``n_open_edges`` (``vtkFeatureEdges``), without building the edges. Each
    point's edges to larger points are gathered by counting, not sorting, and matched.

    Parameters
    ----------
    faces : (m, 3) int array
        Triangles; indices in ``[0, n_points)``.
    n_points : int

    Returns
    -------
    int
    """
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(f):
        return 0
    if f.min() < 0 or f.max() >= n_points:
        raise ValueError(f"faces must index the {n_points} points")
    start = np.zeros(int(n_points) + 1, dtype=np.int64)
    return int(_open_edges(f, start, np.empty(int(n_points), np.int64), np.empty(f.size, np.int64)))


@numba.njit(cache=True, nogil=True)
def _open_edges(faces, start, cursor, slots):  # pragma: no cover - compiled
    """Edges of ``faces`` that do not occur twice: each point's larger ends, sorted in place.

    ``start`` (points + 1) zeros; ``cursor`` (points) and ``slots`` (edges) scratch.
    """
    for t in range(faces.shape[0]):
        for c in range(3):
            a, b = faces[t, c], faces[t, (c + 1) % 3]
            start[min(a, b) + 1] += 1
    for v in range(cursor.size):
        start[v + 1] += start[v]
        cursor[v] = start[v]
    for t in range(faces.shape[0]):
        for c in range(3):
            a, b = faces[t, c], faces[t, (c + 1) % 3]
            low = min(a, b)
            slots[cursor[low]] = max(a, b)
            cursor[low] += 1
    n_open = 0
    for v in range(cursor.size):
        s, t = start[v], start[v + 1]
        for i in range(s + 1, t):  # insertion sort: a point has a handful of edges
            key = slots[i]
            j = i - 1
            while j >= s and slots[j] > key:
                slots[j + 1] = slots[j]
                j -= 1
            slots[j + 1] = key
        i = s
        while i < t:
            j = i + 1
            while j < t and slots[j] == slots[i]:
                j += 1
            n_open += j - i != 2
            i = j
    return n_open


def _newell_normal(p: np.ndarray) -> np.ndarray:
    q = np.roll(p, -1, axis=0)
    return np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )


def _triangulate_polygon(points: np.ndarray, poly: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles of one polygon (vertex ids ``poly``), keeping its orientation."""
    k = len(poly)
    if k == 3:
        return [(int(poly[0]), int(poly[1]), int(poly[2]))]
    p = points[poly]
    normal = _newell_normal(p)
    fan = [(0, i, i + 1) for i in range(1, k - 1)]
    if all(np.dot(np.cross(p[b] - p[a], p[c] - p[a]), normal) > 0 for a, b, c in fan):
        return [(int(poly[a]), int(poly[b]), int(poly[c])) for a, b, c in fan]
    # ear clipping in the plane of the Newell normal
    nn = np.linalg.norm(normal)
    if nn == 0:
        return [(int(poly[a]), int(poly[b]), int(poly[c])) for a, b, c in fan]
    normal = normal / nn
    u = np.cross(normal, [1.0, 0.0, 0.0])
    if np.linalg.norm(u) < 0.1:
        u = np.cross(normal, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    xy = np.stack([(p - p[0]) @ u, (p - p[0]) @ w], axis=1)

    def cross2(a, b, c):
        return (xy[b, 0] - xy[a, 0]) * (xy[c, 1] - xy[a, 1]) - (xy[b, 1] - xy[a, 1]) * (
            xy[c, 0] - xy[a, 0]
        )

    remaining = list(range(k))
    tris = []
    while len(remaining) > 3:
        r = len(remaining)
        for i in range(r):
            a, b, c = remaining[i - 1], remaining[i], remaining[(i + 1) % r]
            if cross2(a, b, c) <= 0:
                continue  # reflex corner
            if any(
                cross2(a, b, d) >= 0 and cross2(b, c, d) >= 0 and cross2(c, a, d) >= 0
                for d in remaining
                if d not in (a, b, c)
            ):
                continue  # another corner inside the ear
            tris.append((a, b, c))
            remaining.pop(i)
            break
        else:  # no ear (self-overlapping polygon): give up and fan the rest
            tris.extend((remaining[0], remaining[j], remaining[j + 1]) for j in range(1, r - 1))
            remaining = remaining[:3]
            break
    if len(remaining) == 3 and len(tris) < k - 2:
        tris.append(tuple(remaining))
    return [(int(poly[a]), int(poly[b]), int(poly[c])) for a, b, c in tris]


def triangulate_polygons(points: np.ndarray, polygons) -> np.ndarray:
    """Triangles of a set of polygons, keeping each polygon's orientation.

    A convex polygon becomes a fan from its first corner; a non-convex one is ear-clipped
    in the plane of its Newell normal, so every format's quads and polygons give the same
    triangles.

    Parameters
    ----------
    points : (n, 3) float64
        Vertex positions.
    polygons : sequence of int arrays
        Vertex ids of each polygon; records with fewer than 3 ids (points, polylines)
        are skipped.

    Returns
    -------
    (m, 3) int64
    """
    tris: list[tuple[int, int, int]] = []
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.int64)
        if len(poly) < 3:
            continue  # points / polyline records
        tris.extend(_triangulate_polygon(points, poly))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


@numba.njit(cache=True)
def _edge_projections(dx, dy, dz, ux, uy, uz, vx, vy, vz):  # pragma: no cover - compiled
    """``d . u`` and ``d . v``: the offset ``d`` projected on two edges (unnormalised)."""
    return ux * dx + uy * dy + uz * dz, vx * dx + vy * dy + vz * dz


@numba.njit(cache=True, inline="always")
def closest_point_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):  # pragma: no cover
    """Closest point of the triangle ``(a, b, c)`` to ``p``, compiled, scalar coordinates.

    The Voronoi-region tests of Ericson (Real-Time Collision Detection, 2004, 5.1.5). The
    one closest-point routine of the package: every distance to a triangle and every
    nearest-face search is built on it. A degenerate triangle whose regions all fail
    (zero area) gives its centroid's region 0.

    Returns
    -------
    qx, qy, qz : float
        The closest point (a corner is returned exactly).
    region : int
        0 face interior, 1 edge ab, 2 edge bc, 3 edge ca, 4 vertex a, 5 vertex b, 6 vertex c.
    """
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    # p seen from each corner, along the two edges out of a
    d1, d2 = _edge_projections(px - ax, py - ay, pz - az, abx, aby, abz, acx, acy, acz)
    d3, d4 = _edge_projections(px - bx, py - by, pz - bz, abx, aby, abz, acx, acy, acz)
    d5, d6 = _edge_projections(px - cx, py - cy, pz - cz, abx, aby, abz, acx, acy, acz)
    # the vertex regions, then the edge regions (disjoint where the area is not zero)
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 4
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, 5
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, 6
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz, 1
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz, 3
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), 2
    den = va + vb + vc
    if den == 0.0:
        v = w = 1.0 / 3.0
    else:
        v = vb / den
        w = vc / den
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, 0


@numba.njit(cache=True, inline="always")
def triangle_distance2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):  # pragma: no cover
    """Squared distance from ``p`` to the triangle ``(a, b, c)`` (compiled, scalar coordinates).

    Over the face interior it is the distance to the triangle's plane, which stays
    accurate for points next to a large face; elsewhere the distance to the closest point
    of :func:`closest_point_on_triangle`.
    """
    qx, qy, qz, region = closest_point_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    if region == 0:
        abx, aby, abz = bx - ax, by - ay, bz - az
        acx, acy, acz = cx - ax, cy - ay, cz - az
        nx = aby * acz - abz * acy
        ny = abz * acx - abx * acz
        nz = abx * acy - aby * acx
        nn = nx * nx + ny * ny + nz * nz
        if nn > 0.0:
            h = (px - ax) * nx + (py - ay) * ny + (pz - az) * nz
            return h * h / nn
    dx, dy, dz = px - qx, py - qy, pz - qz
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, inline="always")
def triangle_distance(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):  # pragma: no cover
    """Distance from ``p`` to the triangle ``(a, b, c)`` (compiled, scalar coordinates)."""
    return math.sqrt(triangle_distance2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz))


@numba.njit(cache=True, inline="always")
def point_triangle_distance2(p, a, b, c):  # pragma: no cover - compiled
    """:func:`triangle_distance2` with the points as 3-vectors ``p``, ``a``, ``b``, ``c``."""
    return triangle_distance2(
        p[0], p[1], p[2], a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2]
    )


@numba.njit(cache=True, nogil=True)
def _closest_rows(start, stop, p, a, b, c, q, region):  # pragma: no cover - compiled
    for k in range(start, stop):
        qx, qy, qz, r = closest_point_on_triangle(
            p[k, 0], p[k, 1], p[k, 2], a[k, 0], a[k, 1], a[k, 2],
            b[k, 0], b[k, 1], b[k, 2], c[k, 0], c[k, 1], c[k, 2],
        )  # fmt: skip
        q[k, 0], q[k, 1], q[k, 2] = qx, qy, qz
        region[k] = r


def closest_points_on_triangles(p, a, b, c):
    """Closest points of triangles ``(a, b, c)`` to points ``p``, row by row.

    Parameters
    ----------
    p, a, b, c : (k, 3) float arrays
        Row ``i`` asks for the point of triangle ``(a[i], b[i], c[i])`` nearest ``p[i]``.

    Returns
    -------
    q : (k, 3) float64
        Closest points.
    region : (k,) int8
        As :func:`closest_point_on_triangle`.
    """
    rows = [np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3) for x in (p, a, b, c)]
    q = np.empty((len(rows[0]), 3))
    region = np.empty(len(rows[0]), dtype=np.int8)
    if len(q):
        run_rows(_closest_rows, len(q), *rows, q, region, grain=4096)
    return q, region


@numba.njit(nogil=True, cache=True)
def _nearest_triangles(start, stop, points, tri, out_face, out_point):  # pragma: no cover
    """Brute force over the triangles: the nearest one to each point, ties to the lowest."""
    for p in range(start, stop):
        best = np.inf
        bi = -1
        bx, by, bz = 0.0, 0.0, 0.0
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        for t in range(tri.shape[0]):
            qx, qy, qz, _ = closest_point_on_triangle(
                px, py, pz, tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2],
                tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2], tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2],
            )  # fmt: skip
            d = (qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2
            if d < best:
                best = d
                bi = t
                bx, by, bz = qx, qy, qz
        out_face[p] = bi
        out_point[p, 0] = bx
        out_point[p, 1] = by
        out_point[p, 2] = bz


def nearest_points_on_mesh(points, vertices, faces):
    """The nearest triangle of a mesh to each point and the closest point on it.

    A brute force over the triangles (compiled, parallel over the points): meant for
    cages, whose faces are few.

    Parameters
    ----------
    points : (P, 3) float array
    vertices : (n, 3) float array
    faces : (m, 3) int array

    Returns
    -------
    face : (P,) int64
        Index of the nearest triangle (the lowest one on ties).
    closest : (P, 3) float64
        The closest point on it.
    """
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64)[np.asarray(faces)])
    face = np.empty(len(p), dtype=np.int64)
    closest = np.empty((len(p), 3))
    if len(p):
        run_rows(_nearest_triangles, len(p), p, tri, face, closest, grain=64)
    return face, closest


def ray_depth(origins, directions, vertices, faces, skip_faces=None) -> np.ndarray:
    """Distance along each ray to the first triangle it crosses (Moller-Trumbore).

    Parameters
    ----------
    origins : (k, 3) float array
        Ray starts.
    directions : (k, 3) float array
        Unit ray directions.
    vertices : (n, 3) float array
    faces : (m, 3) int array
    skip_faces : (k,) int array, optional
        One face per ray that is never hit (the face the ray starts on); -1 for none.

    Returns
    -------
    (k,) float64
        Distance to the first crossing (length units), ``inf`` when the ray meets nothing.
        Rays that touch a triangle's edge or corner count as crossing it.
    """
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    skip = np.full(len(o), -1) if skip_faces is None else np.asarray(skip_faces).ravel()
    a = v[f[:, 0]]
    e1 = v[f[:, 1]] - a
    e2 = v[f[:, 2]] - a
    out = np.full(len(o), np.inf)
    # blocks of at most a million (ray, face) pairs bound the temporaries' memory,
    # whatever the numbers of rays and faces
    step = max(1, 1_000_000 // max(len(f), 1))
    for s in range(0, len(o), step):
        oo, dd = o[s : s + step, None, :], d[s : s + step, None, :]
        p = np.cross(dd, e2[None])
        det = np.einsum("rfi,fi->rf", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            t_vec = oo - a[None]
            u = np.einsum("rfi,rfi->rf", t_vec, p) * inv
            q = np.cross(t_vec, e1[None])
            w = np.einsum("rfi,rfi->rf", np.broadcast_to(dd, q.shape), q) * inv
            t = np.einsum("rfi,fi->rf", q, e2) * inv
            hit = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
        rows = np.arange(len(oo))
        own = skip[s : s + step]
        hit[rows[own >= 0], own[own >= 0]] = False
        out[s : s + step] = np.where(hit, t, np.inf).min(axis=1)
    return out
