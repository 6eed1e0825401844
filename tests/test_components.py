"""Connected components of an edge graph, against SciPy's csgraph (labels included)."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse import csgraph

from vhm_viz.core.components import edge_components


def _scipy_components(n, edges):
    e = np.asarray(edges).reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return csgraph.connected_components(graph, directed=False)


@pytest.mark.parametrize("seed", range(4))
def test_labels_equal_scipys_on_random_graphs(seed):
    rng = np.random.default_rng(seed)
    for _ in range(50):
        n = int(rng.integers(1, 400))
        edges = rng.integers(0, n, (int(rng.integers(0, 2 * n)), 2))
        count, labels = edge_components(n, edges)
        ref_count, ref_labels = _scipy_components(n, edges)
        assert count == ref_count
        assert labels.dtype == ref_labels.dtype
        np.testing.assert_array_equal(labels, ref_labels)


def test_long_chains_and_large_graphs():
    # a path numbered backwards (every hook goes one step down), then disjoint cycles
    n = 5000
    path = np.stack([np.arange(n - 1, 0, -1), np.arange(n - 2, -1, -1)], axis=1)
    count, labels = edge_components(n, path)
    assert count == 1 and not labels.any()
    # more edges than the numpy path takes: SciPy labels it, with the same numbering
    rng = np.random.default_rng(7)
    perm = rng.permutation(60_000)
    cycles = np.stack([perm, np.roll(perm.reshape(-1, 6), 1, axis=1).ravel()], axis=1)
    count, labels = edge_components(60_000, cycles)
    ref_count, ref_labels = _scipy_components(60_000, cycles)
    assert count == ref_count == 10_000
    np.testing.assert_array_equal(labels, ref_labels)


def test_isolated_vertices_and_no_edges():
    count, labels = edge_components(4, np.zeros((0, 2), dtype=int))
    assert count == 4
    np.testing.assert_array_equal(labels, [0, 1, 2, 3])
    count, labels = edge_components(5, [[4, 2], [3, 3]])
    np.testing.assert_array_equal(labels, [0, 1, 2, 3, 2])
    assert count == 4
