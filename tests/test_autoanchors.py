"""Automatic anchors: inside the shape and the cage, spread, on the medial structure."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage, data_path, read_triangles

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
        auto_anchors((v, f), cage, 10_000, resolution=8)
    # the solver's matrices grow with the square of the count: its range ends at 10,000
    with pytest.raises(ValueError, match=r"count must be an integer in \[1, 10000\]"):
        auto_anchors((v, f), cage, 10_001)
    # a grid that cannot fit is refused before any of it exists, naming its size
    grid = r"a \d+x\d+x100005 voxel grid needs about .* use a lower resolution"
    with pytest.raises(ValueError, match=grid):
        auto_anchors((v, f), cage, 4, resolution=100_000)


def test_ball_centre_is_badoiu_clarksons_and_nears_the_smallest_ball():
    from vhm_viz.autocage.anchors import _ball_centre

    def reference(points, rounds=30):  # the iteration as written with numpy
        c = points.mean(axis=0)
        for i in range(1, rounds + 1):
            far = points[np.argmax(((points - c) ** 2).sum(axis=1))]
            c = c + (far - c) / (i + 1)
        return c

    rng = np.random.default_rng(12)
    for n in (1, 2, 5, 300, 4000):
        for scale, shift in ((1.0, 0.0), (50.0, 1e4)):
            pts = scale * rng.normal(size=(n, 3)) + shift
            np.testing.assert_array_equal(_ball_centre(pts), reference(pts))
            ties = np.round(pts, 0)  # equal distances: the first farthest point is taken
            np.testing.assert_array_equal(_ball_centre(ties), reference(ties))
    # points on a sphere, crowded on one side: the centre is the sphere's, not the mean
    d = rng.normal(size=(3000, 3))
    d[:2500, 0] = np.abs(d[:2500, 0])
    sphere = 2.0 * d / np.linalg.norm(d, axis=1, keepdims=True) + [1.0, -3.0, 0.5]
    centre = _ball_centre(sphere, rounds=400)
    assert (
        np.linalg.norm(centre - [1.0, -3.0, 0.5])
        < 0.1
        < np.linalg.norm(sphere.mean(axis=0) - [1.0, -3.0, 0.5])
    )


def test_medial_voxels_are_the_ridge_of_the_distance():
    from scipy import ndimage

    from vhm_viz.autocage.anchors import _medial

    def reference(depth, interior):  # the ridge test written with numpy, every voxel
        pad = np.pad(depth, 1)
        rise = np.full(depth.shape, -np.inf)
        for off in np.argwhere(np.ones((3, 3, 3), bool)) - 1:
            if not off.any():
                continue
            window = tuple(slice(1 + o, 1 + o + s) for o, s in zip(off, depth.shape, strict=True))
            rise = np.maximum(rise, (pad[window] - depth) / np.linalg.norm(off))
        return interior & (rise < 0.5)

    rng = np.random.default_rng(3)
    for shape in ((1, 1, 1), (7, 5, 9), (30, 24, 18)):
        blob = ndimage.gaussian_filter(rng.random(shape), 2.0) > 0.5
        blob[0, 0, 0] = True  # never empty
        depth = ndimage.distance_transform_edt(blob)
        every = np.argwhere(np.ones(shape, bool))
        np.testing.assert_array_equal(
            _medial(depth, blob, every), reference(depth, blob)[tuple(every.T)]
        )


@pytest.mark.parametrize("count", [4, 8, 12])
def test_anchors_of_a_whole_volume_cover_its_box(count):
    # no threshold: the shape is the image's whole box, so the anchors spread through it
    # and the report measures the box's inside, not its corners
    from scipy.spatial import cKDTree

    vol = pv.ImageData(dimensions=(40, 30, 20), spacing=(1.0, 1.5, 2.0), origin=(5, -3, 2))
    vol["v"] = np.arange(vol.n_points, dtype=float)
    cage = auto_cage(vol)
    anchors, report = auto_anchors(vol, cage, count, return_report=True)
    assert anchors.shape == (count, 3) and cage.contains(anchors).all()
    b = np.asarray(vol.bounds).reshape(3, 2)
    diag = float(np.linalg.norm(b[:, 1] - b[:, 0]))
    # brute force: the farthest point of a fine lattice of the box from every anchor
    lattice = np.stack(np.meshgrid(*[np.linspace(*s, 61) for s in b], indexing="ij"), -1)
    coverage = float(cKDTree(anchors).query(lattice.reshape(-1, 3))[0].max())
    # the report's lattice is coarser (32 points along the longest side)
    assert abs(report.coverage - coverage) <= 0.5 * np.sqrt(3) * np.ptp(b, axis=1).max() / 31
    # about the best that `count` balls do in a box: 8 balls each around an eighth
    assert coverage < {4: 0.4, 8: 0.3, 12: 0.27}[count] * diag
    assert report.min_pairwise_distance > 0.1 * diag


@pytest.mark.data
def test_a_cage_that_leaves_points_out_is_refused_with_their_count():
    # 12 of the 252 armadillo points lie outside this cage (an independent count below):
    # anchors of the part it holds are not anchors of the data, as deform refuses it
    from vhm_viz import OutsideCageError

    mesh = pv.read(data_path("bad_cages", "armadillo_252v_for_partial_cage.obj"))
    cage = read_cage(data_path("bad_cages", "partial_armadillo_cage.obj"))
    v, f = read_triangles(data_path("bad_cages", "partial_armadillo_cage.obj"))
    pts = np.asarray(mesh.points)
    outside = np.flatnonzero(winding_number(pts, v, f) < 0.5)
    assert len(outside) == 12
    with pytest.raises(OutsideCageError, match="12 of 252 points") as info:
        auto_anchors(mesh, cage, 24)
    np.testing.assert_array_equal(np.sort(info.value.indices), outside)


@pytest.mark.data
def test_a_cage_around_other_data_is_refused():
    # the bar's cage holds a corner of the hand: all anchors landed on one voxel there
    with pytest.raises(ValueError, match="outside the cage"):
        auto_anchors(
            data_path("hand", "hand.obj"), read_cage(data_path("bar", "bar_cage_3d.obj")), 24
        )


def test_a_volume_must_lie_in_the_cage_as_its_shape_is_chosen():
    # without a threshold the shape is the whole box; with one, the voxels above it
    vol = pv.ImageData(dimensions=(21, 21, 21), spacing=(0.1, 0.1, 0.1))
    vol["v"] = (np.linalg.norm(vol.points - 1.0, axis=1) < 0.5).astype(float)
    ball_cage = Cage(*box_cage((0.4, 0.4, 0.4), (1.6, 1.6, 1.6), 2))
    with pytest.raises(ValueError, match="volume's box"):
        auto_anchors(vol, ball_cage, 4)
    anchors = auto_anchors(vol, ball_cage, 4, threshold=0.5)
    assert np.linalg.norm(anchors - 1.0, axis=1).max() < 0.5
    small = Cage(*box_cage((0.75, 0.75, 0.75), (1.25, 1.25, 1.25), 2))
    above = int((np.abs(vol.points - 1.0).max(axis=1) > 0.25)[vol["v"] > 0.5].sum())
    with pytest.raises(ValueError, match=f"{above} of {int((vol['v'] > 0.5).sum())} voxels"):
        auto_anchors(vol, small, 4, threshold=0.5)


@pytest.mark.parametrize("resolution", [6, 12])
def test_anchors_never_coincide_where_the_skeleton_has_fewer_voxels(resolution):
    # a cube's skeleton at a coarse grid is its centre voxel: the four anchors still get
    # four distinct places inside the cube
    cube = pv.Cube().triangulate()
    cage = Cage(*box_cage((-2, -2, -2), (2, 2, 2)))
    anchors, report = auto_anchors(cube, cage, 4, resolution=resolution, return_report=True)
    assert len(np.unique(anchors, axis=0)) == 4 and report.min_pairwise_distance > 0
    assert np.abs(anchors).max() < 0.5


def test_many_anchors_in_a_fat_shape_are_distinct_and_spread():
    # a cube's skeleton is its centre voxel: every anchor after the first is the free
    # candidate farthest from the anchors placed
    cube = pv.Cube().triangulate()
    cage = Cage(*box_cage((-2, -2, -2), (2, 2, 2)))
    anchors, report = auto_anchors(cube, cage, 300, resolution=24, return_report=True)
    assert len(np.unique(anchors, axis=0)) == 300
    assert np.abs(anchors).max() < 0.5 and cage.contains(anchors).all()
    # farthest-point sampling of 300 points in the unit cube leaves no gap near its side
    assert report.coverage < 0.25 and report.min_pairwise_distance > 0.05


def test_crowding_moves_are_undone_one_anchor_after_another():
    # the Lloyd rounds' rule, checked against its plain statement: anchor after anchor,
    # a move that lands nearer than the spread to another anchor (where that one is now)
    # goes back
    from vhm_viz.autocage.anchors import _undo_crowding

    rng = np.random.default_rng(3)
    centres = rng.random((400, 3))
    undone = kept = 0
    for _ in range(30):
        chosen = rng.choice(400, 60, replace=False)
        moved = chosen.copy()
        hop = rng.random(60) < 0.5
        moved[hop] = rng.integers(0, 400, hop.sum())
        spread = 0.05 + 0.1 * rng.random()
        want = moved.copy()
        for a in range(len(want)):
            others = np.delete(want, a)
            if np.linalg.norm(centres[others] - centres[want[a]], axis=1).min() < spread:
                want[a] = chosen[a]
        got = moved.copy()
        _undo_crowding(centres, chosen, got, spread)
        assert np.array_equal(got, want)
        undone += int(np.sum((want != moved) & hop))
        kept += int(np.sum((want == moved) & (moved != chosen)))
    assert undone > 20 and kept > 20  # both outcomes occur
