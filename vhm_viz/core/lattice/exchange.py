"""Lattices built in windows (MPI ranks), regrouped: parts of lattices and their join.

Each rank builds the lattice of its window of the grid; :meth:`HermiteLattice.part`
hands out some of its leaves as plain arrays (:data:`PART_FIELDS`) and
:func:`join_parts` makes one lattice of the parts a rank receives, ordered as the whole
grid's lattice would be.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.lattice.build import DEFAULT_ROOT
from vhm_viz.core.lattice.cage_edges import cage_edges_in_index
from vhm_viz.core.lattice.hermite import N_TERMS
from vhm_viz.core.lattice.hermite_lattice import HermiteLattice, leaf_stats, root_index
from vhm_viz.core.memory import release_free_memory

#: The arrays of :meth:`HermiteLattice.part`: per leaf (first axis: leaves) but ``data``
#: (first axis: the data rows the leaves read); their trailing shapes and dtypes.
PART_FIELDS = {
    "order": ((2,), np.int64),
    "origin": ((3,), np.int64),
    "size": ((), np.int64),
    "cut": ((), np.bool_),
    "rows": ((8,), np.int64),
    "data": ((N_TERMS, 3), np.float64),
    "centre_f": ((3,), np.float64),
    "centre_ginv": ((3, 3), np.float64),
    "rho": ((), np.float64),
}


def join_parts(parts, harmonic_map, geometry: ImageGeometry, *, tolerance: float,
               root: int = DEFAULT_ROOT, stats=None) -> HermiteLattice:  # fmt: skip
    """One lattice of the leaves of several lattices' parts (:meth:`HermiteLattice.part`).

    The parts come from lattices of the same map and grid (windows of it: MPI ranks);
    no leaf may be in two parts. The leaves are ordered as in the whole grid's lattice
    (by root cell, then as each root cell's build made them), so that resampling with
    the joined lattice visits the same leaves in the same order as with the whole one:
    where those leaves are all the leaves whose images reach the output voxels
    resampled, their pre-images are the whole lattice's, bit for bit. The joined lattice
    has no masks, only the inside and surface flags around the leaves the cage crosses
    (:meth:`HermiteLattice.cut_flags`), the only ones the pull-back reads.

    Parameters
    ----------
    parts : list of dict
        :data:`PART_FIELDS` arrays; each is released (set to None) once joined, so that
        the parts and the lattice are not held twice.
    harmonic_map : HarmonicMap
    geometry : ImageGeometry
        The input grid.
    tolerance : float
        The lattices' tolerance (voxels).
    root : int
        Their root cell size.
    stats : dict, optional
        Build statistics to keep (evaluations...); leaf counts are the join's.
    """
    last = np.asarray(geometry.dimensions, dtype=np.int64) - 1
    n_root = np.maximum(1, -(-last // root))
    lat_geo = ImageGeometry(geometry.origin, geometry.spacing, n_root * root + 1,
                            geometry.direction)  # fmt: skip
    # each part's rows index its own data: shifted past the parts joined before it
    offsets = np.cumsum([0] + [len(p["data"]) for p in parts])
    joined = {}
    for name, (shape, dtype) in PART_FIELDS.items():
        arrays = [p[name] for p in parts]
        if name == "rows":
            arrays = [a + offsets[n] for n, a in enumerate(arrays)]
        joined[name] = np.concatenate(arrays or [np.zeros((0,) + shape, dtype=dtype)])
        del arrays
        for p in parts:  # each part's arrays go as soon as they are joined
            p[name] = None
        release_free_memory()  # their heap pages too: the next field may not fit them
    order = joined.pop("order")
    data = joined.pop("data")
    perm = np.lexsort((order[:, 1], order[:, 0]))
    leaf = {name: np.ascontiguousarray(a[perm]) for name, a in joined.items()}
    rkey = order[perm, 0]
    start, count = root_index(rkey, n_root)
    h = leaf["size"]
    cage = harmonic_map.cage
    edge_a, edge_b = cage_edges_in_index(lat_geo, cage)
    joined = HermiteLattice(
        geometry=geometry,
        tolerance=float(tolerance),
        root=int(root),
        n_root=n_root.astype(np.int64),
        data=data,
        leaf_origin=leaf["origin"],
        leaf_size=leaf["size"],
        leaf_rows=leaf["rows"],
        leaf_cut=leaf["cut"],
        root_start=start,
        root_count=count,
        centre_f=leaf["centre_f"],
        centre_ginv=leaf["centre_ginv"],
        rho=leaf["rho"],
        mask=None,
        near=None,
        edge_a=edge_a,
        edge_b=edge_b,
        stats={**(stats or {}), **leaf_stats(h, len(data))},
        pre_images=True,
    )
    # no masks: the pull-back reads flags only around the leaves the cage crosses, and
    # masks over the rows of all the joined leaves would add to an MPI rank's peak
    joined.cut_flags(lat_geo, np.asarray(cage.vertices, dtype=np.float64), np.asarray(cage.faces))
    return joined
