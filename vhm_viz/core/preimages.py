"""Pre-images found besides the lattice's: the exact map's, and voxels left in place.

The volume engine pulls output voxels back with Newton's method on the lattice's
polynomials (:meth:`~vhm_viz.core.lattice.HermiteLattice.pull_back`); these functions
finish a slab of its pre-images. Those that the lattice found next to the cage are
checked with the winding number (:func:`confirm_tentative`), those next to a cage edge
are polished on the exact map (:func:`polish_next_to_edges`, :func:`exact_preimages`;
:func:`settle_preimages` does both steps), and with the ``"passthrough"`` policy the
output voxels outside the cage left without one take their own position
(:func:`pass_through`).

``state`` of a slab's voxels: 0 no pre-image, 1 inside the cage, 2 found by the lattice
next to the cage (to be confirmed), 3 left in place outside it; the lattice adds
:data:`~vhm_viz.core.lattice.pullback.NEAR_EDGE` to 1 and 2 where the pre-image lies in a
leaf that comes near a cage edge (:func:`leaves_near_edges`), which
:func:`polish_next_to_edges` clears.
"""

from __future__ import annotations

import numba
import numpy as np

from vhm_viz.core.basis import evaluate_map, inside_cage, winding_number
from vhm_viz.core.image import BORDER, ImageGeometry, inside_mask
from vhm_viz.core.lattice.cage_edges import cells_near_edges
from vhm_viz.core.lattice.pullback import NEAR_EDGE

__all__ = ["exact_preimages"]

# Pre-images closer than this (voxels) to a cage edge are polished by Newton's method on
# the exact map: there the map has a logarithmic singularity that no cubic between voxels
# follows, and a position error e moves a pre-image by e / s_min (s_min: the Jacobian's
# smallest singular value in voxels), so that the lattice's pre-images there can miss the
# tolerance where the map compresses. The band is wide enough that those errors stay
# below the tolerance's order farther out (the benchmark measures them).
_EXACT_NEAR_EDGE = 1.5
# Newton on the exact map starts from the lattice's pre-image, a few hundredths of a voxel
# off: two or three steps converge; more means it left for another branch.
_EXACT_ITERATIONS = 6


def leaves_near_edges(lattice) -> np.ndarray:
    """Leaves that may hold pre-images within the polishing band of a cage edge.

    A leaf's pre-images lie within its margin (:meth:`HermiteLattice.margins`), so that
    those :func:`polish_next_to_edges` polishes lie in leaves that the band plus the
    margin reaches; the pull-back marks the pre-images of these leaves only.

    Returns
    -------
    (L,) bool
    """
    size = lattice.leaf_size
    out = np.zeros(len(size), dtype=np.bool_)
    if not len(size) or not len(lattice.edge_a):
        return out
    band = _EXACT_NEAR_EDGE + float(np.max(lattice.margins()))
    for h in np.unique(size):
        pick = np.flatnonzero(size == h)
        near = np.zeros(len(pick), dtype=np.bool_)
        cells_near_edges(np.ascontiguousarray(lattice.leaf_origin[pick]), int(h),
                         lattice.edge_a, lattice.edge_b, band, near)  # fmt: skip
        out[pick] = near
    return out


def settle_preimages(harmonic_map, lattice, geometry: ImageGeometry,
                     out_geo: ImageGeometry, slab, u, state) -> None:  # fmt: skip
    """:func:`confirm_tentative`, then :func:`polish_next_to_edges`, from one scan of a slab.

    The voxels either may change (``state`` 2, with or without :data:`NEAR_EDGE`, or
    ``1 | NEAR_EDGE``) are found in one pass over the slab's states, not one per step.
    Parameters as for :func:`polish_next_to_edges`.
    """
    rows = _rows_with(state, _UNSETTLED)
    confirm_tentative(harmonic_map, geometry, u, state, rows)
    polish_next_to_edges(harmonic_map, lattice, geometry, out_geo, slab, u, state, rows)


def confirm_tentative(harmonic_map, geometry: ImageGeometry, u, state, rows=None) -> None:
    """Pre-images next to the cage (``state`` 2): keep those the winding number puts inside.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    geometry : ImageGeometry
        The input grid (``u`` are its continuous indices).
    u : (P, 3) float64
    state : (P,) uint8
        Set to 1 (inside) or 0 where it was 2 (its :data:`NEAR_EDGE` bit kept where 1).
    rows : (R,) int64, optional
        Ascending voxels among which those with ``state`` 2 are (default: all).
    """
    if rows is None:
        t = _rows_with(state, _TENTATIVE)
    else:
        t = rows[_TENTATIVE[state[rows]]]
    if t.size:
        cage = harmonic_map.cage
        ins = inside_cage(winding_number(geometry.points(u[t]), cage.vertices, cage.faces))
        state[t] = np.where(ins, (state[t] & NEAR_EDGE) | 1, 0)


def _states(test) -> np.ndarray:
    """(256,) bool: which ``state`` values pass ``test``."""
    return np.array([test(v) for v in range(256)], dtype=np.bool_)


# the states that confirm_tentative and polish_next_to_edges look at, and either
_TENTATIVE = _states(lambda v: v & 3 == 2)  # with or without NEAR_EDGE
_NEAR_EDGE_FOUND = _states(lambda v: v == 1 | NEAR_EDGE)
_UNSETTLED = _TENTATIVE | _NEAR_EDGE_FOUND


@numba.njit(cache=True)
def _rows_with(state, passes):  # pragma: no cover - compiled
    """Indices ``p`` where ``passes[state[p]]``, ascending (no boolean array)."""
    count = 0
    for p in range(state.shape[0]):  # (no branches: a slab's states alternate often)
        count += passes[state[p]]
    if count == 0:  # (most slabs: no second pass)
        return np.empty(0, dtype=np.int64)
    out = np.empty(count + 1, dtype=np.int64)
    q = 0
    for p in range(state.shape[0]):
        out[q] = p
        q += passes[state[p]]
    return out[:count]


def polish_next_to_edges(harmonic_map, lattice, geometry: ImageGeometry,
                         out_geo: ImageGeometry, slab, u, state, rows=None) -> int:  # fmt: skip
    """Pre-images next to a cage edge: Newton's method on the exact map from there.

    Kept where it converges within a voxel of the lattice's pre-image (the same branch
    of a fold); elsewhere the lattice's pre-image stays. Only the pre-images marked
    :data:`NEAR_EDGE` are looked at; the mark is cleared (``state`` 1 after).

    Parameters
    ----------
    harmonic_map : HarmonicMap
    lattice : HermiteLattice
        Tells which pre-images lie near a cage edge.
    geometry, out_geo : ImageGeometry
        The input and output grids.
    slab : (6,) int
        The output box of the slab, ``(i0, i1, j0, j1, k0, k1)``.
    u : (P, 3) float64
        The slab's pre-images (input indices), replaced where polished.
    state : (P,) uint8
    rows : (R,) int64, optional
        Ascending voxels among which those marked are (default: all).

    Returns
    -------
    int
        How many pre-images were replaced.
    """
    if rows is None:
        rows = _rows_with(state, _NEAR_EDGE_FOUND)
    else:
        rows = rows[_NEAR_EDGE_FOUND[state[rows]]]
    if not rows.size:
        return 0
    state[rows] = 1
    rows = rows[lattice.near_cage_edges(u[rows], _EXACT_NEAR_EDGE)]
    if not rows.size:
        return 0
    nx, ny = slab[1] - slab[0] + 1, slab[3] - slab[2] + 1
    ijk = np.column_stack([rows % nx, (rows // nx) % ny, rows // (nx * ny)]) + slab[0::2]
    x, ok = exact_preimages(
        harmonic_map, out_geo.points(ijk.astype(np.float64)), geometry.points(u[rows]),
        tolerance=1e-4 * float(np.min(geometry.spacing)), max_iterations=_EXACT_ITERATIONS,
    )  # fmt: skip
    rows, exact = rows[ok], geometry.continuous_index(x[ok])
    same = np.linalg.norm(exact - u[rows], axis=1) <= 1.0
    u[rows[same]] = exact[same]
    return int(same.sum())


def pass_through(harmonic_map, geometry: ImageGeometry, out_geo: ImageGeometry, slab, u,
                 state) -> int:  # fmt: skip
    """Outside voxels left in place: output voxels outside the cage with no pre-image.

    Their pre-image is their own position (``state`` 3) where it lies within the input's
    half-voxel border.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    geometry, out_geo : ImageGeometry
        The input and output grids.
    slab : (6,) int
        The output box of the slab.
    u : (P, 3) float64
    state : (P,) uint8

    Returns
    -------
    int
        How many voxels were left in place.
    """
    if not (state == 0).any():
        return 0
    cage = harmonic_map.cage
    rows = (slab[2], slab[3] + 1, slab[4], slab[5] + 1)
    mask = inside_mask(out_geo, cage.vertices, cage.faces, rows=rows)
    # output index -> input index: x = W_in (o_out + M_out i - o_in)
    to_src = geometry.world_to_index @ out_geo.index_to_world
    shift = geometry.world_to_index @ (out_geo.origin - geometry.origin)
    last = np.asarray(geometry.dimensions, dtype=np.float64) - 1.0
    return int(
        _identity_preimages(to_src, shift, slab, mask[:, :, slab[0] : slab[1] + 1], last, u, state)
    )


@numba.njit(parallel=True, cache=True)
def _identity_preimages(to_src, shift, box, inside, last, u, state):  # pragma: no cover
    """Identity pre-images of the output voxels left without one (``state`` 3).

    Only voxels outside the cage (``inside`` False) whose position lies within the input's
    half-voxel border: there the outside voxels stayed in place.
    """
    nx = box[1] - box[0] + 1
    ny = box[3] - box[2] + 1
    nk = box[5] - box[4] + 1
    count = np.zeros(nk, dtype=np.int64)
    for kk in numba.prange(nk):
        k = box[4] + kk
        for jj in range(ny):
            j = box[2] + jj
            for ii in range(nx):
                p = (kk * ny + jj) * nx + ii
                if state[p] != 0 or inside[kk, jj, ii]:
                    continue
                i = box[0] + ii
                ok = True
                x = np.empty(3)
                for a in range(3):
                    x[a] = shift[a] + to_src[a, 0] * i + to_src[a, 1] * j + to_src[a, 2] * k
                    if x[a] < -BORDER or x[a] > last[a] + BORDER:
                        ok = False
                if ok:
                    for a in range(3):
                        u[p, a] = x[a]
                    state[p] = 3
                    count[kk] += 1
    return count.sum()


def exact_preimages(harmonic_map, targets, starts, *, tolerance: float, max_iterations: int = 30):
    """Solve ``f(x) = y`` by Newton's method on the exact (closed-form) map.

    The reference inverse (slow: one closed-form evaluation per point and iteration);
    the volume engine inverts the lattice's polynomials instead.

    Parameters
    ----------
    harmonic_map : HarmonicMap
    targets : (N, 3) array_like
        The points ``y`` (world).
    starts : (N, 3) array_like
        Initial guesses inside the cage.
    tolerance : float
        Stop when ``|f(x) - y| <= tolerance`` (world units).
    max_iterations : int

    Returns
    -------
    x : (N, 3) float64
        Pre-images (NaN where none was found).
    ok : (N,) bool
        Converged inside the cage.
    """
    y = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    x = np.array(starts, dtype=np.float64).reshape(-1, 3)
    cage = harmonic_map.cage
    V = np.ascontiguousarray(cage.vertices, dtype=np.float64)
    F = np.ascontiguousarray(cage.faces, dtype=np.int64)
    z = np.asarray(harmonic_map.coefficients)
    ok = np.zeros(len(y), bool)
    active = np.arange(len(y))
    for it in range(max_iterations + 1):
        if not active.size:
            break
        # the fused kernel: values and Jacobians without the (N, n + m) basis arrays
        # (HarmonicMap.evaluate's chunks of them would add to a resample's peak)
        f, jac, wind = evaluate_map(x[active], V, F, z, order=1)
        out = ~inside_cage(wind)
        f[out], jac[out] = np.nan, np.nan
        r = f - y[active]
        norm = np.linalg.norm(r, axis=1)
        conv = norm <= tolerance
        ok[active[conv]] = True
        keep = ~conv & np.isfinite(norm)
        active = active[keep]
        if it == max_iterations or not active.size:
            break
        jk, rk = jac[keep], r[keep]
        good = np.abs(np.linalg.det(jk)) > 1e-14
        step = np.full_like(rk, np.nan)
        step[good] = np.linalg.solve(jk[good], rk[good][..., None])[..., 0]
        x[active] -= step
        active = active[np.isfinite(step).all(axis=1)]
    x[~ok] = np.nan
    return x, ok
