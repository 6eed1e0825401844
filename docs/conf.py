"""Sphinx configuration: the vhm_viz user guide, API reference and example gallery.

Build with ``sphinx-build -W -b html docs docs/_build/html`` (``pip install -e .[docs]``).
The gallery's examples run off screen; PyVista's scraper collects their pictures.
"""

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba_cache"))

import pyvista  # noqa: E402

import vhm_viz  # noqa: E402

# Examples that read the real scans run only where the data is (as the tests skip)
try:
    HAVE_DATA = (vhm_viz.examples.data_dir() / "volumes" / "headsq_64x64x93.vti").exists()
except vhm_viz.examples.DataNotFound:
    HAVE_DATA = False
if not HAVE_DATA:
    print("docs: no ../shared/data (or $VHM_VIZ_DATA): the scan example is left out")

pyvista.OFF_SCREEN = True
pyvista.BUILDING_GALLERY = True
pyvista.set_plot_theme("document")
pyvista.global_theme.window_size = [800, 600]

project = "vhm_viz"
author = "vhm_viz developers"
copyright = "2026, vhm_viz developers"  # noqa: A001 - Sphinx's name
release = version = vhm_viz.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "examples/README.rst", "gallery/*.ipynb", "**.codeobj.json"]
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath"]

autodoc_default_options = {"members": True, "show-inheritance": False}
autodoc_member_order = "bysource"
autodoc_typehints = "none"  # the numpydoc Parameters sections give types, shapes and units
napoleon_numpy_docstring = True
napoleon_google_docstring = False
napoleon_use_rtype = False
# "Attributes" sections as fields, so that a documented property is not described twice
napoleon_use_ivar = True

sphinx_gallery_conf = {
    "examples_dirs": "examples",
    "gallery_dirs": "gallery",
    # only plot_*.py run; the ParaView script is shown, not executed (it needs pvpython)
    "filename_pattern": r"/plot_",
    "ignore_pattern": r"__init__\.py" + ("" if HAVE_DATA else r"|plot_03_resample_scan\.py"),
    "image_scrapers": ("pyvista", "matplotlib"),
    "within_subsection_order": "FileNameSortKey",
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "plot_gallery": "True",
}

html_theme = "pydata_sphinx_theme"
html_title = f"vhm_viz {release}"
html_theme_options = {"navigation_with_keys": False, "show_toc_level": 2}
html_static_path = []
