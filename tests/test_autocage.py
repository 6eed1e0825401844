"""Automatic cages: validity, enclosure, face budget, separation, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage, data_path

from vhm_viz.autocage import voxel as vx
from vhm_viz.autocage.meshcheck import edge_problems
from vhm_viz.autocage.proximity import NearDistance, grid_signed_distance
from vhm_viz.autocage.simplify import simplify
from vhm_viz.autocage.voxel_surface import cage_surface, count_cage_faces, triangulate_polygon
from vhm_viz.core.basis import winding_number
from vhm_viz.core.geometry import signed_volume

pv = pytest.importorskip("pyvista")

from vhm_viz.autocage import auto_anchors, auto_cage, otsu_threshold  # noqa: E402
from vhm_viz.core.cage import Cage, validate_cage  # noqa: E402


# ------------------------------------------------------------------ pure voxel core
def test_union_of_cubes_surface_is_a_closed_manifold_with_the_voxel_volume():
    rng = np.random.default_rng(3)
    for _ in range(25):
        n = int(rng.integers(3, 8))
        occ = np.zeros((n + 4,) * 3, dtype=bool)
        occ[2:-2, 2:-2, 2:-2] = rng.random((n, n, n)) < rng.uniform(0.15, 0.85)
        solid = vx.make_well_composed(occ)
        assert (solid | occ).sum() == solid.sum()  # only adds voxels
        if not solid.any():
            continue
        V, F = cage_surface(solid)
        assert not any(edge_problems(F).values())
        # merged coplanar faces: exactly the union's volume, and fewer faces than squares
        assert signed_volume(V.astype(float), F) == pytest.approx(solid.sum(), abs=1e-9)
        assert len(F) == count_cage_faces(solid)
        Cage(V.astype(float), F)  # full validation, self-intersection included


def test_coplanar_merging_gives_a_box_12_triangles():
    occ = np.zeros((9, 9, 9), dtype=bool)
    occ[2:7, 2:6, 2:5] = True
    V, F = cage_surface(vx.make_well_composed(occ))
    assert len(F) == 12 and len(V) == 8


def test_ear_clipping_keeps_collinear_vertices_and_never_degenerates():
    # an L shape with extra collinear points on its sides (T-junctions)
    uv = np.array([[0, 0], [1, 0], [2, 0], [3, 0], [3, 1], [1, 1], [1, 2], [1, 3], [0, 3], [0, 1]])
    t = triangulate_polygon(uv)
    assert len(t) == len(uv) - 2
    p = uv[t]
    cross = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (
        p[:, 2, 0] - p[:, 0, 0]
    )
    assert (cross > 0).all()
    assert cross.sum() / 2 == 3 + 2  # the L's area


def test_near_signed_distance_matches_brute_force():
    v, f = box_cage((0, 0, 0), (1, 2, 3), 2)
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.5, 3.5, size=(2000, 3))
    sd, face = grid_signed_distance(NearDistance(v, f), p, radius=0.4)
    # brute force: distance to the box and inside test
    lo, hi = np.zeros(3), np.array([1.0, 2.0, 3.0])
    inside = ((p > lo) & (p < hi)).all(axis=1)
    out_d = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0), axis=1)
    in_d = np.minimum(p - lo, hi - p).min(axis=1)
    ref = np.where(inside, -in_d, out_d)
    near = np.abs(ref) <= 0.4
    assert np.array_equal(np.isfinite(sd), near)
    np.testing.assert_allclose(sd[near], ref[near], atol=1e-12)


def _outward_sphere(resolution):
    """A triangulated unit sphere, (vertices, faces) outward oriented."""
    sphere = pv.Sphere(radius=1.0, theta_resolution=resolution, phi_resolution=resolution)
    sphere = sphere.triangulate().clean()
    V = np.asarray(sphere.points, dtype=float)
    F = np.asarray(sphere.faces).reshape(-1, 4)[:, 1:]
    return V, (F[:, ::-1] if signed_volume(V, F) < 0 else F)


def test_simplify_keeps_a_closed_manifold_and_stays_outside():
    V, F = _outward_sphere(20)
    V2, F2 = simplify(V, F, 100, outside=True)
    assert len(F2) <= 100
    assert not any(edge_problems(F2).values())
    assert signed_volume(V2, F2) > 0
    # the bounding condition keeps the coarse sphere (nearly) outside the fine one
    assert np.linalg.norm(V2, axis=1).min() > 0.97


def test_compiled_simplify_matches_the_python_reference():
    # a bumpy sphere (no symmetric ties in the collapse order)
    V, F = _outward_sphere(16)
    V = V * (1 + 0.1 * np.random.default_rng(5).random((len(V), 1)))
    a = simplify(V, F, 80)
    b = simplify(V, F, 80, backend="python")
    # same algorithm, same heap order: the same collapses (up to rounding)
    assert np.array_equal(a[1], b[1])
    np.testing.assert_allclose(a[0], b[0], atol=1e-12)
    # with the bounding condition rounding can flip knife-edge feasibility tests, so only
    # the guarantees are compared
    for V2, F2 in (
        simplify(V, F, 80, outside=True),
        simplify(V, F, 80, outside=True, backend="python"),
    ):
        assert len(F2) <= 80
        assert not any(edge_problems(F2).values())
        assert signed_volume(V2, F2) > 0
    with pytest.raises(ValueError, match="backend"):
        simplify(V, F, 80, backend="fortran")


# ------------------------------------------------------------------ Otsu's threshold
def _otsu_brute_force(values, bins=256):
    """The split of the histogram with the largest between-class variance, split by split."""
    hist, edges = np.histogram(values, bins=bins)
    centres = 0.5 * (edges[1:] + edges[:-1])
    best, best_edge = -1.0, None
    for k in range(bins):
        low, high = hist[: k + 1], hist[k + 1 :]
        w0, w1 = low.sum(), high.sum()
        if w0 == 0 or w1 == 0:
            between = 0.0
        else:
            mu0 = (low * centres[: k + 1]).sum() / w0
            mu1 = (high * centres[k + 1 :]).sum() / w1
            between = w0 * w1 * (mu0 - mu1) ** 2
        if between > best:
            best, best_edge = between, edges[k + 1]
    return float(best_edge)


def test_otsu_threshold_maximises_the_between_class_variance():
    rng = np.random.default_rng(3)
    dark = rng.normal(20.0, 4.0, 5_000)
    bright = rng.normal(70.0, 9.0, 2_000)
    values = np.concatenate([dark, bright])
    t = otsu_threshold(values)
    assert t == pytest.approx(_otsu_brute_force(values), rel=1e-12)
    # it separates the two populations
    assert np.mean(dark > t) < 0.01 and np.mean(bright <= t) < 0.01
    # non-finite samples are ignored, the shape of the array does not matter
    noisy = np.concatenate([values, [np.nan, np.inf, -np.inf]]).reshape(-1, 1)
    assert otsu_threshold(noisy) == t
    skewed = rng.gamma(2.0, 3.0, 4_000).astype(np.float32)
    assert otsu_threshold(skewed) == pytest.approx(_otsu_brute_force(skewed), rel=1e-6)


# ------------------------------------------------------------------ models
def _check(cage, report, points, max_faces):
    v, f, _ = validate_cage(cage.vertices, cage.faces)  # independent re-validation
    assert cage.n_faces <= max_faces
    assert report.enclosed and report.clearance > 0
    rng = np.random.default_rng(0)
    sel = points if len(points) <= 20_000 else points[rng.choice(len(points), 20_000, False)]
    assert cage.contains(sel).all()  # winding number (the project's basis), every point
    assert cage.winding_number(sel).min() > 0.999


SURFACES = [
    ("hand", "hand.obj"),
    ("beast", "beast.obj"),
    ("horse", "horse.obj"),
    ("armadillo", "armadillo_43k.obj"),
]


@pytest.mark.data
@pytest.mark.parametrize("folder,name", SURFACES)
def test_surface_models(folder, name):
    mesh = pv.read(data_path(folder, name))
    cage, report = auto_cage(mesh, return_report=True)
    _check(cage, report, np.asarray(mesh.points), 500)
    # the requested 1% clearance, no retry (the hand's fingers needed 2% before)
    assert report.method == "offset" and report.offset_used == report.offset


@pytest.mark.slow
@pytest.mark.data
def test_armadillo_173k():
    mesh = pv.read(data_path("armadillo", "armadillo_173k.ply"))
    cage, report = auto_cage(mesh, return_report=True)
    _check(cage, report, np.asarray(mesh.points), 500)


@pytest.mark.data
def test_tet_mesh():
    meshio = pytest.importorskip("meshio")
    grid = pv.from_meshio(meshio.read(data_path("hand_tet", "hand.mesh")))
    cage, report = auto_cage(grid, max_faces=300, return_report=True)
    _check(cage, report, np.asarray(grid.points), 300)


@pytest.mark.data
def test_point_cloud_sampled_from_a_surface():
    mesh = pv.read(data_path("beast", "beast.obj")).triangulate()
    v = np.asarray(mesh.points)
    f = np.asarray(mesh.faces).reshape(-1, 4)[:, 1:]
    rng = np.random.default_rng(1)
    area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    pick = rng.choice(len(f), 20_000, p=area / area.sum())
    r = rng.random((20_000, 2))
    r[r.sum(1) > 1] = 1 - r[r.sum(1) > 1]
    a, b, c = v[f[pick, 0]], v[f[pick, 1]], v[f[pick, 2]]
    cloud = a + r[:, :1] * (b - a) + r[:, 1:] * (c - a)
    cage, report = auto_cage(cloud, max_faces=400, return_report=True)
    _check(cage, report, cloud, 400)


@pytest.mark.data
def test_volume_threshold_region_and_bounding_box():
    vol = pv.read(data_path("volumes", "headsq_64x64x93.vti"))
    cage, report = auto_cage(vol, threshold="otsu", max_faces=400, return_report=True)
    vals = np.asarray(vol.active_scalars)
    region = np.asarray(vol.points)[vals > otsu_threshold(vals)]
    _check(cage, report, region, 400)
    box = auto_cage(vol)
    assert box.n_faces == 12
    assert box.contains(np.asarray(vol.points)[::97]).all()


# ------------------------------------------------------------------ separation
def two_bars(gap=0.2, divisions=8):
    v1, f1 = box_cage((0, 0, 0), (1, 1, 5), divisions)
    v2, f2 = box_cage((1 + gap, 0, 0), (2 + gap, 1, 5), divisions)
    return np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)])


def gap_for(fraction):
    """The gap between the two bars that is ``fraction`` of the pair's box diagonal."""
    gap = fraction * np.sqrt(30.0)
    for _ in range(50):  # diagonal of (2 + gap) x 1 x 5
        gap = fraction * np.sqrt((2 + gap) ** 2 + 26.0)
    return gap


def mid_plane(gap, n=41):
    """Points on the plane halfway between the bars, over their whole facing sides."""
    gy, gz = np.meshgrid(np.linspace(0.0, 1.0, n // 4 + 1), np.linspace(0.0, 5.0, n))
    return np.stack([np.full(gy.size, 1 + 0.5 * gap), gy.ravel(), gz.ravel()], axis=1)


@pytest.fixture(scope="module")
def bars_cage():
    gap = gap_for(0.03)
    v, f = two_bars(gap)
    return v, f, gap, auto_cage((v, f), return_report=True)


@pytest.mark.parametrize("fraction", [0.03, 0.02, 0.012])
def test_bars_a_narrow_gap_apart_keep_the_gap_open(fraction):
    """Gaps down to the clearance (1% of the diagonal) stay open: mid-plane points outside."""
    gap = gap_for(fraction)
    v, f = two_bars(gap)
    cage, report = auto_cage((v, f), return_report=True)
    validate_cage(cage.vertices, cage.faces)
    assert cage.n_faces <= 500
    w = winding_number(mid_plane(gap), cage.vertices, cage.faces)  # independent check
    assert w.max() < 1e-6, f"gap of {fraction:.1%} of the diagonal enclosed"
    assert (winding_number(v, cage.vertices, cage.faces) > 1 - 1e-9).all()
    assert report.n_components == 2
    assert report.min_gap_kept == pytest.approx(gap, rel=1e-9)
    assert report.clearance <= gap / 3 * (1 + 1e-9)  # the clearance shrank in the gap


def test_bars_closer_than_the_clearance_may_share_a_shell():
    """The rule's other side: a gap below the clearance may be bridged, and is reported."""
    gap = gap_for(0.005)
    v, f = two_bars(gap)
    cage, report = auto_cage((v, f), return_report=True)
    assert report.n_components == 1
    assert report.bridged_gap == pytest.approx(gap, rel=1e-9)
    assert report.bridged_gap <= report.offset_used
    assert cage.contains(v).all()


def test_two_bars_are_not_bridged(bars_cage):
    v, f, gap, (cage, report) = bars_cage
    assert report.n_components == 2
    assert cage.n_faces <= 500
    assert not cage.contains(mid_plane(gap)).any()
    assert cage.contains(v).all()


def test_moving_one_bar_barely_moves_the_other(bars_cage):
    deformer = pytest.importorskip("vhm_viz.core.deformer")

    v, f, gap, (cage, _) = bars_cage
    diag = float(np.linalg.norm(np.ptp(v, axis=0)))
    half = len(v) // 2
    bar1, bar2 = v[:half], v[half:]
    x2 = 1.5 + gap
    pos = np.array([[0.5, 0.5, 0.05], [0.5, 0.5, 4.95], [x2, 0.5, 0.05], [x2, 0.5, 4.95]])
    tgt = pos.copy()
    tgt[1] += [-0.5, 0.8, -0.3]  # drag the top of bar 1; both bottoms and bar 2's top held

    def drift(c):
        anchors = auto_anchors((v, f), c, 24)
        d = deformer.Deformer(c, anchors)
        d.set_constraints(positions=pos, targets=tgt)
        d.solve(max_iterations=5000, tolerance=1e-9)
        moved1 = np.abs(d.bind(bar1).deform() - bar1).max()
        return np.abs(d.bind(bar2).deform() - bar2).max(), moved1

    auto2, auto1 = drift(cage)
    hi = (2.05 + gap, 1.05, 5.05)
    bridged2, _ = drift(Cage(*box_cage((-0.05, -0.05, -0.05), hi, 4)))
    assert auto1 > 0.5  # bar 1 really moved
    # the automatic cage has one shell per bar, and separate shells are separate domains
    # of the harmonic map: bar 2 stays put (the 1e-3 of the diagonal), while a
    # cage bridging the two bars drags bar 2 along
    assert auto2 < 1e-3 * diag
    assert bridged2 > 100 * max(auto2, 1e-6)


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    "data,match",
    [
        (np.array([[1.0, 2.0, 3.0]]), "single point"),
        (np.c_[np.random.default_rng(0).random((50, 2)), np.zeros(50)], "coplanar"),
        (np.zeros((0, 3)), "empty"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.nan]]), "NaN"),
        (np.c_[np.linspace(0, 1, 10), np.linspace(0, 2, 10), np.linspace(0, 3, 10)], "collinear"),
    ],
)
def test_degenerate_inputs_raise_clear_errors(data, match):
    with pytest.raises(ValueError, match=match):
        auto_cage(data)


def test_empty_mesh_and_bad_arguments():
    with pytest.raises(ValueError, match="empty"):
        auto_cage(pv.PolyData())
    v, f = box_cage()
    with pytest.raises(ValueError, match="max_faces"):
        auto_cage((v, f), max_faces=8)
    with pytest.raises(ValueError, match="offset"):
        auto_cage((v, f), offset=-1.0)
    with pytest.raises(ValueError, match="method"):
        auto_cage((v, f), method="magic")


def test_voxel_method_is_valid_and_respects_the_budget():
    v, f = two_bars()
    cage, report = auto_cage((v, f), method="voxel", max_faces=100, return_report=True)
    assert report.method == "voxel" and cage.n_faces <= 100
    assert report.clearance >= report.offset * 0.999  # the voxel cage keeps the full offset
    assert cage.contains(v).all()


def _cube_cloud():
    """Points on a unit cube's faces: a shape whose diagonal is sqrt(3) times its side."""
    g = np.linspace(0.0, 1.0, 9)
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return grid[(np.isclose(grid, 0) | np.isclose(grid, 1)).any(axis=1)]


@pytest.mark.parametrize("offset", [0.0, -1.0, 1.8, 1e5, 1e9, np.inf])
def test_an_offset_past_the_diagonal_is_refused_before_any_grid(offset):
    # the cube's diagonal is sqrt(3): farther out the cage follows nothing of the shape
    # (and its grid, which spans the clearance, grew to petabytes)
    from vhm_viz.core.errors import SettingError

    with pytest.raises(SettingError, match=r"at most the data's bounding-box diagonal, 1\.732"):
        auto_cage(_cube_cloud(), offset=offset)


def test_a_large_offset_keeps_the_grid_within_its_cap():
    # at the largest offset, the diagonal, the grid across the cage stays within the
    # default extraction grid's 115 voxels (it grew with the offset)
    pts = _cube_cloud()
    diag = float(np.sqrt(3.0))
    cage, report = auto_cage(pts, offset=diag, method="offset", return_report=True)
    assert cage.contains(pts).all() and report.clearance >= 0.5 * diag
    assert np.ptp(cage.vertices, axis=0).max() / report.voxel_size <= 116


def test_volume_options_are_refused_for_other_inputs():
    from vhm_viz.core.errors import SettingError

    cube = pv.Cube().triangulate()
    for data, kind in ((_cube_cloud(), "point cloud"), (cube, "surface")):
        with pytest.raises(SettingError, match=f"threshold applies to volumes.*a {kind}"):
            auto_cage(data, threshold=5)
        with pytest.raises(SettingError, match=f"threshold applies to volumes.*a {kind}"):
            auto_anchors(data, Cage(*box_cage((-2, -2, -2), (2, 2, 2))), 4, threshold=5)
    with pytest.raises(SettingError, match="scalars applies to volumes"):
        auto_cage(cube, scalars="v")
