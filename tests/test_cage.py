"""Tests for the cage: validation, properties, I/O and point containment."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from vhm_viz.core.cage import Cage, self_intersections
from vhm_viz.core.errors import CageError
from vhm_viz.io import cage_from_dataset, cage_to_polydata, read_cage

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")

# unit cube, outward triangles
BOX_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=float,
)
BOX_Q = np.array(
    [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
)
BOX_F = np.concatenate([BOX_Q[:, [0, 1, 2]], BOX_Q[:, [0, 2, 3]]])


def box(offset=(0.0, 0.0, 0.0), scale=1.0):
    return BOX_V * scale + np.asarray(offset, dtype=float), BOX_F.copy()


def raises(v, f, match):
    with pytest.raises(CageError, match=match) as info:
        Cage(v, f)
    return info.value


def canonical(cage):
    """Set of triangles as sorted coordinate tuples, with orientation (rotation-invariant)."""
    out = set()
    for t in cage.faces:
        corners = [tuple(np.round(cage.vertices[i], 12)) for i in t]
        k = corners.index(min(corners))
        out.add(tuple(corners[k:] + corners[:k]))
    return out


# ---------------------------------------------------------------------------- valid cages


def test_box_properties():
    v, f = box()
    c = Cage(v, f)
    assert c.n_vertices == 8 and c.n_faces == 12
    assert np.allclose(c.bounds, [[0, 0, 0], [1, 1, 1]])
    assert c.diagonal == pytest.approx(np.sqrt(3))
    assert np.allclose(c.areas, 0.5)
    assert np.allclose(np.linalg.norm(c.face_normals, axis=1), 1)
    # outward: normal points away from the centre
    assert np.all(np.einsum("ij,ij->i", c.face_normals, c.face_centroids - 0.5) > 0)
    assert c.volume == pytest.approx(1.0)
    assert not c.flipped
    for a in (c.vertices, c.faces, c.face_normals, c.areas, c.bounds):
        assert not a.flags.writeable
        with pytest.raises(ValueError):
            a[0] = 0
    vf = c.vertex_faces
    assert vf.shape == (8, 12)
    for vi in range(8):
        expected = np.flatnonzero((f == vi).any(axis=1))
        assert np.array_equal(c.faces_of_vertex(vi), expected)
        assert np.array_equal(vf[vi].indices, expected)
    assert np.array_equal(vf.sum(axis=0).A1, np.full(12, 3))
    assert len(c.edges) == 18
    assert hash(c) == hash(Cage(v, f)) and c == Cage(v, f)


def test_input_not_modified_and_copied():
    v, f = box()
    c = Cage(v, f)
    v[0] = 99
    assert c.vertices[0, 0] == 0


def test_integral_float_faces_accepted():
    v, f = box()
    assert Cage(v, f.astype(float)).n_faces == 12


def test_inward_cage_is_flipped_with_warning():
    v, f = box()
    with pytest.warns(UserWarning, match="inward"):
        c = Cage(v, f[:, [0, 2, 1]])
    assert c.flipped
    assert np.array_equal(c.faces, f)
    assert c.volume > 0
    w = c.winding_number([[0.5, 0.5, 0.5], [0.2, 0.7, 0.1], [2, 2, 2]])
    assert np.allclose(w, [1, 1, 0], atol=1e-12)


def test_unreferenced_vertex_warns_and_is_kept():
    v, f = box()
    v = np.vstack([v, [0.5, 0.5, 0.5]])
    with pytest.warns(UserWarning, match=r"used by no face \(vertices 8\)"):
        c = Cage(v, f)
    assert c.n_vertices == 9
    assert c.vertex_faces[8].nnz == 0


def test_two_disjoint_boxes_and_hollow_are_valid():
    v1, f1 = box()
    v2, f2 = box(offset=(3, 0, 0))
    c = Cage(np.vstack([v1, v2]), np.vstack([f1, f2 + 8]))
    assert c.volume == pytest.approx(2)
    # hollow: inner box oriented inward
    v3, f3 = box(offset=(0.25, 0.25, 0.25), scale=0.5)
    c = Cage(np.vstack([v1, v3]), np.vstack([f1, f3[:, [0, 2, 1]] + 8]))
    assert c.volume == pytest.approx(1 - 0.125)
    assert np.array_equal(c.contains([[0.1, 0.1, 0.1], [0.5, 0.5, 0.5]]), [True, False])


def test_boxes_pinched_at_a_vertex_are_accepted():
    # two boxes sharing one corner: manifold edges, no improper intersection
    v1, f1 = box()
    v2, f2 = box(offset=(1, 1, 1))
    remap = np.arange(8) + 7
    remap[0] = 6
    c = Cage(np.vstack([v1, v2[1:]]), np.vstack([f1, remap[f2]]))
    assert c.n_vertices == 15 and c.volume == pytest.approx(2)


# ---------------------------------------------------------------------------- errors


def test_wrong_shapes_and_dtypes():
    v, f = box()
    raises(v[:, :2], f, r"vertices must have shape \(n, 3\)")
    raises(v, f[:, :2], r"faces must have shape \(m, 3\)")
    raises(v, f + 0.5, "integer")
    raises(v.astype(str), f, "real numbers")


def test_nan_coordinate():
    v, f = box()
    v[3, 1] = np.nan
    v[6, 0] = np.inf
    e = raises(v, f, r"non-finite.*vertices 3, 6")
    assert list(e.indices) == [3, 6]


def test_index_out_of_range():
    v, f = box()
    f[5] = [0, 1, 99]
    f[7, 0] = -1
    e = raises(v, f, r"outside \[0, 8\).*faces 5, 7")
    assert list(e.indices) == [5, 7]


def test_too_few_vertices():
    raises(np.eye(3), [[0, 1, 2], [0, 2, 1]], "at least 4 vertices")


def test_zero_area_face_repeated_index():
    v, f = box()
    f[4] = [1, 1, 2]
    e = raises(v, f, r"degenerate.*faces 4\b")
    assert list(e.indices) == [4]


def test_zero_area_face_collinear():
    # split face (0, 3, 2)'s neighbourhood: vertex 8 on edge (0, 1), with a sliver (0, 1, 8)
    v, f = box()
    v = np.vstack([v, [0.5, 0, 0]])
    # faces containing edge 0->1 direction: (0, 1, 5) [index 8]; replace by two halves
    k = int(np.flatnonzero((f == [0, 1, 5]).all(axis=1))[0])
    f = np.vstack([np.delete(f, k, axis=0), [[0, 8, 5], [8, 1, 5], [1, 0, 8]]])
    e = raises(v, f, r"degenerate.*faces 13\b")
    assert list(e.indices) == [13]


def test_duplicate_face():
    v, f = box()
    f = np.vstack([f, f[2][[1, 2, 0]]])
    e = raises(v, f, r"duplicate faces.*faces 2, 12")
    assert list(e.indices) == [2, 12]


def test_open_box():
    v, f = box()
    removed = f[3]
    e = raises(v, np.delete(f, 3, axis=0), r"not closed: 3 boundary edges")
    expected = sorted(tuple(sorted(p)) for p in [removed[[0, 1]], removed[[1, 2]], removed[[2, 0]]])
    assert sorted(map(tuple, e.indices.tolist())) == expected
    for a, b in expected:
        assert f"({a}, {b})" in str(e)


def test_non_manifold_two_boxes_sharing_an_edge():
    v1, f1 = box()
    v2, f2 = box(offset=(1, 1, 0))
    # box 2's corners 0 and 4 coincide with box 1's corners 2 and 6: merge them
    remap = np.arange(8) + 8
    remap[0], remap[4] = 2, 6
    e = raises(np.vstack([v1, v2]), np.vstack([f1, remap[f2]]), r"non-manifold: 1 edges")
    assert e.indices.tolist() == [[2, 6]]
    assert "(2, 6)" in str(e)


def test_non_manifold_fin():
    # a reversed copy of a face glued onto the box: edges become 3-valent
    v, f = box()
    e = raises(v, np.vstack([f, f[0][::-1]]), r"non-manifold.*fins")
    assert len(e.indices) == 3


def test_flipped_face():
    v, f = box()
    f[7] = f[7][[0, 2, 1]]
    e = raises(v, f, r"inconsistent orientation: faces 7 are oriented")
    assert list(e.indices) == [7]


def test_flipped_faces_majority_reported():
    v, f = box()
    f[[1, 7]] = f[[1, 7]][:, [0, 2, 1]]
    e = raises(v, f, r"inconsistent orientation: faces 1, 7 ")
    assert list(e.indices) == [1, 7]


def test_vertex_pushed_through_opposite_face():
    v, f = box()
    v[6] = [0.5, 0.4, -0.5]  # the top corner goes down through the bottom face
    e = raises(v, f, r"self-intersects")
    pairs = e.indices
    assert pairs.ndim == 2 and pairs.shape[1] == 2
    moved = (f == 6).any(axis=1)
    bottom = np.all(v[f][:, :, 2] == 0, axis=1)
    assert all(moved[a] or moved[b] for a, b in pairs)
    assert any(bottom[a] or bottom[b] for a, b in pairs)
    assert f"({pairs[0, 0]}, {pairs[0, 1]})" in str(e)


def test_two_overlapping_boxes_intersect():
    v1, f1 = box()
    v2, f2 = box(offset=(0.5, 0.5, 0.5))
    e = raises(np.vstack([v1, v2]), np.vstack([f1, f2 + 8]), "self-intersects")
    assert np.all((e.indices[:, 0] < 12) & (e.indices[:, 1] >= 12))


def test_touching_boxes_intersect():
    # disjoint vertex sets, faces in contact (x = 1 plane): not an embedded cage
    v1, f1 = box()
    v2, f2 = box(offset=(1, 0.2, 0.2), scale=0.5)
    raises(np.vstack([v1, v2]), np.vstack([f1, f2 + 8]), "self-intersects")


def test_folded_adjacent_faces():
    # a flat square pyramid's apex pushed onto the base plane, inside: the side faces fold
    # onto the base faces (coplanar overlap of faces sharing an edge or a vertex)
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 0.0]])
    f = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    assert len(self_intersections(v, f)) > 0


def test_nested_boxes_same_orientation():
    v1, f1 = box()
    v2, f2 = box(offset=(0.25, 0.25, 0.25), scale=0.5)
    e = raises(np.vstack([v1, v2]), np.vstack([f1, f2 + 8]), "nested")
    assert set(e.indices.tolist()) == set(range(12, 24))


def test_check_order_boundary_before_self_intersection():
    v, f = box()
    v[6] = [0.5, 0.4, -0.5]
    raises(v, np.delete(f, 0, axis=0), "not closed")


# ---------------------------------------------------------------------------- brute force


def _orient(a, b, c, d):
    """Sign of the volume of the tetrahedron (a, b, c, d), vectorised over leading axes."""
    return np.sign(np.einsum("...i,...i->...", np.cross(b - a, c - a), d - a))


def _segment_crosses_triangle(p, q, a, b, c):
    """Whether segments p-q cross triangles (a, b, c) in their interiors (general position:
    no endpoint on the triangle's plane, no touching), by signed volumes only."""
    s1, s2 = _orient(a, b, c, p), _orient(a, b, c, q)
    t1, t2, t3 = _orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)
    return (s1 * s2 < 0) & (t1 == t2) & (t2 == t3) & (t1 != 0)


def _brute_force_self_intersections(v, f):
    """Every pair of faces tested (no sweep and prune): faces sharing no vertex intersect if
    an edge of one crosses the other, faces sharing one vertex if the edge opposite the
    shared vertex crosses the other face (general position, as real cages are)."""
    m = len(f)
    i, j = np.triu_indices(m, k=1)
    # all pairs' bounding boxes compared (disjoint boxes cannot intersect); no sweep
    lo, hi = v[f].min(axis=1), v[f].max(axis=1)
    near = ((lo[i] <= hi[j]) & (lo[j] <= hi[i])).all(axis=1)
    i, j = i[near], j[near]
    fi, fj = f[i], f[j]
    shared = (fi[:, :, None] == fj[:, None, :]).sum(axis=(1, 2))
    hit = np.zeros(len(i), dtype=bool)
    for src, dst in ((fi, fj), (fj, fi)):
        a, b, c = (v[dst[:, k]] for k in range(3))
        for k in range(3):
            e0, e1 = src[:, k], src[:, (k + 1) % 3]
            # edges touching the other face (at a shared vertex) cannot cross it improperly
            free = ~(e0[:, None] == dst).any(axis=1) & ~(e1[:, None] == dst).any(axis=1)
            usable = (shared <= 1) & free
            hit |= usable & _segment_crosses_triangle(v[e0], v[e1], a, b, c)
    pairs = np.stack([i[hit], j[hit]], axis=1)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _sphere(nsub):
    import pyvista as pv

    s = pv.Icosphere(nsub=nsub)
    return np.asarray(s.points), np.asarray(s.regular_faces)


@pytest.mark.parametrize("nsub", [2, 3])  # 320 and 1280 faces
def test_self_intersections_equal_brute_force_on_spheres(nsub):
    v, f = _sphere(nsub)
    assert len(_brute_force_self_intersections(v, f)) == 0
    assert self_intersections(v, f).shape == (0, 2)
    c = Cage(v, f)  # accepted: no false positive on a fine, nearly flat mesh
    assert not c.flipped and c.n_faces == len(f)
    # push a few vertices through the far side: the sweep must find exactly the crossings
    bad = v.copy()
    rng = np.random.default_rng(nsub)
    for k in rng.choice(len(v), 3, replace=False):
        bad[k] *= -0.2 - 1.2 * rng.random()
    ref = _brute_force_self_intersections(bad, f)
    assert len(ref) > 10
    np.testing.assert_array_equal(self_intersections(bad, f), ref)
    with pytest.raises(CageError, match=f"self-intersects: {len(ref)} pairs"):
        Cage(bad, f)


# ---------------------------------------------------------------------------- contains


def test_contains_near_faces():
    c = Cage(*box())
    eps = 1e-9
    rng = np.random.default_rng(0)
    pts_in, pts_out = [], []
    for axis in range(3):
        for side in (0.0, 1.0):
            p = rng.uniform(0.05, 0.95, (5, 3))
            inward = eps if side == 0.0 else -eps
            q = p.copy()
            q[:, axis] = side + inward
            pts_in.append(q)
            q = p.copy()
            q[:, axis] = side - inward
            pts_out.append(q)
    pts_in, pts_out = np.vstack(pts_in), np.vstack(pts_out)
    assert c.contains(pts_in).all()
    assert not c.contains(pts_out).any()
    # near an edge and a corner
    assert c.contains([[eps, eps, 0.5], [eps, eps, eps]]).all()
    assert not c.contains([[-eps, -eps, 0.5], [-eps, -eps, -eps]]).any()
    # on the surface: winding number 1/2, counted as inside
    assert c.contains([[0.5, 0.5, 0.0]]).all()
    assert c.contains(np.array([0.5, 0.5, 0.5])).shape == (1,)


# ---------------------------------------------------------------------------- I/O


def _pv_box():
    import pyvista as pv

    return pv.PolyData.from_regular_faces(BOX_V, BOX_F)


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "vtp", "vtk"])
def test_from_file_round_trip_pyvista(tmp_path, ext):
    path = tmp_path / f"box.{ext}"
    _pv_box().save(str(path))
    c = read_cage(path)
    ref = Cage(BOX_V, BOX_F)
    assert isinstance(c, Cage)
    assert c.n_faces == 12 and c.n_vertices == 8
    if ext == "stl":
        assert canonical(c) == canonical(ref)  # STL renumbers vertices
    else:
        assert np.allclose(c.vertices, ref.vertices)
        assert np.array_equal(c.faces, ref.faces)


def test_from_file_off_by_hand(tmp_path):
    path = tmp_path / "box.off"
    lines = ["OFF", "# a box", f"{len(BOX_V)} {len(BOX_F)} 0"]
    lines += [" ".join(map(str, p)) for p in BOX_V]
    lines += ["3 " + " ".join(map(str, t)) for t in BOX_F]
    path.write_text("\n".join(lines) + "\n")
    c = read_cage(path)
    assert np.array_equal(c.faces, BOX_F) and np.allclose(c.vertices, BOX_V)
    # quads in OFF as well
    lines = ["OFF", f"{len(BOX_V)} {len(BOX_Q)} 0"]
    lines += [" ".join(map(str, p)) for p in BOX_V]
    lines += ["4 " + " ".join(map(str, q)) for q in BOX_Q]
    path.write_text("\n".join(lines) + "\n")
    assert canonical(read_cage(path)) == canonical(Cage(BOX_V, BOX_F))


def test_from_file_quad_and_mixed_obj(tmp_path):
    path = tmp_path / "quads.obj"
    lines = [f"v {x} {y} {z}" for x, y, z in BOX_V]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}/1" for i in q) for q in BOX_Q[:4]]
    # mixed: the last two quads as triangles, one with negative (relative) indices
    lines += ["f " + " ".join(str(i + 1) for i in t) for t in BOX_F[[4, 10]]]
    lines += ["f " + " ".join(str(i - 8) for i in t) for t in BOX_F[[5, 11]]]
    path.write_text("\n".join(lines) + "\n")
    c = read_cage(path)
    assert c.n_faces == 12
    assert canonical(c) == canonical(Cage(BOX_V, BOX_F))


def test_from_pyvista_and_to_pyvista():
    import pyvista as pv

    cube = pv.Cube()  # quads
    c = cage_from_dataset(cube)
    assert c.n_faces == 12 and c.volume == pytest.approx(1.0)
    mesh = pv.wrap(cage_to_polydata(c))
    assert isinstance(mesh, pv.PolyData)
    assert np.array_equal(mesh.regular_faces, c.faces)
    assert np.allclose(mesh.points, c.vertices)
    assert np.allclose(mesh.cell_data["Normals"], c.face_normals)
    assert cage_from_dataset(mesh) == c
    # an unstructured grid of polygons keeps its point order
    grid = pv.UnstructuredGrid({pv.CellType.TRIANGLE: BOX_F}, BOX_V)
    assert cage_from_dataset(grid) == Cage(BOX_V, BOX_F)


def test_from_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_cage(tmp_path / "missing.obj")
    bad = tmp_path / "x.xyz"
    bad.write_text("1 2 3\n")
    with pytest.raises(CageError, match="unsupported"):
        read_cage(bad)


def test_an_obj_cage_cut_inside_a_face_line_says_which_line(tmp_path):
    """A face of fewer than 3 vertices (an OBJ cut short) is named, not left out to
    make the cage look open."""
    path = tmp_path / "cut.obj"
    lines = [f"v {x} {y} {z}" for x, y, z in BOX_V]
    lines += ["f " + " ".join(str(i + 1) for i in t) for t in BOX_F]
    cut = lines[-1][:4]  # "f 5 8 7" -> "f 5 "
    path.write_text("\n".join([*lines[:-1], cut]))
    with pytest.raises(CageError) as err:
        read_cage(path)
    assert str(err.value) == (
        f"{path}:{len(lines)}: face with fewer than 3 vertices {cut.strip()!r}; the file may "
        "be cut short: copy or export it again"
    )


def test_public_name():
    import vhm_viz

    assert vhm_viz.Cage is Cage


# ---------------------------------------------------------------------------- data files

GOOD = [
    "armadillo/cage_216f.obj",
    "armadillo/cage_500f.obj",
    "beast/cage.obj",
    "hand/cage.obj",
    "horse/cage.obj",
    "bar/bar_cage_3d.obj",
]


@needs_data
@pytest.mark.data
@pytest.mark.parametrize("name", GOOD)
def test_good_cages(name):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        c = read_cage(DATA / name)
    assert not c.flipped and c.volume > 0
    centre = c.face_centroids - 1e-6 * c.diagonal * c.face_normals
    assert c.contains(centre).all()


@needs_data
@pytest.mark.data
@pytest.mark.parametrize(
    "name", ["armadillo/cage_500f.obj", "bad_cages/selfintersecting_armadillo_cage.obj"]
)
def test_data_cage_self_intersections_equal_brute_force(name):
    # the real cages, every face pair tested: none on the 500-face Armadillo cage, the same
    # 27 pairs as the brute force on the self-intersecting one
    c = read_cage(DATA / name, check_self_intersection=False)
    ref = _brute_force_self_intersections(c.vertices, c.faces)
    np.testing.assert_array_equal(self_intersections(c.vertices, c.faces), ref)
    if "bad" in name:
        assert len(ref) == 27
    else:
        assert len(ref) == 0
        assert Cage(c.vertices, c.faces) == c  # the full validation accepts it


@needs_data
@pytest.mark.data
@pytest.mark.parametrize(
    ("name", "message", "count"),
    [
        ("open_selfintersecting_elephant_cage.obj", "not closed: 8 boundary edges", 8),
        ("nonmanifold_peter_cage.obj", "non-manifold: 5 edges", 5),
        # The data README says 23; an independent brute-force segment/triangle crossing
        # test finds the same 27 pairs as we do (see the test below)
        ("selfintersecting_armadillo_cage.obj", "self-intersects: 27 pairs", 27),
    ],
)
def test_bad_cage_is_refused_naming_the_faulty_elements(name, message, count):
    with pytest.raises(CageError, match=message) as info:
        read_cage(DATA / "bad_cages" / name)
    assert info.value.indices.shape == (count, 2)


@needs_data
@pytest.mark.data
def test_bad_cage_self_intersecting_pairs_are_vertex_disjoint_or_share_one():
    # 19 vertex-disjoint pairs + 8 sharing one vertex
    path = DATA / "bad_cages/selfintersecting_armadillo_cage.obj"
    with pytest.raises(CageError) as info:
        read_cage(path)
    pairs = info.value.indices
    c = read_cage(path, check_self_intersection=False)
    shared = [len(set(c.faces[a]) & set(c.faces[b])) for a, b in pairs]
    assert sorted(shared).count(0) == 19 and sorted(shared).count(1) == 8


@needs_data
@pytest.mark.data
def test_partial_cage():
    import pyvista as pv

    c = read_cage(DATA / "bad_cages/partial_armadillo_cage.obj")
    pts = pv.read(DATA / "bad_cages/armadillo_252v_for_partial_cage.obj").points
    outside = ~c.contains(pts)
    assert 0.02 < outside.mean() < 0.08
