"""Shared fixtures: test data location and small generated cages."""

from __future__ import annotations

import signal
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


# the suite sends SIGINT to the commands it starts, which keep an ignored SIGINT ignored
# (as a shell script's background job must): a suite started in the background of a
# script, which ignores SIGINT, gives them the default instead
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def data_path(*parts: str) -> Path:
    """Path of a file in ``../shared/data``; skips the test when the data is absent."""
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"test data not available: {path}")
    return path


@pytest.fixture
def shared_data() -> Path:
    if not DATA.exists():
        pytest.skip("../shared/data not available")
    return DATA


def read_triangles(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a mesh file (quads split), via meshio."""
    import meshio

    mesh = meshio.read(path)
    tris = []
    for block in mesh.cells:
        if block.type == "triangle":
            tris.append(block.data)
        elif block.type == "quad":
            q = block.data
            tris.append(np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]))
    return np.asarray(mesh.points, dtype=np.float64), np.vstack(tris).astype(np.int64)


def box_cage(lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0), divisions: int = 1):
    """Outward-oriented triangulated box with ``divisions`` segments per side."""
    import itertools

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    verts: dict[tuple, int] = {}
    faces = []

    def vid(p):
        key = tuple(np.round(p, 12))
        if key not in verts:
            verts[key] = len(verts)
        return verts[key]

    s = np.linspace(0.0, 1.0, divisions + 1)
    for axis, side in itertools.product(range(3), (0, 1)):
        u, v = [a for a in range(3) if a != axis]
        for i, j in itertools.product(range(divisions), repeat=2):
            quad = []
            for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.empty(3)
                p[axis] = side
                p[u], p[v] = s[i + di], s[j + dj]
                quad.append(vid(lo + p * (hi - lo)))
            a, b, c, d = quad
            # (u, v, axis) right-handed for axis order: flip so normals point outward
            outward = (side == 1) == ((u, v, axis) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)))
            if outward:
                faces += [(a, b, c), (a, c, d)]
            else:
                faces += [(a, c, b), (a, d, c)]
    vertices = np.array(sorted(verts, key=verts.get), dtype=np.float64)
    return vertices, np.array(faces, dtype=np.int64)


def simple_cage(vertices, faces):
    """Minimal cage object (vertices, faces, face_normals) for core tests."""
    from vhm_viz.core.geometry import face_normals_and_areas

    normals, areas = face_normals_and_areas(vertices, faces)
    return SimpleNamespace(vertices=vertices, faces=faces, face_normals=normals, face_areas=areas)


def fd_jacobian(f, points, h: float = 1e-5) -> np.ndarray:
    """Central finite differences of ``f`` at ``points`` (N, 3): ``J[k, i, j] = d f_i / d x_j``."""
    p = np.asarray(points, dtype=np.float64)
    cols = []
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        cols.append((f(p + e) - f(p - e)) / (2 * h))
    return np.stack(cols, axis=2)


def extent_box(extent) -> tuple[tuple[int, int, int], tuple]:
    """A piece's VTK ``extent`` in its whole image's (z, y, x)-ordered arrays.

    Returns the piece's (nz, ny, nx) shape and the index of its voxels in the whole.
    """
    e = extent
    shape = (e[5] - e[4] + 1, e[3] - e[2] + 1, e[1] - e[0] + 1)
    return shape, np.s_[e[4] : e[5] + 1, e[2] : e[3] + 1, e[0] : e[1] + 1]


def interior_points(vertices, faces, count: int, rng, margin: float = 0.0):
    """Random points inside a cage (by winding number), optionally ``margin`` away from it."""
    from vhm_viz.core.basis import winding_number

    lo, hi = vertices.min(0), vertices.max(0)
    out = np.empty((0, 3))
    while len(out) < count:
        p = rng.uniform(lo, hi, (4 * count, 3))
        p = p[winding_number(p, vertices, faces) > 0.5]
        if margin > 0 and len(p):
            p = p[_distance_to_triangles(p, vertices, faces) > margin]
        out = np.vstack([out, p])
    return out[:count]


def _distance_to_triangles(points, vertices, faces):
    """Brute-force point-to-triangle-soup distance (dense sampling is enough for margins)."""
    # sample each triangle densely; margins are coarse so sampling error is acceptable
    bary = []
    k = 12
    for i in range(k + 1):
        for j in range(k + 1 - i):
            bary.append((i / k, j / k, 1 - (i + j) / k))
    bary = np.array(bary)
    x = vertices[faces]
    samples = np.einsum("sb,fbc->fsc", bary, x).reshape(-1, 3)
    from scipy.spatial import cKDTree

    return cKDTree(samples).query(points)[0]


#: ``subprocess.run`` arguments that decode a child's output as UTF-8 (what vhm_viz prints),
#: whatever the locale of the test process (an ASCII one fails on a non-ASCII name).
UTF8 = {"text": True, "encoding": "utf-8", "errors": "replace"}


def subprocess_env() -> dict:
    """The environment for a child Python process that must import this checkout."""
    import os

    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([root, env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def affine_resampled(img, name, matrix, translation):
    """Independent reference for resampling ``img`` through ``x -> A x + T``.

    scipy.ndimage.affine_transform in index space ((k, j, i) order), trilinear, with the
    boundary values beyond the grid ("nearest": the half-voxel border of vtkImageReslice).

    Returns
    -------
    values : (N,) float64
        On the input grid, VTK order.
    clearly_in, clearly_out : (N,) bool
        Output voxels whose pre-image lies inside / outside the input's half-voxel border
        by more than 1e-6 voxel.
    """
    from scipy.ndimage import affine_transform

    sp, org = np.asarray(img.spacing), np.asarray(img.origin)
    a_inv = np.linalg.inv(np.asarray(matrix, float))
    m = np.diag(1 / sp) @ a_inv @ np.diag(sp)
    c = (a_inv @ (org - np.asarray(translation, float)) - org) / sp
    flip = np.eye(3)[::-1]
    nx, ny, nz = img.dimensions
    data = np.asarray(img.point_data[name], dtype=np.float64).reshape(nz, ny, nx)
    ref = affine_transform(data, flip @ m @ flip, offset=flip @ c, order=1, mode="nearest")
    idx = ((np.asarray(img.points) - org) / sp) @ m.T + c
    top = np.array([nx, ny, nz]) - 1
    clearly_in = np.all((idx > -0.5 + 1e-6) & (idx < top + 0.5 - 1e-6), axis=1)
    clearly_out = np.any((idx < -0.5 - 1e-6) | (idx > top + 0.5 + 1e-6), axis=1)
    return ref.ravel(), clearly_in, clearly_out


def trilinear_corner_dets(p):
    """Brute force: each cell's smallest trilinear corner Jacobian determinant (numpy).

    ``p``: (nz, ny, nx, 3) grid points, i fastest. Returns one value per cell, VTK order.
    """
    nz, ny, nx = (d - 1 for d in p.shape[:3])
    out = np.full((nz, ny, nx), np.inf)
    for c in (0, 1):
        for b in (0, 1):
            for a in (0, 1):
                ex = p[c : c + nz, b : b + ny, 1:] - p[c : c + nz, b : b + ny, :-1]
                ey = p[c : c + nz, 1:, a : a + nx] - p[c : c + nz, :-1, a : a + nx]
                ez = p[1:, b : b + ny, a : a + nx] - p[:-1, b : b + ny, a : a + nx]
                with np.errstate(invalid="ignore"):
                    d = np.linalg.det(np.stack([ex, ey, ez], axis=-1))
                out = np.minimum(out, d)
    return out.reshape(-1)


#: Grid of :func:`write_folding_volume`'s image.
FOLDING_DIMS = (9, 9, 24)


def write_folding_volume(folder: Path, record_map: bool = False) -> None:
    """``image.vti`` filling the bar and ``scene.json``, the bar's push, which folds it.

    ``record_map``: the scene holds its solved map (every ParaView rank uses it as it is).
    """
    import pyvista as pv

    from vhm_viz import examples

    scenario = examples.bar("push", resolution=12, top_height=2.5)
    scene = scenario.scene
    scene.solver["steps"] = 8  # the continuation of BarScenario.solve
    if record_map:
        dfm = scene.build()
        assert scene.solve(dfm)[-1].converged and scene.record_map(dfm)
    scene.save(folder / "scene.json")
    lo = np.array(scenario.surface.bounds[0::2])
    hi = np.array(scenario.surface.bounds[1::2])
    size = 0.98 * (hi - lo)
    dims = np.array(FOLDING_DIMS)
    image = pv.ImageData(dimensions=dims, spacing=size / (dims - 1), origin=lo + 0.01 * (hi - lo))
    image["value"] = np.arange(image.n_points, dtype=np.float32)
    image.save(folder / "image.vti")
