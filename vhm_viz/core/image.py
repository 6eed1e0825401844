"""Regular grids (images) as plain arrays: geometry, the cage's inside mask, sampling.

Everything a volume engine needs from an image that is not the harmonic map itself:

* :class:`ImageGeometry` -- origin, spacing, dimensions and direction of a grid, and the
  conversions between world points and continuous voxel indices;
* :func:`inside_mask` -- which grid points lie inside a closed cage, by counting signed
  crossings along grid rows (a scan-line voxeliser). It costs a few operations per row
  and triangle instead of a winding-number evaluation per voxel;
* :func:`sample_linear`, :func:`sample_nearest`, :func:`sample_cubic` -- trilinear,
  nearest or cubic (Catmull-Rom) interpolation of point data at a continuous index, with
  the half-voxel border of ``vtkImageReslice``, for the compiled loops over voxels that
  resample a volume.

Voxel ``(i, j, k)`` sits at ``origin + direction @ (spacing * (i, j, k))``, ``i`` fastest
(VTK's point order). Point data arrays are used as ``(nz, ny, nx[, c])`` views.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "ImageGeometry",
    "INTERPOLATIONS",
    "BORDER",
    "check_interpolation",
    "check_fill_value",
    "inside_mask",
    "surface_mask",
    "sample_cubic",
    "sample_linear",
    "sample_nearest",
]

#: Interpolation kinds (:func:`sample_linear`, :func:`sample_nearest`, :func:`sample_cubic`).
INTERPOLATIONS = ("linear", "nearest", "cubic")


def check_interpolation(kind: str) -> str:
    """``kind`` if it is one of :data:`INTERPOLATIONS`, else a ValueError naming them."""
    if kind not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}; got {kind!r}")
    return kind


def check_fill_value(value, dtypes: dict, name: str = "fill_value") -> float:
    """The fill value as a float, refused unless every array's type holds it exactly.

    The one check of the value given to voxels without a pre-image: the volume engine's
    resampling, its filter and the command line's ``--fill-value`` call it. An integer
    type holds the integers of its range; a floating-point type holds every number up to
    its largest finite one (rounded to its precision), infinities and NaN. Anything else
    would be changed silently by the cast (clipped, rounded, or NaN made 0).

    Parameters
    ----------
    value : float
    dtypes : dict of str -> numpy dtype
        The arrays that take it, by name.
    name : str
        The setting's name, for the message (``--fill-value`` on the command line).

    Raises
    ------
    ValueError
        One line: the value, the type, the values it holds (and the array, where the
        arrays' types differ).
    """
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number; got {value!r}") from None
    shown = str(int(number)) if number.is_integer() and abs(number) < 1e16 else repr(number)
    several = len({np.dtype(d) for d in dtypes.values()}) > 1
    for array, dtype in dtypes.items():
        dtype = np.dtype(dtype)
        if dtype.kind == "f":
            top = float(np.finfo(dtype).max)
            if not math.isfinite(number) or abs(number) <= top:
                continue
            held = f"numbers up to {top:.3g} in magnitude, infinities and nan"
        elif dtype.kind in "iub":
            low, high = (0, 1) if dtype.kind == "b" else (np.iinfo(dtype).min, np.iinfo(dtype).max)
            if number.is_integer() and low <= number <= high:
                continue
            held = f"integers {low} to {high}"
        else:
            continue  # (VTK arrays hold integers or floating-point numbers)
        where = f" of the array {array!r}" if several else ""
        article = "an" if dtype.name.startswith("int") else "a"
        raise ValueError(f"{name} {shown} is not {article} {dtype} value{where} ({held})")
    return number


#: The input volume extends this many voxels beyond its outer grid points, where the
#: nearest boundary values are used (``vtkImageReslice``'s default border): each voxel
#: then stands for a full cube.
BORDER = 0.5


class ImageGeometry:
    """Geometry of a regular grid: origin, spacing, dimensions, direction (3x3).

    Points are ``origin + direction @ (spacing * ijk)``, ``i`` fastest (VTK order).

    Parameters
    ----------
    origin : (3,) array_like
        World position of voxel (0, 0, 0).
    spacing : (3,) array_like
        Positive voxel sizes along the grid axes (world units).
    dimensions : (3,) sequence of int
        Voxels along i, j, k.
    direction : (3, 3) array_like, optional
        Orthonormal matrix whose columns are the grid axes in world space (default I).
    """

    def __init__(self, origin, spacing, dimensions, direction=None):
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.spacing = np.asarray(spacing, dtype=np.float64).reshape(3)
        self.dimensions = tuple(int(d) for d in dimensions)
        self.direction = (
            np.eye(3)
            if direction is None
            else np.asarray(direction, dtype=np.float64).reshape(3, 3)
        )
        if len(self.dimensions) != 3 or min(self.dimensions) < 1:
            raise ValueError(f"dimensions must be three positive integers; got {dimensions}")
        if not (np.isfinite(self.spacing).all() and (self.spacing > 0).all()):
            raise ValueError(f"spacing must be positive; got {spacing}")

    @property
    def n_points(self) -> int:
        """Number of grid points."""
        return int(np.prod(self.dimensions))

    @property
    def index_to_world(self) -> np.ndarray:
        """(3, 3) matrix ``M = direction @ diag(spacing)``: ``x = origin + M @ ijk``."""
        return self.direction * self.spacing

    @property
    def world_to_index(self) -> np.ndarray:
        """(3, 3) inverse of :attr:`index_to_world`."""
        return np.linalg.inv(self.index_to_world)

    def ijk(self) -> np.ndarray:
        """(N, 3) integer indices of all grid points, VTK order (i fastest)."""
        nx, ny, nz = self.dimensions
        k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
        return np.column_stack([i.ravel(), j.ravel(), k.ravel()])

    def points(self, ijk=None) -> np.ndarray:
        """World positions of (continuous) grid indices (all points, VTK order, by default)."""
        ijk = self.ijk() if ijk is None else np.asarray(ijk, dtype=np.float64)
        return self.origin + ijk @ self.index_to_world.T

    def continuous_index(self, points) -> np.ndarray:
        """Continuous (i, j, k) indices of world points, (N, 3)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.world_to_index.T

    def bounds_contain(self, points, tol: float = 1e-9) -> np.ndarray:
        """Whether each world point lies in the grid's box, extended by ``tol`` voxels."""
        c = self.continuous_index(points)
        hi = np.asarray(self.dimensions) - 1
        return np.all((c >= -tol) & (c <= hi + tol), axis=1)

    def sub(self, extent) -> ImageGeometry:
        """The geometry of the sub-grid ``extent = (i0, i1, j0, j1, k0, k1)`` (inclusive)."""
        start = np.array(extent[0::2], dtype=np.float64)
        dims = [extent[2 * a + 1] - extent[2 * a] + 1 for a in range(3)]
        return ImageGeometry(self.points(start[None])[0], self.spacing, dims, self.direction)

    def key(self) -> tuple:
        """A hashable key of the grid: equal grids (bit for bit), equal keys."""
        return (
            self.origin.tobytes(),
            self.spacing.tobytes(),
            tuple(int(n) for n in self.dimensions),
            self.direction.tobytes(),
        )

    def same_as(self, other, rtol: float = 1e-9) -> bool:
        """Whether two geometries describe the same grid (up to rounding)."""
        scale = float(np.max(self.spacing))
        return (
            self.dimensions == other.dimensions
            and np.allclose(self.origin, other.origin, rtol=0, atol=rtol * scale)
            and np.allclose(self.spacing, other.spacing, rtol=rtol)
            and np.allclose(self.direction, other.direction, rtol=0, atol=rtol)
        )

    def __repr__(self) -> str:
        return (
            f"ImageGeometry(origin={self.origin.tolist()}, spacing={self.spacing.tolist()}, "
            f"dimensions={self.dimensions})"
        )


# --------------------------------------------------------------------------------------
# inside mask by scan lines
# --------------------------------------------------------------------------------------
@numba.njit(cache=True)
def _edge_sign(ay, az, by, bz, py, pz):  # pragma: no cover - compiled
    """Sign of ``cross((b - a), (p - a))`` with ``p`` perturbed to ``p + (eps, eps^2)``.

    Simulation of simplicity (Edelsbrunner and Muecke 1990): a perturbed point is never
    on an edge, so two triangles sharing an edge never both (or neither) claim a row.
    """
    dy, dz = by - ay, bz - az
    e = dy * (pz - az) - dz * (py - ay)
    if e > 0.0:
        return 1
    if e < 0.0:
        return -1
    # cross(d, (eps, eps^2)) = dy eps^2 - dz eps
    if dz != 0.0:
        return -1 if dz > 0.0 else 1
    return 1 if dy > 0.0 else -1


@numba.njit(cache=True, nogil=True)
def _scanline_winding(tri, vid, i_count, j0, j1, k0, k1, out, crossed, i_lo=0):  # pragma: no cover
    """Winding numbers of the integer grid points ``(i, j, k)`` in a block of rows.

    For every triangle and every row ``(j, k)`` whose (perturbed) projection falls inside
    the triangle's projection on the (j, k) plane, the row crosses the surface once, at
    ``i = x``: entering (outward normal pointing to -i) adds 1 to the points with
    ``i >= x``, leaving subtracts 1 from those with ``i > x``. Points exactly on the
    surface therefore count as inside, as in :func:`~vhm_viz.core.basis.inside_cage`.

    Parameters
    ----------
    tri : (m, 3, 3) float64
        Triangle corners in index coordinates.
    vid : (m, 3) int64
        Global vertex ids of the corners (fix each shared edge's direction).
    i_count : int
        Points per row (``i = 0 .. i_count - 1``).
    j0, j1, k0, k1 : int
        Rows ``j0 <= j < j1``, ``k0 <= k < k1``.
    out : (k1 - k0, j1 - j0, i_count + 1) int16, or empty
        Zeroed on entry; winding numbers in ``[..., :i_count]`` on return.
    crossed : (k1 - k0, j1 - j0, n) uint8, or empty
        Set to 1 at ``i0 - i_lo`` where the row crosses the surface between points
        ``i0 - 1`` and ``i0`` (crossings that cancel, like a sliver between two points,
        included), for ``i_lo <= i0 < i_lo + n``.
    i_lo : int
        The first crossing ``crossed`` holds (with an empty ``out``: a winding number
        needs the whole row).
    """
    m = tri.shape[0]
    for t in range(m):
        ay, az = tri[t, 0, 1], tri[t, 0, 2]
        by, bz = tri[t, 1, 1], tri[t, 1, 2]
        cy, cz = tri[t, 2, 1], tri[t, 2, 2]
        area = (by - ay) * (cz - az) - (bz - az) * (cy - ay)  # = x of the normal
        if area == 0.0:
            continue
        jlo = max(j0, int(math.ceil(min(ay, by, cy))))
        jhi = min(j1 - 1, int(math.floor(max(ay, by, cy))))
        klo = max(k0, int(math.ceil(min(az, bz, cz))))
        khi = min(k1 - 1, int(math.floor(max(az, bz, cz))))
        if jlo > jhi or klo > khi:
            continue
        sgn = 1 if area > 0.0 else -1
        # the plane: nx (x - ax) + ny (y - ay) + nz (z - az) = 0
        ax = tri[t, 0, 0]
        ux, uy, uz = tri[t, 1, 0] - ax, by - ay, bz - az
        wx, wy, wz = tri[t, 2, 0] - ax, cy - ay, cz - az
        nyc = uz * wx - ux * wz
        nzc = ux * wy - uy * wx
        for k in range(klo, khi + 1):
            for j in range(jlo, jhi + 1):
                inside = True
                for e in range(3):
                    p, q = e, (e + 1) % 3
                    # evaluate every shared edge in one direction (smaller vertex id first)
                    if vid[t, p] < vid[t, q]:
                        s = _edge_sign(tri[t, p, 1], tri[t, p, 2], tri[t, q, 1], tri[t, q, 2], j, k)
                    else:
                        s = -_edge_sign(
                            tri[t, q, 1], tri[t, q, 2], tri[t, p, 1], tri[t, p, 2], j, k
                        )
                    if s != sgn:
                        inside = False
                        break
                if not inside:
                    continue
                x = ax - (nyc * (j - ay) + nzc * (k - az)) / area
                if area < 0.0:  # entering: points with i >= x
                    i0 = int(math.ceil(x))
                    d = 1
                else:  # leaving: points with i > x
                    i0 = int(math.floor(x)) + 1
                    d = -1
                if i0 > i_count:
                    continue
                # a crossing before point i_lo - 1 lies outside the grid edges that
                # ``crossed`` describes: it marks no point
                c = i0 - i_lo
                if crossed.size and 0 <= c < crossed.shape[2]:
                    crossed[k - k0, j - j0, c] = 1
                if out.size:
                    out[k - k0, j - j0, max(i0, 0)] += d
    for k in range(out.shape[0]):
        for j in range(out.shape[1]):
            acc = 0
            for i in range(i_count):
                acc += out[k, j, i]
                out[k, j, i] = acc


def inside_mask(geometry: ImageGeometry, vertices, faces, rows=None, i_count=None) -> np.ndarray:
    """Which grid points lie inside a closed, outward-oriented cage.

    Counts signed crossings of the surface along each grid row (the generalised winding
    number of a closed surface is this integer). Shared edges and vertices are resolved
    by symbolic perturbation, so every row crosses a watertight surface consistently.
    Points on the surface count as inside, as in :func:`~vhm_viz.core.basis.inside_cage`;
    points within rounding of the surface may be classified either way.

    Parameters
    ----------
    geometry : ImageGeometry
        The grid (its direction may be any rotation).
    vertices : (n, 3) array_like
        Cage vertices (world).
    faces : (m, 3) array_like of int
        Outward-oriented triangles.
    rows : (j0, j1, k0, k1), optional
        Only the rows ``j0 <= j < j1``, ``k0 <= k < k1`` (default: all). Rows beyond the
        grid's dimensions are allowed (the lattice of a volume engine overhangs it).
    i_count : int, optional
        Points per row (default the grid's ``nx``).

    Returns
    -------
    (k1 - k0, j1 - j0, i_count) bool
    """
    nx, ny, nz = geometry.dimensions
    j0, j1, k0, k1 = (0, ny, 0, nz) if rows is None else (int(r) for r in rows)
    i_count = nx if i_count is None else int(i_count)
    v, f = _index_triangles(geometry, vertices, faces)
    out = np.zeros((max(k1 - k0, 0), max(j1 - j0, 0), i_count + 1), dtype=np.int16)
    if out.size:
        none = np.zeros((0, 0, 0), dtype=np.uint8)
        _scanline_winding(np.ascontiguousarray(v[f]), f, i_count, j0, j1, k0, k1, out, none, 0)
    return out[..., :i_count] >= 1


def _index_triangles(geometry: ImageGeometry, vertices, faces):
    """Cage vertices in index coordinates and the faces, outward in index space too."""
    v = geometry.continuous_index(np.asarray(vertices, dtype=np.float64))
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if np.linalg.det(geometry.index_to_world) < 0:
        # a mirrored grid turns the faces over in index space: keep them outward there
        f = np.ascontiguousarray(f[:, ::-1])
    return v, f


def surface_mask(geometry: ImageGeometry, vertices, faces, rows=None) -> np.ndarray:
    """Grid points next to the cage surface: an edge of the grid from them crosses it.

    Scan lines along each of the three axes record every crossing, also pairs that cancel
    (a sliver of the outside between two points, which :func:`inside_mask` cannot see).
    A point is marked when the surface crosses the grid edge to one of its six neighbours;
    away from marked points, the inside of a grid cube is decided by its corners.

    Parameters
    ----------
    geometry : ImageGeometry
    vertices : (n, 3) array_like
        Cage vertices (world).
    faces : (m, 3) array_like of int
        Outward-oriented triangles.
    rows : (j0, j1, k0, k1), optional
        Only the points with ``j0 <= j < j1``, ``k0 <= k < k1`` (default: all), as in
        :func:`inside_mask`; their edges to neighbours outside these rows count too.

    Returns
    -------
    (k1 - k0, j1 - j0, nx) bool
    """
    v, f = _index_triangles(geometry, vertices, faces)
    dims = geometry.dimensions
    j0, j1, k0, k1 = (0, dims[1], 0, dims[2]) if rows is None else (int(r) for r in rows)
    j0, k0 = max(j0, 0), max(k0, 0)
    j1, k1 = max(min(j1, dims[1]), j0), max(min(k1, dims[2]), k0)
    near = np.zeros((k1 - k0, j1 - j0, dims[0]), dtype=bool)
    if not near.size:
        return near
    # per scan axis: its rows (the other two axes, cyclic order), restricted where the
    # rows allow it, and the crossings along it that bound the requested points (the
    # crossing at c lies between points c - 1 and c)
    spans = {
        0: ((j0, j1, k0, k1), 0, dims[0]),
        1: ((k0, k1, 0, dims[0]), j0, j1),
        2: ((0, dims[0], j0, j1), k0, k1),
    }
    empty = np.zeros((0, 0, 0), dtype=np.int16)
    for axis in range(3):
        # cyclic permutations keep the faces' orientation: axis ``axis`` becomes i
        order = [(axis + c) % 3 for c in range(3)]
        (a0, a1, b0, b1), c0, c1 = spans[axis]
        tri = np.ascontiguousarray(v[:, order][f])
        crossed = np.zeros((b1 - b0, a1 - a0, c1 - c0 + 1), dtype=np.uint8)
        _scanline_winding(tri, f, dims[order[0]], a0, a1, b0, b1, empty, crossed, c0)
        hit = crossed.view(bool)
        adjacent = hit[..., 1:] | hit[..., :-1]  # the points on both sides of a crossing
        del crossed, hit
        back = {0: (0, 1, 2), 1: (1, 2, 0), 2: (2, 0, 1)}[axis]
        near |= np.transpose(adjacent, back)
    return near


# --------------------------------------------------------------------------------------
# sampling
# --------------------------------------------------------------------------------------
@numba.njit(inline="always", cache=True)
def _clamp(i, n):  # pragma: no cover - compiled
    return 0 if i < 0 else (n - 1 if i > n - 1 else i)


@numba.njit(inline="always", cache=True)
def _catmull_rom(t, w):  # pragma: no cover - compiled
    """Keys' cubic convolution weights (a = -1/2) of the taps at -1, 0, 1, 2."""
    t2 = t * t
    t3 = t2 * t
    w[0] = -0.5 * t3 + t2 - 0.5 * t
    w[1] = 1.5 * t3 - 2.5 * t2 + 1.0
    w[2] = -1.5 * t3 + 2.0 * t2 + 0.5 * t
    w[3] = 0.5 * t3 - 0.5 * t2


@numba.njit(inline="always", cache=True)
def sample_linear(vol, u, p, shift, weights, round_clip, lo, hi, out):  # pragma: no cover
    """Trilinear interpolation of point data at one continuous index, into a row of ``out``.

    The point samplers (this, :func:`sample_nearest`, :func:`sample_cubic`: one per
    kind of :data:`INTERPOLATIONS`, the same parameters) are inlined into the compiled
    loops over voxels that resample a volume: those run on their own threads and hold
    the scratch, so nothing is allocated here, and a loop compiles the code of its kind
    only. Within the half-voxel border beyond the grid the boundary values are used
    (:data:`BORDER`).

    Parameters
    ----------
    vol : (nz, ny, nx, c) array, any numeric dtype
        Point data of the grid (a view of VTK's i-fastest array).
    u : (P, 3) float64
        Continuous (i, j, k) indices, of ``vol`` less ``shift``: ``u[p] - shift`` must lie
        within ``[-0.5, n - 0.5]``.
    p : int
        The row of ``u`` read and of ``out`` written (cast to its dtype).
    shift : (3,) float64
        Where ``vol`` starts in the indices of ``u`` (a box of a larger grid; or zeros).
    weights : (3, 4) float64
        Scratch (of the cubic's weights).
    round_clip : bool
        Round the value and clip it to ``[lo, hi]`` (an integer ``out``; the nearest
        voxel's values are copied as they are).
    lo, hi : float
    out : (P, c) array
    """
    nz, ny, nx, nc = vol.shape
    # clamp to the grid: within the half-voxel border the boundary values are used
    x = min(max(u[p, 0] - shift[0], 0.0), nx - 1.0)
    y = min(max(u[p, 1] - shift[1], 0.0), ny - 1.0)
    z = min(max(u[p, 2] - shift[2], 0.0), nz - 1.0)
    i0, j0, k0 = int(x), int(y), int(z)
    fx, fy, fz = x - i0, y - j0, z - k0
    i1, j1, k1 = min(i0 + 1, nx - 1), min(j0 + 1, ny - 1), min(k0 + 1, nz - 1)
    for c in range(nc):
        a = (1 - fx) * vol[k0, j0, i0, c] + fx * vol[k0, j0, i1, c]
        b = (1 - fx) * vol[k0, j1, i0, c] + fx * vol[k0, j1, i1, c]
        d = (1 - fx) * vol[k1, j0, i0, c] + fx * vol[k1, j0, i1, c]
        e = (1 - fx) * vol[k1, j1, i0, c] + fx * vol[k1, j1, i1, c]
        v = (1 - fz) * ((1 - fy) * a + fy * b) + fz * ((1 - fy) * d + fy * e)
        out[p, c] = min(max(np.rint(v), lo), hi) if round_clip else v


@numba.njit(inline="always", cache=True)
def sample_nearest(vol, u, p, shift, weights, round_clip, lo, hi, out):  # pragma: no cover
    """The nearest voxel's values at one point, copied exactly (for label maps).

    As :func:`sample_linear` (``round_clip`` does not apply).
    """
    nz, ny, nx, nc = vol.shape
    i = _clamp(int(math.floor((u[p, 0] - shift[0]) + 0.5)), nx)
    j = _clamp(int(math.floor((u[p, 1] - shift[1]) + 0.5)), ny)
    k = _clamp(int(math.floor((u[p, 2] - shift[2]) + 0.5)), nz)
    for c in range(nc):
        out[p, c] = vol[k, j, i, c]


@numba.njit(inline="always", cache=True)
def sample_cubic(vol, u, p, shift, weights, round_clip, lo, hi, out):  # pragma: no cover
    """Catmull-Rom cubic convolution at one point (interpolating, may overshoot).

    Keys 1981, ``a = -1/2``; as :func:`sample_linear`.
    """
    nz, ny, nx, nc = vol.shape
    x = min(max(u[p, 0] - shift[0], 0.0), nx - 1.0)
    y = min(max(u[p, 1] - shift[1], 0.0), ny - 1.0)
    z = min(max(u[p, 2] - shift[2], 0.0), nz - 1.0)
    i0, j0, k0 = int(math.floor(x)), int(math.floor(y)), int(math.floor(z))
    wx, wy, wz = weights[0], weights[1], weights[2]
    _catmull_rom(x - i0, wx)
    _catmull_rom(y - j0, wy)
    _catmull_rom(z - k0, wz)
    for c in range(nc):
        acc = 0.0
        for a in range(4):
            kk = _clamp(k0 - 1 + a, nz)
            for b in range(4):
                jj = _clamp(j0 - 1 + b, ny)
                row = 0.0
                for d in range(4):
                    row += wx[d] * vol[kk, jj, _clamp(i0 - 1 + d, nx), c]
                acc += wz[a] * wy[b] * row
        out[p, c] = min(max(np.rint(acc), lo), hi) if round_clip else acc
