"""Connected components of a graph given by its edges (a cage's shells, a mesh's parts).

The labels are SciPy's (``scipy.sparse.csgraph.connected_components``, undirected):
component ``k`` is the one whose smallest vertex is the ``k``-th smallest of those. Small
graphs (cages) are labelled here with numpy, so that a command need not import SciPy's
sparse package; large ones go to SciPy, whose compiled search is faster there.
"""

from __future__ import annotations

import numpy as np

__all__ = ["edge_components"]

#: Graphs with more edges than this are labelled by SciPy.
_NUMPY_EDGES_MAX = 20_000


def edge_components(n: int, edges: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected components of ``n`` vertices joined by ``edges``.

    Parameters
    ----------
    n : int
        Vertex count (vertices on no edge are components of their own).
    edges : (k, 2) int array
        Undirected edges ``(i, j)``, ``0 <= i, j < n``; repeats and loops allowed.

    Returns
    -------
    count : int
    labels : (n,) int32
        Component of every vertex, ``0 .. count - 1``, numbered in the order of each
        component's smallest vertex.
    """
    edges = np.asarray(edges).reshape(-1, 2)
    if len(edges) > _NUMPY_EDGES_MAX:
        import scipy.sparse as sp  # here: importing it is slow, small graphs skip it
        from scipy.sparse import csgraph

        graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
        return csgraph.connected_components(graph, directed=False)
    root = _smallest_vertex_of_component(n, edges.astype(np.intp, copy=False))
    roots, labels = np.unique(root, return_inverse=True)
    return len(roots), labels.astype(np.int32)


def _smallest_vertex_of_component(n: int, edges: np.ndarray) -> np.ndarray:
    """(n,) intp: the smallest vertex of each vertex's component.

    Hooks every tree's root under the smallest root it shares an edge with, then jumps
    pointers until every vertex points at its root, until no edge joins two trees. A
    vertex's parent is never larger than itself, so each root is its tree's smallest
    vertex; the trees at least halve every two rounds.
    """
    parent = np.arange(n)
    u, v = edges[:, 0], edges[:, 1]
    while True:
        pu, pv = parent[u], parent[v]
        apart = pu != pv
        if not apart.any():
            return parent
        lo, hi = np.minimum(pu[apart], pv[apart]), np.maximum(pu[apart], pv[apart])
        np.minimum.at(parent, hi, lo)
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped
