"""An adaptive lattice of exact map values and Jacobians, interpolated by tricubic Hermite.

A harmonic map is real-analytic inside its cage, so its values on the voxels of an image
need not be computed one by one. The lattice evaluates the map exactly (closed-form values
and Jacobians) at the nodes of an octree laid over the voxel grid and interpolates every
voxel in between with the tricubic Hermite polynomial of its cell. The polynomial uses the
exact Jacobians, is C1 between neighbouring cells of the same size and reproduces affine
maps exactly.

**Cells and error estimate.** Root cells are ``root`` voxels wide (a power of two); cells
split into 8 down to single voxels, whose corners are voxels (exact). Every test point is
a voxel position, so its exact evaluation is reused as a node when the cell splits. A cell
is tested at its centre and, within two cell widths of the cage, also at its face centre
and edge midpoint nearest to the cage (the error of a cell concentrates on its side facing
the cage). A cell splits when its largest test error exceeds 0.15 times the tolerance:
the margin covers the points between the tests. Cells within a voxel of a cage edge
always split down to single voxels: there the map has a logarithmic singularity whose
error a larger cell's tests can miss (the benchmark measures the error at random voxels
and next to the cage).

**Node data.** Per node: the value ``f`` (world), ``f_u = df/du`` (``u``: voxel index
coordinates, so ``f_u = J @ direction @ diag(spacing)``), and the mixed derivatives
``f_uv, f_uw, f_vw, f_uvw`` from central differences of the exact Jacobians of the
neighbouring nodes of the same octree level (one-sided where a neighbour is missing).

**Cells that cross the cage.** The map is only defined inside the cage, yet cells next to
it have corners outside. There the node data is the *analytic continuation* of the map
across the nearest cage face ``t``, which the jump relations of the layer potentials give
in closed form (Kress, *Linear Integral Equations*, 3rd ed., Theorems 6.15 and 6.18): the
double layer jumps by its density and the single layer's normal derivative by its density,
so the interior map continued across the plane of face ``t`` is the exterior formula plus
an affine term,

    f_cont(p) = f_formula(p) + A_t(pi_t(p)) + ((p - x_t) . N_t) b_t,

with ``A_t`` the linear interpolation of the vertex coefficients ``a_v`` over the face,
``pi_t`` the projection onto its plane and ``b_t`` the face coefficient (both sides are
harmonic with the same Cauchy data on the face, so they agree). Near cage *edges* the map
has a logarithmic singularity and the continuation is not single-valued; the tests there
refine the cells, down to single voxels.

**Pre-images.** Each leaf keeps its value and inverse Jacobian at the centre and a bound
``rho`` of its nonlinearity, from the Bezier control points of its polynomial (which also
bound its image): a point whose linear pre-image estimate misses the cell by more than
``rho`` has no pre-image in it. Newton's method on the cell's polynomial finds the others.

**Modules.** :mod:`~vhm_viz.core.lattice.hermite` (a cell's polynomial, compiled),
:mod:`~vhm_viz.core.lattice.continuation` (exact node data, continued across the cage),
:mod:`~vhm_viz.core.lattice.cage_edges` (nearness to cage edges),
:mod:`~vhm_viz.core.lattice.nodes` (the node table and each level's node data),
:mod:`~vhm_viz.core.lattice.build` (:func:`build_lattice`),
:mod:`~vhm_viz.core.lattice.exchange` (parts and their join, for MPI ranks),
:mod:`~vhm_viz.core.lattice.pullback` (pre-images) and
:mod:`~vhm_viz.core.lattice.hermite_lattice` (:class:`HermiteLattice`).
"""

from vhm_viz.core.lattice.build import (
    DEFAULT_ROOT,
    DEFAULT_TOLERANCE,
    MAX_TOLERANCE,
    build_lattice,
    check_tolerance,
    exchange_rounds,
)
from vhm_viz.core.lattice.exchange import PART_FIELDS, join_parts
from vhm_viz.core.lattice.hermite_lattice import HermiteLattice

__all__ = [
    "HermiteLattice",
    "build_lattice",
    "join_parts",
    "exchange_rounds",
    "check_tolerance",
    "PART_FIELDS",
    "DEFAULT_ROOT",
    "DEFAULT_TOLERANCE",
    "MAX_TOLERANCE",
]
