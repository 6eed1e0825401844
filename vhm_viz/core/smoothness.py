"""The smoothness term's samples and weight (paper Section 3).

The deformer penalises the Hessian of the map at samples just inside the cage faces; its
weight ``lambda`` balances that term against the rigidity of the anchors' Jacobians.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.basis import evaluate_basis, inside_cage
from vhm_viz.core.errors import OutsideCageError, describe_indices
from vhm_viz.core.geometry import face_normals_and_areas, ray_depth
from vhm_viz.core.points import as_points

__all__ = ["SAMPLE_INSET", "default_smoothness_samples", "smoothness_rows", "smoothness_weight"]

# Barycentric coordinates of the default smoothness samples (3-point quadrature rule).
_SAMPLE_BARY = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
#: Default inward offset of the smoothness samples, as a fraction of the cage's diagonal.
SAMPLE_INSET = 1e-3


def default_smoothness_samples(vertices, faces, inset: float = SAMPLE_INSET) -> np.ndarray:
    """The default smoothness samples of a cage (3 per face, pulled inward).

    Each sample starts at a barycentric point of its face and moves inward along the face
    normal by ``inset`` times the cage's bounding-box diagonal, or by half the cage's local
    thickness there when that is less: the distance along the inward normal to the first
    other face (the far side of a thin plate, or the neighbour of a sharp convex edge). So
    every sample of a valid cage lies strictly inside it, however thin the cage gets.

    Parameters
    ----------
    vertices : (n, 3) array_like
    faces : (m, 3) array_like of int
        Outward-oriented cage.
    inset : float
        Largest inward offset along the face normal, as a fraction of the bounding-box
        diagonal (0 puts the samples on the faces).

    Returns
    -------
    (3 m, 3) float64
        Samples ``3 t + i`` belong to face ``t``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    normals, _ = face_normals_and_areas(v, f)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    on_face = np.einsum("sb,fbc->fsc", _SAMPLE_BARY, v[f]).reshape(-1, 3)
    if inset <= 0:
        return on_face
    inward = -np.repeat(normals, 3, axis=0)
    thickness = ray_depth(on_face, inward, v, f, skip_faces=np.repeat(np.arange(len(f)), 3))
    depth = np.minimum(inset * diag, 0.5 * thickness)
    return on_face + depth[:, None] * inward


def smoothness_weight(alpha, d, Jhat, Hhat, n, vertices) -> float:
    """``lambda = alpha d ||J||_inf / ||H||_inf`` (paper Section 3), free of the length unit.

    The paper's norms mix units: the rows of ``J`` hold ``grad phi`` (1/length) next to
    ``grad psi`` (dimensionless), those of ``H`` ``1/length^2`` next to ``1/length``, so the
    same shape in millimetres would get another lambda than in metres, and another result.
    They are taken here with lengths in units of the cage's bounding-box
    diagonal ``L`` -- the paper's formula for the cage scaled to a unit diagonal -- and
    lambda is scaled back by ``L``, so lambda scales with the cage and the minimiser is
    equivariant under scaling and translation.

    Parameters
    ----------
    alpha : float
    d : int
        Number of anchors.
    Jhat : (3 d, n + m) float64
        Basis gradient rows at the anchors.
    Hhat : (5 k, n + m) float64
        Basis Hessian rows at the smoothness samples.
    n : int
        Number of cage vertices (the ``phi`` columns come first).
    vertices : (n, 3) float64

    Returns
    -------
    float
        lambda, in units of length (``lambda * H z`` is dimensionless like ``J z``).
    """
    L = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    jn = (np.abs(Jhat[:, :n]).sum(axis=1) * L + np.abs(Jhat[:, n:]).sum(axis=1)).max()
    hn = (np.abs(Hhat[:, :n]).sum(axis=1) * L**2 + np.abs(Hhat[:, n:]).sum(axis=1) * L).max()
    return float(L * alpha * d * jn / hn)


def smoothness_rows(vertices, faces, samples=None, host_faces=None) -> tuple:
    """The smoothness samples and the basis Hessian rows there.

    Parameters
    ----------
    vertices : (n, 3) float64
    faces : (m, 3) int64
        Outward-oriented cage.
    samples : (k, 3) array_like, optional
        Default :func:`default_smoothness_samples`.
    host_faces : (k,) array_like of int, optional
        For samples exactly on cage faces, the face index (-1 for others).

    Returns
    -------
    samples : (k, 3) float64
    hessians : (5 k, n + m) float64
        Rows ``5 i + (xx, xy, xz, yy, yz)`` of sample ``i``.

    Raises
    ------
    OutsideCageError
        Samples outside the cage (listed).
    ValueError
        Samples on a cage edge or vertex, where the Hessian diverges.
    """
    n = len(vertices)
    if samples is None:
        w = default_smoothness_samples(vertices, faces)
        host = None
    else:
        w = as_points(samples, "smoothness_samples", allow_empty=False)
        host = host_faces
    evs = evaluate_basis(w, vertices, faces, order=2, host_faces=host)
    wn = evs.values[:, :n].sum(axis=1)
    on_face = np.zeros(len(w), bool) if host is None else np.asarray(host).ravel() >= 0
    out = ~inside_cage(wn) & ~on_face
    if out.any():
        idx = np.nonzero(out)[0]
        raise OutsideCageError(
            f"{idx.size} smoothness samples are outside the cage "
            f"(indices {describe_indices(idx)})"
            + (
                "; default samples lie halfway to the next face along the inward normal, "
                "so the cage is not a closed, embedded surface there"
                if samples is None
                else ""
            ),
            idx,
        )
    if not np.isfinite(evs.hessians).all():
        bad = np.nonzero(~np.isfinite(evs.hessians).all(axis=(1, 2)))[0]
        raise ValueError(f"smoothness samples {describe_indices(bad)} lie on a cage edge or vertex")
    hessians = evs.hessians
    del evs  # free the values and gradients before the caller's QR
    return w, np.ascontiguousarray(hessians.reshape(5 * len(w), -1))
