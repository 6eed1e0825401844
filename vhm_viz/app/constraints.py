"""Per-constraint views of a :class:`~vhm_viz.scene.Scene`'s constraint arrays.

The scene's arrays (``positions``/``targets`` (r, 3), ``jacobian_points`` (s, 3),
``jacobians`` (s, 3, 3)) are the explorer's only constraint model. The UI reads and edits one
constraint at a time through the views here; a Jacobian target is shown as the closest
similarity ``scale * R(angles)`` to its matrix (:func:`similarity_of`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from vhm_viz.scene_fields import check_scene_values

__all__ = [
    "PositionConstraint",
    "JacobianConstraint",
    "similarity_of",
    "similarity_matrix",
    "closest_rotation",
    "Similarity",
]


def closest_rotation(matrix) -> np.ndarray:
    """(3, 3) rotation closest to ``matrix`` (polar decomposition, det +1)."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=float))
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def similarity_of(matrix) -> tuple[np.ndarray, float]:
    """Closest similarity ``scale * R(angles)`` to a (3, 3) Jacobian.

    Returns
    -------
    angles : (3,) ndarray
        Extrinsic x, y, z rotation angles in degrees (scipy's ``"xyz"`` Euler convention).
    scale : float
        Mean singular value.
    """
    m = np.asarray(matrix, dtype=float)
    scale = float(np.mean(np.linalg.svd(m, compute_uv=False)))
    with warnings.catch_warnings():  # gimbal lock: the angles still reproduce the rotation
        warnings.simplefilter("ignore", UserWarning)
        angles = Rotation.from_matrix(closest_rotation(m)).as_euler("xyz", degrees=True)
    return np.asarray(angles, dtype=float), scale


def similarity_matrix(angles, scale: float) -> np.ndarray:
    """(3, 3) ``scale * R(angles)``; ``angles`` in degrees (``"xyz"`` extrinsic)."""
    r = Rotation.from_euler("xyz", np.asarray(angles, float).reshape(3), degrees=True)
    return float(scale) * r.as_matrix()


class _ConstraintView:
    """Row ``index`` of a controller's scene constraint arrays; ``_POINTS`` names its points."""

    _POINTS = ""

    def __init__(self, controller, index: int):
        self._controller = controller
        self.index = int(index)

    def _row(self, name: str) -> np.ndarray:
        return self._controller.scene.constraints[name][self.index]

    @property
    def point(self) -> np.ndarray:
        """(3,) rest-space point."""
        return self._row(self._POINTS)


class PositionConstraint(_ConstraintView):
    """Position constraint ``index`` of a controller's scene: ``f(point) = target``.

    ``point`` (3,) is in rest space, ``target`` (3,) in deformed space; both are read from
    the scene each time (edits go through the controller).
    """

    _POINTS = "positions"

    @property
    def target(self) -> np.ndarray:
        """(3,) deformed-space target."""
        return self._row("targets")


class JacobianConstraint(_ConstraintView):
    """Jacobian constraint ``index`` of a controller's scene: ``J_f(point) = matrix``.

    ``angles`` (degrees) and ``scale`` describe the closest similarity to ``matrix``;
    setting either rewrites the scene's matrix as ``scale * R(angles)``.
    """

    _POINTS = "jacobian_points"

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) target Jacobian ``J[i, j] = d f_i / d x_j``."""
        return self._row("jacobians")

    @property
    def angles(self) -> np.ndarray:
        """(3,) rotation angles in degrees of the closest similarity."""
        return similarity_of(self.matrix)[0]

    @angles.setter
    def angles(self, value) -> None:
        self._controller.set_jacobian(self.index, angles=value)

    @property
    def scale(self) -> float:
        """Scale factor of the closest similarity."""
        return similarity_of(self.matrix)[1]

    @scale.setter
    def scale(self, value: float) -> None:
        self._controller.set_jacobian(self.index, scale=value)

    @staticmethod
    def from_matrix(point, matrix) -> Similarity:
        """The closest similarity to ``matrix`` at ``point`` (not part of any scene)."""
        angles, scale = similarity_of(matrix)
        return Similarity(np.asarray(point, float).copy(), angles, scale)


@dataclass
class Similarity:
    """A Jacobian target ``scale * R(angles)`` at a rest-space ``point`` (3,)."""

    point: np.ndarray
    angles: np.ndarray
    scale: float

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) ``scale * R(angles)``."""
        return similarity_matrix(self.angles, self.scale)


# ----------------------------------------------------------------------------------------
# edits of a scene's constraint arrays: each returns a new dict, the arrays are never
# changed in place (undo snapshots and the deformer may hold them); a value a scene file
# could not hold is refused (:func:`vhm_viz.scene_fields.check_scene_values`)
# ----------------------------------------------------------------------------------------

#: The two arrays of each kind of constraint: rest-space points, and targets.
ARRAYS = {"position": ("positions", "targets"), "jacobian": ("jacobian_points", "jacobians")}


def _shaped(name: str, value) -> np.ndarray:
    shape = (-1, 3, 3) if name == "jacobians" else (-1, 3)
    return np.array(value, dtype=np.float64).reshape(shape)


def replaced(constraints: dict, **arrays) -> dict:
    """``constraints`` with some arrays replaced (copied as float64).

    Raises
    ------
    SceneError
        A value that is not finite or beyond a scene's range, named as in a scene file
        (``constraints.targets[0][0]``); ``constraints`` is left as it was.
    """
    out = dict(constraints)
    for name, value in arrays.items():
        out[name] = check_scene_values(_shaped(name, value), f"constraints.{name}")
    return out


def appended(constraints: dict, kind: str, point, target) -> dict:
    """One more constraint of ``kind`` (``"position"``: target (3,); ``"jacobian"``: (3, 3))."""
    points, targets = ARRAYS[kind]
    return replaced(
        constraints,
        **{
            points: np.vstack([constraints[points], _shaped(points, point)]),
            targets: np.concatenate([constraints[targets], _shaped(targets, target)]),
        },
    )


def removed(constraints: dict, kind: str, index: int) -> dict:
    """Without constraint ``index`` of ``kind``.

    Raises
    ------
    IndexError
        No such constraint.
    """
    names = ARRAYS[kind]
    n = len(constraints[names[0]])
    if not 0 <= index < n:
        raise IndexError(f"{kind} constraint {index} does not exist ({n})")
    return replaced(constraints, **{k: np.delete(constraints[k], index, axis=0) for k in names})


def kept(constraints: dict, kind: str, keep: np.ndarray) -> dict:
    """Only the constraints of ``kind`` where the boolean mask ``keep`` is true."""
    return replaced(constraints, **{k: constraints[k][keep] for k in ARRAYS[kind]})


def with_row(constraints: dict, name: str, index: int, value) -> dict:
    """Row ``index`` of array ``name`` set to ``value``."""
    array = constraints[name].copy()
    array[index] = value
    return replaced(constraints, **{name: array})
