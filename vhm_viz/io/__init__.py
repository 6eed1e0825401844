"""The one place that reads and writes files: datasets, cages, rigidity lines, anchors, text.

Everything that turns a path into numbers (or numbers into a file) lives here, so that the
command line, the explorer, scenes, the automatic cage and the filters agree on what a file
means:

* :func:`read_dataset`, :func:`write_dataset` -- any mesh, tet mesh, point cloud or
  volume, as a PyVista dataset (:mod:`~vhm_viz.io.datasets`);
* :func:`read_cage`, :func:`cage_from_dataset`, :func:`cage_to_polydata`,
  :func:`write_cage` -- the one :class:`~vhm_viz.core.cage.Cage`, from and to files and
  VTK surfaces (VTK only, no PyVista: this path runs inside ParaView)
  (:mod:`~vhm_viz.io.cages`);
* :func:`read_rigidity_lines` (:func:`read_polylines`, :func:`read_tgf`, VTK polylines) --
  rigidity lines for anchors (:mod:`~vhm_viz.io.rigidity`);
* :func:`read_anchors`, :func:`write_anchors` -- anchor files (what ``vhm-viz anchors``
  writes);
* :func:`write_text`, :func:`json_text` -- atomic text, compact JSON (one point per line);
  :func:`atomic_outputs` -- several files that appear together or not at all;
  :func:`refuse_inputs` -- the one guard against writing over an input, the data files
  its header names included (:mod:`~vhm_viz.io.guard`).

Which suffix is which format, and what each reads and writes, is one table
(:mod:`~vhm_viz.io.registry`): :data:`DATASET_SUFFIXES`, :data:`CAGE_SUFFIXES`,
:func:`output_suffixes`, :func:`is_image_format` and :func:`keeps_arrays` are queries of
it. One module per format family does the work: :mod:`~vhm_viz.io.vtk_files` (VTK's
formats), :mod:`~vhm_viz.io.mesh_files` (PLY, STL, OFF, MEDIT, Gmsh, point lists),
:mod:`~vhm_viz.io.medical` (MetaImage, NIfTI), :mod:`~vhm_viz.io.nrrd` and
:mod:`~vhm_viz.io.dicom` (through SimpleITK, :mod:`~vhm_viz.io.itk_images`),
:mod:`~vhm_viz.io.legacy_volumes` (SLC); :mod:`~vhm_viz.io.isolated` runs library readers
in a child process.

Writers take the destination first: ``write_*(path, what)``.
"""

from __future__ import annotations

from vhm_viz.atomic import OverwriteError, same_file
from vhm_viz.atomic import atomic_directory as atomic_outputs
from vhm_viz.io.anchors import read_anchors, write_anchors
from vhm_viz.io.cages import cage_from_dataset, cage_to_polydata, cell_types, read_cage, write_cage
from vhm_viz.io.datasets import dataset_files, read_dataset, write_dataset
from vhm_viz.io.errors import ReadError
from vhm_viz.io.guard import refuse_inputs
from vhm_viz.io.registry import (
    DICOM_FOLDER,
    FORMATS,
    Format,
    cage_suffixes,
    dataset_suffixes,
    format_of,
    image_suffixes,
    is_image_format,
    keeps_arrays,
    output_suffixes,
    suffix_of,
)
from vhm_viz.io.rigidity import read_polylines, read_rigidity_lines, read_tgf
from vhm_viz.io.text import JSONTextError, json_text, parse_json, write_text

#: Dataset formats :func:`read_dataset` reads (VTK's readers, meshio for MEDIT and Gmsh, OFF and
#: plain point lists parsed here). ``.nii.gz`` counts as one suffix.
DATASET_SUFFIXES = dataset_suffixes()
#: Cage formats :func:`read_cage` reads.
CAGE_SUFFIXES = cage_suffixes()

__all__ = [
    "DATASET_SUFFIXES",
    "CAGE_SUFFIXES",
    "DICOM_FOLDER",
    "FORMATS",
    "Format",
    "format_of",
    "output_suffixes",
    "image_suffixes",
    "is_image_format",
    "keeps_arrays",
    "ReadError",
    "read_dataset",
    "write_dataset",
    "dataset_files",
    "read_cage",
    "cage_from_dataset",
    "cage_to_polydata",
    "write_cage",
    "read_polylines",
    "read_tgf",
    "read_rigidity_lines",
    "read_anchors",
    "write_anchors",
    "write_text",
    "atomic_outputs",
    "refuse_inputs",
    "same_file",
    "OverwriteError",
    "json_text",
    "parse_json",
    "JSONTextError",
    "suffix_of",
    "cell_types",
]
