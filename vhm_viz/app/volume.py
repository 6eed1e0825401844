"""Volumes in the explorer (no Qt): orthogonal slices that follow the map, and rendering.

A volume (an image with point scalars) is never bound voxel by voxel: a 256^3 scan has
16.8 million voxels, and binding them would need gigabytes. Instead
:class:`VolumeView` keeps

* the image and its grid (:class:`~vhm_viz.core.image.ImageGeometry`);
* an **outline**: the image's box surface at a few dozen samples per side, which the
  controller deforms as the volume's "shape" (cheap to bind, pickable, shows the bend);
* three **orthogonal slices** (one per axis, at a voxel index the user moves). Each slice
  is a material plane of voxels bound to the deformer (:class:`~vhm_viz.app.analysis.SliceProbe`
  over the voxels of the plane): every solve maps it forward, so the slice bends with the
  volume. Two resolutions: a *drag* slice (at most :data:`DRAG_SAMPLES` samples per side,
  deformed at every drag frame, and coloured by det J or cond J) and a *full* slice (every
  voxel of the plane, up to :data:`FULL_SAMPLES` per side, deformed when the drag ends);
* the **deformed volume** for volume rendering and isosurfaces: the pull-back resampling
  of :class:`~vhm_viz.core.volume.VolumeDeformation` on a grid of at most
  :data:`RENDER_VOXELS` voxels (run in the background after each full solve).

The deformed volume is resampled on an NVIDIA GPU when one is usable
(:mod:`vhm_viz.core.lattice.cuda_pullback`): the device setting is ``VHM_DEVICE``
(:data:`DEVICE_VARIABLE`), ``auto`` by default (the GPU when present, else the CPU,
silently), or ``cpu`` / ``cuda``; ``cuda`` without a usable GPU falls back to the CPU
with one status line (:meth:`VolumeView.device`).
"""

from __future__ import annotations

import math
import os

import numpy as np
import pyvista as pv

from vhm_viz.app.analysis import SliceProbe
from vhm_viz.core.devices import resolve_device
from vhm_viz.core.image import ImageGeometry, inside_mask
from vhm_viz.core.volume import VolumeDeformation
from vhm_viz.filters._common import image_geometry

__all__ = [
    "VolumeView",
    "is_volume",
    "DRAG_SAMPLES",
    "FULL_SAMPLES",
    "OUTLINE_SAMPLES",
    "RENDER_VOXELS",
    "displayed",
    "DEVICE_VARIABLE",
]

#: Environment variable with the volume views' device setting: ``auto`` (default),
#: ``cpu`` or ``cuda`` (:func:`~vhm_viz.core.devices.resolve_device`).
DEVICE_VARIABLE = "VHM_DEVICE"

#: Samples per side of a slice while dragging (and of the det J / cond J colouring).
DRAG_SAMPLES = 96
#: Samples per side of a slice at rest (every voxel up to this).
FULL_SAMPLES = 256
#: Samples per side of the outline box surface (the volume's draggable "shape").
OUTLINE_SAMPLES = 24
#: Voxels of the resampled volume that is rendered (its grid is the input's, subsampled).
RENDER_VOXELS = 160**3


def is_volume(data) -> bool:
    """Whether ``data`` is an image (``pyvista.ImageData``) with point scalars."""
    import pyvista as pv

    return isinstance(data, pv.ImageData) and _scalar_name(data) is not None


def _scalar_name(image) -> str | None:
    name = image.point_data.active_scalars_name
    if name is None:
        names = [n for n in image.point_data.keys() if not n.startswith("vtk")]
        name = names[0] if names else None
    return name


def _step_for(n: int, samples: int) -> int:
    return max(1, math.ceil((n - 1) / max(samples - 1, 1)))


def _indices(n: int, step: int) -> np.ndarray:
    """0, step, 2 step, ... and always the last index."""
    idx = np.arange(0, n, step)
    return idx if idx[-1] == n - 1 else np.append(idx, n - 1)


class VolumeView:
    """The explorer's view of a volume: geometry, values, outline, slices, rendering.

    Parameters
    ----------
    image : pyvista.ImageData
        With point scalars (the first point array when none is active; a multi-component
        array shows its magnitude).
    device : {"auto", "cpu", "cuda"}, optional
        Where the deformed volume is resampled (default: ``$VHM_DEVICE``, else
        ``"auto"``); see :meth:`device`.
    """

    AXES = ("x", "y", "z")

    def __init__(self, image, device: str | None = None):
        self.image = image
        #: The device setting (:meth:`device` resolves it).
        self.device_setting = os.environ.get(DEVICE_VARIABLE, "auto") if device is None else device
        self._device = None
        self.name = _scalar_name(image)
        values = np.asarray(image.point_data[self.name])
        if values.ndim > 1:
            values = np.linalg.norm(values.reshape(len(values), -1), axis=1)
        self.values = np.asarray(values, dtype=np.float32)
        self.geometry = image_geometry(image)
        self.dimensions = tuple(int(d) for d in self.geometry.dimensions)
        finite = self.values[np.isfinite(self.values)]
        self.range = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        #: Voxel index of each axis' slice (default: the middle).
        self.index = [d // 2 for d in self.dimensions]

    def window(self) -> tuple[float, float]:
        """Default grey window: 1st to 99.5th percentile of the values above the minimum.

        The minimum is taken for background; at most a million voxels are sampled.
        """
        v = self.values[:: max(1, self.values.size // 1_000_000)]
        v = v[np.isfinite(v) & (v > self.range[0])]
        if v.size == 0:
            return self.range
        lo, hi = (float(x) for x in np.percentile(v, [1.0, 99.5]))
        return (lo, hi) if hi > lo else self.range

    # ------------------------------------------------------------------ geometry
    def grid_points(self, ijk: np.ndarray) -> np.ndarray:
        """World positions of voxel indices (k, 3)."""
        return self.geometry.points(np.asarray(ijk, dtype=np.float64))

    def outline(self, samples: int = OUTLINE_SAMPLES):
        """The image's box surface, triangulated, about ``samples`` points per side."""
        import pyvista as pv

        dims = np.asarray(self.dimensions)
        m = np.minimum(dims, samples)
        box = pv.ImageData(dimensions=tuple(int(v) for v in m))
        surf = box.extract_surface(algorithm="dataset_surface").triangulate().clean()
        # the small grid's index space -> the volume's voxel indices -> world
        scale = np.where(m > 1, (dims - 1) / np.maximum(m - 1, 1), 0.0)
        pts = self.grid_points(np.asarray(surf.points) * scale)
        return pv.PolyData(np.ascontiguousarray(pts, dtype=np.float64), surf.faces)

    def plane(self, axis: int, index: int | None = None, samples: int = FULL_SAMPLES):
        """Voxels of one plane, subsampled to at most ``samples`` per side.

        Returns
        -------
        points : (a * b, 3) float64
            World positions (rest space), the first in-plane axis fastest.
        shape : (a, b)
            Samples along the plane's two axes (in increasing axis order).
        values : (a * b,) float32
            The volume's values there.
        """
        index = self.index[axis] if index is None else int(index)
        dims = self.dimensions
        if not 0 <= index < dims[axis]:
            raise ValueError(
                f"slice {index} is outside 0..{dims[axis] - 1} along {self.AXES[axis]}"
            )
        u, v = [a for a in range(3) if a != axis]
        step = max(_step_for(dims[u], samples), _step_for(dims[v], samples))
        iu, iv = _indices(dims[u], step), _indices(dims[v], step)
        gv, gu = np.meshgrid(iv, iu, indexing="ij")  # u fastest
        ijk = np.empty((gu.size, 3), dtype=np.int64)
        ijk[:, u], ijk[:, v], ijk[:, axis] = gu.ravel(), gv.ravel(), index
        flat = ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2])
        return self.grid_points(ijk), (len(iu), len(iv)), self.values[flat]

    # ------------------------------------------------------------------ rendering
    def render_step(self, voxels: int = RENDER_VOXELS) -> int:
        """Subsampling step of the rendered (resampled) volume."""
        n = float(np.prod(self.dimensions))
        return max(1, math.ceil((n / voxels) ** (1.0 / 3.0)))

    def _subsampled(self, voxels: int):
        """The values subsampled by :meth:`render_step`, (nz, ny, nx), and their grid."""
        s = self.render_step(voxels)
        nx, ny, nz = self.dimensions
        vol = np.ascontiguousarray(self.values.reshape(nz, ny, nx)[::s, ::s, ::s])
        geo = self.geometry
        return vol, ImageGeometry(geo.origin, geo.spacing * s, vol.shape[::-1], geo.direction)

    @staticmethod
    def _to_image(geometry, values, valid=None):
        import pyvista as pv

        g = geometry
        img = pv.ImageData(dimensions=tuple(int(d) for d in g.dimensions),
                           spacing=tuple(g.spacing), origin=tuple(g.origin))  # fmt: skip
        if not np.allclose(g.direction, np.eye(3)):
            img.direction_matrix = g.direction
        img.point_data["values"] = np.asarray(values).ravel()
        if valid is not None:
            img.point_data["vtkValidPointMask"] = valid
        img.point_data.active_scalars_name = "values"
        return img

    def device(self) -> tuple[str, str | None]:
        """Where :meth:`deformed_image` resamples, and why not on the device asked for.

        Resolved once per view (:func:`~vhm_viz.core.devices.resolve_device`):
        ``("cuda", None)`` with a usable GPU unless the setting is ``cpu``; otherwise
        ``("cpu", reason)``, the reason a status line, or None where the CPU was asked for
        (or ``auto`` found no GPU).
        """
        if self._device is None:
            device, reason = resolve_device(self.device_setting)
            if reason is not None:
                reason = (f"volume views run on the CPU ({DEVICE_VARIABLE}="
                          f"{self.device_setting}: {reason})")  # fmt: skip
            self._device = (device, reason)
        return self._device

    def rest_image(self, voxels: int = RENDER_VOXELS):
        """The input subsampled like :meth:`deformed_image` (before any solve)."""
        vol, geo = self._subsampled(voxels)
        return self._to_image(geo, vol)

    def deformed_image(self, harmonic_map, voxels: int = RENDER_VOXELS, progress=None, abort=None):
        """The deformed volume on a regular grid (pull-back resampling), for rendering.

        The input is subsampled by :meth:`render_step` first, so that the lattice and the
        resampled grid stay small; voxels outside the cage stay in place. Resampled on the
        :meth:`device`.

        Returns
        -------
        pyvista.ImageData
            Point arrays ``"values"`` (float32) and ``"vtkValidPointMask"``.
        """
        vol, geo = self._subsampled(voxels)
        vd = VolumeDeformation(harmonic_map, geo, outside="passthrough", device=self.device()[0])
        out = vd.resample({"values": vol.ravel()}, progress=progress, abort=abort)
        return self._to_image(out.geometry, out.arrays["values"], out.valid)

    def inside(self, cage) -> np.ndarray:
        """(P,) bool: voxels inside the cage (VTK order; the scan-line test)."""
        return inside_mask(self.geometry, cage.vertices, cage.faces).ravel()

    def slice_probe(self, controller, axis: int, samples: int):
        """The slice of ``axis`` at :attr:`index` as a bound :class:`SliceProbe`.

        Point data ``"value"`` holds the volume's values at the samples. Slices with more
        than :data:`DRAG_SAMPLES` samples per side bind in float32 (half the memory).
        """
        pts, shape, values = self.plane(axis, samples=samples)
        dtype = np.float32 if samples > DRAG_SAMPLES else np.float64
        probe = SliceProbe.on_grid(controller, pts, shape, dtype=dtype)
        probe.mesh.point_data["value"] = values
        probe.mesh.point_data.active_scalars_name = "value"
        probe.axis = axis
        return probe


def displayed(data):
    """What the explorer shows and deforms for loaded ``data``.

    Returns
    -------
    data : pyvista.DataSet
        The data; an image or rectilinear grid that is no volume becomes a structured grid.
    display : pyvista.DataSet
        A deep copy with float64 points and no normals (the rest pose's normals would shade,
        and export, the deformed shape wrongly; the renderer shades each triangle by its
        deformed geometry); for a volume, its outline box surface.
    volume : VolumeView or None
    """
    volume = VolumeView(data) if is_volume(data) else None
    if volume is not None:
        display = volume.outline()
    else:
        if isinstance(data, pv.ImageData | pv.RectilinearGrid):
            data = data.cast_to_structured_grid()
        display = data.copy(deep=True)
    display.points = np.asarray(display.points, dtype=np.float64)
    for name in {"Normals", display.point_data.active_normals_name} - {None}:
        if name in display.point_data:
            del display.point_data[name]
    return data, display, volume
