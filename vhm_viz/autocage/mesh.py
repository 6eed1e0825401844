"""Triangle-mesh plumbing shared by the cage builders: components, orientation, conversion.

Plain arrays in and out (``V`` (n, 3) float64 vertices, ``F`` (m, 3) int64 faces), except
:func:`polydata`/:func:`faces_of` at the VTK edge and :func:`make_cage`, which validates
the result as a :class:`vhm_viz.Cage`.
"""

from __future__ import annotations

import itertools
import warnings

import numpy as np

from vhm_viz.core.cage import Cage
from vhm_viz.core.components import edge_components

__all__ = [
    "BOX_TRIANGLES",
    "box_corners",
    "edge_components",
    "face_edges",
    "faces_of",
    "compact",
    "polydata",
    "orient_outward",
    "make_cage",
]

#: the 12 outward triangles of a box whose corners are :func:`box_corners`
BOX_TRIANGLES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
     [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
    dtype=np.int64,
)  # fmt: skip


def box_corners(lo, hi) -> np.ndarray:
    """The 8 corners of the axis-aligned box ``lo``-``hi``.

    Parameters
    ----------
    lo, hi : (3,) float arrays
        Opposite corners (world units).

    Returns
    -------
    (8, 3) float64
        Corner ``4 i + 2 j + k`` takes x from ``(lo, hi)[i]``, y from ``[j]``, z from ``[k]``.
    """
    axes = zip(np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64), strict=True)
    return np.array(list(itertools.product(*axes)), dtype=np.float64)


def face_edges(F: np.ndarray) -> np.ndarray:
    """Edges ``(a, b)`` and ``(b, c)`` of every face: enough to connect each face's vertices.

    Returns
    -------
    (2 m, 2) int array
    """
    return np.concatenate([F[:, [0, 1]], F[:, [1, 2]]])


def faces_of(poly) -> np.ndarray:
    """The (m, 3) int64 faces of an all-triangle PolyData."""
    return np.asarray(poly.faces, dtype=np.int64).reshape(-1, 4)[:, 1:]


def compact(V, F):
    """Drop unreferenced vertices; returns the kept vertices and the renumbered faces."""
    used, inv = np.unique(F, return_inverse=True)
    return V[used], inv.reshape(F.shape)


def polydata(vertices, faces):
    """A triangle PolyData of the arrays."""
    # VTK is loaded only when a surface crosses into it (decimation)
    import pyvista as pv

    f = np.asarray(faces, dtype=np.int64)
    cells = np.hstack([np.full((len(f), 1), 3, dtype=np.int64), f]).ravel()
    return pv.PolyData(np.asarray(vertices, dtype=np.float64), cells)


def orient_outward(V, F):
    """Flip every connected component whose signed volume is negative.

    Returns
    -------
    F : (m, 3) int array
        The faces, outward oriented (a copy).
    count : int
        Connected components of the vertices (unreferenced vertices count as their own).
    """
    ncomp, lab = edge_components(len(V), face_edges(F))
    flab = lab[F[:, 0]]
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    vol = np.bincount(flab, np.einsum("ij,ij->i", a, np.cross(b, c)), minlength=ncomp)
    flip = vol[flab] < 0
    F = F.copy()
    F[flip] = F[flip][:, ::-1]
    return F, ncomp


def make_cage(V, F, check_self_intersection=True) -> Cage:
    """A validated :class:`vhm_viz.Cage` from arrays (raises CageError).

    Thin faces are kept and reported (``Cage.thin_faces``), not repaired: a repair moves the
    surface. :func:`vhm_viz.auto_cage` still checks the enclosure on the cage returned
    here, and pushes the surface back out should a repair ever have cut into the shape.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # an inward or unreferenced cage is a bug
        return Cage(
            np.asarray(V, dtype=np.float64),
            np.asarray(F, dtype=np.int64),
            check_self_intersection=check_self_intersection,
            # thin faces are not refused or repaired here: a repair may not move the surface
            # inward and the simplified cages have many; Cage.thin_faces reports them
            min_angle=0.0,
        )
