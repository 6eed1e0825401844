"""Displacement fields of a volume's deformation, as other imaging tools apply them.

A displacement field holds one world vector per grid point, so a tool that is given the
deformation (SimpleITK/ITK, ANTs, 3D Slicer) can apply it without the harmonic map:

* the **pull-back** field on an output grid, ``u(y) = f^-1(y) - y``: what ITK's
  ``DisplacementFieldTransform`` and ``antsApplyTransforms`` read when they resample a
  moving image onto a fixed grid (``T(y) = y + u(y)`` is sampled in the input). It comes
  from the pre-images that resampling finds
  (:meth:`~vhm_viz.core.volume.VolumeDeformation.resample`), so applying it reproduces
  vhm_viz's resampled image;
* the **forward** field on the input grid, ``u(x) = f(x) - x``: for moving points and
  meshes (a point ``x`` goes to ``x + u(x)``).

Vectors are in vhm_viz's world frame (ITK's physical LPS frame, the frame of the
grid's origin and direction), in world units (millimetres for scans). Points where the
field is not the map's -- an output point with no pre-image, an input voxel with no
image -- get the zero vector (ITK's identity) and 0 in :attr:`DisplacementField.valid`;
points in a fold are flagged in :attr:`DisplacementField.foldover`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vhm_viz.core.image import ImageGeometry

__all__ = ["FIELD_KINDS", "DisplacementField", "check_field_kind", "subtract_grid_points"]

#: The kinds of field: ``"pullback"`` (``f^-1(y) - y`` on an output grid) and
#: ``"forward"`` (``f(x) - x`` on the input grid).
FIELD_KINDS = ("pullback", "forward")


@dataclass
class DisplacementField:
    """One world vector per point of a regular grid, and where it is the map's.

    Attributes
    ----------
    geometry : ImageGeometry
        The grid (origin, spacing, dimensions, direction; world frame, LPS for scans).
    vectors : (P, 3) float64
        The displacement of each grid point (VTK order, i fastest), world units: the
        pull-back ``f^-1(y) - y`` or the forward ``f(x) - x``; 0 where ``valid`` is 0.
    valid : (P,) uint8
        1 where the point has a pre-image (pull-back; ``vtkValidPointMask`` of the
        resample) or an image (forward).
    foldover : (P,) uint8
        Pull-back: 1 where the point has several pre-images more than a voxel apart
        (``vhm_foldover`` of the resample; the vector is one of them). Forward: 1 where
        ``det J <= 0``.
    kind : {"pullback", "forward"}
    counts : dict
        ``points``, ``valid``, ``foldover``.
    """

    geometry: ImageGeometry
    vectors: np.ndarray
    valid: np.ndarray
    foldover: np.ndarray
    kind: str = "pullback"

    @property
    def counts(self) -> dict:
        """``points``, ``valid`` and ``foldover`` counts."""
        return {
            "points": len(self.valid),
            "valid": int(np.count_nonzero(self.valid)),
            "foldover": int(np.count_nonzero(self.foldover)),
        }

    @property
    def mask(self) -> np.ndarray:
        """(P,) uint8 labels: 0 no pre-image (no image), 1 the map's, 2 the map's in a fold."""
        valid = self.valid.astype(bool)
        return np.where(valid, np.where(self.foldover.astype(bool), 2, 1), 0).astype(np.uint8)

    @classmethod
    def forward(cls, geometry: ImageGeometry, displacement, determinant=None, *,
                copy: bool = True) -> DisplacementField:  # fmt: skip
        """The forward field from every grid point's displacement and Jacobian determinant.

        Parameters
        ----------
        geometry : ImageGeometry
            The input grid.
        displacement : (P, 3) array_like
            ``f(x) - x`` (NaN where a voxel has no image: the ``"nan"`` outside policy).
        determinant : (P,) array_like, optional
            ``det J`` at each voxel; ``<= 0`` flags a fold.
        copy : bool
            False: a float64 ``displacement`` becomes :attr:`vectors` (changed in place).
        """
        vectors = np.array(displacement, dtype=np.float64, copy=copy or None).reshape(-1, 3)
        valid = np.isfinite(vectors).all(axis=1)
        vectors[~valid] = 0.0
        fold = np.zeros(len(vectors), dtype=bool)
        if determinant is not None:
            fold = valid & (np.asarray(determinant, dtype=np.float64).ravel() <= 0)
        return cls(geometry, vectors, valid.astype(np.uint8), fold.astype(np.uint8), "forward")


def check_field_kind(kind: str) -> str:
    """``kind`` if it is one of :data:`FIELD_KINDS`; else a ValueError naming them."""
    if kind not in FIELD_KINDS:
        raise ValueError(f"field kind must be one of {', '.join(FIELD_KINDS)}; got {kind!r}")
    return kind


def subtract_grid_points(vectors, geometry: ImageGeometry, box) -> None:
    """Subtract the world positions of a box's grid points from ``vectors``, in place.

    Parameters
    ----------
    vectors : (P, 3) float64
        One row per voxel of ``box`` (VTK order); C-contiguous.
    geometry : ImageGeometry
    box : (6,) int
        ``(i0, i1, j0, j1, k0, k1)`` inclusive.

    Notes
    -----
    Point ``(i, j, k)`` is ``origin + i c_0 + j c_1 + k c_2`` with ``c`` the columns of
    :attr:`ImageGeometry.index_to_world`: three broadcast subtractions, no (P, 3)
    temporary.
    """
    b = np.asarray(box, dtype=np.int64)
    nx, ny, nz = (int(n) for n in b[1::2] - b[0::2] + 1)
    grid = vectors.reshape(nz, ny, nx, 3)
    m = geometry.index_to_world
    grid -= geometry.origin
    grid -= np.arange(b[0], b[1] + 1, dtype=np.float64)[:, None] * m[:, 0]
    grid -= (np.arange(b[2], b[3] + 1, dtype=np.float64)[:, None] * m[:, 1])[:, None, :]
    grid -= (np.arange(b[4], b[5] + 1, dtype=np.float64)[:, None] * m[:, 2])[:, None, None, :]
