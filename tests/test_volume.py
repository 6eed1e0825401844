"""Volumes: the lattice engine against independent references, and volume files.

References: scipy.ndimage.affine_transform (affine maps), the exact closed-form map and
scipy's root finder on it (random bends), the exact winding number (inside tests),
SimpleITK (MetaImage/NIfTI geometry, when installed).
"""

from __future__ import annotations

import gc
import itertools
import json
import threading
import tracemalloc
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from conftest import affine_resampled, box_cage, data_path, extent_box  # noqa: E402
from scipy.ndimage import binary_erosion  # noqa: E402
from scipy.optimize import root as find_root  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from vtkmodules.vtkIOXML import vtkXMLImageDataReader  # noqa: E402

import vhm_viz.core.lattice as lattice_package  # noqa: E402
from vhm_viz import Cage, HarmonicMap, read_cage  # noqa: E402
from vhm_viz.cli import main  # noqa: E402
from vhm_viz.core.basis import inside_cage, winding_number  # noqa: E402
from vhm_viz.core.errors import AbortedError, OutsideCageError  # noqa: E402
from vhm_viz.core.geometry import nearest_points_on_mesh  # noqa: E402
from vhm_viz.core.image import ImageGeometry, inside_mask, surface_mask  # noqa: E402
from vhm_viz.core.lattice import PART_FIELDS, build_lattice, join_parts, nodes  # noqa: E402
from vhm_viz.core.lattice.nodes import NodeTable  # noqa: E402
from vhm_viz.core.lattice.pullback import SUBCELLS, inside_around, subcell_tests  # noqa: E402
from vhm_viz.core.memory import take_in_place  # noqa: E402
from vhm_viz.core.metrics import jacobian_measures  # noqa: E402
from vhm_viz.core.volume import (  # noqa: E402
    DEFAULT_TOLERANCE,
    Resampled,
    VolumeDeformation,
    check_tolerance,
    equal_cuts,
    exact_preimages,
    fast_jacobian_measures,
    lattice_build_work,
    layer_shares,
    output_grid,
    pull_back_shares,
    window_of,
)
from vhm_viz.filters import HarmonicDeformationFilter, HarmonicResampleFilter, update  # noqa: E402
from vhm_viz.io import read_dataset, write_dataset  # noqa: E402


def _cage_around(lo, hi, margin, divisions=2):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pad = margin * (hi - lo).max()
    return Cage(*box_cage(lo - pad, hi + pad, divisions))


def _random_bend(cage, scale, seed):
    """The identity plus random coefficient noise: a smooth map with cage-edge kinks."""
    rng = np.random.default_rng(seed)
    z = np.array(HarmonicMap.identity(cage).coefficients)
    z += scale * cage.diagonal * rng.standard_normal(z.shape)
    return HarmonicMap(cage, z)


def _voxel_error(geo, delta):
    """Euclidean norm of world displacements in voxels of ``geo``'s spacing."""
    return np.linalg.norm(np.asarray(delta) @ geo.world_to_index.T, axis=1)


# --------------------------------------------------------------------------- inside mask


def test_scan_line_mask_equals_winding_number_on_a_rotated_mirrored_grid():

    cage = read_cage(data_path("armadillo", "cage_216f.obj"))
    lo, hi = cage.vertices.min(0), cage.vertices.max(0)
    rot = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix() @ np.diag([1.0, -1.0, 1.0])
    sp = (hi - lo).max() / np.array([40.0, 47.0, 43.0])
    geo = ImageGeometry((lo + hi) / 2 - rot @ (sp * 22), sp, (44, 45, 41), rot)
    mask = inside_mask(geo, cage.vertices, cage.faces).ravel()
    wn = winding_number(geo.points(), cage.vertices, cage.faces)
    clear = np.abs(wn - 0.5) > 0.25  # not within rounding of the surface
    assert 0.1 < mask.mean() < 0.9
    np.testing.assert_array_equal(mask[clear], inside_cage(wn[clear]))


# ------------------------------------------------------------------------- affine maps


def _smooth_volume(dims, spacing, origin):
    img = pv.ImageData(dimensions=dims, spacing=spacing, origin=origin)
    p = np.asarray(img.points)
    img.point_data["density"] = np.sin(0.21 * p[:, 0]) * np.cos(0.17 * p[:, 1]) + 0.05 * p[:, 2]
    return img


def test_affine_map_reproduces_scipy_affine_transform():
    """Warp and resample of an affine map agree with scipy.ndimage to rounding."""
    img = _smooth_volume((48, 44, 40), (1.0, 1.1, 1.2), (-24.0, -24.0, -24.0))
    geo = ImageGeometry(img.origin, img.spacing, img.dimensions)
    lo, hi = np.asarray(img.bounds[0::2]), np.asarray(img.bounds[1::2])
    cage = _cage_around(lo, hi, 0.3, divisions=1)
    A = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix() @ np.diag([1.1, 0.95, 1.0])
    T = np.array([1.5, -2.0, 0.5])
    vol = VolumeDeformation(HarmonicMap.affine(cage, A, T), geo)
    assert vol.root > 1  # the lattice, not voxel by voxel
    pts = vol.warp()
    np.testing.assert_allclose(pts, geo.points() @ A.T + T, rtol=0, atol=1e-9)
    # an affine map is interpolated exactly: cells split only where the lattice always
    # splits them, within a voxel of a cage edge (the cage is 17 voxels out, the root
    # cells overhang the volume by up to 16)
    lat = vol.lattice
    small = np.asarray(lat.leaf_size) < vol.root
    centre = np.asarray(lat.leaf_origin)[small] + np.asarray(lat.leaf_size)[small, None] / 2.0
    e, v = cage.edges, geo.continuous_index(cage.vertices)
    a, d = v[e[:, 0]], v[e[:, 1]] - v[e[:, 0]]
    s = np.clip(np.einsum("cei,ei->ce", centre[:, None] - a, d) / (d * d).sum(1), 0.0, 1.0)
    gap = np.linalg.norm(centre[:, None] - (a + s[..., None] * d), axis=2).min(axis=1)
    # (a leaf's parent, twice its size, came within a voxel of an edge)
    assert np.all(gap <= 1.0 + np.sqrt(3) / 2 * 3 * np.asarray(lat.leaf_size)[small] + 1e-9)
    assert small.mean() < 0.5
    res = vol.resample({"density": np.asarray(img.point_data["density"])}, geometry=geo)
    ref, clearly_in, clearly_out = affine_resampled(img, "density", A, T)
    assert clearly_in.mean() > 0.5 and clearly_out.any()
    assert res.valid[clearly_in].all() and not res.valid[clearly_out].any()
    got = res.arrays["density"]
    np.testing.assert_allclose(got[clearly_in], ref[clearly_in], rtol=0, atol=1e-10)
    assert res.counts["foldover"] == 0


# ----------------------------------------------------------------------- random bends


@pytest.fixture(scope="module")
def bend():
    """A 72 x 64 x 56 volume in a 2-division box cage, randomly bent by up to ~14 voxels."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.25), (72, 64, 56))
    lo, hi = geo.origin, geo.points(np.array([geo.dimensions]) - 1.0)[0]
    cage = _cage_around(lo, hi, 0.02)
    hm = _random_bend(cage, 0.004, seed=4)
    vol = VolumeDeformation(hm, geo, tolerance=0.05)
    vol.build()
    return geo, cage, hm, vol


def _near_cage_voxels(geo, cage, count, rng):
    """Voxels within two voxels of the cage (the hard ones), by the scan-line mask."""

    nx, ny, nz = geo.dimensions
    inside = inside_mask(geo, cage.vertices, cage.faces)
    band = inside & ~binary_erosion(inside, iterations=2, border_value=0)
    ijk = np.argwhere(band)[:, ::-1]
    return ijk[rng.choice(len(ijk), min(count, len(ijk)), replace=False)]


def test_tolerance_has_one_default_and_is_refused_unless_positive_and_at_most_a_root_cell():
    """The volume tolerance's one default; the engine and the lattice builder refuse a
    tolerance that is not a positive number of voxels up to a root cell, before any work."""
    assert lattice_package.DEFAULT_TOLERANCE is DEFAULT_TOLERANCE
    assert lattice_package.MAX_TOLERANCE == lattice_package.DEFAULT_ROOT == 16
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (6, 6, 6))
    hm = HarmonicMap.identity(_cage_around((0, 0, 0), (5, 5, 5), 0.1, divisions=1))
    assert VolumeDeformation(hm, geo).tolerance == DEFAULT_TOLERANCE
    assert VolumeDeformation(hm, geo, tolerance=1).tolerance == 1.0
    assert VolumeDeformation(hm, geo, tolerance=16).tolerance == 16.0
    for bad in (0.0, -0.05, float("nan"), float("inf"), 16.001, 1000):
        with pytest.raises(ValueError, match="positive number of voxels"):
            VolumeDeformation(hm, geo, tolerance=bad)
        with pytest.raises(ValueError, match="positive number of voxels"):
            build_lattice(hm, geo, tolerance=bad)
        with pytest.raises(ValueError, match="positive number of voxels"):
            check_tolerance(bad)


def test_warp_matches_exact_map_within_tolerance(bend):
    geo, cage, hm, vol = bend
    rng = np.random.default_rng(0)
    pts = vol.warp()
    nx, ny, _ = geo.dimensions
    everywhere = rng.choice(geo.n_points, 4000, replace=False)
    ijk = np.column_stack([everywhere % nx, (everywhere // nx) % ny, everywhere // (nx * ny)])
    ijk = np.vstack([ijk, _near_cage_voxels(geo, cage, 3000, rng)])
    flat = ijk[:, 0] + nx * (ijk[:, 1] + ny * ijk[:, 2])
    exact = hm.map(geo.points(ijk))
    err = _voxel_error(geo, pts[flat] - exact)
    assert err.max() <= vol.tolerance
    # a real deformation, refined near the cage
    assert _voxel_error(geo, exact - geo.points(ijk)).max() > 2.0
    assert min(vol.lattice.stats["leaves_per_size"]) < vol.root


def _turned_box():
    """A 64x64x52 grid and a box cage turned so that its edges cross the voxel rows
    obliquely."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.25), (64, 64, 52))
    c = geo.points(np.array([geo.dimensions]) / 2.0 - 0.5)[0]
    cage = Cage(*box_cage(c - 20.0, c + 20.0, 2))
    a1, a2 = np.radians(27.0), np.radians(-19.0)  # turned about z, then x
    rz = np.array([[np.cos(a1), -np.sin(a1), 0], [np.sin(a1), np.cos(a1), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(a2), -np.sin(a2)], [0, np.sin(a2), np.cos(a2)]])
    return geo, Cage((cage.vertices - c) @ (rx @ rz).T + c, cage.faces)


def _edge_distance(geo, cage, u):
    """Brute force: distance (voxel index units) from each point to the nearest cage edge."""
    e, v = cage.edges, geo.continuous_index(cage.vertices)
    dist = np.full(len(u), np.inf)
    for p, q in zip(v[e[:, 0]], v[e[:, 1]], strict=True):
        d = q - p
        s = np.clip((u - p) @ d / (d @ d), 0.0, 1.0)
        dist = np.minimum(dist, np.linalg.norm(u - (p + s[:, None] * d), axis=1))
    return dist


def test_every_voxel_next_to_a_cage_edge_is_within_tolerance():
    """All inside voxels within two voxels of a cage edge (brute force), for a cage whose
    edges cross the voxel rows obliquely: next to an edge the map has a logarithmic
    singularity that a large cell's test points can miss: the cells there split down to
    single voxels)."""
    geo, cage = _turned_box()
    worst = 0.0
    for seed in range(3):
        hm = _random_bend(cage, 0.01, seed=seed)
        vol = VolumeDeformation(hm, geo, tolerance=0.05, outside="passthrough")
        nx, ny, _ = geo.dimensions
        ijk = np.argwhere(inside_mask(geo, cage.vertices, cage.faces))[:, ::-1].astype(float)
        near = _edge_distance(geo, cage, ijk) <= 2.0
        ijk = ijk[near].astype(np.int64)
        assert len(ijk) > 5000
        flat = ijk[:, 0] + nx * (ijk[:, 1] + ny * ijk[:, 2])
        err = _voxel_error(geo, vol.warp()[flat] - hm.map(geo.points(ijk)))
        worst = max(worst, float(err.max()))
    assert worst <= 0.05, worst


def test_lattice_finds_the_points_next_to_cage_edges():
    """``near_cage_edges`` (edges binned) against the brute-force distance."""
    geo, cage = _turned_box()
    vol = VolumeDeformation(_random_bend(cage, 0.01, seed=0), geo, outside="passthrough")
    rng = np.random.default_rng(3)
    v = geo.continuous_index(cage.vertices)
    e = cage.edges
    t = rng.uniform(0, 1, (4000, 1))
    k = rng.integers(0, len(e), 4000)
    # points around random edges (up to 1.5 voxels off) and anywhere in the grid
    u = np.vstack([
        v[e[k, 0]] + t * (v[e[k, 1]] - v[e[k, 0]]) + rng.uniform(-1.5, 1.5, (4000, 3)),
        rng.uniform(-5, np.asarray(geo.dimensions) + 5, (4000, 3)),
    ])  # fmt: skip
    dist = _edge_distance(geo, cage, u)
    for radius in (0.5, 1.3):
        got = vol.lattice.near_cage_edges(u, radius)
        clear = np.abs(dist - radius) > 1e-9
        np.testing.assert_array_equal(got[clear], dist[clear] <= radius)
        assert 100 < got.sum() < len(u) - 100


def test_preimages_next_to_a_cage_edge_solve_the_exact_map():
    """Pre-images next to a cage edge come from Newton's method on the exact map: there
    no cubic between voxels follows the map's logarithmic singularity, whose pre-image
    errors there can exceed the tolerance."""
    geo, cage = _turned_box()
    hm = _random_bend(cage, 0.01, seed=1)
    vol = VolumeDeformation(hm, geo, tolerance=0.05, outside="passthrough")
    out = vol.output_geometry()
    rng = np.random.default_rng(4)
    v = geo.continuous_index(cage.vertices)
    e = cage.edges
    k = rng.integers(0, len(e), 8000)
    u = v[e[k, 0]] + rng.uniform(0, 1, (8000, 1)) * (v[e[k, 1]] - v[e[k, 0]])
    u += rng.uniform(-0.6, 0.6, (8000, 3))
    x = geo.points(u)
    x = x[inside_cage(winding_number(x, cage.vertices, cage.faces))]
    voxels = np.unique(np.rint(out.continuous_index(hm.map(x))).astype(np.int64), axis=0)
    got, kind, fold = vol.preimages(out, voxels)
    ok = (kind == 1) & (fold == 0)
    ref, conv = exact_preimages(
        hm, out.points(voxels[ok].astype(float)), geo.points(got[ok]), tolerance=1e-10
    )
    assert conv.mean() > 0.95  # (Newton can step out of the cage next to it)
    ref = geo.continuous_index(ref[conv])
    near = _edge_distance(geo, cage, ref) < 0.45
    assert near.sum() > 100
    err = np.linalg.norm(got[ok][conv][near] - ref[near], axis=1)
    assert err.max() < 1e-3, err.max()


def test_resample_preimages_match_exact_inverse(bend):
    """Pre-images of output voxels over the deformed volume (and of voxels whose pre-image
    is next to the cage) are within the tolerance of scipy's root of the exact map.

    A position error ``e`` moves a pre-image by up to ``e / s_min`` (``s_min``: smallest
    singular value of the Jacobian in voxel units), so the bound is the tolerance divided
    by ``min(1, s_min)``: this bend folds space in places, where no inverse is accurate.
    """

    geo, cage, hm, vol = bend
    out = vol.output_geometry()
    rng = np.random.default_rng(1)
    near = geo.points(_near_cage_voxels(geo, cage, 150, rng).astype(float))
    near_out = np.rint(out.continuous_index(hm.map(near))).astype(np.int64)
    # output voxels over the deformed volume: near images of random input voxels
    x = geo.points(rng.uniform(0, np.asarray(geo.dimensions) - 1, (600, 3)))
    x = x[inside_cage(winding_number(x, cage.vertices, cage.faces))]
    anywhere = np.rint(out.continuous_index(hm.map(x))).astype(np.int64)
    voxels = np.vstack([near_out, anywhere])
    u, kind, fold = vol.preimages(out, voxels)
    found = np.nonzero(kind == 1)[0]
    assert len(found) > 0.9 * len(voxels)
    assert (kind[: len(near_out)] == 1).mean() > 0.8  # next to the cage too (rounding to a
    # voxel can leave the deformed volume there)
    scaled, plain = [], []
    for p in found:
        y = out.points(voxels[p][None].astype(float))[0]
        sol = find_root(lambda x, y=y: hm.map(x[None])[0] - y, geo.points(u[p][None])[0], tol=1e-12)
        assert np.linalg.norm(hm.map(sol.x[None])[0] - y) < 1e-9  # (success may be False
        # when the start is already the root to rounding)
        err = np.linalg.norm(geo.continuous_index(sol.x[None])[0] - u[p])
        jac = geo.world_to_index @ hm.jacobian(sol.x[None])[0] @ geo.index_to_world
        s_min = np.linalg.svd(jac, compute_uv=False)[-1]
        scaled.append(err * min(1.0, s_min))
        if not fold[p] and s_min > 0.3:
            plain.append(err)
    assert max(scaled) <= vol.tolerance
    assert len(plain) > 0.5 * len(found) and max(plain) <= vol.tolerance


def test_output_grid_contains_every_deformed_voxel(bend):
    geo, cage, hm, vol = bend
    out = vol.output_geometry()
    np.testing.assert_allclose(out.spacing, geo.spacing)
    inside = inside_mask(geo, cage.vertices, cage.faces).ravel()
    deformed = hm.map(geo.points()[inside])
    idx = out.continuous_index(deformed)
    top = np.asarray(out.dimensions) - 1
    assert (idx >= 0).all() and (idx <= top).all()
    # not oversized: each side within two voxels of the deformed voxels' extent
    assert (idx.min(0) < 2).all() and (idx.max(0) > top - 2).all()
    # on the input's voxel lattice: the offset is a whole number of voxels
    shift = geo.continuous_index(out.origin[None])[0]
    np.testing.assert_allclose(shift, np.round(shift), atol=1e-9)


def test_resampled_voxels_hold_the_input_at_their_preimage(bend):
    geo, cage, hm, vol = bend
    rng = np.random.default_rng(2)
    values = rng.standard_normal(geo.n_points).astype(np.float32)
    labels = rng.integers(0, 7, geo.n_points).astype(np.uint16) * 1000
    res = vol.resample({"v": values, "label": labels}, interpolation="nearest")
    assert res.arrays["label"].dtype == np.uint16 and res.arrays["v"].dtype == np.float32
    assert set(np.unique(res.arrays["label"][res.valid == 1])) <= set(np.unique(labels))
    assert (res.arrays["label"][res.valid == 0] == 0).all()
    lin = vol.resample({"label": labels}, interpolation="linear", fill_value=65535)
    assert lin.arrays["label"].dtype == np.uint16  # rounded and clipped back
    assert (lin.arrays["label"][lin.valid == 0] == 65535).all()
    # a fill value the type cannot hold is refused, not clipped or rounded
    for bad in (-5, 65536, 2.5, float("nan")):
        with pytest.raises(ValueError, match=r"not a uint16 value .*'label' \(integers 0 to"):
            vol.resample({"v": values, "label": labels}, fill_value=bad)
    # integer arrays hold the float result rounded and clipped (cubic overshoots 0..250)
    steps = (rng.integers(0, 2, geo.n_points) * 250).astype(np.uint8)
    cub = vol.resample({"b": steps, "f": steps.astype(np.float64)}, interpolation="cubic")
    inside = cub.valid == 1
    ref = np.clip(np.rint(cub.arrays["f"][inside]), 0, 255)
    np.testing.assert_array_equal(cub.arrays["b"][inside], ref)
    assert (cub.arrays["f"][inside] > 255.5).any() and (cub.arrays["f"][inside] < -0.5).any()
    # 64-bit labels beyond float64's integers are copied exactly by "nearest"
    huge = np.int64(2**62) + labels.astype(np.int64) + 1
    near = vol.resample({"h": huge}, interpolation="nearest")
    assert set(np.unique(near.arrays["h"][near.valid == 1])) <= set(np.unique(huge))


def test_two_pieces_equal_one_piece(bend):
    geo, cage, hm, vol = bend
    rng = np.random.default_rng(3)
    values = rng.standard_normal(geo.n_points)
    out = vol.output_geometry()
    whole = vol.resample({"v": values}, out)
    nx, ny, nz = out.dimensions
    half = nz // 2
    parts = [
        vol.resample({"v": values}, out, box=(0, nx - 1, 0, ny - 1, 0, half)),
        vol.resample({"v": values}, out, box=(0, nx - 1, 0, ny - 1, half + 1, nz - 1)),
    ]
    joined = np.concatenate([p.arrays["v"] for p in parts])
    np.testing.assert_allclose(joined, whole.arrays["v"], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.concatenate([p.valid for p in parts]), whole.valid)
    pts = vol.warp()
    box = (5, 40, 3, 60, 10, 30)
    sub = vol.warp(box)
    ref = pts.reshape(geo.dimensions[::-1] + (3,))[10:31, 3:61, 5:41].reshape(-1, 3)
    np.testing.assert_array_equal(sub, ref)


def test_memory_bound_slabs_do_not_grow_with_the_volume():
    """With a small budget the largest slab is the same for a volume 4 times longer."""
    cage_lo, cage_hi = (-1.0, -1.0, -1.0), (33.0, 33.0, 130.0)
    cage = _cage_around(cage_lo, cage_hi, 0.0)
    hm = _random_bend(cage, 0.002, seed=1)
    values = {}
    for nz in (32, 128):
        geo = ImageGeometry((0, 0, 0), (1, 1, 1), (32, 32, nz))
        vol = VolumeDeformation(hm, geo, memory_budget=200_000)
        vol.warp()
        warp_slab = vol.largest_slab
        res = vol.resample({"v": np.zeros(geo.n_points, np.float32)}, geometry=geo)
        assert res.counts["voxels"] == geo.n_points
        values[nz] = (warp_slab, vol.largest_slab, vol.slab_count)
    (w32, r32, n32), (w128, r128, n128) = values[32], values[128]
    assert w32 == w128 and r32 == r128  # the working set per slab is fixed
    assert r32 * 56 <= 200_000 + 32 * 32 * 56  # within the budget (one plane at least)
    assert n128 >= 3 * n32  # more slabs instead


def test_pull_back_slabs_stay_small_whatever_the_budget():
    """A larger budget does not make the pull-back's slabs larger than 64 MiB of arrays."""
    geo = ImageGeometry((0, 0, 0), (1, 1, 1), (128, 128, 80))
    cage = _cage_around((-1.0, -1.0, -1.0), (129.0, 129.0, 81.0), 0.0)
    hm = _random_bend(cage, 0.002, seed=2)
    plane = 128 * 128
    for budget in (None, 2**30):
        vol = VolumeDeformation(hm, geo, memory_budget=budget)
        vol.resample({"v": np.zeros(geo.n_points, np.float32)}, geometry=geo)
        assert vol.slab_count == 2  # 73 planes, then 7
        assert vol.largest_slab * 56 <= 64 * 2**20 < (vol.largest_slab + plane) * 56


def test_outside_voxels_of_a_piece_are_counted_of_the_piece():
    """A piece's warp (an MPI rank's window) refusing voxels outside the cage counts
    them of the piece's voxels, not of the whole volume's: the count is the piece's, as
    the cage's box counts them; the whole volume's warp says the whole count."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (20, 20, 20))
    cage = _cage_around((2.5, 2.5, 2.5), (16.5, 16.5, 16.5), 0.0)  # no voxel on the cage
    hm = _random_bend(cage, 0.01, seed=3)
    p = geo.points().reshape(20, 20, 20, 3)
    outside = ((p < 2.5) | (p > 16.5)).any(axis=-1)
    with pytest.raises(OutsideCageError) as whole:
        VolumeDeformation(hm, geo).warp()
    assert str(whole.value).startswith(f"{outside.sum()} of 8000 voxels are outside the cage")
    box = [0, 19, 0, 19, 10, 19]
    with pytest.raises(OutsideCageError) as piece:
        VolumeDeformation(hm, geo, window=box, pre_images=False).warp(box)
    assert str(piece.value).startswith(
        f"{outside[10:].sum()} of the 4000 voxels of the piece {box} (8000 in all) are "
        "outside the cage"
    ), str(piece.value)


def test_outside_policies_and_abort(bend):
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (40, 40, 40))
    cage = _cage_around((8, 8, 8), (30, 30, 30), 0.0)  # the volume sticks out
    hm = _random_bend(cage, 0.01, seed=3)
    with pytest.raises(OutsideCageError, match="voxels are outside the cage"):
        VolumeDeformation(hm, geo).warp()
    inside = inside_mask(geo, cage.vertices, cage.faces).ravel()
    kept = VolumeDeformation(hm, geo, outside="passthrough")
    pts = kept.warp()
    np.testing.assert_array_equal(pts[~inside], geo.points()[~inside])
    dropped = VolumeDeformation(hm, geo, outside="nan").warp()
    assert np.isnan(dropped[~inside]).all() and np.isfinite(dropped[inside]).all()
    # resampled: outside voxels stay in place (passthrough) or vanish (nan)
    values = {"v": np.ones(geo.n_points)}
    res_kept = kept.resample(values, geometry=geo)
    res_nan = VolumeDeformation(hm, geo, outside="nan").resample(values, geometry=geo)
    assert res_kept.counts["identity"] > 0 and res_nan.counts["identity"] == 0
    assert res_kept.counts["valid"] > res_nan.counts["valid"]
    calls = []

    def abort():
        calls.append(1)
        return len(calls) > 2

    fresh = VolumeDeformation(hm, geo, outside="passthrough", memory_budget=100_000)
    with pytest.raises(AbortedError):
        fresh.warp(abort=abort)


def test_fold_is_flagged():
    """A map that folds space over itself gives voxels with two pre-images."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (40, 36, 36))
    cage = _cage_around((0, 0, 0), (39, 35, 35), 0.05, divisions=3)
    z = np.array(HarmonicMap.identity(cage).coefficients)
    v = np.asarray(cage.vertices)
    # push the cage vertices of the left half far to the right (past the others)
    left = v[:, 0] < 10
    z[: len(v)][left, 0] += 45.0
    vol = VolumeDeformation(HarmonicMap(cage, z), geo)
    res = vol.resample({"v": np.ones(geo.n_points)})
    det = vol.jacobian_measures()["determinant"]
    assert (det <= 0).any()  # the map folds
    assert res.counts["foldover"] > 0
    assert res.foldover.sum() == res.counts["foldover"]


# ----------------------------------------------------------------------- volume files


@pytest.mark.parametrize("suffix", [".mhd", ".mha", ".nii", ".nii.gz", ".vti"])
def test_volume_files_keep_origin_spacing_direction(tmp_path, suffix):
    img = pv.ImageData(dimensions=(5, 6, 7), spacing=(0.5, 0.7, 0.9), origin=(1.0, -2.0, 3.0))
    img.direction_matrix = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    img.point_data["a"] = np.arange(img.n_points, dtype=np.int16)
    path = tmp_path / f"v{suffix}"
    write_dataset(path, img)
    back = read_dataset(path)
    np.testing.assert_allclose(back.origin, img.origin, atol=1e-5)
    np.testing.assert_allclose(back.spacing, img.spacing, atol=1e-6)
    np.testing.assert_allclose(back.direction_matrix, img.direction_matrix, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(back.active_scalars), img.point_data["a"])
    if suffix == ".vti":
        return
    sitk = pytest.importorskip("SimpleITK")  # the geometry as ITK reads it
    s = sitk.ReadImage(str(path))
    np.testing.assert_allclose(s.GetOrigin(), img.origin, atol=1e-5)
    direction = np.reshape(s.GetDirection(), (3, 3))
    np.testing.assert_allclose(direction, img.direction_matrix, atol=1e-6)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(s).ravel(), img.point_data["a"])


# ------------------------------------------------------------------------ command line


def _write_slc(path, vol, spacing):
    """A minimal SLC file (8 bits, uncompressed, 1 x 1 icon), as VTK's reader reads it."""
    nz, ny, nx = vol.shape
    header = f"11111\n{nx} {ny} {nz} 8\n{spacing[0]} {spacing[1]} {spacing[2]}\n0 0 0 0\n1 1 X"
    path.write_bytes(header.encode() + b"\0\0\0" + vol.astype(np.uint8).tobytes())


def _bend_scene(folder, lo, hi):
    """A scene file: box cage around [lo, hi], the far end turned by 20 degrees."""

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pad = 0.08 * (hi - lo)
    v, f = box_cage(lo - pad, hi + pad, divisions=2)
    centre = 0.5 * (lo + hi)
    axis = np.array([0.0, 0.0, 1.0]) * (hi - lo)
    anchors = [centre + t * 0.35 * axis for t in np.linspace(-1, 1, 5)]
    turn = Rotation.from_rotvec([np.radians(20), 0, 0]).as_matrix()
    base, top = centre - 0.35 * axis, centre + 0.35 * axis
    scene = {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": {"vertices": v.tolist(), "faces": f.tolist()},
        "anchors": np.array(anchors).tolist(),
        "constraints": {
            "positions": [base.tolist(), top.tolist()],
            "targets": [base.tolist(), (base + turn @ (top - base)).tolist()],
            "jacobian_points": [base.tolist(), top.tolist()],
            "jacobians": [np.eye(3).tolist(), turn.tolist()],
        },
    }
    path = folder / "scene.json"
    path.write_text(json.dumps(scene))
    return path


@pytest.fixture(scope="module")
def cli_volume(tmp_path_factory):
    folder = tmp_path_factory.mktemp("volcli")
    z, y, x = np.mgrid[0:44, 0:36, 0:34]
    vol = (40 + 100 * (((x // 6) + (y // 6) + (z // 6)) % 2)).astype(np.uint8)
    spacing = (1.0, 1.1, 0.9)
    img = pv.ImageData(dimensions=vol.shape[::-1], spacing=spacing)
    img.point_data["v"] = vol.ravel()
    files = {}
    for suffix in (".vti", ".mhd", ".nii.gz"):
        files[suffix] = folder / f"in{suffix}"
        write_dataset(files[suffix], img)
    files[".slc"] = folder / "in.slc"
    _write_slc(files[".slc"], vol, spacing)
    scene = _bend_scene(folder, img.bounds[0::2], img.bounds[1::2])
    return folder, img, files, scene


def _cli(capsys, *argv):

    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.parametrize("source", [".vti", ".slc", ".mhd", ".nii.gz"])
def test_cli_deforms_every_volume_format(cli_volume, source, tmp_path, capsys):
    folder, img, files, scene = cli_volume
    outputs = {}
    for target in (".vti", ".mhd", ".nii.gz", ".vts"):
        path = tmp_path / f"out{target}"
        rc, out, err = _cli(capsys, "deform", files[source], "-s", scene, "-o", path, "-q")
        assert rc == 0, err
        assert "tolerance 0.05 voxel" in out and str(path) in out
        if target != ".vts":
            assert "voxels with a pre-image" in out and "in folds" in out
        outputs[target] = read_dataset(path)
    grid = outputs[".vti"]
    for target in (".mhd", ".nii.gz"):  # the same grid and voxels in every format
        other = outputs[target]
        np.testing.assert_allclose(other.origin, grid.origin, atol=1e-4)
        np.testing.assert_allclose(other.spacing, grid.spacing, atol=1e-6)
        np.testing.assert_allclose(other.direction_matrix, grid.direction_matrix, atol=1e-6)
        np.testing.assert_array_equal(other.active_scalars, grid.active_scalars)
    assert grid.active_scalars.dtype == np.uint8
    assert "vtkValidPointMask" in grid.point_data and "vhm_foldover" in grid.point_data
    warped = outputs[".vts"]
    assert warped.n_points == img.n_points
    np.testing.assert_array_equal(warped.active_scalars, img.point_data["v"])
    moved = np.linalg.norm(np.asarray(warped.points) - np.asarray(img.points), axis=1)
    assert moved.max() > 3.0  # really bent


def test_cli_resampling_options(cli_volume, tmp_path, capsys):
    folder, img, files, scene = cli_volume
    src = files[".vti"]
    rc, out, err = _cli(
        capsys, "deform", src, "-s", scene, "-o", tmp_path / "a.vti", "-q",
        "--interpolation", "nearest", "--spacing", "2", "--fill-value", "7",
    )  # fmt: skip
    assert rc == 0, err
    a = read_dataset(tmp_path / "a.vti")
    np.testing.assert_allclose(a.spacing, 2.0)
    values = np.asarray(a.point_data["v"])
    valid = np.asarray(a.point_data["vtkValidPointMask"]).astype(bool)
    assert set(np.unique(values[valid])) <= {40, 140} and (values[~valid] == 7).all()
    # onto another image's grid
    ref = pv.ImageData(dimensions=(20, 21, 22), spacing=(1.5, 1.5, 1.5), origin=(-3, -2, -1))
    ref.point_data["r"] = np.zeros(ref.n_points, np.uint8)
    write_dataset(tmp_path / "ref.mhd", ref)
    rc, out, err = _cli(
        capsys, "deform", src, "-s", scene, "-o", tmp_path / "b.nii.gz", "-q",
        "--reference", tmp_path / "ref.mhd", "--tolerance", "0.02",
    )  # fmt: skip
    assert rc == 0, err
    b = read_dataset(tmp_path / "b.nii.gz")
    assert b.dimensions == ref.dimensions
    np.testing.assert_allclose(b.origin, ref.origin, atol=1e-4)
    # bad values are refused
    for extra in (["--tolerance", "0"], ["--spacing", "1,2"], ["--interpolation", "sinc"]):
        try:
            rc, _, err = _cli(capsys, "deform", src, "-s", scene, "-o", tmp_path / "c.vti", *extra)
        except SystemExit as exc:  # argparse
            rc, err = exc.code, capsys.readouterr().err
        assert rc != 0 and err.strip()
    assert not (tmp_path / "c.vti").exists()


def test_cli_reference_grid_the_deformed_volume_misses_is_refused(cli_volume, tmp_path, capsys):
    # the cli_volume's voxels and its deformation stay within 50 units of the origin
    folder, img, files, scene = cli_volume
    ref = pv.ImageData(dimensions=(20, 21, 22), spacing=(1.5, 1.5, 1.5), origin=(500, 0, 0))
    ref.point_data["r"] = np.zeros(ref.n_points, np.uint8)
    write_dataset(tmp_path / "far.mhd", ref)
    out = tmp_path / "far_out.vti"
    rc, _, err = _cli(
        capsys, "deform", files[".vti"], "-s", scene, "-o", out, "-q",
        "--reference", tmp_path / "far.mhd",
    )  # fmt: skip
    assert rc == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "none of its 9240 voxels lies in the deformed volume" in lines[0]
    assert not out.exists()


def test_cli_resample_grid_is_the_deformed_volumes_whatever_the_tolerance(
    cli_volume, tmp_path, capsys
):
    """The output grid holds the deformed volume and no more: a larger tolerance (a
    coarser lattice) gives the default's grid, and the identity gives the input grid with
    the input's values."""
    folder, img, files, scene = cli_volume
    grids = []
    for extra in ([], ["--tolerance", "1"]):
        path = tmp_path / f"t{len(grids)}.vti"
        rc, out, err = _cli(capsys, "deform", files[".vti"], "-s", scene, "-o", path, "-q", *extra)
        assert rc == 0, err
        grids.append(read_dataset(path))
    assert grids[1].dimensions == grids[0].dimensions
    np.testing.assert_allclose(grids[1].origin, grids[0].origin, rtol=0, atol=1e-9)
    # the scene with its far end left in place: the identity
    data = json.loads(scene.read_text())
    data["constraints"]["targets"] = data["constraints"]["positions"]
    data["constraints"]["jacobians"] = [np.eye(3).tolist()] * 2
    still = tmp_path / "still.json"
    still.write_text(json.dumps(data))
    path = tmp_path / "still.vti"
    rc, out, err = _cli(capsys, "deform", files[".vti"], "-s", still, "-o", path, "-q")
    assert rc == 0, err
    same = read_dataset(path)
    assert same.dimensions == img.dimensions
    np.testing.assert_allclose(same.origin, img.origin, rtol=0, atol=1e-9)
    assert np.asarray(same.point_data["vtkValidPointMask"]).all()
    np.testing.assert_array_equal(same.point_data["v"], img.point_data["v"])


def test_cli_fill_value_is_refused_unless_the_data_type_holds_it(tmp_path, capsys):
    """--fill-value: on an integer image a value outside its type's integers is refused in
    one line before the solve; a floating-point image takes any number, nan included. The
    outside voxels then hold the value exactly, and no Python warning is printed."""
    z, y, x = np.mgrid[0:16, 0:18, 0:20]
    img = pv.ImageData(dimensions=(20, 18, 16), spacing=(1.0, 1.1, 0.9))
    scene = _bend_scene(tmp_path, img.bounds[0::2], img.bounds[1::2])
    base = (50 + 10 * x + 3 * y + z).ravel()
    uint16 = "is not a uint16 value (integers 0 to 65535)"
    float32 = "is not a float32 value (numbers up to 3.4e+38 in magnitude, infinities and nan)"
    cases = {
        np.uint16: ({"-1": uint16, "70000": uint16, "1.5": uint16, "nan": uint16,
                     "inf": uint16}, ["0", "65535", "7"]),
        np.float32: ({"1e39": float32, "-1e39": float32}, ["-1.5", "nan", "-inf", "1e30"]),
        np.int16: ({"40000": "is not an int16 value (integers -32768 to 32767)"}, ["-5"]),
    }  # fmt: skip
    out = tmp_path / "out.vti"
    for dtype, (refused, accepted) in cases.items():
        img.point_data.clear()
        img.point_data["v"] = base.astype(dtype)
        src = tmp_path / f"in_{np.dtype(dtype).name}.vti"
        write_dataset(src, img)
        for text in [*refused, *accepted]:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                rc, _, err = _cli(capsys, "deform", src, "-s", scene, "-o", out, "-q",
                                  f"--fill-value={text}", "--timings")  # fmt: skip
            assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], text
            assert "Warning" not in err, err
            if text in refused:
                assert rc == 1 and not out.exists(), err
                errors = [ln for ln in err.splitlines() if ln.startswith("vhm-viz deform")]
                shown = f"{float(text):g}" if "e" in text else text
                assert errors == [f"vhm-viz deform: error: --fill-value {shown} {refused[text]}"]
                assert " solve " not in next(ln for ln in err.splitlines() if "timings:" in ln)
                continue
            assert rc == 0, err
            got = read_dataset(out)
            values = np.asarray(got.point_data["v"])
            outside = np.asarray(got.point_data["vtkValidPointMask"]) == 0
            assert values.dtype == dtype and outside.any() and (~outside).any()
            want = np.asarray(float(text)).astype(dtype)
            np.testing.assert_array_equal(values[outside], np.full(outside.sum(), want))
            out.unlink()


def test_cli_volume_outside_the_cage(cli_volume, tmp_path, capsys):

    folder, img, files, scene = cli_volume
    data = json.loads(scene.read_text())
    v = np.asarray(data["cage"]["vertices"])
    centre = v.mean(0)
    data["cage"]["vertices"] = (centre + 0.8 * (v - centre)).tolist()  # too small now
    small = tmp_path / "small.json"
    small.write_text(json.dumps(data))
    target = tmp_path / "o.vti"
    rc, out, err = _cli(capsys, "deform", files[".vti"], "-s", small, "-o", target, "-q")
    assert rc != 0 and len(err.strip().splitlines()) == 1
    assert "outside the cage" in err and "--outside passthrough" in err
    rc, out, err = _cli(
        capsys, "deform", files[".vti"], "-s", small, "-o", tmp_path / "o.vti", "-q",
        "--outside", "passthrough",
    )  # fmt: skip
    assert rc == 0, err
    assert "left in place outside the cage" in out


def test_slice_is_the_plane_of_the_resampled_volume(bend):
    geo, cage, hm, vol = bend
    values = {"v": np.arange(geo.n_points, dtype=np.float64)}
    whole = vol.resample(values)
    nx, ny, nz = whole.geometry.dimensions
    plane = vol.slice(values, axis=1, index=ny // 3)
    assert plane.geometry.dimensions == (nx, 1, nz)
    ref = whole.arrays["v"].reshape(nz, ny, nx)[:, ny // 3, :].ravel()
    np.testing.assert_allclose(plane.arrays["v"], ref, rtol=0, atol=1e-6)


def test_surface_mask_catches_every_cube_the_cage_crosses():
    """Cubes whose corners agree and touch no marked point are entirely on one side."""
    cage = read_cage(data_path("armadillo", "cage_216f.obj"))
    lo, hi = cage.vertices.min(0), cage.vertices.max(0)
    sp = (hi - lo).max() / np.array([40.0, 47.0, 43.0])
    rot = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    geo = ImageGeometry((lo + hi) / 2 - rot @ (sp * 22), sp, (44, 45, 41), rot)
    near = surface_mask(geo, cage.vertices, cage.faces)
    inside = inside_mask(geo, cage.vertices, cage.faces)
    # some rows only (a window's): the same points as in the whole grid's masks
    for rows in ((0, 45, 0, 41), (0, 45, 10, 27), (7, 30, 0, 41), (3, 44, 20, 21), (5, 5, 0, 9)):
        j0, j1, k0, k1 = rows
        got = surface_mask(geo, cage.vertices, cage.faces, rows=rows)
        np.testing.assert_array_equal(got, near[k0:k1, j0:j1])
        np.testing.assert_array_equal(
            inside_mask(geo, cage.vertices, cage.faces, rows=rows), inside[k0:k1, j0:j1]
        )
    assert near[10:27].any() and near[:, 7:30].any()
    # marked points are next to the surface, within one grid step of it (brute force),
    # also in a grid that the cage reaches past on its low sides: crossings outside the
    # grid mark nothing
    inner = ImageGeometry(geo.origin + rot @ (sp * 12), sp, (30, 30, 30), rot)
    for grid, marks in ((geo, near), (inner, surface_mask(inner, cage.vertices, cage.faces))):
        marked = grid.points(np.argwhere(marks)[:, ::-1].astype(float))
        closest = nearest_points_on_mesh(marked, cage.vertices, cage.faces)[1]
        gap = np.linalg.norm(marked - closest, axis=1)
        assert marks.any() and (gap <= np.linalg.norm(sp) * (1 + 1e-9)).all()

    def cubes(a, op):
        """``op`` over the 8 corners of every grid cube."""
        nz, ny, nx = (n - 1 for n in a.shape)
        c = a[:nz, :ny, :nx]
        for d in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1)):
            c = op(c, a[d[0] : d[0] + nz, d[1] : d[1] + ny, d[2] : d[2] + nx])
        return c

    all_in = cubes(inside, np.logical_and)
    any_in = cubes(inside, np.logical_or)
    touched = cubes(near, np.logical_or)
    assert not ((all_in != any_in) & ~touched).any()  # mixed corners: always marked
    rng = np.random.default_rng(0)
    u = rng.uniform(0, np.asarray(geo.dimensions) - 1, (100_000, 3))
    i, j, k = np.minimum(np.floor(u).astype(int), np.asarray(geo.dimensions) - 2).T
    clean = ~touched[k, j, i]
    wn = inside_cage(winding_number(geo.points(u[clean]), cage.vertices, cage.faces))
    np.testing.assert_array_equal(wn, all_in[k, j, i][clean])
    assert clean.mean() > 0.5


def test_fast_jacobian_measures_equal_the_svd_ones(bend):
    """Condition numbers and Higham's polar iteration against numpy's SVD."""
    geo, cage, hm, vol = bend
    box = (10, 50, 5, 45, 8, 40)
    got = vol.jacobian_measures(box)
    jac = vol.jacobians(box)
    ref = jacobian_measures(jac)
    np.testing.assert_allclose(got["determinant"], ref["determinant"], rtol=1e-12)
    np.testing.assert_allclose(got["condition_number"], ref["condition_number"], rtol=1e-12)
    np.testing.assert_allclose(got["rotation_angle"], ref["rotation_angle"], atol=1e-9)
    # and the lattice's Jacobians are those of the exact map, to the tolerance's order
    exact = hm.jacobian(geo.sub(box).points())
    scale = np.abs(exact).max()
    assert np.median(np.abs(jac - exact)) < 1e-4 * scale
    # mirrored and degenerate matrices take the SVD's values (the closed form gives NaN or
    # loses s_min there); the identity the closed form's exact ones

    odd = np.array([np.diag([1.0, 1.0, -1.0]), np.diag([1.0, 1.0, 1e-15]), np.eye(3)])
    fast, svd = fast_jacobian_measures(odd), jacobian_measures(odd)
    np.testing.assert_allclose(fast["determinant"], svd["determinant"], rtol=1e-12)
    np.testing.assert_allclose(fast["condition_number"], svd["condition_number"], rtol=1e-12)
    np.testing.assert_allclose(fast["rotation_angle"], svd["rotation_angle"], atol=1e-9)
    assert np.isfinite(fast["condition_number"]).all()
    assert fast["condition_number"][1] > 1e14  # s_min kept, not lost to rounding
    assert fast["condition_number"][2] == 1.0 and fast["rotation_angle"][2] == 0.0


def test_fast_condition_numbers_keep_their_digits_where_singular_values_meet():
    # a closed form of J^T J's eigenvalues loses half the digits where two of them meet
    rng = np.random.default_rng(12)
    n = 3000
    one = np.ones(n)
    s = np.concatenate([
        np.column_stack([2 * one, 2 * (1 - 1e-9) * one, 1 + rng.random(n)]),
        np.column_stack([3 * one, (1 + 1e-9) * one, one]),
    ])  # fmt: skip
    q1, q2 = (np.linalg.qr(rng.normal(size=(len(s), 3, 3)))[0] for _ in range(2))
    q1 *= np.sign(np.linalg.det(q1 @ q2))[:, None, None]  # positive determinants: fast path
    jac = q1 @ (s[:, :, None] * q2)
    fast, svd = fast_jacobian_measures(jac), jacobian_measures(jac)
    np.testing.assert_allclose(fast["condition_number"], svd["condition_number"], rtol=1e-12)


def test_cubic_sampling_reproduces_quadratics():
    """Catmull-Rom reproduces quadratics: a translated quadratic volume comes out exact."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (40, 36, 34))
    cage = _cage_around((0, 0, 0), (39, 35, 33), 0.1, divisions=1)
    shift = np.array([0.37, -0.61, 0.25])
    vol = VolumeDeformation(HarmonicMap.affine(cage, np.eye(3), shift), geo)
    p = geo.points()

    def quadratic(x):
        return 0.02 * x[:, 0] ** 2 - 0.01 * x[:, 0] * x[:, 1] + 0.03 * x[:, 2] ** 2 + x[:, 1]

    res = vol.resample({"q": quadratic(p)}, geometry=geo, interpolation="cubic")
    pre = p - shift  # the exact pre-images
    away = np.all((pre >= 2) & (pre <= np.asarray(geo.dimensions) - 3), axis=1)
    assert away.sum() > 0.5 * len(p) and res.valid[away].all()
    np.testing.assert_allclose(res.arrays["q"][away], quadratic(pre[away]), atol=1e-9)
    lin = vol.resample({"q": quadratic(p)}, geometry=geo, interpolation="linear")
    assert np.abs(lin.arrays["q"][away] - quadratic(pre[away])).max() > 1e-3  # not exact


def test_vtk_filters_two_pieces_equal_one_on_the_lattice():
    """Warp and resample filters on a volume large enough for the lattice (not exact)."""
    img = pv.ImageData(dimensions=(44, 40, 36), spacing=(1.0, 1.0, 1.2))
    rng = np.random.default_rng(7)
    img.point_data["v"] = rng.integers(0, 200, img.n_points).astype(np.uint8)
    lo, hi = np.asarray(img.bounds[0::2]), np.asarray(img.bounds[1::2])
    hm = _random_bend(_cage_around(lo, hi, 0.03), 0.004, seed=2)
    for cls in (HarmonicDeformationFilter, HarmonicResampleFilter):
        whole_filter = cls()
        whole_filter.SetInputData(img)
        whole_filter.SetHarmonicMap(hm)
        whole = pv.wrap(update(whole_filter))
        assert whole.n_points > 32768
        nx, ny, nz = whole.dimensions
        points = np.full((nz, ny, nx, 3), np.nan)
        values = np.zeros((nz, ny, nx), dtype=np.uint8)
        for piece in range(2):
            flt = cls()
            flt.SetInputData(img)
            flt.SetHarmonicMap(hm)
            part = update(flt, piece, 2)
            e = part.GetExtent()
            assert e != whole.GetExtent()
            part = pv.wrap(part)
            shape, box = extent_box(e)
            points[box] = np.asarray(part.points).reshape(shape + (3,))
            values[box] = np.asarray(part.point_data["v"]).reshape(shape)
        if cls is HarmonicDeformationFilter:  # same lattice, same arithmetic
            np.testing.assert_array_equal(points.reshape(-1, 3), whole.points)
            assert isinstance(whole, pv.StructuredGrid)
        else:
            np.testing.assert_array_equal(values.ravel(), whole.point_data["v"])
            assert whole.point_data["v"].dtype == np.uint8


def test_a_lattice_for_the_voxels_only_gives_them_the_same_values():
    """``pre_images=False`` (the warp's and analysis' lattice) skips the single-voxel cells'
    twists and the leaves' pre-image summaries: the voxels' positions and Jacobians stay
    those of the full lattice, bit for bit; what needs the polynomial between voxels is
    refused."""
    cage = read_cage(data_path("armadillo", "cage_216f.obj"))
    lo, hi = cage.vertices.min(0), cage.vertices.max(0)
    geo = ImageGeometry(lo + 0.1 * (hi - lo), 0.8 * (hi - lo) / 47.0, (48, 48, 48))
    hm = _random_bend(cage, 0.003, seed=5)
    full = VolumeDeformation(hm, geo, outside="passthrough", root=8)
    lean = VolumeDeformation(hm, geo, outside="passthrough", root=8, pre_images=False)
    assert lean.lattice.stats["leaves_per_size"].get(1, 0) > 100  # cells next to the cage
    assert (~lean.lattice.inside((0, 47, 0, 47, 0, 47))).any()
    np.testing.assert_array_equal(lean.warp(), full.warp())
    np.testing.assert_array_equal(lean.jacobians(), full.jacobians())
    np.testing.assert_array_equal(lean.lattice.leaf_rows, full.lattice.leaf_rows)
    np.testing.assert_array_equal(lean.lattice.leaf_origin, full.lattice.leaf_origin)
    assert lean.lattice.near is None  # (the surface mask: pre-images only read it)
    ones = np.unique(lean.lattice.leaf_rows[lean.lattice.leaf_size == 1])
    assert not lean.lattice.data[ones, 4:].any() and full.lattice.data[ones, 4:].any()
    assert lean.lattice.nbytes < full.lattice.nbytes
    with pytest.raises(ValueError, match="pre_images=False"):
        lean.resample({"v": np.zeros(geo.n_points)})
    with pytest.raises(ValueError, match="pre_images=False"):
        lean.output_geometry()
    with pytest.raises(ValueError, match="pre_images=False"):
        lean.lattice.evaluate([[20.0, 20.0, 20.0]])
    # the policy's copy keeps it
    assert not lean.with_outside("nan").pre_images


def test_a_window_of_the_lattice_gives_the_whole_lattices_voxels():
    """A piece's lattice (its root cells only) warps its voxels as the whole lattice does."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.2), (44, 40, 70))
    hm = _random_bend(_cage_around((0, 0, 0), (43, 39, 82.8), 0.03), 0.004, seed=2)
    whole = VolumeDeformation(hm, geo, outside="passthrough")
    pts, jac = whole.warp(), whole.jacobians()
    shape = geo.dimensions[::-1]
    scale = np.linalg.norm(np.ptp(pts, axis=0))
    for window in ([0, 43, 0, 39, 0, 34], [0, 43, 0, 39, 34, 69], [5, 30, 3, 20, 9, 33]):
        part = VolumeDeformation(hm, geo, outside="passthrough", window=window)
        i0, i1, j0, j1, k0, k1 = window
        cut = np.s_[k0 : k1 + 1, j0 : j1 + 1, i0 : i1 + 1]
        np.testing.assert_allclose(
            part.warp(), pts.reshape(shape + (3,))[cut].reshape(-1, 3), rtol=0, atol=1e-12 * scale
        )
        np.testing.assert_allclose(
            part.jacobians(), jac.reshape(shape + (3, 3))[cut].reshape(-1, 3, 3), rtol=0,
            atol=1e-10,
        )  # fmt: skip
        assert part.lattice.stats["evaluations"] < whole.lattice.stats["evaluations"]
        # its masks: the whole lattice's in its root cells' rows, untouched elsewhere
        rows = np.zeros(part.lattice.mask.shape[:2], dtype=bool)
        r = part.root
        rows[k0 // r * r : (k1 // r + 1) * r + 1, j0 // r * r : (j1 // r + 1) * r + 1] = True
        # (a window's engine warps only: its lattice has no surface mask, which only
        # pre-images read; one built with them has that mask too, the same way)
        assert part.lattice.near is None
        with_near = VolumeDeformation(hm, geo, window=window, pre_images=True).lattice
        for lat, name in ((part.lattice, "mask"), (with_near, "mask"), (with_near, "near")):
            mine, all_ = getattr(lat, name), getattr(whole.lattice, name)
            np.testing.assert_array_equal(mine[rows], all_[rows])
            assert not mine[~rows].any()
        with pytest.raises(ValueError, match="not inside the window"):
            part.warp([0, 43, 0, 39, 0, 69])
        with pytest.raises(ValueError, match="needs the whole lattice"):
            part.resample({"v": np.zeros(geo.n_points)})


class _ThreadExchange:
    """``build_lattice``'s exchange between builders in threads, as MPI ranks do it.

    Every round the builders post their keys and meet; builder ``r`` evaluates every
    ``n``-th of the distinct keys from the ``r``-th on; they meet again and each takes its
    own keys' data. It records what each builder evaluated.
    """

    def __init__(self, n):

        self.n = n
        # the failures as all builders met: a builder failing in a round's evaluation must
        # not be seen at that round's first meeting by a slower builder, which would then
        # leave without meeting the failed one again
        self.meet = threading.Barrier(n, action=self._take_failures, timeout=60)
        self.keys = [None] * n
        self.data = [None] * n
        self.failed = [False] * n
        self.failed_at_meeting = False
        self.evaluated = [[] for _ in range(n)]

    def _take_failures(self):
        self.failed_at_meeting = any(self.failed)

    def builder(self, r):
        exchange = self

        class One:
            def __call__(self, keys, evaluate):
                exchange.keys[r] = keys
                exchange.meet.wait()
                if exchange.failed_at_meeting:
                    raise RuntimeError("another builder failed")
                distinct = np.unique(np.concatenate(exchange.keys))
                mine = distinct[r :: exchange.n]
                try:
                    exchange.data[r] = (mine, evaluate(mine))
                except BaseException:
                    exchange.failed[r] = True
                    exchange.meet.wait()
                    raise
                exchange.evaluated[r].append(mine)
                exchange.meet.wait()
                if exchange.failed_at_meeting:
                    raise RuntimeError("another builder failed")
                f = np.empty((len(distinct), 3))
                fu = np.empty((len(distinct), 3, 3))
                ins = np.empty(len(distinct), dtype=bool)
                for got, (f_s, fu_s, ins_s) in exchange.data:
                    at = np.searchsorted(distinct, got)
                    f[at], fu[at], ins[at] = f_s, fu_s, ins_s
                exchange.meet.wait()  # everyone has read the round's data
                at = np.searchsorted(distinct, keys)
                return f[at], fu[at], ins[at]

            def abandon(self):
                exchange.failed[r] = True
                exchange.meet.wait()

        return One()


def _build_together(hm, geo, windows, **kw):
    """Build ``VolumeDeformation`` lattices of ``windows`` in threads that share evaluations."""

    exchange = _ThreadExchange(len(windows))
    engines = [VolumeDeformation(hm, geo, outside="passthrough", window=w,
                                 exchange=exchange.builder(r), **kw)
               for r, w in enumerate(windows)]  # fmt: skip
    with ThreadPoolExecutor(len(windows)) as pool:
        done = [pool.submit(e.build) for e in engines]
        errors = [f.exception(timeout=120) for f in done]
    return engines, exchange, errors


def test_builders_sharing_evaluations_build_the_serial_lattice():
    """Two builders (MPI ranks) sharing their exact evaluations: each point is evaluated
    once, by one of them, and each gets the lattice a builder alone makes, bit for bit --
    two halves of the grid (the warp's pieces) and the whole grid twice (the resample's)."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.2), (44, 40, 70))
    hm = _random_bend(_cage_around((0, 0, 0), (43, 39, 82.8), 0.03), 0.004, seed=2)
    alone = VolumeDeformation(hm, geo, outside="passthrough")
    halves = ([0, 43, 0, 39, 0, 34], [0, 43, 0, 39, 34, 69])
    for windows in (halves, (None, None)):
        engines, exchange, errors = _build_together(hm, geo, windows)
        assert errors == [None, None]
        for rounds in zip(*exchange.evaluated, strict=True):  # each round: a point once
            both = np.concatenate(rounds)
            assert len(np.unique(both)) == len(both)
        evaluated = [np.concatenate(e) for e in exchange.evaluated]
        both = np.concatenate(evaluated)
        # shared about equally (interleaved shares of each round)
        assert min(map(len, evaluated)) > 0.45 * len(both)
        if windows is halves:  # the points both need in the same round: evaluated once
            apart = [VolumeDeformation(hm, geo, outside="passthrough", window=w).lattice
                     for w in windows]  # fmt: skip
            assert len(both) < sum(a.stats["evaluations"] for a in apart)
        for engine, window in zip(engines, windows, strict=True):
            if window is None:  # the whole lattice: the same data, in the same rows
                for name in ("data", "leaf_origin", "leaf_rows", "centre_f"):
                    np.testing.assert_array_equal(
                        getattr(engine.lattice, name), getattr(alone.lattice, name)
                    )
                continue
            own = VolumeDeformation(hm, geo, outside="passthrough", window=window)
            np.testing.assert_array_equal(engine.warp(), own.warp())
            np.testing.assert_array_equal(engine.lattice.data, own.lattice.data)
    # the whole lattice built twice together: its points evaluated once between them
    assert len(both) == alone.lattice.stats["evaluations"]


def test_lattice_masks_made_by_planes_equal_one_call():
    """A lattice's masks are made 16 k-planes at a time (memory), over the lattice rows of
    its window's root cells only: the same as one call over those rows, with False
    outside them."""
    cage = _cage_around((2.0, 3.0, 1.0), (27.0, 24.0, 44.0), 0.0)
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (30, 28, 50))
    hm = HarmonicMap.affine(cage, np.eye(3), np.zeros(3))
    V, F = cage.vertices, cage.faces
    # root cells of 16 voxels: the lattice has 33 x 33 x 65 points; the window's k-voxels
    # 20..35 lie in the root layers 1 and 2, the lattice's k-rows 16..48 (33 planes)
    for window, rows in (((0, 29, 0, 27, 20, 35), (0, 33, 16, 49)), (None, None)):
        lat = build_lattice(hm, geo, root=16, window=window)
        lat_geo = ImageGeometry(geo.origin, geo.spacing, lat.end + 1, geo.direction)
        assert tuple(lat_geo.dimensions) == (33, 33, 65)
        j0, j1, k0, k1 = (0, 33, 0, 65) if rows is None else rows
        mask, near = lat.mask, lat.near
        assert mask.shape == near.shape == (65, 33, 33)
        inside = inside_mask(lat_geo, V, F, rows=(j0, j1, k0, k1))
        assert inside.any() and not inside.all()
        np.testing.assert_array_equal(mask[k0:k1, j0:j1], inside)
        surface = surface_mask(lat_geo, V, F, rows=(j0, j1, k0, k1))
        assert surface.any()
        np.testing.assert_array_equal(near[k0:k1, j0:j1], surface)
        mask[k0:k1, j0:j1] = near[k0:k1, j0:j1] = False
        assert not mask.any() and not near.any()


def test_cut_flags_cover_every_cube_the_pull_back_reads_and_equal_the_masks():
    """The pull-back reads the inside/surface flags only in the grid cubes around pre-images
    of the leaves the cage crosses; they are kept in blocks (cut_flags). Computed from
    the cage (a joined lattice has no masks) they equal the masks in every kept block; every
    cube a cut leaf's pre-image can lie in is kept; and the blocks answer as the masks do."""
    geo, cage = _turned_box()
    hm = _random_bend(cage, 0.03, seed=5)
    lat = build_lattice(hm, geo)
    block_of, pool, dims = lat.cut_flags()
    _BLOCK = pool.shape[1]  # blocks of _BLOCK^3 lattice points
    assert pool.shape[1:] == (_BLOCK, _BLOCK, _BLOCK)
    # all the leaves, joined: the same leaves without the masks
    joined = join_parts([lat.part(np.arange(len(lat.leaf_size)))], hm, geo,
                        tolerance=lat.tolerance, root=lat.root)  # fmt: skip
    assert joined.mask is None
    from_cage = joined.cut_flags()
    np.testing.assert_array_equal(from_cage[0], block_of)
    np.testing.assert_array_equal(from_cage[1], pool)
    np.testing.assert_array_equal(from_cage[2], dims)
    assert 0 < len(pool) < block_of.size  # some blocks, not all
    flags = lat.mask.astype(np.uint8) | (lat.near.astype(np.uint8) << 1)
    for kb, jb, ib in np.argwhere(block_of >= 0):
        k, j, i = kb * _BLOCK, jb * _BLOCK, ib * _BLOCK
        block = flags[k : k + _BLOCK, j : j + _BLOCK, i : i + _BLOCK]
        got = pool[block_of[kb, jb, ib]]
        np.testing.assert_array_equal(got[: block.shape[0], : block.shape[1], : block.shape[2]],
                                      block)  # fmt: skip
    # every corner of every cube around a cut leaf grown by its margin is kept
    cut = np.nonzero(lat.leaf_cut)[0]
    assert len(cut) > 50
    m = lat.margins()[cut, None]
    o, h = lat.leaf_origin[cut], lat.leaf_size[cut, None]
    lo = np.clip(np.floor(o - m), 0, dims - 2).astype(int)
    hi = np.clip(np.floor(o + h + m), 0, dims - 2).astype(int) + 1
    for a, b in zip(lo, hi, strict=True):
        blocks = block_of[a[2] // _BLOCK : b[2] // _BLOCK + 1, a[1] // _BLOCK : b[1] // _BLOCK + 1,
                          a[0] // _BLOCK : b[0] // _BLOCK + 1]  # fmt: skip
        assert (blocks >= 0).all()
    # at points in those cubes, the blocks' answer is the masks' (brute force over corners)
    rng = np.random.default_rng(2)
    pick = rng.choice(cut, 400)
    sel = np.searchsorted(cut, pick)
    u = lo[sel] + rng.random((400, 3)) * (hi[sel] - lo[sel])
    for p in u:
        i0, j0, k0 = np.minimum(np.maximum(np.floor(p).astype(int), 0), dims - 2)
        corners = (slice(k0, k0 + 2), slice(j0, j0 + 2), slice(i0, i0 + 2))
        expected = -1 if lat.near[corners].any() else int(lat.mask[corners].sum())
        expected = expected if expected in (-1, 0, 8) else -1
        assert inside_around(block_of, pool, dims, p) == expected


def test_rows_read_in_chunks_equals_one_pass(monkeypatch):
    """The rows a level's node data reads are found in chunks of nodes (the build's peak
    memory): with chunks of 7 nodes the lattice is bit for bit the one-chunk lattice."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.2), (30, 28, 40))
    hm = _random_bend(_cage_around((0, 0, 0), (29, 27, 46.8), 0.03), 0.02, seed=4)
    monkeypatch.setattr(nodes, "LEVEL_CHUNK", 10**9)
    whole = build_lattice(hm, geo)
    monkeypatch.setattr(nodes, "LEVEL_CHUNK", 7)
    chunked = build_lattice(hm, geo)
    assert whole.stats["leaves_per_size"].get(1, 0) > 100  # a level of many small cells
    assert np.abs(whole.data[:, 4:]).max() > 0  # twists made
    np.testing.assert_array_equal(chunked.data, whole.data)
    np.testing.assert_array_equal(chunked.leaf_rows, whole.leaf_rows)
    # and for the voxels only (no twists at single-voxel cells)
    chunked = build_lattice(hm, geo, pre_images=False)
    monkeypatch.setattr(nodes, "LEVEL_CHUNK", 10**9)
    whole = build_lattice(hm, geo, pre_images=False)
    np.testing.assert_array_equal(chunked.data, whole.data)
    assert not chunked.data[chunked.leaf_rows[chunked.leaf_size == 1], 4:].any()


def test_finest_level_is_made_from_the_nodes_it_reads_only(monkeypatch):
    """Before the finest level's node data the table keeps the nodes that data reads
    (the build's peak memory): the lattice is bit for bit the one made from the whole
    table, with and without twists, and the table did shrink."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.2), (30, 28, 40))
    hm = _random_bend(_cage_around((0, 0, 0), (29, 27, 46.8), 0.03), 0.02, seed=4)
    keep = NodeTable.keep
    sizes = []

    def recorded(table, rows):
        sizes.append((len(table.keys), len(rows)))
        keep(table, rows)
        assert len(table.keys) == len(rows) and (np.diff(table.keys) > 0).all()

    for pre_images in (True, False):
        monkeypatch.setattr(NodeTable, "keep", recorded)
        kept = build_lattice(hm, geo, pre_images=pre_images)
        monkeypatch.setattr(NodeTable, "keep", lambda table, rows: None)
        whole = build_lattice(hm, geo, pre_images=pre_images)
        np.testing.assert_array_equal(kept.data, whole.data)
        np.testing.assert_array_equal(kept.leaf_rows, whole.leaf_rows)
        assert kept.stats["leaves_per_size"].get(1, 0) > 100
    (all_twists, kept_twists), (all_voxels, kept_voxels) = sizes
    assert kept_twists < all_twists and kept_voxels < kept_twists and all_voxels == all_twists


def test_node_table_merges_new_nodes_in_place_in_key_order():
    """The build's node table grows in place, the new rows merged in from the back (its
    memory): the same table as concatenating and sorting by key, for sorted and unsorted
    batches, an empty one, and keys before, between and after the old ones; an array
    held elsewhere too is copied, not resized under its other holder."""
    rng = np.random.default_rng(7)
    table = NodeTable((40, 40, 40))
    pool = rng.permutation(64000)
    batches = [np.sort(pool[:500]), pool[500:501], pool[:0], np.sort(pool[1000:6000]),
               pool[6000:9000], np.array([pool[9000:].min(), pool[9000:].max()])]  # fmt: skip
    keys, f, fu, inside = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), []
    for batch in batches:
        bf, bfu = rng.normal(size=(len(batch), 3)), rng.normal(size=(len(batch), 3, 3))
        bin_ = rng.random(len(batch)) > 0.5
        table.add(batch, bf, bfu, bin_)
        keys, f = np.concatenate([keys, batch]), np.concatenate([f, bf])
        fu = np.concatenate([fu, bfu])
        inside = np.concatenate([inside, bin_]).astype(bool)
        order = np.argsort(keys, kind="stable")
        np.testing.assert_array_equal(table.keys, keys[order])
        np.testing.assert_array_equal(table.f, f[order])
        np.testing.assert_array_equal(table.fu, fu[order])
        np.testing.assert_array_equal(table.inside, inside[order])
        np.testing.assert_array_equal(table.find(batch), np.searchsorted(table.keys, batch))
    assert len(table.keys) == 8503
    # the batches put keys before, between and after those already there
    assert batches[-1].min() < batches[0].min() and batches[-1].max() > batches[0].max()
    held = table.fu
    copy = table.fu.copy()
    new_key = np.setdiff1d(np.arange(64000), table.keys)[:1]
    table.add(new_key, np.ones((1, 3)), np.ones((1, 3, 3)), np.ones(1, dtype=bool))
    np.testing.assert_array_equal(held, copy)  # the other holder's array is untouched
    at = table.find(new_key)[0]
    np.testing.assert_array_equal(np.delete(table.fu, at, axis=0), copy)
    assert table.fu[at].sum() == 9.0


def test_node_table_grows_without_holding_itself_twice():
    """Adding rows to the node table allocates about the new rows, not a second table
    (concatenating and reordering held each field three times at once). What this code
    allocates (tracemalloc), not what realloc may copy below glibc's mmap threshold."""

    rng = np.random.default_rng(3)
    keys = np.sort(rng.choice(10**7, size=250_000, replace=False))
    old, new = keys[::5], np.setdiff1d(keys, keys[::5])[:50_000]
    table = NodeTable((1000, 1000, 1000))
    table.add(np.array([1]), np.zeros((1, 3)), np.zeros((1, 3, 3)), np.zeros(1, bool))  # compiled
    args = (new, rng.normal(size=(len(new), 3)), rng.normal(size=(len(new), 3, 3)),
            np.ones(len(new), dtype=bool))  # fmt: skip
    table = NodeTable((1000, 1000, 1000))
    tracemalloc.start()
    try:
        n = len(old)
        table.add(old, np.zeros((n, 3)), np.zeros((n, 3, 3)), np.zeros(n, dtype=bool))
        start = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        table.add(*args)
        peak = tracemalloc.get_traced_memory()[1] - start
    finally:
        tracemalloc.stop()
    row = 8 + 24 + 72 + 1  # key, f, fu, inside
    assert len(table.keys) == len(old) + len(new)
    # the new rows, their positions and index temporaries; a second fu alone is 7.2 MB
    assert peak < len(new) * (row + 40), peak


def test_taking_rows_in_place_equals_indexing_in_the_same_memory():
    """A lattice's last part is taken out of its own arrays (take_in_place): the same rows as
    fancy indexing, for every field's dtype and shape; in place (the same memory, no second
    array) for an ascending index; copied when the index is not ascending or the array is
    held elsewhere, which is then left untouched."""

    rng = np.random.default_rng(11)
    arrays = {"data": rng.normal(size=(5000, 8, 3)), "origin": rng.integers(0, 99, (5000, 3)),
              "cut": rng.random(5000) > 0.5, "rho": rng.random(5000)}  # fmt: skip
    index = np.sort(rng.choice(5000, size=3100, replace=False))
    for a in arrays.values():  # compiled first: a first call's compiler may hold a
        take_in_place({"x": a[:4].copy()}, "x", np.arange(2))  # reference (then it copies)
    gc.collect()
    for name, a in arrays.items():
        expected = a[index]
        holder = {name: a.copy()}
        address = holder[name].ctypes.data
        got = take_in_place(holder, name, index)
        assert holder[name] is None
        np.testing.assert_array_equal(got, expected)
        assert got.ctypes.data == address  # the same memory, shrunk (realloc never moves
        # a shrinking block), not a second array
    holder = {"x": arrays["data"].copy()}
    other = holder["x"]
    before = other.copy()
    np.testing.assert_array_equal(take_in_place(holder, "x", index), before[index])
    np.testing.assert_array_equal(other, before)  # its other holder's array is untouched
    shuffled = rng.permutation(index)
    got = take_in_place({"x": before.copy()}, "x", shuffled)
    np.testing.assert_array_equal(got, before[shuffled])
    for empty in (np.zeros(0, np.int64), index[:1]):
        got = take_in_place({"x": before.copy()}, "x", empty)
        np.testing.assert_array_equal(got, before[empty])
    nothing = np.zeros((0, 8, 3))  # (an MPI rank's empty window)
    assert take_in_place({"x": nothing}, "x", np.zeros(0, np.int64)).shape == (0, 8, 3)

    big = {"data": rng.normal(size=(200_000, 8, 3))}  # 38 MB: mmapped, shrunk by mremap
    address = big["data"].ctypes.data
    expected = big["data"][::3].copy()
    part = take_in_place(big, "data", np.arange(0, 200_000, 3))
    assert part.ctypes.data == address
    np.testing.assert_array_equal(part, expected)


def test_a_builder_of_an_empty_piece_only_shares_the_evaluations():
    """An MPI rank with an empty piece (more ranks than planes) builds no cell but takes
    its share of the other's evaluations, so that neither waits for the other."""

    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.2), (44, 40, 70))
    hm = _random_bend(_cage_around((0, 0, 0), (43, 39, 82.8), 0.03), 0.004, seed=2)
    alone = build_lattice(hm, geo)
    exchange = _ThreadExchange(2)
    with ThreadPoolExecutor(2) as pool:
        full = pool.submit(build_lattice, hm, geo, exchange=exchange.builder(0))
        # (through the volume engine, as the ParaView filter builds it)
        empty = pool.submit(VolumeDeformation(hm, geo, window=[0, -1, 0, 39, 0, 69],
                                              exchange=exchange.builder(1)).build)  # fmt: skip
        full, empty = full.result(timeout=120), empty.result(timeout=120)
    np.testing.assert_array_equal(full.data, alone.data)
    assert empty.stats["leaves"] == 0
    assert len(np.concatenate(exchange.evaluated[1])) > 0.45 * alone.stats["evaluations"]
    with pytest.raises(ValueError, match="not inside the grid"):  # alone: a mistake
        build_lattice(hm, geo, window=[0, -1, 0, 39, 0, 69])
    with pytest.raises(ValueError, match="not inside the grid"):
        VolumeDeformation(hm, geo, window=[0, -1, 0, 39, 0, 69])


def test_a_builder_failing_stops_the_builders_sharing_with_it():
    """An abort on one builder: every builder raises, none waits for the others."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.2), (44, 40, 70))
    hm = _random_bend(_cage_around((0, 0, 0), (43, 39, 82.8), 0.03), 0.004, seed=2)
    calls = []

    def abort():  # the second builder aborts in its third chunk of evaluations
        calls.append(1)
        return len(calls) > 4

    exchange = _ThreadExchange(2)
    engines = [
        VolumeDeformation(hm, geo, outside="passthrough", exchange=exchange.builder(0)),
        VolumeDeformation(hm, geo, outside="passthrough", exchange=exchange.builder(1)),
    ]

    with ThreadPoolExecutor(2) as pool:
        done = [pool.submit(engines[0].build), pool.submit(engines[1].build, abort=abort)]
        errors = [f.exception(timeout=120) for f in done]
    assert isinstance(errors[1], AbortedError)
    assert isinstance(errors[0], RuntimeError) and "another builder" in str(errors[0])
    # failing between two rounds (here before the first): the others hear of it there

    exchange = _ThreadExchange(2)
    with ThreadPoolExecutor(2) as pool:
        good = pool.submit(build_lattice, hm, geo, exchange=exchange.builder(0))
        bad = pool.submit(build_lattice, hm, geo, window=[0, 99, 0, 9, 0, 9],
                          exchange=exchange.builder(1))  # fmt: skip
        errors = [good.exception(timeout=120), bad.exception(timeout=120)]
    assert isinstance(errors[1], ValueError) and "not inside the grid" in str(errors[1])
    assert isinstance(errors[0], RuntimeError) and "another builder" in str(errors[0])


def test_another_outside_policy_shares_the_lattice():
    """Changing the outside policy keeps the lattice (ParaView sets properties one by one,
    each with an information pass): the other policy's results, no second build."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (40, 36, 34))
    hm = _random_bend(_cage_around((4, 4, 4), (30, 28, 26), 0.0), 0.004, seed=5)
    kept = VolumeDeformation(hm, geo, outside="passthrough")
    kept.build()
    other = kept.with_outside("nan")
    assert other.lattice is kept.lattice and other.outside == "nan"
    fresh = VolumeDeformation(hm, geo, outside="nan").warp()
    np.testing.assert_array_equal(other.warp(), fresh)
    assert np.isnan(fresh).any() and not np.isnan(kept.warp()).any()
    with pytest.raises(OutsideCageError):
        kept.with_outside("error").warp()


def test_resample_pieces_read_only_the_window_their_preimages_reach(tmp_path):
    """Streamed in 4 pieces from a reader, each piece reads only a window of the volume,
    holding its pre-images, and the pieces equal the whole."""

    img = pv.ImageData(dimensions=(30, 28, 80), spacing=(1.0, 1.0, 1.0))
    rng = np.random.default_rng(5)
    img.point_data["v"] = rng.integers(0, 60000, img.n_points).astype(np.uint16)
    img.save(tmp_path / "v.vti")
    hm = _random_bend(_cage_around((0, 0, 0), (29, 27, 79), 0.03), 0.003, seed=4)

    def pipeline():  # a fresh reader: one that holds the whole volume would not read again
        reader = vtkXMLImageDataReader()  # it reads sub-extents (a trivial producer cannot)
        reader.SetFileName(str(tmp_path / "v.vti"))
        flt = HarmonicResampleFilter()
        flt.SetInputConnection(reader.GetOutputPort())
        flt.SetHarmonicMap(hm)
        flt.SetInterpolation("cubic")
        return flt

    flt = pipeline()
    whole = pv.wrap(update(flt))
    nx, ny, nz = whole.dimensions
    ref = {n: np.asarray(whole.point_data[n]).reshape(nz, ny, nx) for n in
           ("v", "vtkValidPointMask", "vhm_foldover")}  # fmt: skip
    assert ref["vtkValidPointMask"].mean() > 0.5
    vol, out_geo = flt.volume_engine, flt._geometry
    read = []
    for piece in range(4):
        flt = pipeline()
        part = update(flt, piece, 4)
        e = part.GetExtent()
        window = flt.GetInputDataObject(0, 0).GetExtent()  # what the reader delivered
        read.append(window[5] - window[4] + 1)
        part = pv.wrap(part)
        _, box = extent_box(e)
        for name, values in ref.items():
            np.testing.assert_array_equal(part.point_data[name], values[box].ravel())
        # the window holds every pre-image of the piece with its cubic stencil (-1 .. +2)
        k, j, i = np.meshgrid(*[np.arange(e[2 * a], e[2 * a + 1] + 1) for a in (2, 1, 0)],
                              indexing="ij")  # fmt: skip
        u, kind, _ = vol.preimages(out_geo, np.column_stack([i.ravel(), j.ravel(), k.ravel()]))
        u = u[kind > 0]
        lo = np.clip(np.floor(u) - 1, 0, np.asarray(img.dimensions) - 1)
        hi = np.clip(np.floor(u) + 2, 0, np.asarray(img.dimensions) - 1)
        assert (lo >= window[0::2]).all() and (hi <= window[1::2]).all()
    assert max(read) < img.dimensions[2]  # no piece read the whole volume


def test_cage_of_two_shells():
    """Two outward shells, each around half of the volume: each half follows its own."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (64, 30, 30))
    v1, f1 = box_cage((-1.0, -1.0, -1.0), (29.5, 30.0, 30.0), 2)
    v2, f2 = box_cage((32.5, -1.0, -1.0), (64.0, 30.0, 30.0), 2)
    cage = Cage(np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)]))
    hm = _random_bend(cage, 0.004, seed=9)
    vol = VolumeDeformation(hm, geo, outside="passthrough")
    pts = vol.warp()
    inside = inside_mask(geo, cage.vertices, cage.faces).ravel()
    assert 0.8 < inside.mean() < 0.97  # the gap between the shells is outside
    rng = np.random.default_rng(0)
    pick = rng.choice(np.nonzero(inside)[0], 3000, replace=False)
    err = _voxel_error(geo, pts[pick] - hm.map(geo.points()[pick]))
    assert err.max() <= vol.tolerance
    np.testing.assert_array_equal(pts[~inside], geo.points()[~inside])
    res = vol.resample({"v": np.ones(geo.n_points)})
    assert res.counts["valid"] > 0.9 * geo.n_points


def test_input_window_holds_every_preimage_of_its_box_and_is_computed_once():
    """Each half of the output reads only its input window (brute force: every voxel's
    pre-image, with the linear stencil around it), asked for again at no cost; the
    leaves' candidate boxes are computed once for both halves and the pre-images."""
    geo, cage = _turned_box()
    hm = _random_bend(cage, 0.01, seed=1)
    vol = VolumeDeformation(hm, geo, tolerance=0.05, outside="passthrough")
    out = vol.output_geometry()
    assert vol.output_geometry() is out
    nx, ny, nz = out.dimensions
    scans = []
    boxes = vol.lattice.candidate_boxes
    vol.lattice.candidate_boxes = lambda g: scans.append(1) or boxes(g)
    windows = []
    for box in ([0, nx - 1, 0, ny - 1, 0, nz // 2], [0, nx - 1, 0, ny - 1, nz // 2 + 1, nz - 1]):
        w = vol.input_window(out, box)
        assert len(scans) == 1  # the leaves' candidate boxes: one pass, kept for the grid
        sub = out.sub(box)
        ijk = sub.ijk() + np.array(box[0::2])
        u, kind, _ = vol.preimages(out, ijk)
        found = kind > 0
        assert found.mean() > 0.3
        assert (np.floor(u[found]) >= w[0::2]).all() and (np.ceil(u[found]) <= w[1::2]).all()
        again = vol.input_window(out, box)
        assert len(scans) == 1  # kept, not scanned again
        np.testing.assert_array_equal(again, w)
        again[:] = -1  # a copy: the kept window stays
        np.testing.assert_array_equal(vol.input_window(out, box), w)
        windows.append(w)
    assert windows[0][5] < nz - 1 or windows[1][4] > 0  # the halves read less than all


def test_pieces_resampled_with_leaves_joined_from_windows_equal_the_whole_lattice():
    """MPI ranks resample without the whole lattice: each builds a window of root cells,
    they agree on the output grid from their bounds, and each output piece is resampled
    with the leaves (from every window) whose images reach it -- bit for bit the whole
    lattice's result, with an input window that holds the one the whole lattice names."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.2), (44, 40, 70))
    hm = _random_bend(_cage_around((0, 0, 0), (43, 39, 82.8), 0.03), 0.02, seed=2)
    whole = VolumeDeformation(hm, geo, outside="passthrough")
    values = np.asarray(_smooth_volume(geo.dimensions, geo.spacing, geo.origin)["density"])
    out_geo = whole.output_geometry()
    # windows of whole root cells (16 voxels), each with two voxels beyond the split: the
    # twists of single-voxel cells read the neighbours there
    windows = [
        VolumeDeformation(hm, geo, outside="passthrough", window=w, pre_images=True)
        for w in ([0, 43, 0, 39, 0, 33], [0, 43, 0, 39, 30, 69])
    ]
    own = [(0, 1), (2, 4)]  # each window's own root layers (along k)
    layer = [w.lattice.root_keys() // int(np.prod(w.lattice.n_root[:2])) for w in windows]
    bounds = [w.image_bounds() for w in windows]
    lo = np.min([b[0] for b in bounds], axis=0)
    hi = np.max([b[1] for b in bounds], axis=0)
    any_outside = any(b[2] for b in bounds)
    assert any_outside == (not whole.lattice.inside([0, 43, 0, 39, 0, 69]).all())
    joined_geo = output_grid(geo, lo, hi, keep_input=any_outside)
    assert joined_geo.key() == out_geo.key()
    # (an engine's own grid over the bounds)
    assert windows[0].grid_over(lo, hi, keep_input=any_outside).key() == out_geo.key()
    table = np.concatenate([w.reach_table(out_geo) for w in windows])
    n = out_geo.dimensions
    # pieces across the windows' split (along j), so that each takes leaves from both
    pieces = [[0, n[0] - 1, 0, n[1] // 2 - 1, 0, n[2] - 1],
              [0, n[0] - 1, n[1] // 2, n[1] - 1, 0, n[2] - 1]]  # fmt: skip
    for piece in pieces:
        parts, sources = [], []
        for w, (k0, k1), lay in zip(windows, own, layer, strict=True):
            clo, chi = w.lattice.candidate_boxes(out_geo)
            mine = (lay >= k0) & (lay <= k1)
            hit = np.nonzero(mine & np.all((clo <= piece[1::2]) & (chi >= piece[0::2]), axis=1))[0]
            parts.append(w.lattice.part(hit))
            sources.append(len(hit))
        assert min(sources) > 0
        if piece is pieces[0]:
            lat = join_parts(parts, hm, geo, tolerance=whole.tolerance, root=whole.root)
            engine = VolumeDeformation.for_piece(
                hm, geo, lat, out_geo, piece, any_outside=any_outside,
                tolerance=whole.tolerance, outside="passthrough",
            )  # fmt: skip
        else:  # the same through a window engine, with its own map, tolerance and policy
            lat = windows[1].join_parts(parts)
            engine = windows[1].piece_engine(lat, out_geo, piece, any_outside=any_outside)
            assert (engine.tolerance, engine.outside) == (whole.tolerance, "passthrough")
        assert lat.stats["leaves"] < whole.lattice.stats["leaves"]
        got = engine.resample({"v": values}, out_geo, box=piece)
        ref = whole.resample({"v": values}, out_geo, box=piece)
        assert ref.counts["valid"] > 0.3 * geo.n_points / 2
        np.testing.assert_array_equal(got.arrays["v"], ref.arrays["v"])
        np.testing.assert_array_equal(got.valid, ref.valid)
        np.testing.assert_array_equal(got.foldover, ref.foldover)
        assert got.counts == ref.counts
        # the windows' root-cell tables name an input window that holds the leaves'
        need = whole.input_window(out_geo, piece)
        have = window_of(table, piece, geo, out_geo, margin=0.75, in_place=any_outside)
        assert (have[0::2] <= need[0::2]).all() and (have[1::2] >= need[1::2]).all()
        assert engine.input_window(out_geo, piece).tolist() == need.tolist()
        with pytest.raises(ValueError, match="one output piece only"):
            engine.warp()
        other = pieces[1] if piece is pieces[0] else pieces[0]
        with pytest.raises(ValueError, match="reach the output piece"):
            engine.resample({"v": values}, out_geo, box=other)
    # the last part taken from a window's lattice frees it as it is copied: same part
    w = windows[1]
    hit = np.arange(0, w.lattice.stats["leaves"], 3)
    kept = w.lattice.part(hit)
    # the data rows the leaves read, once each and renumbered: each leaf reads the same
    # node data as in its lattice
    np.testing.assert_array_equal(kept["data"][kept["rows"]],
                                  w.lattice.data[w.lattice.leaf_rows[hit]])  # fmt: skip
    assert len(kept["data"]) == len(np.unique(w.lattice.leaf_rows[hit]))
    # without copies: the same part, its lattice arrays' fields as (array, index) pairs
    pairs = w.lattice.part(hit, copy=False)
    assert isinstance(pairs["data"], tuple) and pairs["data"][0] is w.lattice.data
    for name in PART_FIELDS:
        value = pairs[name]
        np.testing.assert_array_equal(
            value[0][value[1]] if isinstance(value, tuple) else value, kept[name]
        )
    lat = w.lattice
    w.drop_lattice()
    taken = lat.part(hit, release=True)
    assert taken.keys() == kept.keys() == PART_FIELDS.keys()
    for name in PART_FIELDS:
        np.testing.assert_array_equal(taken[name], kept[name])
    assert lat.data is None and lat.mask is None and lat.leaf_origin is None


def test_layer_shares_split_the_voxels_inside_the_cage_evenly():
    """MPI ranks' root layers: cuts nearest to equal shares of the voxels inside the cage.

    A pyramid cage (the voxels inside per layer fall with height) against the best cuts
    found by brute force from every voxel's winding number.
    """

    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (40, 40, 121))
    verts = np.array([[2, 2, -1], [38, 2, -1], [38, 38, -1], [2, 38, -1], [20, 20, 119.5]],
                     dtype=float)  # fmt: skip
    faces = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    cage = Cage(verts, faces)
    root = 16
    n_layers = 8  # (121 - 1) / 16, rounded up
    k = np.arange(geo.n_points) // (40 * 40)  # VTK order: k slowest
    inside = inside_cage(winding_number(geo.points(), cage.vertices, cage.faces))
    per_layer = np.bincount(np.minimum(k // root, n_layers - 1)[inside], minlength=n_layers)
    assert (np.diff(per_layer) < 0).all()  # the work is uneven: equal layer counts are not
    below = np.concatenate([[0], np.cumsum(per_layer)])
    for parts in (2, 3, 4):
        cuts = layer_shares(geo, cage, root, parts)
        assert cuts[0] == 0 and cuts[-1] == n_layers and (np.diff(cuts) >= 0).all()
        for r in range(1, parts):
            target = below[-1] * r / parts
            best = np.abs(below - target).min()
            assert abs(below[cuts[r]] - target) <= best + 0.02 * below[-1]
    # more parts than layers: some get none; every layer is somewhere
    many = layer_shares(geo, cage, root, 12)
    assert len(many) == 13 and many[-1] == n_layers and (np.diff(many) >= 0).all()
    # no voxel inside: equal numbers of layers
    far = Cage(verts + [0.0, 0.0, 1000.0], faces)
    np.testing.assert_array_equal(layer_shares(geo, far, root, 2), [0, 4, 8])


def test_equal_cuts_are_the_nearest_boundaries_to_equal_shares():
    """Against brute force: each cut is an item boundary nearest its share of the total."""
    rng = np.random.default_rng(7)
    for n, parts in ((1, 2), (5, 2), (40, 3), (200, 7), (3, 5)):
        weight = rng.exponential(size=n) * (rng.random(n) < 0.8)
        cuts = equal_cuts(weight, parts)
        below = np.concatenate([[0.0], np.cumsum(weight)])
        assert len(cuts) == parts + 1 and cuts[0] == 0 and cuts[-1] == n
        assert (np.diff(cuts) >= 0).all()
        for r in range(1, parts):
            target = below[-1] * r / parts
            assert abs(below[cuts[r]] - target) <= np.abs(below - target).min() + 1e-12
    np.testing.assert_array_equal(equal_cuts(np.zeros(6), 3), [0, 2, 4, 6])


def test_subcell_tests_hold_the_image_of_their_subcell(bend):
    """Each sub-cell's test of the pull-back: ``d`` is the linear pre-image estimate from
    the sub-cell's centre, ``G_s^-1 (y - f_s)`` (value and Jacobian from the lattice's
    polynomial), affine in the output index and shifted per axis; every point of the
    sub-cell within the volume's half-voxel border passes it, and the bound is tighter
    than the leaf's own (half its size, its rho and its margin)."""
    geo, _, _, vol = bend
    out = vol.output_geometry()
    lat = vol.lattice
    tests = subcell_tests(lat, out)
    assert tests.shape == (len(lat.leaf_size), SUBCELLS**3, 3, 5)
    rng = np.random.default_rng(7)
    leaves = rng.choice(len(lat.leaf_size), size=min(60, len(lat.leaf_size)), replace=False)
    to_index = np.linalg.inv(out.index_to_world)
    last = np.asarray(geo.dimensions) - 1.0
    tighter = tried = 0
    for n in leaves:
        h = float(lat.leaf_size[n])
        for s in range(SUBCELLS**3):
            corner = np.array([s % SUBCELLS, (s // SUBCELLS) % SUBCELLS, s // SUBCELLS**2])
            lo = lat.leaf_origin[n] + corner * h / SUBCELLS
            centre = lo + 0.5 * h / SUBCELLS
            # points inside the sub-cell (kept off its faces: a face is shared with the next
            # leaf, whose polynomial the lattice evaluates there) and the volume's border
            u = lo + (0.02 + 0.96 * rng.random((40, 3))) * h / SUBCELLS
            u = u[((u >= -0.5) & (u <= last + 0.5)).all(axis=1)]
            if not len(u):
                continue
            tried += 1
            f_c, g_c = lat.evaluate(centre[None], gradient=True)
            y = lat.evaluate(u)
            ijk = (y - out.origin) @ to_index.T
            c, p, q, slope, bound = tests[n, s].T
            d = c + ijk[:, 1:2] * p + ijk[:, 2:3] * q + ijk[:, 0:1] * slope
            shift = d - (y - f_c) @ np.linalg.inv(g_c[0]).T
            np.testing.assert_allclose(shift - shift[0], 0.0, atol=1e-8 * h)
            assert (np.abs(d) <= bound).all()
            tighter += (bound < 0.5 * h + lat.rho[n] + lat.margins()[n]).all()
    assert tried > 0 and tighter == tried


def test_pull_back_pairs_count_every_voxels_candidate_leaves(bend):
    """Per output plane, the (voxel, leaf) pairs that pulling back tries: against a count
    volume incremented over every leaf's candidate box; leaves split among callers add up,
    and the shares cut from them are equal shares of that work. With the leaves' spans,
    the cuts give the smallest largest share of work or of leaves (brute force)."""
    geo, _, _, vol = bend
    out = vol.output_geometry()
    lo, hi = vol.lattice.candidate_boxes(out)
    count = np.zeros(out.dimensions[::-1], dtype=np.int64)  # (k, j, i)
    for a, b in zip(lo, hi, strict=True):
        a, b = np.maximum(a, 0), b + 1
        count[a[2] : b[2], a[1] : b[1], a[0] : b[0]] += 1
    per_plane = count.sum(axis=(1, 2))
    pairs = vol.pull_back_pairs(out)
    assert pairs.shape == (out.dimensions[2],) and per_plane.sum() > out.n_points
    np.testing.assert_array_equal(pairs, per_plane)
    leaves = np.arange(len(lo))
    split = vol.pull_back_pairs(out, leaves[::2]) + vol.pull_back_pairs(out, leaves[1::2])
    np.testing.assert_array_equal(split, per_plane)
    cuts = pull_back_shares(pairs, out, 3)
    work = per_plane + 0.2 * out.dimensions[0] * out.dimensions[1]
    shares = [work[cuts[r] : cuts[r + 1]].sum() for r in range(3)]
    assert max(shares) - min(shares) <= 2 * work.max()
    # the leaves each run of planes needs: against the boxes reaching it, counted leaf by
    # leaf; split leaves add up
    spans = vol.pull_back_spans(out)
    split = [vol.pull_back_spans(out, leaves[::2]), vol.pull_back_spans(out, leaves[1::2])]
    for a, b in zip(spans, np.add(*split), strict=True):
        np.testing.assert_array_equal(a, b)
    nz = out.dimensions[2]
    reach = np.all((lo <= np.asarray(out.dimensions) - 1) & (hi >= 0), axis=1)

    def needed(a, b):  # leaves whose boxes reach planes a..b-1
        return int((reach & (lo[:, 2] <= b - 1) & (hi[:, 2] >= a)).sum())

    starts, ends = spans
    for a, b in ((0, nz), (3, 9), (nz // 2, nz), (5, 6)):
        assert np.cumsum(starts)[b - 1] - ends[:a].sum() == needed(a, b)

    # cuts by work and leaves: the smallest largest share of the two, by brute force; with
    # work shared evenly besides the planes (a build), a part's share of the work counts
    # its share of that too
    def largest(cuts, shared):
        parts = len(cuts) - 1
        return max(max((shared / parts + work[a:b].sum()) / (shared + work.sum()),
                       needed(a, b) / reach.sum())
                   for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a)  # fmt: skip

    for parts in (2, 3):
        for shared in (0.0, 2.0 * work.sum()):
            cuts = pull_back_shares(pairs, out, parts, spans, shared)
            assert cuts[0] == 0 and cuts[-1] == nz and (np.diff(cuts) >= 0).all()
            best = min(largest([0, *c, nz], shared)
                       for c in itertools.combinations(range(1, nz), parts - 1))  # fmt: skip
            assert largest(cuts, shared) == pytest.approx(best, rel=1e-9)

    # work in the first planes, leaves in the last: counting the work every part does
    # alike (the build), the cuts lean on the leaves
    line = ImageGeometry((0, 0, 0), (1, 1, 1), (1, 1, 6))
    per_plane = np.array([1.0, 1, 1, 5, 5, 5])  # leaves, each in one plane
    spans = (per_plane, per_plane)
    pairs = np.array([10.0, 10, 1, 1, 1, 1])
    np.testing.assert_array_equal(pull_back_shares(pairs, line, 2, spans), [0, 3, 6])
    np.testing.assert_array_equal(pull_back_shares(pairs, line, 2, spans, 30.0), [0, 4, 6])
    assert lattice_build_work(2000, 754) == 2 * lattice_build_work(1000, 754) > 0


def test_resampling_boxes_into_one_set_of_arrays_equals_resampling_it_whole(bend):
    """``out``: runs of planes resampled into views of one piece's arrays fill them as
    resampling the piece does; arrays that do not fit are refused."""
    geo, _, _, vol = bend
    values = np.asarray(_smooth_volume(geo.dimensions, geo.spacing, geo.origin)["density"])
    labels = (np.arange(geo.n_points) % 7).astype(np.int16)
    arrays = {"v": values, "labels": labels}
    out = vol.output_geometry()
    nx, ny, nz = out.dimensions
    piece = [0, nx - 1, 0, ny - 1, 3, nz - 4]
    ref = vol.resample(arrays, out, box=piece)
    n = len(ref.valid)
    target = Resampled(None, {"v": np.full(n, -1.0), "labels": np.full(n, -1, np.int16)},
                       np.full(n, 7, np.uint8), np.full(n, 7, np.uint8))  # fmt: skip
    plane = nx * ny
    cut = nz // 2
    for k0, k1 in ((3, cut), (cut + 1, nz - 4)):
        rows = slice((k0 - 3) * plane, (k1 - 2) * plane)
        view = Resampled(None, {k: a[rows] for k, a in target.arrays.items()},
                         target.valid[rows], target.foldover[rows])  # fmt: skip
        got = vol.resample(arrays, out, box=[0, nx - 1, 0, ny - 1, k0, k1], out=view)
        assert got is view and got.counts["voxels"] == (k1 - k0 + 1) * plane
    for name in arrays:
        np.testing.assert_array_equal(target.arrays[name], ref.arrays[name])
    np.testing.assert_array_equal(target.valid, ref.valid)
    np.testing.assert_array_equal(target.foldover, ref.foldover)
    assert ref.counts["valid"] > 0.3 * n
    wrong = Resampled(None, {"v": np.zeros(n, np.float32), "labels": labels[:n]},
                      np.zeros(n, np.uint8), np.zeros(n, np.uint8))  # fmt: skip
    with pytest.raises(ValueError, match="out array 'v' is float32"):
        vol.resample(arrays, out, box=piece, out=wrong)


def test_an_unknown_interpolation_is_refused_naming_the_kinds():
    """The engine and the resample filter refuse an interpolation they do not have, with
    the kinds they do have."""
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (8, 8, 8))
    hm = _random_bend(_cage_around((-1, -1, -1), (8, 8, 8), 0.0), 0.002, seed=1)
    vol = VolumeDeformation(hm, geo)
    with pytest.raises(ValueError, match="linear.*nearest.*cubic.*'spline'"):
        vol.resample({"v": np.zeros(geo.n_points)}, interpolation="spline")
    flt = HarmonicResampleFilter()
    with pytest.raises(ValueError, match="linear.*nearest.*cubic.*'spline'"):
        flt.SetInterpolation("spline")
    flt.SetInterpolation("nearest")
    assert flt.GetInterpolation() == "nearest"
