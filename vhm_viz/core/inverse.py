"""Inverse of a harmonic map by Newton's method, and pull-back resampling of volumes.

Pure numpy/scipy. To resample a deformed volume onto a regular grid, each output voxel
centre ``y`` is pulled back to its pre-image ``x`` with ``f(x) = y``:

1. a *forward lattice* (the input grid points inside the cage, subsampled with a stride)
   is deformed once; a k-d tree on the deformed positions gives every ``y`` a starting
   point ``x_0`` (the rest position of its nearest deformed lattice point). Output points
   farther from the deformed lattice than its largest deformed edge have no pre-image in
   the volume and are not iterated;
2. Newton iterations ``x <- x - J(x)^{-1} (f(x) - y)`` with the closed-form Jacobian of the
   map (``HarmonicMap.evaluate(order=1)``), until ``|f(x) - y|`` is below the tolerance;
3. the input arrays are sampled at ``x`` by trilinear interpolation.

Like ``vtkImageReslice`` (its default border), the input volume extends half a voxel
beyond its outer grid points, where the interpolation uses the nearest boundary values:
each input voxel then stands for a full cube, and the voxel sums of the input and of a
rigidly moved output agree. Voxels whose pre-image leaves the cage, lies outside this
extended volume, or for which Newton does not converge get the *fill value* and
``vtkValidPointMask = 0`` (the ``vtkProbeFilter`` convention).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from vhm_viz.core.errors import AbortedError

__all__ = ["ImageGeometry", "inverse_map", "forward_lattice", "trilinear", "pull_back"]

# Half a voxel of border around the input grid (vtkImageReslice's default).
_BORDER = 0.5


class ImageGeometry:
    """Geometry of a regular grid: origin, spacing, dimensions, direction (3x3).

    Points are ``origin + direction @ (spacing * ijk)``, ``i`` fastest (VTK order).
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

    @property
    def n_points(self) -> int:
        """Number of grid points."""
        return int(np.prod(self.dimensions))

    def ijk(self, index_range=None) -> np.ndarray:
        """(N, 3) integer indices of the grid points, VTK order (i fastest)."""
        nx, ny, nz = self.dimensions
        k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
        return np.column_stack([i.ravel(), j.ravel(), k.ravel()])

    def points(self, ijk=None) -> np.ndarray:
        """World positions of grid indices (all points, VTK order, by default)."""
        ijk = self.ijk() if ijk is None else np.asarray(ijk)
        return self.origin + (ijk * self.spacing) @ self.direction.T

    def continuous_index(self, points) -> np.ndarray:
        """Continuous (i, j, k) indices of world points."""
        local = (np.asarray(points) - self.origin) @ self.direction
        return local / self.spacing

    def bounds_contain(self, points, tol: float = 1e-9) -> np.ndarray:
        """Whether each point lies in the grid's box (up to ``tol`` voxels)."""
        c = self.continuous_index(points)
        hi = np.asarray(self.dimensions) - 1
        return np.all((c >= -tol) & (c <= hi + tol), axis=1)


def forward_lattice(
    harmonic_map, geometry: ImageGeometry, stride: int | None = None, max_points: int = 40000
):
    """Deform a subsampled lattice of the input grid (points inside the cage).

    Parameters
    ----------
    harmonic_map : HarmonicMap
    geometry : ImageGeometry
        The input volume's grid.
    stride : int, optional
        Take every ``stride``-th grid point along each axis (default: the smallest stride
        giving at most ``max_points`` lattice points). The last index is always included.
    max_points : int

    Returns
    -------
    rest : (L, 3) float64
        Lattice points inside the cage.
    deformed : (L, 3) float64
        Their images.
    reach : float
        Largest deformed lattice edge (world units): output points farther than this from
        every deformed lattice point have no pre-image inside the sampled volume.
    """
    dims = np.asarray(geometry.dimensions)
    if stride is None:
        stride = 1
        while np.prod([len(_axis(d, stride)) for d in dims]) > max_points:
            stride += 1
    axes = [_axis(d, stride) for d in dims]
    kk, jj, ii = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    ijk = np.column_stack([ii.ravel(), jj.ravel(), kk.ravel()])
    rest = geometry.points(ijk)
    f, _, _ = harmonic_map.evaluate(rest, order=0, outside="nan")
    shape = (len(axes[2]), len(axes[1]), len(axes[0]), 3)
    grid = f.reshape(shape)
    reach = 0.0
    for ax in range(3):
        if grid.shape[ax] > 1:
            d = np.linalg.norm(np.diff(grid, axis=ax), axis=-1)
            if np.isfinite(d).any():
                reach = max(reach, float(np.nanmax(d)))
    if reach == 0.0:
        reach = float(np.max(geometry.spacing) * stride)
    ok = np.isfinite(f).all(axis=1)
    return rest[ok], f[ok], reach


def _axis(n: int, stride: int) -> np.ndarray:
    a = np.arange(0, n, stride)
    if a[-1] != n - 1:
        a = np.append(a, n - 1)
    return a


def inverse_map(
    harmonic_map,
    targets,
    starts,
    *,
    tolerance: float,
    max_iterations: int = 30,
    progress=None,
    abort=None,
):
    """Solve ``f(x) = y`` for each target ``y`` by Newton's method from ``starts``.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    targets : (N, 3) array_like
        The points ``y``.
    starts : (N, 3) array_like
        Initial guesses ``x_0`` (inside the cage).
    tolerance : float
        Stop when ``|f(x) - y| <= tolerance`` (world units).
    max_iterations : int
    progress : callable(fraction, message), optional
    abort : callable() -> bool, optional

    Returns
    -------
    x : (N, 3) float64
        Pre-images (NaN where not found).
    ok : (N,) bool
        Converged inside the cage.
    iterations : int
        Largest number of Newton iterations used.
    """
    y = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    x = np.array(starts, dtype=np.float64).reshape(-1, 3)
    n = len(y)
    ok = np.zeros(n, bool)
    active = np.arange(n)
    used = 0
    done = 0
    for it in range(max_iterations + 1):
        if active.size == 0:
            break
        if abort is not None and abort():
            raise AbortedError("aborted")
        f, jac, _ = harmonic_map.evaluate(x[active], order=1, outside="nan")
        r = f - y[active]
        norm = np.linalg.norm(r, axis=1)
        conv = norm <= tolerance
        ok[active[conv]] = True
        bad = ~np.isfinite(norm)
        keep = ~conv & ~bad
        done += int(conv.sum() + bad.sum())
        if progress is not None:
            progress(min(1.0, done / max(n, 1)), "inverting")
        if it == max_iterations or not keep.any():
            used = it
            active = active[keep]
            break
        act = active[keep]
        jk, rk = jac[keep], r[keep]
        det = np.linalg.det(jk)
        good = np.abs(det) > 1e-14
        step = np.full_like(rk, np.nan)
        if good.any():
            step[good] = np.linalg.solve(jk[good], rk[good][..., None])[..., 0]
        x[act] -= step
        active = act[np.isfinite(step).all(axis=1)]
        used = it + 1
    x[~ok] = np.nan
    return x, ok, used


def trilinear(values: np.ndarray, geometry: ImageGeometry, points, fill_value: float):
    """Trilinear interpolation of point data on a grid at world points.

    Parameters
    ----------
    values : (N,) or (N, c) array
        Point data in VTK order (i fastest), ``N = prod(dimensions)``.
    geometry : ImageGeometry
    points : (P, 3) array_like
        World points (NaN rows give ``fill_value``).
    fill_value : float

    Returns
    -------
    (P,) or (P, c) float64
    """
    nx, ny, nz = geometry.dimensions
    v = np.asarray(values)
    comps = 1 if v.ndim == 1 else v.shape[1]
    vol = v.reshape(nz, ny, nx, comps).astype(np.float64)
    c = geometry.continuous_index(points)
    finite = np.isfinite(c).all(axis=1)
    border = geometry.bounds_contain(np.where(finite[:, None], points, 0.0), tol=_BORDER)
    finite &= border
    # within the border, clamp to the grid (nearest boundary value)
    c = np.clip(c, 0.0, np.asarray(geometry.dimensions) - 1.0)
    coords = np.where(finite[:, None], c, -10.0)[:, ::-1].T  # (k, j, i) order
    out = np.empty((len(c), comps))
    for q in range(comps):
        out[:, q] = map_coordinates(
            vol[..., q], coords, order=1, mode="constant", cval=fill_value, prefilter=False
        )
    out[~finite] = fill_value
    return out[:, 0] if v.ndim == 1 else out


def pull_back(
    harmonic_map,
    source: ImageGeometry,
    target_points,
    *,
    tolerance: float,
    max_iterations: int = 30,
    progress=None,
    abort=None,
    lattice=None,
):
    """Pre-images of output grid points inside the source volume (see module doc).

    Returns
    -------
    x : (P, 3) float64
        Pre-images, NaN where there is none.
    valid : (P,) bool
        Converged, inside the cage and inside the source volume.
    """
    y = np.asarray(target_points, dtype=np.float64).reshape(-1, 3)
    rest, deformed, reach = (
        lattice if lattice is not None else forward_lattice(harmonic_map, source)
    )
    x = np.full_like(y, np.nan)
    valid = np.zeros(len(y), bool)
    if len(rest) == 0 or len(y) == 0:
        return x, valid
    dist, nearest = cKDTree(deformed).query(y, distance_upper_bound=1.001 * reach)
    cand = np.nonzero(np.isfinite(dist))[0]
    if cand.size:
        xc, okc, _ = inverse_map(
            harmonic_map,
            y[cand],
            rest[nearest[cand]],
            tolerance=tolerance,
            max_iterations=max_iterations,
            progress=progress,
            abort=abort,
        )
        inside = okc & source.bounds_contain(np.where(okc[:, None], xc, 0.0), tol=_BORDER)
        x[cand[inside]] = xc[inside]
        valid[cand[inside]] = True
    return x, valid
