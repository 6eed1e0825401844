"""Automatic cages and anchors: everything that builds a deformation's set-up from data.

* :func:`auto_cage` (:mod:`.cage`, the driver) -- a closed, manifold cage enclosing a
  dataset. Inputs become points in :mod:`.samples` (volumes thresholded by
  :mod:`.threshold`) and are split into parts (:mod:`.parts`). The ``"offset"`` method
  builds one offset surface per group of parts (:mod:`.offset_surface`), simplifies it
  (:mod:`.offset_cage`, :mod:`.simplify` with its compiled loop :mod:`.edge_collapse`,
  guards :mod:`.collapse_guard` and Python reference :mod:`.edge_collapse_reference`) and
  restores the clearance (:mod:`.clearance`, distances from :mod:`.proximity`); the
  ``"voxel"`` method merges voxels (:mod:`.voxel_cage`, occupancy in :mod:`.voxel`, the
  surface in :mod:`.voxel_surface`). Mesh plumbing lives in :mod:`.mesh`, edge checks in
  :mod:`.meshcheck`;
* :func:`auto_anchors` (:mod:`.anchors`) -- anchors on the medial axis inside the cage.

Datasets given as paths are read by :mod:`vhm_viz.io`; everything else here is numbers.
"""

from vhm_viz.autocage.anchors import AnchorReport, auto_anchors
from vhm_viz.autocage.cage import AutoCageReport, auto_cage
from vhm_viz.autocage.samples import collect_samples
from vhm_viz.autocage.threshold import otsu_threshold

__all__ = [
    "auto_cage",
    "auto_anchors",
    "collect_samples",
    "otsu_threshold",
    "AutoCageReport",
    "AnchorReport",
]
