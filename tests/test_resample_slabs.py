"""What a resample writes for each output voxel, slab by slab, against independent references.

The volume engine finishes each slab of pulled-back voxels in one compiled pass per
array on its row threads (the masks, the counts, the fill and the sampling). Here its
output on a small grid, cut into many slabs, is checked against the pre-images the
engine reports for the same voxels (:meth:`VolumeDeformation.preimages`) and SciPy's
trilinear interpolation at them: every component of a multi-component array, the masks
and their counts, the fill, and an integer array's rounding.
"""

from __future__ import annotations

import numpy as np
from conftest import box_cage
from scipy.ndimage import map_coordinates

from vhm_viz import Cage, HarmonicMap
from vhm_viz.core.image import ImageGeometry
from vhm_viz.core.volume import VolumeDeformation


def test_every_voxel_holds_its_preimages_interpolation_and_the_counts_its_masks():
    geo = ImageGeometry((0.0, 0.0, 0.0), (1.0, 1.0, 1.25), (36, 34, 30))
    # the volume sticks out of the cage: voxels left in place, and pre-images next to the
    # cage that the winding number confirms
    cage = Cage(*box_cage((6.0, 5.0, 5.0), (29.0, 28.0, 31.0), 2))
    rng = np.random.default_rng(5)
    z = np.array(HarmonicMap.identity(cage).coefficients)
    z += 0.01 * cage.diagonal * rng.standard_normal(z.shape)
    vol = VolumeDeformation(HarmonicMap(cage, z), geo, outside="passthrough",
                            memory_budget=200_000)  # fmt: skip
    rgb = rng.standard_normal((geo.n_points, 3))
    labels = rng.integers(-900, 900, geo.n_points).astype(np.int16) * 40
    res = vol.resample({"rgb": rgb, "labels": labels, "f": labels.astype(np.float64)},
                       geometry=geo, fill_value=-7.0)  # fmt: skip
    assert vol.slab_count > 4  # several slabs, of whole rows

    nx, ny, nz = geo.dimensions
    ijk = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"),
                   axis=-1).transpose(2, 1, 0, 3).reshape(-1, 3)  # fmt: skip
    u, kind, fold = vol.preimages(geo, ijk)
    found = kind > 0
    np.testing.assert_array_equal(res.valid, found)
    np.testing.assert_array_equal(res.foldover, fold)
    assert res.counts == {"voxels": geo.n_points, "valid": int(found.sum()),
                          "identity": int((kind == 3).sum()),
                          "foldover": int(fold.sum())}  # fmt: skip
    assert 0 < res.counts["identity"] < res.counts["valid"] < geo.n_points

    # trilinear at the pre-image, the grid's boundary values within the half-voxel border
    at = u[found][:, ::-1].T  # (k, j, i)
    for c in range(3):
        ref = map_coordinates(rgb[:, c].reshape(nz, ny, nx), at, order=1, mode="nearest")
        np.testing.assert_allclose(res.arrays["rgb"][found, c], ref, rtol=0, atol=1e-12)
    assert (res.arrays["rgb"][~found] == -7.0).all()
    ref = map_coordinates(labels.astype(np.float64).reshape(nz, ny, nx), at, order=1,
                          mode="nearest")  # fmt: skip
    np.testing.assert_allclose(res.arrays["f"][found], ref, rtol=0, atol=1e-9)
    # the integer array: the same values rounded (and the fill) in its own type
    assert res.arrays["labels"].dtype == np.int16
    np.testing.assert_array_equal(res.arrays["labels"], np.rint(res.arrays["f"]).astype(np.int16))
