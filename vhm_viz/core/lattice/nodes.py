"""The node table of a lattice build, and each level's node data rows.

:class:`NodeTable` holds the exact data (value, Jacobian, side of the cage) of every
lattice point evaluated so far, keyed by position; :func:`level_node_data` turns the nodes of
one level into Hermite node data rows, the mixed derivatives differenced from the exact
Jacobians of neighbouring nodes of the same level.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from vhm_viz.core.lattice.hermite import N_TERMS
from vhm_viz.core.memory import grow_in_place, release_free_memory, take_in_place


class NodeTable:
    """Exact node data keyed by lattice position, grown level by level."""

    def __init__(self, dims):
        self.dims = np.asarray(dims, dtype=np.int64)  # lattice points per axis
        self.clear()

    def clear(self) -> None:
        """Forget every node."""
        self.keys = np.zeros(0, dtype=np.int64)
        self.f = np.zeros((0, 3))
        self.fu = np.zeros((0, 3, 3))
        self.inside = np.zeros(0, dtype=bool)

    def key(self, ijk) -> np.ndarray:
        """One int64 key per lattice point ``ijk`` (..., 3), i fastest."""
        ijk = np.asarray(ijk, dtype=np.int64)
        return ijk[..., 0] + self.dims[0] * (ijk[..., 1] + self.dims[1] * ijk[..., 2])

    def ijk(self, keys) -> np.ndarray:
        """The lattice points (..., 3) of ``keys`` (inverse of :meth:`key`)."""
        i = keys % self.dims[0]
        j = (keys // self.dims[0]) % self.dims[1]
        k = keys // (self.dims[0] * self.dims[1])
        return np.stack([i, j, k], axis=-1)

    def find(self, keys) -> np.ndarray:
        """Row of each key (-1 where absent)."""
        if len(self.keys) == 0:
            return np.full(np.shape(keys), -1, dtype=np.int64)
        pos = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        return np.where(self.keys[pos] == keys, pos, -1)

    def keep(self, rows) -> None:
        """Keep only the nodes at ``rows`` (ascending table rows), each field in place.

        The rows move to the front of each array, which is then shrunk (:func:`take_in_place`),
        and the heap's freed pages go back to the system: the kept table is never held
        beside the whole one.
        """
        rows = np.asarray(rows, dtype=np.int64)
        for name in ("keys", "f", "fu", "inside"):
            setattr(self, name, take_in_place(vars(self), name, rows))
        release_free_memory()

    def add(self, keys, f, fu, inside) -> None:
        """Add nodes not in the table yet (``keys`` distinct), keeping the keys sorted.

        Each array grows in place (realloc) and the new rows are merged into it from
        the back, one field at a time, so that this code never makes a second table
        (realloc itself may still copy a block below glibc's mmap threshold):
        concatenating and reordering would hold each field three times at once, at the
        finest level the build's peak. A failure part way leaves the table unusable (the
        build drops it).
        """
        keys = np.asarray(keys, dtype=np.int64).ravel()
        fields = [keys, np.asarray(f), np.asarray(fu), np.asarray(inside, dtype=bool)]
        if np.any(keys[1:] < keys[:-1]):  # (the build adds them sorted)
            order = np.argsort(keys, kind="stable")
            fields = [a[order] for a in fields]
        # where each new row goes in the merged table (ascending)
        at = np.searchsorted(self.keys, fields[0]) + np.arange(len(keys))
        for name, new in zip(("keys", "f", "fu", "inside"), fields, strict=True):
            table = grow_in_place(vars(self), name, len(new))
            width = math.prod(table.shape[1:])
            rows = new.reshape(len(new), width).astype(table.dtype, copy=False)
            # as rows of bytes: one compiled merge serves every field's dtype
            _merge_from_back(
                table.reshape(len(table), width).view(np.uint8),
                at,
                np.ascontiguousarray(rows).view(np.uint8),
            )
            setattr(self, name, table)


@numba.njit(cache=True)
def _merge_from_back(table, at, new):  # pragma: no cover - compiled
    """Merge rows ``new`` into ``table`` at rows ``at`` (ascending), in place.

    ``table`` and ``new`` are 2-D byte views (one row per node).

    ``table`` holds its old rows first and room for ``len(new)`` more at its end; old
    rows move back past the new rows that come before them, last first, so that no row
    is overwritten before it has moved.
    """
    n_old = table.shape[0] - new.shape[0]
    width = table.shape[1]
    j = n_old - 1
    for t in range(new.shape[0] - 1, -1, -1):
        while j >= 0 and j + t + 1 > at[t]:
            for c in range(width):  # element copies: no broadcasting checks to compile
                table[j + t + 1, c] = table[j, c]
            j -= 1
        for c in range(width):
            table[at[t], c] = new[t, c]


# Offsets (in units of h) of the lattice points a node's differenced terms read: the six
# along the axes (twists) and the twelve edge diagonals (f_uvw from the twists of the six).
_STENCIL = np.array(
    [d for d in np.ndindex(3, 3, 3) if 0 < sum(abs(x - 1) for x in d) <= 2], dtype=np.int64
) - 1


#: Nodes whose twists :func:`level_node_data` computes at a time.
LEVEL_CHUNK = 8192


def stencil_keys(table: NodeTable, keys: np.ndarray, h: int) -> np.ndarray:
    """Keys of the lattice points that :func:`level_node_data` reads around ``keys`` at ``h``.

    Each key plus the 18 stencil offsets times ``h`` (a key is linear in the point), the
    points beyond the lattice left out; 1-D, by key, then by offset.
    """
    ijk = table.ijk(keys)
    top = table.dims - 1
    ok = np.ones((len(keys), len(_STENCIL)), dtype=bool)
    for axis in range(3):
        at = ijk[:, axis, None] + h * _STENCIL[None, :, axis]
        ok &= (at >= 0) & (at <= top[axis])
    del at
    offsets = h * table.key(_STENCIL)  # a key is linear in ijk
    return (keys[:, None] + offsets[None])[ok]


def rows_read(table: NodeTable, keys: np.ndarray, h: int, twists: bool = True) -> np.ndarray:
    """Table rows that :func:`level_node_data` reads for ``keys`` (ascending).

    The nodes themselves and, for their twists, the nodes one and two steps ``h`` away
    along the axes (the differences of the neighbours' twists); absent ones are absent
    either way. In chunks of :data:`LEVEL_CHUNK` nodes.
    """
    read = np.zeros(len(table.keys), dtype=bool)
    ring = table.find(keys)
    read[ring] = True
    for _ in range(2 if twists else 0):
        # the neighbours of the nodes marked last, only: the others' are marked already
        before = read.copy()
        for c0 in range(0, len(ring), LEVEL_CHUNK):
            near = _axis_neighbours(table, ring[c0 : c0 + LEVEL_CHUNK], h)
            read[near[near >= 0]] = True
        ring = np.flatnonzero(read & ~before)
    return np.flatnonzero(read)


def level_node_data(table: NodeTable, keys: np.ndarray, h: int, twists: bool = True) -> np.ndarray:
    """Node data rows ``(P, 8, 3)`` of one level: exact ``f``, ``f_u``; differenced twists.

    Mixed derivatives are central differences of the exact Jacobians at the lattice points
    ``+- h`` along each axis (for ``h > 1`` all in ``table``: :func:`build_lattice`
    evaluates them; one-sided only at the lattice's own boundary), symmetrised; ``f_uvw``
    likewise from the mixed derivatives of those points. For ``h > 1`` a node's data thus
    depends on its position and ``h`` alone, not on which other cells were refined: the
    lattice of a root cell is the same whether the whole grid or a window of it is built
    (see ``window``).

    For ``h = 1`` the neighbours are not evaluated for the purpose: the differences use
    those present (each corner of a single-voxel cell has one along every axis inside its
    split parent), one-sided where one is missing. The corners of these cells are voxels,
    where the warp and the Jacobians are exact whatever the twists; the twists only shape
    the polynomial between voxels (pre-images), and there they may differ between a
    window and the whole grid next to a root cell's border.
    """
    rows = table.find(keys)
    out = np.empty((len(keys), N_TERMS, 3))
    # in chunks of nodes: a whole fine level's neighbour tables and twists (about 400
    # bytes a node) would be the build's peak. A node's twists depend on the table
    # alone, so the chunks give the same numbers
    slot = np.full(len(table.keys), -1, dtype=np.int64) if twists else None
    for c0 in range(0, len(rows), LEVEL_CHUNK):
        chunk = rows[c0 : c0 + LEVEL_CHUNK]
        out[c0 : c0 + len(chunk), 0] = table.f[chunk]
        out[c0 : c0 + len(chunk), 1:4] = np.swapaxes(table.fu[chunk], 1, 2)
        if not twists:  # a lattice for the voxels only (see build_lattice's pre_images)
            out[c0 : c0 + len(chunk), 4:] = 0.0
            continue
        # the nodes whose twists are read: the chunk's and their neighbours along the
        # axes (f_uvw differences the twists of those), each looked up once
        near = _axis_neighbours(table, chunk, h)
        around = np.unique(np.concatenate([chunk, near[near >= 0]]))
        slot[around] = np.arange(len(around))
        mixed = _twists(table, around, _axis_neighbours(table, around, h), h)
        here = slot[chunk]
        out[c0 : c0 + len(chunk), 4:7] = mixed[here]
        # f_uvw: differences along the third axis of each twist, averaged over the three
        third = np.zeros((len(chunk), 3))
        for axis, pair in ((2, 0), (1, 1), (0, 2)):  # twist (0, 1) along w, ...
            at = mixed[:, pair]
            third += _difference(at, here, _slot_of(slot, near[:, axis, 0]),
                                 _slot_of(slot, near[:, axis, 1]), h)  # fmt: skip
        out[c0 : c0 + len(chunk), 7] = third / 3.0
        slot[around] = -1
    return out


def _slot_of(slot, rows):
    """Positions in ``slot``'s numbering of table rows (-1 stays -1)."""
    return np.where(rows >= 0, slot[np.maximum(rows, 0)], -1)


def _axis_neighbours(table: NodeTable, rows: np.ndarray, h: int) -> np.ndarray:
    """Table rows ``(P, 3, 2)`` of the nodes ``+-h`` along each axis (-1: none there)."""
    ijk = table.ijk(table.keys[rows])
    top = table.dims - 1
    out = np.full((len(rows), 3, 2), -1, dtype=np.int64)
    for axis in range(3):
        for side, sign in ((0, 1), (1, -1)):
            n = ijk.copy()
            n[:, axis] += sign * h
            ok = (n[:, axis] >= 0) & (n[:, axis] <= top[axis])
            out[ok, axis, side] = table.find(table.key(n[ok]))
    return out


def _difference(values, here, plus, minus, h):
    """d/du of ``values`` at ``here`` from its neighbours: central, one-sided, else 0.

    ``here``, ``plus``, ``minus``: rows of ``values`` (-1: no neighbour on that side).
    """
    d = np.zeros((len(here),) + values.shape[1:])
    both = (plus >= 0) & (minus >= 0)
    fwd = (plus >= 0) & ~both
    bwd = (minus >= 0) & ~both
    d[both] = (values[plus[both]] - values[minus[both]]) / (2.0 * h)
    d[fwd] = (values[plus[fwd]] - values[here[fwd]]) / h
    d[bwd] = (values[here[bwd]] - values[minus[bwd]]) / h
    return d


def _twists(table: NodeTable, rows: np.ndarray, near: np.ndarray, h: int) -> np.ndarray:
    """Symmetrised mixed derivatives ``(P, 3, 3)`` (pairs uv, uw, vw) at table rows.

    ``(d/du_b f_u_a + d/du_a f_u_b) / 2`` by :func:`_difference` of the exact Jacobians
    at the neighbours ``near`` (:func:`_axis_neighbours`).
    """
    out = np.empty((len(rows), 3, 3))
    for pair, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        d_b = _difference(table.fu[:, :, a], rows, near[:, b, 0], near[:, b, 1], h)
        d_a = _difference(table.fu[:, :, b], rows, near[:, a, 0], near[:, a, 1], h)
        out[:, pair] = 0.5 * (d_b + d_a)
    return out
