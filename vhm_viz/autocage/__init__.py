"""Automatic cages and anchors: everything that builds a deformation's set-up from data.

* :func:`auto_cage` (:mod:`.cage`) -- a closed, manifold cage enclosing a dataset, from a
  voxelisation (:mod:`.voxel`), an offset surface, a compiled simplifier (:mod:`.simplify`),
  near-distance queries (:mod:`.proximity`) and edge checks (:mod:`.meshcheck`);
* :func:`auto_anchors` (:mod:`.anchors`) -- anchors on the medial axis inside the cage.

Datasets given as paths are read by :mod:`vhm_viz.io`; everything else here is numbers.
"""

from vhm_viz.autocage.anchors import AnchorReport, auto_anchors
from vhm_viz.autocage.cage import AutoCageReport, auto_cage, collect_samples

__all__ = ["auto_cage", "auto_anchors", "collect_samples", "AutoCageReport", "AnchorReport"]
