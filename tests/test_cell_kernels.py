"""Compiled per-cell measures against numpy's SVD, determinants and brute force."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from conftest import trilinear_corner_dets

from vhm_viz.core.cell_kernels import (
    hexahedron_corner_determinants,
    inverted_hexahedra,
    kuhn_corners,
    lattice_tetrahedron_measures,
    singular_values_3x3,
    tetrahedron_measures,
)


def _near_flat(rng, n, thickness):
    """Matrices with one direction squashed to ``thickness``, randomly rotated."""
    q1 = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    q2 = np.linalg.qr(rng.normal(size=(n, 3, 3)))[0]
    s = np.column_stack([1 + rng.random(n), 0.5 + rng.random(n), np.full(n, thickness)])
    return q1 @ (s[:, :, None] * q2)


@pytest.mark.parametrize("kind", ["random", "near-flat", "inverted", "rank-deficient"])
def test_singular_values_match_numpy(kind):
    rng = np.random.default_rng(5)
    if kind == "random":
        m = rng.normal(size=(2000, 3, 3))
    elif kind == "near-flat":
        m = _near_flat(rng, 2000, 1e-6)
    elif kind == "inverted":
        m = rng.normal(size=(2000, 3, 3))
        m[np.linalg.det(m) > 0, :, 0] *= -1
    else:
        m = rng.normal(size=(500, 3, 3))
        m[:, :, 2] = m[:, :, 0] + 2 * m[:, :, 1]
    s = singular_values_3x3(m)
    ref = np.linalg.svd(m, compute_uv=False)
    # both are accurate relative to the largest singular value (backward stable)
    assert np.all(np.abs(s - ref) <= 1e-12 * ref[:, :1])
    if kind == "random":
        np.testing.assert_allclose(s, ref, rtol=1e-12)


@pytest.mark.parametrize("scale", [1e-200, 1e-150, 1e150, 1e200])
def test_singular_values_and_condition_numbers_hold_at_any_scale(scale):
    # squares of the entries over- or underflow at these scales: the matrices are scaled
    # by a power of two while they are worked on
    rng = np.random.default_rng(8)
    a = rng.normal(size=(500, 3, 3))
    ref = np.linalg.svd(a, compute_uv=False)
    s = singular_values_3x3(a * scale)
    assert np.all(np.abs(s / scale - ref) <= 1e-12 * ref[:, :1])
    x = np.tile(np.vstack([np.zeros(3), np.eye(3)]), (len(a), 1))
    y = np.einsum("tij,tkj->tki", a * scale, x.reshape(-1, 4, 3)).reshape(-1, 3)
    cond = tetrahedron_measures(x, y, np.arange(len(x)).reshape(-1, 4))["condition_number"]
    want = ref[:, 0] / ref[:, 2]
    assert np.all(np.abs(cond - want) <= 1e-12 * want + 1e-13 * want**2)


def test_singular_values_of_nan_matrices_are_nan():
    m = np.eye(3)[None].repeat(2, axis=0)
    m[1, 0, 1] = np.nan
    s = singular_values_3x3(m)
    np.testing.assert_array_equal(s[0], [1, 1, 1])
    assert np.isnan(s[1]).all()


def _numpy_measures(x, y, tets):
    """Per tet det F and cond F straight from numpy (solve, det, svd)."""
    dr = np.stack([x[tets[:, i]] - x[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    dd = np.stack([y[tets[:, i]] - y[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    f = np.swapaxes(np.linalg.solve(np.swapaxes(dr, 1, 2), np.swapaxes(dd, 1, 2)), 1, 2)
    s = np.linalg.svd(f, compute_uv=False)
    with np.errstate(divide="ignore"):
        return np.linalg.det(f), s[:, 0] / s[:, 2]


def test_tetrahedra_match_numpy_on_random_flat_and_inverted_tets():
    rng = np.random.default_rng(9)
    n = 3000
    x = rng.normal(size=(4 * n, 3))
    tets = np.arange(4 * n).reshape(n, 4)
    # a mix: random affine images, nearly flattened ones and inverted ones
    a = rng.normal(size=(n, 3, 3))
    a[n // 3 : 2 * n // 3] = _near_flat(rng, 2 * n // 3 - n // 3, 1e-5)
    y = np.einsum("tij,tkj->tki", a, x.reshape(n, 4, 3)).reshape(-1, 3)
    m = tetrahedron_measures(x, y, tets)
    det, cond = _numpy_measures(x, y, tets)
    # both are accurate relative to |F|^3 (det) and to cond F times rounding (cond)
    scale = np.linalg.svd(a, compute_uv=False)[:, 0] ** 3
    assert np.all(np.abs(m["determinant"] - det) <= 1e-12 * scale)
    assert np.all(np.abs(m["condition_number"] - cond) <= 1e-13 * cond**2)
    # det F of a tet is the determinant of the affine map that made it
    assert np.all(np.abs(m["determinant"] - np.linalg.det(a)) <= 1e-12 * scale)
    assert (m["determinant"] < 0).sum() == (np.linalg.det(a) < 0).sum() > 0
    well = np.abs(np.linalg.det(a)) > 0.1
    np.testing.assert_allclose(m["condition_number"][well], cond[well], rtol=1e-12)


def _with_singular_values(rng, s):
    """Random rotations around the diagonal of singular values ``s`` (N, 3)."""
    q1 = np.linalg.qr(rng.normal(size=(len(s), 3, 3)))[0]
    q2 = np.linalg.qr(rng.normal(size=(len(s), 3, 3)))[0]
    return q1 @ (s[:, :, None] * q2)


@pytest.mark.parametrize("gap", [1e-1, 1e-4, 1e-8, 1e-12, 0.0])
def test_condition_numbers_where_singular_values_meet_match_numpy(gap):
    # where two or three singular values (nearly) meet, a closed form of the eigenvalues of
    # F^T F loses digits: the cells' condition numbers must not
    rng = np.random.default_rng(int(gap * 1e12) % 997)
    n = 4000
    one = np.ones(n)
    s = np.concatenate([
        np.column_stack([2 * one, 2 * (1 - gap) * one, 1 + rng.random(n)]),  # top pair
        np.column_stack([3 * one, (1 + gap) * one, one]),  # bottom pair
        1 + gap * rng.normal(size=(n, 3)),  # all three: a scaled rotation, nearly
        -(1 + gap * rng.normal(size=(n, 3))),  # the same, mirrored
        np.column_stack([one, 0.5 + rng.random(n), 10 ** rng.uniform(-8, -1, n)]),  # flat
    ])  # fmt: skip
    a = _with_singular_values(rng, s)
    m = len(a)
    # the unit corner tet, so F is a itself, to the bit
    x = np.tile(np.vstack([np.zeros(3), np.eye(3)]), (m, 1))
    y = np.einsum("tij,tkj->tki", a, x.reshape(m, 4, 3)).reshape(-1, 3)
    cond = tetrahedron_measures(x, y, np.arange(4 * m).reshape(m, 4))["condition_number"]
    sv = np.linalg.svd(a, compute_uv=False)
    ref = sv[:, 0] / sv[:, 2]
    # numpy's s_min is accurate to rounding of s_max: its cond to eps times cond squared
    assert np.all(np.abs(cond - ref) <= 1e-12 * ref + 1e-15 * ref**2)
    np.testing.assert_allclose(cond[: 4 * n], ref[: 4 * n], rtol=1e-12)


def test_cells_take_the_worst_tet_and_flag_rest_problems():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 2, 2]], float)
    y = x.copy()
    y[4] = [0.1, 0.1, 0.1]  # tet 1 (0, 1, 2, 4) comes back inverted? its rest is (1,1,1)
    tets = np.array(
        [
            [0, 1, 2, 3],  # cell 0: identity
            [0, 1, 2, 4],  # cell 0: squashed, still positive
            [0, 2, 1, 3],  # cell 1: stored inverted at rest
            [0, 4, 5, 1],  # cell 2: degenerate at rest (0, 4, 5 collinear)
            [0, 1, 2, 3],  # cell 3: a NaN corner below
        ]
    )
    y_nan = y.copy()
    m = tetrahedron_measures(x, y_nan, tets[:4], owner=[0, 0, 1, 2], n_cells=4)
    assert m["determinant"][0] == pytest.approx(0.1)
    assert m["determinant"][1] == pytest.approx(1.0)
    assert np.isnan(m["determinant"][2]) and np.isnan(m["determinant"][3])
    np.testing.assert_array_equal(m["rest_inverted"], [False, True, False, False])
    np.testing.assert_array_equal(m["degenerate"], [False, False, True, False])
    y_nan[3] = np.nan
    m = tetrahedron_measures(x, y_nan, tets[4:])
    assert np.isnan(m["determinant"][0]) and not m["degenerate"][0]
    m = tetrahedron_measures(x, y, tets[:1], condition=False)
    assert m["determinant"][0] == 1.0 and np.isnan(m["condition_number"][0])


@pytest.mark.parametrize("condition", [True, False])
def test_a_cell_per_tet_gives_the_per_cell_reduction_s_numbers(condition):
    # one tet per cell skips the reduction over cells: the same arrays, bit for bit, for
    # measured, inverted, flattened, degenerate, rest-inverted and not finite tets
    rng = np.random.default_rng(21)
    n = 500
    x = rng.normal(size=(4 * n, 3))
    tets = np.arange(4 * n).reshape(n, 4)
    a = rng.normal(size=(n, 3, 3))
    a[::7] = _near_flat(rng, len(a[::7]), 0.0)  # flattened exactly
    y = np.einsum("tij,tkj->tki", a, x.reshape(n, 4, 3)).reshape(-1, 3)
    x[4 * 11 + 3] = x[4 * 11]  # a degenerate rest tet
    tets[13] = tets[13, [0, 2, 1, 3]]  # stored inverted at rest
    y[4 * 17 + 1] = np.nan  # a corner not mapped
    y[4 * 19 + 2, 0] = np.inf
    alone = tetrahedron_measures(x, y, tets, condition=condition)
    reduced = tetrahedron_measures(x, y, tets, owner=np.arange(n), n_cells=n, condition=condition)
    for key in ("determinant", "condition_number", "rest_inverted", "degenerate"):
        np.testing.assert_array_equal(alone[key], reduced[key])
    assert alone["degenerate"][11] and alone["rest_inverted"][13]
    assert np.isnan(alone["determinant"][[11, 17, 19]]).all()
    assert (alone["determinant"] <= 0).sum() > n // 7
    with pytest.raises(ValueError, match="n_cells"):  # a tet's cell beyond the arrays
        tetrahedron_measures(x, y, tets, n_cells=n - 1, condition=condition)


def _brute_kuhn_tets(dims):
    """Kuhn's six tets of every lattice cell, one monotone corner path per axis order."""
    nx, ny, nz = dims
    tets, owner = [], []
    for k, j, i in itertools.product(range(nz - 1), range(ny - 1), range(nx - 1)):
        for order in itertools.permutations(range(3)):
            corner, path = [i, j, k], [i + nx * (j + ny * k)]
            for axis in order:
                corner[axis] += 1
                path.append(corner[0] + nx * (corner[1] + ny * corner[2]))
            inversions = sum(a > b for a, b in itertools.combinations(order, 2))
            if inversions % 2:  # an odd path: its middle corners swapped
                path[1], path[2] = path[2], path[1]
            tets.append(path)
            owner.append(i + (nx - 1) * (j + (ny - 1) * k))
    return np.array(tets), np.array(owner)


def _lattice_points(dims, frame):
    nx, ny, nz = dims
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return np.column_stack([i.ravel(), j.ravel(), k.ravel()]).astype(float) @ frame.T


def test_kuhn_tets_of_a_voxel_are_positive_and_fill_it():
    tets, _ = _brute_kuhn_tets((2, 2, 2))
    corners = kuhn_corners()
    ids = corners[..., 0] + 2 * (corners[..., 1] + 2 * corners[..., 2])
    np.testing.assert_array_equal(ids, tets)
    x = _lattice_points((2, 2, 2), np.eye(3))
    vol = [np.linalg.det((x[t[1:]] - x[t[0]]).T) / 6 for t in tets]
    np.testing.assert_allclose(vol, 1 / 6, rtol=1e-15)  # six positive tets of volume 1/6


@pytest.mark.parametrize("condition", [True, False])
def test_lattice_cells_match_numpy_on_their_kuhn_tets(condition):
    # a skewed, mirrored lattice (an LPS image's frame can flip) with jittered points, moved
    # by a random affine map plus noise: some cells fold, one corner is not mapped and one
    # cell is flat at rest
    rng = np.random.default_rng(33)
    dims = (6, 5, 4)
    frame = np.diag([0.7, -1.1, 2.0]) + 0.2 * rng.normal(size=(3, 3))
    x = _lattice_points(dims, frame) + 0.05 * rng.normal(size=(np.prod(dims), 3))
    y = x @ rng.normal(size=(3, 3)).T + 0.3 * rng.normal(size=x.shape)
    y[37] = np.nan
    x[[0, 1, 6, 7]] = x[0] + [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]  # cell 0 is flat
    x[[30, 31, 36, 37]] = x[30]
    m = lattice_tetrahedron_measures(x, y, dims, condition=condition)
    tets, owner = _brute_kuhn_tets(dims)
    n = (dims[0] - 1) * (dims[1] - 1) * (dims[2] - 1)
    # the general kernel on the same tets: the same numbers, bit for bit
    general = tetrahedron_measures(x, y, tets, owner, n, condition=condition)
    for key in general:
        np.testing.assert_array_equal(m[key], general[key])
    # numpy, tet by tet: the smallest det and the largest cond of each cell's measured tets
    rest = np.stack([x[tets[:, q]] - x[tets[:, 0]] for q in (1, 2, 3)], axis=2)
    mapped = np.isfinite(y[tets]).all(axis=(1, 2))
    flat = np.abs(np.linalg.det(rest)) <= 1e-12 * np.linalg.norm(rest, axis=1).max(1) ** 3
    measured = mapped & ~flat
    det, cond = _numpy_measures(x, y, tets[measured])
    ref_det = np.full(n, np.inf)
    ref_cond = np.full(n, -np.inf)
    np.minimum.at(ref_det, owner[measured], det)
    np.maximum.at(ref_cond, owner[measured], cond)
    has = np.bincount(owner[measured], minlength=n) > 0
    assert not has[0] and has.sum() > n - 5
    scale = np.abs(y[np.isfinite(y)]).max() ** 3 / np.abs(np.linalg.det(frame))
    assert np.all(np.abs(m["determinant"][has] - ref_det[has]) <= 1e-12 * scale)
    assert np.isnan(m["determinant"][~has]).all()
    assert 0 < (m["determinant"] <= 0).sum() < has.sum()
    if condition:
        np.testing.assert_allclose(m["condition_number"][has], ref_cond[has], rtol=1e-10)
    else:
        assert np.isnan(m["condition_number"]).all()
    np.testing.assert_array_equal(m["degenerate"], np.bincount(owner[flat], minlength=n) > 0)
    # stored inverted at rest (the mirrored frame), compared where no tet is flat (whose
    # sign is rounding's)
    sound = ~m["degenerate"]
    mirrored = np.bincount(owner[(np.linalg.det(rest) < 0) & ~flat], minlength=n) > 0
    np.testing.assert_array_equal(m["rest_inverted"][sound], mirrored[sound])
    assert 0 < (~sound).sum() < 10 and mirrored[sound].sum() > n - 10
    with pytest.raises(ValueError, match="needs 120 rest and deformed points"):
        lattice_tetrahedron_measures(x[:-1], y[:-1], dims)


def test_hexahedra_of_an_affine_map_have_its_determinant():
    dims = (5, 4, 3)
    spacing = np.array([0.5, 0.7, 1.1])
    k, j, i = np.meshgrid(*(np.arange(n) for n in dims[::-1]), indexing="ij")
    rest = np.stack([i, j, k], axis=-1).reshape(-1, 3) * spacing
    a = np.array([[1.2, 0.3, 0.0], [-0.2, 0.9, 0.1], [0.05, 0.0, 1.4]])
    out = hexahedron_corner_determinants(rest @ a.T + 3.0, dims, float(np.prod(spacing)))
    assert out.shape == (4 * 3 * 2,)
    np.testing.assert_allclose(out, np.linalg.det(a), rtol=1e-12)


def test_hexahedra_match_brute_force_and_find_inverted_cells():
    rng = np.random.default_rng(2)
    dims = (6, 5, 7)
    k, j, i = np.meshgrid(*(np.arange(n) for n in dims[::-1]), indexing="ij")
    p = np.stack([i, j, k], axis=-1).astype(float)
    p += 0.15 * rng.normal(size=p.shape)
    p[3, 2, 2] += [2.0, 0.0, 0.0]  # pushed through its neighbours: folds cells around it
    p[5, 4, 5] = np.nan
    out = hexahedron_corner_determinants(p.reshape(-1, 3), dims, 2.0)
    ref = trilinear_corner_dets(p) / 2.0
    np.testing.assert_allclose(out, ref, rtol=1e-12)
    assert np.isnan(out).sum() == np.isnan(ref).sum() > 0
    assert (out[np.isfinite(out)] >= 0).any() and (out[np.isfinite(out)] < 0).any()
    with pytest.raises(ValueError, match="rest_det"):
        hexahedron_corner_determinants(p.reshape(-1, 3), dims, 0.0)


def test_a_mirrored_image_is_not_inverted_by_its_mirror_frame():
    # a left-handed image (negative rest determinant) deformed by the same displacement
    # as its right-handed twin, mirrored: the same volume ratios, the same folds
    rng = np.random.default_rng(4)
    dims = (7, 6, 5)
    k, j, i = np.meshgrid(*(np.arange(n) for n in dims[::-1]), indexing="ij")
    p = np.stack([i, j, k], axis=-1).astype(float) + 0.3 * rng.normal(size=(*dims[::-1], 3))
    ref = trilinear_corner_dets(p) / 1.5
    assert (ref <= 0).any() and (ref > 0).any()
    mirrored = p * [-1.0, 1.0, 1.0]
    out = hexahedron_corner_determinants(mirrored.reshape(-1, 3), dims, -1.5)
    np.testing.assert_allclose(out, ref, rtol=1e-12)
    found = inverted_hexahedra(mirrored.reshape(-1, 3), dims, -1.5)
    np.testing.assert_array_equal(found["inverted"], np.flatnonzero(ref <= 0))


@pytest.mark.parametrize("rest_det", [0.7, -0.7])
def test_inverted_hexahedra_are_those_of_the_per_cell_kernel(rest_det):
    # thousands of inverted cells (more than a chunk's first room), NaN points, and
    # near-degenerate cells: a layer squashed flat to rounding, a cell's corner on 0
    rng = np.random.default_rng(8)
    dims = (31, 23, 17)
    k, j, i = np.meshgrid(*(np.arange(n) for n in dims[::-1]), indexing="ij")
    p = np.stack([i, j, k], axis=-1).astype(float)
    p += 0.45 * rng.normal(size=p.shape)
    p[9, :, :, 2] = p[8, :, :, 2] + 1e-15 * rng.normal(size=p.shape[1:3])
    p[12, 3, 4] = p[12, 3, 3]  # an edge of length 0: corner determinants exactly 0
    p[2, 7, 30] = [np.nan, 0.0, 0.0]  # on the grid's i = nx - 1 face: in 4 cells
    p[14, 20, 5, 1] = np.inf  # inside: in 8 cells
    pts = p.reshape(-1, 3)
    every = hexahedron_corner_determinants(pts, dims, rest_det)
    found = inverted_hexahedra(pts, dims, rest_det)
    bad = np.flatnonzero(every <= 0)
    assert bad.size > 4096
    np.testing.assert_array_equal(found["inverted"], bad)
    np.testing.assert_array_equal(found["determinant"], every[bad])
    assert found["cells"] == np.isfinite(every).sum() == every.size - 4 - 8
    # and both are the brute force's (numpy's determinants, their own rounding)
    ref = trilinear_corner_dets(p * [np.sign(rest_det), 1.0, 1.0]) / abs(rest_det)
    clear = np.abs(ref) > 1e-9
    np.testing.assert_array_equal((every <= 0)[clear], (ref <= 0)[clear])
    np.testing.assert_allclose(every[clear], ref[clear], rtol=1e-9)


def test_inverted_hexahedra_of_boxes_are_those_cells_of_the_whole_grid():
    # boxes of every shape (blocks, layers, rows, single cells) over a folded grid with
    # points that are not finite: their cells alone, with the whole kernel's numbers
    rng = np.random.default_rng(11)
    dims = (29, 21, 15)
    k, j, i = np.meshgrid(*(np.arange(n) for n in dims[::-1]), indexing="ij")
    p = np.stack([i, j, k], axis=-1).astype(float) + 0.45 * rng.normal(size=(*dims[::-1], 3))
    p[4, 6, 7] = np.nan
    pts = p.reshape(-1, 3)
    every = hexahedron_corner_determinants(pts, dims, -0.9)
    boxes = np.array(
        [
            [0, 27, 0, 19, 0, 0],  # the first layer of cells
            [3, 10, 2, 9, 1, 8],  # a block (holding the NaN point's cells)
            [27, 27, 0, 19, 1, 13],  # the last column of cells
            [12, 20, 15, 15, 5, 5],  # a row
            [14, 14, 3, 3, 9, 9],  # a cell
        ]
    )
    chosen = np.zeros((dims[2] - 1, dims[1] - 1, dims[0] - 1), dtype=bool)
    for i0, i1, j0, j1, k0, k1 in boxes:
        chosen[k0 : k1 + 1, j0 : j1 + 1, i0 : i1 + 1] = True
    chosen = chosen.reshape(-1)
    found = inverted_hexahedra(pts, dims, -0.9, boxes)
    bad = np.flatnonzero(chosen & (every <= 0))
    assert bad.size > 100
    np.testing.assert_array_equal(found["inverted"], bad)
    np.testing.assert_array_equal(found["determinant"], every[bad])
    assert found["cells"] == np.isfinite(every[chosen]).sum() < chosen.sum()
    # one box of the whole grid: thousands of inverted cells in one chunk, more than its
    # first room
    whole = inverted_hexahedra(pts, dims, -0.9, [[0, 27, 0, 19, 0, 13]])
    bad = np.flatnonzero(every <= 0)
    assert bad.size > 2048
    np.testing.assert_array_equal(whole["inverted"], bad)
    np.testing.assert_array_equal(whole["determinant"], every[bad])
    empty = inverted_hexahedra(pts, dims, -0.9, np.zeros((0, 6), np.int64))
    assert empty["cells"] == 0 and empty["inverted"].size == 0
    for wrong in ([0, 28, 0, 0, 0, 0], [5, 4, 0, 0, 0, 0], [0, 0, -1, 0, 0, 0]):
        with pytest.raises(ValueError, match="cell ranges"):
            inverted_hexahedra(pts, dims, -0.9, [wrong])
