"""Figures: off-screen rendering to non-blank PNGs of the expected size and colours."""

from __future__ import annotations

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
pytest.importorskip("matplotlib")

from conftest import box_cage  # noqa: E402

from vhm_viz import Cage, HarmonicMap, plotting  # noqa: E402


def _png(path):
    from matplotlib.image import imread

    img = imread(str(path))
    return img[..., :3] if img.ndim == 3 else img


def _bent_map():
    v, f = box_cage((-0.7, -0.7, -0.2), (0.7, 0.7, 2.2), 2)
    cage = Cage(v, f)
    tgt = cage.vertices.copy()
    tgt[:, 0] += 0.3 * (tgt[:, 2] / 2.2) ** 2  # bend the top along +x
    return HarmonicMap.from_target_cage(cage, tgt)


@pytest.fixture(scope="module")
def bar_and_map():
    bar = pv.Box(bounds=(-0.5, 0.5, -0.5, 0.5, 0.0, 2.0), level=6).triangulate().clean()
    return bar, _bent_map()


def test_jacobian_slice_identity_and_bend(bar_and_map):
    bar, hm = bar_and_map
    ident = HarmonicMap.identity(hm.cage)
    sl = plotting.jacobian_slice(bar, ident, normal=(0, 1, 0), resolution=60)
    assert sl.n_points > 100
    np.testing.assert_allclose(sl.point_data["jacobian_determinant"], 1.0, atol=1e-9)
    np.testing.assert_allclose(sl.point_data["condition_number"], 1.0, atol=1e-8)
    np.testing.assert_allclose(sl.points, sl.point_data["rest_points"], atol=1e-12)
    # slice points lie in the plane and inside the bar
    rest = np.asarray(sl.point_data["rest_points"])
    np.testing.assert_allclose(rest[:, 1], bar.center[1], atol=1e-9)
    assert rest[:, 0].min() >= -0.5 - 1e-6 and rest[:, 0].max() <= 0.5 + 1e-6

    sl = plotting.jacobian_slice(bar, hm, resolution=60)
    np.testing.assert_allclose(sl.field_data["slice_normal"], [0, 1, 0])  # y barely moves
    rest = np.asarray(sl.point_data["rest_points"])
    np.testing.assert_allclose(sl.points, hm.map(rest), atol=1e-12)
    np.testing.assert_allclose(
        sl.point_data["jacobian_determinant"], np.linalg.det(hm.jacobian(rest)), rtol=1e-10
    )


def test_jacobian_slice_of_tets_and_volume(bar_and_map):
    _, hm = bar_and_map
    img = pv.ImageData(dimensions=(8, 8, 16), spacing=(0.14, 0.14, 0.14), origin=(-0.5, -0.5, 0))
    sl = plotting.jacobian_slice(img, hm, normal=(0, 1, 0))
    assert sl.n_points > 50 and "condition_number" in sl.point_data
    tets = img.cast_to_unstructured_grid().triangulate()
    sl2 = plotting.jacobian_slice(tets, hm, normal=(0, 1, 0))
    assert sl2.n_points > 50


def test_figure4_png(bar_and_map, tmp_path):
    bar, hm = bar_and_map
    sl = plotting.jacobian_slice(bar, hm, resolution=80)
    path = tmp_path / "fig4.png"
    pl = plotting.figure4(sl, filename=path, window_size=(900, 400))
    assert isinstance(pl, pv.Plotter)
    pl.close()
    img = _png(path)
    assert img.shape[:2] == (400, 900)
    assert img.std() > 0.05  # not blank
    left, right = img[:, :450], img[:, 450:]
    # det J panel uses a diverging blue-red map: reddish and bluish pixels; cond J uses viridis
    red = (left[..., 0] > 0.6) & (left[..., 2] < 0.5)
    blue = (left[..., 2] > 0.6) & (left[..., 0] < 0.6)
    assert red.sum() + blue.sum() > 500
    purple_green = (right[..., 1] > right[..., 0] + 0.1) | (
        (right[..., 2] > 0.3) & (right[..., 1] < 0.3)
    )
    assert purple_green.sum() > 500
    white = (img > 0.95).all(axis=-1)
    assert 0.2 < white.mean() < 0.98  # white background around coloured slices


def test_figure12_and_energy_png(tmp_path):
    rng = np.random.default_rng(0)
    fig = plotting.figure12(
        {"rigid": 1 + rng.gamma(2, 0.05, 5000), "similar": 1 + rng.gamma(2, 0.03, 5000)},
        filename=tmp_path / "h.png",
        figsize=(5, 3),
        dpi=100,
    )
    from matplotlib.figure import Figure

    assert isinstance(fig, Figure)
    img = _png(tmp_path / "h.png")
    assert img.shape[:2] == (300, 500)
    assert img.std() > 0.05
    blueish = (img[..., 2] > img[..., 0] + 0.2).sum()
    orangeish = (img[..., 0] > img[..., 2] + 0.3).sum()
    assert blueish > 200 and orangeish > 200

    class Report:
        def __init__(self, e):
            self.energy = np.asarray(e)

    fig = plotting.energy_plot(
        [Report([5.0, 2.0, 1.0]), Report([1.0, 0.5, 0.4])],
        filename=tmp_path / "e.png",
        figsize=(4, 3),
        dpi=80,
    )
    line = fig.axes[0].lines[0]
    np.testing.assert_array_equal(line.get_ydata(), [5.0, 2.0, 1.0, 0.5, 0.4])
    img = _png(tmp_path / "e.png")
    assert img.shape[:2] == (240, 320) and img.std() > 0.05
    fig = plotting.energy_plot({"a": np.array([3.0, 1.0]), "b": np.array([2.0, 1.5])})
    assert len(fig.axes[0].lines) == 2
