"""The closed-form basis against independent references.

References: exact affine reproduction, brute-force quadrature of the defining integrals
(with analytic kernel derivatives), finite differences, and the numpy reference vs the
numba kernel.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import box_cage, data_path, interior_points, read_triangles, simple_cage

from vhm_viz.core.basis import (
    domain_columns,
    evaluate_basis,
    evaluate_map,
    hessian5_to_full,
    winding_number,
)
from vhm_viz.core.basis_kernel import lanes_evaluation, per_point_evaluation
from vhm_viz.core.cage_tables import prepare_cage
from vhm_viz.core.geometry import face_normals_and_areas


def _perturbed_box(seed=1, divisions=2, amount=0.08):
    """An irregular closed cage: a subdivided box with jittered vertices."""
    v, f = box_cage((0, 0, 0), (1.0, 1.3, 0.9), divisions)
    rng = np.random.default_rng(seed)
    return v + rng.uniform(-amount, amount, v.shape), f


def _cage(name):
    if name == "box":
        return _perturbed_box()
    paths = {
        "hand": ("hand", "cage.obj"),
        "beast": ("beast", "cage.obj"),
        "armadillo500": ("armadillo", "cage_500f.obj"),
    }
    return read_triangles(data_path(*paths[name]))


def _apply(basis, z):
    """f (N,3), J (N,3,3) [i,j], H (N,3,3,3) [i,j,l] from a basis evaluation and z."""
    f = basis.values @ z
    jac = np.swapaxes(basis.gradients @ z, 1, 2) if basis.gradients is not None else None
    hess = (
        hessian5_to_full(np.swapaxes(basis.hessians @ z, 1, 2))
        if basis.hessians is not None
        else None
    )
    return f, jac, hess


# ------------------------------------------------------------------------------- affine
@pytest.mark.parametrize("name", ["box", "hand", "beast", "armadillo500"])
def test_affine_reproduction(name):
    v, f = _cage(name)
    rng = np.random.default_rng(7)
    pts = interior_points(v, f, 60, rng)
    a = rng.normal(size=(3, 3))
    t = rng.normal(size=3)
    normals, _ = face_normals_and_areas(v, f)
    z = np.vstack([v @ a.T + t, normals @ a.T])
    fv, jac, hess = _apply(evaluate_basis(pts, v, f, order=2), z)
    scale = np.abs(pts @ a.T + t).max()
    assert np.abs(fv - (pts @ a.T + t)).max() <= 1e-10 * scale
    assert np.abs(jac - a).max() <= 1e-10 * np.abs(a).max()
    # H = 0: relative to the size of the individual terms it cancels
    hscale = np.abs(evaluate_basis(pts, v, f, order=2).hessians).max() * np.abs(z).max()
    assert np.abs(hess).max() <= 1e-10 * hscale


@pytest.mark.parametrize("name", ["box", "hand"])
def test_partition_of_unity_inside_zero_outside(name):
    v, f = _cage(name)
    rng = np.random.default_rng(3)
    inside = interior_points(v, f, 100, rng)
    n = len(v)
    assert np.allclose(evaluate_basis(inside, v, f).values[:, :n].sum(1), 1.0, atol=1e-12)
    lo, hi = v.min(0), v.max(0)
    size = (hi - lo).max()
    outside = hi + rng.uniform(0.05, 2.0, (50, 3)) * size
    assert np.allclose(evaluate_basis(outside, v, f).values[:, :n].sum(1), 0.0, atol=1e-12)
    assert np.allclose(winding_number(outside, v, f), 0.0, atol=1e-12)
    assert np.allclose(winding_number(inside, v, f), 1.0, atol=1e-12)
    # the SIMD kernel (150 points: a padded last group) against the numpy reference
    both = np.vstack([inside, outside])
    ref = winding_number(both, v, f, backend="numpy")
    assert np.abs(winding_number(both, v, f) - ref).max() <= 1e-13


# --------------------------------------------------------------------------- quadrature
def _gauss_triangle(level: int, order: int = 6):
    """Quadrature on the reference triangle: ``level`` uniform subdivisions x Duffy Gauss."""
    g, gw = np.polynomial.legendre.leggauss(order)
    g, gw = 0.5 * (g + 1), 0.5 * gw
    # collapsed square -> triangle (s, t) with s + t <= 1
    s = g[:, None] * np.ones_like(g)[None, :]
    t = (1 - g[:, None]) * g[None, :]
    w = gw[:, None] * gw[None, :] * (1 - g[:, None])
    base = np.stack([s.ravel(), t.ravel()], 1)
    bw = w.ravel()
    pts, wts = [], []
    k = 2**level
    for i in range(k):
        for j in range(k - i):
            for up in (True, False):
                if up:
                    o = np.array([i, j]) / k
                    e1, e2 = np.array([1, 0]) / k, np.array([0, 1]) / k
                else:
                    if i + j + 1 >= k:
                        continue
                    o = np.array([i + 1, j + 1]) / k
                    e1, e2 = np.array([-1, 0]) / k, np.array([0, -1]) / k
                pts.append(o + base[:, :1] * e1 + base[:, 1:] * e2)
                wts.append(bw / k**2)
    return np.vstack(pts), np.concatenate(wts)  # weights sum to 1/2


def _quadrature_basis(p, v, f, level=3):
    """phi, psi and derivatives by brute-force quadrature of the defining integrals."""
    st, w = _gauss_triangle(level)
    n, m = len(v), len(f)
    normals, areas = face_normals_and_areas(v, f)
    vals = np.zeros(n + m)
    grads = np.zeros((3, n + m))
    hess = np.zeros((3, 3, n + m))
    eye = np.eye(3)
    for t in range(m):
        x0, x1, x2 = v[f[t]]
        gam = np.stack([1 - st[:, 0] - st[:, 1], st[:, 0], st[:, 1]], 1)  # hat functions
        q = gam @ np.stack([x0, x1, x2])
        da = w * 2 * areas[t]  # dA weights
        r = q - p
        rl = np.linalg.norm(r, axis=1)
        nn = normals[t]
        rn = r @ nn
        # single layer G = 1/(4 pi |r|); d/dp = -d/dr
        g0 = 1 / (4 * np.pi * rl)
        g1 = r / (4 * np.pi * rl[:, None] ** 3)
        g2 = (3 * r[:, :, None] * r[:, None, :] - (rl**2)[:, None, None] * eye) / (
            4 * np.pi * rl[:, None, None] ** 5
        )
        vals[n + t] = da @ g0
        grads[:, n + t] = da @ g1
        hess[:, :, n + t] = np.einsum("q,qij->ij", da, g2)
        # double layer K = (r.N)/(4 pi |r|^3)
        k0 = rn / (4 * np.pi * rl**3)
        dk_dr = (nn[None] / rl[:, None] ** 3 - 3 * rn[:, None] * r / rl[:, None] ** 5) / (4 * np.pi)
        d2k = (
            -3 * nn[None, :, None] * r[:, None, :] / rl[:, None, None] ** 5
            - 3 * nn[None, None, :] * r[:, :, None] / rl[:, None, None] ** 5
            - 3 * rn[:, None, None] * eye / rl[:, None, None] ** 5
            + 15 * rn[:, None, None] * r[:, :, None] * r[:, None, :] / rl[:, None, None] ** 7
        ) / (4 * np.pi)
        for c in range(3):
            wg = da * gam[:, c]
            vals[f[t, c]] += wg @ k0
            grads[:, f[t, c]] += -(wg @ dk_dr)
            hess[:, :, f[t, c]] += np.einsum("q,qij->ij", wg, d2k)
    return vals, grads, hess


def test_agrees_with_quadrature():
    v, f = _perturbed_box(divisions=1, amount=0.05)
    rng = np.random.default_rng(11)
    pts = interior_points(v, f, 4, rng, margin=0.25)
    z = rng.normal(size=(len(v) + len(f), 3))
    b = evaluate_basis(pts, v, f, order=2)
    fv, jac, hess = _apply(b, z)
    for k, p in enumerate(pts):
        qv, qg, qh = _quadrature_basis(p, v, f)
        # per-function comparison (values, gradients, Hessians of every basis function)
        assert np.allclose(b.values[k], qv, rtol=0, atol=1e-7 * np.abs(qv).max())
        assert np.allclose(b.gradients[k], qg, rtol=0, atol=1e-6 * np.abs(qg).max())
        qh5 = np.stack([qh[0, 0], qh[0, 1], qh[0, 2], qh[1, 1], qh[1, 2]])
        assert np.allclose(b.hessians[k], qh5, rtol=0, atol=1e-5 * np.abs(qh5).max())
        # and the map built from random coefficients
        assert np.allclose(fv[k], qv @ z, atol=1e-7 * np.abs(qv @ z).max())
        qj = (qg @ z).T
        assert np.allclose(jac[k], qj, atol=1e-6 * np.abs(qj).max())
        qhz = np.einsum("jlc,ci->ijl", qh, z)
        assert np.allclose(hess[k], qhz, atol=1e-5 * np.abs(qhz).max())


# --------------------------------------------------------------------- finite differences
def test_finite_differences_and_harmonicity():
    v, f = read_triangles(data_path("hand", "cage.obj"))
    rng = np.random.default_rng(5)
    pts = interior_points(v, f, 15, rng)
    z = rng.normal(size=(len(v) + len(f), 3))
    fv, jac, hess = _apply(evaluate_basis(pts, v, f, order=2), z)
    h = 1e-5 * np.ptp(v, axis=0).max()
    fd_j = np.empty_like(jac)
    fd_h = np.empty_like(hess)
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        fp, jp, _ = _apply(evaluate_basis(pts + d, v, f, order=1), z)
        fm, jm, _ = _apply(evaluate_basis(pts - d, v, f, order=1), z)
        fd_j[:, :, j] = (fp - fm) / (2 * h)
        fd_h[:, :, :, j] = (jp - jm) / (2 * h)
    assert np.abs(fd_j - jac).max() <= 1e-7 * np.abs(jac).max()
    assert np.abs(fd_h - hess).max() <= 1e-6 * np.abs(hess).max()
    # the finite-difference Hessian (nothing assumed about its zz entry) is traceless
    trace = np.einsum("kijj->ki", fd_h)
    assert np.abs(trace).max() <= 1e-6 * np.abs(fd_h).max()


# --------------------------------------------------------------------- near the boundary
def _approach_points(v, f):
    """Points of a box cage plus inward directions: face interior, edge, vertex."""
    normals, _ = face_normals_and_areas(v, f)
    t = 3
    face_pt = v[f[t]].mean(0)
    face_dir = -normals[t]
    # an edge shared by two faces with different normals (a box edge)
    for a in range(len(f)):
        for b in range(a + 1, len(f)):
            shared = set(f[a]) & set(f[b])
            if len(shared) == 2 and abs(normals[a] @ normals[b]) < 0.5:
                i, j = sorted(shared)
                edge_pt = 0.5 * (v[i] + v[j])
                edge_dir = -(normals[a] + normals[b])
                break
        else:
            continue
        break
    vert = 0
    vdir = -normals[np.any(f == vert, axis=1)].sum(0)
    return [
        ("face", face_pt, face_dir / np.linalg.norm(face_dir)),
        ("edge", edge_pt, edge_dir / np.linalg.norm(edge_dir)),
        ("edge off-centre", 0.8 * v[i] + 0.2 * v[j], edge_dir / np.linalg.norm(edge_dir)),
        ("edge near its end", 0.99 * v[i] + 0.01 * v[j], edge_dir / np.linalg.norm(edge_dir)),
        ("vertex", v[vert], vdir / np.linalg.norm(vdir)),
    ]


@pytest.mark.parametrize("order", [0, 1, 2])
@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_near_boundary_is_finite_and_affine(backend, order):
    v, f = box_cage((0, 0, 0), (1, 1, 1), 2)
    rng = np.random.default_rng(2)
    a = np.eye(3) + 0.3 * rng.normal(size=(3, 3))
    t = rng.normal(size=3)
    normals, _ = face_normals_and_areas(v, f)
    z = np.vstack([v @ a.T + t, normals @ a.T])
    dists = 10.0 ** -np.arange(2, 13)
    for _kind, base, direction in _approach_points(v, f):
        pts = base + dists[:, None] * direction
        b = evaluate_basis(pts, v, f, order=order, backend=backend)
        assert all(np.isfinite(x).all() for x in b if x is not None)
        fv, jac, _ = _apply(b, z)
        assert np.abs(fv - (pts @ a.T + t)).max() <= 1e-6
        if order >= 1:
            assert np.abs(jac - a).max() <= 1e-6
        assert np.allclose(winding_number(pts, v, f, backend=backend), 1.0, atol=1e-9)


def test_exactly_on_face_gives_interior_limit():
    v, f = _perturbed_box()
    normals, _ = face_normals_and_areas(v, f)
    rng = np.random.default_rng(4)
    faces = rng.choice(len(f), 6, replace=False)
    bary = rng.dirichlet([2, 2, 2], size=6)
    on = np.einsum("kb,kbc->kc", bary, v[f[faces]])
    exact = evaluate_basis(on, v, f, order=2, host_faces=faces)
    inside = evaluate_basis(on - 1e-7 * normals[faces], v, f, order=2)
    for got, lim in zip(exact, inside, strict=True):
        scale = np.abs(lim).max(axis=-1, keepdims=True)
        assert np.all(np.abs(got - lim) <= 1e-4 * scale)
    assert np.allclose(exact.values[:, : len(v)].sum(1), 1.0, atol=1e-12)


def test_exactly_on_edge_and_vertex_values():
    # axis-aligned box: edge midpoints and vertices are exact in floating point
    v, f = box_cage((0, 0, 0), (1, 2, 1), 1)
    cage = simple_cage(v, f)
    from vhm_viz.core.harmonic_map import HarmonicMap

    rng = np.random.default_rng(8)
    a = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    hm = HarmonicMap.affine(cage, a, (1, 2, 3))
    pts = np.array([v[0], v[5], 0.5 * (v[0] + v[1]), [0.0, 0.0, 0.5]])
    b = evaluate_basis(pts, v, f, order=1)
    assert np.allclose(b.values[:, : len(v)].sum(1), 1.0, atol=1e-12)
    assert np.allclose(b.values @ hm.coefficients, pts @ a.T + [1, 2, 3], atol=1e-12)
    assert np.isnan(b.gradients).all()  # documented: not differentiable there


@pytest.mark.parametrize("order", [0, 1, 2])
def test_numba_matches_numpy_reference(order):
    v, f = read_triangles(data_path("beast", "cage.obj"))
    rng = np.random.default_rng(9)
    pts = interior_points(v, f, 40, rng)
    host = np.full(len(pts), -1)
    # include points on faces (interior limit) too
    on = v[f[:5]].mean(1)
    pts = np.vstack([pts, on])
    host = np.concatenate([host, np.arange(5)])
    a = evaluate_basis(pts, v, f, order=order, host_faces=host, backend="numba")
    b = evaluate_basis(pts, v, f, order=order, host_faces=host, backend="numpy", chunk_size=7)
    for x, y in zip(a, b, strict=True):
        if y is None:
            assert x is None
        else:
            assert np.abs(x - y).max() <= 1e-12 * np.abs(y).max()


def _run_lanes_and_per_point(pts, v, f, order):
    """Both compiled kernels on the same points: (lanes values, grads, flagged), per-point."""
    cd = prepare_cage(v, f)
    host = np.full(len(pts), -1, dtype=np.int64)
    vals, grads, flagged = lanes_evaluation(pts, cd, order, host)
    ref = per_point_evaluation(pts, cd, order, host)
    return vals, grads, flagged, ref


@pytest.mark.parametrize("order", [0, 1])
@pytest.mark.parametrize("count", [1, 15, 16, 17, 83])
def test_lanes_kernel_matches_per_point_kernel(order, count):
    """The 16-point SIMD kernel equals the careful per-point kernel where it applies.

    Counts around the group size check the padded last group; every row must be written.
    """
    v, f = read_triangles(data_path("armadillo", "cage_500f.obj"))
    pts = interior_points(v, f, count, np.random.default_rng(count))
    vals, grads, flagged, ref = _run_lanes_and_per_point(pts, v, f, order)
    ok = ~flagged
    assert ok.sum() >= 0.9 * count  # deep interior points are the kernel's business
    scale = np.abs(ref[0]).max()
    assert np.abs(vals[ok] - ref[0][ok]).max() <= 1e-13 * scale
    if order:
        gscale = np.abs(ref[1]).max()
        assert np.abs(grads[ok] - ref[1][ok]).max() <= 1e-13 * gscale


def test_lanes_kernel_flags_points_next_to_edges_and_vertices():
    """Points near a cage edge or vertex are left to the per-point kernel, others are not."""
    v, f = box_cage((0, 0, 0), (1, 1, 1), 2)
    centre = np.full(3, 0.5)
    near = []
    for _kind, base, direction in _approach_points(v, f):
        near.append(base + 1e-9 * direction)
    face_centre = v[f[0]].mean(0)
    inward = centre - face_centre
    pts = np.vstack(near + [face_centre + 1e-9 * inward / np.linalg.norm(inward), centre])
    _, _, flagged, _ = _run_lanes_and_per_point(pts, v, f, 0)
    kinds = [k for k, _b, _d in _approach_points(v, f)]
    for kind, flag in zip(kinds, flagged[: len(kinds)], strict=True):
        assert flag == (kind != "face"), kind
    assert not flagged[-2:].any()  # next to a face's interior, and the centre


@pytest.mark.parametrize("order", [0, 1])
def test_fused_map_equals_basis_times_coefficients(order):
    """``evaluate_map`` (basis contracted inside the kernel) is the basis matrix product.

    Random coefficients, points in the deep interior, next to edges and vertices (per-point
    kernel), on an edge and outside; and a cage of two shells (the matrix path).
    """
    v, f = read_triangles(data_path("armadillo", "cage_216f.obj"))
    rng = np.random.default_rng(5)
    z = rng.normal(size=(len(v) + len(f), 3))
    near = [base + 1e-7 * d for _k, base, d in _approach_points(v, f)]
    edge_mid = 0.5 * (v[f[0, 0]] + v[f[0, 1]])
    pts = np.vstack([interior_points(v, f, 40, rng), *near, edge_mid, v.max(0) + 1.0])
    values, jac, winding = evaluate_map(pts, v, f, z, order=order)
    b = evaluate_basis(pts, v, f, order=order)
    n = len(v)
    np.testing.assert_allclose(values, b.values @ z, rtol=0, atol=1e-12 * np.abs(z).sum(0).max())
    np.testing.assert_allclose(winding, b.values[:, :n].sum(1), atol=1e-13)
    if order:
        ref = np.swapaxes(b.gradients @ z, 1, 2)
        finite = np.isfinite(ref).all(axis=(1, 2))
        assert np.array_equal(finite, np.isfinite(jac).all(axis=(1, 2)))
        np.testing.assert_allclose(jac[finite], ref[finite], rtol=1e-12, atol=1e-10)
    else:
        assert jac is None


@pytest.mark.parametrize("order", [0, 1])
def test_fused_map_of_several_shells_equals_basis(order):
    """Several outward shells and a hole: each point sees the shells containing it.

    ``evaluate_map`` runs the fused kernel shell by shell; ``evaluate_basis`` zeroes the
    columns of the shells that do not contain a point. Two boxes side by side, the second
    with an inward box (a hole) inside it; points in both, in the hole, in the gap and
    outside everything, and next to an edge of each (the per-point kernel).
    """
    rng = np.random.default_rng(7)
    v2, f2 = box_cage((0, 0, 0), (1, 1, 1), 2)
    hv, hf = box_cage((2.4, 0.4, 0.4), (2.6, 0.6, 0.6), 1)
    vv = np.vstack([v2, v2 + (2.0, 0, 0), hv])
    ff = np.vstack([f2, f2 + len(v2), hf[:, ::-1] + 2 * len(v2)])
    z2 = rng.normal(size=(len(vv) + len(ff), 3))
    pts = np.vstack([
        rng.uniform((-0.5, -0.5, -0.5), (3.5, 1.5, 1.5), (200, 3)),
        [[0.5, 1e-7, 1e-7], [2.5, 1e-7, 1.0 - 1e-7], [2.5, 0.5, 0.5], [1.5, 0.5, 0.5]],
    ])  # fmt: skip
    n = len(vv)
    values, jac, winding = evaluate_map(pts, vv, ff, z2, order=order)
    b2 = evaluate_basis(pts, vv, ff, order=order)
    scale = np.abs(z2).sum(0).max()
    np.testing.assert_allclose(values, b2.values @ z2, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(winding, b2.values[:, :n].sum(1), atol=1e-12)
    if order:
        ref = np.swapaxes(b2.gradients @ z2, 1, 2)
        np.testing.assert_allclose(jac, ref, rtol=1e-11, atol=1e-10 * scale)
    # the classification is real: in the hole and in the gap nothing is inside
    assert winding[-2] == pytest.approx(0.0, abs=1e-9)
    assert winding[-1] == pytest.approx(0.0, abs=1e-9)
    assert 0 < (winding > 0.5).sum() < len(pts)


def test_bad_arguments():
    v, f = box_cage()
    with pytest.raises(ValueError, match="shape"):
        evaluate_basis(np.zeros((3, 2)), v, f)
    with pytest.raises(ValueError, match="non-finite.*1"):
        evaluate_basis(np.array([[0.5, 0.5, 0.5], [np.nan, 0, 0]]), v, f)
    with pytest.raises(ValueError, match="order"):
        evaluate_basis(np.zeros((1, 3)), v, f, order=3)
    with pytest.raises(ValueError, match="backend"):
        evaluate_basis(np.zeros((1, 3)), v, f, backend="cuda")
    with pytest.raises(ValueError, match="host_faces"):
        evaluate_basis(np.zeros((2, 3)), v, f, host_faces=[0])
    assert evaluate_basis(np.zeros((0, 3)), v, f, order=2).hessians.shape == (0, 5, len(v) + len(f))


def test_disjoint_shells_are_separate_domains():
    """Two outward shells bound two domains: each point sees only its own shell."""
    v1, f1 = box_cage((0, 0, 0), (1, 1, 3), 2)
    v2, f2 = box_cage((1.2, 0, 0), (2.2, 1, 3), 2)
    v = np.vstack([v1, v2])
    f = np.vstack([f1, f2 + len(v1)])
    n1, m1 = len(v1), len(f1)
    rng = np.random.default_rng(12)
    p1 = rng.uniform((0.1, 0.1, 0.1), (0.9, 0.9, 2.9), (20, 3))
    p2 = p1 + (1.2, 0, 0)
    gap = np.column_stack([np.full(5, 1.1), rng.uniform(0.1, 0.9, 5), rng.uniform(0.1, 2.9, 5)])
    normals, _ = face_normals_and_areas(v, f)
    a = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    z = np.vstack([v @ a.T + 1.0, normals @ a.T])
    b = evaluate_basis(np.vstack([p1, p2, gap]), v, f, order=2)
    fv, jac, hess = _apply(b, z)
    inside = slice(0, 40)
    assert np.allclose(fv[inside], np.vstack([p1, p2])[inside] @ a.T + 1.0, atol=1e-12)
    assert np.allclose(jac[inside], a, atol=1e-12) and np.abs(hess[inside]).max() < 1e-10
    assert np.allclose(b.values[40:, : len(v)].sum(1), 0.0, atol=1e-12)  # the gap is outside
    # moving shell 1 (any coefficients) changes nothing inside shell 2, exactly
    z2 = z.copy()
    z2[:n1] += rng.normal(size=(n1, 3))
    z2[len(v) : len(v) + m1] += rng.normal(size=(m1, 3))
    fv2, jac2, hess2 = _apply(evaluate_basis(p2, v, f, order=2), z2)
    assert np.array_equal(fv2, fv[20:40]) and np.array_equal(jac2, jac[20:40])
    assert np.array_equal(hess2, hess[20:40])
    # numpy reference agrees
    ref = evaluate_basis(np.vstack([p1, p2, gap]), v, f, order=2, backend="numpy")
    for x, y in zip(b, ref, strict=True):
        assert np.abs(x - y).max() <= 1e-12 * np.abs(y).max()


def test_domain_columns_own_each_shell_and_its_holes():
    """Each outward shell owns its vertex and face columns, and the hole shell inside it."""
    v1, f1 = box_cage((0, 0, 0), (1, 1, 3), 1)
    v2, f2 = box_cage((2, 0, 0), (3, 1, 3), 1)
    v3, f3 = box_cage((2.3, 0.3, 1), (2.7, 0.7, 2), 1)  # a hole in the second box
    v = np.vstack([v1, v2, v3])
    f = np.vstack([f1, f2 + 8, f3[:, ::-1] + 16])
    n = len(v)
    d = domain_columns(v, f)
    assert len(d) == 2
    np.testing.assert_array_equal(d[0], np.r_[0:8, n + np.arange(0, 12)])
    np.testing.assert_array_equal(d[1], np.r_[8:24, n + np.arange(12, 36)])
    # a single shell owns every column
    np.testing.assert_array_equal(domain_columns(v1, f1)[0], np.arange(8 + 12))
