"""SciPy's compiled extensions, loaded without their subpackage's ``__init__``.

Importing a SciPy subpackage runs its ``__init__``, which imports every one of its
submodules and, since SciPy 1.15, its array-API layer (which touches ``numpy.f2py``,
``numpy.testing`` and ``numpy.ma``): far more than the compiled routines a command calls.
``scipy.linalg``'s LAPACK wrappers (:mod:`vhm_viz.core.lapack`) and ``scipy.spatial``'s
KD-tree (:func:`kd_tree`) are loaded here by file instead; once the subpackage is
imported, its real modules are used. A Cython extension loaded by file is the module the
subpackage later imports (the same module object), so its classes are the same classes.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import os
import sys
from functools import cache

__all__ = ["extension", "kd_tree"]


def extension(package: str, name: str):
    """SciPy's compiled ``<package>.<name>``, loaded without ``<package>``'s ``__init__``.

    Parameters
    ----------
    package : str
        A SciPy subpackage (``"scipy.linalg"``).
    name : str
        The compiled module in it (``"_flapack"``).

    Returns
    -------
    module
        The real submodule when ``package`` is already imported, or when the extension's
        file is not where a SciPy installation puts it.
    """
    full = f"{package}.{name}"
    if full in sys.modules or package in sys.modules:
        return importlib.import_module(full)
    scipy_spec = importlib.util.find_spec("scipy")
    folders = scipy_spec.submodule_search_locations if scipy_spec is not None else None
    sub = package.removeprefix("scipy.").replace(".", os.sep)
    for folder in folders or ():
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = os.path.join(folder, sub, name + suffix)
            if os.path.isfile(path):
                loader = importlib.machinery.ExtensionFileLoader(full, path)
                spec = importlib.util.spec_from_file_location(full, path, loader=loader)
                module = importlib.util.module_from_spec(spec)
                loader.exec_module(module)
                return module
    return importlib.import_module(full)


@cache
def _ckdtree():
    return extension("scipy.spatial", "_ckdtree")


def kd_tree(data, **options):
    """``scipy.spatial.cKDTree(data, **options)``, without importing ``scipy.spatial``.

    Parameters
    ----------
    data : (n, k) array_like
        The points.
    **options
        cKDTree's (``leafsize``, ``balanced_tree``, ...).

    Returns
    -------
    scipy.spatial.cKDTree
    """
    return _ckdtree().cKDTree(data, **options)
