"""HarmonicMap: evaluation API, Green Coordinates mode, outside-point policies."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage, data_path, interior_points
from scipy.spatial.transform import Rotation

from vhm_viz.core.errors import OutsideCageError
from vhm_viz.core.harmonic_map import HarmonicMap, green_stretch


@pytest.fixture
def hand_cage():
    import vhm_viz

    return vhm_viz.read_cage(data_path("hand", "cage.obj"))


def test_identity_map(hand_cage):
    rng = np.random.default_rng(0)
    pts = interior_points(hand_cage.vertices, hand_cage.faces, 50, rng)
    hm = HarmonicMap.identity(hand_cage)
    f, jac, hess = hm.evaluate(pts, order=2)
    assert np.allclose(f, pts, atol=1e-12 * hand_cage.diagonal)
    assert np.allclose(jac, np.eye(3), atol=1e-12)
    assert np.abs(hess).max() < 1e-9
    assert np.allclose(hm.map(pts), f) and np.allclose(hm.jacobian(pts), jac)
    assert np.allclose(hm.hessian(pts), hess)


def test_green_coordinates_identity_and_similarity(hand_cage):
    rng = np.random.default_rng(1)
    pts = interior_points(hand_cage.vertices, hand_cage.faces, 40, rng)
    v = hand_cage.vertices
    ident = HarmonicMap.from_target_cage(hand_cage, v)
    assert np.allclose(green_stretch(v, v, hand_cage.faces), 1.0)
    assert np.allclose(ident.map(pts), pts, atol=1e-12 * hand_cage.diagonal)
    rot = Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix()
    scale, shift = 1.7, np.array([3.0, -1.0, 0.5])
    sim = HarmonicMap.from_target_cage(hand_cage, scale * v @ rot.T + shift)
    assert np.allclose(green_stretch(v, scale * v @ rot.T, hand_cage.faces), scale)
    f, jac, _ = sim.evaluate(pts, order=1)
    assert np.allclose(f, scale * pts @ rot.T + shift, atol=1e-10 * scale * hand_cage.diagonal)
    assert np.allclose(jac, scale * rot, atol=1e-10)


def test_green_coordinates_general_target_is_quasi_conformal(hand_cage):
    # a non-similarity target: still harmonic and smooth, det J > 0 for a mild stretch
    v = hand_cage.vertices
    target = v * np.array([1.2, 1.0, 0.9])
    rng = np.random.default_rng(2)
    pts = interior_points(v, hand_cage.faces, 30, rng)
    jac = HarmonicMap.from_target_cage(hand_cage, target).jacobian(pts)
    assert (np.linalg.det(jac) > 0).all()
    with pytest.raises(ValueError, match="target_vertices"):
        HarmonicMap.from_target_cage(hand_cage, target[:-1])


def test_outside_points_policies():
    import vhm_viz

    v, f = box_cage((0, 0, 0), (1, 1, 1), 2)
    cage = vhm_viz.Cage(v, f)
    hm = HarmonicMap.affine(cage, 2 * np.eye(3), (1, 0, 0))
    pts = np.array([[0.5, 0.5, 0.5], [2.0, 0.5, 0.5], [0.2, 0.3, 0.4], [-1.0, 0, 0]])
    with pytest.raises(OutsideCageError, match=r"2 of 4 points.*1, 3") as err:
        hm.map(pts)
    assert list(err.value.indices) == [1, 3]
    f, jac, hess = hm.evaluate(pts, order=2, outside="passthrough")
    assert np.allclose(f[[1, 3]], pts[[1, 3]]) and np.allclose(jac[[1, 3]], np.eye(3))
    assert np.allclose(f[[0, 2]], 2 * pts[[0, 2]] + [1, 0, 0])
    assert np.allclose(hess, 0, atol=1e-10)
    f = hm.map(pts, outside="nan")
    assert np.isnan(f[[1, 3]]).all() and np.isfinite(f[[0, 2]]).all()
    assert list(hm.inside(pts)) == [True, False, True, False]
    with pytest.raises(ValueError, match="outside"):
        hm.map(pts, outside="clip")


def test_chunking_does_not_change_results(hand_cage):
    rng = np.random.default_rng(3)
    pts = interior_points(hand_cage.vertices, hand_cage.faces, 100, rng)
    z = rng.normal(size=(hand_cage.n_vertices + hand_cage.n_faces, 3))
    hm = HarmonicMap(hand_cage, z)
    a = hm.evaluate(pts, order=2, memory_budget=1)  # the smallest chunk: 16 points
    b = hm.evaluate(pts, order=2)
    for x, y in zip(a, b, strict=True):
        # BLAS blocking differs between chunk sizes: equal to rounding, not bit-for-bit
        assert np.abs(x - y).max() <= 1e-13 * np.abs(y).max()


def test_bad_coefficients(hand_cage):
    n = hand_cage.n_vertices + hand_cage.n_faces
    with pytest.raises(ValueError, match=r"\(n_vertices \+ n_faces, 3\)"):
        HarmonicMap(hand_cage, np.zeros((n - 1, 3)))
    z = np.zeros((n, 3))
    z[5, 1] = np.inf
    with pytest.raises(ValueError, match="rows 5"):
        HarmonicMap(hand_cage, z)
    hm = HarmonicMap.identity(hand_cage)
    with pytest.raises(ValueError, match="read-only"):
        hm.coefficients[0, 0] = 1.0


@pytest.mark.parametrize("cage_kind", ["box", "hand"])
def test_points_on_cage_edges_and_vertices_take_the_interior_limit(cage_kind, hand_cage):
    """At a cage vertex or on an edge the closed forms' derivatives are undefined: such a
    point is evaluated just inside, like one that rounding put outside. An affine map
    must come out as itself there, on the flat (subdivided box) and concave (hand) edges
    and vertices as on the convex ones."""
    from vhm_viz.core.cage import Cage

    cage = Cage(*box_cage((0, 0, 0), (1, 1, 2), 2)) if cage_kind == "box" else hand_cage
    v, f = np.asarray(cage.vertices), np.asarray(cage.faces)
    a = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix() * 1.7
    t = np.array([0.3, -1.0, 2.0])
    hm = HarmonicMap.affine(cage, a, t)
    points = np.vstack([v, (v[f] + v[np.roll(f, 1, axis=1)]).reshape(-1, 3) / 2])
    value, jac, hess = hm.evaluate(points, order=2)
    size = np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    assert np.abs(value - (points @ a.T + t)).max() < 1e-9 * size
    assert np.isfinite(jac).all() and np.isfinite(hess).all()
    assert np.abs(jac - a).max() < 1e-6 * np.abs(a).max()
