"""Geometry helpers against independent references.

The one closest-point routine against brute force over dense triangle samples; volumes and
open edges against VTK's own (``vtkCellSizeFilter``, ``vtkFeatureEdges`` through
PyVista).
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from vhm_viz.core.geometry import (
    closest_points_on_triangles,
    nearest_points_on_mesh,
    open_edge_count,
    point_triangle_distance2,
    signed_volume,
    tetrahedra_volume,
)


@numba.njit
def _distances2(p, a, b, c):
    out = np.empty(p.shape[0])
    for k in range(p.shape[0]):
        out[k] = point_triangle_distance2(p[k], a[k], b[k], c[k])
    return out


def _triangles(rng, n):
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    # every tenth triangle nearly flat: c close to the segment ab
    flat = slice(0, n, 10)
    c[flat] = a[flat] + 0.37 * (b[flat] - a[flat]) + 1e-7 * rng.normal(size=(len(c[flat]), 3))
    return a, b, c


def _sampled_min_distance(p, a, b, c, m=300):
    s, t = np.meshgrid(np.linspace(0, 1, m + 1), np.linspace(0, 1, m + 1), indexing="ij")
    keep = s + t <= 1 + 1e-12
    s, t = s[keep], t[keep]
    q = a + s[:, None] * (b - a) + t[:, None] * (c - a)
    return np.sqrt(((q - p) ** 2).sum(axis=1).min())


def test_closest_points_agree_with_dense_samples():
    rng = np.random.default_rng(7)
    n = 60
    a, b, c = _triangles(rng, n)
    p = 1.5 * rng.normal(size=(n, 3))
    q, region = closest_points_on_triangles(p, a, b, c)
    d = np.linalg.norm(q - p, axis=1)
    for k in range(n):
        sampled = _sampled_min_distance(p[k], a[k], b[k], c[k])
        longest = max(np.linalg.norm(b[k] - a[k]), np.linalg.norm(c[k] - a[k]))
        assert d[k] <= sampled + 1e-12
        assert d[k] >= sampled - 2 * longest / 300
    # q lies in its triangle: barycentric coordinates in [0, 1], the region's ones at 0
    corners = {4: a, 5: b, 6: c}
    for r, corner in corners.items():
        np.testing.assert_array_equal(q[region == r], corner[region == r])
    np.testing.assert_allclose(_distances2(p, a, b, c), d**2, rtol=1e-9, atol=1e-15)


def test_points_on_a_face_are_at_distance_zero_to_rounding():
    rng = np.random.default_rng(3)
    a, b, c = (rng.normal(size=(40, 3)) for _ in range(3))
    w = rng.dirichlet(np.ones(3), size=40)
    p = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    q, region = closest_points_on_triangles(p, a, b, c)
    assert np.all(region == 0)
    np.testing.assert_allclose(q, p, atol=1e-14)
    assert np.all(_distances2(p, a, b, c) < 1e-28)


@pytest.mark.parametrize("n_points", [0, 1, 500])
def test_nearest_points_on_mesh_is_the_brute_force_minimum(n_points):
    rng = np.random.default_rng(11)
    vertices = rng.normal(size=(30, 3))
    faces = np.array([rng.choice(30, 3, replace=False) for _ in range(40)])
    points = 2 * rng.normal(size=(n_points, 3))
    face, closest = nearest_points_on_mesh(points, vertices, faces)
    assert face.shape == (n_points,) and closest.shape == (n_points, 3)
    if not n_points:
        return
    tri = vertices[faces]
    rows = np.repeat(points, len(faces), axis=0)
    t = np.tile(np.arange(len(faces)), n_points)
    q, _ = closest_points_on_triangles(rows, tri[t, 0], tri[t, 1], tri[t, 2])
    d = np.linalg.norm(q - rows, axis=1).reshape(n_points, len(faces))
    np.testing.assert_array_equal(face, d.argmin(axis=1))
    np.testing.assert_allclose(np.linalg.norm(closest - points, axis=1), d.min(axis=1))


def _triangles_of(surface):
    return np.asarray(surface.faces).reshape(-1, 4)[:, 1:]


def test_open_edges_are_vtks():
    pv = pytest.importorskip("pyvista")
    sphere = pv.Sphere(theta_resolution=40, phi_resolution=30)
    cut = sphere.clip("x", origin=(0.1, 0, 0)).triangulate()
    two = pv.Sphere(center=(3, 0, 0)).merge(cut).triangulate()  # a closed and an open part
    # an edge of three triangles (open: not manifold) and a stray triangle
    fin = pv.PolyData(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [5, 5, 5.0]]),
        np.array([3, 0, 1, 2, 3, 1, 0, 3, 3, 0, 1, 4, 3, 5, 2, 4]),
    )
    for mesh in (sphere, cut, two, fin):
        expected = mesh.n_open_edges
        assert open_edge_count(_triangles_of(mesh), mesh.n_points) == expected
    assert sphere.n_open_edges == 0 and cut.n_open_edges > 0
    assert open_edge_count(np.zeros((0, 3), int), 0) == 0
    with pytest.raises(ValueError, match="index"):
        open_edge_count([[0, 1, 3]], 3)


def test_volumes_are_vtks():
    pv = pytest.importorskip("pyvista")
    from vtkmodules.vtkFiltersCore import vtkMassProperties

    rng = np.random.default_rng(3)
    # a closed surface far from the origin, scaled unevenly: VTK's volume of its solid
    shape = pv.Sphere(theta_resolution=60, phi_resolution=40).scale([1.0, 2.0, 0.5])
    mass = vtkMassProperties()
    mass.SetInputData(shape)
    mass.Update()
    far = np.asarray(shape.points, dtype=np.float64) + [1e4, -3e3, 2e3]
    got = signed_volume(far, _triangles_of(shape))
    assert got == pytest.approx(mass.GetVolume(), rel=1e-9)
    assert signed_volume(far, _triangles_of(shape)[:, ::-1]) == pytest.approx(-got, rel=1e-12)
    # tets, some inverted: VTK's signed cell volumes, summed
    points = rng.normal(size=(400, 3))
    tets = rng.integers(0, 400, size=(900, 4))
    tets = tets[np.array([len(set(t)) == 4 for t in tets])]
    grid = pv.UnstructuredGrid(
        np.hstack([np.full((len(tets), 1), 4), tets]).ravel(),
        np.full(len(tets), pv.CellType.TETRA),
        points,
    )
    got = tetrahedra_volume(points, tets)
    assert got == pytest.approx(grid.volume, rel=1e-12, abs=1e-12)
    corners = points[tets]
    signed = np.linalg.det(corners[:, 1:] - corners[:, :1]) / 6.0
    assert (signed < 0).any() and got == pytest.approx(signed.sum(), rel=1e-12, abs=1e-12)
    with pytest.raises(ValueError, match="index"):
        tetrahedra_volume(points, [[0, 1, 2, 400]])
