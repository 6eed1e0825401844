"""The closed form of one cage face seen from one point, as plain scalar functions.

Paper Appendix A (Ben-Chen, Weber, Gotsman 2009; Urago 2000): the contribution of a face
``t`` to the basis at a point ``p`` needs, besides the face's own constants, only

* the vectors ``e_a = x_a - p`` to its corners and their lengths,
* per edge opposite corner ``v``, ``C_v = log(1 + 2 |d| / (R - |d|)) / (4 pi |d|)`` with
  ``R = |e_i| + |e_j|`` (:func:`edge_log_argument` gives the argument of ``log1p``),
* the face's signed solid angle ``w = atan2(det, den) / 2 pi``
  (:func:`solid_angle_parts` gives ``det`` and ``den``, Van Oosterom and Strackee),

and then :func:`face_terms` combines them into ``psi_t``, the three increments of the
``phi`` of its corners and the vector ``P`` whose cross products give the gradients.

The functions are plain arithmetic, free of ``numba`` and of transcendental calls: each
caller compiles them for its target (``numba.cuda.jit(device=True)`` in
:mod:`vhm_viz.core.cuda_map`) and applies its own ``log1p`` and ``atan2`` to the
arguments returned. Points next to an edge are *flagged* by :func:`edge_log_argument`;
for them the plain formulas lose accuracy and the careful per-point kernel of
:mod:`vhm_viz.core.basis_kernel` takes over.
"""

from __future__ import annotations

__all__ = ["edge_log_argument", "face_terms", "solid_angle_parts"]


def edge_log_argument(ux, uy, uz, lu, wx, wy, wz, lw, length, near_limit):
    """Argument ``2 |d| / (R - |d|)`` of ``log1p`` in ``C`` of an edge, and its flag.

    Parameters
    ----------
    ux, uy, uz, lu, wx, wy, wz, lw : float
        Vectors from the point to the edge's ends and their lengths.
    length : float
        ``|d|``, the edge's length.
    near_limit : float
        ``near_edge * |d|``: the point is *near* the edge when ``R - |d|`` is below it.

    Returns
    -------
    argument : float
        ``2 |d| / (R - |d|)``, with ``R - |d|`` computed without cancellation
        (see :mod:`vhm_viz.core.basis_reference`); 1.0 (a placeholder) when flagged.
    near : bool
        The point is near (or on) the edge: its values must come from elsewhere.
    """
    cx = uy * wz - uz * wy
    cy = uz * wx - ux * wz
    cz = ux * wy - uy * wx
    uw = ux * wx + uy * wy + uz * wz
    lulw = lu * lw
    big = lu + lw + length
    # R - |d| = num / den
    neg = uw <= 0.0
    num = 2.0 * (cx * cx + cy * cy + cz * cz) if neg else 2.0 * (lulw + uw)
    den = (lulw - uw) * big if neg else big
    ok = (num > 0.0) & (num >= near_limit * den)  # also False on a vertex (0 / 0)
    return (2.0 * length * den / num if ok else 1.0), not ok


def solid_angle_parts(x0, y0, z0, l0, x1, y1, z1, l1, x2, y2, z2, l2):
    """``det`` and ``den`` of a face's solid angle ``2 atan2(det, den)``.

    Parameters
    ----------
    x0, y0, z0, l0, x1, y1, z1, l1, x2, y2, z2, l2 : float
        The vectors ``e_a`` from the point to the face's corners, and their lengths.

    Returns
    -------
    det : float
        ``e_0 . (e_1 x e_2)``.
    den : float
        ``l0 l1 l2 + (e_0.e_1) l2 + (e_0.e_2) l1 + (e_1.e_2) l0``.
    """
    det = x0 * (y1 * z2 - z1 * y2) + y0 * (z1 * x2 - x1 * z2) + z0 * (x1 * y2 - y1 * x2)
    den = (
        l0 * l1 * l2
        + (x0 * x1 + y0 * y1 + z0 * z1) * l2
        + (x0 * x2 + y0 * y2 + z0 * z2) * l1
        + (x1 * x2 + y1 * y2 + z1 * z2) * l0
    )
    return det, den


def face_terms(
    x0, y0, z0, x1, y1, z1, x2, y2, z2, w, c0, c1, c2, nx, ny, nz,
    m0x, m0y, m0z, m1x, m1y, m1z, m2x, m2y, m2z, inv_twice_area,
):  # fmt: skip
    """One face's ``psi_t``, increments of its corners' ``phi`` and the vector ``P``.

    Paper Appendix A: with ``Jv_v = e_{v+2} x e_{v+1}``,
    ``P = -w N + sum_v C_v (N x d_v)``, ``psi_t = -w (e_0 . N) - sum_v C_v (Jv_v . N)``
    and ``phi_v += (P . Jv_v) / 2A``; the gradients are ``grad psi_t = -P`` and
    ``grad phi_v += (P x d_v) / 2A``.

    Parameters
    ----------
    x0, y0, z0, x1, y1, z1, x2, y2, z2 : float
        ``e_a = x_a - p`` for the face's corners.
    w : float
        The face's signed solid angle divided by ``4 pi`` (``atan2(det, den) / 2 pi``,
        or the interior limit 1/2 exactly in the face's plane inside the triangle).
    c0, c1, c2 : float
        ``C_v`` of the edges opposite corners 0, 1, 2.
    nx, ny, nz : float
        The face's unit normal ``N``.
    m0x, m0y, m0z, m1x, m1y, m1z, m2x, m2y, m2z : float
        ``N x d_v`` for the edges ``d_v = x_{v+1} - x_{v+2}``.
    inv_twice_area : float
        ``1 / (2 A)``.

    Returns
    -------
    psi, phi0, phi1, phi2, px, py, pz : float
    """
    # Jv_v = e_{v+2} x e_{v+1}
    j0x = y2 * z1 - z2 * y1
    j0y = z2 * x1 - x2 * z1
    j0z = x2 * y1 - y2 * x1
    j1x = y0 * z2 - z0 * y2
    j1y = z0 * x2 - x0 * z2
    j1z = x0 * y2 - y0 * x2
    j2x = y1 * z0 - z1 * y0
    j2y = z1 * x0 - x1 * z0
    j2z = x1 * y0 - y1 * x0
    hd = x0 * nx + y0 * ny + z0 * nz
    px = -w * nx + c0 * m0x + c1 * m1x + c2 * m2x
    py = -w * ny + c0 * m0y + c1 * m1y + c2 * m2y
    pz = -w * nz + c0 * m0z + c1 * m1z + c2 * m2z
    psi = (
        -w * hd
        - c0 * (j0x * nx + j0y * ny + j0z * nz)
        - c1 * (j1x * nx + j1y * ny + j1z * nz)
        - c2 * (j2x * nx + j2y * ny + j2z * nz)
    )
    ia = inv_twice_area
    phi0 = (px * j0x + py * j0y + pz * j0z) * ia
    phi1 = (px * j1x + py * j1y + pz * j1z) * ia
    phi2 = (px * j2x + py * j2y + pz * j2z) * ia
    return psi, phi0, phi1, phi2, px, py, pz
