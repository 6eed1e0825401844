"""LAPACK's QR and triangular solves for the solver, without importing all of ``scipy.linalg``.

Importing ``scipy.linalg`` runs its package's ``__init__``, which imports every one of its
submodules and SciPy's array-API layer (that one touches ``numpy.f2py``, ``numpy.testing``
and ``numpy.ma``): far more than the few LAPACK routines the solver calls. Those live in
compiled extensions of SciPy's linalg folder: ``_flapack`` (the f2py wrappers behind
:func:`scipy.linalg.qr` and :func:`scipy.linalg.solve_triangular`), ``cython_blas`` and
``cython_lapack`` (the function pointers numba's array functions call). They are loaded
by file, without the package's ``__init__`` (:mod:`vhm_viz.core.scipy_extensions`); once
``scipy.linalg`` is imported the real modules are used instead.

The functions call the same routines with the same arguments and workspace sizes as the
SciPy functions named in their docstrings, so the results are the same, bit for bit.
"""

from __future__ import annotations

import sys
from functools import cache

import numpy as np

from vhm_viz.core.scipy_extensions import extension

__all__ = ["flapack", "qr", "register_cython_linalg", "solve_triangular"]

_PACKAGE = "scipy.linalg"


def _extension(name: str):
    """SciPy's compiled ``scipy.linalg.<name>`` (:func:`.scipy_extensions.extension`)."""
    return extension(_PACKAGE, name)


@cache
def flapack():
    """SciPy's f2py LAPACK wrappers (``scipy.linalg._flapack``); loads SciPy's OpenBLAS."""
    return _extension("_flapack")


@cache
def register_cython_linalg() -> None:
    """Make ``scipy.linalg.cython_blas`` and ``cython_lapack`` importable on their own.

    numba imports those modules by name, for their BLAS and LAPACK function pointers, when
    it loads its array functions and when its compiled ``np.linalg`` helpers are first
    called; put in ``sys.modules`` here, the imports find them there instead of running
    ``scipy.linalg``'s ``__init__``.
    """
    for name in ("cython_blas", "cython_lapack"):
        full = f"{_PACKAGE}.{name}"
        if full not in sys.modules:
            sys.modules[full] = _extension(name)


def _call(routine, name: str, *args, **kwargs):
    """``routine(*args, **kwargs)`` with LAPACK's workspace query first (SciPy's ``safecall``)."""
    kwargs["lwork"] = -1
    ret = routine(*args, **kwargs)
    kwargs["lwork"] = ret[-2][0].real.astype(np.int_)
    ret = routine(*args, **kwargs)
    if ret[-1] < 0:
        raise ValueError(f"illegal value in {-ret[-1]}th argument of internal {name}")
    return ret[:-2]


def qr(a: np.ndarray, economic: bool = False, pivoting: bool = False, overwrite_a: bool = False):
    """QR factorisation of a float64 matrix, ``a[:, P] = Q R``.

    ``scipy.linalg.qr(a, mode="economic" if economic else "full", pivoting=pivoting,
    overwrite_a=overwrite_a, check_finite=False)`` (LAPACK ``dgeqrf`` or ``dgeqp3``, then
    ``dorgqr``).

    Parameters
    ----------
    a : (M, N) float64
        The matrix; overwritten with ``overwrite_a`` when it is Fortran-ordered.
    economic : bool
        ``Q`` of shape ``(M, K)`` and ``R`` of ``(K, N)``, ``K = min(M, N)``; else
        ``(M, M)`` and ``(M, N)``.
    pivoting : bool
        Column pivoting (rank revealing): ``abs(diag(R))`` does not increase.
    overwrite_a : bool
        ``a`` may be overwritten.

    Returns
    -------
    Q : (M, M) or (M, K) float64
    R : (M, N) or (K, N) float64
    P : (N,) int32
        Only with ``pivoting``: the column permutation.
    """
    a1 = np.asarray(a)
    if a1.dtype != np.float64 or a1.ndim != 2 or a1.size == 0:
        raise ValueError(f"expected a non-empty 2-D float64 matrix; got {a1.dtype} {a1.shape}")
    lapack = flapack()
    m, n = a1.shape
    overwrite_a = overwrite_a or a1 is not a
    if pivoting:
        packed, jpvt, tau = _call(lapack.dgeqp3, "geqp3", a1, overwrite_a=overwrite_a)
        jpvt -= 1  # LAPACK counts from 1
    else:
        packed, tau = _call(lapack.dgeqrf, "geqrf", a1, overwrite_a=overwrite_a)
    r = np.triu(packed) if not economic or m < n else np.triu(packed[:n, :])
    if m < n:
        q = _call(lapack.dorgqr, "gorgqr/gungqr", packed[:, :m], tau, overwrite_a=1)[0]
    elif economic:
        q = _call(lapack.dorgqr, "gorgqr/gungqr", packed, tau, overwrite_a=1)[0]
    else:
        full = np.empty((m, m), dtype=packed.dtype)
        full[:, :n] = packed
        q = _call(lapack.dorgqr, "gorgqr/gungqr", full, tau, overwrite_a=1)[0]
    return (q, r, jpvt) if pivoting else (q, r)


def solve_triangular(a: np.ndarray, b: np.ndarray, transpose: bool = False) -> np.ndarray:
    """Solve ``a x = b`` (or ``a^T x = b``) for an upper triangular float64 ``a``.

    ``scipy.linalg.solve_triangular(a, b, trans="T" if transpose else "N",
    check_finite=False)`` (LAPACK ``dtrtrs``).

    Parameters
    ----------
    a : (M, M) float64
        Upper triangular (the strict lower part is not read).
    b : (M,) or (M, K) float64
    transpose : bool
        Solve with ``a^T``.

    Returns
    -------
    x : shaped as ``b``

    Raises
    ------
    numpy.linalg.LinAlgError
        ``a`` is singular.
    """
    a1, b1 = np.asarray(a), np.asarray(b)
    if a1.ndim != 2 or a1.shape[0] != a1.shape[1] or a1.shape[0] != b1.shape[0]:
        raise ValueError(f"shapes of a {a1.shape} and b {b1.shape} are incompatible")
    overwrite_b = b1 is not b
    trans = int(transpose)
    if a1.flags.f_contiguous:
        x, info = flapack().dtrtrs(a1, b1, overwrite_b=overwrite_b, lower=0, trans=trans)
    else:  # trtrs expects Fortran order: solve the transposed system of the C-ordered a
        x, info = flapack().dtrtrs(a1.T, b1, overwrite_b=overwrite_b, lower=1, trans=1 - trans)
    if info > 0:
        raise np.linalg.LinAlgError(f"singular matrix: resolution failed at diagonal {info - 1}")
    if info < 0:
        raise ValueError(f"illegal value in {-info}-th argument of internal trtrs")
    return x
