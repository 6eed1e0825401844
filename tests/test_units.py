"""Results do not depend on the length unit or on where the origin is.

A deformation scaled by s and translated by t must give the scaled and translated result:
``f_{s,t}(s p + t) = s f(p) + t``. Solves here converge to 1e-10 so that what is compared is
the numbers, not where two runs with different rounding happen to stop.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import data_path

from vhm_viz import examples
from vhm_viz.core.cage import Cage
from vhm_viz.core.deformer import Deformer
from vhm_viz.core.geometry import signed_volume

TIGHT = {"tolerance": 1e-10, "max_iterations": 20000}


def _moved(cage, anchors, constraints, points, scale, shift):
    """Solve the scene scaled by ``scale`` and moved by ``shift``; points mapped back."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an inward-flip warning would be the defect itself
        c = Cage(np.asarray(cage.vertices) * scale + shift, cage.faces)
    dfm = Deformer(c, anchors * scale + shift)
    kw = {
        "positions": constraints["positions"] * scale + shift,
        "targets": constraints["targets"] * scale + shift,
    }
    if len(constraints.get("jacobian_points", [])):
        kw.update(jacobian_points=constraints["jacobian_points"] * scale + shift,
                  jacobians=constraints["jacobians"])  # fmt: skip
    dfm.set_constraints(**kw)
    report = dfm.solve(**TIGHT)
    assert report.converged
    out = dfm.bind(points * scale + shift).deform()
    return (out - shift) / scale, dfm


@pytest.fixture(scope="module")
def bar():
    sc = examples.bar("bend-u", resolution=10)
    ref, dfm = _moved(sc.cage, sc.anchors, sc.constraints, sc.points, 1.0, 0.0)
    return sc, ref, dfm


@pytest.mark.parametrize(
    "scale,shift",
    [(1000.0, 0.0), (1e-3, 0.0), (1.0, 1e6), (1.0, 1e7), (1000.0, np.array([1e6, -2e6, 5e5]))],
)
def test_bar_result_is_equivariant_under_scaling_and_translation(bar, scale, shift):
    sc, ref, dfm0 = bar
    out, dfm = _moved(sc.cage, sc.anchors, sc.constraints, sc.points, scale, shift)
    diag = float(np.linalg.norm(np.ptp(sc.points, axis=0)))
    # the smoothness weight lambda scales with the length unit: the rows it weighs
    # (1/length) and the dimensionless ones stay in proportion
    print(f"scale {scale:g}, shift {shift}: {np.abs(out - ref).max() / diag:.1e} of the diagonal")
    assert np.abs(out - ref).max() <= 1e-6 * diag
    assert dfm.lambda_ == pytest.approx(scale * dfm0.lambda_, rel=1e-6)
    assert dfm.last_report.final_energy == pytest.approx(dfm0.last_report.final_energy, rel=1e-6)


@pytest.mark.data
@pytest.mark.parametrize("shift", [1e6, 1e7])
def test_armadillo_cage_far_from_the_origin_behaves_as_at_the_origin(shift):
    from vhm_viz.io import read_cage, read_dataset

    cage = read_cage(data_path("armadillo", "cage_216f.obj"))
    pts = np.asarray(read_dataset(data_path("armadillo", "armadillo_43k.obj")).points)
    # far from the origin the signed volume must not lose its digits to cancellation, or
    # the cage is judged inward, flipped, and every anchor falls outside
    moved = np.asarray(cage.vertices) + shift
    assert signed_volume(moved, cage.faces) == pytest.approx(cage.volume, rel=1e-6)
    rng = np.random.default_rng(3)
    anchors = pts[rng.choice(len(pts), 12, replace=False)]
    constraints = {"positions": pts[[0, 1000]], "targets": pts[[0, 1000]] + [0.0, 0.02, 0.0]}
    ref, _ = _moved(cage, anchors, constraints, pts, 1.0, 0.0)
    out, _ = _moved(cage, anchors, constraints, pts, 1.0, shift)
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    print(f"Armadillo shift {shift:g}: {np.abs(out - ref).max() / diag:.1e} of the diagonal")
    assert np.abs(out - ref).max() <= 1e-6 * diag
