"""Tests of vhm_viz.core.metrics, the anchor sampler and the rigidity-line readers."""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import box_cage, data_path
from scipy.spatial.transform import Rotation

from vhm_viz.core import metrics
from vhm_viz.core.anchors import anchors_from_polylines
from vhm_viz.io import ReadError, read_polylines, read_tgf


@pytest.fixture(scope="module")
def box():
    return box_cage((0, 0, 0), (1, 2, 3), divisions=4)


def test_rigid_motion_has_no_distortion(box):
    v, f = box
    R = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    y = v @ R.T + [1, 2, 3]
    assert metrics.rigidity_distortion(v, y, f) == pytest.approx(0, abs=1e-24)
    assert metrics.volume_change(v, y, f) == pytest.approx(0, abs=1e-14)


@pytest.mark.parametrize("s", [0.5, 1.3, 2.0])
def test_uniform_scale(box, s):
    v, f = box
    assert metrics.rigidity_distortion(v, s * v, f) == pytest.approx(2 * (s - 1) ** 2, rel=1e-12)
    assert metrics.volume_change(v, s * v, f) == pytest.approx(abs(s**3 - 1), rel=1e-12)


def test_anisotropic_stretch_is_area_weighted():
    # two triangles in the xy plane, one stretched by 2 along x, the other rigid
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [12, 0, 0], [10, 2, 0.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    y = v.copy()
    y[:3, 0] *= 2.0
    # triangle 0: singular values (2, 1) -> 1; area 0.5. Triangle 1: rigid, area 2.
    assert metrics.rigidity_distortion(v, y, f) == pytest.approx(1.0 * 0.5 / 2.5)
    s, area = metrics.triangle_singular_values(v, y, f)
    np.testing.assert_allclose(s[0], [2, 1])
    np.testing.assert_allclose(area, [0.5, 2.0])
    # the 2x2 map of a triangle is independent of its placement in 3D
    R = Rotation.from_euler("zx", [35, 60], degrees=True).as_matrix()
    s2, _ = metrics.triangle_singular_values(v @ R.T, y, f)
    np.testing.assert_allclose(s2, s, atol=1e-12)


def test_collapsed_and_bad_input():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    f = np.array([[0, 1, 2]])
    y = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]])  # collapsed onto a line
    s, _ = metrics.triangle_singular_values(v, y, f)
    assert np.isfinite(s).all() and s[0, 1] == pytest.approx(0, abs=1e-12)
    with pytest.raises(ValueError):
        metrics.rigidity_distortion(v, y[:2], f)
    with pytest.raises(ValueError):
        metrics.rigidity_distortion(v, v, np.array([[0, 1, 5]]))
    with pytest.raises(ValueError):
        metrics.volume_change(v, v, f)  # encloses no volume


def test_jacobian_measures():
    R = Rotation.from_rotvec([0, 0, np.pi / 3]).as_matrix()
    S = np.diag([3.0, 2.0, 0.5])
    flip = np.diag([1.0, 1.0, -1.0])
    J = np.array([R, 2 * R, R @ S, flip, np.zeros((3, 3))])
    m = metrics.jacobian_measures(J)
    np.testing.assert_allclose(m["determinant"], [1, 8, 3, -1, 0], atol=1e-12)
    np.testing.assert_allclose(m["condition_number"][:4], [1, 1, 6, 1], rtol=1e-12)
    assert np.isinf(m["condition_number"][4])
    np.testing.assert_allclose(m["rotation_angle"][:3], np.pi / 3, atol=1e-12)
    np.testing.assert_allclose(m["stretch"], [1, 2, 3, 1, 0], atol=1e-12)
    assert m["foldovers"] == 2
    np.testing.assert_allclose(metrics.jacobian_determinant(J), m["determinant"])
    np.testing.assert_allclose(metrics.condition_number(J)[:4], m["condition_number"][:4])
    np.testing.assert_allclose(metrics.rotation_angle(J[:3], degrees=True), 60.0)
    np.testing.assert_allclose(metrics.stretch(J), m["stretch"], atol=1e-12)
    assert metrics.foldover_count(J) == 2
    # polar factor of a reflection is a proper rotation (angle pi for diag(1, 1, -1) -> ...)
    assert 0 <= m["rotation_angle"][3] <= np.pi
    with pytest.raises(ValueError):
        metrics.jacobian_measures(np.zeros((4, 2, 2)))


# ----------------------------------------------------------------------------- anchors / io


def test_anchors_evenly_spaced_on_a_line():
    a = anchors_from_polylines([[0, 0, 0], [0, 0, 5]], [[0, 1]], 6)
    np.testing.assert_allclose(a[:, 2], (np.arange(6) + 0.5) * 5 / 6)
    np.testing.assert_allclose(a[:, :2], 0)


def test_anchors_proportional_to_length():
    # a 3-long and a 1-long line (disconnected), plus a zero-length segment
    p = np.array([[0, 0, 0], [3, 0, 0], [0, 5, 0], [0, 6, 0], [7, 7, 7]])
    e = np.array([[0, 1], [2, 3], [4, 4]])
    a = anchors_from_polylines(p, e, 8)
    assert np.sum(a[:, 1] == 0) == 6 and np.sum(a[:, 0] == 0) == 2
    assert len(np.unique(a, axis=0)) == 8
    with pytest.raises(ValueError):
        anchors_from_polylines(p, e, 0)
    with pytest.raises(ValueError):
        anchors_from_polylines(p, [[0, 9]], 3)
    with pytest.raises(ValueError):
        anchors_from_polylines(p, [[4, 4]], 3)


def test_read_polylines_roundtrip(tmp_path):
    path = tmp_path / "lines.off"
    path.write_text("OFF\n4 0 3\n0 0 0\n1 0 0\n1 1 0\n# comment\n1 1 1\n2 0 1\n2 1 2\n2 2 3\n")
    p, e = read_polylines(path)
    assert p.shape == (4, 3) and e.tolist() == [[0, 1], [1, 2], [2, 3]]
    a = anchors_from_polylines(p, e, 3)
    np.testing.assert_allclose(a, [[0.5, 0, 0], [1, 0.5, 0], [1, 1, 0.5]])
    bad = tmp_path / "bad.off"
    bad.write_text("PLY\n")
    with pytest.raises(ValueError):
        read_polylines(bad)
    bad.write_text("OFF\n2 0 1\n0 0 0\n1 1 1\n2 0 7\n")
    with pytest.raises(ValueError):
        read_polylines(bad)


def test_read_tgf(tmp_path):
    path = tmp_path / "s.tgf"
    path.write_text("1 0 0 0 extra\n2 0 1 0\n3 1 1 0\n#\n1 2 1 0 0\n2 3\n#\n")
    j, b = read_tgf(path)
    np.testing.assert_allclose(j, [[0, 0, 0], [0, 1, 0], [1, 1, 0]])
    assert b.tolist() == [[0, 1], [1, 2]]
    path.write_text("1 0 0 0\n#\n1 5\n")
    with pytest.raises(ValueError):
        read_tgf(path)


def test_a_file_that_is_no_tgf_skeleton_is_named_as_such(tmp_path):
    """An OBJ named as the skeleton, or joints without bones: the file, not 'the polylines
    have zero total length' from the anchors placed on nothing."""
    obj = tmp_path / "cage.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ReadError, match=re.escape(f"{obj}:1: malformed TGF joint line 'v 0 0 0'")):
        read_tgf(obj)
    joints = tmp_path / "joints.tgf"
    joints.write_text("1 0 0 0\n2 0 1 0\n#\n")
    with pytest.raises(ReadError) as err:
        read_tgf(joints)
    assert str(err.value) == (
        f"{joints}: no bones: a TGF skeleton lists its joints, a line '#', then its bones "
        "(two joint numbers a line)"
    )


@pytest.mark.data
def test_shared_rigidity_lines():
    p, e = read_polylines(data_path("hand", "polylines.off"))
    assert p.shape == (311, 3) and e.shape == (310, 2)
    j, b = read_tgf(data_path("hand_tet", "hand.tgf"))
    assert j.shape == (21, 3) and b.shape == (20, 2)
    a = anchors_from_polylines(j, b, 28)
    assert a.shape == (28, 3)
