"""The checks after the map that tell whether a deformation folds the data.

:func:`fold_warning` is the one line ``deform`` prints (or refuses with) when it does:
inverted cells of a warped volume (:func:`warped_voxel_folds`) or tet mesh, resampled
voxels in folds (the resample filter's ``fold_voxels``,
:mod:`vhm_viz.core.fold_voxels`), and ``det J <= 0`` at evenly spread points of the
continuous map.
:func:`load_check_kernels` loads these checks' compiled kernels while the solve runs.
"""

from __future__ import annotations

import numpy as np

from vhm_viz import interrupts
from vhm_viz.core.fold_voxels import FOLDS, fold_voxels_text, inverted_cells, inverted_cells_text
from vhm_viz.core.fold_voxels import position_text as _position

#: Points at which ``vhm-viz deform`` samples ``det J`` for its fold warning (evenly spread)
#: when nothing else checks the whole output (a surface, a point cloud): at most this many,
#: and at most one in :data:`FOLD_SAMPLE_SPREAD` of the data's (:func:`fold_samples`).
FOLD_SAMPLES = 20000
#: The exact Jacobian at a point costs about twice the map's value there (both sum over
#: the cage's faces; the Jacobian three gradients besides the value): one point in this
#: many holds the samples to about a sixteenth of the map's work, so that with the
#: summary's measures (``E_volume``) the checks stay a small part of the map.
FOLD_SAMPLE_SPREAD = 32
#: Points of the spot check beside a check of the whole output -- every cell of a warped
#: volume or tet mesh, every resampled voxel's pre-image -- at most (evenly spread): there
#: the output's own check finds its folds, and this one samples the exact ``det J`` of the
#: continuous map itself, at a cost that stays a small part of even a fast map's (a
#: volume engine's map is far cheaper per voxel than the exact Jacobian). Also the fewest
#: points of :func:`fold_samples`.
FOLD_SPOT_SAMPLES = 256


def fold_samples(n_points: int) -> int:
    """Points of the fold warning's ``det J`` samples of an output of ``n_points`` points."""
    return min(FOLD_SAMPLES, max(FOLD_SPOT_SAMPLES, int(n_points) // FOLD_SAMPLE_SPREAD))


def _where(points: np.ndarray, values: np.ndarray) -> str:
    """``worst -0.12 at (x, y, z), within [lo]-[hi]`` for the bad points (rest positions)."""
    k = int(np.argmin(values))
    text = f"worst {values[k]:.3g} at {_position(points[k])}"
    if len(points) > 1:  # column by column: numpy's axis-0 reduction of (K, 3) is slow
        lo = [points[:, c].min() for c in range(points.shape[1])]
        hi = [points[:, c].max() for c in range(points.shape[1])]
        text += f", within {_position(lo)}-{_position(hi)}"
    return text


def _points_of(data, index) -> np.ndarray:
    """Positions of the points ``index`` of ``data``; an image's without making them all."""
    import pyvista as pv

    from vhm_viz.filters._vtk import image_geometry

    index = np.asarray(index, dtype=np.int64)
    if isinstance(data, pv.ImageData):
        ijk = np.column_stack(np.unravel_index(index, tuple(data.dimensions), order="F"))
        return image_geometry(data).points(ijk)
    return np.asarray(data.points, dtype=np.float64)[index]


#: Cells per slab of :func:`inverted_voxel_cells` at most: a slab takes a small fraction
#: of a second, and an interrupt is acted on between slabs.
FOLD_SLAB_CELLS = 1 << 22
#: Share of a grid's cells above which :func:`inverted_voxel_cells` sweeps every cell
#: rather than measuring the unproven ones alone: the sweep shares each plane's work
#: between the layers of cells and runs along whole rows, several times faster per cell.
_SWEEP_FRACTION = 0.2
#: Working memory of :func:`inverted_voxel_cells` per cell of a slab at most (bytes): an
#: inverted cell's index and determinant (no memory per cell that is not inverted).
_FOLD_CELL_BYTES = 16


def inverted_voxel_cells(
    points, dimensions, rest_det: float, progress=None, memory_budget=None, unproven=None
) -> dict:
    """The inverted cells of a warped voxel grid, slab by slab, in bounded memory.

    :func:`~vhm_viz.core.cell_kernels.inverted_hexahedra` of a slab of voxel layers at a
    time (or of a group of ``unproven`` boxes): only the inverted cells are held, and an
    interrupt is acted on between slabs, so that Ctrl-C or SIGTERM stops the fold check of
    a large warped volume promptly.

    Parameters
    ----------
    points : (nx * ny * nz, 3) array_like
        Deformed positions in VTK's point order.
    dimensions : (3,) int
    rest_det : float
    progress : callable, optional
        ``progress(fraction)`` after each slab.
    memory_budget : int, optional
        Bytes of working memory per slab (default: slabs of :data:`FOLD_SLAB_CELLS`
        cells; a slab is at least one layer of cells).
    unproven : (K, 6) int array_like, optional
        The only cells to measure (inclusive cell ranges,
        :meth:`~vhm_viz.core.volume.VolumeDeformation.unproven_cells`): the others are
        proven not inverted, and counted as measured cells. Where they are more than
        :data:`_SWEEP_FRACTION` of the cells, every cell is measured.

    Returns
    -------
    dict
        :func:`fold_warning`'s ``cells``: ``summary`` (``cells``: cells with finite
        corners, ``inverted``: of them with a corner determinant ``<= 0``, ``proven``:
        of them proven not inverted without being measured), ``inverted`` (K,) int64 (the
        inverted cells in VTK's cell order) and ``inverted_determinant`` (K,) float64
        (their smallest corner determinant relative to the rest voxel's).
    """
    from vhm_viz.core.cell_kernels import inverted_hexahedra

    nx, ny, nz = (int(d) for d in dimensions)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    plane, cell_plane = nx * ny, max(nx - 1, 0) * max(ny - 1, 0)
    slab_cells = FOLD_SLAB_CELLS
    if memory_budget is not None:
        slab_cells = min(slab_cells, int(memory_budget) // _FOLD_CELL_BYTES)
    checked, proven, inverted, worst = 0, 0, [np.zeros(0, np.int64)], [np.zeros(0)]
    boxes = np.asarray([] if unproven is None else unproven, dtype=np.int64).reshape(-1, 6)
    ends = np.cumsum(np.prod(boxes[:, 1::2] - boxes[:, 0::2] + 1, axis=1))
    n_unproven, all_cells = int(ends[-1]) if ends.size else 0, cell_plane * max(nz - 1, 0)
    if unproven is not None and n_unproven <= _SWEEP_FRACTION * all_cells:
        proven = all_cells - n_unproven
        # groups of boxes of about slab_cells cells
        group_of = (ends - 1) // max(slab_cells, 1)
        groups = np.split(boxes, np.flatnonzero(np.diff(group_of)) + 1)
        for g, group in enumerate(groups):
            part = inverted_hexahedra(points, dimensions, rest_det, group)
            checked += part["cells"]
            inverted.append(part["inverted"])
            worst.append(part["determinant"])
            interrupts.check()
            if progress is not None:
                progress((g + 1) / len(groups))
        bad = np.concatenate(inverted)
        order = np.argsort(bad, kind="stable")
        bad, worst = bad[order], np.concatenate(worst)[order]
    else:
        layers = max(1, slab_cells // max(cell_plane, 1))
        for k0 in range(0, nz - 1, layers):
            k1 = min(k0 + layers, nz - 1)
            slab = inverted_hexahedra(
                points[k0 * plane : (k1 + 1) * plane], (nx, ny, k1 - k0 + 1), rest_det
            )
            checked += slab["cells"]
            inverted.append(slab["inverted"] + k0 * cell_plane)
            worst.append(slab["determinant"])
            interrupts.check()
            if progress is not None:
                progress(k1 / (nz - 1))
        bad, worst = np.concatenate(inverted), np.concatenate(worst)
    return {
        "summary": {"cells": checked + proven, "inverted": int(bad.size), "proven": proven},
        "inverted": bad,
        "inverted_determinant": worst,
    }


def _spot_jacobian_determinants(harmonic_map, points) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``det J`` at points inside the cage: (which points, their ``det J``).

    Through :meth:`~vhm_viz.core.harmonic_map.HarmonicMap.jacobian`, the basis kernel that
    solving the scene has already run (a sample of points needs no kernel of its own).
    Points outside the cage, or on a cage edge (no Jacobian), are left out.
    """
    from vhm_viz.core.metrics import jacobian_determinant

    jac = harmonic_map.jacobian(points, outside="nan")
    ok = np.isfinite(jac).all(axis=(1, 2))
    return ok, jacobian_determinant(jac[ok])


def fold_warning(
    rest, harmonic_map, cells=None, point_det=None, samples: int = FOLD_SAMPLES, voxels=None
) -> str | None:
    """One warning line when a deformation folds the data, naming how many and where.

    Parameters
    ----------
    rest : pyvista.DataSet
        The rest data (positions in the message are rest positions).
    harmonic_map : HarmonicMap
    cells : dict, optional
        The output's cells (3D cells only): :func:`vhm_viz.filters.cell_quality` of the
        output (``determinant`` per cell), or :func:`inverted_voxel_cells` (``inverted``
        cells and their ``inverted_determinant``); either with its ``summary``, and
        optionally ``centres(cells)``, the rest centres of cells given by index, and
        ``outside``, (N,) flags of the points left in place outside the cage (the line
        counts the inverted cells that straddle the cage).
    point_det : (N,) array_like, optional
        ``det J`` at every point, when already computed; else it is sampled exactly at up
        to ``samples`` points.
    samples : int
        :func:`fold_samples`, or :data:`FOLD_SPOT_SAMPLES` beside a check of the whole
        output.
    voxels : dict, optional
        A resampled output's voxels in folds (several pre-images):
        :func:`~vhm_viz.core.fold_voxels.fold_voxels`, the resample filter's
        ``fold_voxels``.

    Returns
    -------
    str or None
        None when no cell is inverted, no output voxel lies in a fold and no sampled
        ``det J`` is ``<= 0``.
    """
    voxel_text = None if voxels is None else fold_voxels_text(voxels)
    voxel_part = [] if voxel_text is None else [voxel_text]
    parts = list(voxel_part)
    if cells is not None and cells["summary"]["inverted"]:
        if "inverted" in cells:
            bad, worst = np.asarray(cells["inverted"]), np.asarray(cells["inverted_determinant"])
        else:
            det = np.asarray(cells["determinant"])
            bad = np.nonzero(det <= 0)[0]
            worst = det[bad]
        if "centres" in cells:
            centres = np.asarray(cells["centres"](bad))
        else:
            from vhm_viz.filters.cells import cell_centres

            centres = cell_centres(rest, bad)
        straddling = 0
        if cells.get("outside") is not None:  # points left in place outside the cage
            from vhm_viz.filters.cells import cells_touching

            straddling = int(np.count_nonzero(cells_touching(rest, bad, cells["outside"])))
        summary = inverted_cells(worst, centres, cells["summary"]["cells"], straddling)
        parts.append(inverted_cells_text(summary))
    n_points = rest.GetNumberOfPoints()
    if point_det is None:
        idx = np.unique(np.linspace(0, n_points - 1, min(n_points, samples)).astype(int))
        ok, det = _spot_jacobian_determinants(harmonic_map, _points_of(rest, idx))
        idx = idx[ok]
        what = f"{idx.size} sampled points"
    else:
        det = np.asarray(point_det, dtype=np.float64)
        idx = np.nonzero(np.isfinite(det))[0]
        det = det[idx]
        what = f"{idx.size} points"
    bad = det <= 0
    if bad.any():
        parts.append(
            f"det J <= 0 at {int(bad.sum())} of {what} "
            f"({_where(_points_of(rest, idx[bad]), det[bad])})"
        )
    if not parts:
        return None
    # the cells' and the sampled points' positions are rest positions; the voxels' say theirs
    rest = "rest positions; " if len(parts) > len(voxel_part) else ""
    return FOLDS + "; ".join(parts) + f" ({rest}vhm-viz analyze --certify checks every point)"


#: Voxel cells of a warped image from which its fold check measures only the cells that
#: the volume engine's lattice does not prove unfolded: below it, measuring every cell
#: takes less time than loading the proof's compiled kernels.
PROOF_MIN_CELLS = 1 << 23


def proof_sized(dimensions) -> bool:
    """Whether the fold check of a warped image of ``dimensions`` asks the lattice's proof.

    By its cells' count (:data:`PROOF_MIN_CELLS`).
    """
    return int(np.prod(np.asarray(dimensions) - 1)) >= PROOF_MIN_CELLS


def output_folds(
    rest, result, harmonic_map, *, resampled=None, engine=None, progress=None, memory_budget=None
) -> str | None:
    """:func:`fold_warning` of a deformation's output: how many folds, and where, or None.

    What ``vhm-viz deform`` refuses without ``--allow-folds`` and the explorer's export
    says. A warped image's cells are judged by the corner Jacobians of its trilinear
    voxels (:func:`~vhm_viz.core.cell_kernels.inverted_hexahedra`), measured where the
    volume engine's lattice does not prove them unfolded
    (:meth:`~vhm_viz.core.volume.VolumeDeformation.unproven_cells`); other 3D cells by
    the tetrahedra they split into, taken from the output's cell arrays when the filter
    computed them; a resample's voxels in folds are the filter's count. Beside a check of
    the whole output ``det J`` is spot-checked, else sampled (:func:`fold_samples`).

    Parameters
    ----------
    rest : pyvista.DataSet
        The input (positions in the line are rest positions).
    result : pyvista.DataSet
        The deformed output (a warp: its points; a resample: unused beside ``resampled``).
    harmonic_map : HarmonicMap
    resampled : dict, optional
        A resample's voxels in folds (the resample filter's ``fold_voxels``).
    engine : VolumeDeformation, optional
        The volume engine that warped ``rest`` (its lattice's proof spares cells).
    progress : callable, optional
        ``progress(fraction)`` while a warped image's cells are measured.
    memory_budget : int, optional
        Bytes of a warped image's slabs of cells at most.
    """
    import pyvista as pv

    from vhm_viz.filters import cell_quality
    from vhm_viz.filters._vtk import image_geometry

    cells = point_det = None
    if resampled is None:
        if isinstance(rest, pv.ImageData):
            unproven = None  # the engine's lattice proves most voxel cells unfolded
            grid = image_geometry(rest)
            if (
                proof_sized(grid.dimensions)
                and engine is not None
                and engine.geometry.same_as(grid)
            ):
                unproven = engine.unproven_cells()
            cells = warped_voxel_folds(grid, result.points, progress, memory_budget, unproven)
        elif "cell_jacobian_determinant" in result.cell_data:
            det = np.asarray(result.cell_data["cell_jacobian_determinant"])
            finite = np.isfinite(det)
            summary = {"cells": int(finite.sum()), "inverted": int((det[finite] <= 0).sum())}
            cells = {"determinant": det, "summary": summary}
        else:
            cells = cell_quality(rest, result.points, condition=False)
        if cells is not None and "vhm_outside" in result.point_data:
            cells["outside"] = np.asarray(result.point_data["vhm_outside"])
        if "jacobian_determinant" in result.point_data:
            point_det = np.asarray(result.point_data["jacobian_determinant"])
            if "vhm_outside" in result.point_data:  # passthrough points are not the map's
                point_det = np.where(result.point_data["vhm_outside"] == 0, point_det, np.nan)
    whole = resampled is not None or cells is not None
    samples = FOLD_SPOT_SAMPLES if whole else fold_samples(rest.GetNumberOfPoints())
    return fold_warning(rest, harmonic_map, cells=cells, point_det=point_det, samples=samples,
                        voxels=resampled)  # fmt: skip


def load_check_kernels(data, *, cells: bool = True, voxels: bool = False, proof: bool = False):
    """Start loading the compiled kernels of ``data``'s checks, on a second thread.

    The checks after the map -- the summary's ``E_volume``
    (:func:`~vhm_viz.cli._util.surface_metrics`) and the fold check's cells
    (:func:`~vhm_viz.filters.cell_quality`, :func:`inverted_voxel_cells`) -- run compiled
    kernels that a process loads from numba's cache before their first call: a fixed cost
    that a small map cannot amortise.
    Started before the solve, which leaves a core idle, the thread calls the same numeric
    functions on a tiny input of the same types, so it loads what they will load; it
    touches no VTK object. With one thread for the kernels (``--threads 1``, one CPU) it
    does nothing. Join it before the checks (a check that finds its kernel still
    loading waits for it).

    Parameters
    ----------
    data : pyvista.DataSet
        The input.
    cells : bool
        The fold check measures the cells of an unstructured grid (not when the filter
        measured them itself: ``--arrays cells``).
    voxels : bool
        The fold check measures a warped image's voxel cells (a forward warp).
    proof : bool
        Those of them that the volume engine's lattice does not prove unfolded (a large
        image: :data:`PROOF_MIN_CELLS`).

    Returns
    -------
    threading.Thread
    """
    import threading

    import numba
    import pyvista as pv

    from vhm_viz.core.geometry import moved_tetrahedra_volume, open_edge_count
    from vhm_viz.core.metrics import cell_measures
    from vhm_viz.filters.cells import tetra_cells

    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    tet = np.array([[0, 1, 2, 3]])
    work = []
    if isinstance(data, pv.ImageData) and voxels:
        cube = np.stack(np.meshgrid([0.0, 1], [0.0, 1], [0.0, 1], indexing="ij"), -1)
        cube = cube.reshape(-1, 3)
        if proof:  # the proof, then the cells it leaves (boxes of them, or every cell)
            from vhm_viz.core.cell_kernels import inverted_hexahedra
            from vhm_viz.core.lattice import HermiteLattice

            work.append(HermiteLattice.load_proof_kernel)
            work.append(lambda: inverted_hexahedra(cube, (2, 2, 2), 1.0, [[0] * 6]))
        work.append(lambda: inverted_voxel_cells(cube, (2, 2, 2), 1.0))
    elif isinstance(data, pv.UnstructuredGrid):
        found = tetra_cells(data)
        if found is None or len(found[0]):  # 3D cells: their volumes as tets (E_volume)
            work.append(lambda: moved_tetrahedra_volume(corners, corners, tet))
        if found is None:  # other 3D cells: split into tets, reduced per cell
            if cells:
                work.append(lambda: cell_measures(corners, corners, tet, [0], 1, condition=False))
        elif len(found[0]):  # a tet mesh: a cell per tet
            if cells:
                work.append(lambda: cell_measures(corners, corners, tet, condition=False))
    elif isinstance(data, pv.PolyData):
        faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        work.append(lambda: open_edge_count(faces, 4))  # E_volume of a closed surface

    if numba.get_num_threads() < 2:  # one CPU: nothing idles; the checks load their own
        work.clear()

    def run():
        for step in work:
            try:
                step()
            except Exception:  # noqa: BLE001 - the checks themselves meet it and say so
                pass

    thread = threading.Thread(target=run, name="vhm-check-kernels", daemon=True)
    thread.start()
    return thread


def warped_voxel_folds(
    geometry, points, progress=None, memory_budget=None, unproven=None
) -> dict | None:
    """:func:`fold_warning`'s cells of a warped image: its voxels' corner Jacobians.

    ``geometry``: the image's rest grid (:class:`~vhm_viz.core.image.ImageGeometry`);
    ``points``: its warped positions in VTK's point order; ``unproven``: the only cells to
    measure (the volume engine's
    :meth:`~vhm_viz.core.volume.VolumeDeformation.unproven_cells`; default: all). None
    for a grid without cells.
    """
    dims = tuple(int(d) for d in geometry.dimensions)
    if min(dims) < 2:
        return None
    rest_det = float(np.linalg.det(geometry.index_to_world))
    cells = inverted_voxel_cells(points, dims, rest_det, progress, memory_budget, unproven)

    def centres(index):
        """Rest centres of voxel cells given by index, without extracting the cells."""
        index = np.asarray(index, dtype=np.int64)
        row, i = np.divmod(index, dims[0] - 1)
        k, j = np.divmod(row, dims[1] - 1)
        frame = geometry.index_to_world
        out = np.empty((index.size, 3))
        for c in range(3):  # column by column: no (K, 3) index array
            out[:, c] = geometry.origin[c] + frame[c, 0] * (i + 0.5)
            out[:, c] += frame[c, 1] * (j + 0.5)
            out[:, c] += frame[c, 2] * (k + 0.5)
        return out

    cells["centres"] = centres
    return cells
