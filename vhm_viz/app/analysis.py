"""Analysis helpers of the explorer (no Qt): the Jacobian slice and marker images.

The slice is a planar grid in **rest space** (inside the cage and, for closed surfaces,
inside the shape), bound to the deformer; each frame it is mapped through the harmonic map
and coloured by a closed-form Jacobian measure (``Binding.jacobians``), as in the paper's
Figure 4: the material cross-section, shown deformed.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from vhm_viz.colours import measure_style
from vhm_viz.core import metrics as M
from vhm_viz.core.metrics import foldover_count
from vhm_viz.filters import cell_quality

__all__ = ["SliceProbe", "measure_values", "shape_metrics", "shown_values", "triangles_of"]


def measure_values(jacobians: np.ndarray, measure: str) -> np.ndarray:
    """Per-point ``determinant`` or ``condition_number`` of (N, 3, 3) Jacobians."""
    if measure == "determinant":
        return M.jacobian_determinant(jacobians)
    if measure == "condition_number":
        return M.condition_number(jacobians)
    raise ValueError(f"unknown measure {measure!r} (determinant, condition_number)")


def shown_values(values: np.ndarray, style: dict) -> np.ndarray:
    """Values to draw with a :func:`vhm_viz.colours.measure_style` (log scale safe).

    Clipped into the colour range; a fold (``det J <= 0``, no logarithm) goes below it
    so that it takes the style's ``below_color``.
    """
    lo, hi = style["clim"]
    v = np.clip(np.nan_to_num(values, nan=hi, posinf=hi), lo, hi)
    if style["below_color"] is not None:
        v[np.asarray(values) <= 0] = 0.5 * lo
    return v


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = np.asarray(normal, float)
    n = n / np.linalg.norm(n)
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    return n, u, np.cross(n, u)


class SliceProbe:
    """A planar slice of the rest shape, bound to a deformer.

    Parameters
    ----------
    controller : ExplorerController
        Must be :attr:`~ExplorerController.ready`.
    origin, normal : (3,) array_like
        The plane (rest space).
    resolution : int
        Samples per side of the square grid (side = cage bounding-box diagonal).

    Attributes
    ----------
    mesh : pyvista.PolyData
        Quads between kept samples; points are the deformed samples (updated in place by
        :meth:`update`), point data ``"measure"``.
    """

    def __init__(self, controller, origin, normal, resolution: int = 60):

        cage = controller.cage
        n, u, v = _plane_basis(normal)
        o = np.asarray(origin, float)
        half = 0.5 * float(np.linalg.norm(cage.bounds[1] - cage.bounds[0]))
        r = int(resolution)
        s = np.linspace(-half, half, r)
        ss, tt = np.meshgrid(s, s, indexing="ij")
        pts = o + ss.reshape(-1, 1) * u + tt.reshape(-1, 1) * v
        lo, hi = cage.bounds[0], cage.bounds[1]
        keep = np.all((pts >= lo) & (pts <= hi), axis=1)
        idx = np.nonzero(keep)[0]
        if idx.size:
            keep[idx] = cage.contains(pts[idx])
        keep &= self._inside_shape(controller, pts)
        grid = np.arange(r * r).reshape(r, r)
        a, b = grid[:-1, :-1].ravel(), grid[1:, :-1].ravel()
        c, d = grid[1:, 1:].ravel(), grid[:-1, 1:].ravel()
        quads = np.column_stack([a, b, c, d])
        quads = quads[keep[quads].all(axis=1)]
        used = np.unique(quads)
        remap = -np.ones(r * r, dtype=np.int64)
        remap[used] = np.arange(used.size)
        self.normal, self.origin = n, o
        self._setup(controller, pts[used], remap[quads])

    def _setup(self, controller, rest_points, quads, dtype=np.float64) -> None:
        self.rest_points = np.ascontiguousarray(rest_points, dtype=np.float64)
        faces = np.column_stack([np.full(len(quads), 4), quads]).ravel()
        self.mesh = pv.PolyData(self.rest_points.copy(), faces if len(quads) else None)
        self.mesh.point_data["measure"] = np.zeros(len(self.rest_points))
        self.binding = None
        if len(self.rest_points) and controller is not None and controller.ready:
            self.binding = controller.deformer.bind(
                self.rest_points, outside="passthrough", dtype=dtype
            )
        self.jacobians = np.broadcast_to(np.eye(3), (len(self.rest_points), 3, 3))

    def colour(self, measure: str, values: np.ndarray) -> dict:
        """Store ``values`` for drawing in the style of :mod:`vhm_viz.colours`; the style."""
        style = measure_style(measure, values)
        self.mesh.point_data["shown"] = shown_values(values, style)
        return style

    @classmethod
    def on_grid(cls, controller, points, shape, dtype=np.float64) -> SliceProbe:
        """A slice through given rest points on a (a, b) grid (first axis fastest).

        The volume's slices (:class:`~vhm_viz.app.volume.VolumeView`): every sample is
        kept; outside the cage it stays in place. ``dtype``: the binding's (float32
        halves the memory of a large slice). Before a deformation is ready (``controller``
        None or not ready) the slice is not bound and stays at rest.
        """
        a, b = (int(v) for v in shape)
        grid = np.arange(a * b).reshape(b, a)
        quads = np.column_stack([grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel(),
                                 grid[1:, 1:].ravel(), grid[1:, :-1].ravel()])  # fmt: skip
        self = cls.__new__(cls)
        pts = np.asarray(points, dtype=np.float64)
        self.origin = pts.mean(axis=0) if len(pts) else np.zeros(3)
        self.normal = None
        self._setup(controller, pts, quads, dtype)
        return self

    @staticmethod
    def _inside_shape(controller, pts: np.ndarray) -> np.ndarray:
        """Samples inside a closed surface (all samples for other data)."""
        surf = controller.rest
        if not isinstance(surf, pv.PolyData) or surf.GetNumberOfPolys() == 0:
            return np.ones(len(pts), bool)
        try:
            probe = pv.PolyData(pts)
            sel = probe.select_interior_points(surf, check_surface=True)
            return np.asarray(sel.point_data["selected_points"], bool)
        except (RuntimeError, ValueError, AttributeError):
            return np.ones(len(pts), bool)  # not closed: keep the cage section

    @property
    def n_points(self) -> int:
        """Number of slice samples."""
        return len(self.rest_points)

    def update(self, measure: str | None = "determinant") -> np.ndarray:
        """Deform the slice and recompute the measure (None: deform only); returns it."""
        if self.binding is None:
            return np.zeros(0)
        pts = np.asarray(self.mesh.points)
        self.binding.deform(out=pts)
        self.mesh.GetPoints().Modified()
        if measure is None:
            return np.zeros(0)
        self.jacobians = self.binding.jacobians()
        vals = measure_values(self.jacobians, measure)
        self.mesh.point_data["measure"][:] = vals
        self.mesh.point_data.Modified()
        self.mesh.GetPointData().GetArray("measure").Modified()
        return vals

    def foldovers(self) -> int:
        """Slice samples with ``det J <= 0``."""
        return foldover_count(np.asarray(self.jacobians)) if self.n_points else 0


def triangles_of(data) -> np.ndarray | None:
    """(m, 3) triangles of a polygonal surface made only of triangles, else None."""
    if not isinstance(data, pv.PolyData) or data.GetNumberOfPolys() == 0:
        return None
    if not data.is_all_triangles:
        return None
    return np.asarray(data.regular_faces)


def shape_metrics(rest, display, rest_points: np.ndarray, cells: bool = True) -> dict:
    """Distortion of the displayed shape against its rest pose.

    Parameters
    ----------
    rest : pyvista.DataSet
        The loaded data.
    display : pyvista.DataSet
        The displayed, deformed copy (its points are the deformed positions).
    rest_points : (P, 3) ndarray
        The display's rest positions.
    cells : bool
        Count inverted 3D cells (:func:`vhm_viz.filters.cell_quality`).

    Returns
    -------
    dict
        ``E_rigid`` and ``E_volume`` of a triangle surface (NaN otherwise); with ``cells``
        and data with 3D cells also ``inverted_cells`` and ``cells``.
    """
    out = {"E_rigid": float("nan"), "E_volume": float("nan")}
    tris = triangles_of(display)
    deformed = np.asarray(display.points)
    if tris is not None and len(tris):
        out["E_rigid"] = float(M.rigidity_distortion(rest_points, deformed, tris))
        try:
            out["E_volume"] = float(M.volume_change(rest_points, deformed, tris))
        except ValueError:
            pass
    if cells:
        quality = cell_quality(rest, deformed)
        if quality is not None:
            out["inverted_cells"] = quality["summary"]["inverted"]
            out["cells"] = quality["summary"]["cells"]
    return out
