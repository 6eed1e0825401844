"""Certified local injectivity: a proof that ``det J > 0`` on a whole region, or a witness.

A slice or a histogram of ``det J`` shows only the points that happened to be sampled, and
harmonic maps with position constraints can fold between them (paper Section 3, the local
step). :func:`certify_injectivity` answers for *every* point of a region, in the spirit of
the certified harmonic maps of Liao et al. (Real-time locally injective volumetric
deformation, ACM Trans. Graph. 40(4), article 74, 2021): it covers the region with cubes
and proves, cube by cube, that the Jacobian cannot become singular, or finds a point where
it already is. The answer is one of

* **certified** -- every cube covering the region was proved: ``det J > 0`` everywhere in
  it, so the map is locally injective (orientation-preserving) there;
* **not injective** -- a *witness* was found: a point where the exactly evaluated
  ``det J <= 0``;
* **undecided** -- the budget of cubes ran out (or cubes were too close to the cage to be
  bounded); the cubes left are returned. Undecided is never reported as certified.

The bound
---------
The map is (paper eq. 1, discrete form of Section 2.1)

    f(y) = sum_t int_t a(q) K1(q, y) dA  +  sum_t b_t int_t K0(q, y) dA,
    K0 = 1 / (4 pi |q - y|),   K1 = N_t . grad_y K0,

with ``a`` the piecewise-linear interpolation of the vertex coefficients ``a_v`` and
``b`` constant (``b_t``) on each face. Take a cube with centre ``p``, half extents ``e`` and
circumradius ``r = |e|``. For ``p + h`` in the cube, Taylor's theorem with integral
remainder gives

    J(p + h) = J(p) + H(p)[h] + R(h),    ||R(h)||_F <= 1/2 M3 |h|^2,                   (1)

where ``M3 = sqrt(sum_i M3_i^2)`` and ``M3_i`` bounds the third derivative of ``f_i`` on the
ball ``B(p, r)`` (``|D^3 f_i[., h, h]| <= M3_i |h|^2``). Weyl's inequality for singular
values, ``sigma_min(A + E) >= sigma_min(A) - ||E||_2``, bounds the whole cube:

    sigma_min(J(p + h)) >= sigma_min(J(p)) - max_corners sqrt(h^T G h) - 1/2 M3 r^2,   (2)

with ``G_kl = sum_ij H_ijk H_ijl`` (``||H[h]||_2 <= ||H[h]||_F = sqrt(h^T G h)``, a convex
function of ``h``, so its maximum over the cube is at a corner). When the right-hand side
exceeds a rounding margin and ``det J(p) > 0``, ``J`` is nonsingular on the whole cube and
``det J``, being continuous, keeps its sign: ``det J > 0`` on the cube.

*M3 from the boundary integral.* The k-th derivatives of ``1/|x|`` are bounded by
``k! / |x|^(k+1)`` in operator norm: the directional ones are ``k! P_k(cos theta) /
|x|^(k+1)`` (the generating function of the Legendre polynomials, ``|P_k| <= 1``), and a
symmetric multilinear form attains its norm on the diagonal (Banach 1938). So
``|D^3 K0| <= 6 / (4 pi d^4)`` and ``|D^3 K1| <= |D^4 K0| <= 24 / (4 pi d^5)``, ``d = |q - y|``:

    M3_i <= 1/(4 pi) sum_t [ 24 int_t |a'_i(q)| d^-5 dA  +  6 |b'_ti| int_t d^-4 dA ].  (3)

*Subtracting an affine map.* The basis reproduces ``y -> A y + T`` exactly with
``a(q) = A q + T``, ``b_t = A N_t`` (paper Section 2.1), and an affine map has no third
derivative, so (3) may use the coefficients minus any affine map:
``a'_v = a_v - A x_v - T``, ``b'_t = b_t - A N_t``. We subtract the tangent map at ``p``
(``A = J(p)``, ``T = f(p) - J(p) p``): on the faces near the cube, where the kernels are
large, the coefficients follow the tangent map closely. Without this step even the
identity map gets a useless bound.

*Face integrals.* For ``y`` in the ball and a (sub-)triangle ``s`` of area ``A`` at distance
``delta = dist(p, s) - r > 0`` from the ball, ``s`` lies outside the sphere of radius
``delta`` about ``y``; on a plane ``dA = pi d(d^2)``, so by the bathtub principle

    int_s d^-k dA <= 2 pi / (k - 2) [delta^(2-k) - (delta^2 + A / pi)^((2-k)/2)],       (4)

which is below both ``A / delta^k`` and the whole plane's ``2 pi delta^(2-k) / (k - 2)``.
``|a'_i|`` is linear on ``s``, so its maximum is at a corner. Faces closer to the ball than
their size are split into four (recursively) before (4) is applied: the bound then follows
the kernel's decay across the face.

Refinement
----------
The cubes form an octree over the region's bounding box (only cubes that may meet the
region, :class:`Region`, are kept). Level by level, each cube's centre is evaluated
exactly (value, Jacobian, Hessian in closed form): ``det J(p) <= 0`` is a witness; a
positive bound (2) certifies the cube; otherwise it is split into eight. Cubes whose ball
touches the cage cannot be bounded (the kernels are singular on the cage) and are split
too. Within a level, cubes are visited from the lowest ``det J`` of their parent up, and
from the lowest few a short descent of ``det J`` (its gradient is ``cof(J) : H``, Jacobi's
formula, from the same exact evaluation) probes for a witness, which finds folds long
before the octree reaches them. The children of cubes entirely inside the region skip the
region test. Budget: ``max_cubes`` cubes examined; what is left then is undecided. The cost
grows steeply as the region nears the cage (the bound grows like the gap to the power -3).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba
import numpy as np

from vhm_viz.core.errors import AbortedError
from vhm_viz.core.geometry import face_normals_and_areas, triangle_distance
from vhm_viz.core.metrics import finite_or_none

__all__ = [
    "Region",
    "InjectivityCertificate",
    "certify_injectivity",
    "jacobian_deviation_bounds",
    "third_derivative_bounds",
    "cage_distance",
    "as_region",
    "default_margin",
    "OUTSIDE",
    "MEETS",
    "INSIDE",
]

# Faces closer to the ball than KAPPA times their diameter are split (tightens (4)), if they
# are within NEAR times the distance of the nearest face (farther ones weigh little).
_KAPPA = 1.0
_NEAR = 3.0
# Deepest face subdivision (4^8 sub-triangles at most; reached only right next to a face).
_MAX_FACE_DEPTH = 8
# Relative margin absorbing the rounding of the closed forms in sigma_min(J(p)) (the
# basis is accurate to ~1e-13 relative; the margin is far above that and far below any
# singular value the certificate is meant to separate from zero).
_ROUNDING_MARGIN = 1e-8
# Cubes visited per batch (bounds the basis arrays of one evaluation: ~9 x (n + m) floats
# per cube).
_BATCH = 4096
# Witness probes per batch: the cubes with the lowest det J(p) that were not certified,
# each followed by a few steps of descent of det J.
_PROBES = 32
_DESCENT_STEPS = 3
_FOUR_PI = 4.0 * math.pi

#: Cube classes of :meth:`Region.classify`.
OUTSIDE, MEETS, INSIDE = 0, 1, 2


# --------------------------------------------------------------------------------------
# regions
# --------------------------------------------------------------------------------------
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
        from vhm_viz.core.basis import inside_cage, winding_number

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
        from scipy.spatial import cKDTree

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
        for k in np.unique(cls):
            ids = np.nonzero(cls == k)[0]
            self.classes.append((ids, cKDTree(c[ids]), float(rad[ids].max())))

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


# --------------------------------------------------------------------------------------
# compiled kernels
# --------------------------------------------------------------------------------------
@numba.njit(cache=True, parallel=True)
def _cage_distance_kernel(points, V, F, out):  # pragma: no cover - compiled
    for k in numba.prange(points.shape[0]):
        px, py, pz = points[k, 0], points[k, 1], points[k, 2]
        best = np.inf
        for t in range(F.shape[0]):
            a, b, c = F[t, 0], F[t, 1], F[t, 2]
            d = triangle_distance(
                px, py, pz, V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1], V[b, 2],
                V[c, 0], V[c, 1], V[c, 2],
            )  # fmt: skip
            if d < best:
                best = d
        out[k] = best


def cage_distance(points, vertices, faces) -> np.ndarray:
    """Unsigned distance from each point to the cage surface.

    Parameters
    ----------
    points : (N, 3) array_like
    vertices : (n, 3) array_like
    faces : (m, 3) array_like of int

    Returns
    -------
    (N,) float64
    """
    p = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(p))
    if len(p):
        _cage_distance_kernel(
            p,
            np.ascontiguousarray(vertices, dtype=np.float64),
            np.ascontiguousarray(faces, dtype=np.int64),
            out,
        )
    return out


@numba.njit(cache=True, inline="always")
def _kernel_integrals(delta, area):  # pragma: no cover - compiled
    """Bounds (4) of ``int d^-5 dA`` and ``int d^-4 dA`` over an area at distance ``delta``.

    Written with ``x = A / (pi delta^2)`` so that small pieces lose no digits:
    ``2 pi/3 delta^-3 (1 - (1 + x)^(-3/2))`` and ``pi delta^-2 x / (1 + x)``. Far pieces
    (``x < 1e-3``) take ``A / delta^k``, an upper bound of both that costs no logarithm
    and is within 0.15% of them there.
    """
    d2 = delta * delta
    x = area / (math.pi * d2)
    if x < 1e-3:
        i4 = area / (d2 * d2)
        return i4 / delta, i4
    i5 = (2.0 * math.pi / 3.0) / (d2 * delta) * (-math.expm1(-1.5 * math.log1p(x)))
    i4 = math.pi / d2 * (x / (1.0 + x))
    return i5, i4


@numba.njit(cache=True)
def _face_integrals(
    px, py, pz, r, X, D, area, diameter, dist, near, work, sx, sd, sdepth, out
):  # pragma: no cover - compiled
    """Add one face's ``int |a'_i| d^-5`` (out[0:3]) and ``int d^-4`` (out[3]).

    ``X`` (3, 3) corners, ``D`` (3, 3) signed residual densities ``a'`` at the corners
    (rows: corners), ``diameter`` its longest edge, ``dist`` a lower bound of its distance
    to ``p``. The face is
    split into four while it is closer to the ball than ``_KAPPA`` times its diameter and
    closer than ``near``; ``sx``, ``sd``, ``sdepth`` are the explicit stack and ``work``
    (4, 3, 3) scratch (nothing is allocated per piece). Returns False when a piece touches
    the ball (no bound).
    """
    top = 0
    sx[0] = X
    sd[0] = D
    sdepth[0] = 0
    while top >= 0:
        # the popped piece's slot is overwritten by its children: work on a copy
        Y, E, M, Mq = work[0], work[1], work[2], work[3]
        for i in range(3):
            for c in range(3):
                Y[i, c] = sx[top, i, c]
                E[i, c] = sd[top, i, c]
        depth = sdepth[top]
        top -= 1
        if depth == 0:
            d = dist
        else:
            d = triangle_distance(
                px, py, pz, Y[0, 0], Y[0, 1], Y[0, 2], Y[1, 0], Y[1, 1], Y[1, 2],
                Y[2, 0], Y[2, 1], Y[2, 2],
            )  # fmt: skip
        delta = d * (1.0 - 1e-12) - r
        if delta <= 0.0:
            return False
        # midpoint subdivision halves every edge: the pieces are similar to the face
        diam = diameter / (2.0**depth)
        if diam > _KAPPA * delta and delta < near and depth < _MAX_FACE_DEPTH:
            # four children: the corner triangles and the middle one
            for i in range(3):
                j = (i + 1) % 3
                for c in range(3):
                    M[i, c] = 0.5 * (Y[i, c] + Y[j, c])  # midpoint of edge (i, i+1)
                    Mq[i, c] = 0.5 * (E[i, c] + E[j, c])
            for i in range(3):
                top += 1
                k = (i + 2) % 3  # the edge (i-1, i) midpoint
                for c in range(3):
                    sx[top, 0, c] = Y[i, c]
                    sx[top, 1, c] = M[i, c]
                    sx[top, 2, c] = M[k, c]
                    sd[top, 0, c] = E[i, c]
                    sd[top, 1, c] = Mq[i, c]
                    sd[top, 2, c] = Mq[k, c]
                sdepth[top] = depth + 1
            top += 1
            sx[top] = M
            sd[top] = Mq
            sdepth[top] = depth + 1
            continue
        piece = area / (4.0**depth)
        i5, i4 = _kernel_integrals(delta, piece)
        for c in range(3):
            m = max(abs(E[0, c]), abs(E[1, c]), abs(E[2, c]))
            out[c] += m * i5
        out[3] += i4
    return True


@numba.njit(cache=True)
def _fit_affine(px, py, pz, V, F, N, areas, a, b, dist, wv, M, R, A, T):  # pragma: no cover
    """The affine map subtracted in (3) for a ball at ``p``: a weighted least-squares fit.

    Minimises ``sum_v w_v |a_v - A x_v - T|^2 + sum_t w_t |b_t - A N_t|^2`` with the weights
    of the kernels in (3): ``w ~ area / (d^2 + area/pi)^3`` for the double layer (spread to
    the face's corners) and a quarter of ``area / (d^2 + area/pi)^2.5`` for the single
    layer (``d`` the face's distance to ``p``). Any affine map gives a valid bound; this
    one makes the residual densities small on the faces that dominate it, where the
    tangent map at ``p`` would keep the whole curvature of the map. ``wv`` is scratch.
    """
    M[:, :] = 0.0
    R[:, :] = 0.0
    wv[:] = 0.0
    for t in range(F.shape[0]):
        s = dist[t] * dist[t] + areas[t] / math.pi
        w = areas[t] / (s * s * s) / 3.0
        for i in range(3):
            wv[F[t, i]] += w
        # the single layer's rows (N_t, 0)
        wb = 0.25 * areas[t] / (s * s * math.sqrt(s))
        for r in range(3):
            for c in range(3):
                M[r, c] += wb * N[t, r] * N[t, c]
                R[r, c] += wb * N[t, r] * b[t, c]
    for v in range(V.shape[0]):
        w = wv[v]
        if w == 0.0:
            continue  # an unreferenced vertex
        # rows (x_v - p, 1): coordinates relative to p keep the equations well conditioned
        x0, x1, x2 = V[v, 0] - px, V[v, 1] - py, V[v, 2] - pz
        row = (x0, x1, x2, 1.0)
        for r in range(4):
            wr = w * row[r]
            for c in range(4):
                M[r, c] += wr * row[c]
            for c in range(3):
                R[r, c] += wr * a[v, c]
    X = np.linalg.solve(M, R)  # (4, 3): rows A^T, then the value at p
    for i in range(3):
        for j in range(3):
            A[i, j] = X[j, i]
    for i in range(3):
        T[i] = X[3, i] - (A[i, 0] * px + A[i, 1] * py + A[i, 2] * pz)


@numba.njit(cache=True, parallel=True)
def _third_derivative_kernel(
    centres, radii, fit, A_in, T_in, V, F, N, areas, fc, fr, diam, a, b, out_m3, out_dist
):  # pragma: no cover - compiled
    """Bound (3) of the third derivative on each ball, and the centre's distance to the cage.

    With ``fit`` the affine map subtracted is :func:`_fit_affine`'s, else ``A_in`` (k, 3, 3),
    ``T_in`` (k, 3). ``fc``, ``fr``, ``diam``: face centroids, the radii of their
    circumscribing balls about the centroids and longest edges (faces far from ``p``
    use ``|p - centroid| - radius``, a lower bound of their distance). ``out_m3`` gets
    ``sqrt(sum_i M3_i^2)`` (inf where the ball touches the cage); ``out_dist`` a lower bound
    of the centre's distance to the cage (exact where it is below ``r`` plus four times the
    nearest faces' radius).
    """
    k_total = centres.shape[0]
    m = F.shape[0]
    for k in numba.prange(k_total):
        sx = np.empty((3 * _MAX_FACE_DEPTH + 4, 3, 3))
        sd = np.empty((3 * _MAX_FACE_DEPTH + 4, 3, 3))
        sdepth = np.empty(3 * _MAX_FACE_DEPTH + 4, dtype=np.int64)
        work = np.empty((4, 3, 3))
        X = np.empty((3, 3))
        D = np.empty((3, 3))
        acc = np.zeros(4)
        sa = np.zeros(3)
        sb = np.zeros(3)
        dist = np.empty(m)
        wv = np.empty(V.shape[0])
        M = np.empty((4, 4))
        R = np.empty((4, 3))
        res = np.empty((V.shape[0], 3))
        A = np.empty((3, 3))
        T = np.empty(3)
        px, py, pz = centres[k, 0], centres[k, 1], centres[k, 2]
        r = radii[k]
        dmin = np.inf
        for t in range(m):
            cx, cy, cz = px - fc[t, 0], py - fc[t, 1], pz - fc[t, 2]
            d = math.sqrt(cx * cx + cy * cy + cz * cz) - fr[t]
            if d <= r + 4.0 * fr[t]:  # near: the exact distance
                i0, i1, i2 = F[t, 0], F[t, 1], F[t, 2]
                d = triangle_distance(
                    px, py, pz, V[i0, 0], V[i0, 1], V[i0, 2], V[i1, 0], V[i1, 1], V[i1, 2],
                    V[i2, 0], V[i2, 1], V[i2, 2],
                )  # fmt: skip
            dist[t] = d
            dmin = min(dmin, d)
        out_dist[k] = dmin
        if dmin * (1.0 - 1e-12) - r <= 0.0:
            out_m3[k] = np.inf  # the ball touches the cage: the kernels are singular there
            continue
        if fit:
            _fit_affine(px, py, pz, V, F, N, areas, a, b, dist, wv, M, R, A, T)
        else:
            A[:, :] = A_in[k]
            T[:] = T_in[k]
        # the residual double-layer density at the vertices, once per cube
        for v in range(V.shape[0]):
            for c in range(3):
                res[v, c] = (
                    a[v, c] - (A[c, 0] * V[v, 0] + A[c, 1] * V[v, 1] + A[c, 2] * V[v, 2]) - T[c]
                )
        ok = True
        for t in range(m):
            for i in range(3):
                v = F[t, i]
                for c in range(3):
                    X[i, c] = V[v, c]
                    D[i, c] = res[v, c]
            acc[:] = 0.0
            near = _NEAR * (dmin - r)
            if not _face_integrals(
                px, py, pz, r, X, D, areas[t], diam[t], dist[t], near, work, sx, sd, sdepth, acc
            ):
                ok = False
                break
            for c in range(3):
                sa[c] += acc[c]
                bres = b[t, c] - (A[c, 0] * N[t, 0] + A[c, 1] * N[t, 1] + A[c, 2] * N[t, 2])
                sb[c] += abs(bres) * acc[3]
        if ok:
            s = 0.0
            for c in range(3):
                mi = (24.0 * sa[c] + 6.0 * sb[c]) / _FOUR_PI
                s += mi * mi
            out_m3[k] = math.sqrt(s) * (1.0 + 1e-12)
        else:
            out_m3[k] = np.inf


# --------------------------------------------------------------------------------------
# the bound, per cube
# --------------------------------------------------------------------------------------
def _harmonic_map(deformation):
    hm = getattr(deformation, "harmonic_map", deformation)
    if not hasattr(hm, "evaluate") or not hasattr(hm, "coefficients"):
        raise TypeError(f"need a Deformer or a HarmonicMap; got {type(deformation).__name__}")
    return hm


def _cage_arrays(hm):
    cage = hm.cage
    v = np.ascontiguousarray(cage.vertices, dtype=np.float64)
    f = np.ascontiguousarray(cage.faces, dtype=np.int64)
    normals, areas = face_normals_and_areas(v, f)
    z = np.asarray(hm.coefficients, dtype=np.float64)
    n = len(v)
    corners = v[f]
    centroids = corners.mean(axis=1)
    radii = np.linalg.norm(corners - centroids[:, None], axis=2).max(axis=1)
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    return (
        v, f, normals, areas, np.ascontiguousarray(centroids), radii, edges,
        np.ascontiguousarray(z[:n]), np.ascontiguousarray(z[n:]),
    )  # fmt: skip


def third_derivative_bounds(harmonic_map, centres, radii, values=None, jacobians=None):
    """Bound (3) of ``|D^3 f|`` on balls, after subtracting an affine map per ball.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    centres : (k, 3) array_like
        Ball centres ``p`` (inside the cage).
    radii : (k,) array_like
        Ball radii ``r``.
    values, jacobians : (k, 3), (k, 3, 3) array_like, optional
        Subtract the map ``y -> values + jacobians (y - p)`` (e.g. the tangent map, with
        ``f(p)`` and ``J(p)``). Default: the kernel-weighted least-squares fit to the
        coefficients (much tighter where the map bends; any affine map is valid).

    Returns
    -------
    m3 : (k,) float64
        ``M3 = sqrt(sum_i M3_i^2)``: ``||J(p + h) - J(p) - H(p)[h]||_F <= M3 |h|^2 / 2``
        for ``|h| <= r``; ``inf`` where the ball touches the cage.
    distance : (k,) float64
        Distance from each centre to the cage.
    """
    v, f, normals, areas, fc, fr, diam, a, b = _cage_arrays(harmonic_map)
    p = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.ascontiguousarray(np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(p),)))
    fit = jacobians is None
    if fit:
        jac, t = np.zeros((len(p), 3, 3)), np.zeros((len(p), 3))
    else:
        jac = np.ascontiguousarray(jacobians, dtype=np.float64).reshape(-1, 3, 3)
        t = np.asarray(values, dtype=np.float64).reshape(-1, 3) - np.einsum("kij,kj->ki", jac, p)
        t = np.ascontiguousarray(t)
    m3 = np.empty(len(p))
    dist = np.empty(len(p))
    if len(p):
        _third_derivative_kernel(
            p, r, fit, jac, t, v, f, normals, areas, fc, fr, diam, a, b, m3, dist
        )
    return m3, dist


def _corner_signs() -> np.ndarray:
    # h^T G h is even in h: four of the eight corners suffice
    return np.array([[1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]], dtype=np.float64)


def _hessian_term(hessians: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """``max over the cube's corners of ||H(p)[h]||_F`` (the linear term of (2))."""
    g = np.einsum("nijk,nijl->nkl", hessians, hessians)
    h = _corner_signs() * np.asarray(half_extents, dtype=np.float64)
    q = np.einsum("ck,nkl,cl->nc", h, g, h)
    return np.sqrt(np.maximum(q.max(axis=1), 0.0))


def jacobian_deviation_bounds(harmonic_map, centres, half_extents):
    """Bound of ``max ||J(x) - J(p)||_2`` over axis-aligned cubes (centre ``p``).

    The linear and remainder terms of (2): ``max_corners ||H(p)[h]||_F + M3 r^2 / 2``.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    centres : (k, 3) array_like
        Cube centres, inside the cage.
    half_extents : (3,) array_like
        Half side lengths (common to the cubes).

    Returns
    -------
    (k,) float64
        ``inf`` for cubes whose circumscribed ball touches the cage.
    """
    p = np.ascontiguousarray(centres, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(half_extents, dtype=np.float64).reshape(3)
    r = float(np.linalg.norm(e))
    f, jac, hess = harmonic_map.evaluate(p, order=2)
    m3, _ = third_derivative_bounds(harmonic_map, p, np.full(len(p), r))
    return _hessian_term(hess, e) + 0.5 * m3 * r * r


# --------------------------------------------------------------------------------------
# the certificate
# --------------------------------------------------------------------------------------
@dataclass
class InjectivityCertificate:
    """The answer of :func:`certify_injectivity`.

    Attributes
    ----------
    certified : bool
        True only when every cube covering the region was proved (``det J > 0`` on all of
        it).
    status : {"certified", "not injective", "undecided"}
    cubes : int
        Cubes examined (each one exact evaluation of ``f, J, H`` and one bound).
    certified_cubes : int
        Cubes proved.
    witnesses : (w, 3) float64
        Points (rest space) where the exactly evaluated ``det J <= 0``, most negative first.
    witness_determinants : (w,) float64
        ``det J`` there.
    undecided : (u, 2, 3) float64
        Boxes ``(lo, hi)`` left unproved when the budget ran out (or that touch the cage
        at the smallest size, or lie outside it).
    outside : int
        Undecided boxes lying entirely outside the cage (the map is not the deformation
        there; make the cage enclose the region).
    min_det : float
        Smallest ``det J`` seen at any examined centre or probe.
    region : dict
        What was certified (:attr:`Region.description`).
    max_cubes : int
        The budget.
    seconds : float
        Wall time.
    smallest_cube : float
        Longest side of the smallest cubes examined.
    """

    certified: bool
    status: str
    cubes: int
    certified_cubes: int
    witnesses: np.ndarray
    witness_determinants: np.ndarray
    undecided: np.ndarray
    outside: int
    min_det: float
    region: dict
    max_cubes: int
    seconds: float
    smallest_cube: float = field(default=float("nan"))

    def to_json(self) -> dict:
        """The summary written to ``metrics.json`` (plain types)."""
        return {
            "certified": bool(self.certified),
            "status": self.status,
            "cubes": int(self.cubes),
            "certified_cubes": int(self.certified_cubes),
            "witnesses": np.asarray(self.witnesses, dtype=float).tolist(),
            "witness_determinants": np.asarray(self.witness_determinants, dtype=float).tolist(),
            "undecided": int(len(self.undecided)),
            "outside_cage": int(self.outside),
            "min_det_sampled": finite_or_none(self.min_det),
            "smallest_cube": finite_or_none(self.smallest_cube),
            "region": self.region,
            "max_cubes": int(self.max_cubes),
            "seconds": float(self.seconds),
        }

    def summary(self) -> str:
        """One line: the status, with the numbers that back it."""
        if self.status == "certified":
            return f"certified injective ({self.cubes} cubes, {self.seconds:.2f} s)"
        if self.status == "not injective":
            w = self.witnesses[0]
            return (
                f"not injective: det J = {self.witness_determinants[0]:.3g} at "
                f"({w[0]:.4g}, {w[1]:.4g}, {w[2]:.4g}) ({len(self.witnesses)} witnesses, "
                f"{self.cubes} cubes, {self.seconds:.2f} s)"
            )
        return (
            f"undecided: {len(self.undecided)} cubes left after {self.cubes} "
            f"(budget {self.max_cubes}; {self.seconds:.2f} s)"
        )


def _initial_cubes(region: Region, initial_cubes: int):
    """Near-cubic cells tiling the region's bounding box, at most ~``initial_cubes``."""
    size = np.maximum(region.hi - region.lo, 1e-12 * max(region.diagonal, 1e-300))
    side = (np.prod(size) / max(initial_cubes, 1)) ** (1.0 / 3.0)
    side = max(side, size.max() / 64.0)
    counts = np.maximum(1, np.ceil(size / side - 1e-9)).astype(np.int64)
    half = size / counts / 2.0
    axes = [region.lo[a] + half[a] * (2 * np.arange(counts[a]) + 1) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return grid, half


def _children(centres: np.ndarray, half: np.ndarray):
    """The eight children of each cube (centres), and their half extents."""
    h = half / 2.0
    offsets = np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
    )
    return (centres[:, None, :] + offsets[None] * h).reshape(-1, 3), h


def _det_gradient(jac: np.ndarray, hess: np.ndarray) -> np.ndarray:
    """``d det J / d x_k = sum_ij cof(J)_ij H_ijk`` (Jacobi's formula)."""
    c0, c1, c2 = jac[:, :, 0], jac[:, :, 1], jac[:, :, 2]
    cof = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=2)
    return np.einsum("nij,nijk->nk", cof, hess)


def certify_injectivity(
    deformation,
    region="cage",
    *,
    max_cubes: int = 200_000,
    max_witnesses: int = 16,
    initial_cubes: int = 64,
    progress=None,
    abort=None,
) -> InjectivityCertificate:
    """Prove that ``det J > 0`` on a whole region, or find a point where it is not.

    See the module documentation for the bound and its derivation.

    Parameters
    ----------
    deformation : Deformer or HarmonicMap
        The map (a deformer's current solution).
    region : Region, ``"cage"`` or ``(lo, hi)``
        What to certify: a :class:`Region`; ``"cage"`` for the cage's interior farther than
        :func:`default_margin` from it; or an axis-aligned box. Datasets (tet meshes,
        images, closed surfaces) become regions through :func:`vhm_viz.filters.region_of`.
    max_cubes : int
        Budget: cubes examined at most. When it runs out the answer is "undecided".
    max_witnesses : int
        Witnesses kept (the most negative ``det J`` first).
    initial_cubes : int
        Cubes of the first level (about; the bounding box is tiled by near-cubes).
    progress : callable(fraction, message), optional
        Called after each batch; the fraction is the share of the region's volume decided.
    abort : callable() -> bool, optional
        Checked before each batch; :class:`~vhm_viz.core.errors.AbortedError` when true.

    Returns
    -------
    InjectivityCertificate
    """
    t0 = time.perf_counter()
    hm = _harmonic_map(deformation)
    region = as_region(region, hm.cage)
    if int(max_cubes) < 1:
        raise ValueError(f"max_cubes must be at least 1; got {max_cubes}")
    max_cubes = int(max_cubes)
    min_half = 1e-7 * max(region.diagonal, 1e-300)

    centres, half = _initial_cubes(region, initial_cubes)
    state = region.classify(centres, half)
    centres, state = centres[state != OUTSIDE], state[state != OUTSIDE]
    parent_det = np.zeros(len(centres))
    total_volume = max(len(centres), 1) * float(np.prod(2 * half))
    decided_volume = 0.0
    cubes = certified_cubes = outside = 0
    undecided: list[np.ndarray] = []
    wit_points, wit_dets = [], []
    min_det = np.inf
    smallest = float(2.0 * half.max())

    while len(centres):
        order = np.argsort(parent_det, kind="stable")  # near the lowest det J first
        centres, state = centres[order], state[order]
        r = float(np.linalg.norm(half))
        smallest = min(smallest, float(2.0 * half.max()))
        split: list[np.ndarray] = []
        split_det: list[np.ndarray] = []
        split_state: list[np.ndarray] = []
        s = 0
        while s < len(centres):
            if abort is not None and abort():
                raise AbortedError("aborted")
            budget = max_cubes - cubes
            if budget <= 0:
                # out of budget: what is left of this level, and the cubes waiting to be
                # split, are the undecided boxes
                undecided.append(_boxes(centres[s:], half))
                undecided.extend(_boxes(rest, half) for rest in split)
                split = []
                break
            batch = centres[s : s + min(_BATCH, budget)]
            batch_state = state[s : s + len(batch)]
            s += len(batch)
            cubes += len(batch)
            f, jac, hess = hm.evaluate(batch, order=2, outside="nan")
            finite = np.isfinite(jac).all(axis=(1, 2)) & np.isfinite(hess).all(axis=(1, 2, 3))
            det = np.full(len(batch), np.nan)
            det[finite] = np.linalg.det(jac[finite])
            if finite.any():
                min_det = min(min_det, float(np.nanmin(det)))
            negative = finite & (det <= 0.0)
            if negative.any():
                # a witness must lie in the region (a cube's centre may not, near its edge)
                edge = negative & (batch_state != INSIDE)
                negative[edge] = region.contains(batch[edge])
                if negative.any():
                    wit_points.append(batch[negative])
                    wit_dets.append(det[negative])
                    break
            lower = np.full(len(batch), -np.inf)
            m3 = np.full(len(batch), np.inf)
            dist = np.zeros(len(batch))
            if finite.any():
                sub = np.nonzero(finite)[0]
                m3[sub], dist[sub] = third_derivative_bounds(hm, batch[sub], np.full(sub.size, r))
                sv = np.linalg.svd(jac[sub], compute_uv=False)
                lower[sub] = (
                    sv[:, 2]
                    - _ROUNDING_MARGIN * sv[:, 0]
                    - _hessian_term(hess[sub], half)
                    - 0.5 * m3[sub] * r * r
                )
            if (~finite).any():
                # outside the cage (NaN) or exactly on a cage edge: distance decides below
                dist[~finite] = cage_distance(batch[~finite], hm.cage.vertices, hm.cage.faces)
            # nonsingular on the whole cube and positive at its centre: positive everywhere
            proved = finite & (det > 0.0) & (lower > 0.0)
            certified_cubes += int(proved.sum())
            decided_volume += float(proved.sum()) * float(np.prod(2 * half))
            entirely_outside = ~finite & (dist > r)
            # cubes outside the cage cannot be certified (the map is not the deformation)
            if entirely_outside.any():
                outside += int(entirely_outside.sum())
                undecided.append(_boxes(batch[entirely_outside], half))
            rest = ~proved & ~entirely_outside
            probe = _probe_witnesses(hm, region, batch, half, jac, hess, det, rest & finite)
            if probe is not None:
                wit_points.append(probe[0])
                wit_dets.append(probe[1])
                min_det = min(min_det, float(probe[1].min()))
                break
            if rest.any():
                if np.all(half <= min_half):
                    undecided.append(_boxes(batch[rest], half))
                else:
                    split.append(batch[rest])
                    split_det.append(np.where(np.isfinite(det[rest]), det[rest], np.inf))
                    split_state.append(batch_state[rest])
            if progress is not None:
                progress(min(decided_volume / total_volume, 1.0), f"{cubes} cubes")
        if wit_points:
            break
        if not split:
            break
        children, child_half = _children(np.concatenate(split), half)
        # children of a cube inside the region are inside: only the others are tested
        state = np.repeat(np.concatenate(split_state), 8)
        edge = state != INSIDE
        if edge.any():
            state[edge] = region.classify(children[edge], child_half)
        keep = state != OUTSIDE
        centres, state = children[keep], state[keep]
        parent_det = np.repeat(np.concatenate(split_det), 8)[keep]
        half = child_half

    seconds = time.perf_counter() - t0
    und = np.concatenate(undecided) if undecided else np.zeros((0, 2, 3))
    if wit_points:
        pts = np.concatenate(wit_points)
        dets = np.concatenate(wit_dets)
        order = np.argsort(dets)[: int(max_witnesses)]
        pts, dets = pts[order], dets[order]
        status = "not injective"
    else:
        pts, dets = np.zeros((0, 3)), np.zeros(0)
        status = "undecided" if len(und) else "certified"
    return InjectivityCertificate(
        certified=status == "certified",
        status=status,
        cubes=cubes,
        certified_cubes=certified_cubes,
        witnesses=pts,
        witness_determinants=dets,
        undecided=und,
        outside=outside,
        min_det=float(min_det) if np.isfinite(min_det) else float("nan"),
        region=region.description,
        max_cubes=max_cubes,
        seconds=seconds,
        smallest_cube=smallest,
    )


def _boxes(centres: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(k, 2, 3) boxes ``(lo, hi)`` of cubes."""
    return np.stack([centres - half, centres + half], axis=1)


def _probe_witnesses(hm, region, centres, half, jac, hess, det, candidates):
    """Look for a witness near the most suspicious cubes: a short descent of ``det J``.

    From the centres with the lowest ``det J`` that were not certified, each step moves to
    the point where the linear model ``det J + grad det . h`` reaches ``-det J`` (capped at
    two cube sides per axis, kept in the region's box), and the first step also tries the
    cube corner where the model is lowest. Every probe is evaluated exactly. Returns
    ``(points, dets)`` of the probes in the region with ``det J <= 0``, or None.
    """
    idx = np.nonzero(candidates)[0]
    if idx.size == 0:
        return None
    idx = idx[np.argsort(det[idx])[:_PROBES]]
    x, d = centres[idx], det[idx]
    grad = _det_gradient(jac[idx], hess[idx])
    reach = 4.0 * half
    for step in range(_DESCENT_STEPS):
        g2 = np.einsum("ij,ij->i", grad, grad)
        with np.errstate(divide="ignore", invalid="ignore"):
            h = np.where(g2 > 0, -2.0 * d / g2, 0.0)[:, None] * grad
        pts = np.clip(x + np.clip(h, -reach, reach), region.lo, region.hi)
        if step == 0:
            corner = np.clip(x - half * np.sign(grad), region.lo, region.hi)
            pts = np.concatenate([pts, corner])
        _, pj, ph = hm.evaluate(pts, order=2, outside="nan")
        ok = np.isfinite(pj).all(axis=(1, 2)) & np.isfinite(ph).all(axis=(1, 2, 3))
        pdet = np.full(len(pts), np.inf)
        pdet[ok] = np.linalg.det(pj[ok])
        hit = ok & (pdet <= 0.0)
        if hit.any():
            hit[hit] = region.contains(pts[hit])
            if hit.any():
                return pts[hit], pdet[hit]
        # carry on from the better of the two probes of each start
        k = len(x)
        if step == 0:
            use_corner = pdet[k:] < pdet[:k]
            pick = np.where(use_corner, np.arange(k) + k, np.arange(k))
        else:
            pick = np.arange(k)
        keep = np.isfinite(pdet[pick]) & (pdet[pick] < d)
        if not keep.any():
            return None
        pick = pick[keep]
        x, d = pts[pick], pdet[pick]
        grad = _det_gradient(pj[pick], ph[pick])
    return None
