"""Automatic anchors: inside the shape and the cage, spread, on the medial structure."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage, data_path

pv = pytest.importorskip("pyvista")

from vhm_viz.autocage import auto_anchors, auto_cage, otsu_threshold  # noqa: E402
from vhm_viz.core.basis import winding_number  # noqa: E402
from vhm_viz.core.cage import Cage  # noqa: E402
from vhm_viz.io import read_cage  # noqa: E402


def test_bar_anchors_lie_on_the_centre_line_and_are_spread():
    v, f = box_cage((0, 0, 0), (1, 1, 5), 6)
    cage = Cage(*box_cage((-0.1, -0.1, -0.1), (1.1, 1.1, 5.1), 2))
    anchors, report = auto_anchors((v, f), cage, 6, return_report=True)
    assert anchors.shape == (6, 3)
    # medial axis of a square bar: its centre line (within a voxel or two)
    assert np.abs(anchors[:, :2] - 0.5).max() < 0.15
    assert np.ptp(anchors[:, 2]) > 3.0  # spread along the bar
    assert report.min_pairwise_distance > 0.5
    assert cage.contains(anchors).all()
    assert (winding_number(anchors, v, f) > 0.999).all()


@pytest.mark.data
def test_hand_anchors_inside_shape_and_cage():
    mesh = pv.read(data_path("hand", "hand.obj")).triangulate()
    v = np.asarray(mesh.points)
    f = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    cage = read_cage(data_path("hand", "cage.obj"))
    anchors, report = auto_anchors(mesh, cage, 40, return_report=True)
    assert anchors.shape == (40, 3)
    assert cage.contains(anchors).all()
    assert (winding_number(anchors, v, f) > 0.999).all()
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    # farthest point sampling on the medial structure: well spread
    assert report.min_pairwise_distance > 0.03 * diag
    # strictly inside: each anchor is away from the surface
    d = np.min(np.linalg.norm(anchors[:, None, :] - v[None, ::3, :], axis=2), axis=1)
    assert d.min() > 0.005 * diag


@pytest.mark.data
def test_volume_anchors_inside_the_thresholded_region():
    vol = pv.read(data_path("volumes", "headsq_64x64x93.vti"))
    cage = auto_cage(vol, threshold="otsu", max_faces=300)
    anchors = auto_anchors(vol, cage, 12, threshold="otsu")
    assert cage.contains(anchors).all()
    vals = np.asarray(vol.active_scalars)
    # the image sample nearest to each anchor is in the region above the threshold
    nearest = vol.find_closest_point
    idx = np.array([nearest(a) for a in anchors])
    assert (vals[idx] > otsu_threshold(vals)).all()


def test_bad_counts_and_inputs():
    v, f = box_cage((0, 0, 0), (1, 1, 5), 4)
    cage = Cage(*box_cage((-0.1, -0.1, -0.1), (1.1, 1.1, 5.1), 1))
    with pytest.raises(ValueError, match="count"):
        auto_anchors((v, f), cage, 0)
    with pytest.raises(ValueError, match="NaN"):
        auto_anchors(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan]]), cage, 3)
    with pytest.raises(ValueError, match="interior"):
        auto_anchors((v, f), cage, 10**6)
