"""What a filter keeps between updates: the binding of its points and its volume engine.

Both are costly to build and depend only on part of a filter's settings, so a filter keeps
the last one while what it was built from still holds:

* :class:`BindingCache`: the binding of a point set to a deformer (its basis matrix),
  kept while the deformer (the same object, with the same constraint layout), the points'
  geometry, the outside policy and the memory budget hold -- moving targets re-uses it;
* :class:`VolumeEngineCache`: the :class:`~vhm_viz.core.volume.VolumeDeformation` of a
  map on an image grid, kept while the map's content, the grid, the tolerance, the budget
  and the window hold (its tolerance checked by
  :func:`~vhm_viz.core.volume.check_tolerance`).

Objects are compared by identity (``is``) and held by the cache, never by ``id()``: an id
is reused once its object is collected, and a new deformer could then pass for the old.
"""

from __future__ import annotations

import hashlib

import numpy as np

from vhm_viz.core.binding import bind_map
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.memory import release_free_memory
from vhm_viz.core.volume import VolumeDeformation

__all__ = ["BindingCache", "VolumeEngineCache", "map_digest"]


def map_digest(harmonic_map) -> str:
    """A digest of a harmonic map's content: its cage (vertices, faces) and coefficients.

    The same map solved again (a re-read scene, another MPI rank) gives the same digest.
    """
    h = hashlib.blake2b(digest_size=16)
    for array, dtype in (
        (harmonic_map.cage.vertices, np.float64),
        (harmonic_map.cage.faces, np.int64),
        (harmonic_map.coefficients, np.float64),
    ):
        a = np.ascontiguousarray(array, dtype=dtype)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


class BindingCache:
    """The binding of a filter's points, rebuilt only when what it depends on changes."""

    def __init__(self):
        self._deformer = None
        self._key = None
        self.binding = None
        #: Number of times a binding was built for a deformer.
        self.count = 0

    def get(self, harmonic_map, deformer, points, *, data_key, outside, budget, progress, abort):
        """The binding of ``points`` (N, 3) to ``deformer`` (or to a fixed map).

        Parameters
        ----------
        harmonic_map : HarmonicMap
            The map, bound afresh on every call when ``deformer`` is None (nothing to keep).
        deformer : Deformer or None
            Its binding is kept while the deformer, its ``n_factorizations``, ``data_key``
            (the points' geometry), ``outside`` and ``budget`` hold.
        points : (N, 3) float64 array
        data_key : hashable
            Changes when the points move (:func:`~vhm_viz.filters._vtk.geometry_key`).
        outside : str
            The outside policy.
        budget : int or None
            Bytes of basis arrays per chunk.
        progress : callable(fraction, message)
        abort : callable() -> bool

        Returns
        -------
        Binding
        """
        if deformer is None:
            return bind_map(harmonic_map, points, outside=outside, memory_budget=budget)
        key = (deformer.n_factorizations, data_key, outside, budget)
        if self.binding is None or deformer is not self._deformer or key != self._key:
            self.binding = None  # free the old basis matrix before computing the new one
            self.binding = deformer.bind(
                points, outside=outside, memory_budget=budget, progress=progress, abort=abort
            )
            self._deformer, self._key = deformer, key
            self.count += 1
        return self.binding


class VolumeEngineCache:
    """The volume engine of a map on an image grid, rebuilt only when its inputs change."""

    def __init__(self):
        self.engine = None
        #: What the engine was built from (map digest, grid, tolerance, budget, window, ...).
        self.key = None

    def get(
        self,
        harmonic_map,
        geometry: ImageGeometry,
        *,
        tolerance: float,
        outside: str,
        budget,
        window=None,
        pre_images: bool = True,
        exchange=None,
        device: str = "cpu",
    ) -> VolumeDeformation:
        """The engine of ``harmonic_map`` on ``geometry``.

        Parameters
        ----------
        harmonic_map : HarmonicMap
        geometry : ImageGeometry
            The whole input grid.
        tolerance : float
            Largest position error of a mapped voxel, in voxels (validated by the filter).
        outside : str
            The outside policy; a change keeps the lattice (it does not depend on it).
        budget : int or None
            Bytes of working memory per chunk.
        window : sequence of 6 int, optional
            A piece's box of voxels: its lattice covers the piece's root cells only
            (aligned with the whole grid, so its voxels get the values the whole lattice
            gives them). None: the whole lattice, shared by the pieces of an update.
        pre_images : bool
            False for warping and analysing voxels only (a faster lattice).
        exchange : LatticeExchange, optional
            Under MPI, the ranks' shared evaluation of the lattice points.
        device : {"cpu", "cuda"}
            Where the lattice's exact evaluations run (see :class:`VolumeDeformation`).

        Returns
        -------
        VolumeDeformation
        """
        key = (
            map_digest(harmonic_map),
            geometry.key(),
            tolerance,
            budget,
            None if window is None else tuple(int(v) for v in window),
            bool(pre_images),
            device,
        )
        if self.engine is not None and key == self.key:
            if self.engine.outside != outside:
                # ParaView pushes properties one by one, each with an information pass:
                # a new policy must not rebuild the lattice
                self.engine = self.engine.with_outside(outside)
            return self.engine
        self.engine = None  # free the old lattice first
        release_free_memory()
        self.engine = VolumeDeformation(
            harmonic_map,
            geometry,
            tolerance=tolerance,
            outside=outside,
            memory_budget=budget,
            window=window,
            exchange=exchange,
            pre_images=pre_images,
            device=device,
        )
        self.key = key
        return self.engine
