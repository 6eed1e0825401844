"""vhm_viz.tetrahedralize: fTetWild's mesh of a closed surface, checked against the solid."""

import warnings

import numpy as np
import pytest

from vhm_viz import examples, tetrahedralize


def _signed_volumes(grid):
    x = np.asarray(grid.points)[grid.cells_dict[10]]
    a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def test_a_closed_box_fills_with_tetrahedra_of_its_volume(tmp_path, monkeypatch):
    """The bar's surface (1 x 1 x 5): tetrahedra only, one orientation, their volumes
    summing to the box's within fTetWild's envelope, inside the envelope around the box;
    no stray file where the user works and no library deprecation warning."""
    monkeypatch.chdir(tmp_path)
    epsilon = 1e-3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        grid = tetrahedralize(examples.bar_surface(3), edge_length=0.25, optimize=False,
                              epsilon=epsilon, num_threads=1)  # fmt: skip
    assert set(grid.cells_dict) == {10} and grid.n_cells > 100
    vol = _signed_volumes(grid)
    assert (vol > 0).all() or (vol < 0).all()
    diagonal = np.sqrt(1 + 1 + 25)
    surface_area = 4 * 5 + 2
    assert abs(abs(vol).sum() - 5.0) <= surface_area * epsilon * diagonal
    lo, hi = np.asarray(grid.points).min(0), np.asarray(grid.points).max(0)
    tol = epsilon * diagonal
    assert np.all(lo >= np.array([-0.5, -0.5, 0.0]) - tol)
    assert np.all(hi <= np.array([0.5, 0.5, 5.0]) + tol)
    assert list(tmp_path.iterdir()) == []


def test_an_open_surface_is_refused_before_meshing():
    points, triangles = examples.bar_surface(2)
    with pytest.raises(ValueError, match="not closed .* boundary edges"):
        tetrahedralize((points, triangles[1:]))
