"""The validated cage: a closed, consistently outward-oriented, embedded triangle mesh.

Pure numpy/scipy. :class:`Cage` checks its input once, at construction, and stores
read-only arrays, so a cage can be shared and cached safely. The public
``vhm_viz.Cage`` subclasses it to add file and PyVista I/O.

The checks, their order and the ``CageError.indices`` conventions are those of
:mod:`vhm_viz.core.cage_validation`; slivers and their repair live in
:mod:`vhm_viz.core.slivers`, the self-intersection test in
:mod:`vhm_viz.core.self_intersection`. This module re-exports their public names, so
``from vhm_viz.core.cage import Cage, MIN_FACE_ANGLE, validate_cage`` keeps working.

A closed, consistent cage whose signed volume is negative (normals pointing inward) is
not an error: its faces are flipped and a :class:`UserWarning` says so. Unreferenced
vertices are kept, with a warning.
"""

from __future__ import annotations

from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from vhm_viz.core.cage_validation import (
    AREA_RTOL,
    DIST_RTOL,
    as_cage_arrays,
    edge_table,
    validate_cage,
)
from vhm_viz.core.errors import CageError
from vhm_viz.core.geometry import face_normals_and_areas, signed_volume
from vhm_viz.core.inside import classify_inside, winding_number
from vhm_viz.core.self_intersection import self_intersections
from vhm_viz.core.slivers import MIN_FACE_ANGLE, SliverError, face_angles, repair_slivers

if TYPE_CHECKING:
    import scipy.sparse

__all__ = [
    "AREA_RTOL",
    "DIST_RTOL",
    "MIN_FACE_ANGLE",
    "Cage",
    "SliverError",
    "face_angles",
    "repair_slivers",
    "self_intersections",
    "validate_cage",
]


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.flags.writeable = False
    return a


class Cage:
    """A closed, consistently outward-oriented, non-self-intersecting triangle mesh.

    Construction validates the input (see :func:`validate_cage` and the module
    docstring for the checks and the ``CageError.indices`` conventions). An inward
    cage is flipped with a :class:`UserWarning`; unreferenced vertices are kept with a
    warning. All array attributes are read-only.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
        Cage vertex positions.
    faces : (m, 3) array_like of int
        Triangles (0-based vertex indices).
    check_self_intersection : bool
        Skip the self-intersection test when False (only for input known to be embedded).
    min_angle : float
        Faces whose smallest angle is below this many degrees are slivers (default
        :data:`MIN_FACE_ANGLE`; 0 accepts any face, see :attr:`thin_faces`).
    repair : bool
        Repair slivers by edge flips and collapses that move no part of the surface inward
        (:func:`repair_slivers`; each step is listed in :attr:`repairs`, and a collapse
        removes a vertex, so vertex numbers then differ from the input's). When False, or
        when no such repair exists, a sliver is a :class:`SliverError` naming the face.

    Raises
    ------
    CageError
        If the mesh cannot be a cage; the message names the problem and the indices.
    """

    def __init__(
        self,
        vertices,
        faces,
        *,
        check_self_intersection: bool = True,
        min_angle: float = MIN_FACE_ANGLE,
        repair: bool = True,
    ):
        self._repairs: tuple[str, ...] = ()
        self._min_angle = float(min_angle)
        checks = {"check_self_intersection": check_self_intersection, "min_angle": min_angle}
        try:
            v, f, flipped = validate_cage(vertices, faces, stacklevel=3, **checks)
        except SliverError as exc:
            if not repair:
                raise
            v0, f0 = as_cage_arrays(vertices, faces)
            v1, f1, notes = repair_slivers(v0, f0, min_angle, error=exc)
            try:
                v, f, flipped = validate_cage(v1, f1, stacklevel=3, **checks)
            except CageError:  # the repair broke the cage: the slivers are the problem
                raise exc from None
            self._repairs = tuple(notes)
        self._vertices = _readonly(v)
        self._faces = _readonly(f)
        self._flipped = flipped
        normals, areas = face_normals_and_areas(v, f)
        self._normals = _readonly(normals)
        self._areas = _readonly(areas)
        self._bounds = _readonly(np.stack([v.min(axis=0), v.max(axis=0)]))

    # --- basic data
    @property
    def vertices(self) -> np.ndarray:
        """(n, 3) float64, read-only: vertex positions."""
        return self._vertices

    @property
    def faces(self) -> np.ndarray:
        """(m, 3) int64, read-only: triangles, counter-clockwise about the outward normal."""
        return self._faces

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``."""
        return len(self._vertices)

    @property
    def n_faces(self) -> int:
        """Number of faces ``m``."""
        return len(self._faces)

    @property
    def flipped(self) -> bool:
        """Whether the input was oriented inward and its faces were flipped."""
        return self._flipped

    @property
    def repairs(self) -> tuple[str, ...]:
        """What was done to repair slivers (empty when the input had none)."""
        return self._repairs

    @property
    def min_angle(self) -> float:
        """The smallest face angle (degrees) this cage was checked against."""
        return self._min_angle

    @cached_property
    def thin_faces(self) -> np.ndarray:
        """Faces whose smallest angle is below :data:`MIN_FACE_ANGLE` (read-only).

        Empty unless the cage was made with a smaller ``min_angle`` (automatic cages are):
        such faces make the smoothness weight collapse, and the command line says so.
        """
        return _readonly(
            np.flatnonzero(face_angles(self._vertices, self._faces).min(1) < MIN_FACE_ANGLE)
        )

    @property
    def face_normals(self) -> np.ndarray:
        """(m, 3) float64, read-only: unit outward normals ``N_t``."""
        return self._normals

    normals = face_normals

    @property
    def areas(self) -> np.ndarray:
        """(m,) float64, read-only: face areas ``A_t``."""
        return self._areas

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64, read-only: ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``."""
        return self._bounds

    @property
    def diagonal(self) -> float:
        """Length of the bounding-box diagonal."""
        return float(np.linalg.norm(self._bounds[1] - self._bounds[0]))

    @property
    def volume(self) -> float:
        """Enclosed volume (positive: the cage is outward oriented)."""
        return signed_volume(self._vertices, self._faces)

    @cached_property
    def face_centroids(self) -> np.ndarray:
        """(m, 3) float64, read-only: face centroids."""
        return _readonly(self._vertices[self._faces].mean(axis=1))

    @cached_property
    def edges(self) -> np.ndarray:
        """(3m/2, 2) int64, read-only: undirected edges ``(i, j)``, ``i < j``, sorted."""
        _, _, edges, _, _ = edge_table(self._faces)
        return _readonly(edges)

    @cached_property
    def vertex_faces(self) -> scipy.sparse.csr_matrix:
        """Vertex-face incidence, a read-only ``scipy.sparse.csr_matrix`` of shape (n, m).

        Entry ``(v, t)`` is 1 when face ``t`` uses vertex ``v``. The faces around vertex
        ``v`` are ``vertex_faces.indices[vertex_faces.indptr[v]:vertex_faces.indptr[v+1]]``
        (sorted ascending); ``vertex_faces @ x`` sums a per-face quantity onto vertices.
        """
        import scipy.sparse as sp  # here: importing it is slow, most commands skip it

        m = self.n_faces
        mat = sp.csr_matrix(
            (
                np.ones(3 * m, dtype=np.int8),
                (self._faces.ravel(), np.repeat(np.arange(m), 3)),
            ),
            shape=(self.n_vertices, m),
        )
        mat.sum_duplicates()
        mat.sort_indices()
        for a in (mat.data, mat.indices, mat.indptr):
            a.flags.writeable = False
        return mat

    def faces_of_vertex(self, v: int) -> np.ndarray:
        """Return the indices of the faces using vertex ``v`` (ascending)."""
        vf = self.vertex_faces
        return vf.indices[vf.indptr[v] : vf.indptr[v + 1]]

    # --- point classification
    def winding_number(self, points) -> np.ndarray:
        """Generalized winding number ``sum_v phi_v(p)``: 1 inside, 0 outside, 1/2 on faces.

        Parameters
        ----------
        points : (k, 3) array_like of float

        Returns
        -------
        (k,) float64
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.asarray(winding_number(p, self._vertices, self._faces), dtype=np.float64)

    def contains(self, points) -> np.ndarray:
        """Whether points lie inside the cage or on its surface.

        The one inside test (:func:`~vhm_viz.core.basis.classify_inside`): winding number
        at least 1/2, or within rounding of the surface (points computed on a face land a
        few ulps to either side of it).

        Parameters
        ----------
        points : (k, 3) or (3,) array_like of float

        Returns
        -------
        (k,) bool array
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return classify_inside(p, self._vertices, self._faces)[0]

    # --- misc
    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(n_vertices={self.n_vertices}, n_faces={self.n_faces}, "
            f"diagonal={self.diagonal:.4g})"
        )

    def __eq__(self, other) -> bool:
        """Compare vertices and faces exactly."""
        if not isinstance(other, Cage):
            return NotImplemented
        return np.array_equal(self._vertices, other._vertices) and np.array_equal(
            self._faces, other._faces
        )

    def __hash__(self) -> int:
        """Hash of the (immutable) vertex and face arrays, so cages can key caches."""
        return hash((self._vertices.tobytes(), self._faces.tobytes()))
