"""PyVista dataset accessor ``mesh.vhm``: deform, analyse, resample with one call.

Registered on :class:`pyvista.DataSet` when this module is imported, and found by PyVista
through the ``pyvista.accessors`` entry point (PyVista >= 0.48), so ``import vhm_viz`` is
not even needed. Open scans with :func:`vhm_viz.read_dataset` (ITK's LPS frame: origin,
spacing and direction, as the command line, the explorer and ParaView's "VHM Medical
Image Reader" place them; ``pyvista.read`` drops the direction)::

    image = vhm_viz.read_dataset("scan.nii.gz")
    deformed = mesh.vhm.deform(deformer)        # same type rules as vtkWarpVector
    quality = mesh.vhm.analyze(deformer)        # det / cond / rotation / foldover arrays,
                                                # and cell arrays of tet meshes and volumes
    volume = image.vhm.resample(deformer)       # deformed volume on a regular grid
    field = image.vhm.displacement_field(deformer)  # f^-1(y) - y, as ITK/ANTs apply it
    answer = mesh.vhm.certify(deformer)         # det J > 0 everywhere in the shape?

``deformation`` is a :class:`~vhm_viz.Deformer`, a :class:`~vhm_viz.HarmonicMap`, a
:class:`~vhm_viz.scene.Scene` or the path of a scene file.

PyVista may load this module whenever it loads its accessors: the filters and the
certificate (compiled kernels) are imported by the method that needs them, not here.
"""

from __future__ import annotations

import pyvista as pv

__all__ = ["VHMAccessor"]


def _run(flt, mesh, deformation, cage, outside, **settings):
    """Update filter ``flt`` on ``mesh``; ``settings``: ``Set<Name>`` values (None: unset)."""
    from vhm_viz.filters import update

    flt.SetInputData(mesh)
    flt.SetDeformation(deformation)
    flt.SetOutsidePolicy(outside)
    for name, value in {"CageData": cage, **settings}.items():
        if value is not None:
            getattr(flt, f"Set{name}")(value)
    return pv.wrap(update(flt))


class VHMAccessor:
    """``mesh.vhm``: variational harmonic map operations on a PyVista dataset.

    Parameters
    ----------
    mesh : pyvista.DataSet
    """

    def __init__(self, mesh):
        self._mesh = mesh

    def deform(
        self,
        deformation,
        *,
        outside: str = "error",
        cage=None,
        displacement: bool = False,
        determinant: bool = False,
        condition_number: bool = False,
        normals: bool = True,
        tolerance: float | None = None,
    ):
        """The deformed dataset (:class:`vhm_viz.filters.HarmonicDeformationFilter`).

        Parameters
        ----------
        deformation : Deformer, HarmonicMap, Scene or path
        outside : {"error", "passthrough", "nan"}
            Points outside the cage: raise, leave in place (flagged ``vhm_outside``), or
            NaN.
        cage : pyvista.PolyData or Cage, optional
            The cage (input port 1); default: the deformation's.
        displacement, determinant, condition_number : bool
            Add the point arrays ``displacement``, ``jacobian_determinant``,
            ``condition_number``.
        normals : bool
            Deform normals through the Jacobian.
        tolerance : float, optional
            Images: largest position error of a voxel, in voxels (default:
            :data:`vhm_viz.core.volume.DEFAULT_TOLERANCE`); images are mapped through
            the volume engine's lattice (:mod:`vhm_viz.core.volume`).

        Returns
        -------
        pyvista.DataSet
            PolyData, UnstructuredGrid or StructuredGrid (images and rectilinear grids
            become structured grids).
        """
        from vhm_viz.filters import HarmonicDeformationFilter

        return _run(HarmonicDeformationFilter(), self._mesh, deformation, cage, outside,
                    Tolerance=tolerance, ComputeDisplacement=displacement,
                    ComputeJacobianDeterminant=determinant,
                    ComputeConditionNumber=condition_number, DeformNormals=normals)  # fmt: skip

    def analyze(self, deformation, *, outside: str = "error", cage=None):
        """The dataset with Jacobian quality arrays (rest geometry).

        Adds the point arrays ``jacobian_determinant``, ``condition_number``,
        ``rotation_angle`` (degrees) and ``foldover``, and for datasets with 3D cells the
        cell arrays ``cell_jacobian_determinant``, ``cell_condition_number``,
        ``cell_inverted`` and ``cell_rest_inverted``, with their counts in the field arrays
        ``vhm_cells_inverted`` and ``vhm_cells_rest_inverted`` (see
        :class:`vhm_viz.filters.JacobianAnalysisFilter`).
        """
        from vhm_viz.filters import JacobianAnalysisFilter

        return _run(JacobianAnalysisFilter(), self._mesh, deformation, cage, outside)

    def certify(self, deformation, *, max_cubes: int = 200_000, progress=None):
        """Prove that the map folds nowhere in this shape, or find where it does.

        The region is :func:`vhm_viz.region_of` of the dataset (a volume's box, a mesh's
        tetrahedra, a closed surface's solid, or the cage's interior for point clouds);
        see :func:`vhm_viz.certify_injectivity`.

        Parameters
        ----------
        deformation : Deformer or HarmonicMap
            A scene must be built and solved first (``Scene.build``, ``Scene.solve``).
        max_cubes : int
        progress : callable(fraction, message), optional

        Returns
        -------
        InjectivityCertificate
        """
        from vhm_viz.core.certify import certify_injectivity
        from vhm_viz.filters import region_of

        hm = getattr(deformation, "harmonic_map", deformation)
        region = region_of(self._mesh, getattr(hm, "cage", None))
        return certify_injectivity(deformation, region, max_cubes=max_cubes, progress=progress)

    def resample(
        self,
        deformation,
        *,
        fill_value: float = 0.0,
        output: str = "deformed",
        cage=None,
        outside: str = "error",
        interpolation: str = "linear",
        spacing=None,
        reference=None,
        tolerance: float | None = None,
    ):
        """A deformed volume on a regular grid (``pyvista.ImageData`` input only).

        See :class:`vhm_viz.filters.HarmonicResampleFilter`.

        Parameters
        ----------
        deformation : Deformer, HarmonicMap, Scene or path
        fill_value : float
            Value of the voxels without a pre-image (``vtkValidPointMask`` 0 there), held
            exactly by every array's type (an integer in its range for integer arrays).
        output : {"deformed", "input"}
            The grid holding the whole deformed volume (default) or the input grid.
        cage : pyvista.PolyData or Cage, optional
        outside : {"error", "passthrough", "nan"}
            Voxels outside the cage: refuse, leave in place, or drop.
        interpolation : {"linear", "nearest", "cubic"}
            ``"nearest"`` for label maps (values copied, integer type kept).
        spacing : (3,) float, optional
            Output voxel size of the ``"deformed"`` grid (default: the input's).
        reference : pyvista.ImageData, optional
            Resample onto this image's grid instead.
        tolerance : float, optional
            Largest position error of a voxel, in voxels (default:
            :data:`vhm_viz.core.volume.DEFAULT_TOLERANCE`).

        Returns
        -------
        pyvista.ImageData
        """
        from vhm_viz.filters import HarmonicResampleFilter

        if not isinstance(self._mesh, pv.ImageData):
            raise TypeError(f"resample needs pyvista.ImageData; got {type(self._mesh).__name__}")
        return _run(HarmonicResampleFilter(), self._mesh, deformation, cage, outside,
                    Tolerance=tolerance, FillValue=fill_value, OutputMode=output,
                    Interpolation=interpolation, OutputSpacing=spacing,
                    ReferenceImage=reference)  # fmt: skip

    def displacement_field(
        self,
        deformation,
        *,
        kind: str = "pullback",
        output: str = "deformed",
        spacing=None,
        reference=None,
        cage=None,
        outside: str = "error",
        tolerance: float | None = None,
    ):
        """The deformation of this volume as a displacement field (``pyvista.ImageData``).

        See :mod:`vhm_viz.core.displacement`; write it for SimpleITK, ANTs or 3D Slicer
        with :func:`vhm_viz.io.fields.write_displacement_field` (after
        :func:`vhm_viz.filters.resample.displacement_field_of`).

        Parameters
        ----------
        deformation : Deformer, HarmonicMap, Scene or path
        kind : {"pullback", "forward"}
            ``"pullback"``: ``f^-1(y) - y`` on the output grid of :meth:`resample` (the
            same pre-images: ITK's ``DisplacementFieldTransform`` of it reproduces the
            resampled volume). ``"forward"``: ``f(x) - x`` on this image's grid (for
            moving points and meshes).
        output, spacing, reference
            The pull-back field's grid, as for :meth:`resample`.
        cage, outside, tolerance
            As for :meth:`resample`.

        Returns
        -------
        pyvista.ImageData
            Point arrays ``vhm_displacement_field`` (3 float64 components, world units and
            frame, the active vectors; 0 where there is no pre-image or image),
            ``vtkValidPointMask`` (1 where the vector is the map's) and ``vhm_foldover``
            (pull-back: several pre-images; forward: ``det J <= 0``).
        """
        from vhm_viz.core.displacement import DisplacementField, check_field_kind
        from vhm_viz.filters import HarmonicDeformationFilter, HarmonicResampleFilter
        from vhm_viz.filters.resample import FIELD_ARRAY, image_geometry

        if not isinstance(self._mesh, pv.ImageData):
            raise TypeError(
                f"displacement_field needs pyvista.ImageData; got {type(self._mesh).__name__}"
            )
        bare = pv.ImageData()  # the grid only: no array is resampled or warped
        bare.CopyStructure(self._mesh)
        if check_field_kind(kind) == "pullback":
            out = _run(HarmonicResampleFilter(), bare, deformation, cage, outside,
                       Tolerance=tolerance, OutputMode=output, OutputSpacing=spacing,
                       ReferenceImage=reference, ComputeDisplacementField=True)  # fmt: skip
        else:
            warped = _run(HarmonicDeformationFilter(), bare, deformation, cage, outside,
                          Tolerance=tolerance, ComputeDisplacement=True,
                          ComputeJacobianDeterminant=True, DeformNormals=False)  # fmt: skip
            field = DisplacementField.forward(
                image_geometry(bare), warped.point_data["displacement"],
                warped.point_data["jacobian_determinant"],
            )  # fmt: skip
            out = bare
            out.point_data[FIELD_ARRAY] = field.vectors
            out.point_data["vtkValidPointMask"] = field.valid
            out.point_data["vhm_foldover"] = field.foldover
        out.point_data.active_vectors_name = FIELD_ARRAY
        return out


# PyVista >= 0.48 has the accessor registry; older versions simply lack ``mesh.vhm``.
if hasattr(pv, "register_dataset_accessor"):
    pv.register_dataset_accessor("vhm", pv.DataSet)(VHMAccessor)
