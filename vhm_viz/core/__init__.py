"""Numeric core of vhm_viz: pure numpy/scipy/numba, no VTK, PyVista or Qt.

Everything here takes and returns plain arrays so it runs anywhere, including inside
ParaView's own Python.
"""
