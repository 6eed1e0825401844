"""An adaptive lattice of exact map values and Jacobians, interpolated by tricubic Hermite.

A harmonic map is real-analytic inside its cage, so its values on the voxels of an image
need not be computed one by one. The lattice evaluates the map exactly (closed-form values
and Jacobians) at the nodes of an octree laid over the voxel grid and interpolates every
voxel in between with the tricubic Hermite polynomial of its cell. The polynomial uses the
exact Jacobians, is C1 between neighbouring cells of the same size and reproduces affine
maps exactly.

**Cells and error estimate.** Root cells are ``root`` voxels wide (a power of two); cells
split into 8 down to single voxels, whose corners are voxels (exact). Every test point is
a voxel position, so its exact evaluation is reused as a node when the cell splits. A cell
is tested at its centre and, within two cell widths of the cage, also at its face centre
and edge midpoint nearest to the cage (the error of a cell concentrates on its side facing
the cage). A
cell splits when its largest test error exceeds 0.15 times the tolerance: the margin
covers the points between the tests. Cells within a voxel of a cage edge always split
down to single voxels: there the map has a logarithmic singularity whose error a larger
cell's tests can miss (with a 500-face automatic cage of the CT head, 4 of its 164,529
inside voxels, 0.2-0.35 voxel from an edge, came out at 0.050-0.067 voxel before; the
benchmark measures the error at random voxels and next to the cage).

**Node data.** Per node: the value ``f`` (world), ``f_u = df/du`` (``u``: voxel index
coordinates, so ``f_u = J @ direction @ diag(spacing)``), and the mixed derivatives
``f_uv, f_uw, f_vw, f_uvw`` from central differences of the exact Jacobians of the
neighbouring nodes of the same octree level (one-sided where a neighbour is missing).

**Cells that cross the cage.** The map is only defined inside the cage, yet cells next to
it have corners outside. There the node data is the *analytic continuation* of the map
across the nearest cage face ``t``, which the jump relations of the layer potentials give
in closed form (Kress, *Linear Integral Equations*, 3rd ed., Theorems 6.15 and 6.18): the
double layer jumps by its density and the single layer's normal derivative by its density,
so the interior map continued across the plane of face ``t`` is the exterior formula plus
an affine term,

    f_cont(p) = f_formula(p) + A_t(pi_t(p)) + ((p - x_t) . N_t) b_t,

with ``A_t`` the linear interpolation of the vertex coefficients ``a_v`` over the face,
``pi_t`` the projection onto its plane and ``b_t`` the face coefficient (both sides are
harmonic with the same Cauchy data on the face, so they agree). Near cage *edges* the map
has a logarithmic singularity and the continuation is not single-valued; the tests there
refine the cells, down to single voxels.

**Pre-images.** Each leaf keeps its value and inverse Jacobian at the centre and a bound
``rho`` of its nonlinearity, from the Bezier control points of its polynomial (which also
bound its image): a point whose linear pre-image estimate misses the cell by more than
``rho`` has no pre-image in it. Newton's method on the cell's polynomial finds the others.
"""

from __future__ import annotations

import math
import sys
import time

import numba
import numpy as np

from vhm_viz.core.basis import chunk_rows, evaluate_map, inside_cage
from vhm_viz.core.errors import AbortedError
from vhm_viz.core.geometry import nearest_points_on_mesh
from vhm_viz.core.image import BORDER, ImageGeometry, inside_mask, surface_mask
from vhm_viz.core.memory import release_free_memory

__all__ = ["HermiteLattice", "build_lattice", "exchange_rounds", "DEFAULT_ROOT"]

#: Root cell size in voxels (a power of two).
DEFAULT_ROOT = 16
#: A cell passes when its largest test error is below this fraction of the tolerance.
_SAFETY = 0.15
# Cells within this many voxels (box distance) of a cage edge split down to single voxels,
# whose corners are exact: next to an edge the map has a logarithmic singularity that the
# tests of a larger cell can miss (measured on the CT head with a 500-face automatic cage:
# 4 of 164,529 inside voxels, 0.19-0.35 voxel from an edge, had errors of 0.050-0.067 voxel;
# the largest error farther than 0.5 voxel from an edge was 0.046).
_EDGE_BAND = 1.0
# Nodes whose closed-form Jacobian is undefined (exactly on a cage edge or vertex) are
# evaluated this many voxels away, along a fixed generic direction.
_NUDGE = 1e-7
# Node data terms, in order: f, f_u, f_v, f_w, f_uv, f_uw, f_vw, f_uvw.
_N_TERMS = 8
# Newton on a cell's polynomial: converged when the step is below this (voxels; the step
# is applied, and convergence is quadratic, so the pre-image is then good to ~1e-10) ...
_NEWTON_STEP = 1e-4
# ... within this many iterations.
_NEWTON_ITERATIONS = 12
# A pre-image may lie this far (voxels) outside its cell: cells of different sizes meet
# with mismatches of the order of the tolerance, which would otherwise leave gaps.
_MARGIN = 0.25


# --------------------------------------------------------------------------------------
# tricubic Hermite evaluation (compiled)
# --------------------------------------------------------------------------------------
@numba.njit(inline="always", cache=True)
def _term(du, dv, dw):  # pragma: no cover - compiled
    """Index of the node term ``d^(du+dv+dw) f / du^du dv^dv dw^dw``."""
    if du + dv + dw == 0:
        return 0
    if du + dv + dw == 1:
        return 1 if du else (2 if dv else 3)
    if du + dv + dw == 2:
        return 6 if du == 0 else (5 if dv == 0 else 4)
    return 7


@numba.njit(inline="always", cache=True)
def _weights(t, h):  # pragma: no cover - compiled
    """Cubic Hermite weights on ``[0, h]`` at ``t * h`` and their u-derivatives.

    Returns ``(w0, w1, w2, w3, d0, d1, d2, d3)``: the left value, left derivative (times
    ``h``, so that it multiplies ``df/du``), right value and right derivative weights,
    then their derivatives in ``u``.
    """
    t2 = t * t
    t3 = t2 * t
    return (
        2.0 * t3 - 3.0 * t2 + 1.0,
        h * (t3 - 2.0 * t2 + t),
        -2.0 * t3 + 3.0 * t2,
        h * (t3 - t2),
        (6.0 * t2 - 6.0 * t) / h,
        3.0 * t2 - 4.0 * t + 1.0,
        (-6.0 * t2 + 6.0 * t) / h,
        3.0 * t2 - 2.0 * t,
    )


@numba.njit(cache=True)
def _cell_eval(data, rows, h, tu, tv, tw, f, grad, want_grad):  # pragma: no cover
    """Value (and u-gradient) of a cell's tricubic Hermite polynomial.

    Parameters
    ----------
    data : (Q, 8, 3) float64
        Node data rows.
    rows : (8,) int
        Data rows of the corners, corner ``a + 2 b + 4 c`` at offset ``(a, b, c) * h``.
    h : float
        Cell size (voxels).
    tu, tv, tw : float
        Local coordinates (0..1 inside the cell; the polynomial extrapolates outside).
    f : (3,) out
    grad : (3, 3) out
        ``grad[i, j] = d f_i / d u_j`` when ``want_grad``.
    want_grad : bool
    """
    u0, u1, u2, u3, du0, du1, du2, du3 = _weights(tu, h)
    v0, v1, v2, v3, dv0, dv1, dv2, dv3 = _weights(tv, h)
    w0, w1, w2, w3, dw0, dw1, dw2, dw3 = _weights(tw, h)
    for i in range(3):
        f[i] = 0.0
        if want_grad:
            grad[i, 0] = 0.0
            grad[i, 1] = 0.0
            grad[i, 2] = 0.0
    for corner in range(8):
        a = corner & 1
        b = (corner >> 1) & 1
        c = corner >> 2
        # value / derivative weights of this corner along each axis, and their u-derivatives
        x0, x1, dx0, dx1 = (u0, u1, du0, du1) if a == 0 else (u2, u3, du2, du3)
        y0, y1, dy0, dy1 = (v0, v1, dv0, dv1) if b == 0 else (v2, v3, dv2, dv3)
        z0, z1, dz0, dz1 = (w0, w1, dw0, dw1) if c == 0 else (w2, w3, dw2, dw3)
        r = rows[corner]
        for i in range(3):
            d0 = data[r, 0, i]
            d1 = data[r, 1, i]
            d2 = data[r, 2, i]
            d3 = data[r, 3, i]
            d4 = data[r, 4, i]
            d5 = data[r, 5, i]
            d6 = data[r, 6, i]
            d7 = data[r, 7, i]
            # sum over the 8 terms: (kind in u) x (kind in v) x (kind in w)
            g00 = y0 * z0 * d0 + y1 * z0 * d2 + y0 * z1 * d3 + y1 * z1 * d6  # u-value part
            g10 = y0 * z0 * d1 + y1 * z0 * d4 + y0 * z1 * d5 + y1 * z1 * d7  # u-derivative part
            f[i] += x0 * g00 + x1 * g10
            if want_grad:
                grad[i, 0] += dx0 * g00 + dx1 * g10
                grad[i, 1] += (
                    x0 * (dy0 * z0 * d0 + dy1 * z0 * d2 + dy0 * z1 * d3 + dy1 * z1 * d6)
                    + x1 * (dy0 * z0 * d1 + dy1 * z0 * d4 + dy0 * z1 * d5 + dy1 * z1 * d7)
                )
                grad[i, 2] += (
                    x0 * (y0 * dz0 * d0 + y1 * dz0 * d2 + y0 * dz1 * d3 + y1 * dz1 * d6)
                    + x1 * (y0 * dz0 * d1 + y1 * dz0 * d4 + y0 * dz1 * d5 + y1 * dz1 * d7)
                )


@numba.njit(parallel=True, cache=True)
def _test_errors(data, cell_rows, h, offsets, test_rows, node_f, to_voxel, out):
    """Largest error (voxels) of each cell's polynomial at its test points.

    ``offsets[c, k]`` are the local coordinates of test point ``k`` of cell ``c`` and
    ``test_rows[c, k]`` its node-table row (-1: no test); ``to_voxel`` turns a world
    error into voxels.
    """  # noqa: D401
    for c in numba.prange(cell_rows.shape[0]):
        f = np.empty(3)
        g = np.empty((3, 3))
        worst = 0.0
        for k in range(offsets.shape[1]):
            r = test_rows[c, k]
            if r < 0:
                continue
            _cell_eval(
                data, cell_rows[c], h, offsets[c, k, 0], offsets[c, k, 1], offsets[c, k, 2],
                f, g, False,
            )  # fmt: skip
            e = 0.0
            for i in range(3):
                d = 0.0
                for j in range(3):
                    d += to_voxel[i, j] * (f[j] - node_f[r, j])
                e += d * d
            worst = max(worst, math.sqrt(e))
        out[c] = worst


@numba.njit(cache=True)
def _control_points(data, rows, h, cp):  # pragma: no cover - compiled
    """The 64 Bezier control points of a cell's polynomial (convex hull of its image).

    A cubic Hermite segment with end values ``p0, p1`` and end derivatives ``m0, m1``
    (per unit of ``t``) has Bezier points ``p0, p0 + m0/3, p1 - m1/3, p1``; the tensor
    product gives ``P[a, b, c] = f + s_a (h/3) f_u + ... + s_a s_b s_c (h/3)^3 f_uvw`` at
    the corner nearest to ``(a, b, c) / 3``, with ``s = 0, +1, -1, 0`` for 0..3.
    """
    k3 = h / 3.0
    for c in range(4):
        for b in range(4):
            for a in range(4):
                r = rows[(a >= 2) + 2 * (b >= 2) + 4 * (c >= 2)]
                sa = k3 * (1.0 if a == 1 else (-1.0 if a == 2 else 0.0))
                sb = k3 * (1.0 if b == 1 else (-1.0 if b == 2 else 0.0))
                sc = k3 * (1.0 if c == 1 else (-1.0 if c == 2 else 0.0))
                n = a + 4 * b + 16 * c
                for i in range(3):
                    cp[n, i] = (
                        data[r, 0, i]
                        + sa * data[r, 1, i]
                        + sb * data[r, 2, i]
                        + sc * data[r, 3, i]
                        + sa * sb * data[r, 4, i]
                        + sa * sc * data[r, 5, i]
                        + sb * sc * data[r, 6, i]
                        + sa * sb * sc * data[r, 7, i]
                    )


@numba.njit(parallel=True, cache=True)
def _leaf_summaries(data, rows, size, centre_f, centre_ginv, rho):  # pragma: no cover
    """Per leaf: value and inverse u-Jacobian at the centre, and the nonlinearity ``rho``.

    ``rho`` bounds ``|G_c^-1 (f(u) - f_c) - (u - u_c)|_inf`` over the cell: the control
    points of that tricubic minus those of the linear function ``u - u_c`` (at the cell's
    thirds) bound it. A point whose linear pre-image estimate is farther than ``rho`` from
    the cell has no pre-image in it.
    """
    for n in numba.prange(rows.shape[0]):
        h = float(size[n])
        g = np.empty((3, 3))
        f = np.empty(3)
        _cell_eval(data, rows[n], h, 0.5, 0.5, 0.5, f, g, True)
        if abs(np.linalg.det(g)) > 1e-300:
            gi = np.linalg.inv(g)
        else:
            gi = np.full((3, 3), np.nan)
        centre_f[n] = f
        centre_ginv[n] = gi
        cp = np.empty((64, 3))
        _control_points(data, rows[n], h, cp)
        worst = 0.0
        for q in range(64):
            lin = ((q % 4) / 3.0 - 0.5, ((q // 4) % 4) / 3.0 - 0.5, (q // 16) / 3.0 - 0.5)
            for i in range(3):
                d = -lin[i] * h
                for j in range(3):
                    d += gi[i, j] * (cp[q, j] - f[j])
                worst = max(worst, abs(d))
        rho[n] = worst if np.isfinite(worst) else np.inf


# --------------------------------------------------------------------------------------
# exact node data, continued across the cage
# --------------------------------------------------------------------------------------
def _continuation_terms(points, faces, vertices, face_ids, a, b, normals):
    """Affine term of the map continued across each point's face, and its gradient.

    ``A_t(pi_t(p)) + ((p - x_t0) . N_t) b_t`` (see the module documentation) and its
    derivative ``dA_t/dp + b_t N_t^T``.

    Returns
    -------
    value : (P, 3)
    grad : (P, 3, 3)
        ``grad[k, i, j] = d value_i / d p_j``.
    """
    f = faces[face_ids]
    x0, x1, x2 = vertices[f[:, 0]], vertices[f[:, 1]], vertices[f[:, 2]]
    n = normals[face_ids]
    e1, e2 = x1 - x0, x2 - x0
    d11 = np.einsum("ij,ij->i", e1, e1)
    d12 = np.einsum("ij,ij->i", e1, e2)
    d22 = np.einsum("ij,ij->i", e2, e2)
    det = d11 * d22 - d12 * d12
    # barycentric gradients in the face plane: l1 = g1 . (p - x0), l2 = g2 . (p - x0)
    g1 = (d22[:, None] * e1 - d12[:, None] * e2) / det[:, None]
    g2 = (d11[:, None] * e2 - d12[:, None] * e1) / det[:, None]
    r = points - x0
    l1 = np.einsum("ij,ij->i", g1, r)
    l2 = np.einsum("ij,ij->i", g2, r)
    a0, a1, a2 = a[f[:, 0]], a[f[:, 1]], a[f[:, 2]]
    bt = b[face_ids]
    s = np.einsum("ij,ij->i", r, n)
    value = a0 + l1[:, None] * (a1 - a0) + l2[:, None] * (a2 - a0) + s[:, None] * bt
    grad = (
        np.einsum("ki,kj->kij", a1 - a0, g1)
        + np.einsum("ki,kj->kij", a2 - a0, g2)
        + np.einsum("ki,kj->kij", bt, n)
    )
    return value, grad


class _Shells:
    """Outward shells of a cage (connected components enclosing positive volume).

    For a cage of several outward shells a point outside all of them is continued from
    its nearest face's shell, with that shell's (and the inward hole shells') basis
    functions only -- the functions the map uses inside that shell.
    """

    def __init__(self, vertices, faces):
        import scipy.sparse as sp
        import scipy.sparse.csgraph as csgraph

        n = len(vertices)
        f = np.asarray(faces)
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
        _, labels = csgraph.connected_components(graph, directed=False)
        face_label = labels[f[:, 0]]
        x = np.asarray(vertices)[f]
        vol = np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2]))
        self.face_shell = np.full(len(f), -1)
        outward, holes = [], []
        for k in np.unique(face_label):
            ids = np.nonzero(face_label == k)[0]
            (outward if vol[ids].sum() > 0 else holes).append(ids)
        for s, ids in enumerate(outward):
            self.face_shell[ids] = s
        self.outward = outward
        self.holes = np.concatenate(holes) if holes else np.zeros(0, np.int64)

    @property
    def several(self) -> bool:
        """Whether the cage has more than one outward shell."""
        return len(self.outward) > 1

    def faces_of(self, shell: int) -> np.ndarray:
        """Face ids of one outward shell plus the hole shells (a cage of its own)."""
        return np.concatenate([self.outward[shell], self.holes])


def _exact_data(hm, points, to_index, shells, memory_budget=None, abort=None):
    """Map values and u-Jacobians at world points: exact inside, continued outside.

    Parameters
    ----------
    hm : HarmonicMap
    points : (P, 3) float64
        World points.
    to_index : (3, 3) float64
        ``index_to_world`` of the grid: ``f_u = J @ to_index``.
    shells : _Shells
    memory_budget : int, optional
        Bytes of working memory per chunk.
    abort : callable, optional

    Returns
    -------
    f : (P, 3)
    fu : (P, 3, 3)
        ``fu[k, i, j] = d f_i / d u_j``.
    inside : (P,) bool
        Inside the cage (by the winding number of the basis).
    """
    cage = hm.cage
    V = np.ascontiguousarray(cage.vertices, dtype=np.float64)
    F = np.ascontiguousarray(cage.faces, dtype=np.int64)
    z = np.asarray(hm.coefficients)
    n = len(V)
    P = len(points)
    f = np.empty((P, 3))
    jac = np.empty((P, 3, 3))
    inside = np.empty(P, dtype=bool)
    # the fused kernel keeps no basis arrays: chunks only bound progress and abort
    rows = 8 * chunk_rows(len(z), 1, memory_budget)
    for s in range(0, P, rows):
        if abort is not None and abort():
            raise AbortedError("aborted")
        e = min(P, s + rows)
        f[s:e], jac[s:e], wind = evaluate_map(points[s:e], V, F, z, order=1)
        inside[s:e] = inside_cage(wind)
    out = np.nonzero(~inside)[0]
    if out.size:
        face, _ = nearest_points_on_mesh(points[out], V, F)
        if shells.several:
            # outside every shell the basis drops all outward shells: evaluate the nearest
            # face's shell (with the holes) as a cage of its own
            for s_id in np.unique(shells.face_shell[face]):
                pick = out[shells.face_shell[face] == s_id]
                sub = shells.faces_of(int(s_id))
                fs = F[sub]
                used = np.unique(fs)
                remap = np.full(n, -1)
                remap[used] = np.arange(len(used))
                zs = np.vstack([z[used], z[n + sub]])
                f[pick], jac[pick], _ = evaluate_map(points[pick], V[used], remap[fs], zs)
        add, dadd = _continuation_terms(
            points[out], F, V, face, z[:n], z[n:], np.asarray(cage.face_normals)
        )
        f[out] += add
        jac[out] += dadd
    bad = np.nonzero(~np.isfinite(jac).all(axis=(1, 2)))[0]
    if bad.size:
        # exactly on a cage edge or vertex the Jacobian is undefined: take it 1e-7 voxels
        # away (and the value there, which differs by ~1e-7 voxels)
        step = to_index @ (np.array([0.5, 0.3, 0.2]) * _NUDGE)
        f2, fu2, _ = _exact_data(hm, points[bad] + step, to_index, shells, memory_budget)
        f[bad] = f2
        jac[bad] = fu2 @ np.linalg.inv(to_index)
    return f, jac @ to_index, inside


# --------------------------------------------------------------------------------------
# building
# --------------------------------------------------------------------------------------
class _NodeTable:
    """Exact node data keyed by lattice position, grown level by level."""

    def __init__(self, dims):
        self.dims = np.asarray(dims, dtype=np.int64)  # lattice points per axis
        self.clear()

    def clear(self) -> None:
        """Forget every node."""
        self.keys = np.zeros(0, dtype=np.int64)
        self.f = np.zeros((0, 3))
        self.fu = np.zeros((0, 3, 3))
        self.inside = np.zeros(0, dtype=bool)

    def key(self, ijk) -> np.ndarray:
        ijk = np.asarray(ijk, dtype=np.int64)
        return ijk[..., 0] + self.dims[0] * (ijk[..., 1] + self.dims[1] * ijk[..., 2])

    def ijk(self, keys) -> np.ndarray:
        i = keys % self.dims[0]
        j = (keys // self.dims[0]) % self.dims[1]
        k = keys // (self.dims[0] * self.dims[1])
        return np.stack([i, j, k], axis=-1)

    def find(self, keys) -> np.ndarray:
        """Row of each key (-1 where absent)."""
        if len(self.keys) == 0:
            return np.full(np.shape(keys), -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        return np.where(self.keys[pos] == keys, pos, -1)

    def keep(self, rows) -> None:
        """Keep only the nodes at ``rows`` (ascending table rows), each field in place.

        The rows move to the front of each array, which is then shrunk (:func:`_taken`),
        and the heap's freed pages go back to the system: the kept table is never held
        beside the whole one.
        """
        rows = np.asarray(rows, dtype=np.int64)
        for name in ("keys", "f", "fu", "inside"):
            setattr(self, name, _taken(vars(self), name, rows))
        release_free_memory()

    def add(self, keys, f, fu, inside) -> None:
        """Add nodes not in the table yet (``keys`` distinct), keeping the keys sorted.

        Each array grows in place (realloc) and the new rows are merged into it from
        the back, one field at a time, so that this code never makes a second table
        (realloc itself may still copy a block below glibc's mmap threshold).
        Concatenating and reordering instead held each field three times at once, 42 MB
        on an MPI rank's share of the embryo at its finest level, that rank's build
        peak. A failure part way leaves the table unusable (the build drops it).
        """
        keys = np.asarray(keys, dtype=np.int64).ravel()
        fields = [keys, np.asarray(f), np.asarray(fu), np.asarray(inside, dtype=bool)]
        if np.any(keys[1:] < keys[:-1]):  # (the build adds them sorted)
            order = np.argsort(keys, kind="stable")
            fields = [a[order] for a in fields]
        # where each new row goes in the merged table (ascending)
        at = np.searchsorted(self.keys, fields[0]) + np.arange(len(keys))
        for name, new in zip(("keys", "f", "fu", "inside"), fields, strict=True):
            table = _grown(vars(self), name, len(new))
            width = math.prod(table.shape[1:])
            rows = new.reshape(len(new), width).astype(table.dtype, copy=False)
            _merge_from_back(table.reshape(len(table), width), at, rows)
            setattr(self, name, table)


def _grown(holder, key, extra: int) -> np.ndarray:
    """The array ``holder[key]``, grown by ``extra`` rows (uninitialised).

    The array is taken out of ``holder`` (a dict or list; the slot is set to None) and
    grown in place if it can be: a caller's reference would make ``resize`` refuse.
    """
    a = holder[key]
    holder[key] = None  # the one reference left is ours: resize may run
    shape = (len(a) + extra,) + a.shape[1:]
    try:
        a.resize(shape)  # realloc: a large (mmapped) block is remapped, not copied
        return a
    except ValueError:  # referenced elsewhere (or not its own memory): copied after all
        return np.concatenate([a, np.empty((extra,) + a.shape[1:], dtype=a.dtype)])


def _taken(holder, key, index) -> np.ndarray:
    """``holder[key][index]`` for ascending ``index``, made in place when it can.

    The array is taken out of ``holder`` (a dict or list; the slot is set to None), its
    rows ``index`` are moved to its front and it is shrunk (realloc), so that the array
    and its selection are never held together. Where that cannot be done (not its own
    contiguous memory, referenced elsewhere, an index not ascending) the rows are copied.
    """
    a = holder[key]
    holder[key] = None  # the one reference left is ours: resize may run
    index = np.asarray(index, dtype=np.int64).ravel()
    if (
        a.ndim == 0
        or len(a) == 0
        or sys.getrefcount(a) > 2  # held elsewhere too (or viewed): not moved under it
        or not (a.flags.c_contiguous and a.flags.owndata)
        or (len(index) > 1 and not (index[1:] > index[:-1]).all())
        or (len(index) and (index[0] < 0 or index[-1] >= len(a)))
    ):
        return a[index]
    rows = a.reshape(len(a), -1)
    _move_rows_forward(rows, index)
    del rows
    try:
        a.resize((len(index),) + a.shape[1:])
        return a
    except ValueError:  # referenced elsewhere after all
        return a[: len(index)].copy()


@numba.njit(cache=True)
def _move_rows_forward(rows, index):  # pragma: no cover - compiled
    """``rows[t] = rows[index[t]]`` for ascending ``index`` (no row read after it moved)."""
    for t in range(index.shape[0]):
        if index[t] != t:
            rows[t] = rows[index[t]]


@numba.njit(cache=True)
def _merge_from_back(table, at, new):  # pragma: no cover - compiled
    """Merge rows ``new`` into ``table`` at rows ``at`` (ascending), in place.

    ``table`` holds its old rows first and room for ``len(new)`` more at its end; old
    rows move back past the new rows that come before them, last first, so that no row
    is overwritten before it has moved.
    """
    n_old = table.shape[0] - new.shape[0]
    j = n_old - 1
    for t in range(new.shape[0] - 1, -1, -1):
        while j >= 0 and j + t + 1 > at[t]:
            table[j + t + 1] = table[j]
            j -= 1
        table[at[t]] = new[t]


# Offsets (in units of h) of the lattice points a node's differenced terms read: the six
# along the axes (twists) and the twelve edge diagonals (f_uvw from the twists of the six).
_STENCIL = np.array(
    [d for d in np.ndindex(3, 3, 3) if 0 < sum(abs(x - 1) for x in d) <= 2], dtype=np.int64
) - 1


# Nodes whose twists :func:`_level_data` computes at a time.
_LEVEL_CHUNK = 8192


def _stencil_points(table: _NodeTable, keys: np.ndarray, h: int) -> np.ndarray:
    """Lattice points (ijk) that :func:`_level_data` reads around ``keys`` at level ``h``."""
    ijk = table.ijk(keys)
    pts = (ijk[:, None, :] + h * _STENCIL[None]).reshape(-1, 3)
    ok = np.all((pts >= 0) & (pts <= table.dims - 1), axis=1)
    return pts[ok]


def _rows_read(table: _NodeTable, keys: np.ndarray, h: int, twists: bool = True) -> np.ndarray:
    """Table rows that :func:`_level_data` reads for ``keys`` (ascending).

    The nodes themselves and, for their twists, the nodes one and two steps ``h`` away
    along the axes (the differences of the neighbours' twists); absent ones are absent
    either way. In chunks of :data:`_LEVEL_CHUNK` nodes.
    """
    read = np.zeros(len(table.keys), dtype=bool)
    ring = table.find(keys)
    read[ring] = True
    for _ in range(2 if twists else 0):
        # the neighbours of the nodes marked last, only: the others' are marked already
        before = read.copy()
        for c0 in range(0, len(ring), _LEVEL_CHUNK):
            near = _axis_neighbours(table, ring[c0 : c0 + _LEVEL_CHUNK], h)
            read[near[near >= 0]] = True
        ring = np.flatnonzero(read & ~before)
    return np.flatnonzero(read)


def _level_data(table: _NodeTable, keys: np.ndarray, h: int, twists: bool = True) -> np.ndarray:
    """Node data rows ``(P, 8, 3)`` of one level: exact ``f``, ``f_u``; differenced twists.

    Mixed derivatives are central differences of the exact Jacobians at the lattice points
    ``+- h`` along each axis (for ``h > 1`` all in ``table``: :func:`build_lattice`
    evaluates them; one-sided only at the lattice's own boundary), symmetrised; ``f_uvw``
    likewise from the mixed derivatives of those points. For ``h > 1`` a node's data thus
    depends on its position and ``h`` alone, not on which other cells were refined: the
    lattice of a root cell is the same whether the whole grid or a window of it is built
    (see ``window``).

    For ``h = 1`` the neighbours are not evaluated for the purpose: the differences use
    those present (each corner of a single-voxel cell has one along every axis inside its
    split parent), one-sided where one is missing. The corners of these cells are voxels,
    where the warp and the Jacobians are exact whatever the twists; the twists only shape
    the polynomial between voxels (pre-images), and there they may differ between a
    window and the whole grid next to a root cell's border.
    """
    rows = table.find(keys)
    out = np.empty((len(keys), _N_TERMS, 3))
    # in chunks of nodes: a whole fine level's neighbour tables and twists (about 400
    # bytes a node) were the build's peak, 94 MB on the embryo; its exact Jacobians
    # gathered at once, 14 MB more. A node's twists depend on the table alone, so the
    # chunks give the same numbers
    slot = np.full(len(table.keys), -1, dtype=np.int64) if twists else None
    for c0 in range(0, len(rows), _LEVEL_CHUNK):
        chunk = rows[c0 : c0 + _LEVEL_CHUNK]
        out[c0 : c0 + len(chunk), 0] = table.f[chunk]
        out[c0 : c0 + len(chunk), 1:4] = np.swapaxes(table.fu[chunk], 1, 2)
        if not twists:  # a lattice for the voxels only (see build_lattice's pre_images)
            out[c0 : c0 + len(chunk), 4:] = 0.0
            continue
        # the nodes whose twists are read: the chunk's and their neighbours along the
        # axes (f_uvw differences the twists of those), each looked up once
        near = _axis_neighbours(table, chunk, h)
        around = np.unique(np.concatenate([chunk, near[near >= 0]]))
        slot[around] = np.arange(len(around))
        mixed = _twists(table, around, _axis_neighbours(table, around, h), h)
        here = slot[chunk]
        out[c0 : c0 + len(chunk), 4:7] = mixed[here]
        # f_uvw: differences along the third axis of each twist, averaged over the three
        third = np.zeros((len(chunk), 3))
        for axis, pair in ((2, 0), (1, 1), (0, 2)):  # twist (0, 1) along w, ...
            at = mixed[:, pair]
            third += _difference(at, here, _slot_of(slot, near[:, axis, 0]),
                                 _slot_of(slot, near[:, axis, 1]), h)  # fmt: skip
        out[c0 : c0 + len(chunk), 7] = third / 3.0
        slot[around] = -1
    return out


def _slot_of(slot, rows):
    """Positions in ``slot``'s numbering of table rows (-1 stays -1)."""
    return np.where(rows >= 0, slot[np.maximum(rows, 0)], -1)


def _axis_neighbours(table: _NodeTable, rows: np.ndarray, h: int) -> np.ndarray:
    """Table rows ``(P, 3, 2)`` of the nodes ``+-h`` along each axis (-1: none there)."""
    ijk = table.ijk(table.keys[rows])
    top = table.dims - 1
    out = np.full((len(rows), 3, 2), -1, dtype=np.int64)
    for axis in range(3):
        for side, sign in ((0, 1), (1, -1)):
            n = ijk.copy()
            n[:, axis] += sign * h
            ok = (n[:, axis] >= 0) & (n[:, axis] <= top[axis])
            out[ok, axis, side] = table.find(table.key(n[ok]))
    return out


def _difference(values, here, plus, minus, h):
    """d/du of ``values`` at ``here`` from its neighbours: central, one-sided, else 0.

    ``here``, ``plus``, ``minus``: rows of ``values`` (-1: no neighbour on that side).
    """
    d = np.zeros((len(here),) + values.shape[1:])
    both = (plus >= 0) & (minus >= 0)
    fwd = (plus >= 0) & ~both
    bwd = (minus >= 0) & ~both
    d[both] = (values[plus[both]] - values[minus[both]]) / (2.0 * h)
    d[fwd] = (values[plus[fwd]] - values[here[fwd]]) / h
    d[bwd] = (values[here[bwd]] - values[minus[bwd]]) / h
    return d


def _twists(table: _NodeTable, rows: np.ndarray, near: np.ndarray, h: int) -> np.ndarray:
    """Symmetrised mixed derivatives ``(P, 3, 3)`` (pairs uv, uw, vw) at table rows.

    ``(d/du_b f_u_a + d/du_a f_u_b) / 2`` by :func:`_difference` of the exact Jacobians
    at the neighbours ``near`` (:func:`_axis_neighbours`).
    """
    out = np.empty((len(rows), 3, 3))
    for pair, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        d_b = _difference(table.fu[:, :, a], rows, near[:, b, 0], near[:, b, 1], h)
        d_a = _difference(table.fu[:, :, b], rows, near[:, a, 0], near[:, a, 1], h)
        out[:, pair] = 0.5 * (d_b + d_a)
    return out


@numba.njit(parallel=True, cache=True)
def _count_inside(mask, near, origins, h, last, counts):  # pragma: no cover - compiled
    """Inside, outside and next-to-the-surface voxels of the volume in each closed cell."""
    for c in numba.prange(origins.shape[0]):
        nin = 0
        nout = 0
        nnear = 0
        for k in range(origins[c, 2], min(origins[c, 2] + h, last[2]) + 1):
            for j in range(origins[c, 1], min(origins[c, 1] + h, last[1]) + 1):
                for i in range(origins[c, 0], min(origins[c, 0] + h, last[0]) + 1):
                    if mask[k, j, i]:
                        nin += 1
                    else:
                        nout += 1
                    if near[k, j, i]:
                        nnear += 1
        counts[c, 0] = nin
        counts[c, 1] = nout
        counts[c, 2] = nnear


@numba.njit(parallel=True, cache=True)
def _near_edges(cells, h, a, b, band, out):  # pragma: no cover - compiled
    """Whether each cell may come within ``band`` voxels of a cage edge.

    ``out[c]`` is True when a segment ``a[e] b[e]`` (voxel index units) meets the box
    ``[cells[c], cells[c] + h]`` grown by ``band``, tested conservatively: the distance
    from the cell's centre to the segment against ``band`` plus the half diagonal, after a
    bounding-box rejection.
    """
    reach = band + 0.8660254037844386 * h
    for c in numba.prange(cells.shape[0]):
        cx = cells[c, 0] + 0.5 * h
        cy = cells[c, 1] + 0.5 * h
        cz = cells[c, 2] + 0.5 * h
        hit = False
        for e in range(a.shape[0]):
            if (min(a[e, 0], b[e, 0]) > cx + reach or max(a[e, 0], b[e, 0]) < cx - reach
                    or min(a[e, 1], b[e, 1]) > cy + reach or max(a[e, 1], b[e, 1]) < cy - reach
                    or min(a[e, 2], b[e, 2]) > cz + reach or max(a[e, 2], b[e, 2]) < cz - reach):
                continue
            if _segment_distance2(cx, cy, cz, a, b, e) <= reach * reach:
                hit = True
                break
        out[c] = hit


def _cage_edges_in_index(lat_geo, cage):
    """(E, 3) end points ``a``, ``b`` of the cage's edges in the lattice's index units."""
    e = cage.edges
    v = lat_geo.continuous_index(np.asarray(cage.vertices, dtype=np.float64))
    return np.ascontiguousarray(v[e[:, 0]]), np.ascontiguousarray(v[e[:, 1]])


# Edges are binned in cubes of this many voxels for :meth:`HermiteLattice.near_cage_edges`.
_EDGE_BIN = 4.0


def _bin_edges(a, b, radius):
    """Bins of the edges ``a b`` (voxel index units) grown by ``radius``, as CSR lists.

    Returns ``lo`` (3,) the grid's first corner, ``shape`` (3,) bins per axis, ``start``
    (nbins + 1,) and ``ids`` (edge ids), bin ``(x, y, z)`` being ``x + nx (y + ny z)``.
    """
    if not len(a):
        return np.zeros(3), np.ones(3, np.int64), np.zeros(2, np.int64), np.zeros(0, np.int64)
    lo = np.minimum(a, b).min(axis=0) - radius
    hi = np.maximum(a, b).max(axis=0) + radius
    shape = np.maximum(1, np.ceil((hi - lo) / _EDGE_BIN).astype(np.int64))
    counts = np.zeros(int(np.prod(shape)) + 1, dtype=np.int64)
    _edge_bin_entries(a, b, radius, lo, shape, counts, np.zeros(0, np.int64), False)
    start = np.zeros(len(counts), dtype=np.int64)
    start[1:] = np.cumsum(counts[:-1])
    ids = np.empty(int(start[-1]), dtype=np.int64)
    _edge_bin_entries(a, b, radius, lo, shape, start.copy(), ids, True)
    return lo, shape, start, ids


@numba.njit(cache=True)
def _segment_distance2(px, py, pz, a, b, e):  # pragma: no cover - compiled
    """Squared distance from a point to segment ``a[e] b[e]``."""
    dx, dy, dz = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1], b[e, 2] - a[e, 2]
    qx, qy, qz = px - a[e, 0], py - a[e, 1], pz - a[e, 2]
    ll = dx * dx + dy * dy + dz * dz
    s = 0.0 if ll == 0.0 else min(1.0, max(0.0, (qx * dx + qy * dy + qz * dz) / ll))
    qx, qy, qz = qx - s * dx, qy - s * dy, qz - s * dz
    return qx * qx + qy * qy + qz * qz


@numba.njit(cache=True)
def _edge_bin_entries(a, b, radius, lo, shape, cursor, ids, fill):  # pragma: no cover
    """Count (``fill`` False) or write the edge ids of each bin the grown edge meets."""
    reach = radius + 0.8660254037844386 * _EDGE_BIN  # bin centre to anything in it
    for e in range(a.shape[0]):
        r0 = np.empty(3, np.int64)
        r1 = np.empty(3, np.int64)
        for ax in range(3):
            r0[ax] = max(0, int((min(a[e, ax], b[e, ax]) - radius - lo[ax]) // _EDGE_BIN))
            r1[ax] = min(shape[ax] - 1,
                         int((max(a[e, ax], b[e, ax]) + radius - lo[ax]) // _EDGE_BIN))
        for z in range(r0[2], r1[2] + 1):
            for y in range(r0[1], r1[1] + 1):
                for x in range(r0[0], r1[0] + 1):
                    cx = lo[0] + (x + 0.5) * _EDGE_BIN
                    cy = lo[1] + (y + 0.5) * _EDGE_BIN
                    cz = lo[2] + (z + 0.5) * _EDGE_BIN
                    if _segment_distance2(cx, cy, cz, a, b, e) > reach * reach:
                        continue
                    k = x + shape[0] * (y + shape[1] * z)
                    if fill:
                        ids[cursor[k]] = e
                    cursor[k] += 1


@numba.njit(parallel=True, cache=True)
def _near_binned_edges(u, a, b, radius, lo, shape, start, ids, out):  # pragma: no cover
    """``out[p]``: point ``u[p]`` within ``radius`` of an edge of its bin."""
    r2 = radius * radius
    for p in numba.prange(u.shape[0]):
        x = int(math.floor((u[p, 0] - lo[0]) / _EDGE_BIN))
        y = int(math.floor((u[p, 1] - lo[1]) / _EDGE_BIN))
        z = int(math.floor((u[p, 2] - lo[2]) / _EDGE_BIN))
        if not (0 <= x < shape[0] and 0 <= y < shape[1] and 0 <= z < shape[2]):
            continue  # bins cover every edge grown by radius: nothing out there
        k = x + shape[0] * (y + shape[1] * z)
        for q in range(start[k], start[k + 1]):
            if _segment_distance2(u[p, 0], u[p, 1], u[p, 2], a, b, ids[q]) <= r2:
                out[p] = True
                break


_CORNERS = np.array([[a, b, c] for c in (0, 1) for b in (0, 1) for a in (0, 1)])
def _test_points(cells, h, lat_geo, vertices, faces):
    """Test points of each cell, as local coordinates (L, T, 3); NaN rows: no test.

    The centre (where a smooth cell's error peaks); for cells within two widths of the
    cage also the face centre and the edge midpoint nearest to the cage (where the error
    of a cell next to it concentrates). Measured on the CT head and the embryo (all
    voxels of the head, 150,000 next to the embryo's cage): adding the nearest octant
    centre, or the 8 octant centres of farther cells, changed no error above 0.04 voxel
    and cost 4% and 5% more evaluations; leaving out the edge midpoint let errors of 0.12
    voxel through. All are voxel positions.
    """
    L = len(cells)
    out = np.full((L, 3, 3), np.nan)
    out[:, 0] = 0.5
    centres = lat_geo.points(cells + h / 2.0)
    _, q = nearest_points_on_mesh(centres, vertices, faces)
    rel = (lat_geo.continuous_index(q) - cells) / h  # nearest cage point, local coordinates
    near = np.linalg.norm(rel - 0.5, axis=1) < 2.0
    cl = np.clip(rel, 0.0, 1.0)
    dev = np.abs(cl - 0.5)
    order = np.argsort(-dev, axis=1)
    rows = np.arange(L)
    face = np.full((L, 3), 0.5)
    face[rows, order[:, 0]] = np.round(cl[rows, order[:, 0]])
    edge = face.copy()
    edge[rows, order[:, 1]] = np.round(cl[rows, order[:, 1]])
    out[near, 1] = face[near]
    out[near, 2] = edge[near]
    return out


def build_lattice(
    harmonic_map,
    geometry: ImageGeometry,
    *,
    tolerance: float = 0.05,
    root: int = DEFAULT_ROOT,
    memory_budget: int | None = None,
    progress=None,
    abort=None,
    window=None,
    exchange=None,
    pre_images: bool = True,
) -> HermiteLattice:
    """Build the adaptive Hermite lattice of a map over an image grid.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    geometry : ImageGeometry
        The input volume's grid.
    tolerance : float
        Largest allowed position error, in voxels of the input spacing (Euclidean norm
        of the error in index coordinates).
    root : int
        Root cell size (voxels, a power of two).
    memory_budget : int, optional
        Bytes of working memory per evaluation chunk (sets progress and abort steps).
    progress : callable(fraction, message), optional
    abort : callable() -> bool, optional
        Checked between evaluation chunks; :class:`~vhm_viz.core.errors.AbortedError`.
    window : (i0, i1, j0, j1, k0, k1), optional
        Build only the root cells that own a voxel of this box (inclusive voxel ranges;
        default: the whole grid). Root cells stay aligned with the whole grid and every
        node's data depends on its position alone, so each root cell's subtree -- and
        every voxel of the window -- is the same as in the whole grid's lattice (to
        rounding: the exact evaluations run in other chunks). For pieces of a volume
        (MPI ranks, streaming): each builds only its own part. Within those root cells
        only the cells that own a voxel of the box are refined. With an ``exchange`` an
        empty box (``i1 < i0``: an MPI rank's empty piece) builds no cell; the builder
        only shares the others' evaluations.
    exchange : callable(keys, evaluate) -> (f, fu, inside), optional
        How the exact evaluations are shared by builders working together (MPI ranks):
        called with the keys (int64, sorted; a key names the same lattice point on every
        builder of the grid) of the points whose data this builder needs, and
        ``evaluate``, which computes the data of any keys here; it returns this builder's
        keys' data, computed wherever it likes (each point's data depends on the point
        alone).
        A collective: it is called exactly :func:`exchange_rounds` ``(root)`` times, in
        the same order on every builder, with zero points where a builder needs none. If
        it has an ``abandon()`` method, that is called when the build fails between two
        calls, so that the others are not left waiting. Default: ``evaluate(points)``.
    pre_images : bool
        False: a lattice for the voxels only (warps and Jacobians), without what only
        the polynomial between voxels needs: the single-voxel cells' twists (zero: at
        their corners, the voxels, every derivative term has a zero weight) and the
        leaves' pre-image summaries. The voxels' values are the same; :meth:`evaluate`,
        :meth:`image_boxes` and :meth:`pull_back` refuse it. On the embryo it saves
        about 1.3 s of the serial warp's 12.7 s (in ParaView), and 26 MB.

    Returns
    -------
    HermiteLattice
    """
    t0 = time.perf_counter()
    tolerance = float(tolerance)
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive number of voxels; got {tolerance}")
    root = int(root)
    if root < 1 or root & (root - 1):
        raise ValueError(f"root must be a power of two; got {root}")
    last = np.asarray(geometry.dimensions, dtype=np.int64) - 1
    n_root = np.maximum(1, -(-last // root))  # root cells per axis
    lattice_dims = n_root * root + 1
    to_index = geometry.index_to_world
    cage = harmonic_map.cage
    V = np.asarray(cage.vertices, dtype=np.float64)
    Fc = np.asarray(cage.faces)
    shells = _Shells(V, Fc)
    # every lattice point's side of the cage (the lattice overhangs the volume)
    lat_geo = ImageGeometry(geometry.origin, geometry.spacing, lattice_dims, geometry.direction)
    table = _NodeTable(lattice_dims)
    n_eval = np.zeros(2, dtype=np.int64)  # inside, outside (continued)
    edge_a, edge_b = _cage_edges_in_index(lat_geo, cage)

    def evaluate(keys):
        points = lat_geo.points(table.ijk(keys).astype(np.float64))
        return _exact_data(harmonic_map, points, to_index, shells, memory_budget, abort)

    rounds, in_round = [0], [False]

    def ensure(ijk):
        keys = np.unique(table.key(ijk.reshape(-1, 3)))
        new = keys[table.find(keys) < 0]
        if exchange is not None:  # every round, with or without points of its own
            in_round[0] = True  # a round that raises has been agreed by everyone
            f, fu, ins = exchange(new, evaluate)
            in_round[0] = False
            rounds[0] += 1
        elif new.size:
            f, fu, ins = evaluate(new)
        if new.size:
            table.add(new, f, fu, ins)
            n_eval[0] += ins.sum()
            n_eval[1] += (~ins).sum()
            del f, fu, ins
        # the round's transients (evaluation chunks, an MPI exchange's messages) leave
        # free pages inside the heap, which the next, larger level would not reuse
        # whole: back to the system (an MPI rank's build peak on the embryo, -10 MB)
        release_free_memory()

    try:
        roots = _window_roots(window, root, n_root, geometry, exchange is not None)
        mask, near = _masks(lat_geo, V, Fc, _mask_rows(window, roots, root))
        lattice = _build_levels(
            ensure, table, harmonic_map, geometry, lat_geo, tolerance, root, last, n_root,
            mask, near, (edge_a, edge_b), roots, None if exchange is not None else abort,
            progress, pre_images=pre_images,
        )  # fmt: skip
        # builders working together meet the same number of times
        for _ in range(exchange_rounds(root) - rounds[0] if exchange is not None else 0):
            ensure(np.zeros((0, 3), dtype=np.int64))
    except BaseException:
        # failed between two rounds: the others are waiting in the next one
        if not in_round[0] and rounds[0] < exchange_rounds(root) and hasattr(
            exchange, "abandon"
        ):
            exchange.abandon()
        raise
    release_free_memory()
    lattice.stats.update(
        evaluations=int(n_eval.sum()),
        evaluations_outside=int(n_eval[1]),
        seconds=time.perf_counter() - t0,
    )
    if progress is not None:
        progress(1.0, "lattice")
    return lattice


#: The arrays of :meth:`HermiteLattice.part`: per leaf (first axis: leaves) but ``data``
#: (first axis: the data rows the leaves read); their trailing shapes and dtypes.
PART_FIELDS = {
    "order": ((2,), np.int64),
    "origin": ((3,), np.int64),
    "size": ((), np.int64),
    "cut": ((), np.bool_),
    "rows": ((8,), np.int64),
    "data": ((_N_TERMS, 3), np.float64),
    "centre_f": ((3,), np.float64),
    "centre_ginv": ((3, 3), np.float64),
    "rho": ((), np.float64),
}


def join_parts(parts, harmonic_map, geometry: ImageGeometry, *, tolerance: float,
               root: int = DEFAULT_ROOT, stats=None) -> HermiteLattice:  # fmt: skip
    """One lattice of the leaves of several lattices' parts (:meth:`HermiteLattice.part`).

    The parts come from lattices of the same map and grid (windows of it: MPI ranks);
    no leaf may be in two parts. The leaves are ordered as in the whole grid's lattice
    (by root cell, then as each root cell's build made them), so that resampling with
    the joined lattice visits the same leaves in the same order as with the whole one:
    where those leaves are all the leaves whose images reach the output voxels
    resampled, their pre-images are the whole lattice's, bit for bit. The joined lattice
    has no masks, only the inside and surface flags around the leaves the cage crosses
    (:meth:`HermiteLattice.cut_flags`), the only ones the pull-back reads.

    Parameters
    ----------
    parts : list of dict
        :data:`PART_FIELDS` arrays; each is released (set to None) once joined, so that
        the parts and the lattice are not held twice.
    harmonic_map : HarmonicMap
    geometry : ImageGeometry
        The input grid.
    tolerance : float
        The lattices' tolerance (voxels).
    root : int
        Their root cell size.
    stats : dict, optional
        Build statistics to keep (evaluations...); leaf counts are the join's.
    """
    last = np.asarray(geometry.dimensions, dtype=np.int64) - 1
    n_root = np.maximum(1, -(-last // root))
    lat_geo = ImageGeometry(geometry.origin, geometry.spacing, n_root * root + 1,
                            geometry.direction)  # fmt: skip
    # each part's rows index its own data: shifted past the parts joined before it
    offsets = np.cumsum([0] + [len(p["data"]) for p in parts])
    joined = {}
    for name, (shape, dtype) in PART_FIELDS.items():
        arrays = [p[name] for p in parts]
        if name == "rows":
            arrays = [a + offsets[n] for n, a in enumerate(arrays)]
        joined[name] = np.concatenate(arrays or [np.zeros((0,) + shape, dtype=dtype)])
        del arrays
        for p in parts:  # each part's arrays go as soon as they are joined
            p[name] = None
        release_free_memory()  # their heap pages too: the next field may not fit them
    order = joined.pop("order")
    data = joined.pop("data")
    perm = np.lexsort((order[:, 1], order[:, 0]))
    leaf = {name: np.ascontiguousarray(a[perm]) for name, a in joined.items()}
    rkey = order[perm, 0]
    start, count = _root_index(rkey, n_root)
    h = leaf["size"]
    cage = harmonic_map.cage
    edge_a, edge_b = _cage_edges_in_index(lat_geo, cage)
    joined = HermiteLattice(
        geometry=geometry,
        tolerance=float(tolerance),
        root=int(root),
        n_root=n_root.astype(np.int64),
        data=data,
        leaf_origin=leaf["origin"],
        leaf_size=leaf["size"],
        leaf_rows=leaf["rows"],
        leaf_cut=leaf["cut"],
        root_start=start,
        root_count=count,
        centre_f=leaf["centre_f"],
        centre_ginv=leaf["centre_ginv"],
        rho=leaf["rho"],
        mask=None,
        near=None,
        edge_a=edge_a,
        edge_b=edge_b,
        stats={**(stats or {}), **_leaf_stats(h, len(data))},
        pre_images=True,
    )
    # no masks: the pull-back reads flags only around the leaves the cage crosses. The
    # masks over the rows of all the joined leaves were 23 MB of an MPI rank's pull-back
    # peak on the embryo
    joined.cut_flags(lat_geo, np.asarray(cage.vertices, dtype=np.float64), np.asarray(cage.faces))
    return joined


def _root_keys(origin, root, n_root) -> np.ndarray:
    """Root cell of leaves at ``origin`` (voxels), as one int64 key (i fastest)."""
    rid = origin // root
    return rid[:, 0] + n_root[0] * (rid[:, 1] + n_root[1] * rid[:, 2])


def _root_index(rkey, n_root):
    """``(start, count)`` per root cell of leaves sorted by root key (:func:`_locate`)."""
    count = np.bincount(rkey, minlength=int(np.prod(n_root))).astype(np.int64)
    return np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64), count


def _leaf_stats(size, data_rows: int) -> dict:
    """A lattice's leaf counts (``stats``): leaves, leaves per size, data rows."""
    sizes, per_size = np.unique(size, return_counts=True)
    return {
        "leaves": int(len(size)),
        "leaves_per_size": {int(s): int(c) for s, c in zip(sizes, per_size, strict=True)},
        "data_rows": int(data_rows),
    }


def _window_roots(window, root, n_root, geometry, shared):
    """The window (validated) and the range of root cells it builds, per axis.

    Returns ``(w, lo_root, hi_root)``: ``w`` None for the whole grid, or for an empty
    piece of a shared build (more MPI ranks than planes: no cells of its own, but its
    builder still evaluates its share of the others' points; then ``hi_root < lo_root``).
    """
    lo_root, hi_root = np.zeros(3, dtype=np.int64), n_root - 1
    if window is None:
        return None, lo_root, hi_root
    w = np.asarray(window, dtype=np.int64).reshape(6)
    if shared and (w[1::2] < w[0::2]).any():
        return None, lo_root, np.full(3, -1, dtype=np.int64)
    last = np.asarray(geometry.dimensions, dtype=np.int64) - 1
    if (w[0::2] < 0).any() or (w[1::2] > last).any() or (w[1::2] < w[0::2]).any():
        raise ValueError(f"window {w.tolist()} is not inside the grid of dimensions "
                         f"{tuple(geometry.dimensions)}")  # fmt: skip
    # a root cell owns [o, o + root); the grid's last voxel belongs to the last cell
    return w, np.minimum(w[0::2] // root, n_root - 1), np.minimum(w[1::2] // root, n_root - 1)


def _mask_rows(window, roots, root):
    """The lattice rows ``(j0, j1, k0, k1)`` of a window's root cells (None: every row).

    Outside them a window's build reads neither mask (its cells are those root cells).
    """
    if window is None:
        return None
    _, lo_root, hi_root = roots
    if (hi_root < lo_root).any():  # an empty piece: no cells, no rows
        return (0, 0, 0, 0)
    lo, hi = lo_root * root, (hi_root + 1) * root + 1  # up to the far corners
    return (int(lo[1]), int(hi[1]), int(lo[2]), int(hi[2]))


# k-planes of the lattice's masks computed at a time (see _masks).
_MASK_PLANES = 16


def _masks(lat_geo: ImageGeometry, vertices, faces, rows):
    """Inside and next-to-the-surface masks of the lattice points, computed in ``rows``.

    Both have the whole lattice's shape. Outside ``rows`` (default: all) they stay False
    and their zero pages are never written, so a window's build holds the memory of its
    own rows only (an MPI rank's half of the embryo: 17 MB less). They are made
    ``_MASK_PLANES`` k-planes at a time: :func:`~vhm_viz.core.image.inside_mask` keeps
    16-bit winding numbers of the points it is asked for, and a whole window's (26 MB on
    the embryo) plus its copy into the masks were the joined lattice's peak. A row's
    values do not depend on which others are computed with it; by planes it also ran
    2.5x faster (0.06 s against 0.15 s for 200 planes of the embryo's lattice).
    """
    nx, ny, nz = lat_geo.dimensions
    j0, j1, k0, k1 = (0, ny, 0, nz) if rows is None else rows
    mask = np.zeros((nz, ny, nx), dtype=bool)
    near = np.zeros((nz, ny, nx), dtype=bool)
    if j1 > j0:
        for a in range(k0, k1, _MASK_PLANES):
            b = min(k1, a + _MASK_PLANES)
            mask[a:b, j0:j1] = inside_mask(lat_geo, vertices, faces, rows=(j0, j1, a, b))
            near[a:b, j0:j1] = surface_mask(lat_geo, vertices, faces, rows=(j0, j1, a, b))
    return mask, near


def exchange_rounds(root: int) -> int:
    """How many times :func:`build_lattice` calls its ``exchange`` for a root cell size.

    Two per level with cells larger than a voxel (their corners and test points, then the
    points the twists read), one for single-voxel cells.
    """
    return 2 * int(math.log2(int(root))) + 1


def _build_levels(
    ensure, table, harmonic_map, geometry, lat_geo, tolerance, root, last, n_root, mask,
    near, edges, roots, abort, progress, pre_images=True,
):  # fmt: skip
    """The level loop of :func:`build_lattice`: refine cells until they fit the map."""
    V = np.asarray(harmonic_map.cage.vertices, dtype=np.float64)
    Fc = np.asarray(harmonic_map.cage.faces)
    to_voxel = np.ascontiguousarray(geometry.world_to_index)
    edge_a, edge_b = edges
    end = n_root * root
    w, lo_root, hi_root = roots
    ranges = [np.arange(lo_root[a], hi_root[a] + 1) for a in range(3)]
    g = np.stack(np.meshgrid(*ranges[::-1], indexing="ij"), -1)
    cells = (g.reshape(-1, 3)[:, ::-1] * root).astype(np.int64)
    leaves: list = []
    level_data: list = []
    h = root
    n_levels = int(math.log2(root)) + 1
    while len(cells):
        if abort is not None and abort():
            raise AbortedError("aborted")
        if w is not None and h < root:
            # only cells that own a voxel of the window matter (each cell's refinement is
            # its own: the window's leaves are the whole lattice's)
            cells = cells[_owns_voxel_of(cells, h, end, w)]
        # only cells with a voxel inside the cage matter
        counts = np.zeros((len(cells), 3), dtype=np.int64)
        _count_inside(mask, near, cells, h, last, counts)
        keep = counts[:, 0] > 0
        # cut: the cage passes through the cell (voxels outside, or next to the surface)
        cells, cut = cells[keep], (counts[keep, 1] > 0) | (counts[keep, 2] > 0)
        del counts, keep
        if not len(cells):
            break
        corners = cells[:, None, :] + _CORNERS[None] * h
        if h > 1:
            offsets = _test_points(cells, h, lat_geo, V, Fc)
            has = np.isfinite(offsets[..., 0])
            tests = cells[:, None, :] + np.rint(np.nan_to_num(offsets) * h).astype(np.int64)
            ensure(np.concatenate([corners.reshape(-1, 3), tests[has]]))
        else:
            ensure(corners.reshape(-1, 3))
        # the corners as rows of the level's keys, (n, 8), before the level's data is
        # made: the corners themselves, (n, 8, 3), were held through it, 40 MB of the
        # serial embryo's build peak at its finest level
        corner_keys = table.key(corners)
        del corners
        level_keys = np.unique(corner_keys)
        rows = np.searchsorted(level_keys, corner_keys)
        del corner_keys
        if h > 1:
            # single-voxel cells skip the stencil: their corners are voxels, which the
            # warp and the Jacobians read exactly whatever the twists; it saved 238,089
            # of 790,199 evaluations on the embryo (see _level_data)
            ensure(_stencil_points(table, level_keys, h))
        if h == 1:
            # the finest level, the last: the table keeps only the nodes its data reads
            # before that data is made beside it. The others (corners and test points of
            # coarser levels) were 11 MB of an MPI rank's build peak on the embryo
            table.keep(_rows_read(table, level_keys, h, twists=pre_images))
        data = _level_data(table, level_keys, h, twists=pre_images or h > 1)
        split = np.zeros(len(cells), dtype=bool)
        if h > 1:
            test_rows = np.where(has, table.find(table.key(tests)), -1)
            err = np.empty(len(cells))
            _test_errors(
                data, rows, float(h), np.nan_to_num(offsets), test_rows, table.f, to_voxel, err
            )
            near_edge = np.zeros(len(cells), dtype=np.bool_)
            _near_edges(cells, h, edge_a, edge_b, _EDGE_BAND, near_edge)
            split = (err > _SAFETY * tolerance) | near_edge
            # (not carried into the next, finer level's peak)
            del offsets, has, tests, test_rows, err, near_edge
        level_data.append(data)
        leaves.append((cells[~split], h, len(level_data) - 1, rows[~split], cut[~split]))
        if progress is not None:
            progress(min(0.95, len(level_data) / n_levels), "lattice")
        if not split.any():
            break
        cells = (cells[split][:, None, :] + _CORNERS[None] * (h // 2)).reshape(-1, 3)
        h //= 2
    # the levels hold their own copies of the node data: hand the table's memory back
    # before the levels are packed (and let go of the last level: _assemble grows it)
    data = None
    table.clear()
    release_free_memory()
    return _assemble(
        leaves, level_data, n_root, root, geometry, tolerance, mask, near, edges, pre_images
    )


def _owns_voxel_of(cells, h, end, box) -> np.ndarray:
    """Which cells of size ``h`` own a voxel of ``box`` (as :func:`_owned_range` counts)."""
    far = cells + h - 1 + (cells + h == end)  # the lattice's far end: the last cell's
    return np.all((cells <= box[1::2]) & (far >= box[0::2]), axis=1)


def _assemble(
    leaves, level_data, n_root, root, geometry, tolerance, mask, near, edges, pre_images=True
):
    """Pack the levels into one data table and the leaves, grouped by root cell."""
    # packed level by level, each level freed once copied. The largest level (the
    # finest, most of the table: 77 MB of the embryo's) comes first and is grown in place
    # into the table (realloc remaps a large block rather than copying it), so that the
    # peak is the packed table, not the table plus that level
    sizes = [len(d) for d in level_data]
    big = int(np.argmax(sizes)) if sizes else -1
    packing = ([big] if sizes else []) + [lv for lv in range(len(sizes)) if lv != big]
    starts = np.zeros(len(sizes), dtype=np.int64)
    starts[packing] = np.cumsum([0] + [sizes[lv] for lv in packing])[:-1]
    total = int(sum(sizes))
    data = _grown(level_data, big, total - sizes[big]) if sizes else np.empty((0, _N_TERMS, 3))
    for lv in packing[1:]:
        data[starts[lv] : starts[lv] + sizes[lv]] = level_data[lv]
        level_data[lv] = None
        release_free_memory()  # the level's heap pages too, not only its array
    origin = np.concatenate([c for c, *_ in leaves] or [np.zeros((0, 3), np.int64)])
    size = np.concatenate([np.full(len(c), s, np.int64) for c, s, *_ in leaves] or [[]])
    rows = np.concatenate(
        [r + starts[lv] for _, _, lv, r, _ in leaves] or [np.zeros((0, 8), np.int64)]
    )
    cut = np.concatenate([c for *_, c in leaves] or [np.zeros(0, bool)])
    rkey = _root_keys(origin, root, n_root)
    order = np.argsort(rkey, kind="stable")
    # one at a time, each old array freed before the next is reordered
    origin = origin[order]
    size = size.astype(np.int64)[order]
    rows = rows[order]
    cut = cut[order]
    rkey = rkey[order]
    release_free_memory()
    start, count = _root_index(rkey, n_root)
    n = len(origin)
    m = n if pre_images else 0
    centre_f, centre_ginv, rho = np.empty((m, 3)), np.empty((m, 3, 3)), np.empty(m)
    if m:
        _leaf_summaries(data, rows, size, centre_f, centre_ginv, rho)
    stats = _leaf_stats(size, len(data))
    return HermiteLattice(
        geometry=geometry,
        tolerance=tolerance,
        root=root,
        n_root=n_root.astype(np.int64),
        data=data,
        leaf_origin=np.ascontiguousarray(origin),
        leaf_size=np.ascontiguousarray(size),
        leaf_rows=np.ascontiguousarray(rows),
        leaf_cut=np.ascontiguousarray(cut),
        root_start=start,
        root_count=count,
        centre_f=centre_f,
        centre_ginv=centre_ginv,
        rho=rho,
        mask=mask,
        near=near,
        edge_a=edges[0],
        edge_b=edges[1],
        stats=stats,
        pre_images=bool(pre_images),
    )


# --------------------------------------------------------------------------------------
# using the lattice (compiled)
# --------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _owned_range(o, h, end, lo, hi):  # pragma: no cover - compiled
    """Voxels ``[a, b]`` (inclusive) of one axis owned by a leaf, within ``[lo, hi]``.

    A leaf owns ``[o, o + h)``; the lattice's far end belongs to the last leaf.
    """
    a = max(o, lo)
    b = o + h - 1
    if o + h == end:
        b = o + h
    return a, min(b, hi)


@numba.njit(inline="always", cache=True)
def _owned_box(origin, h, end, box, n):  # pragma: no cover - compiled
    """The voxels of ``box`` owned by leaf ``n``: ``(ia, ib, ja, jb, ka, kb)`` inclusive."""
    ia, ib = _owned_range(origin[n, 0], h, end[0], box[0], box[1])
    ja, jb = _owned_range(origin[n, 1], h, end[1], box[2], box[3])
    ka, kb = _owned_range(origin[n, 2], h, end[2], box[4], box[5])
    return ia, ib, ja, jb, ka, kb


@numba.njit(parallel=True, cache=True)
def _leaf_voxels(data, rows, origin, size, leaves, end, box, mask, jacobians, to_index, out):
    """Interpolated positions (or u-Jacobians) of the inside voxels of a box, leaf by leaf.

    ``box = (i0, i1, j0, j1, k0, k1)`` (inclusive voxel ranges); ``out`` is the box's
    (P, 3) positions or (P, 3, 3) world Jacobians ``df/du @ to_index`` (``jacobians``;
    ``to_index`` = du/dx), i fastest. Positions are
    evaluated separably: per voxel row the polynomial is reduced to 4 cubic terms in u,
    then each voxel costs 12 products.
    """
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    for q in numba.prange(leaves.shape[0]):
        n = leaves[q]
        h = size[n]
        hf = float(h)
        ia, ib, ja, jb, ka, kb = _owned_box(origin, h, end, box, n)
        wv = np.empty(4)
        ww = np.empty(4)
        qrow = np.empty((2, 2, 3))
        f = np.empty(3)
        g = np.empty((3, 3))
        gw = np.empty((3, 3))
        r = rows[n]
        for k in range(ka, kb + 1):
            ww[0], ww[1], ww[2], ww[3], _, _, _, _ = _weights((k - origin[n, 2]) / hf, hf)
            for j in range(ja, jb + 1):
                base = ((k - box[4]) * ny + (j - box[2])) * nx - box[0]
                if jacobians:
                    for i_ in range(ia, ib + 1):
                        if mask[k, j, i_]:
                            _cell_eval(
                                data, r, hf, (i_ - origin[n, 0]) / hf, (j - origin[n, 1]) / hf,
                                (k - origin[n, 2]) / hf, f, g, True,
                            )  # fmt: skip
                            for a in range(3):
                                for b in range(3):
                                    gw[a, b] = (
                                        g[a, 0] * to_index[0, b]
                                        + g[a, 1] * to_index[1, b]
                                        + g[a, 2] * to_index[2, b]
                                    )
                            out[base + i_] = gw
                    continue
                wv[0], wv[1], wv[2], wv[3], _, _, _, _ = _weights((j - origin[n, 1]) / hf, hf)
                # reduce to 4 terms in u: qrow[a, ku] = sum over (b, c, kv, kw)
                qrow[:] = 0.0
                for c in range(2):
                    for b in range(2):
                        for kw in range(2):
                            for kv in range(2):
                                s = wv[2 * b + kv] * ww[2 * c + kw]
                                for a in range(2):
                                    node = r[a + 2 * b + 4 * c]
                                    for ku in range(2):
                                        t = _term(ku, kv, kw)
                                        for i in range(3):
                                            qrow[a, ku, i] += s * data[node, t, i]
                for i_ in range(ia, ib + 1):
                    if not mask[k, j, i_]:
                        continue
                    a0, a1, a2, a3, _, _, _, _ = _weights((i_ - origin[n, 0]) / hf, hf)
                    for i in range(3):
                        out[base + i_, i] = (
                            a0 * qrow[0, 0, i]
                            + a1 * qrow[0, 1, i]
                            + a2 * qrow[1, 0, i]
                            + a3 * qrow[1, 1, i]
                        )


@numba.njit(parallel=True, cache=True)
def _eval_points(data, rows, origin, size, leaf, u, f, g):  # pragma: no cover - compiled
    for p in numba.prange(u.shape[0]):
        n = leaf[p]
        h = float(size[n])
        fp = np.empty(3)
        gp = np.empty((3, 3))
        _cell_eval(
            data, rows[n], h, (u[p, 0] - origin[n, 0]) / h, (u[p, 1] - origin[n, 1]) / h,
            (u[p, 2] - origin[n, 2]) / h, fp, gp, True,
        )  # fmt: skip
        f[p] = fp
        g[p] = gp


@numba.njit(parallel=True, cache=True)
def _locate(origin, size, root_start, root_count, n_root, root, u, out):  # pragma: no cover
    """Leaf owning each point: half-open boxes ``[o, o + h)``, closed at the lattice's end.

    Points beyond the lattice are clamped onto it; points in pruned cells get -1.
    """
    for p in numba.prange(u.shape[0]):
        out[p] = -1
        x = np.empty(3)
        r = 0
        scale = 1
        for a in range(3):
            top = n_root[a] * root
            x[a] = min(max(u[p, a], 0.0), float(top))
            ra = min(int(math.floor(x[a] / root)), n_root[a] - 1)
            r += ra * scale
            scale *= n_root[a]
        for n in range(root_start[r], root_start[r] + root_count[r]):
            ok = True
            for a in range(3):
                lo = origin[n, a]
                hi = lo + size[n]
                if x[a] < lo or x[a] > hi or (x[a] == hi and hi != n_root[a] * root):
                    ok = False
                    break
            if ok:
                out[p] = n
                break


@numba.njit(cache=True)
def _clip_net(cp, axis, t0, t1):  # pragma: no cover - compiled
    """Restrict a tricubic Bezier net to ``t0 <= t <= t1`` along one axis (de Casteljau).

    The new net's control points bound the image of the restricted cell only.
    """
    b = np.empty((4, 3))
    for line in range(16):
        # the 4 control points of this line along ``axis``
        idx = np.empty(4, dtype=np.int64)
        for q in range(4):
            if axis == 0:
                idx[q] = q + 4 * (line % 4) + 16 * (line // 4)
            elif axis == 1:
                idx[q] = (line % 4) + 4 * q + 16 * (line // 4)
            else:
                idx[q] = (line % 4) + 4 * (line // 4) + 16 * q
        for q in range(4):
            b[q] = cp[idx[q]]
        # keep [0, t1]: the left half of a split at t1
        for r in range(1, 4):
            for q in range(3, r - 1, -1):
                b[q] = (1.0 - t1) * b[q - 1] + t1 * b[q]
        # keep [t0 / t1, 1] of that: the right half of a split
        s = t0 / t1 if t1 > 0.0 else 0.0
        for r in range(1, 4):
            for q in range(0, 4 - r):
                b[q] = (1.0 - s) * b[q] + s * b[q + 1]
        for q in range(4):
            cp[idx[q]] = b[q]


@numba.njit(parallel=True, cache=True)
def _output_boxes(data, rows, origin, size, lower, upper, origin_out, to_out, margin, lo, hi):
    """Per leaf: the box of output-grid indices its image can reach.

    The control points bound the image of the cell, restricted to the input region
    ``lower <= u <= upper`` (the volume: cells overhang it); ``margin[n]`` (input voxels)
    around that adds at most that times the largest corner Jacobian (output voxels per
    input voxel), a first-order bound that the rounding of the box to whole voxels covers.
    """  # noqa: D401
    for n in numba.prange(rows.shape[0]):
        h = float(size[n])
        cp = np.empty((64, 3))
        _control_points(data, rows[n], h, cp)
        for a in range(3):
            t0 = max((lower[a] - origin[n, a]) / h, 0.0)
            t1 = min((upper[a] - origin[n, a]) / h, 1.0)
            if t0 > 0.0 or t1 < 1.0:
                _clip_net(cp, a, t0, max(t1, t0))
        for a in range(3):
            lo[n, a] = np.inf
            hi[n, a] = -np.inf
        for q in range(64):
            for a in range(3):
                v = 0.0
                for b in range(3):
                    v += to_out[a, b] * (cp[q, b] - origin_out[b])
                lo[n, a] = min(lo[n, a], v)
                hi[n, a] = max(hi[n, a], v)
        for a in range(3):
            pad = 0.0
            for corner in range(8):
                r = rows[n, corner]
                s = 0.0
                for t in range(1, 4):  # |d(out_a)/du_t| summed over t
                    d = 0.0
                    for b in range(3):
                        d += to_out[a, b] * data[r, t, b]
                    s += abs(d)
                pad = max(pad, s)
            lo[n, a] -= margin[n] * pad
            hi[n, a] += margin[n] * pad


@numba.njit(cache=True)
def _candidate_rows(leaves, ilo, ihi, box, row_start, row_leaf, row_i0, row_i1):  # pragma: no cover
    """Rows of an output box and the leaves whose image boxes cross each (CSR).

    ``ilo, ihi`` (L, 3) int: inclusive output index boxes of the leaves; the box is
    ``(i0, i1, j0, j1, k0, k1)``. First call with ``row_leaf`` empty counts into
    ``row_start`` (length rows + 1); the second fills.
    """
    ny = box[3] - box[2] + 1
    fill = row_leaf.shape[0] > 0
    pos = row_start.copy()
    for q in range(leaves.shape[0]):
        n = leaves[q]
        a = max(ilo[n, 0], box[0])
        b = min(ihi[n, 0], box[1])
        if a > b:
            continue
        for k in range(max(ilo[n, 2], box[4]), min(ihi[n, 2], box[5]) + 1):
            for j in range(max(ilo[n, 1], box[2]), min(ihi[n, 1], box[3]) + 1):
                r = (k - box[4]) * ny + (j - box[2])
                if fill:
                    row_leaf[pos[r]] = n
                    row_i0[pos[r]] = a
                    row_i1[pos[r]] = b
                    pos[r] += 1
                else:
                    row_start[r + 1] += 1


# Edge of the blocks in which the inside and surface flags around the leaves the cage
# crosses are kept for the pull-back (:func:`_cut_blocks`): 8^3 lattice points, 512 bytes.
_BLOCK = 8


@numba.njit(cache=True)
def _mark_cut_blocks(origin, size, cut, margin, dims, marks):  # pragma: no cover
    """Mark the blocks holding the grid cubes around the pre-images of the cut leaves.

    A pre-image lies within its leaf grown by its margin (:meth:`HermiteLattice.margins`);
    :func:`_inside_around` reads the 8 corners of the grid cube around it.
    """
    lo = np.empty(3, dtype=np.int64)
    hi = np.empty(3, dtype=np.int64)
    for n in range(origin.shape[0]):
        if not cut[n]:
            continue
        for a in range(3):
            lo[a] = min(max(int(math.floor(origin[n, a] - margin[n])), 0), dims[a] - 2)
            hi[a] = min(max(int(math.floor(origin[n, a] + size[n] + margin[n])), 0), dims[a] - 2)
            hi[a] += 1
        for kb in range(lo[2] // _BLOCK, hi[2] // _BLOCK + 1):
            for jb in range(lo[1] // _BLOCK, hi[1] // _BLOCK + 1):
                for ib in range(lo[0] // _BLOCK, hi[0] // _BLOCK + 1):
                    marks[kb, jb, ib] = True


def _cut_blocks(lattice, lat_geo=None, vertices=None, faces=None):
    """The inside and surface flags around the leaves the cage crosses, in blocks.

    Returns ``(block_of, pool, dims)``: ``pool`` (B, 8, 8, 8) uint8 holds the flags of
    blocks of ``_BLOCK``^3 lattice points (bit 0 inside, bit 1 next to the surface).
    ``block_of[kb, jb, ib]``: the block's row of ``pool`` (-1: not kept); ``dims``: the
    lattice's points per axis. Taken from the lattice's masks, or computed from the cage
    (``lat_geo``, ``vertices``, ``faces``) for a lattice without them (a joined one): the
    same values, a row's flags not depending on which other rows are computed.
    """
    dims = np.asarray(lattice.end + 1, dtype=np.int64)  # (nx, ny, nz)
    nb = -(-dims // _BLOCK)
    marks = np.zeros((nb[2], nb[1], nb[0]), dtype=np.bool_)
    if len(lattice.leaf_size):
        _mark_cut_blocks(lattice.leaf_origin, lattice.leaf_size, lattice.leaf_cut,
                         lattice.margins(), dims, marks)  # fmt: skip
    block_of = np.full(marks.shape, -1, dtype=np.int64)
    block_of[marks] = np.arange(int(marks.sum()))
    pool = np.zeros((int(marks.sum()), _BLOCK, _BLOCK, _BLOCK), dtype=np.uint8)
    for kb in np.nonzero(marks.any(axis=(1, 2)))[0]:
        kb_marks = marks[kb]
        jbs = np.nonzero(kb_marks.any(axis=1))[0]
        k0, k1 = kb * _BLOCK, min((kb + 1) * _BLOCK, dims[2])
        j0, j1 = jbs[0] * _BLOCK, min((jbs[-1] + 1) * _BLOCK, dims[1])
        if lattice.mask is not None:
            inside = lattice.mask[k0:k1, j0:j1]
            near = lattice.near[k0:k1, j0:j1]
        else:
            inside = inside_mask(lat_geo, vertices, faces, rows=(j0, j1, k0, k1))
            near = surface_mask(lat_geo, vertices, faces, rows=(j0, j1, k0, k1))
        flags = inside.astype(np.uint8) | (near.astype(np.uint8) << 1)
        for jb, ib in zip(*np.nonzero(kb_marks), strict=True):
            a, b = jb * _BLOCK - j0, ib * _BLOCK
            block = flags[:, a : a + _BLOCK, b : b + _BLOCK]
            pool[block_of[kb, jb, ib], : block.shape[0], : block.shape[1], : block.shape[2]] = block
    return block_of, pool, dims


@numba.njit(cache=True)
def _inside_around(block_of, pool, dims, u):  # pragma: no cover - compiled
    """Whether ``u`` is inside the cage, from the grid cube around it.

    8 (inside) or 0 (outside) when the cage does not cross the cube's edges and the
    corners agree; -1 (ask the winding number) when the surface runs next to the cube, or
    the cube's flags were not kept (:func:`_cut_blocks`).
    """
    i0 = min(max(int(math.floor(u[0])), 0), dims[0] - 2)
    j0 = min(max(int(math.floor(u[1])), 0), dims[1] - 2)
    k0 = min(max(int(math.floor(u[2])), 0), dims[2] - 2)
    count = 0
    for c in range(2):
        for b in range(2):
            for a in range(2):
                k, j, i = k0 + c, j0 + b, i0 + a
                blk = block_of[k // _BLOCK, j // _BLOCK, i // _BLOCK]
                if blk < 0:
                    return -1
                flags = pool[blk, k % _BLOCK, j % _BLOCK, i % _BLOCK]
                if flags & 2:
                    return -1
                if flags & 1:
                    count += 1
    return count if count == 0 or count == 8 else -1


@numba.njit(parallel=True, cache=True)
def _pull_back_rows(
    data, rows, origin, size, cut, centre_f, centre_ginv, rho, margin, block_of, pool, dims,
    last, origin_out, to_world_out, box, row_start, row_leaf, row_i0, row_i1,
    u_out, state, fold, quality,
):  # pragma: no cover - compiled  # fmt: skip
    """Pre-images of the output voxels of a box: Newton on the leaves' polynomials.

    For every row of the box and every leaf whose image box crosses it, each voxel ``y``
    gets a linear pre-image estimate from the leaf's centre; a leaf more than ``rho`` plus
    the margin away is skipped, otherwise Newton's method on the leaf's polynomial starts
    from that estimate (or from the previous voxel's pre-image, advanced by the inverse
    Jacobian). A converged pre-image within the margin of its leaf and within the input
    volume's half-voxel border is kept:

    * ``state`` 1 (inside the cage), or 2 when the leaf crosses the cage and the voxels
      around it disagree (the caller checks those with the winding number);
    * a second pre-image more than one voxel from the first marks a fold (``fold`` 1); a
      nearer one (the same point, found from a neighbouring leaf) replaces the first when
      it lies deeper inside its leaf (``quality`` = distance outside the leaf).
    """
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    n_rows = row_start.shape[0] - 1
    step = np.empty(3)
    for a in range(3):
        step[a] = to_world_out[a, 0]
    for r in numba.prange(n_rows):
        k = box[4] + r // ny
        j = box[2] + r % ny
        y = np.empty(3)
        ul = np.empty(3)
        u = np.empty(3)
        f = np.empty(3)
        g = np.empty((3, 3))
        gi = np.empty((3, 3))
        prev1 = np.empty(3)
        prev2 = np.empty(3)
        for c in range(row_start[r], row_start[r + 1]):
            n = row_leaf[c]
            h = float(size[n])
            lim = 0.5 * h + rho[n] + margin[n]
            chained = 0  # consecutive converged voxels before this one
            for i_ in range(row_i0[c], row_i1[c] + 1):
                for a in range(3):
                    y[a] = origin_out[a] + to_world_out[a, 0] * i_ + (
                        to_world_out[a, 1] * j + to_world_out[a, 2] * k
                    )
                far = False
                for a in range(3):
                    d = 0.0
                    for b in range(3):
                        d += centre_ginv[n, a, b] * (y[b] - centre_f[n, b])
                    ul[a] = origin[n, a] + 0.5 * h + d
                    if not abs(d) <= lim:  # also catches NaN
                        far = True
                if far:
                    chained = 0
                    continue
                v = ((k - box[4]) * ny + (j - box[2])) * nx + (i_ - box[0])
                if state[v] == 1 and quality[v] == 0.0:
                    # a pre-image inside its own leaf is known: a pre-image in this leaf
                    # (within rho of the estimate) more than a voxel away would be a fold
                    gap = 0.0
                    for a in range(3):
                        gap = max(gap, abs(ul[a] - u_out[v, a]))
                    if gap + rho[n] < 1.0:
                        chained = 0
                        continue
                if chained >= 3:
                    # the pre-images of a row are smooth: quadratic extrapolation
                    for a in range(3):
                        nxt = 3.0 * u[a] - 3.0 * prev1[a] + prev2[a]
                        prev2[a] = prev1[a]
                        prev1[a] = u[a]
                        u[a] = nxt
                elif chained > 0:
                    # previous pre-image advanced by the inverse Jacobian (one voxel along i)
                    for a in range(3):
                        d = 0.0
                        for b in range(3):
                            d += gi[a, b] * step[b]
                        prev2[a] = prev1[a]
                        prev1[a] = u[a]
                        u[a] += d
                else:
                    for a in range(3):
                        u[a] = ul[a]
                ok = False
                for _ in range(_NEWTON_ITERATIONS):
                    _cell_eval(
                        data, rows[n], h, (u[0] - origin[n, 0]) / h, (u[1] - origin[n, 1]) / h,
                        (u[2] - origin[n, 2]) / h, f, g, True,
                    )  # fmt: skip
                    det = (
                        g[0, 0] * (g[1, 1] * g[2, 2] - g[1, 2] * g[2, 1])
                        - g[0, 1] * (g[1, 0] * g[2, 2] - g[1, 2] * g[2, 0])
                        + g[0, 2] * (g[1, 0] * g[2, 1] - g[1, 1] * g[2, 0])
                    )
                    if not abs(det) > 1e-300:
                        break
                    inv = 1.0 / det
                    gi[0, 0] = (g[1, 1] * g[2, 2] - g[1, 2] * g[2, 1]) * inv
                    gi[0, 1] = (g[0, 2] * g[2, 1] - g[0, 1] * g[2, 2]) * inv
                    gi[0, 2] = (g[0, 1] * g[1, 2] - g[0, 2] * g[1, 1]) * inv
                    gi[1, 0] = (g[1, 2] * g[2, 0] - g[1, 0] * g[2, 2]) * inv
                    gi[1, 1] = (g[0, 0] * g[2, 2] - g[0, 2] * g[2, 0]) * inv
                    gi[1, 2] = (g[0, 2] * g[1, 0] - g[0, 0] * g[1, 2]) * inv
                    gi[2, 0] = (g[1, 0] * g[2, 1] - g[1, 1] * g[2, 0]) * inv
                    gi[2, 1] = (g[0, 1] * g[2, 0] - g[0, 0] * g[2, 1]) * inv
                    gi[2, 2] = (g[0, 0] * g[1, 1] - g[0, 1] * g[1, 0]) * inv
                    big = 0.0
                    for a in range(3):
                        d = 0.0
                        for b in range(3):
                            d += gi[a, b] * (y[b] - f[b])
                        u[a] += d
                        big = max(big, abs(d))
                    if not big < 2.0 * h:  # diverging (or NaN)
                        break
                    if big < _NEWTON_STEP:
                        ok = True
                        break
                chained = chained + 1 if ok else 0
                if not ok:
                    continue
                q = 0.0
                inside_vol = True
                for a in range(3):
                    # beyond the volume's boundary the border takes over from the margin
                    below = origin[n, a] - u[a] - (BORDER if origin[n, a] <= 0 else 0.0)
                    above = u[a] - origin[n, a] - h - (
                        BORDER if origin[n, a] + size[n] >= last[a] else 0.0
                    )
                    q = max(q, below, above)
                    if u[a] < -BORDER or u[a] > last[a] + BORDER:
                        inside_vol = False
                if q > _MARGIN or not inside_vol:
                    continue
                s = 1
                if cut[n]:
                    around = _inside_around(block_of, pool, dims, u)
                    if around == 0:
                        continue
                    if around < 0:
                        s = 2
                if state[v] == 0 or (state[v] == 2 and s == 1):
                    state[v] = s
                    quality[v] = q
                    for a in range(3):
                        u_out[v, a] = u[a]
                elif state[v] == s:
                    apart = 0.0
                    for a in range(3):
                        apart = max(apart, abs(u[a] - u_out[v, a]))
                    if apart > 1.0:
                        fold[v] = 1
                    elif q < quality[v]:
                        quality[v] = q
                        for a in range(3):
                            u_out[v, a] = u[a]


# --------------------------------------------------------------------------------------
# the lattice object
# --------------------------------------------------------------------------------------
class HermiteLattice:
    """The adaptive Hermite lattice of a harmonic map over an image grid.

    Built by :func:`build_lattice`. Positions ``u`` are continuous voxel indices of the
    input grid (``geometry``); values are world positions.

    Attributes
    ----------
    geometry : ImageGeometry
        The input grid.
    tolerance : float
        Largest position error aimed at (voxels of the input spacing).
    data : (Q, 8, 3) float64
        Node data rows: ``f, f_u, f_v, f_w, f_uv, f_uw, f_vw, f_uvw``.
    leaf_origin : (L, 3) int64
        Lowest corner of each leaf cell (voxel indices).
    leaf_size : (L,) int64
        Cell size (voxels, a power of two).
    leaf_rows : (L, 8) int64
        Data rows of the corners (corner ``a + 2 b + 4 c`` at ``origin + (a, b, c) size``).
    leaf_cut : (L,) bool
        The cage passes through the cell (voxels outside it, or next to its surface).
    mask : (Nz, Ny, Nx) bool or None
        Inside the cage, for every lattice point (the volume's voxels and the lattice's
        overhang beyond them); a window's lattice fills only its root cells' rows. None
        in a joined lattice (:func:`join_parts`), which resamples only: its pull-back
        reads :meth:`cut_flags`.
    near : (Nz, Ny, Nx) bool or None
        Lattice points next to the cage surface (:func:`~vhm_viz.core.image.surface_mask`):
        pre-images in grid cubes touching them are checked with the winding number. Filled
        as ``mask`` is.
    edge_a, edge_b : (E, 3) float64
        End points of the cage's edges, in voxel indices (:meth:`near_cage_edges`).
    pre_images : bool
        False: a lattice for the voxels only (see :func:`build_lattice`).
    stats : dict
        ``evaluations`` (exact map evaluations), ``leaves``, ``leaves_per_size``,
        ``data_rows``, ``seconds``.
    """

    def __init__(self, **arrays):
        self.__dict__.update(arrays)
        self.end = self.n_root * self.root  # index of the lattice's far corner per axis
        self._margins = None
        self._edge_bins = None
        self._cut_flags = None

    def cut_flags(self, lat_geo=None, vertices=None, faces=None):
        """The inside and surface flags the pull-back reads: :func:`_cut_blocks` (kept).

        From the masks; a lattice without them (joined) is given them by
        :func:`join_parts`, which passes the cage.
        """
        if self._cut_flags is None:
            if self.mask is None and lat_geo is None:
                raise ValueError("this lattice has no masks: its cut flags need the cage")
            self._cut_flags = _cut_blocks(self, lat_geo, vertices, faces)
        return self._cut_flags

    def _need_pre_images(self, what: str) -> None:
        if not self.pre_images:
            raise ValueError(
                f"{what} needs the polynomial between voxels: this lattice was built for "
                "the voxels only (pre_images=False)"
            )

    @property
    def nbytes(self) -> int:
        """Memory held by the lattice's arrays (bytes)."""
        return int(
            sum(v.nbytes for v in self.__dict__.values() if isinstance(v, np.ndarray))
        )

    @property
    def last(self) -> np.ndarray:
        """Largest voxel index per axis of the input grid."""
        return np.asarray(self.geometry.dimensions, dtype=np.int64) - 1

    def inside(self, box) -> np.ndarray:
        """Inside mask (nz, ny, nx) of the voxels of ``box = (i0, i1, j0, j1, k0, k1)``."""
        i0, i1, j0, j1, k0, k1 = box
        return self.mask[k0 : k1 + 1, j0 : j1 + 1, i0 : i1 + 1]

    def leaves_in(self, box) -> np.ndarray:
        """Leaves owning a voxel of ``box`` (inclusive voxel ranges)."""
        o, h = self.leaf_origin, self.leaf_size
        lo = np.asarray(box[0::2])
        hi = np.asarray(box[1::2])
        ok = np.all((o <= hi) & (o + h[:, None] >= lo), axis=1)
        return np.ascontiguousarray(np.nonzero(ok)[0])

    def warp(self, box, out) -> None:
        """Interpolated world positions of the inside voxels of ``box``.

        Parameters
        ----------
        box : (i0, i1, j0, j1, k0, k1)
            Inclusive voxel ranges.
        out : (P, 3) float64
            The box's voxels, i fastest; rows of inside voxels are written.
        """
        b = np.asarray(box, dtype=np.int64)
        _leaf_voxels(
            self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, self.leaves_in(b),
            self.end, b, self.mask, False, np.eye(3), out,
        )  # fmt: skip

    def jacobians(self, box, out) -> None:
        """World Jacobians ``J[p, i, j] = d f_i / d x_j`` of the inside voxels of ``box``."""
        b = np.asarray(box, dtype=np.int64)
        _leaf_voxels(
            self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, self.leaves_in(b),
            self.end, b, self.mask, True, self.geometry.world_to_index, out,
        )  # fmt: skip


    def evaluate(self, u, *, gradient: bool = False):
        """The interpolated map at continuous voxel indices.

        Parameters
        ----------
        u : (P, 3) array_like
            Voxel indices (points beyond the lattice are clamped onto it).
        gradient : bool
            Also return ``df/du`` (P, 3, 3).

        Returns
        -------
        f : (P, 3)
        fu : (P, 3, 3), only with ``gradient``

        Raises
        ------
        ValueError
            For points in cells with no voxel inside the cage (no data there).
        """
        self._need_pre_images("evaluate")
        u = np.ascontiguousarray(np.atleast_2d(u), dtype=np.float64)
        leaf = self.locate(u)
        if (leaf < 0).any():
            raise ValueError("points in cells without a voxel inside the cage")
        f = np.empty((len(u), 3))
        g = np.empty((len(u), 3, 3))
        if len(u):
            _eval_points(self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, leaf, u, f, g)
        return (f, g) if gradient else f

    def near_cage_edges(self, u, radius: float) -> np.ndarray:
        """Whether each point lies within ``radius`` voxels of a cage edge.

        Parameters
        ----------
        u : (P, 3) array_like
            Continuous voxel indices.
        radius : float
            Euclidean distance in voxel index units.

        Returns
        -------
        (P,) bool
        """
        u = np.ascontiguousarray(np.atleast_2d(u), dtype=np.float64)
        if self._edge_bins is None or self._edge_bins[0] < radius:
            self._edge_bins = (radius, *_bin_edges(self.edge_a, self.edge_b, radius))
        _, lo, shape, start, ids = self._edge_bins
        out = np.zeros(len(u), dtype=np.bool_)
        if len(u) and len(self.edge_a):
            _near_binned_edges(u, self.edge_a, self.edge_b, radius, lo, shape, start, ids, out)
        return out

    def locate(self, u) -> np.ndarray:
        """Index of the leaf owning each point (``-1`` in cells without inside voxels)."""
        u = np.ascontiguousarray(np.atleast_2d(u), dtype=np.float64)
        out = np.empty(len(u), dtype=np.int64)
        _locate(
            self.leaf_origin, self.leaf_size, self.root_start, self.root_count, self.n_root,
            self.root, u, out,
        )  # fmt: skip
        return out

    def image_boxes(self, geometry: ImageGeometry, margin=0.0, border: float = 0.0):
        """Per leaf, the box of ``geometry``'s continuous indices its image can reach.

        From the Bezier control points of each leaf's polynomial, which contain its image,
        restricted to the volume (extended by ``border`` voxels); ``margin`` (voxels,
        scalar or per leaf) grows each cell before mapping (to first order).

        Returns
        -------
        lo, hi : (L, 3) float64
        """
        self._need_pre_images("image_boxes")
        n = len(self.leaf_size)
        lo, hi = np.empty((n, 3)), np.empty((n, 3))
        if n:
            _output_boxes(
                self.data, self.leaf_rows, self.leaf_origin, self.leaf_size,
                np.full(3, -border), self.last + border, geometry.origin,
                np.ascontiguousarray(geometry.world_to_index),
                np.broadcast_to(np.asarray(margin, dtype=np.float64), (n,)).copy(), lo, hi,
            )  # fmt: skip
        return lo, hi

    def margins(self) -> np.ndarray:
        """How far (voxels) outside each leaf its pre-images may lie.

        :data:`_MARGIN` (mismatch between cells of different sizes), plus the half-voxel
        border for leaves on the volume's boundary.
        """
        if self._margins is None:
            o, h = self.leaf_origin, self.leaf_size[:, None]
            boundary = ((o <= 0) | (o + h >= self.last)).any(axis=1)
            self._margins = _MARGIN + BORDER * boundary
        return self._margins

    def candidate_boxes(self, geometry: ImageGeometry):
        """Per leaf, the output voxels (inclusive int64 boxes) where it may hold pre-images."""
        lo, hi = self.image_boxes(geometry, self.margins(), BORDER)
        return np.floor(lo).astype(np.int64), np.ceil(hi).astype(np.int64)

    def pull_back(self, geometry: ImageGeometry, box, boxes, u, state, fold, quality) -> None:
        """Pre-images (input voxel indices) of the voxels of an output box.

        Parameters
        ----------
        geometry : ImageGeometry
            The output grid.
        box : (i0, i1, j0, j1, k0, k1)
            Inclusive output voxel ranges.
        boxes : (lo, hi) int64 arrays
            :meth:`image_boxes` rounded outward to output voxels.
        u : (P, 3) float64
            Pre-images of the box's voxels (i fastest), written where found.
        state, fold : (P,) uint8
            Zeroed by the caller; see :func:`_pull_back_rows`.
        quality : (P,) float64
        """
        self._need_pre_images("pull_back")
        b = np.asarray(box, dtype=np.int64)
        lo, hi = boxes
        leaves = np.nonzero(
            np.all((lo <= b[1::2]) & (hi >= b[0::2]), axis=1)
        )[0].astype(np.int64)
        n_rows = (b[3] - b[2] + 1) * (b[5] - b[4] + 1)
        start = np.zeros(n_rows + 1, dtype=np.int64)
        empty = np.zeros(0, dtype=np.int64)
        _candidate_rows(leaves, lo, hi, b, start, empty, empty, empty)
        start = np.cumsum(start)
        total = int(start[-1])
        row_leaf = np.empty(total, dtype=np.int64)
        row_i0 = np.empty(total, dtype=np.int64)
        row_i1 = np.empty(total, dtype=np.int64)
        if total:
            _candidate_rows(leaves, lo, hi, b, start, row_leaf, row_i0, row_i1)
            _pull_back_rows(
                self.data, self.leaf_rows, self.leaf_origin, self.leaf_size, self.leaf_cut,
                self.centre_f, self.centre_ginv, self.rho, self.margins(), *self.cut_flags(),
                self.last,
                geometry.origin, geometry.index_to_world, b, start, row_leaf, row_i0, row_i1,
                u, state, fold, quality,
            )  # fmt: skip

    def release_masks(self) -> None:
        """Free the masks, which no part carries: afterwards only :meth:`part` may be used.

        For a window's lattice about to hand out its leaves (an MPI rank's 17 MB of the
        embryo, held while it packed the other ranks' parts).
        """
        self.mask = self.near = None
        self._cut_flags = None
        release_free_memory()

    def root_keys(self, leaves=None) -> np.ndarray:
        """Root cell of each leaf (or of ``leaves``), as one int64 key (i fastest)."""
        o = self.leaf_origin if leaves is None else self.leaf_origin[leaves]
        return _root_keys(o, self.root, self.n_root)

    def part(self, leaves, *, release: bool = False, copy: bool = True) -> dict:
        """Some leaves with the data they read, as plain arrays (:data:`PART_FIELDS`).

        For lattices built in windows (MPI ranks) whose leaves are regrouped by
        :func:`join_parts`: each leaf carries its place in the whole lattice's order (its
        root cell, and its rank among that root cell's leaves, which a window's build
        keeps), so that the joined lattice visits them as the whole lattice would.

        ``release``: make the part out of this lattice's own arrays (their rows moved
        in place and the arrays shrunk, :func:`_taken`), so that the lattice and the
        part are not held together (the last part taken from a lattice about to be
        dropped); the lattice cannot be used afterwards. Copying instead held each field
        twice: on the embryo's rank 0, 33 MB of node data at its peak.

        ``copy`` False: the fields taken from the lattice's arrays are ``(array, index)``
        pairs (the part's rows are ``array[index]``), for a caller that copies them
        straight into a buffer (:func:`~vhm_viz.filters._parallel.send_parts`): a copy
        of the part and its packed buffer were held together (rank 0 of the embryo,
        27 MB).
        """
        self._need_pre_images("part")
        leaves = np.asarray(leaves, dtype=np.int64).ravel()
        # the data rows the leaves read, renumbered in their order: by marks over the
        # data rows, not np.unique (whose sort of every corner's row held five copies of
        # them at once, 48 MB of an MPI rank's exchange peak on the embryo)
        rows = self.leaf_rows[leaves]
        read = np.zeros(len(self.data), dtype=bool)
        read[rows] = True
        used = np.flatnonzero(read)
        del read
        renumber = np.zeros(len(self.data), dtype=np.int64)
        renumber[used] = np.arange(len(used))
        rows = renumber[rows]
        del renumber
        rkey = self.root_keys(leaves)
        out = {"order": np.column_stack([rkey, leaves - self.root_start[rkey]]),
               "rows": rows}  # fmt: skip
        if release:  # what no part needs goes first
            self.leaf_rows = self.root_start = self.root_count = None
            self._margins = self._edge_bins = None
            self.release_masks()
        for name, attr in (("origin", "leaf_origin"), ("size", "leaf_size"),
                           ("cut", "leaf_cut"), ("centre_f", "centre_f"),
                           ("centre_ginv", "centre_ginv"), ("rho", "rho"),
                           ("data", "data")):  # fmt: skip
            index = used if name == "data" else leaves
            if release:
                out[name] = _taken(self.__dict__, attr, index)
                release_free_memory()  # (a shrunk heap block's tail)
            elif not copy:
                out[name] = (getattr(self, attr), index)
            else:
                out[name] = getattr(self, attr)[index]
        return out

    def __repr__(self) -> str:
        return (
            f"HermiteLattice(leaves={self.stats['leaves']}, "
            f"evaluations={self.stats.get('evaluations')}, {self.nbytes / 1e6:.1f} MB)"
        )
