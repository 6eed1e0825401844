"""Readers for rigidity lines: OFF polylines with edge records and libigl ``.tgf`` skeletons.

Both return ``(points, edges)``, ready for :func:`vhm_viz.anchors_from_polylines`.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["read_polylines", "read_tgf"]


def _data_lines(text: str):
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            yield line


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

    Returns
    -------
    points : (P, 3) float64
    edges : (E, 2) int64

    Raises
    ------
    ValueError
        Not an OFF file, truncated, or indices out of range.
    """
    with open(os.fspath(path), encoding="utf-8", errors="replace") as fh:
        lines = list(_data_lines(fh.read()))
    if not lines or not lines[0].upper().startswith("OFF"):
        raise ValueError(f"{path}: not an OFF file (missing 'OFF' header)")
    head = lines[0][3:].split()
    idx = 1
    if not head:
        if len(lines) < 2:
            raise ValueError(f"{path}: missing the counts line")
        head = lines[1].split()
        idx = 2
    try:
        n_points = int(head[0])
        n_records = int(head[1]) + (int(head[2]) if len(head) > 2 else 0)
    except (IndexError, ValueError) as exc:
        raise ValueError(f"{path}: bad counts line {' '.join(head)!r}") from exc
    if len(lines) < idx + n_points:
        raise ValueError(f"{path}: expected {n_points} points, file is truncated")
    try:
        pts = np.array([[float(v) for v in lines[idx + i].split()[:3]] for i in range(n_points)])
    except ValueError as exc:
        raise ValueError(f"{path}: bad point line") from exc
    pts = pts.reshape(-1, 3)
    edges = []
    for line in lines[idx + n_points :]:
        vals = line.split()
        k = int(vals[0])
        ids = [int(v) for v in vals[1 : 1 + k]]
        if len(ids) != k:
            raise ValueError(f"{path}: truncated record {line!r}")
        if k == 2:
            edges.append(ids)
        elif k > 2:
            edges.extend([ids[i], ids[(i + 1) % k]] for i in range(k))
    del n_records  # informational only
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if e.size and (e.min() < 0 or e.max() >= n_points):
        raise ValueError(f"{path}: edge index out of range [0, {n_points})")
    return pts, e


def read_tgf(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a libigl ``.tgf`` skeleton: joints, then bones.

    Format: one line per joint ``index x y z [ignored...]`` (1-based index), a line ``#``,
    then one line per bone ``a b [ignored...]`` (1-based joint indices), optionally another
    ``#`` followed by point handles or cage edges (ignored).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    joints : (J, 3) float64
        In file order.
    bones : (B, 2) int64
        0-based joint indices.

    Raises
    ------
    ValueError
        Malformed lines or bone indices out of range.
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
                joints.append([float(v) for v in vals[1:4]])
                if len(joints[-1]) != 3:
                    raise ValueError
            else:
                bones.append([int(vals[0]) - 1, int(vals[1]) - 1])
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{path}:{n}: malformed line {s!r}") from exc
    j = np.asarray(joints, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(bones, dtype=np.int64).reshape(-1, 2)
    if b.size and (b.min() < 0 or b.max() >= len(j)):
        raise ValueError(f"{path}: bone index out of range [1, {len(j)}]")
    return j, b
