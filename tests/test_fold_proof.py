"""The lattice's proof that voxel cells of a warp are not inverted, against brute force."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage, trilinear_corner_dets

from vhm_viz import Cage, HarmonicMap
from vhm_viz.core.cell_kernels import hexahedron_corner_determinants, inverted_hexahedra
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.volume import VolumeDeformation

DIMS = (40, 36, 36)


def _box_map(lo, hi, push: float, seed: int | None = None) -> HarmonicMap:
    """A 3-division box cage around ``[lo, hi]``; its vertices left of ``x = 10`` pushed
    ``push`` along x (past the others: the map folds), plus random noise with ``seed``."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pad = 0.05 * (hi - lo).max()
    cage = Cage(*box_cage(lo - pad, hi + pad, 3))
    z = np.array(HarmonicMap.identity(cage).coefficients)
    v = np.asarray(cage.vertices)
    z[: len(v)][v[:, 0] < 10, 0] += push
    if seed is not None:
        z += 0.004 * cage.diagonal * np.random.default_rng(seed).standard_normal(z.shape)
    return HarmonicMap(cage, z)


def _cover(boxes, cells) -> np.ndarray:
    """How many boxes hold each cell, in VTK's cell order (``cells``: per axis)."""
    count = np.zeros(tuple(cells[::-1]), dtype=np.int64)
    for i0, i1, j0, j1, k0, k1 in boxes:
        count[k0 : k1 + 1, j0 : j1 + 1, i0 : i1 + 1] += 1
    return count.reshape(-1)


def _check(hm, geo, outside="error"):
    """Warp, prove, and compare with every cell measured; returns the proven fraction."""
    vol = VolumeDeformation(hm, geo, pre_images=False, outside=outside)
    points = vol.warp()
    boxes = vol.unproven_cells()
    dims = tuple(int(d) for d in geo.dimensions)
    cells = np.array(dims) - 1
    cover = _cover(boxes, cells)
    assert cover.max() <= 1  # disjoint, and within the image's cells
    rest_det = float(np.linalg.det(geo.index_to_world))
    every = hexahedron_corner_determinants(points, dims, rest_det)
    # the independent reference: numpy's determinants of every cell
    grid = points.reshape(*dims[::-1], 3) * [np.sign(rest_det), 1.0, 1.0]
    ref = trilinear_corner_dets(grid) / abs(rest_det)
    np.testing.assert_allclose(every, ref, rtol=1e-9, atol=1e-12)
    inverted = np.flatnonzero(every <= 0)
    # no inverted cell was proven, and the closest call among the proven cells is far
    assert cover[inverted].all()
    proven = cover == 0
    if proven.any():
        assert ref[proven].min() > 1e-4 * np.median(ref[proven])
    # a proven cell's eight corners are values of leaves of one size, none cut (the
    # polynomials agree on the faces they share): brute force over the proven cells
    lat = vol.lattice
    i, j, k = np.unravel_index(np.flatnonzero(proven), cells, order="F")
    lower = np.column_stack([i, j, k])
    owners = np.stack(
        [lat.locate((lower + [(c >> a) & 1 for a in range(3)]).astype(float)) for c in range(8)]
    )
    assert (owners >= 0).all() and not lat.leaf_cut[owners].any()
    assert (lat.leaf_size[owners] == lat.leaf_size[owners[0]]).all()
    found = inverted_hexahedra(points, dims, rest_det, boxes)
    np.testing.assert_array_equal(found["inverted"], inverted)
    np.testing.assert_array_equal(found["determinant"], every[inverted])
    assert found["cells"] == int(np.isfinite(every[cover == 1]).sum())
    return proven.mean(), inverted.size, vol


@pytest.mark.parametrize("mirror", [False, True])
def test_no_inverted_cell_is_proven_in_a_folding_map(mirror):
    # mirrored: a left-handed image of the same box of space, i running along -x
    direction = np.diag([-1.0, 1.0, 1.0]) if mirror else np.eye(3)
    origin = (DIMS[0] - 1.0 if mirror else 0.0, 0.0, 0.0)
    geo = ImageGeometry(origin, (1.0, 1.0, 1.0), DIMS, direction)
    hm = _box_map((0, 0, 0), np.array(DIMS) - 1.0, 45.0)
    fraction, inverted, vol = _check(hm, geo)
    assert inverted > 100  # the map folds the image
    # ... also in leaves large enough to be proven, were the proof wrong
    big = vol.lattice.leaf_size >= 4
    assert big.sum() > 10
    assert 0.2 < fraction < 1.0


@pytest.mark.parametrize("push", [25.0, 35.0])
def test_no_inverted_cell_is_proven_as_a_fold_starts(push):
    # folds just starting: leaves whose bound fails next to inverted cells, where the
    # octants' own bounds decide (a loose octant bound proves inverted cells here)
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), DIMS)
    fraction, inverted, _ = _check(_box_map((0, 0, 0), np.array(DIMS) - 1.0, push, seed=1), geo)
    assert inverted > 100 and 0.2 < fraction < 1.0


def test_cells_next_to_voxels_outside_the_cage_are_measured():
    # the image reaches beyond the cage: pruned cells, cut leaves and passed-through voxels
    geo = ImageGeometry((-6.0, -6.0, -6.0), (1.0, 1.0, 1.0), (52, 48, 48))
    hm = _box_map((0, 0, 0), (39, 35, 35), 8.0, seed=3)
    fraction, _, vol = _check(hm, geo, outside="passthrough")
    assert vol.lattice.leaf_cut.any()
    assert 0.2 < fraction < 1.0


def test_a_smooth_map_is_mostly_proven():
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.25), (72, 64, 56))
    hm = _box_map((0, 0, 0), (71, 63, 68.75), 4.0, seed=4)
    fraction, inverted, _ = _check(hm, geo)
    assert inverted == 0 and fraction > 0.6


def test_boxes_of_a_window_are_its_cells_of_the_whole_grids():
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), DIMS)
    hm = _box_map((0, 0, 0), (39, 35, 35), 45.0)
    vol = VolumeDeformation(hm, geo, pre_images=False)
    cells = np.array(DIMS) - 1
    whole = _cover(vol.unproven_cells(), cells).reshape(cells[::-1])
    box = (3, 30, 5, 20, 2, 33)  # voxels: cells 3..29, 5..19, 2..32
    part = _cover(vol.unproven_cells(box), [27, 15, 31]).reshape(31, 15, 27)
    np.testing.assert_array_equal(part, whole[2:33, 5:20, 3:30])
    assert len(vol.unproven_cells((4, 4, 0, 35, 0, 35))) == 0  # one plane: no cells
