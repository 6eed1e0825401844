"""Per-cage tables the basis evaluation reads: edges, normals, shells, kernel arrays.

Every evaluation of the harmonic basis (:mod:`vhm_viz.core.basis`) needs, besides the
cage's vertices and faces, its face normals and areas, the edge vectors of each face, the
table of unique edges, and -- for a cage of several disjoint outward shells -- which
vertices and faces belong to each shell. :func:`prepare_cage` builds them once per cage
(cached on the arrays' contents); the compiled kernels take them as plain arrays in the
order of :func:`kernel_arrays`.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from vhm_viz.core.components import edge_components
from vhm_viz.core.geometry import face_normals_and_areas

__all__ = [
    "CageTables",
    "kernel_arrays",
    "prepare_cage",
    "read_only",
    "separate_shells",
    "shell_cages",
]


class CageTables(NamedTuple):
    """The arrays of one cage that the basis kernels read (see :func:`prepare_cage`)."""

    vertices: np.ndarray  # (n, 3)
    faces: np.ndarray  # (m, 3) int64
    normals: np.ndarray  # (m, 3)
    twice_area: np.ndarray  # (m,)
    d: np.ndarray  # (m, 3, 3): d[t, v] = x_{v+1} - x_{v+2}, edge opposite local vertex v
    n_cross_d: np.ndarray  # (m, 3, 3): N_t x d[t, v]
    edges: np.ndarray  # (E, 2) unique undirected edges
    edge_length: np.ndarray  # (E,)
    face_edges: np.ndarray  # (m, 3) index of the edge opposite local vertex v
    face_edge_sign: np.ndarray  # (m, 3) +1 if edges[..] = (v+1, v+2) in that order, else -1
    shells: tuple  # ((vertex ids, face ids), ...) of outward shells; empty for one shell


def prepare_cage(vertices: np.ndarray, faces: np.ndarray) -> CageTables:
    """The tables of a cage, built once per distinct cage.

    Parameters
    ----------
    vertices : (n, 3) array_like
    faces : (m, 3) array_like of int
        Outward-oriented cage.

    Returns
    -------
    CageTables
        Shared, read-only arrays (cached on the arrays' contents).
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(
            f"cage vertices must be (n, 3) and faces (m, 3); got {v.shape} and {f.shape}"
        )
    # Maps and bindings evaluate the same cage chunk after chunk: keyed on the arrays'
    # contents, the edge table, normals and shells are built once per cage.
    # (A cage of several shells also caches one entry per shell, see shell_cages.)
    return _prepare_cage_cached(v.shape, v.tobytes(), f.shape, f.tobytes())


@functools.lru_cache(maxsize=16)
def _prepare_cage_cached(vshape, vbytes, fshape, fbytes) -> CageTables:
    v = np.frombuffer(vbytes, dtype=np.float64).reshape(vshape)
    f = np.frombuffer(fbytes, dtype=np.int64).reshape(fshape)
    normals, areas = face_normals_and_areas(v, f)
    x = v[f]  # (m, 3 corners, 3)
    d = np.stack([x[:, (i + 1) % 3] - x[:, (i + 2) % 3] for i in range(3)], axis=1)
    n_cross_d = np.cross(normals[:, None, :], d)
    # edge opposite local vertex i joins corners i+1 and i+2
    a = np.stack([f[:, (i + 1) % 3] for i in range(3)], axis=1)
    b = np.stack([f[:, (i + 2) % 3] for i in range(3)], axis=1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys = np.stack([lo.ravel(), hi.ravel()], axis=1)
    edges, inverse = np.unique(keys, axis=0, return_inverse=True)
    face_edges = inverse.reshape(f.shape).astype(np.int64)
    face_edge_sign = np.where(a == lo, 1.0, -1.0)
    edge_length = np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)
    return CageTables(
        v,
        f,
        normals,
        2.0 * areas,
        np.ascontiguousarray(d),
        np.ascontiguousarray(n_cross_d),
        np.ascontiguousarray(edges.astype(np.int64)),
        edge_length,
        face_edges,
        face_edge_sign,
        _outward_shells(v, f, edges),
    )


def _outward_shells(v: np.ndarray, f: np.ndarray, edges: np.ndarray) -> tuple:
    """Vertex and face ids of each outward shell of a cage made of several shells.

    A cage of several disjoint outward shells bounds several separate domains, and by
    Green's third identity the map inside one of them needs only that shell's basis
    functions (plus inward "hole" shells, which are kept for every point). Evaluating the
    other shells' potentials there would couple parts of the shape that the cage
    separates (paper Figure 11), so :func:`~vhm_viz.core.basis.evaluate_basis` zeroes
    them. Returns ``()`` for a single shell (nothing to separate).
    """
    n = len(v)
    count, labels = edge_components(n, edges)
    used = np.unique(f)
    shell_ids = np.unique(labels[used])
    if len(shell_ids) < 2:
        return ()
    face_label = labels[f[:, 0]]
    centred = v - v.mean(axis=0)  # cones from the centroid: origin-free (geometry.signed_volume)
    a, b, c = centred[f[:, 0]], centred[f[:, 1]], centred[f[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c))
    shells = []
    for k in shell_ids:
        faces_k = np.nonzero(face_label == k)[0]
        if vol[faces_k].sum() > 0:  # outward shell: a separate domain
            shells.append((np.nonzero(labels == k)[0], faces_k))
    return tuple(shells) if len(shells) > 1 else ()


def separate_shells(cd: CageTables, values, gradients, hessians) -> None:
    """Zero, for each point, the basis functions of outward shells that do not contain it."""
    n = cd.vertices.shape[0]
    for vids, fids in cd.shells:
        outside = values[:, vids].sum(axis=1) < 0.5  # this shell's own winding number
        if not outside.any():
            continue
        rows = np.nonzero(outside)[0]
        cols = np.concatenate([vids, n + fids])
        for arr in (values, gradients, hessians):
            if arr is not None:
                arr[np.ix_(rows, *([np.arange(arr.shape[1])] if arr.ndim == 3 else []), cols)] = 0.0


def shell_cages(cd: CageTables) -> list:
    """``(columns, cage data, every point)`` of each outward shell, then of the holes.

    ``columns`` are the shell's basis columns in the whole cage (its vertices, then ``n``
    plus its faces); the hole shells, which every point keeps, form one cage.
    """
    n = cd.vertices.shape[0]
    out = []
    owned = np.zeros(cd.faces.shape[0], dtype=bool)
    groups = []
    for _, fids in cd.shells:
        owned[fids] = True
        groups.append((fids, False))
    holes = np.flatnonzero(~owned)
    if holes.size:
        groups.append((holes, True))
    for fids, every_point in groups:
        vids = np.unique(cd.faces[fids])
        remap = np.full(n, -1, dtype=np.int64)
        remap[vids] = np.arange(len(vids))
        sub = prepare_cage(cd.vertices[vids], remap[cd.faces[fids]])
        out.append((np.concatenate([vids, n + fids]), sub, every_point))
    return out


def read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view of ``a``.

    numba compiles a kernel once for each combination of writeable and read-only
    arrays; the cage's vertices and faces are read-only (cached), whereas a shell's
    coefficients, a caller's vertices or the points may not be: passed read-only
    everywhere, one compiled variant serves them all (each further variant is a full
    compilation on a first run). The kernels do not write to them.
    """
    view = a.view()
    view.flags.writeable = False
    return view


def kernel_arrays(cd: CageTables) -> tuple:
    """The cage arrays the compiled kernels take, in their order.

    ``vertices, faces, normals, 1 / (2 area), d, N x d, edges, edge lengths,
    1 / (4 pi |edge|), face_edges``: the leading parameters of
    :func:`~vhm_viz.core.basis_lanes.lanes_kernel`,
    :func:`~vhm_viz.core.basis_lanes.lanes_map_kernel` and the per-point kernel of
    :mod:`vhm_viz.core.basis_kernel`.
    """
    return (
        cd.vertices,
        cd.faces,
        cd.normals,
        1.0 / cd.twice_area,
        cd.d,
        cd.n_cross_d,
        cd.edges,
        cd.edge_length,
        1.0 / (4.0 * math.pi * cd.edge_length),
        cd.face_edges,
    )
