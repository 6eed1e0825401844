"""Numeric core of vhm_viz: pure numpy/scipy/numba, no VTK, PyVista or Qt.

Everything here takes and returns plain arrays so it runs anywhere, including inside
ParaView's own Python.
"""

import os

#: OpenMP's wait policy, unless the process was given one: the compiled kernels alternate
#: numba's OpenMP loops with loops on their own row threads
#: (:mod:`vhm_viz.core.row_threads`). Spinning between loops (OpenMP's default), the
#: OpenMP threads would take the cores from the row threads, and from other processes on
#: a shared machine; asleep, they cost a wake-up per loop. Read by OpenMP when it starts,
#: at the first parallel loop of the process, so it is set here, before any kernel runs.
OPENMP_WAIT_POLICY = "passive"
os.environ.setdefault("OMP_WAIT_POLICY", OPENMP_WAIT_POLICY)
