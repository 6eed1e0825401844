"""Small triangle-mesh geometry helpers shared by the cage, basis and metrics."""

from __future__ import annotations

import numpy as np


def face_normals_and_areas(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals and areas of triangles.

    Parameters
    ----------
    vertices : (n, 3) float array
        Vertex positions.
    faces : (m, 3) int array
        Triangles, counter-clockwise about the normal returned.

    Returns
    -------
    normals : (m, 3) float64
        Unit normals ``(x1 - x0) x (x2 - x0)`` normalised; zero rows for degenerate faces.
    areas : (m,) float64
        Triangle areas (same length unit squared as ``vertices``).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    twice_area = np.linalg.norm(cross, axis=1)
    normals = np.zeros_like(cross)
    nz = twice_area > 0
    normals[nz] = cross[nz] / twice_area[nz, None]
    return normals, 0.5 * twice_area


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by a closed triangle mesh (positive for outward orientation).

    Parameters
    ----------
    vertices : (n, 3) float array
    faces : (m, 3) int array

    Returns
    -------
    float
        Volume in length units cubed, by the divergence theorem.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
