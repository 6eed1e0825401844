"""Exact node data: the map inside the cage and its analytic continuation across it.

Cells next to the cage have corners outside it, where the map is not defined. There the
node data is the map continued across the nearest cage face ``t`` (see
:mod:`vhm_viz.core.lattice`): the exterior formula plus the affine term
``A_t(pi_t(p)) + ((p - x_t) . N_t) b_t``. The nearest face comes from the one
nearest-face service, :func:`~vhm_viz.core.geometry.nearest_points_on_mesh`.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.basis import chunk_rows, evaluate_map, inside_cage
from vhm_viz.core.components import edge_components
from vhm_viz.core.errors import AbortedError
from vhm_viz.core.geometry import nearest_points_on_mesh

# Nodes whose closed-form Jacobian is undefined (exactly on a cage edge or vertex) are
# evaluated this many voxels away, along a fixed generic direction.
_NUDGE = 1e-7


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


class CageShells:
    """Outward shells of a cage (connected components enclosing positive volume).

    For a cage of several outward shells a point outside all of them is continued from
    its nearest face's shell, with that shell's (and the inward hole shells') basis
    functions only -- the functions the map uses inside that shell.
    """

    def __init__(self, vertices, faces):
        n = len(vertices)
        f = np.asarray(faces)
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        _, labels = edge_components(n, edges)
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


def exact_data(hm, points, to_index, shells, memory_budget=None, abort=None):
    """Map values and u-Jacobians at world points: exact inside, continued outside.

    Parameters
    ----------
    hm : HarmonicMap
    points : (P, 3) float64
        World points.
    to_index : (3, 3) float64
        ``index_to_world`` of the grid: ``f_u = J @ to_index``.
    shells : CageShells
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
    device = getattr(hm, "device", "cpu")  # HarmonicMap.device: where the closed forms run
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
        f[s:e], jac[s:e], wind = evaluate_map(points[s:e], V, F, z, order=1, device=device)
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
        f2, fu2, _ = exact_data(hm, points[bad] + step, to_index, shells, memory_budget)
        f[bad] = f2
        jac[bad] = fu2 @ np.linalg.inv(to_index)
    return f, jac @ to_index, inside
