"""Cheap topology check for triangle meshes (pure numpy).

Used by :func:`vhm_viz.auto_cage` to reject a simplified surface early, before pushing it
out (which needs a closed 2-manifold) and before :class:`vhm_viz.Cage` validates it fully.
"""

from __future__ import annotations

import numpy as np

__all__ = ["edge_problems"]


def edge_problems(faces: np.ndarray) -> dict[str, int]:
    """Count open, non-manifold and inconsistently oriented edges, and non-manifold vertices.

    Parameters
    ----------
    faces : (m, 3) int array

    Returns
    -------
    dict
        ``open``, ``nonmanifold``, ``misoriented``, ``nonmanifold_vertices``, ``degenerate``
        (faces repeating a vertex); all zero for a closed, oriented 2-manifold.
    """
    f = np.asarray(faces, dtype=np.int64)
    degenerate = int(((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])).sum())
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1 if len(f) else 0
    key = directed[:, 0] * n + directed[:, 1]
    ukey, dcount = np.unique(key, return_counts=True)
    undirected = np.sort(directed, axis=1)
    ukey2, ucount = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    open_edges = int((ucount == 1).sum())
    nonmanifold = int((ucount > 2).sum())
    misoriented = int((dcount > 1).sum())
    # vertex manifoldness: the link of every vertex is one cycle
    nm_vertices = 0
    if open_edges == 0 and nonmanifold == 0 and misoriented == 0 and len(f):
        # walk links: for face (v, b, c) the link edge of v is b -> c
        v = f.ravel()
        b = f[:, [1, 2, 0]].ravel()
        c = f[:, [2, 0, 1]].ravel()
        order = np.lexsort((b, v))
        v, b, c = v[order], b[order], c[order]
        # successor of link edge (v, b->c) is the link edge (v, c->?)
        keys = v * n + b
        pos = np.searchsorted(keys, v * n + c)
        succ = pos
        # count cycles per vertex by pointer jumping
        visited = np.zeros(len(v), dtype=bool)
        cycles = np.zeros(n, dtype=np.int64)
        for start in range(len(v)):
            if visited[start]:
                continue
            cycles[v[start]] += 1
            cur = start
            while not visited[cur]:
                visited[cur] = True
                cur = succ[cur]
        nm_vertices = int((cycles > 1).sum())
    return {
        "open": open_edges,
        "nonmanifold": nonmanifold,
        "misoriented": misoriented,
        "nonmanifold_vertices": nm_vertices,
        "degenerate": degenerate,
    }
