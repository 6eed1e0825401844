"""Level of detail: a light proxy of a large shape, deformed while dragging.

A shape with more than :attr:`LevelOfDetail.points` points gets a *proxy* (a decimated
triangle surface of about :attr:`LevelOfDetail.triangles` triangles, or a subset of a point
cloud) with its own float32 binding. While dragging only the proxy is deformed; the full
shape follows on release.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

__all__ = [
    "LOD_POINTS",
    "PROXY_TRIANGLES",
    "LevelOfDetail",
    "level_of_detail_setting",
    "make_proxy",
]

# shapes with more points than this are dragged as a decimated proxy
LOD_POINTS = 30000
# triangles of the proxy (software OpenGL renders ~10k triangles well within a frame)
PROXY_TRIANGLES = 12000


def make_proxy(data, triangles: int = PROXY_TRIANGLES):
    """A light stand-in of ``data`` to deform and render while dragging.

    Parameters
    ----------
    data : pyvista.DataSet
        The shape (rest space).
    triangles : int
        Target size: triangles of a decimated surface, or twice the points of a point subset.

    Returns
    -------
    pyvista.PolyData
        Float64 points. Surfaces (polygons, or the outer surface of volumetric cells) are
        triangulated and reduced by quadric decimation (``vtkQuadricDecimation``); point
        clouds and line sets become a regular subset of their points (vertex cells).
    """
    if isinstance(data, pv.PolyData) and data.GetNumberOfPolys() == 0:
        surf = None
    elif isinstance(data, pv.PolyData):
        surf = data
    else:
        surf = data.extract_surface(algorithm="dataset_surface")
        if surf.GetNumberOfPolys() == 0:
            surf = None
    if surf is None:  # points (and lines): a regular subset of the points
        n = data.n_points
        step = max(1, int(np.ceil(n / max(triangles // 2, 1))))
        pts = np.asarray(data.points, dtype=np.float64)[::step]
        proxy = pv.PolyData(np.ascontiguousarray(pts))
    else:
        surf = pv.PolyData(surf.points, surf.faces) if surf.n_points else surf
        surf = surf.triangulate().clean()
        if surf.n_cells > triangles:
            surf = surf.decimate(1.0 - triangles / surf.n_cells)
        proxy = pv.PolyData(np.asarray(surf.points, dtype=np.float64), surf.faces)
    proxy.points = np.ascontiguousarray(proxy.points, dtype=np.float64)
    return proxy


class LevelOfDetail:
    """The drag proxy of one shape and its binding.

    Attributes
    ----------
    enabled : bool
        Drag a proxy when the shape has more than ``points`` points.
    points, triangles : int
        Threshold and proxy size (see :func:`make_proxy`).
    proxy : pyvista.PolyData or None
        The proxy, deformed in place by :meth:`deform`.
    binding : ShapeBinding or None
        The proxy's float32 binding.
    rest_points : (Q, 3) ndarray
        Rest positions of the proxy's points (empty without a proxy).
    """

    def __init__(self, enabled: bool = True, points: int = LOD_POINTS,
                 triangles: int = PROXY_TRIANGLES):  # fmt: skip
        self.enabled = bool(enabled)
        self.points = int(points)
        self.triangles = int(triangles)
        self.clear()

    def clear(self) -> None:
        """Forget the proxy (new data)."""
        self.proxy = None
        self.binding = None
        self.rest_points = np.zeros((0, 3))

    def settings_from(self, other: LevelOfDetail) -> None:
        """Take ``enabled``, ``points`` and ``triangles`` from another instance."""
        self.enabled, self.points, self.triangles = other.enabled, other.points, other.triangles

    @property
    def active(self) -> bool:
        """Whether drags deform the proxy instead of the full shape."""
        return self.enabled and self.binding is not None

    def prepared(self, rest, n_points: int, deformer, rebuilt: bool, cancelled):
        """The proxy and its binding for ``deformer``, built or refreshed (not stored yet).

        Parameters
        ----------
        rest : pyvista.DataSet
            The shape in rest space.
        n_points : int
            Points of the displayed shape (compared with :attr:`points`).
        deformer : Deformer
        rebuilt : bool
            The deformer is new (the binding is rebuilt, not refreshed).
        cancelled : callable() -> bool

        Returns
        -------
        (proxy, binding, rest_points)
            Pass them to :meth:`adopt` once everything else is built. ``(None, None, empty)``
            for a small shape or with level of detail off.
        """
        if not self.enabled or n_points <= self.points:
            return None, None, np.zeros((0, 3))
        proxy, binding, rest_points = self.proxy, self.binding, self.rest_points
        if proxy is None:
            proxy = make_proxy(rest, self.triangles)
            rest_points = np.array(proxy.points, dtype=np.float64)
            binding = None
        if binding is None or rebuilt:
            binding = deformer.bind(
                rest_points, outside="passthrough", dtype=np.float32, abort=cancelled
            )
        else:
            binding.refresh(abort=cancelled)
        return proxy, binding, rest_points

    def adopt(self, proxy, binding, rest_points) -> None:
        """Use what :meth:`prepared` returned."""
        self.proxy, self.binding, self.rest_points = proxy, binding, rest_points

    def deform(self) -> np.ndarray:
        """Write the deformed points into :attr:`proxy` in place and return them."""
        out = np.asarray(self.proxy.points)
        self.binding.deform(out=out)
        self.proxy.GetPoints().Modified()
        return out

    def reset(self) -> None:
        """Show the proxy's rest shape."""
        if self.proxy is not None:
            np.asarray(self.proxy.points)[:] = self.rest_points
            self.proxy.GetPoints().Modified()


def level_of_detail_setting(name: str, doc: str) -> property:
    """A property of an owner of ``level_of_detail`` that reads and sets its ``name``."""

    def get(self):
        return getattr(self.level_of_detail, name)

    def set(self, value) -> None:
        setattr(self.level_of_detail, name, type(get(self))(value))

    return property(get, set, doc=doc)
