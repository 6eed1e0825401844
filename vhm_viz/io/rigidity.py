"""Rigidity lines (polylines along which anchors are placed): OFF edges, TGF, VTK lines.

Which files hold them, and who reads each, is the format table's ``lines`` column
(:mod:`vhm_viz.io.registry`); any other dataset gives its line cells.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from vhm_viz.io.datasets import read_dataset
from vhm_viz.io.errors import ReadError
from vhm_viz.io.mesh_files import parse_off
from vhm_viz.io.registry import format_of

__all__ = ["read_polylines", "read_tgf", "read_rigidity_lines"]


def read_polylines(path) -> tuple[np.ndarray, np.ndarray]:
    """Read polylines stored as an OFF file with edge records.

    The format (used e.g. by the hand model's ``polylines.off``)::

        OFF
        <n_points> <n_faces> <n_edges>
        x y z                 (n_points lines)
        k i j ...             (n_faces + n_edges records; a record with k = 2 is an edge)

    Records with ``k > 2`` (polygons) are read as closed polylines: their consecutive
    vertex pairs (and last to first) become edges. ``n_faces`` and ``n_edges`` are only
    used to know how many records follow; all records are read either way.

    Parameters
    ----------
    path : str or os.PathLike
        The OFF file.

    Returns
    -------
    points, edges : (P, 3) float64, (E, 2) int64
        The polylines' points, and their segments as pairs of 0-based point indices.

    Raises
    ------
    ValueError
        Not an OFF file, truncated, or indices out of range.
    """
    pts, records, _ = parse_off(Path(path))
    edges = []
    for ids in records:
        k = len(ids)
        if k == 2:
            edges.append(ids)
        elif k > 2:
            edges.extend([ids[i], ids[(i + 1) % k]] for i in range(k))
    return pts, np.asarray(edges, dtype=np.int64).reshape(-1, 2)


def read_tgf(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a libigl ``.tgf`` skeleton: joints, then bones.

    Format: one line per joint ``index x y z [ignored...]`` (1-based index), a line ``#``,
    then one line per bone ``a b [ignored...]`` (1-based joint indices), optionally another
    ``#`` followed by point handles or cage edges (ignored).

    Parameters
    ----------
    path : str or os.PathLike
        The ``.tgf`` file.

    Returns
    -------
    joints : (J, 3) float64
        In file order.
    bones : (B, 2) int64
        0-based joint indices.

    Raises
    ------
    ReadError
        Malformed lines, no bones, or bone indices out of range.
    """
    with open(os.fspath(path), encoding="utf-8", errors="replace") as fh:
        raw = fh.read().splitlines()
    section = 0
    joints, bones = [], []
    for n, line in enumerate(raw, 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            section += 1
            if section >= 2:
                break
            continue
        vals = s.split()
        try:
            if section == 0:
                int(vals[0])  # the joint's number: an OBJ's "v x y z" is no joint
                joints.append([float(v) for v in vals[1:4]])
                if len(joints[-1]) != 3:
                    raise ValueError
            else:
                bones.append([int(vals[0]) - 1, int(vals[1]) - 1])
        except (ValueError, IndexError) as exc:
            kind = "joint" if section == 0 else "bone"
            raise ReadError(f"{path}:{n}: malformed TGF {kind} line {s[:40]!r}") from exc
    j = np.asarray(joints, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(bones, dtype=np.int64).reshape(-1, 2)
    if not b.size:
        raise ReadError(
            f"{path}: no bones: a TGF skeleton lists its joints, a line '#', then its bones "
            "(two joint numbers a line)"
        )
    if b.min() < 0 or b.max() >= len(j):
        raise ReadError(f"{path}: bone index out of range [1, {len(j)}]")
    return j, b


def read_rigidity_lines(path) -> tuple[np.ndarray, np.ndarray]:
    """Rigidity lines from any file that holds them, by suffix.

    ``.tgf`` (libigl skeleton, :func:`read_tgf`), ``.off`` (OFF polylines,
    :func:`read_polylines`), or any dataset with line cells (``.vtp``, ``.vtk``, ...).

    Returns
    -------
    points, edges : (P, 3) float64, (E, 2) int64
        As :func:`read_polylines` returns them (a skeleton's joints and bones).

    Raises
    ------
    FileNotFoundError, ReadError, ValueError
    """
    fmt = format_of(path)
    read = fmt.function("lines") if fmt is not None else None
    if read is not None:
        return read(path)
    data = read_dataset(path)
    lines = np.asarray(getattr(data, "lines", np.zeros(0, int)))
    if not len(lines):
        raise ReadError(f"{path}: no polylines in this file")
    edges, i = [], 0
    while i < len(lines):
        k = int(lines[i])
        ids = lines[i + 1 : i + 1 + k]
        edges.extend(zip(ids[:-1], ids[1:], strict=True))
        i += k + 1
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    return np.asarray(data.points, dtype=np.float64), edges
