"""Freed heap memory handed back to the operating system, and arrays changed in place.

Building a lattice or a deformer allocates and frees many mid-sized arrays (node tables,
level data, evaluation chunks). glibc serves arrays below its dynamic mmap threshold
(which grows up to 32 MiB once a large block has been freed) from the heap, and freed
heap memory stays in the process (on a large volume, a hundred MiB or more), which
would add to the peak when the output is allocated next. :func:`release_free_memory` asks the
allocator to return it (``malloc_trim``), a few milliseconds.

:func:`grow_in_place` and :func:`take_in_place` grow an array or keep some of its rows
without holding the array and its new version at once (``ndarray.resize``, a realloc:
a large mmapped block is remapped rather than copied).

:func:`volume_job_bytes` estimates, before anything is allocated, the memory a volume job
(a warp or a resample of :class:`~vhm_viz.core.volume.VolumeDeformation`) will still
take, so that a job that cannot fit is refused at once (the limits themselves are found
by :mod:`vhm_viz.resources`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

import numba
import numpy as np

__all__ = [
    "release_free_memory",
    "grow_in_place",
    "take_in_place",
    "LATTICE_BYTES_PER_VOXEL",
    "volume_job_bytes",
]

_LIBC = None


def release_free_memory() -> bool:
    """Return the heap's free pages to the operating system (glibc); elsewhere a no-op.

    Returns
    -------
    bool
        Whether memory could be handed back (glibc's ``malloc_trim`` reports it).
    """
    global _LIBC
    if not sys.platform.startswith("linux"):
        return False
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _LIBC.malloc_trim.argtypes = [ctypes.c_size_t]
        except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
            _LIBC = False
    if not _LIBC:
        return False
    return bool(_LIBC.malloc_trim(0))


def grow_in_place(holder, key, extra: int) -> np.ndarray:
    """The array ``holder[key]``, grown by ``extra`` rows (uninitialised).

    The array is taken out of ``holder`` (a dict or list; the slot is set to None) and
    grown in place if it can be: a caller's reference would make ``resize`` refuse.

    Parameters
    ----------
    holder : dict or list
        Holds the array ``(N, ...)``, its only reference; ``holder[key]`` becomes None.
    key : hashable or int
    extra : int
        Rows to add.

    Returns
    -------
    (N + extra, ...) ndarray
        The old rows first, then ``extra`` uninitialised ones.
    """
    a = holder[key]
    holder[key] = None  # the one reference left is ours: resize may run
    shape = (len(a) + extra,) + a.shape[1:]
    try:
        a.resize(shape)  # realloc: a large (mmapped) block is remapped, not copied
        return a
    except ValueError:  # referenced elsewhere (or not its own memory): copied after all
        return np.concatenate([a, np.empty((extra,) + a.shape[1:], dtype=a.dtype)])


def take_in_place(holder, key, index) -> np.ndarray:
    """``holder[key][index]`` for ascending ``index``, made in place when it can.

    The array is taken out of ``holder`` (a dict or list; the slot is set to None), its
    rows ``index`` are moved to its front and it is shrunk (realloc), so that the array
    and its selection are never held together. Where that cannot be done (not its own
    contiguous memory, referenced elsewhere, an index not ascending) the rows are copied.

    Parameters
    ----------
    holder : dict or list
        Holds the array ``(N, ...)``; ``holder[key]`` becomes None.
    key : hashable or int
    index : (M,) int array_like
        Rows to keep, ascending for the move to be in place.

    Returns
    -------
    (M, ...) ndarray
        ``holder[key][index]``: in the array's own memory where it could be moved.
    """
    a = holder[key]
    holder[key] = None  # the one reference left is ours: resize may run
    index = np.asarray(index, dtype=np.int64).ravel()
    if (
        a.ndim == 0
        or len(a) == 0
        or sys.getrefcount(a) > 2  # held elsewhere too (or viewed): not moved under it
        or not (a.flags.c_contiguous and a.flags.owndata)
        or (len(index) > 1 and not (index[1:] > index[:-1]).all())
        or (len(index) and (index[0] < 0 or index[-1] >= len(a)))
    ):
        return a[index]
    rows = a.reshape(len(a), -1).view(np.uint8)  # bytes: one compiled move for every dtype
    _move_rows_forward(rows, index)
    del rows
    try:
        a.resize((len(index),) + a.shape[1:])
        return a
    except ValueError:  # referenced elsewhere after all
        return a[: len(index)].copy()


@numba.njit(cache=True)
def _move_rows_forward(rows, index):  # pragma: no cover - compiled
    """``rows[t] = rows[index[t]]`` for ascending ``index`` (no row read after it moved).

    ``rows``: a 2-D byte view; element copies, so no broadcasting checks are compiled.
    """
    width = rows.shape[1]
    for t in range(index.shape[0]):
        if index[t] != t:
            for c in range(width):
                rows[t, c] = rows[index[t], c]


#: Bytes of lattice per input voxel a volume job is estimated to hold: nodes (exact values
#: and Jacobians, 12 float64 each, with their tables) at about one per 32 voxels near the
#: default tolerance, where the map bends most; the lattice is coarser where it does not.
LATTICE_BYTES_PER_VOXEL = 8
#: Slab working arrays per voxel: a warp slab's positions; a pull-back slab's pre-image,
#: state, fold, quality, outside flag and one sampled float64 component.
SLAB_VOXEL_BYTES = {"warp": 16, "resample": 56}
#: Bytes per voxel besides the output data: a warp's float64 positions and room for the
#: fold check's inverted cells (an index and a determinant, 16 bytes each: up to half of
#: the cells); a resample's valid and fold masks.
_EXTRA_VOXEL_BYTES = {"warp": 3 * 8 + 8, "resample": 2}
#: A pull-back slab's working arrays stay within this whatever the memory budget, since
#: each process (each MPI rank) holds them; fewer slabs mean fewer of the serial steps
#: and thread hand-overs between a slab's kernels.
PULL_BACK_SLAB_BYTES = 64 * 2**20
#: A displacement field's bytes per grid point: 3 float64 components and its masks.
FIELD_VOXEL_BYTES = 3 * 8 + 2
#: Whole copies of a field's vectors its writer makes: SimpleITK's image of the array,
#: and ITK's own copy as it writes (a NIfTI vector field is stored component by
#: component).
FIELD_WRITER_COPIES = 2


def volume_job_bytes(
    input_voxels: int,
    output_voxels: int,
    value_bytes: int,
    *,
    kind: str,
    memory_budget: int,
    writer_copies: int = 0,
    field: str | None = None,
) -> dict:
    """The memory a volume job will still allocate once its input is read (an estimate).

    Parameters
    ----------
    input_voxels : int
        Voxels of the input grid.
    output_voxels : int
        Voxels of the output: the output grid of a resample, the input's of a warp.
    value_bytes : int
        Bytes of data per voxel (all point arrays, all components).
    kind : {"warp", "resample"}
    memory_budget : int
        Working bytes per slab and per evaluation chunk (the engine's memory budget).
    writer_copies : int
        Whole copies of the output data the writer makes (a MetaImage writer: one).
    field : {"pullback", "forward"} or None
        A displacement field written beside the output: the pull-back one on the output
        grid (the resample computes it with the data), the forward one on the input grid
        (its own warp of the input: positions and vectors).

    Returns
    -------
    dict
        Bytes of ``output`` (data, positions and masks), ``lattice``, ``slab`` (working
        arrays of one slab and one evaluation chunk), ``write``, ``field`` (its vectors,
        masks and the writer's copies; 0 without one) and their ``total``.
    """
    if kind not in SLAB_VOXEL_BYTES:
        raise ValueError(f"kind must be 'warp' or 'resample'; got {kind!r}")
    input_voxels, output_voxels = int(input_voxels), int(output_voxels)
    data = output_voxels * int(value_bytes)
    slab = min(int(memory_budget), PULL_BACK_SLAB_BYTES) if kind == "resample" else memory_budget
    parts = {
        "output": data + output_voxels * _EXTRA_VOXEL_BYTES[kind],
        "lattice": input_voxels * LATTICE_BYTES_PER_VOXEL,
        # a slab's working arrays, and a chunk of exact evaluations building the lattice
        "slab": int(slab) + int(memory_budget),
        "write": data * int(writer_copies),
        "field": 0,
    }
    if field is not None:
        if field not in ("pullback", "forward"):
            raise ValueError(f"field must be 'pullback' or 'forward'; got {field!r}")
        points = output_voxels if field == "pullback" else input_voxels
        vectors = points * 3 * 8
        warp = points * _EXTRA_VOXEL_BYTES["warp"] if field == "forward" else 0
        parts["field"] = points * FIELD_VOXEL_BYTES + warp + vectors * FIELD_WRITER_COPIES
    parts["total"] = sum(parts.values())
    return parts


#: Whole (3d, 3d) float64 matrices a solver of d anchors holds at once: ``C_R`` (see
#: :func:`vhm_viz.core.constraints.factor_constraints`) and, while a new constraint layout
#: is factorised, its successor.
SOLVER_SQUARE_COPIES = 2
#: (3d, N) float64 matrices beside them, N the cage's coefficients: the anchors' basis
#: Jacobians, the least-squares factor's anchor block, and B's anchor columns with the
#: working copies the factorisation makes of them.
SOLVER_TALL_COPIES = 6


def solver_bytes(anchors: int, coefficients: int) -> int:
    """The memory a :class:`~vhm_viz.core.deformer.Deformer` of ``anchors`` will allocate.

    The local/global solver's factorisation is dense in the anchors' local matrices: its
    largest arrays are (3d, 3d) and (3d, N) float64, so it grows with the square of the
    anchor count ``d`` (an estimate, for refusing before allocating).

    Parameters
    ----------
    anchors : int
        Anchor count ``d``.
    coefficients : int
        The cage's basis functions ``N`` (vertices plus faces).

    Returns
    -------
    int
        Bytes.
    """
    rows = 3 * int(anchors)
    return 8 * rows * (SOLVER_SQUARE_COPIES * rows + SOLVER_TALL_COPIES * int(coefficients))


#: (5k, N) float64 matrices of the smoothness term held at once, k its samples: the basis
#: Hessians and the least-squares matrix they are copied into (the values and gradients
#: evaluated beside the Hessians take about as much, earlier).
SMOOTHNESS_ROW_COPIES = 2


def smoothness_bytes(samples: int, coefficients: int) -> int:
    """Bytes the smoothness term of a :class:`~vhm_viz.core.deformer.Deformer` takes.

    Its rows are the basis Hessians at ``samples`` points (three per cage face by
    default), each ``coefficients`` long (the cage's vertices plus faces): it grows with
    the square of the cage's size.
    """
    return 8 * 5 * int(samples) * int(coefficients) * SMOOTHNESS_ROW_COPIES
