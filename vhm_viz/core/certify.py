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

The bound itself (Taylor's theorem, Weyl's inequality and the boundary-integral bound of
the third derivative) is derived in :mod:`vhm_viz.core.derivative_bounds`; the regions
are those of :mod:`vhm_viz.core.region`. This module re-exports their public names.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vhm_viz.core.derivative_bounds import (
    cage_distance,
    hessian_term,
    jacobian_deviation_bounds,
    third_derivative_bounds,
)
from vhm_viz.core.errors import AbortedError
from vhm_viz.core.metrics import finite_or_none
from vhm_viz.core.region import INSIDE, MEETS, OUTSIDE, Region, as_region, default_margin

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


def _harmonic_map(deformation):
    hm = getattr(deformation, "harmonic_map", deformation)
    if not hasattr(hm, "evaluate") or not hasattr(hm, "coefficients"):
        raise TypeError(f"need a Deformer or a HarmonicMap; got {type(deformation).__name__}")
    return hm


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
        Smallest ``det J`` seen at any examined centre or probe in the region (centres of
        cubes that only meet the region may lie outside it, where the map may fold
        without folding the region).
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
            min_det = _lowest_in_region(region, batch, batch_state, det, finite, min_det)
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
                    - hessian_term(hess[sub], half)
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


def _lowest_in_region(region, centres, state, det, finite, lowest: float) -> float:
    """``lowest``, or the lowest ``det`` below it at a centre that lies in the region."""
    low = finite & (det < lowest)
    inside = low & (state == INSIDE)
    if inside.any():
        lowest = float(det[inside].min())
    # centres of cubes that meet the region: tested only where they would lower it
    edge = np.flatnonzero(low & (state != INSIDE) & (det < lowest))
    if edge.size:
        edge = edge[region.contains(centres[edge])]
        if edge.size:
            lowest = float(det[edge].min())
    return lowest


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
