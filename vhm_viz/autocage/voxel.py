"""Voxel occupancy: grids, splatting, growing, closing and well-composed sets (numpy/scipy).

The automatic cage of :func:`vhm_viz.auto_cage` is the paper's "uniform decomposition of
space with co-planar faces merged" (Section 4, Figure 13):

1. mark the voxels of a uniform grid that contain samples of the input
   (:func:`make_grid`, :func:`splat`),
2. grow them by a clearance and fill interior cavities (:func:`grow`),
3. add voxels until the set is *well composed* (no two voxels touch only along an edge or
   at a vertex, in the set or in its complement), which makes the boundary of the union of
   cubes a 2-manifold (:func:`make_well_composed`),
4. merge the boundary squares into maximal coplanar pieces, cut pieces that have holes,
   and triangulate each piece from its corner vertices only
   (:func:`vhm_viz.autocage.voxel_surface.cage_surface`).

The result is closed, manifold, consistently outward oriented and free of
self-intersections by construction, and every sample is at least the clearance away from
it. Everything works in integer grid coordinates; :class:`Grid` converts to world units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from vhm_viz.resources import require_memory

__all__ = [
    "Grid",
    "make_grid",
    "sample_triangles",
    "splat",
    "grow",
    "cube_dilate",
    "fill_inside",
    "close_shell",
    "make_well_composed",
]


@dataclass(frozen=True)
class Grid:
    """A uniform voxel grid: voxel ``(i, j, k)`` spans ``origin + h * [i, i+1] x ...``.

    Attributes
    ----------
    origin : (3,) float64
        World position of the grid corner (vertex ``(0, 0, 0)``).
    h : float
        Edge length of a voxel (world units).
    shape : tuple of int
        Number of voxels along x, y, z.
    """

    origin: np.ndarray
    h: float
    shape: tuple[int, int, int]

    def voxel_of(self, points: np.ndarray) -> np.ndarray:
        """Integer voxel index ``(N, 3)`` of each point (clipped to the grid)."""
        idx = np.floor((np.asarray(points, dtype=np.float64) - self.origin) / self.h)
        return np.clip(idx, 0, np.asarray(self.shape) - 1).astype(np.int64)

    def centers(self, index: np.ndarray) -> np.ndarray:
        """World positions of the centres of voxels ``index`` (N, 3)."""
        return self.origin + (np.asarray(index, dtype=np.float64) + 0.5) * self.h

    def vertex_positions(self, vertex_index: np.ndarray) -> np.ndarray:
        """World positions of integer grid vertices ``(N, 3)``."""
        return self.origin + np.asarray(vertex_index, dtype=np.float64) * self.h


#: Working bytes per voxel of a grid the automatic cage and anchors use, at most: two
#: float64 distance transforms with their int32 feature indices, a label image and masks.
GRID_VOXEL_BYTES = 48


def make_grid(
    lo: np.ndarray, hi: np.ndarray, resolution: int | None, pad: int, h: float | None = None
) -> Grid:
    """Grid with ``resolution`` voxels along the longest side of the box ``[lo, hi]``.

    Parameters
    ----------
    lo, hi : (3,) array
        Bounding box of the data.
    resolution : int or None
        Voxels along the longest box side (>= 1); ignored when ``h`` is given.
    pad : int
        Empty voxels added on every side (room for the clearance and a border).
    h : float, optional
        Voxel size instead of ``resolution`` (world units).

    Returns
    -------
    Grid
        Centred on the box.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    ext = hi - lo
    if h is None:
        h = float(ext.max()) / max(int(resolution), 1)
    if not h > 0:
        raise ValueError("the data has no extent")
    # a hair more than the extent so points on the upper face fall inside the last voxel
    n = np.ceil(ext / h * (1 + 1e-9) + 1e-9).astype(np.int64)
    n = np.maximum(n, 1) + 2 * int(pad)
    # the working arrays of a grid (distance transforms and their feature indices, labels,
    # masks), refused before any exists when they cannot fit
    shape = "x".join(str(int(k)) for k in n)
    require_memory(
        int(np.prod(n.astype(np.float64))) * GRID_VOXEL_BYTES,
        f"a {shape} voxel grid",
        "use a lower resolution (voxels along its longest side)",
        ValueError,
    )
    origin = 0.5 * (lo + hi) - 0.5 * n * h
    return Grid(origin=origin, h=h, shape=(int(n[0]), int(n[1]), int(n[2])))


def sample_triangles(
    vertices: np.ndarray, faces: np.ndarray, spacing: float, return_faces: bool = False
):
    """Extra points on triangles whose longest edge exceeds ``spacing``.

    Every point of such a triangle is within ``spacing`` of a returned point or of a
    triangle corner (a barycentric grid with sub-edges no longer than ``spacing``).

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (m, 3) int array
    spacing : float
        Largest allowed distance between neighbouring samples.
    return_faces : bool
        Also return the triangle each sample lies on.

    Returns
    -------
    samples : (k, 3) float64
        Samples (triangle corners not repeated); may be empty.
    face : (k,) int64, only with ``return_faces``
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or spacing <= 0:
        return (np.empty((0, 3)), np.empty(0, np.int64)) if return_faces else np.empty((0, 3))
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    longest = np.maximum.reduce(
        [
            np.linalg.norm(b - a, axis=1),
            np.linalg.norm(c - b, axis=1),
            np.linalg.norm(a - c, axis=1),
        ]
    )
    divisions = np.ceil(longest / spacing).astype(np.int64)
    out, owner = [], []
    total = 0
    for k in np.unique(divisions[divisions > 1]):
        sel = np.flatnonzero(divisions == k)
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = (
            (i + j <= k) & ~((i == 0) & (j == 0)) & ~((i == k) & (j == 0)) & ~((i == 0) & (j == k))
        )
        wb = (i[keep] / k)[None, :, None]
        wc = (j[keep] / k)[None, :, None]
        aa, bb, cc = a[sel][:, None, :], b[sel][:, None, :], c[sel][:, None, :]
        out.append((aa + wb * (bb - aa) + wc * (cc - aa)).reshape(-1, 3))
        owner.append(np.repeat(sel, int(keep.sum())))
        total += len(out[-1])
        if total > 20_000_000:  # pragma: no cover - defensive
            raise ValueError("triangles too large for the voxel size; use a lower resolution")
    pts = np.concatenate(out) if out else np.empty((0, 3))
    if return_faces:
        return pts, (np.concatenate(owner) if owner else np.empty(0, np.int64))
    return pts


def splat(grid: Grid, points: np.ndarray) -> np.ndarray:
    """Boolean occupancy of the voxels that contain at least one point."""
    occ = np.zeros(grid.shape, dtype=bool)
    if len(points):
        idx = grid.voxel_of(points)
        occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return occ


def cube_dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Dilation of a voxel mask by a cube of ``2 radius + 1`` voxels (a copy for 0).

    Parameters
    ----------
    mask : (nx, ny, nz) bool
    radius : int
        Voxels.

    Returns
    -------
    (nx, ny, nz) bool
    """
    if radius <= 0:
        return mask.copy()
    return ndimage.maximum_filter(mask.view(np.uint8), size=2 * radius + 1, mode="constant").astype(
        bool
    )


def _cube_erode(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask.copy()
    return ndimage.minimum_filter(mask.view(np.uint8), size=2 * radius + 1, mode="constant").astype(
        bool
    )


def close_shell(occ: np.ndarray, radius: int) -> np.ndarray:
    """Morphological closing (with cavity filling) for sparse samples; keeps ``occ``.

    Used for point clouds whose samples are farther apart than a voxel, so that their
    splatted shell becomes watertight before its inside is filled.
    """
    if radius <= 0:
        return occ
    grown = ndimage.binary_fill_holes(cube_dilate(occ, radius))
    return _cube_erode(grown, radius) | occ


def grow(occ: np.ndarray, offset_voxels: float) -> np.ndarray:
    """Voxels within the clearance of ``occ``, with interior cavities filled.

    A voxel ``e`` is added when the distance between the *boxes* of ``e`` and of some
    occupied voxel is below ``offset_voxels`` (always including the 26 neighbours). Every
    point inside an occupied voxel is therefore at least ``max(1, offset_voxels)`` voxels
    away from every voxel left out, hence from the boundary of the result.

    Parameters
    ----------
    occ : (nx, ny, nz) bool
    offset_voxels : float
        Clearance in voxel units.

    Returns
    -------
    (nx, ny, nz) bool
    """
    near = cube_dilate(occ, 1)
    if offset_voxels > 1:
        # box distance between voxels == centre distance to the 26-dilated set
        dist = ndimage.distance_transform_edt(~near)
        near = dist < offset_voxels
    return ndimage.binary_fill_holes(near)


def fill_inside(occ: np.ndarray) -> np.ndarray:
    """The voxels inside a shell of occupied voxels, the shell included.

    The shell grown by a voxel closes pinholes before its cavities are filled; the growth
    is eroded away again, except where it is occupied.

    Parameters
    ----------
    occ : (nx, ny, nz) bool

    Returns
    -------
    (nx, ny, nz) bool
    """
    inside = ndimage.binary_fill_holes(grow(occ, 1.0))
    return ndimage.binary_erosion(inside, structure=np.ones((3, 3, 3), bool)) | occ


# ---------------------------------------------------------------------------------------
# well-composed sets
# ---------------------------------------------------------------------------------------

_CORNERS = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]


def _fix_once(s: np.ndarray) -> int:
    """Add voxels to remove critical configurations; returns how many were added."""
    nx, ny, nz = s.shape
    added = 0
    # 2D critical squares (two voxels sharing only an edge) in the three orientations
    for a, b in ((0, 1), (0, 2), (1, 2)):

        def sl(da, db, a=a, b=b):
            idx = [slice(0, None)] * 3
            n = s.shape
            idx[a] = slice(da, n[a] - 1 + da)
            idx[b] = slice(db, n[b] - 1 + db)
            return tuple(idx)

        p00, p10, p01, p11 = s[sl(0, 0)], s[sl(1, 0)], s[sl(0, 1)], s[sl(1, 1)]
        crit1 = p00 & p11 & ~p10 & ~p01
        crit2 = p10 & p01 & ~p00 & ~p11
        if crit1.any():
            view = s[sl(1, 0)]
            view |= crit1
            added += int(crit1.sum())
        if crit2.any():
            # recompute: the first fix may already have resolved some
            p00, p10, p01, p11 = s[sl(0, 0)], s[sl(1, 0)], s[sl(0, 1)], s[sl(1, 1)]
            crit2 = p10 & p01 & ~p00 & ~p11
            view = s[sl(0, 0)]
            view |= crit2
            added += int(crit2.sum())
    # 3D critical cubes (vertex-only contacts in the set or in its complement)
    c = {(i, j, k): s[i : nx - 1 + i, j : ny - 1 + j, k : nz - 1 + k] for (i, j, k) in _CORNERS}
    count = sum(cv.view(np.uint8).astype(np.int8) for cv in c.values())
    for p in _CORNERS:
        q = (1 - p[0], 1 - p[1], 1 - p[2])
        if p > q:
            continue
        two = (count == 2) & c[p] & c[q]
        six = (count == 6) & ~c[p] & ~c[q]
        if two.any():
            # fill the neighbour of p across x and the one across x and y: a face path
            n1 = (1 - p[0], p[1], p[2])
            n2 = (1 - p[0], 1 - p[1], p[2])
            for n in (n1, n2):
                view = s[n[0] : nx - 1 + n[0], n[1] : ny - 1 + n[1], n[2] : nz - 1 + n[2]]
                view |= two
            added += 2 * int(two.sum())
        if six.any():
            view = s[p[0] : nx - 1 + p[0], p[1] : ny - 1 + p[1], p[2] : nz - 1 + p[2]]
            view |= six
            added += int(six.sum())
    return added


def make_well_composed(occ: np.ndarray, max_rounds: int = 100) -> np.ndarray:
    """Smallest-effort superset of ``occ`` whose boundary surface is a 2-manifold.

    Adds voxels (never removes: enclosure and clearance are kept) until no 2x2 square
    holds two diagonal voxels alone (edge contact) and no 2x2x2 cube holds exactly two
    antipodal voxels or exactly two antipodal holes (vertex contacts).

    Parameters
    ----------
    occ : (nx, ny, nz) bool
        Must be empty on the grid border.
    max_rounds : int
        Safety bound on repair passes.

    Returns
    -------
    (nx, ny, nz) bool
    """
    s = occ.copy()
    for _ in range(max_rounds):
        if _fix_once(s) == 0:
            return s
    raise RuntimeError("could not make the voxel set well composed")  # pragma: no cover
