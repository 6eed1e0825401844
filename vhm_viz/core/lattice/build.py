"""Building the lattice: root cells refined level by level until they fit the map.

Cells are tested against the exact map at their centre and, near the cage, at the face
centre and edge midpoint nearest to it; a cell whose largest test error exceeds a
fraction of the tolerance, or that lies within a voxel of a cage edge, splits into 8.
The exact evaluations may be shared by builders working together (MPI ranks:
``exchange``), each building a window of the grid.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from vhm_viz.core.errors import AbortedError
from vhm_viz.core.geometry import nearest_points_on_mesh
from vhm_viz.core.image import ImageGeometry, inside_mask, surface_mask
from vhm_viz.core.lattice.cage_edges import cage_edges_in_index, cells_near_edges
from vhm_viz.core.lattice.continuation import CageShells, exact_data
from vhm_viz.core.lattice.hermite import N_TERMS, cell_eval, leaf_summaries
from vhm_viz.core.lattice.hermite_lattice import (
    HermiteLattice,
    leaf_stats,
    root_index,
    root_keys_of,
)
from vhm_viz.core.lattice.nodes import NodeTable, level_node_data, rows_read, stencil_keys
from vhm_viz.core.memory import grow_in_place, release_free_memory

#: Default largest position error of a mapped voxel, in voxels of the input spacing (the
#: Euclidean norm of the error in index coordinates). The one default of every front end.
DEFAULT_TOLERANCE = 0.05
#: Root cell size in voxels (a power of two).
DEFAULT_ROOT = 16
#: Largest tolerance, in voxels: the width of a root cell, the lattice's largest cell. An
#: error bound wider than the cells that carry the map bounds nothing of use (a voxel could
#: land a whole cell away), so a larger value is refused as a mistake.
MAX_TOLERANCE = float(DEFAULT_ROOT)
#: A cell passes when its largest test error is below this fraction of the tolerance.
_SAFETY = 0.15
# Cells within this many voxels (box distance) of a cage edge split down to single voxels,
# whose corners are exact: next to an edge the map has a logarithmic singularity that the
# tests of a larger cell can miss, errors of a few hundredths of a voxel within half a voxel
# of the edge.
_EDGE_BAND = 1.0
# Corner offsets of a cell, corner ``a + 2 b + 4 c`` at ``(a, b, c)``.
_CORNERS = np.array([[a, b, c] for c in (0, 1) for b in (0, 1) for a in (0, 1)])


def check_tolerance(tolerance) -> float:
    """The volume tolerance as a float, refused unless in (0, :data:`MAX_TOLERANCE`] voxels.

    The one check of the setting: the volume engine's constructors, the filters'
    ``SetTolerance`` and the command line's ``--tolerance`` all call it.

    Parameters
    ----------
    tolerance : float
        Largest position error of a mapped voxel, in voxels of the input spacing.

    Returns
    -------
    float
        The tolerance, in voxels.

    Raises
    ------
    ValueError
        When it is not a number of voxels in (0, :data:`MAX_TOLERANCE`].
    """
    try:
        value = float(tolerance)
    except (TypeError, ValueError):
        value = math.nan
    if not (value > 0 and value <= MAX_TOLERANCE):
        shown = f"{value:g}" if value == value else repr(tolerance)
        raise ValueError(
            f"tolerance must be a positive number of voxels, at most {MAX_TOLERANCE:g} (the "
            f"lattice's root cell); got {shown}"
        )
    return value


def build_lattice(
    harmonic_map,
    geometry: ImageGeometry,
    *,
    tolerance: float = DEFAULT_TOLERANCE,
    root: int = DEFAULT_ROOT,
    memory_budget: int | None = None,
    progress=None,
    abort=None,
    window=None,
    exchange=None,
    pre_images: bool = True,
) -> HermiteLattice:
    """Build the adaptive Hermite lattice of a map over an image grid.

    Parameters
    ----------
    harmonic_map, geometry : HarmonicMap, ImageGeometry
        The map, and the input volume's grid it is built over.
    tolerance : float
        Largest allowed position error, in voxels of the input spacing (Euclidean norm
        of the error in index coordinates); default :data:`DEFAULT_TOLERANCE`.
    root : int
        Root cell size (voxels, a power of two).
    memory_budget : int, optional
        Bytes of working memory per evaluation chunk (sets progress and abort steps).
    progress : callable(fraction, message), optional
    abort : callable() -> bool, optional
        Checked between evaluation chunks; :class:`~vhm_viz.core.errors.AbortedError`.
    window : (i0, i1, j0, j1, k0, k1), optional
        Build only the root cells that own a voxel of this box (inclusive voxel ranges;
        default: the whole grid). Root cells stay aligned with the whole grid and every
        node's data depends on its position alone, so each root cell's subtree -- and
        every voxel of the window -- is the same as in the whole grid's lattice (to
        rounding: the exact evaluations run in other chunks). For pieces of a volume
        (MPI ranks, streaming): each builds only its own part. Within those root cells
        only the cells that own a voxel of the box are refined. With an ``exchange`` an
        empty box (``i1 < i0``: an MPI rank's empty piece) builds no cell; the builder
        only shares the others' evaluations.
    exchange : callable(keys, evaluate) -> (f, fu, inside), optional
        How the exact evaluations are shared by builders working together (MPI ranks):
        called with the keys (int64, sorted; a key names the same lattice point on every
        builder of the grid) of the points whose data this builder needs, and
        ``evaluate``, which computes the data of any keys here; it returns this builder's
        keys' data, computed wherever it likes (each point's data depends on the point
        alone).
        A collective: it is called exactly :func:`exchange_rounds` ``(root)`` times, in
        the same order on every builder, with zero points where a builder needs none. If
        it has an ``abandon()`` method, that is called when the build fails between two
        calls, so that the others are not left waiting. Default: ``evaluate(points)``.
    pre_images : bool
        False: a lattice for the voxels only (warps and Jacobians), without what only
        the polynomial between voxels needs: the single-voxel cells' twists (zero: at
        their corners, the voxels, every derivative term has a zero weight) and the
        leaves' pre-image summaries. The voxels' values are the same; :meth:`evaluate`,
        :meth:`image_boxes` and :meth:`pull_back` refuse it. It builds faster and holds
        less memory.

    Returns
    -------
    HermiteLattice
    """
    t0 = time.perf_counter()
    tolerance = check_tolerance(tolerance)
    root = int(root)
    if root < 1 or root & (root - 1):
        raise ValueError(f"root must be a power of two; got {root}")
    last = np.asarray(geometry.dimensions, dtype=np.int64) - 1
    n_root = np.maximum(1, -(-last // root))  # root cells per axis
    lattice_dims = n_root * root + 1
    to_index = geometry.index_to_world
    cage = harmonic_map.cage
    V = np.asarray(cage.vertices, dtype=np.float64)
    Fc = np.asarray(cage.faces)
    shells = CageShells(V, Fc)
    # every lattice point's side of the cage (the lattice overhangs the volume)
    lat_geo = ImageGeometry(geometry.origin, geometry.spacing, lattice_dims, geometry.direction)
    table = NodeTable(lattice_dims)
    n_eval = np.zeros(2, dtype=np.int64)  # inside, outside (continued)
    edge_a, edge_b = cage_edges_in_index(lat_geo, cage)

    def evaluate(keys):
        points = lat_geo.points(table.ijk(keys).astype(np.float64))
        return exact_data(harmonic_map, points, to_index, shells, memory_budget, abort)

    rounds, in_round = [0], [False]

    def ensure(keys, distinct=False):
        """Evaluate the points of ``keys`` not in the table (``distinct``: sorted, unique)."""
        keys = keys if distinct else np.unique(keys)
        new = keys[table.find(keys) < 0]
        if exchange is not None:  # every round, with or without points of its own
            in_round[0] = True  # a round that raises has been agreed by everyone
            f, fu, ins = exchange(new, evaluate)
            in_round[0] = False
            rounds[0] += 1
        elif new.size:
            f, fu, ins = evaluate(new)
        if new.size:
            table.add(new, f, fu, ins)
            n_eval[0] += ins.sum()
            n_eval[1] += (~ins).sum()
            del f, fu, ins
        # the round's transients (evaluation chunks, an MPI exchange's messages) leave
        # free pages inside the heap, which the next, larger level would not reuse
        # whole: back to the system, so that they do not add to the build's peak
        release_free_memory()

    try:
        roots = _window_roots(window, root, n_root, geometry, exchange is not None)
        mask, near = _masks(lat_geo, V, Fc, _mask_rows(window, roots, root), pre_images)
        lattice = _build_levels(
            ensure, table, harmonic_map, geometry, lat_geo, tolerance, root, last, n_root,
            mask, near, (edge_a, edge_b), roots, None if exchange is not None else abort,
            progress, pre_images=pre_images,
        )  # fmt: skip
        # builders working together meet the same number of times
        for _ in range(exchange_rounds(root) - rounds[0] if exchange is not None else 0):
            ensure(np.zeros(0, dtype=np.int64), distinct=True)
    except BaseException:
        # failed between two rounds: the others are waiting in the next one
        if not in_round[0] and rounds[0] < exchange_rounds(root) and hasattr(
            exchange, "abandon"
        ):
            exchange.abandon()
        raise
    release_free_memory()
    lattice.stats.update(
        evaluations=int(n_eval.sum()),
        evaluations_outside=int(n_eval[1]),
        seconds=time.perf_counter() - t0,
    )
    if progress is not None:
        progress(1.0, "lattice")
    return lattice


def exchange_rounds(root: int) -> int:
    """How many times :func:`build_lattice` calls its ``exchange`` for a root cell size.

    Two per level with cells larger than a voxel (their corners and test points, then the
    points the twists read), one for single-voxel cells.
    """
    return 2 * int(math.log2(int(root))) + 1


def _window_roots(window, root, n_root, geometry, shared):
    """The window (validated) and the range of root cells it builds, per axis.

    Returns ``(w, lo_root, hi_root)``: ``w`` None for the whole grid, or for an empty
    piece of a shared build (more MPI ranks than planes: no cells of its own, but its
    builder still evaluates its share of the others' points; then ``hi_root < lo_root``).
    """
    lo_root, hi_root = np.zeros(3, dtype=np.int64), n_root - 1
    if window is None:
        return None, lo_root, hi_root
    w = np.asarray(window, dtype=np.int64).reshape(6)
    if shared and (w[1::2] < w[0::2]).any():
        return None, lo_root, np.full(3, -1, dtype=np.int64)
    last = np.asarray(geometry.dimensions, dtype=np.int64) - 1
    if (w[0::2] < 0).any() or (w[1::2] > last).any() or (w[1::2] < w[0::2]).any():
        raise ValueError(f"window {w.tolist()} is not inside the grid of dimensions "
                         f"{tuple(geometry.dimensions)}")  # fmt: skip
    # a root cell owns [o, o + root); the grid's last voxel belongs to the last cell
    return w, np.minimum(w[0::2] // root, n_root - 1), np.minimum(w[1::2] // root, n_root - 1)


def _mask_rows(window, roots, root):
    """The lattice rows ``(j0, j1, k0, k1)`` of a window's root cells (None: every row).

    Outside them a window's build reads neither mask (its cells are those root cells).
    """
    if window is None:
        return None
    _, lo_root, hi_root = roots
    if (hi_root < lo_root).any():  # an empty piece: no cells, no rows
        return (0, 0, 0, 0)
    lo, hi = lo_root * root, (hi_root + 1) * root + 1  # up to the far corners
    return (int(lo[1]), int(hi[1]), int(lo[2]), int(hi[2]))


# At most this many k-planes of the lattice's masks are computed at a time (see _masks).
_MASK_PLANES = 16


def _masks(lat_geo: ImageGeometry, vertices, faces, rows, surface=True):
    """Inside and next-to-the-surface masks of the lattice points, computed in ``rows``.

    Both have the whole lattice's shape; without ``surface`` the second is empty
    (0, 0, 0): only pre-images read it (a lattice without them leaves it out, see
    :func:`_count_inside`). Outside ``rows`` (default: all) they stay False
    and their zero pages are never written, so a window's build holds the memory of its
    own rows only. They are made a few k-planes at a time (at most ``_MASK_PLANES``),
    the blocks shared by the compiled kernels' threads:
    :func:`~vhm_viz.core.image.inside_mask` keeps 16-bit winding numbers of the points it
    is asked for, which for a whole window would add to the build's peak (and a few
    planes at a time stay in cache). A row's values do not depend on which others are
    computed with it.
    """
    nx, ny, nz = lat_geo.dimensions
    j0, j1, k0, k1 = (0, ny, 0, nz) if rows is None else rows
    mask = np.zeros((nz, ny, nx), dtype=bool)
    near = np.zeros((nz, ny, nx) if surface else (0, 0, 0), dtype=bool)
    if j1 <= j0 or k1 <= k0:
        return mask, near
    workers = numba.get_num_threads()
    # a few blocks per worker, so that blocks of uneven cost even out
    planes = min(_MASK_PLANES, max(1, -(-(k1 - k0) // (4 * workers))))

    def block(a):
        b = min(k1, a + planes)
        mask[a:b, j0:j1] = inside_mask(lat_geo, vertices, faces, rows=(j0, j1, a, b))
        if surface:
            near[a:b, j0:j1] = surface_mask(lat_geo, vertices, faces, rows=(j0, j1, a, b))

    starts = range(k0, k1, planes)
    if workers == 1 or len(starts) == 1:
        for a in starts:
            block(a)
    else:  # the scanline kernel and numpy's array operations release the GIL
        with ThreadPoolExecutor(min(workers, len(starts))) as pool:
            list(pool.map(block, starts))
    return mask, near


def _build_levels(
    ensure, table, harmonic_map, geometry, lat_geo, tolerance, root, last, n_root, mask,
    near, edges, roots, abort, progress, pre_images=True,
):  # fmt: skip
    """The level loop of :func:`build_lattice`: refine cells until they fit the map."""
    V = np.asarray(harmonic_map.cage.vertices, dtype=np.float64)
    Fc = np.asarray(harmonic_map.cage.faces)
    to_voxel = np.ascontiguousarray(geometry.world_to_index)
    edge_a, edge_b = edges
    end = n_root * root
    w, lo_root, hi_root = roots
    ranges = [np.arange(lo_root[a], hi_root[a] + 1) for a in range(3)]
    g = np.stack(np.meshgrid(*ranges[::-1], indexing="ij"), -1)
    cells = (g.reshape(-1, 3)[:, ::-1] * root).astype(np.int64)
    leaves: list = []
    level_data: list = []
    h = root
    n_levels = int(math.log2(root)) + 1
    parent_cut = np.ones(len(cells), dtype=bool)  # (the root cells: none known)
    while len(cells):
        if abort is not None and abort():
            raise AbortedError("aborted")
        if w is not None and h < root:
            # only cells that own a voxel of the window matter (each cell's refinement is
            # its own: the window's leaves are the whole lattice's)
            own = _owns_voxel_of(cells, h, end, w)
            cells, parent_cut = cells[own], parent_cut[own]
        # only cells with a voxel inside the cage matter; cut: the cage passes through the
        # cell (voxels outside, or next to the surface). A cell lies in its parent's
        # closed box: in an uncut parent its voxels are all inside and none is next to the
        # surface, so only the children of cut cells are counted voxel by voxel
        keep = np.all(cells <= last, axis=1)  # (a voxel of the volume in the cell)
        cut = np.zeros(len(cells), dtype=bool)
        scan = np.flatnonzero(parent_cut)
        if len(scan):
            counts = np.zeros((len(scan), 3), dtype=np.int64)
            _count_inside(mask, near, np.ascontiguousarray(cells[scan]), h, last, counts)
            keep[scan] = counts[:, 0] > 0
            cut[scan] = (counts[:, 1] > 0) | (counts[:, 2] > 0)
            del counts
        cells, cut = cells[keep], cut[keep]
        del keep, scan
        if not len(cells):
            break
        # the corners as rows of the level's keys, (n, 8): the corners themselves,
        # (n, 8, 3), are not held through the level (the finest level's would be a large
        # part of the build's peak)
        corner_keys = table.key(cells[:, None, :] + _CORNERS[None] * h)
        level_keys = np.unique(corner_keys)
        rows = np.searchsorted(level_keys, corner_keys)
        del corner_keys
        if h > 1:
            offsets = _test_points(cells, h, lat_geo, V, Fc)
            has = np.isfinite(offsets[..., 0])
            tests = cells[:, None, :] + np.rint(np.nan_to_num(offsets) * h).astype(np.int64)
            ensure(np.concatenate([level_keys, table.key(tests[has])]))
        else:
            ensure(level_keys, distinct=True)
        if h > 1:
            # single-voxel cells skip the stencil: their corners are voxels, which the
            # warp and the Jacobians read exactly whatever the twists (see
            # level_node_data): the finest level's stencil would be many evaluations
            ensure(stencil_keys(table, level_keys, h), distinct=True)
        if h == 1:
            # the finest level, the last: the table keeps only the nodes its data reads
            # before that data is made beside it: the others (corners and test points of
            # coarser levels) would add to the build's peak
            table.keep(rows_read(table, level_keys, h, twists=pre_images))
        data = level_node_data(table, level_keys, h, twists=pre_images or h > 1)
        split = np.zeros(len(cells), dtype=bool)
        if h > 1:
            test_rows = np.where(has, table.find(table.key(tests)), -1)
            err = np.empty(len(cells))
            _test_errors(
                data, rows, float(h), np.nan_to_num(offsets), test_rows, table.f, to_voxel, err
            )
            near_edge = np.zeros(len(cells), dtype=np.bool_)
            cells_near_edges(cells, h, edge_a, edge_b, _EDGE_BAND, near_edge)
            split = (err > _SAFETY * tolerance) | near_edge
            # (not carried into the next, finer level's peak)
            del offsets, has, tests, test_rows, err, near_edge
        level_data.append(data)
        leaves.append((cells[~split], h, len(level_data) - 1, rows[~split], cut[~split]))
        if progress is not None:
            progress(min(0.95, len(level_data) / n_levels), "lattice")
        if not split.any():
            break
        parent_cut = np.repeat(cut[split], len(_CORNERS))
        cells = (cells[split][:, None, :] + _CORNERS[None] * (h // 2)).reshape(-1, 3)
        h //= 2
    # the levels hold their own copies of the node data: hand the table's memory back
    # before the levels are packed (and let go of the last level: _assemble grows it)
    data = None
    table.clear()
    release_free_memory()
    return _assemble(
        leaves, level_data, n_root, root, geometry, tolerance, mask, near, edges, pre_images
    )


def _owns_voxel_of(cells, h, end, box) -> np.ndarray:
    """Which cells of size ``h`` own a voxel of ``box`` (as the voxel kernels count them)."""
    far = cells + h - 1 + (cells + h == end)  # the lattice's far end: the last cell's
    return np.all((cells <= box[1::2]) & (far >= box[0::2]), axis=1)


def _assemble(
    leaves, level_data, n_root, root, geometry, tolerance, mask, near, edges, pre_images=True
):
    """Pack the levels into one data table and the leaves, grouped by root cell."""
    # packed level by level, each level freed once copied. The largest level (the
    # finest, most of the table) comes first and is grown in place
    # into the table (realloc remaps a large block rather than copying it), so that the
    # peak is the packed table, not the table plus that level
    sizes = [len(d) for d in level_data]
    big = int(np.argmax(sizes)) if sizes else -1
    packing = ([big] if sizes else []) + [lv for lv in range(len(sizes)) if lv != big]
    starts = np.zeros(len(sizes), dtype=np.int64)
    starts[packing] = np.cumsum([0] + [sizes[lv] for lv in packing])[:-1]
    total = int(sum(sizes))
    if sizes:
        data = grow_in_place(level_data, big, total - sizes[big])
    else:
        data = np.empty((0, N_TERMS, 3))
    for lv in packing[1:]:
        data[starts[lv] : starts[lv] + sizes[lv]] = level_data[lv]
        level_data[lv] = None
        release_free_memory()  # the level's heap pages too, not only its array
    origin = np.concatenate([c for c, *_ in leaves] or [np.zeros((0, 3), np.int64)])
    size = np.concatenate([np.full(len(c), s, np.int64) for c, s, *_ in leaves] or [[]])
    rows = np.concatenate(
        [r + starts[lv] for _, _, lv, r, _ in leaves] or [np.zeros((0, 8), np.int64)]
    )
    cut = np.concatenate([c for *_, c in leaves] or [np.zeros(0, bool)])
    rkey = root_keys_of(origin, root, n_root)
    order = np.argsort(rkey, kind="stable")
    # one at a time, each old array freed before the next is reordered
    origin = origin[order]
    size = size.astype(np.int64)[order]
    rows = rows[order]
    cut = cut[order]
    rkey = rkey[order]
    release_free_memory()
    start, count = root_index(rkey, n_root)
    n = len(origin)
    m = n if pre_images else 0
    centre_f, centre_ginv, rho = np.empty((m, 3)), np.empty((m, 3, 3)), np.empty(m)
    if m:
        leaf_summaries(data, rows, size, centre_f, centre_ginv, rho)
    stats = leaf_stats(size, len(data))
    return HermiteLattice(
        geometry=geometry,
        tolerance=tolerance,
        root=root,
        n_root=n_root.astype(np.int64),
        data=data,
        leaf_origin=np.ascontiguousarray(origin),
        leaf_size=np.ascontiguousarray(size),
        leaf_rows=np.ascontiguousarray(rows),
        leaf_cut=np.ascontiguousarray(cut),
        root_start=start,
        root_count=count,
        centre_f=centre_f,
        centre_ginv=centre_ginv,
        rho=rho,
        mask=mask,
        near=near if pre_images else None,
        edge_a=edges[0],
        edge_b=edges[1],
        stats=stats,
        pre_images=bool(pre_images),
    )


@numba.njit(parallel=True, cache=True)
def _count_inside(mask, near, origins, h, last, counts):  # pragma: no cover - compiled
    """Inside, outside and next-to-the-surface voxels of the volume in each closed cell.

    An empty ``near`` (a lattice without pre-images) counts no voxel next to the surface:
    a cell is then cut only where voxels are outside. Which cells are kept is the same
    either way (the children of an uncut parent are all inside), only ``leaf_cut``,
    which the pull-back alone reads, differs.
    """
    surface = near.size > 0
    for c in numba.prange(origins.shape[0]):
        nin = 0
        nout = 0
        nnear = 0
        for k in range(origins[c, 2], min(origins[c, 2] + h, last[2]) + 1):
            for j in range(origins[c, 1], min(origins[c, 1] + h, last[1]) + 1):
                for i in range(origins[c, 0], min(origins[c, 0] + h, last[0]) + 1):
                    if mask[k, j, i]:
                        nin += 1
                    else:
                        nout += 1
                    if surface and near[k, j, i]:
                        nnear += 1
        counts[c, 0] = nin
        counts[c, 1] = nout
        counts[c, 2] = nnear


def _test_points(cells, h, lat_geo, vertices, faces):
    """Test points of each cell, as local coordinates (L, T, 3); NaN rows: no test.

    The centre (where a smooth cell's error peaks); for cells within two widths of the
    cage also the face centre and the edge midpoint nearest to the cage (where the error
    of a cell next to it concentrates). More tests (the nearest octant centre, or the 8
    octant centres of farther cells) cost evaluations without catching larger errors;
    without the edge midpoint, errors of a cell's edge facing the cage would pass. All
    are voxel positions.
    """
    L = len(cells)
    out = np.full((L, 3, 3), np.nan)
    out[:, 0] = 0.5
    centres = lat_geo.points(cells + h / 2.0)
    _, q = nearest_points_on_mesh(centres, vertices, faces)
    rel = (lat_geo.continuous_index(q) - cells) / h  # nearest cage point, local coordinates
    near = np.linalg.norm(rel - 0.5, axis=1) < 2.0
    cl = np.clip(rel, 0.0, 1.0)
    dev = np.abs(cl - 0.5)
    order = np.argsort(-dev, axis=1)
    rows = np.arange(L)
    face = np.full((L, 3), 0.5)
    face[rows, order[:, 0]] = np.round(cl[rows, order[:, 0]])
    edge = face.copy()
    edge[rows, order[:, 1]] = np.round(cl[rows, order[:, 1]])
    out[near, 1] = face[near]
    out[near, 2] = edge[near]
    return out


@numba.njit(parallel=True, cache=True)
def _test_errors(data, cell_rows, h, offsets, test_rows, node_f, to_voxel, out):
    """Largest error (voxels) of each cell's polynomial at its test points.

    ``offsets[c, k]`` are the local coordinates of test point ``k`` of cell ``c`` and
    ``test_rows[c, k]`` its node-table row (-1: no test); ``to_voxel`` turns a world
    error into voxels.
    """  # noqa: D401
    for c in numba.prange(cell_rows.shape[0]):
        f = np.empty(3)
        g = np.empty((3, 3))
        worst = 0.0
        for k in range(offsets.shape[1]):
            r = test_rows[c, k]
            if r < 0:
                continue
            cell_eval(
                data, cell_rows[c], h, offsets[c, k, 0], offsets[c, k, 1], offsets[c, k, 2],
                f, g, False,
            )  # fmt: skip
            e = 0.0
            for i in range(3):
                d = 0.0
                for j in range(3):
                    d += to_voxel[i, j] * (f[j] - node_f[r, j])
                e += d * d
            worst = max(worst, math.sqrt(e))
        out[c] = worst
