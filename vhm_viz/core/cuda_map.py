"""The closed-form map and its Jacobians on an NVIDIA GPU (numba-cuda, float64).

The GPU counterpart of :func:`~vhm_viz.core.basis_lanes.lanes_map_kernel`: one thread per
point sums, face by face, the contributions of the paper's closed forms (Ben-Chen, Weber,
Gotsman 2009, Section 2.1 and Appendix A) to ``f(p) = sum_v a_v phi_v(p) + sum_t b_t
psi_t(p)`` and to its Jacobian, contracted with the coefficients at once, so nothing of
size ``(N, n + m)`` exists. The per-face arithmetic is that of
:mod:`vhm_viz.core.face_formulas`, compiled here as device functions. Each thread
recomputes its corners' vectors and edge logarithms per face (the CPU kernels share them
between neighbouring faces through scratch arrays, which a GPU thread cannot hold for a
large cage).

Points next to a cage edge are flagged, as by the CPU kernel, and evaluated by the careful
per-point CPU kernel (:func:`~vhm_viz.core.basis.evaluate_map` does both). Importing this
module imports ``numba.cuda``; callers import it only when ``device="cuda"`` is asked for
(:func:`~vhm_viz.core.devices.require_device` checks first).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import cuda

from vhm_viz.core.face_formulas import edge_log_argument, face_terms, solid_angle_parts

__all__ = ["THREADS_PER_BLOCK", "map_on_gpu"]

#: Threads per block of the map kernel (one point each). Small blocks spread the lattice's
#: chunks of ten thousand points or so over every multiprocessor.
THREADS_PER_BLOCK = 64
_INV_TWO_PI = 1.0 / (2.0 * math.pi)

_edge_log_argument = cuda.jit(device=True)(edge_log_argument)
_solid_angle_parts = cuda.jit(device=True)(solid_angle_parts)
_face_terms = cuda.jit(device=True)(face_terms)


@cuda.jit(device=True)
def _edge_log(ux, uy, uz, lu, wx, wy, wz, lw, q, edge_len, inv_4pi_len, near_edge):
    """``C`` of edge ``q`` seen from the point, and whether the point is near it."""
    dl = edge_len[q]
    arg, near = _edge_log_argument(ux, uy, uz, lu, wx, wy, wz, lw, dl, near_edge * dl)
    return math.log1p(arg) * inv_4pi_len[q], near


@cuda.jit
def _map_kernel(
    points, V, F, N, inv_twice_area, D, NxD, edges, edge_len, inv_4pi_len, face_edges,
    near_edge, order, z, values, jacobians, winding, flagged,
):  # pragma: no cover - compiled for the GPU  # fmt: skip
    """``f`` (and ``J[k, i, j] = d f_i / d x_j`` when ``order`` is 1) at each point.

    Cage arrays as in :func:`~vhm_viz.core.cage_tables.kernel_arrays` (``edges`` unused:
    each face names its edges in ``face_edges``); ``winding[k]`` is the sum of the vertex
    functions and ``flagged[k]`` is 1 for points near a cage edge, whose other results
    are placeholders.
    """
    k = cuda.grid(1)
    if k >= points.shape[0]:
        return
    n = V.shape[0]
    px = points[k, 0]
    py = points[k, 1]
    pz = points[k, 2]
    acc = cuda.local.array(12, numba.float64)  # f (3), then J row by row (9)
    for i in range(12):
        acc[i] = 0.0
    wsum = 0.0
    near = False
    for t in range(F.shape[0]):
        a0 = F[t, 0]
        a1 = F[t, 1]
        a2 = F[t, 2]
        x0 = V[a0, 0] - px
        y0 = V[a0, 1] - py
        z0 = V[a0, 2] - pz
        x1 = V[a1, 0] - px
        y1 = V[a1, 1] - py
        z1 = V[a1, 2] - pz
        x2 = V[a2, 0] - px
        y2 = V[a2, 1] - py
        z2 = V[a2, 2] - pz
        l0 = math.sqrt(x0 * x0 + y0 * y0 + z0 * z0)
        l1 = math.sqrt(x1 * x1 + y1 * y1 + z1 * z1)
        l2 = math.sqrt(x2 * x2 + y2 * y2 + z2 * z2)
        # the edge opposite corner v joins corners v + 1 and v + 2
        c0, n0 = _edge_log(
            x1, y1, z1, l1, x2, y2, z2, l2, face_edges[t, 0], edge_len, inv_4pi_len, near_edge
        )
        c1, n1 = _edge_log(
            x2, y2, z2, l2, x0, y0, z0, l0, face_edges[t, 1], edge_len, inv_4pi_len, near_edge
        )
        c2, n2 = _edge_log(
            x0, y0, z0, l0, x1, y1, z1, l1, face_edges[t, 2], edge_len, inv_4pi_len, near_edge
        )
        near = near or n0 or n1 or n2
        det, den = _solid_angle_parts(x0, y0, z0, l0, x1, y1, z1, l1, x2, y2, z2, l2)
        # exactly in the plane, inside the triangle: the interior limit
        w = 0.5 if (det == 0.0) and (den < 0.0) else math.atan2(det, den) * _INV_TWO_PI
        ia = inv_twice_area[t]
        psi, f0, f1, f2, qx, qy, qz = _face_terms(
            x0, y0, z0, x1, y1, z1, x2, y2, z2, w, c0, c1, c2, N[t, 0], N[t, 1], N[t, 2],
            NxD[t, 0, 0], NxD[t, 0, 1], NxD[t, 0, 2], NxD[t, 1, 0], NxD[t, 1, 1],
            NxD[t, 1, 2], NxD[t, 2, 0], NxD[t, 2, 1], NxD[t, 2, 2], ia,
        )  # fmt: skip
        wsum += f0 + f1 + f2
        for i in range(3):
            acc[i] += psi * z[n + t, i] + f0 * z[a0, i] + f1 * z[a1, i] + f2 * z[a2, i]
        if order >= 1:
            # grad psi_t = -P ;  grad phi_v += (P x d_v) / 2A
            for i in range(3):
                zb = z[n + t, i]
                acc[3 + 3 * i] -= qx * zb
                acc[4 + 3 * i] -= qy * zb
                acc[5 + 3 * i] -= qz * zb
            for v in range(3):
                dx = D[t, v, 0]
                dy = D[t, v, 1]
                dz = D[t, v, 2]
                gx = (qy * dz - qz * dy) * ia
                gy = (qz * dx - qx * dz) * ia
                gz = (qx * dy - qy * dx) * ia
                a = F[t, v]
                for i in range(3):
                    za = z[a, i]
                    acc[3 + 3 * i] += gx * za
                    acc[4 + 3 * i] += gy * za
                    acc[5 + 3 * i] += gz * za
    for i in range(3):
        values[k, i] = acc[i]
    winding[k] = wsum
    flagged[k] = 1 if near else 0
    if order >= 1:
        for i in range(3):
            for j in range(3):
                jacobians[k, i, j] = acc[3 + 3 * i + j]


def map_on_gpu(points, cage_arrays, near_edge: float, order: int, z) -> tuple:
    """The map (and its Jacobians) at points, on the GPU.

    Parameters
    ----------
    points : (N, 3) float64
    cage_arrays : tuple
        :func:`~vhm_viz.core.cage_tables.kernel_arrays` of the cage.
    near_edge : float
        The near-edge threshold of :data:`~vhm_viz.core.basis_kernel.NEAR_EDGE`.
    order : {0, 1}
    z : (n + m, 3) float64
        The coefficients.

    Returns
    -------
    values : (N, 3) float64
    jacobians : (N, 3, 3) float64
        ``J[k, i, j] = d f_i / d x_j`` (``order`` 1; zeros otherwise).
    winding : (N,) float64
        Sum of the vertex functions.
    flagged : (N,) bool
        Points near a cage edge: their other results are placeholders.
    """
    npts = points.shape[0]
    dev = [cuda.to_device(np.ascontiguousarray(a)) for a in (points, *cage_arrays, z)]
    values = cuda.device_array((npts, 3), dtype=np.float64)
    jacobians = cuda.device_array((npts if order >= 1 else 1, 3, 3), dtype=np.float64)
    winding = cuda.device_array(npts, dtype=np.float64)
    flagged = cuda.device_array(npts, dtype=np.uint8)
    if npts:
        blocks = (npts + THREADS_PER_BLOCK - 1) // THREADS_PER_BLOCK
        _map_kernel[blocks, THREADS_PER_BLOCK](
            *dev[:-1], float(near_edge), int(order), dev[-1], values, jacobians, winding, flagged
        )
    jac = jacobians.copy_to_host() if order >= 1 else np.zeros((npts, 3, 3))
    return (
        values.copy_to_host(),
        jac,
        winding.copy_to_host(),
        flagged.copy_to_host().astype(bool),
    )
