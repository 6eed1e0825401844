"""Exact signed distances from points to a closed triangle mesh, near the mesh only.

The sign uses angle-weighted pseudo-normals (Baerentzen and Aanaes 2005), exact for a
closed, consistently oriented 2-manifold. Only points within ``radius`` of some face are
evaluated (a k-d tree on the points selects them per face), which is what the automatic
cage needs: the clearance and the points that violate it all lie near the cage.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba
import numpy as np

from vhm_viz.core.geometry import closest_point_on_triangle, closest_points_on_triangles
from vhm_viz.core.row_threads import run_rows
from vhm_viz.core.scipy_extensions import kd_tree

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

__all__ = ["NearDistance", "near_signed_distance"]


class NearDistance:
    """Pseudo-normals of a closed mesh, for :func:`near_signed_distance`.

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (m, 3) int array, outward oriented, closed 2-manifold
    """

    def __init__(self, vertices, faces):
        V = np.asarray(vertices, dtype=np.float64)
        F = np.asarray(faces, dtype=np.int64)
        self.V, self.F = V, F
        e1 = V[F[:, 1]] - V[F[:, 0]]
        e2 = V[F[:, 2]] - V[F[:, 0]]
        n = np.cross(e1, e2)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        self.fn = n
        # vertex pseudo-normals: angle weighted
        vn = np.zeros_like(V)
        for k in range(3):
            u = V[F[:, (k + 1) % 3]] - V[F[:, k]]
            w = V[F[:, (k + 2) % 3]] - V[F[:, k]]
            cosang = np.einsum("ij,ij->i", u, w) / np.maximum(
                np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300
            )
            ang = np.arccos(np.clip(cosang, -1, 1))
            np.add.at(vn, F[:, k], n * ang[:, None])
        self.vn = vn
        # edge pseudo-normals: sum of the two face normals, per (face, local edge)
        ea = F.ravel()
        eb = F[:, [1, 2, 0]].ravel()
        key = np.minimum(ea, eb) * len(V) + np.maximum(ea, eb)
        uk, inv = np.unique(key, return_inverse=True)
        en = np.zeros((len(uk), 3))
        np.add.at(en, inv, np.repeat(n, 3, axis=0))
        self.edge_normal = en[inv].reshape(len(F), 3, 3)  # [face, local edge k (k->k+1)]
        tri = V[F]
        self.centroid = tri.mean(axis=1)
        self.radius = np.linalg.norm(tri - self.centroid[:, None, :], axis=2).max(axis=1)

    def signed_distance(self, points, tree: cKDTree | None = None, radius: float = np.inf):
        """Signed distances (negative inside) of the points within ``radius`` of the mesh.

        Parameters
        ----------
        points : (N, 3) float array
        tree : cKDTree, optional
            A tree on ``points`` (reuse it across calls).
        radius : float
            Points farther than this from every face are not evaluated.

        Returns
        -------
        index : (k,) int64
            The evaluated points (those within ``radius``).
        sd : (k,) float64
            Their signed distances.
        face : (k,) int64
            Their nearest faces.
        """
        P = np.asarray(points, dtype=np.float64)
        if tree is None:
            tree = kd_tree(P)
        if np.isfinite(radius):
            lists = tree.query_ball_point(self.centroid, self.radius + radius, workers=-1)
            counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
            pi = (
                np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])
                if counts.sum()
                else np.empty(0, dtype=np.int64)
            )
            fi = np.repeat(np.arange(len(self.F)), counts)
        else:
            pi = np.repeat(np.arange(len(P)), len(self.F))
            fi = np.tile(np.arange(len(self.F)), len(P))
        if len(pi) == 0:
            return np.empty(0, np.int64), np.empty(0), np.empty(0, np.int64)
        best_d = np.full(len(P), np.inf)
        best_pair = np.full(len(P), -1, dtype=np.int64)
        step = 2_000_000
        tri = self.V[self.F]
        for s in range(0, len(pi), step):
            p_ = pi[s : s + step]
            f_ = fi[s : s + step]
            q, _ = closest_points_on_triangles(P[p_], tri[f_, 0], tri[f_, 1], tri[f_, 2])
            d = np.linalg.norm(P[p_] - q, axis=1)
            order = np.lexsort((d, p_))
            first = np.ones(len(order), dtype=bool)
            first[1:] = p_[order[1:]] != p_[order[:-1]]
            sel = order[first]
            upd = d[sel] < best_d[p_[sel]]
            best_d[p_[sel][upd]] = d[sel][upd]
            best_pair[p_[sel][upd]] = s + sel[upd]
        index = np.flatnonzero(best_pair >= 0)
        pair = best_pair[index]
        f = fi[pair]
        q, region = closest_points_on_triangles(P[index], tri[f, 0], tri[f, 1], tri[f, 2])
        normal = self.fn[f].copy()
        for r, k in ((1, 0), (2, 1), (3, 2)):
            m = region == r
            normal[m] = self.edge_normal[f[m], k]
        for r, k in ((4, 0), (5, 1), (6, 2)):
            m = region == r
            normal[m] = self.vn[self.F[f[m], k]]
        diff = P[index] - q
        dist = np.linalg.norm(diff, axis=1)
        sign = np.where(np.einsum("ij,ij->i", diff, normal) > 0, 1.0, -1.0)
        keep = dist <= radius
        return index[keep], (sign * dist)[keep], f[keep]


def near_signed_distance(vertices, faces, points, radius: float, tree: cKDTree | None = None):
    """Shortcut for ``NearDistance(vertices, faces).signed_distance(points, tree, radius)``."""
    return NearDistance(vertices, faces).signed_distance(points, tree=tree, radius=radius)


# ---------------------------------------------------------------------------------------
# compiled version: a uniform grid of faces, one thread per point
# ---------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _fill_cells(lo, hi, origin, cs, dims, count_only, start, out):
    m = lo.shape[0]
    total = 0
    for f in range(m):
        i0 = max(0, int((lo[f, 0] - origin[0]) / cs))
        j0 = max(0, int((lo[f, 1] - origin[1]) / cs))
        k0 = max(0, int((lo[f, 2] - origin[2]) / cs))
        i1 = min(dims[0] - 1, int((hi[f, 0] - origin[0]) / cs))
        j1 = min(dims[1] - 1, int((hi[f, 1] - origin[1]) / cs))
        k1 = min(dims[2] - 1, int((hi[f, 2] - origin[2]) / cs))
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for k in range(k0, k1 + 1):
                    c = (i * dims[1] + j) * dims[2] + k
                    if count_only:
                        start[c + 1] += 1
                    else:
                        out[start[c]] = f
                        start[c] += 1
                    total += 1
    return total


@numba.njit(cache=True, nogil=True)
def _grid_query(  # pragma: no cover - compiled
    start, stop, P, V, F, fn, en, vn, cell_start, faces_in_cell, origin, cs, dims, radius,
    out_sd, out_f,
):  # fmt: skip
    for ip in range(start, stop):
        px, py, pz = P[ip, 0], P[ip, 1], P[ip, 2]
        out_sd[ip] = np.inf
        out_f[ip] = -1
        i = int(np.floor((px - origin[0]) / cs))
        j = int(np.floor((py - origin[1]) / cs))
        k = int(np.floor((pz - origin[2]) / cs))
        if i < 0 or j < 0 or k < 0 or i >= dims[0] or j >= dims[1] or k >= dims[2]:
            continue
        c = (i * dims[1] + j) * dims[2] + k
        best = np.inf
        bq0 = 0.0
        bq1 = 0.0
        bq2 = 0.0
        bf = -1
        breg = 0
        for s in range(cell_start[c], cell_start[c + 1]):
            f = faces_in_cell[s]
            va, vb, vc = F[f, 0], F[f, 1], F[f, 2]
            q0, q1, q2, reg = closest_point_on_triangle(
                px, py, pz, V[va, 0], V[va, 1], V[va, 2],
                V[vb, 0], V[vb, 1], V[vb, 2], V[vc, 0], V[vc, 1], V[vc, 2],
            )  # fmt: skip
            dd = (px - q0) ** 2 + (py - q1) ** 2 + (pz - q2) ** 2
            if dd < best:
                best = dd
                bq0, bq1, bq2 = q0, q1, q2
                bf = f
                breg = reg
        if bf < 0:
            continue
        dist = np.sqrt(best)
        if dist > radius:
            continue
        if breg == 0:
            n0, n1, n2 = fn[bf, 0], fn[bf, 1], fn[bf, 2]
        elif breg <= 3:
            n0, n1, n2 = en[bf, breg - 1, 0], en[bf, breg - 1, 1], en[bf, breg - 1, 2]
        else:
            vv = F[bf, breg - 4]
            n0, n1, n2 = vn[vv, 0], vn[vv, 1], vn[vv, 2]
        dot = (px - bq0) * n0 + (py - bq1) * n1 + (pz - bq2) * n2
        out_sd[ip] = dist if dot > 0 else -dist
        out_f[ip] = bf


def grid_signed_distance(nd: NearDistance, points, radius: float):
    """Compiled :meth:`NearDistance.signed_distance` for all points at once.

    Parameters
    ----------
    nd : NearDistance
    points : (N, 3) float array
    radius : float
        Points farther than this from the mesh get ``inf``.

    Returns
    -------
    sd : (N,) float64
        Signed distance (negative inside), ``inf`` beyond ``radius``.
    face : (N,) int64
        Nearest face, -1 beyond ``radius``.
    """
    P = np.ascontiguousarray(points, dtype=np.float64)
    tri = nd.V[nd.F]
    lo = tri.min(axis=1) - radius
    hi = tri.max(axis=1) + radius
    origin = lo.min(axis=0)
    ext = hi.max(axis=0) - origin
    # cells about the size of an average face box, at most ~2M cells
    cs = max(float(np.median(np.ptp(tri, axis=1).max(axis=1))) + 2 * radius, 1e-300)
    cs = max(cs, float(np.prod(ext) / 2e6) ** (1 / 3))
    dims = np.maximum(np.ceil(ext / cs).astype(np.int64), 1)
    ncell = int(np.prod(dims))
    start = np.zeros(ncell + 1, dtype=np.int64)
    _fill_cells(lo, hi, origin, cs, dims, True, start, start)
    np.cumsum(start, out=start)
    fill = start[:-1].copy()
    out = np.empty(int(start[-1]), dtype=np.int64)
    _fill_cells(lo, hi, origin, cs, dims, False, fill, out)
    sd = np.empty(len(P))
    face = np.empty(len(P), dtype=np.int64)
    run_rows(
        _grid_query,
        len(P),
        P,
        nd.V,
        nd.F,
        nd.fn,
        np.ascontiguousarray(nd.edge_normal),
        nd.vn,
        start,
        out,
        origin,
        cs,
        dims,
        float(radius),
        sd,
        face,
    )
    return sd, face
