"""The volume engine's results do not depend on how many threads compute them.

The compiled kernels hand out their work items (output rows, leaves) dynamically: whichever
thread is free takes the next ones (:mod:`vhm_viz.core.work_items`), and the lattice's
masks are made in blocks shared by threads. Each item's arithmetic is the same whoever
computes it, so one thread and several give the same bits.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest
from conftest import box_cage

from vhm_viz import Cage, HarmonicMap
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.volume import VolumeDeformation

pytestmark = pytest.mark.skipif(
    numba.config.NUMBA_NUM_THREADS < 2, reason="numba was started with a single thread"
)


def _run(threads: int, hm, geo, values):
    """Warp, Jacobians, resample and pre-images with ``threads`` threads."""
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        warp = VolumeDeformation(hm, geo, pre_images=False)
        vol = VolumeDeformation(hm, geo)
        res = vol.resample({"v": values}, displacement=True)
        return {
            "warp": warp.warp(),
            "jacobians": warp.jacobians(),
            "lattice_f": vol.lattice.data,
            "resampled": res.arrays["v"],
            "valid": res.valid,
            "foldover": res.foldover,
            "displacement": res.displacement,
        }
    finally:
        numba.set_num_threads(before)


def test_one_thread_and_several_give_the_same_bits():
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.25), (48, 40, 36))
    lo, hi = geo.origin, geo.points(np.array([geo.dimensions]) - 1.0)[0]
    pad = 0.02 * (hi - lo).max()
    cage = Cage(*box_cage(lo - pad, hi + pad, 2))
    rng = np.random.default_rng(7)
    z = np.array(HarmonicMap.identity(cage).coefficients)
    z += 0.004 * cage.diagonal * rng.standard_normal(z.shape)
    hm = HarmonicMap(cage, z)
    values = rng.random(geo.n_points).astype(np.float32)
    one = _run(1, hm, geo, values)
    several = _run(min(4, numba.config.NUMBA_NUM_THREADS), hm, geo, values)
    assert one["valid"].sum() > 0.5 * geo.n_points  # a real pull-back, not an empty one
    for name, array in one.items():
        np.testing.assert_array_equal(several[name], array, err_msg=name)
