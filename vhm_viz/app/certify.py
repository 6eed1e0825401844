"""The explorer's injectivity certificate: run it over the shape, and what to draw of it."""

from __future__ import annotations

import numpy as np

from vhm_viz.app.cancellation import Cancelled
from vhm_viz.core.certify import certify_injectivity
from vhm_viz.core.errors import AbortedError
from vhm_viz.filters import region_of
from vhm_viz.plotting import mapped_boxes

__all__ = ["certify_shape", "certificate_geometry"]


def certify_shape(harmonic_map, data, cage, max_cubes: int, progress, cancelled):
    """Certify ``harmonic_map`` injective over ``data``'s region, or find witnesses of folds.

    The region is :func:`vhm_viz.filters.region_of` of the data (a tet mesh's tetrahedra, a
    closed surface's solid, a volume's box, or the cage's interior for a point cloud).

    Returns
    -------
    InjectivityCertificate

    Raises
    ------
    Cancelled
        ``cancelled()`` became true.
    """
    region = region_of(data, cage)
    try:
        return certify_injectivity(
            harmonic_map, region, max_cubes=max_cubes, progress=progress, abort=cancelled
        )
    except AbortedError as exc:
        raise Cancelled("cancelled") from exc


def certificate_geometry(certificate, harmonic_map):
    """What to draw of a certificate, in deformed space.

    Returns
    -------
    witnesses : (w, 3) ndarray
        Images of the witnesses (``det J <= 0`` there).
    undecided : pyvista.UnstructuredGrid or None
        The undecided cubes as hexahedra with mapped corners.
    """
    if certificate is None:
        return np.zeros((0, 3)), None
    witnesses = (
        harmonic_map.map(certificate.witnesses, outside="passthrough")
        if len(certificate.witnesses)
        else np.zeros((0, 3))
    )
    cubes = (
        mapped_boxes(certificate.undecided, harmonic_map) if len(certificate.undecided) else None
    )
    return witnesses, cubes
