"""Bundled scenarios, generated in code (no data files): the paper's bar (Figures 4, 8, 9).

``bar(kind)`` builds the 1 x 1 x 5 bar (square cross-section, along +z from z = 0, about
33,000 surface vertices), its 1.3 x 1.3 x 5.4 box cage (208 triangles), 6 anchors on the
centre line, the constraints of the chosen deformation and a ready :class:`~vhm_viz.Deformer`:

* ``"bend-u"``: the bottom end held (position constraints at the bottom cap's centre and its
  4 corners inset by 0.1, Jacobian = identity at the bottom centre); the top centre moved to
  ``(3.18, 0, 0)`` (a half circle of the bar's length) with Jacobian = rotation of 180
  degrees about y -- an upside-down U.
* ``"bend-90"``: same bottom; top centre to ``(3.18, 0, 3.18)`` with a 90 degree rotation
  about y.
* ``"twist"``: same bottom; top centre fixed, Jacobian = rotation of 180 degrees about z.
* ``"bulge"``: ``"bend-90"`` plus a Jacobian constraint ``1.3 x`` (rotation of 45 degrees
  about y) at the bar's middle (the paper's muscle bulge, Figure 3).
* ``"push"`` (not one of :data:`BAR_KINDS`: a scenario that folds): same bottom; the top
  centre pushed straight down to ``(0, 0, top_height)``, kept upright (Jacobian = identity).
  A harmonic map cannot shorten the bar that much without folding next to the top face:
  measured minimum of ``det J`` over the bar's solid, 0.13 at ``top_height`` 4.0, 0.014 at
  3.666, -0.01 at 3.582 (between the vertices of :func:`bar_tets`: none of its tets
  inverts), -0.13 at 2.5 (a clear fold). :mod:`vhm_viz.core.certify` is tested on these.

A 180 degree twist started from the identity sits on a symmetric saddle of the energy, so
:meth:`BarScenario.solve` ramps the Jacobian targets of ``"twist"`` (and, harmlessly, of the
other kinds when ``steps > 1``) over several warm-started solves.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vhm_viz.core.anchors import anchors_from_polylines
from vhm_viz.core.cage import Cage
from vhm_viz.scene import Scene

__all__ = [
    "bar",
    "bar_surface",
    "bar_tets",
    "bar_cage",
    "BarScenario",
    "BAR_KINDS",
    "FOLD_KINDS",
    "rotation",
    "data_dir",
    "DataNotFound",
    "DATA_ENV",
]

BAR_KINDS = ("bend-u", "bend-90", "twist", "bulge")
#: Scenarios made to fold (see ``"push"`` above); not drawn in the paper's figures.
FOLD_KINDS = ("push",)
BAR_LENGTH = 5.0
BAR_WIDTH = 1.0
# top-centre target of the bends: a half circle of the bar's length has diameter 2L/pi
_BEND_REACH = 3.18


#: Environment variable naming the folder of the real models and volumes (``shared/data``).
DATA_ENV = "VHM_VIZ_DATA"


class DataNotFound(FileNotFoundError):
    """The folder of the real models is not where :func:`data_dir` looked (message: where)."""


def _data_candidates(cwd=None) -> list[Path]:
    """Where ``shared/data`` may be, in order.

    The repository's sibling, then the sibling of the current folder and of each of its
    parents (``../shared/data`` seen from any of them).
    """
    cwd = Path.cwd() if cwd is None else Path(cwd)
    repo = Path(__file__).resolve().parents[1]  # the checkout (or site-packages) holding us
    out: list[Path] = []
    for base in (repo, cwd, *cwd.parents):
        path = base.parent / "shared" / "data"
        if path not in out:
            out.append(path)
    return out


def data_dir(cwd=None) -> Path:
    """The folder of the real models and volumes (the repository's ``../shared/data``).

    Found from any working folder: ``$VHM_VIZ_DATA`` when set (then only there); else
    ``shared/data`` beside the repository that holds this package; else ``../shared/data``
    seen from the current folder or any of its parents.

    Parameters
    ----------
    cwd : path-like, optional
        The folder to search from instead of the current one.

    Returns
    -------
    pathlib.Path
        An existing folder (absolute).

    Raises
    ------
    DataNotFound
        With one line naming every place looked at and how to say where the data is.
    """
    env = os.environ.get(DATA_ENV)
    if env:
        path = Path(env).expanduser().resolve()
        if path.is_dir():
            return path
        raise DataNotFound(
            f"the data folder {DATA_ENV}={env} does not exist (or is not a folder); "
            f"point {DATA_ENV} at the folder holding volumes/, hand_tet/, armadillo/, ..."
        )
    candidates = _data_candidates(cwd)
    for path in candidates:
        if path.is_dir():
            return path.resolve()
    raise DataNotFound(
        "the data folder shared/data was not found; looked in "
        + ", ".join(str(p) for p in candidates)
        + f"; set {DATA_ENV} to the folder holding volumes/, hand_tet/, armadillo/, ..."
    )


def rotation(axis: str, degrees: float) -> np.ndarray:
    """3x3 rotation matrix about a coordinate axis (``"x"``, ``"y"`` or ``"z"``)."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    if axis == "z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    raise ValueError(f"axis must be 'x', 'y' or 'z'; got {axis!r}")


def _box_surface(lo, hi, divisions) -> tuple[np.ndarray, np.ndarray]:
    """Watertight, outward-oriented triangulation of a box's surface on a structured grid.

    ``divisions`` = cells along x, y, z. Vertices are shared between faces (one per surface
    grid node); each grid cell is split into two triangles.
    """
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    nx, ny, nz = (int(v) for v in divisions)
    shape = (nx + 1, ny + 1, nz + 1)
    ids = -np.ones(shape, dtype=np.int64)
    ii, jj, kk = np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij")
    surf = (ii == 0) | (ii == nx) | (jj == 0) | (jj == ny) | (kk == 0) | (kk == nz)
    ids[surf] = np.arange(np.count_nonzero(surf))
    coords = [np.linspace(lo[a], hi[a], shape[a]) for a in range(3)]
    pts = np.column_stack([coords[0][ii[surf]], coords[1][jj[surf]], coords[2][kk[surf]]])
    tris = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for side in (0, shape[axis] - 1):
            sl = [slice(None)] * 3
            sl[axis] = side
            grid = ids[tuple(sl)]  # 2D array indexed (u, v)
            a = grid[:-1, :-1].ravel()
            b = grid[1:, :-1].ravel()
            c = grid[1:, 1:].ravel()
            d = grid[:-1, 1:].ravel()
            t = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
            # orientation: (u, v, axis) cyclic => (b - a) x (d - a) points along +axis
            positive = (u, v, axis) in ((0, 1, 2), (1, 2, 0), (2, 0, 1))
            outward_plus = side != 0
            if positive != outward_plus:
                t = t[:, ::-1]
            tris.append(t)
    return pts, np.concatenate(tris)


def bar_surface(resolution: int = 39) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated surface of the 1 x 1 x 5 bar (x, y in [-0.5, 0.5], z in [0, 5]).

    Parameters
    ----------
    resolution : int
        Grid cells per unit length; 39 gives 33,464 vertices and 66,924 triangles (the
        paper's bar has 32,908 vertices).

    Returns
    -------
    points : (N, 3) float64
    triangles : (M, 3) int64
        Outward oriented, watertight, vertices shared.
    """
    r = int(resolution)
    h = BAR_WIDTH / 2
    return _box_surface((-h, -h, 0.0), (h, h, BAR_LENGTH), (r, r, round(r * BAR_LENGTH)))


def bar_tets(resolution: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral mesh of the 1 x 1 x 5 bar's solid, on a structured grid.

    Each grid cube is split into six tetrahedra around its main diagonal (Kuhn's
    subdivision, conforming between neighbouring cubes), all positively oriented.

    Parameters
    ----------
    resolution : int
        Grid cells per unit length (10: 30,000 tetrahedra, 6,171 vertices).

    Returns
    -------
    points : (N, 3) float64
    tets : (T, 4) int64
        Positive volume (``det [x1 - x0, x2 - x0, x3 - x0] > 0``).
    """
    r = int(resolution)
    if r < 1:
        raise ValueError(f"resolution must be at least 1; got {resolution}")
    h = BAR_WIDTH / 2
    dims = (r + 1, r + 1, round(r * BAR_LENGTH) + 1)
    axes = [
        np.linspace(-h, h, dims[0]),
        np.linspace(-h, h, dims[1]),
        np.linspace(0, BAR_LENGTH, dims[2]),
    ]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    ids = np.arange(points.shape[0]).reshape(dims)
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(d - 1) for d in dims), indexing="ij"))
    corner = {(a, b, c): ids[i + a, j + b, k + c] for a in (0, 1) for b in (0, 1) for c in (0, 1)}
    tets = []
    # the six monotone paths from corner (0,0,0) to (1,1,1), one tetrahedron each
    for order in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        path = [(0, 0, 0)]
        for axis in order:
            step = list(path[-1])
            step[axis] = 1
            path.append(tuple(step))
        tets.append(np.column_stack([corner[c] for c in path]))
    tets = np.concatenate(tets)
    x = points[tets]
    vol = np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]))
    flip = vol < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return points, tets


def bar_cage(divisions=(2, 2, 12)):
    """The bar's cage: a 1.3 x 1.3 x 5.4 box around it (z in [-0.2, 5.2]).

    The default ``(2, 2, 12)`` cells give 106 vertices and 208 triangles (the paper's count),
    with near-isotropic 0.65 x 0.45 cells on the long sides.

    Returns
    -------
    vhm_viz.Cage
    """
    v, f = _box_surface((-0.65, -0.65, -0.2), (0.65, 0.65, 5.2), divisions)
    return Cage(v, f)


@dataclass
class BarScenario:
    """A generated bar deformation scenario.

    Attributes
    ----------
    kind : str
    surface : pyvista.PolyData
        The bar's rest surface.
    points, triangles : ndarray
        The same surface as arrays.
    cage : Cage
    anchors : (6, 3) ndarray
    constraints : dict
        ``positions``, ``targets``, ``jacobian_points``, ``jacobians`` (user-facing ``J``).
    deformer : Deformer
        With the constraints set (not yet solved).
    scene : Scene
        The scenario as a :class:`~vhm_viz.scene.Scene` (inline cage and anchors), which
        built :attr:`deformer` and ramps its solves.
    """

    kind: str
    points: np.ndarray
    triangles: np.ndarray
    cage: object
    anchors: np.ndarray
    constraints: dict
    deformer: object
    scene: object
    _surface: object = field(default=None, repr=False)

    @property
    def surface(self):
        """The rest surface as a ``pyvista.PolyData`` (built on first access)."""
        if self._surface is None:
            import pyvista as pv  # only here: the scenarios are plain arrays otherwise

            faces = np.column_stack([np.full(len(self.triangles), 3), self.triangles]).ravel()
            self._surface = pv.PolyData(self.points.copy(), faces)
        return self._surface

    def solve(self, steps: int | None = None, **kwargs):
        """Solve, ramping the targets over ``steps`` warm-started solves.

        ``steps`` defaults to 6 for ``"twist"`` (a 180 degree twist from the identity sits on
        a saddle), 8 for ``"push"`` (a continuation, so the fold is the one reached by
        pushing) and 1 for the other kinds. Intermediate targets interpolate positions
        linearly and Jacobian rotations by angle (scale factors linearly). Extra keyword
        arguments go to :meth:`Deformer.solve`; the reports of all steps are returned (the
        last one describes the final solve).
        """
        if steps is None:
            steps = {"twist": 6, "push": 8}.get(self.kind, 1)
        return self.scene.solve(self.deformer, steps=steps, **kwargs)

    def deformed_points(self, binding=None) -> np.ndarray:
        """The deformed surface points for the deformer's current solution."""
        if binding is None:
            return self.deformer.harmonic_map.map(self.points)
        return binding.deform()


def bar(
    kind: str = "bend-u",
    *,
    mode: str = "rigid",
    alpha: float = 0.01,
    n_anchors: int = 6,
    resolution: int = 39,
    cage_divisions=(2, 2, 12),
    top_height: float = 2.5,
) -> BarScenario:
    """The bar scenario of the given kind, with a ready :class:`~vhm_viz.Deformer`.

    Parameters
    ----------
    kind : {"bend-u", "bend-90", "twist", "bulge", "push"}
    mode : {"rigid", "similar"}
    alpha : float
        Deformer stiffness.
    n_anchors : int
        Anchors evenly spaced on the centre line (midpoints of equal arc-length intervals).
    resolution : int
        Surface grid cells per unit length (39: 33,464 vertices).
    cage_divisions : (int, int, int)
        Cage cells along x, y, z (default 208 triangles).
    top_height : float
        ``"push"`` only: where the top centre goes, ``(0, 0, top_height)``.

    Returns
    -------
    BarScenario
    """
    if kind not in BAR_KINDS + FOLD_KINDS:
        raise ValueError(f"kind must be one of {BAR_KINDS + FOLD_KINDS}; got {kind!r}")
    points, tris = bar_surface(resolution)
    cage = bar_cage(cage_divisions)
    anchors = anchors_from_polylines(
        np.array([[0.0, 0.0, 0.0], [0.0, 0.0, BAR_LENGTH]]), np.array([[0, 1]]), n_anchors
    )
    inset = BAR_WIDTH / 2 - 0.1
    bottom = np.array(
        [[0, 0, 0], [-inset, -inset, 0], [inset, -inset, 0], [inset, inset, 0], [-inset, inset, 0]],
        dtype=float,
    )
    top = np.array([[0.0, 0.0, BAR_LENGTH]])
    if kind == "bend-u":
        top_target, top_jac = np.array([[_BEND_REACH, 0.0, 0.0]]), rotation("y", 180)
    elif kind in ("bend-90", "bulge"):
        top_target, top_jac = np.array([[_BEND_REACH, 0.0, _BEND_REACH]]), rotation("y", 90)
    elif kind == "push":
        top_target, top_jac = np.array([[0.0, 0.0, float(top_height)]]), np.eye(3)
    else:  # twist
        top_target, top_jac = top.copy(), rotation("z", 180)
    positions = np.vstack([bottom, top])
    targets = np.vstack([bottom, top_target])
    jac_points = [bottom[0], top[0]]
    jacobians = [np.eye(3), top_jac]
    if kind == "bulge":
        jac_points.append(np.array([0.0, 0.0, BAR_LENGTH / 2]))
        jacobians.append(1.3 * rotation("y", 45))
    constraints = {
        "positions": positions,
        "targets": targets,
        "jacobian_points": np.array(jac_points),
        "jacobians": np.array(jacobians),
    }
    scene = Scene(
        cage={"vertices": np.array(cage.vertices), "faces": np.array(cage.faces)},
        anchors={"points": np.array(anchors, dtype=np.float64)},
        constraints=constraints,
        mode=mode,
        alpha=alpha,
    )
    dfm = scene.build(cage=cage)
    return BarScenario(kind, points, tris, cage, anchors, constraints, dfm, scene)
