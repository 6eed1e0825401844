"""Public :class:`Cage`: the validated core cage plus file and PyVista input/output.

OBJ and OFF files are parsed here directly, so vertex numbering matches the file exactly
(VTK's OBJ reader can split vertices that carry several texture coordinates or normals,
and reads OFF only through meshio as an unstructured grid). PLY, STL, VTP and VTK go
through :func:`pyvista.read`. Polygons are triangulated the same way whatever the format:
a fan from the first corner when the polygon is convex, ear clipping otherwise.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from vhm_viz.core.cage import Cage as _CoreCage
from vhm_viz.core.errors import CageError

__all__ = ["Cage"]

_PV_SUFFIXES = {".ply", ".stl", ".vtp", ".vtk", ".vtu"}


# ----------------------------------------------------------------------------------------
# Polygon triangulation
# ----------------------------------------------------------------------------------------


def _newell_normal(p: np.ndarray) -> np.ndarray:
    q = np.roll(p, -1, axis=0)
    return np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )


def _triangulate_polygon(points: np.ndarray, poly: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangles of one polygon (vertex ids ``poly``), keeping its orientation."""
    k = len(poly)
    if k == 3:
        return [(int(poly[0]), int(poly[1]), int(poly[2]))]
    p = points[poly]
    normal = _newell_normal(p)
    fan = [(0, i, i + 1) for i in range(1, k - 1)]
    if all(np.dot(np.cross(p[b] - p[a], p[c] - p[a]), normal) > 0 for a, b, c in fan):
        return [(int(poly[a]), int(poly[b]), int(poly[c])) for a, b, c in fan]
    # ear clipping in the plane of the Newell normal
    nn = np.linalg.norm(normal)
    if nn == 0:
        return [(int(poly[a]), int(poly[b]), int(poly[c])) for a, b, c in fan]
    normal = normal / nn
    u = np.cross(normal, [1.0, 0.0, 0.0])
    if np.linalg.norm(u) < 0.1:
        u = np.cross(normal, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    xy = np.stack([(p - p[0]) @ u, (p - p[0]) @ w], axis=1)

    def cross2(a, b, c):
        return (xy[b, 0] - xy[a, 0]) * (xy[c, 1] - xy[a, 1]) - (xy[b, 1] - xy[a, 1]) * (
            xy[c, 0] - xy[a, 0]
        )

    remaining = list(range(k))
    tris = []
    while len(remaining) > 3:
        r = len(remaining)
        for i in range(r):
            a, b, c = remaining[i - 1], remaining[i], remaining[(i + 1) % r]
            if cross2(a, b, c) <= 0:
                continue  # reflex corner
            if any(
                cross2(a, b, d) >= 0 and cross2(b, c, d) >= 0 and cross2(c, a, d) >= 0
                for d in remaining
                if d not in (a, b, c)
            ):
                continue  # another corner inside the ear
            tris.append((a, b, c))
            remaining.pop(i)
            break
        else:  # no ear (self-overlapping polygon): give up and fan the rest
            tris.extend((remaining[0], remaining[j], remaining[j + 1]) for j in range(1, r - 1))
            remaining = remaining[:3]
            break
    if len(remaining) == 3 and len(tris) < k - 2:
        tris.append(tuple(remaining))
    return [(int(poly[a]), int(poly[b]), int(poly[c])) for a, b, c in tris]


def _triangulate(points: np.ndarray, polygons) -> np.ndarray:
    """(m, 3) int64 triangles from a sequence of polygons (index arrays of length >= 3)."""
    tris: list[tuple[int, int, int]] = []
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.int64)
        if len(poly) < 3:
            continue  # points / polyline records
        tris.extend(_triangulate_polygon(points, poly))
    return np.asarray(tris, dtype=np.int64).reshape(-1, 3)


# ----------------------------------------------------------------------------------------
# Readers
# ----------------------------------------------------------------------------------------


def _read_obj(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    verts: list[list[float]] = []
    polys: list[np.ndarray] = []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "v":
                try:
                    verts.append([float(x) for x in tok[1:4]])
                except ValueError as exc:
                    raise CageError(f"{path}:{lineno}: bad vertex line {line.strip()!r}") from exc
                if len(verts[-1]) != 3:
                    raise CageError(f"{path}:{lineno}: vertex with fewer than 3 coordinates")
            elif tok[0] == "f":
                try:
                    ids = [int(t.split("/")[0]) for t in tok[1:]]
                except ValueError as exc:
                    raise CageError(f"{path}:{lineno}: bad face line {line.strip()!r}") from exc
                nv = len(verts)
                # 1-based; negative indices count back from the latest vertex
                polys.append(np.array([i - 1 if i > 0 else nv + i for i in ids], dtype=np.int64))
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), polys


def _read_off(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    with open(path, encoding="utf-8", errors="replace") as fh:
        lines = [ln.split("#", 1)[0].split() for ln in fh]
    lines = [t for t in lines if t]
    if not lines or not lines[0][0].endswith("OFF"):
        raise CageError(f"{path}: not an OFF file (no OFF header)")
    head = lines[0][1:]
    rest = lines[1:]
    if not head:
        head, rest = rest[0], rest[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
        verts = np.array([[float(x) for x in t[:3]] for t in rest[:nv]], dtype=np.float64)
        polys = []
        for t in rest[nv : nv + nf]:
            k = int(t[0])
            polys.append(np.array([int(x) for x in t[1 : 1 + k]], dtype=np.int64))
    except (ValueError, IndexError) as exc:
        raise CageError(f"{path}: malformed OFF file: {exc}") from exc
    if len(verts) != nv or len(polys) != nf:
        raise CageError(f"{path}: OFF header announces {nv} vertices / {nf} faces, file is short")
    return verts.reshape(-1, 3), polys


def _polydata_polygons(mesh) -> tuple[np.ndarray, list[np.ndarray]]:
    """Points and polygon list of a PyVista dataset (surface cells only)."""
    import pyvista as pv

    if isinstance(mesh, pv.UnstructuredGrid):
        types = np.asarray(mesh.celltypes)
        polygonal = {int(pv.CellType.TRIANGLE), int(pv.CellType.QUAD), int(pv.CellType.POLYGON)}
        if mesh.n_cells and np.isin(types, list(polygonal)).all():
            mesh = pv.PolyData(np.asarray(mesh.points), faces=np.asarray(mesh.cells))
        else:
            mesh = mesh.extract_surface()
    elif not isinstance(mesh, pv.PolyData):
        mesh = pv.wrap(mesh)
        if not isinstance(mesh, pv.PolyData):
            mesh = mesh.extract_surface()
    if mesh.n_strips:
        mesh = mesh.triangulate()
    return np.asarray(mesh.points, dtype=np.float64), list(mesh.irregular_faces)


def _merge_exact_duplicates(points: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical points (STL stores each facet's corners separately)."""
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(first)  # keep first-occurrence order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return points[np.sort(first)], rank[inverse][tris]


# ----------------------------------------------------------------------------------------
# The public Cage
# ----------------------------------------------------------------------------------------


class Cage(_CoreCage):
    """A validated cage (closed, outward, embedded triangle mesh) with file and PyVista I/O.

    See :class:`vhm_viz.core.cage.Cage` for the properties, the checks and the
    ``CageError`` conventions.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
    faces : (m, 3) array_like of int
    check_self_intersection : bool
        Skip the self-intersection test when False.

    Examples
    --------
    >>> import vhm_viz
    >>> cage = vhm_viz.Cage.from_file("cage.obj")  # doctest: +SKIP
    >>> inside = cage.contains(points)  # doctest: +SKIP
    """

    @classmethod
    def from_file(cls, path: str | os.PathLike, **kwargs) -> Cage:
        """Read a cage from OBJ, OFF, PLY, STL, VTP or VTK (legacy) and validate it.

        Quads and polygons are triangulated (OBJ files may mix them with triangles).
        OBJ and OFF keep the file's vertex numbering; STL's per-facet corners are merged
        when bit-identical.

        Parameters
        ----------
        path : str or path-like
        **kwargs
            Passed to the constructor (``check_self_intersection``).

        Returns
        -------
        Cage

        Raises
        ------
        CageError
            If the file cannot be parsed or the mesh is not a valid cage.
        FileNotFoundError
            If ``path`` does not exist.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no such cage file: {path}")
        suffix = path.suffix.lower()
        if suffix == ".obj":
            points, polys = _read_obj(path)
            return cls(points, _triangulate(points, polys), **kwargs)
        if suffix == ".off":
            points, polys = _read_off(path)
            return cls(points, _triangulate(points, polys), **kwargs)
        if suffix in _PV_SUFFIXES:
            import pyvista as pv

            mesh = pv.read(path)
            if suffix == ".stl":
                points, polys = _polydata_polygons(mesh)
                points, tris = _merge_exact_duplicates(points, _triangulate(points, polys))
                return cls(points, tris, **kwargs)
            return cls.from_pyvista(mesh, **kwargs)
        raise CageError(
            f"unsupported cage file type {suffix!r} ({path}); use OBJ, OFF, PLY, STL, VTP or VTK"
        )

    @classmethod
    def from_pyvista(cls, mesh, **kwargs) -> Cage:
        """Build a cage from a PyVista (or VTK) surface; polygons are triangulated.

        An ``UnstructuredGrid`` of triangles/quads/polygons is used as is (point order
        kept); any other dataset contributes its extracted surface.

        Parameters
        ----------
        mesh : pyvista.DataSet or vtk.vtkDataSet
        **kwargs
            Passed to the constructor (``check_self_intersection``).

        Returns
        -------
        Cage
        """
        points, polys = _polydata_polygons(mesh)
        return cls(points, _triangulate(points, polys), **kwargs)

    def to_pyvista(self):
        """Return the cage as a triangle ``pyvista.PolyData`` (a copy; point order kept).

        Returns
        -------
        pyvista.PolyData
            With cell data ``"Normals"`` (unit outward face normals).
        """
        import pyvista as pv

        mesh = pv.PolyData.from_regular_faces(np.array(self.vertices), np.array(self.faces))
        mesh.cell_data["Normals"] = np.array(self.face_normals)
        return mesh

    def save(self, path: str | os.PathLike) -> None:
        """Write the cage to any format PyVista writes (OBJ, PLY, STL, VTP, VTK).

        Parameters
        ----------
        path : str or path-like
        """
        self.to_pyvista().save(str(path))
