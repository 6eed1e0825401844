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
from vhm_viz.core.row_threads import run_rows


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


# The stencil: the lattice points a node's differenced terms read, offsets of -1, 0 or 1
# times h along each axis with one or two of them non-zero -- the six along the axes
# (twists) and the twelve edge diagonals (f_uvw from the twists of the six). Kernels walk
# the 3 x 3 x 3 offsets ``o``: ``(o % 3 - 1, o // 3 % 3 - 1, o // 9 - 1)``.


#: Nodes whose neighbours :func:`rows_read` looks up at a time.
LEVEL_CHUNK = 8192


def stencil_keys(table: NodeTable, keys: np.ndarray, h: int) -> np.ndarray:
    """Keys of the lattice points that :func:`level_node_data` reads around ``keys`` at ``h``.

    Each key plus the 18 stencil offsets times ``h``, the points beyond the lattice left
    out; distinct and ascending. The nodes of a level lie on the lattice's points of
    step ``h``: the stencil is marked on that coarser grid (a byte a point, by
    :func:`_mark_stencil`), whose marks in order are the keys in order.
    """
    if h < 1 or ((table.dims - 1) % h).any():
        raise ValueError(f"the lattice's points of step {h} do not span it")
    coarse = (table.dims - 1) // h + 1
    marks = np.zeros(int(np.prod(coarse)), dtype=bool)
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    run_rows(_mark_stencil, len(keys), keys, table.dims, int(h), coarse, marks, grain=4096)
    flat = np.flatnonzero(marks)
    del marks
    i = flat % coarse[0]
    j = (flat // coarse[0]) % coarse[1]
    k = flat // (coarse[0] * coarse[1])
    return h * (i + table.dims[0] * (j + table.dims[1] * k))


@numba.njit(cache=True, nogil=True)
def _mark_stencil(start, stop, keys, dims, h, coarse, marks):  # pragma: no cover - compiled
    """Mark the stencil points around the nodes ``start..stop`` on the grid of step ``h``.

    ``coarse``: that grid's points per axis. Marks are only ever set, so chunks on
    several threads may share ``marks``.
    """
    for n in range(start, stop):
        key = keys[n]
        i = key % dims[0] // h
        j = (key // dims[0]) % dims[1] // h
        k = key // (dims[0] * dims[1]) // h
        for o in range(27):
            dx, dy, dz = o % 3 - 1, (o // 3) % 3 - 1, o // 9 - 1
            moved = (dx != 0) + (dy != 0) + (dz != 0)
            if moved == 0 or moved == 3:
                continue
            a, b, c = i + dx, j + dy, k + dz
            if 0 <= a < coarse[0] and 0 <= b < coarse[1] and 0 <= c < coarse[2]:
                marks[a + coarse[0] * (b + coarse[1] * c)] = True


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

    Compiled (:func:`_node_rows`), in chunks of nodes on the threads of
    :func:`~vhm_viz.core.row_threads.run_rows`: a chunk finds its nodes' stencil rows by
    walking the sorted table beside its sorted keys, and holds nothing else; a row does
    not depend on the chunk that made it.
    """
    keys = np.asarray(keys, dtype=np.int64)
    order = None
    if np.any(keys[1:] <= keys[:-1]):  # (a level's keys come sorted and distinct)
        keys, order = np.unique(keys, return_inverse=True)
    out = np.empty((len(keys), N_TERMS, 3))
    if len(keys):
        run_rows(
            _node_rows, len(keys), np.ascontiguousarray(keys), table.keys, table.f, table.fu,
            table.dims, int(h), bool(twists), out, grain=_NODE_GRAIN,
        )  # fmt: skip
    return out if order is None else out[order]


#: Nodes per chunk of :func:`_node_rows` at least (smaller levels take one thread).
_NODE_GRAIN = 1024


@numba.njit(cache=True, nogil=True)
def _first_not_below(sorted_keys, q):  # pragma: no cover - compiled
    """The first index of ascending ``sorted_keys`` whose key is not below ``q``.

    A binary search written out: loops and scalars only, cheaper to compile than
    ``np.searchsorted`` in a kernel.
    """
    lo, hi = 0, sorted_keys.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if sorted_keys[mid] < q:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True, nogil=True)
def _stencil_rows(start, stop, keys, table_keys, dims, h, rows):  # pragma: no cover
    """Table rows of the 3 x 3 x 3 lattice points of step ``h`` around nodes ``start..stop``.

    ``rows[n - start, (dx + 1) + 3 (dy + 1) + 9 (dz + 1)]`` for offsets with at most two
    non-zero components (the point itself, its 6 axis and 12 edge-diagonal neighbours);
    -1 where the point is beyond the lattice, absent from the table, or a cube corner.
    The keys are ascending, and so are those of each offset: one walk through the
    table per offset.
    """
    n_table = table_keys.shape[0]
    for o in range(27):
        dx, dy, dz = o % 3 - 1, (o // 3) % 3 - 1, o // 9 - 1
        if dx != 0 and dy != 0 and dz != 0:
            for n in range(stop - start):
                rows[n, o] = -1
            continue
        shift = h * (dx + dims[0] * (dy + dims[1] * dz))
        t = _first_not_below(table_keys, keys[start] + shift)
        for n in range(start, stop):
            key = keys[n]
            i = key % dims[0] + h * dx
            j = (key // dims[0]) % dims[1] + h * dy
            k = key // (dims[0] * dims[1]) + h * dz
            if i < 0 or j < 0 or k < 0 or i >= dims[0] or j >= dims[1] or k >= dims[2]:
                rows[n - start, o] = -1
                continue
            q = key + shift
            while t < n_table and table_keys[t] < q:
                t += 1
            rows[n - start, o] = t if t < n_table and table_keys[t] == q else -1


@numba.njit(cache=True, nogil=True)
def _difference(values, col, i, here, plus, minus, h):  # pragma: no cover - compiled
    """d/du of ``values[:, i, col]`` at row ``here`` from rows ``plus``, ``minus`` (-1: none).

    Central where both neighbours are there, one-sided where one is, else 0.
    """
    if plus >= 0 and minus >= 0:
        return (values[plus, i, col] - values[minus, i, col]) / (2.0 * h)
    if plus >= 0:
        return (values[plus, i, col] - values[here, i, col]) / h
    if minus >= 0:
        return (values[here, i, col] - values[minus, i, col]) / h
    return 0.0


@numba.njit(cache=True, nogil=True)
def _twist(fu, around, centre, pair, h, out):  # pragma: no cover - compiled
    """Symmetrised mixed derivative ``pair`` (0: uv, 1: uw, 2: vw) at a stencil point.

    ``out[i] = (d/du_b f_u_a + d/du_a f_u_b)_i / 2``, differenced from the exact Jacobians
    of the points ``+-h`` along the pair's axes ``a`` and ``b``; ``around``: the stencil
    rows (:func:`_stencil_rows`) of a node, ``centre``: the point's stencil index.
    """
    a = 0 if pair < 2 else 1
    b = 1 if pair == 0 else 2
    sa, sb = 3**a, 3**b  # a unit step along the axis, in stencil indices
    row = around[centre]
    for i in range(3):
        d_b = _difference(fu, a, i, row, around[centre + sb], around[centre - sb], h)
        d_a = _difference(fu, b, i, row, around[centre + sa], around[centre - sa], h)
        out[i] = 0.5 * (d_b + d_a)


@numba.njit(cache=True, nogil=True)
def _node_rows(start, stop, keys, table_keys, f, fu, dims, h, twists, out):  # pragma: no cover
    """:func:`level_node_data`'s rows of the nodes ``start <= n < stop``."""
    around = np.empty((stop - start, 27), dtype=np.int64)
    _stencil_rows(start, stop, keys, table_keys, dims, h, around)
    here = np.empty((3, 3))  # the node's twists uv, uw, vw
    plus = np.empty(3)
    minus = np.empty(3)
    third = np.empty(3)
    centre = around.shape[1] // 2  # 13, not a literal: one specialisation of _twist
    for n in range(start, stop):
        rows = around[n - start]
        r = rows[centre]
        for i in range(3):
            out[n, 0, i] = f[r, i]
            for a in range(3):
                out[n, 1 + a, i] = fu[r, i, a]
        if not twists:  # a lattice for the voxels only (see build_lattice's pre_images)
            for t in range(4, out.shape[1]):
                for i in range(3):
                    out[n, t, i] = 0.0
            continue
        for pair in range(3):
            _twist(fu, rows, centre, pair, h, here[pair])
            for i in range(3):
                out[n, 4 + pair, i] = here[pair, i]
        # f_uvw: the difference of twist uv along w, uw along v and vw along u, averaged
        for i in range(3):
            third[i] = 0.0
        for pair in range(3):
            step = 3 ** (2 - pair)
            p, m = rows[centre + step], rows[centre - step]
            if p >= 0:
                _twist(fu, rows, centre + step, pair, h, plus)
            if m >= 0:
                _twist(fu, rows, centre - step, pair, h, minus)
            for i in range(3):
                if p >= 0 and m >= 0:
                    third[i] += (plus[i] - minus[i]) / (2.0 * h)
                elif p >= 0:
                    third[i] += (plus[i] - here[pair, i]) / h
                elif m >= 0:
                    third[i] += (here[pair, i] - minus[i]) / h
        for i in range(3):
            out[n, 7, i] = third[i] / 3.0


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
