"""The region a certificate covers: a box, balls, tetrahedra or the cage's interior.

:func:`~vhm_viz.core.certify.certify_injectivity` covers a region with cubes; a
:class:`Region` tells, for a batch of cubes, which lie outside it, which meet it and which
lie inside it, so that the octree keeps only the cubes that matter.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.derivative_bounds import cage_distance
from vhm_viz.core.inside import inside_cage, winding_number

__all__ = ["INSIDE", "MEETS", "OUTSIDE", "Region", "as_region", "default_margin"]

#: Cube classes of :meth:`Region.classify`.
OUTSIDE, MEETS, INSIDE = 0, 1, 2


class Region:
    """What to certify: a set of points, known through a conservative cube test.

    A region has a bounding box (``lo``, ``hi``), a cube test :meth:`classify` (outside,
    may meet, or entirely inside; conservative: a cube that meets the region is never said
    to be outside, so some cubes are certified needlessly, none is skipped wrongly) and an
    exact membership test :meth:`contains` (a witness must lie in the region). The children
    of a cube entirely inside are entirely inside, so the octree tests only cubes near the
    region's boundary. Build one with a class method:

    * :meth:`box` -- an axis-aligned box (an image's voxel box, a bar's solid);
    * :meth:`tetrahedra` -- the solid of a tet mesh (any mesh VTK triangulates into tets;
      :func:`vhm_viz.filters.region_of` converts datasets);
    * :meth:`balls` -- a union of balls (e.g. the voxels of a solid);
    * :meth:`cage_interior` -- the space inside the cage farther than ``margin`` from it;

    or give ``test(centres, half_extents) -> (k,) int8`` (:data:`OUTSIDE`, :data:`MEETS`,
    :data:`INSIDE`; booleans mean outside / meets) and ``contains(points) -> (k,) bool``.

    Attributes
    ----------
    kind : str
    lo, hi : (3,) float64
        Bounding box.
    description : dict
        What the region is, for reports (``metrics.json``).
    """

    def __init__(self, kind: str, lo, hi, test, contains, description: dict):
        self.kind = kind
        self.lo = np.asarray(lo, dtype=np.float64).reshape(3)
        self.hi = np.asarray(hi, dtype=np.float64).reshape(3)
        if not (np.isfinite(self.lo).all() and np.isfinite(self.hi).all()):
            raise ValueError("the region's bounds are not finite")
        if (self.hi < self.lo).any():
            raise ValueError(f"empty region: lo {self.lo} > hi {self.hi}")
        self._test = test
        self._contains = contains
        self.description = {"kind": kind, **description}

    def classify(self, centres: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
        """Where each axis-aligned cube lies: :data:`OUTSIDE`, :data:`MEETS` or :data:`INSIDE`.

        Parameters
        ----------
        centres : (k, 3) float64
        half_extents : (3,) float64
            Common to all cubes.

        Returns
        -------
        (k,) int8
            Conservative: ``OUTSIDE`` only for cubes that do not meet the region,
            ``INSIDE`` only for cubes that lie entirely in it.
        """
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        e = np.asarray(half_extents, dtype=np.float64).reshape(3)
        in_box = np.all((c + e >= self.lo) & (c - e <= self.hi), axis=1)
        out = in_box.astype(np.int8)  # MEETS where the boxes overlap
        if self._test is None:
            out[np.all((c - e >= self.lo) & (c + e <= self.hi), axis=1)] = INSIDE
        elif in_box.any():
            out[in_box] = np.asarray(self._test(c[in_box], e), dtype=np.int8)
        return out

    def may_meet(self, centres: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
        """Whether each cube may meet the region: ``classify(...) != OUTSIDE``, (k,) bool."""
        return self.classify(centres, half_extents) != OUTSIDE

    def contains(self, points) -> np.ndarray:
        """Whether each point lies in the region (closed set), shape (k,) bool."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        inside = np.all((p >= self.lo) & (p <= self.hi), axis=1)
        if self._contains is None or not inside.any():
            return inside
        inside[inside] = self._contains(p[inside])
        return inside

    @property
    def diagonal(self) -> float:
        """Length of the bounding box's diagonal."""
        return float(np.linalg.norm(self.hi - self.lo))

    # ---------------------------------------------------------------- constructors
    @classmethod
    def box(cls, lo, hi) -> Region:
        """The axis-aligned box ``[lo, hi]``."""
        lo = np.asarray(lo, dtype=np.float64).reshape(3)
        hi = np.asarray(hi, dtype=np.float64).reshape(3)
        return cls("box", lo, hi, None, None, {"lo": lo.tolist(), "hi": hi.tolist()})

    @classmethod
    def balls(cls, centres, radius) -> Region:
        """The union of the balls ``B(centres[i], radius[i])``.

        Parameters
        ----------
        centres : (k, 3) array_like
        radius : float or (k,) array_like
        """
        balls = _Balls(centres, radius)

        def contains(p):
            out = np.zeros(len(p), dtype=bool)
            for i, cand in enumerate(balls.candidates(p)):
                d = np.linalg.norm(balls.centres[cand] - p[i], axis=1)
                out[i] = bool((d <= balls.radii[cand]).any())
            return out

        return cls(
            "balls", *balls.bounds(), balls.near, contains,
            {"balls": int(len(balls.centres)), "max_radius": float(balls.radii.max())},
        )  # fmt: skip

    @classmethod
    def tetrahedra(cls, points, tets) -> Region:
        """The solid of a tet mesh (each tet is covered by the ball about its centroid).

        Parameters
        ----------
        points : (N, 3) array_like
        tets : (T, 4) array_like of int
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        t = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
        if len(t) == 0:
            raise ValueError("a tet-mesh region needs at least one tetrahedron")
        if t.min() < 0 or t.max() >= len(p):
            raise ValueError(f"tet indices must lie in [0, {len(p)})")
        corners = p[t]
        centroid = corners.mean(axis=1)
        balls = _Balls(centroid, np.linalg.norm(corners - centroid[:, None], axis=2).max(axis=1))

        def contains(q):
            out = np.zeros(len(q), dtype=bool)
            for i, cand in enumerate(balls.candidates(q)):
                if cand.size:
                    out[i] = bool(_in_tetrahedra(q[i], corners[cand]).any())
            return out

        used = p[np.unique(t)]  # the solid's bounding box is its vertices'
        description = {"tetrahedra": int(len(t))}
        return cls("tetrahedra", used.min(0), used.max(0), balls.near, contains, description)

    @classmethod
    def cage_interior(cls, cage, margin: float) -> Region:
        """Points inside the cage whose distance to it is at least ``margin``.

        Parameters
        ----------
        cage : Cage
        margin : float
            In length units (> 0: the bound needs a gap between the cubes and the cage).
        """
        if not margin > 0:
            raise ValueError(f"the margin must be positive; got {margin}")
        v = np.ascontiguousarray(cage.vertices, dtype=np.float64)
        f = np.ascontiguousarray(cage.faces, dtype=np.int64)

        def test(cubes, e):
            r = float(np.linalg.norm(e))
            d = cage_distance(cubes, v, f)
            inside = inside_cage(winding_number(cubes, v, f))
            # inside: the ball reaches depth >= margin; outside: it crosses the cage by margin
            state = np.where(inside, d + r >= margin, r >= d + margin).astype(np.int8)
            state[inside & (d - r >= margin)] = INSIDE  # the whole ball is deep enough
            return state

        def contains(p):
            return inside_cage(winding_number(p, v, f)) & (cage_distance(p, v, f) >= margin)

        lo, hi = v.min(0) + margin, v.max(0) - margin
        if (hi < lo).any():
            raise ValueError(f"the margin {margin} leaves nothing of the cage's interior")
        return cls("cage", lo, hi, test, contains, {"margin": float(margin)})


class _Balls:
    """Balls in a few k-d trees, one per radius class (so a few big balls cost nothing)."""

    def __init__(self, centres, radius):
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        if len(c) == 0:
            raise ValueError("a region of balls needs at least one ball")
        rad = np.ascontiguousarray(np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(c),)))
        if not (np.isfinite(c).all() and np.isfinite(rad).all()) or (rad < 0).any():
            raise ValueError("ball centres must be finite and radii non-negative")
        self.centres, self.radii = c, rad
        top = max(float(rad.max()), 1e-300)
        # classes of radius (top/2^(k+1), top/2^k]; the tiny ones share the last class
        cls = np.minimum(np.floor(-np.log2(np.maximum(rad, top * 1e-6) / top)), 16).astype(int)
        self.classes = []
        from vhm_viz.core.scipy_extensions import kd_tree

        for k in np.unique(cls):
            ids = np.nonzero(cls == k)[0]
            self.classes.append((ids, kd_tree(c[ids]), float(rad[ids].max())))

    def bounds(self):
        """Bounding box of the union of balls."""
        r = self.radii[:, None]
        return (self.centres - r).min(0), (self.centres + r).max(0)

    def near(self, points, half_extents) -> np.ndarray:
        """Whether a cube (centre, half extents) may meet a ball: |c - c_i| <= |e| + r_i."""
        reach = float(np.linalg.norm(half_extents))
        out = np.zeros(len(points), dtype=bool)
        for _, tree, r_max in self.classes:
            todo = ~out
            if not todo.any():
                break
            d, _ = tree.query(points[todo], k=1, distance_upper_bound=reach + r_max)
            out[np.nonzero(todo)[0][np.isfinite(d)]] = True
        return out

    def candidates(self, points) -> list[np.ndarray]:
        """For each point, the balls of its radius classes close enough to contain it."""
        out = [[] for _ in range(len(points))]
        for ids, tree, r_max in self.classes:
            for i, hits in enumerate(tree.query_ball_point(points, r_max)):
                if hits:
                    out[i].append(ids[np.asarray(hits, dtype=np.int64)])
        return [np.concatenate(o) if o else np.zeros(0, np.int64) for o in out]


def _in_tetrahedra(q: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Whether the point ``q`` lies in each tetrahedron ``corners`` (k, 4, 3) (closed)."""
    e = corners[:, 1:] - corners[:, :1]  # (k, 3, 3) rows: edges from corner 0
    det = np.linalg.det(e)
    ok = np.abs(det) > 0
    out = np.zeros(len(corners), dtype=bool)
    if ok.any():
        lam = np.linalg.solve(np.swapaxes(e[ok], 1, 2), (q - corners[ok, 0])[:, :, None])[..., 0]
        tol = 1e-12
        out[ok] = (lam >= -tol).all(axis=1) & (lam.sum(axis=1) <= 1 + tol)
    return out


def as_region(region, cage=None) -> Region:
    """A :class:`Region` from a Region, a ``(lo, hi)`` box, or ``"cage"`` (needs ``cage``)."""
    if isinstance(region, Region):
        return region
    if isinstance(region, str):
        if region != "cage" or cage is None:
            raise ValueError(f"unknown region {region!r}; use 'cage', a Region or (lo, hi)")
        return Region.cage_interior(cage, default_margin(cage))
    if hasattr(region, "GetNumberOfCells") or hasattr(region, "n_cells"):
        raise TypeError(
            "the numeric core takes a Region: convert a dataset with "
            "vhm_viz.region_of(dataset, cage), or call dataset.vhm.certify(deformer)"
        )
    arr = np.asarray(region, dtype=np.float64)
    if arr.shape == (2, 3):
        return Region.box(arr[0], arr[1])
    raise TypeError(f"cannot make a region of {type(region).__name__}; use a Region")


def default_margin(cage) -> float:
    """The default margin of the cage interior: 2% of the cage's bounding-box diagonal."""
    v = np.asarray(cage.vertices, dtype=np.float64)
    return 0.02 * float(np.linalg.norm(v.max(0) - v.min(0)))
