"""Compiled 3x3 matrix algebra on scalar entries, for numba kernels.

Kernels that handle one small matrix per thread keep its nine entries in registers
(scalars, no ``(3, 3)`` array per thread); the algebra they share lives here.
"""

from __future__ import annotations

import numba

__all__ = ["cofactors3"]


@numba.njit(cache=True)
def cofactors3(a00, a01, a02, a10, a11, a12, a20, a21, a22):  # pragma: no cover - compiled
    """Cofactors ``c_ij`` of the 3x3 matrix ``a`` (compiled, scalar entries, row-major).

    ``c_ij = (-1)^(i+j)`` times the minor of ``a_ij``, so that ``adj(a) = c^T``,
    ``det a = a00 c00 + a01 c01 + a02 c02`` and ``a^-1 = c^T / det a``.

    Returns
    -------
    c00, c01, c02, c10, c11, c12, c20, c21, c22 : float
    """
    return (
        a11 * a22 - a12 * a21,
        a12 * a20 - a10 * a22,
        a10 * a21 - a11 * a20,
        a02 * a21 - a01 * a22,
        a00 * a22 - a02 * a20,
        a01 * a20 - a00 * a21,
        a01 * a12 - a02 * a11,
        a02 * a10 - a00 * a12,
        a00 * a11 - a01 * a10,
    )
