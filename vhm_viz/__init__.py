"""vhm_viz: Variational Harmonic Maps for space deformation in the VTK world.

The public names are imported lazily so that ``import vhm_viz`` stays fast and the
numeric core can be used without loading VTK.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# public name -> module that defines it
_LAZY = {
    "Cage": "vhm_viz.core.cage",
    "read_cage": "vhm_viz.io",
    "write_cage": "vhm_viz.io",
    "read_dataset": "vhm_viz.io",
    "read_anchors": "vhm_viz.io",
    "CageError": "vhm_viz.core.errors",
    "OutsideCageError": "vhm_viz.core.errors",
    "ConstraintError": "vhm_viz.core.errors",
    "HarmonicMap": "vhm_viz.core.harmonic_map",
    "Deformer": "vhm_viz.core.deformer",
    "anchors_from_polylines": "vhm_viz.core.anchors",
    "read_polylines": "vhm_viz.io",
    "read_tgf": "vhm_viz.io",
    "auto_cage": "vhm_viz.autocage",
    "auto_anchors": "vhm_viz.autocage",
    "tetrahedralize": "vhm_viz.tetra",
    "certify_injectivity": "vhm_viz.core.certify",
    "Region": "vhm_viz.core.certify",
    "region_of": "vhm_viz.filters.cells",
}
_SUBMODULES = {"metrics", "examples", "filters", "plotting", "scene", "core", "io"}

__all__ = sorted([*_LAZY, *_SUBMODULES, "__version__"])


def __getattr__(name: str):
    if name in _LAZY:
        module = importlib.import_module(_LAZY[name])
        value = getattr(module, name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        target = "vhm_viz.core.metrics" if name == "metrics" else f"vhm_viz.{name}"
        module = importlib.import_module(target)
        globals()[name] = module
        return module
    raise AttributeError(f"module 'vhm_viz' has no attribute {name!r}")


def __dir__():
    return __all__
