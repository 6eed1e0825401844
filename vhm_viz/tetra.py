"""Tetrahedralize a closed surface (fTetWild through pytetwild), to deform the solid."""

from __future__ import annotations

import contextlib
import os
import tempfile
import warnings

import numpy as np

__all__ = ["tetrahedralize"]


def tetrahedralize(
    surface,
    *,
    edge_length: float | None = None,
    edge_length_fac: float = 0.05,
    optimize: bool = True,
    epsilon: float = 1e-3,
    num_threads: int = 0,
    quiet: bool = True,
    **kwargs,
):
    """Tetrahedral mesh of the solid bounded by a closed triangle surface.

    A thin wrapper of :func:`pytetwild.tetrahedralize_pv` (fTetWild: robust to small
    defects; the boundary follows the input within ``epsilon`` of the bounding-box
    diagonal, it is not the input triangulation). fTetWild is not deterministic: the same
    surface and options give a different mesh from run to run, with a different number of
    tetrahedra (fTetWild issue #72), so save the mesh to deform the same one twice.

    Parameters
    ----------
    surface : pyvista.PolyData, (vertices, faces) tuple or path
        A closed surface; polygons are triangulated.
    edge_length : float, optional
        Target tetrahedron edge length in world units (overrides ``edge_length_fac``).
    edge_length_fac : float
        Target edge length as a fraction of the bounding-box diagonal (default 1/20).
    optimize : bool
        Improve the element quality (slower).
    epsilon : float
        Envelope size relative to the bounding-box diagonal.
    num_threads : int
        Threads (0: all cores).
    quiet : bool
        Silence fTetWild.
    **kwargs
        Other :func:`pytetwild.tetrahedralize_pv` options.

    Returns
    -------
    pyvista.UnstructuredGrid
        Tetrahedra only.

    Raises
    ------
    ValueError
        Empty or open surface, or a non-positive edge length.
    """
    import pyvista as pv

    mesh = _as_surface(surface)
    if mesh.n_points == 0 or mesh.n_cells == 0:
        raise ValueError("tetrahedralize: the surface is empty")
    if not mesh.is_all_triangles:
        mesh = mesh.triangulate()
    open_edges = mesh.extract_feature_edges(
        boundary_edges=True, non_manifold_edges=False, feature_edges=False, manifold_edges=False
    ).n_cells
    if open_edges:
        raise ValueError(
            f"tetrahedralize: the surface is not closed ({open_edges} boundary edges); "
            "fill its holes first"
        )
    if edge_length is not None and not edge_length > 0:
        raise ValueError(f"tetrahedralize: edge_length must be positive; got {edge_length}")
    from pytetwild import tetrahedralize_pv

    # fTetWild writes a debug file (__tracked_surface.stl) into the working directory;
    # run it in a scratch directory so no stray files appear where the user works.
    # pytetwild calls a PyVista method that PyVista deprecates: nothing for the user to change
    with (
        tempfile.TemporaryDirectory(prefix="vhm_tetwild_") as scratch,
        _working_directory(scratch),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("ignore", pv.PyVistaDeprecationWarning)
        grid = tetrahedralize_pv(
            pv.PolyData(mesh.points, mesh.faces),
            edge_length_fac=edge_length_fac,
            edge_length_abs=edge_length,
            optimize=optimize,
            epsilon=epsilon,
            num_threads=num_threads,
            quiet=quiet,
            **kwargs,
        )
    if grid.n_cells == 0:
        raise ValueError("tetrahedralize: fTetWild produced no tetrahedra")
    return grid


@contextlib.contextmanager
def _working_directory(path):
    """Temporarily change the process's working directory (not thread-safe, like chdir)."""
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


def _as_surface(surface):
    import pyvista as pv

    if isinstance(surface, tuple) and len(surface) == 2:
        v = np.asarray(surface[0], dtype=np.float64)
        f = np.asarray(surface[1], dtype=np.int64)
        return pv.PolyData.from_regular_faces(v, f)
    if not isinstance(surface, pv.DataSet):
        from vhm_viz.io import read_dataset

        surface = read_dataset(surface)
    if not isinstance(surface, pv.PolyData):
        surface = surface.extract_surface()
    return surface
