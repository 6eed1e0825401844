"""Cross products of vectors from a point to two cage vertices, exact to a few ulps.

Next to the interior of an edge ``(b, c)`` the vectors ``e_b = x_b - p`` and
``e_c = x_c - p`` point in nearly opposite directions, and ``e_b x e_c`` (length about
distance times edge length) cancels: with ``e_b`` and ``e_c`` rounded (error about
``eps |e|``), its relative error is about ``eps |e| / distance``, and every term built on it
(``R - |d|``, the solid angle) inherits it. Computed from the exact differences (Knuth's
two-sum: ``x - p = hi + lo``) with exact products (Dekker's split), the cross product is
correct to a few ulps at any distance. A numpy version serves the reference evaluation
(:mod:`vhm_viz.core.basis_reference`), a compiled one the per-point kernel
(:mod:`vhm_viz.core.basis_kernel`).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["cross_exact", "cross_exact_np"]

_SPLIT = 134217729.0  # 2**27 + 1


def _two_diff_np(a, b):
    """``a - b = s + err`` exactly (Knuth)."""
    s = a - b
    bb = s - a
    return s, (a - (s - bb)) - (b + bb)


def _two_prod_np(a, b):
    """``a * b = p + err`` exactly (Dekker; no fused multiply-add needed)."""
    p = a * b
    ca, cb = _SPLIT * a, _SPLIT * b
    ah, bh = ca - (ca - a), cb - (cb - b)
    al, bl = a - ah, b - bh
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


def cross_exact_np(xu, xw, p):
    """``(xu - p) x (xw - p)`` to a few ulps of the result, for stacks ``(..., 3)``."""
    uh, ul = _two_diff_np(xu, p)
    wh, wl = _two_diff_np(xw, p)
    out = []
    for i, j in ((1, 2), (2, 0), (0, 1)):
        p1, e1 = _two_prod_np(uh[..., i], wh[..., j])
        p2, e2 = _two_prod_np(uh[..., j], wh[..., i])
        d, ed = _two_diff_np(p1, p2)
        tail = uh[..., i] * wl[..., j] + ul[..., i] * wh[..., j]
        tail -= uh[..., j] * wl[..., i] + ul[..., j] * wh[..., i]
        out.append(d + (ed + (e1 - e2) + tail))
    return np.stack(out, axis=-1)


# --------------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _two_diff(a, b):  # pragma: no cover - compiled
    """``a - b = s + err`` exactly (see :func:`_two_diff_np`)."""
    s = a - b
    bb = s - a
    return s, (a - (s - bb)) - (b + bb)


@numba.njit(cache=True, inline="always")
def _two_prod(a, b):  # pragma: no cover - compiled
    """``a * b = p + err`` exactly (see :func:`_two_prod_np`)."""
    p = a * b
    ca = _SPLIT * a
    cb = _SPLIT * b
    ah = ca - (ca - a)
    bh = cb - (cb - b)
    al = a - ah
    bl = b - bh
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


@numba.njit(cache=True, inline="always")
def _cross_component(ui, ul_i, uj, ul_j, wi, wl_i, wj, wl_j):  # pragma: no cover - compiled
    """``u_i w_j - u_j w_i`` from exact splits ``u = uh + ul``, ``w = wh + wl``."""
    p1, e1 = _two_prod(ui, wj)
    p2, e2 = _two_prod(uj, wi)
    d, ed = _two_diff(p1, p2)
    tail = (ui * wl_j + ul_i * wj) - (uj * wl_i + ul_j * wi)
    return d + (ed + (e1 - e2) + tail)


@numba.njit(cache=True)
def cross_exact(V, i, j, px, py, pz, out):  # pragma: no cover - compiled
    """``out = (V[i] - p) x (V[j] - p)`` to a few ulps (see :func:`cross_exact_np`)."""
    ux, uxl = _two_diff(V[i, 0], px)
    uy, uyl = _two_diff(V[i, 1], py)
    uz, uzl = _two_diff(V[i, 2], pz)
    wx, wxl = _two_diff(V[j, 0], px)
    wy, wyl = _two_diff(V[j, 1], py)
    wz, wzl = _two_diff(V[j, 2], pz)
    out[0] = _cross_component(uy, uyl, uz, uzl, wy, wyl, wz, wzl)
    out[1] = _cross_component(uz, uzl, ux, uxl, wz, wzl, wx, wxl)
    out[2] = _cross_component(ux, uxl, uy, uyl, wx, wxl, wy, wyl)
