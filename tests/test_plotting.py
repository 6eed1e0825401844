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


def _stretched_map():
    """Bent and stretched along z, non-uniformly: det J from about 1.2 to 1.8."""
    v, f = box_cage((-0.7, -0.7, -0.2), (0.7, 0.7, 2.2), 2)
    cage = Cage(v, f)
    tgt = cage.vertices.copy()
    tgt[:, 2] *= 1 + 0.4 * (tgt[:, 2] + 0.2) / 2.4
    tgt[:, 0] += 0.3 * (tgt[:, 2] / 2.2) ** 2
    return HarmonicMap.from_target_cage(cage, tgt)


def _fd_jacobian(hm, points, h=1e-5):
    """Central finite differences of the mapped positions, ``J[k, i, j] = d f_i / d x_j``."""
    p = np.asarray(points, dtype=np.float64)
    cols = []
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        cols.append((hm.map(p + e) - hm.map(p - e)) / (2 * h))
    return np.stack(cols, axis=2)


def _det_cond(jac):
    sv = np.linalg.svd(jac, compute_uv=False)
    return np.linalg.det(jac), sv[:, 0] / sv[:, 2]


def _colormap_positions(pixels, cmap, tol=4 / 255):
    """For each RGB pixel, the position in [0, 1] of the nearest colour of ``cmap`` and
    whether it is within ``tol`` of it (anti-aliased edges and text are not)."""
    from matplotlib import colormaps

    t = np.linspace(0.0, 1.0, 2049)
    colours = colormaps[cmap](t)[:, :3]
    unique, inverse = np.unique(pixels, axis=0, return_inverse=True)
    d = np.linalg.norm(unique[:, None, :] - colours[None], axis=2)
    k = d.argmin(axis=1)
    inverse = inverse.ravel()
    return t[k][inverse], (d[np.arange(len(unique)), k] < tol)[inverse]


def _coloured(region):
    """The saturated pixels of an image region (neither white/grey background nor text)."""
    px = region.reshape(-1, 3)
    return px[px.max(axis=1) - px.min(axis=1) > 0.05]


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


@pytest.mark.parametrize("kind", ["image", "tets"])
def test_jacobian_slice_of_tets_and_volume(bar_and_map, kind):
    _, hm = bar_and_map
    img = pv.ImageData(dimensions=(8, 8, 16), spacing=(0.14, 0.14, 0.14), origin=(-0.5, -0.5, 0))
    data = img if kind == "image" else img.cast_to_unstructured_grid().triangulate()
    assert kind == "image" or (data.celltypes == pv.CellType.TETRA).all()
    sl = plotting.jacobian_slice(data, hm, normal=(0, 1, 0))
    assert sl.n_points > 50
    rest = np.asarray(sl.point_data["rest_points"])
    # the slice is the plane y = centre through the data, mapped by the deformation
    np.testing.assert_allclose(rest[:, 1], img.center[1], atol=1e-9)
    lo, hi = np.asarray(img.bounds[0::2]), np.asarray(img.bounds[1::2])
    assert (rest >= lo - 1e-9).all() and (rest <= hi + 1e-9).all()
    # it spans the data's extent in the plane (x and z)
    np.testing.assert_allclose(rest[:, [0, 2]].min(axis=0), lo[[0, 2]], atol=1e-9)
    np.testing.assert_allclose(rest[:, [0, 2]].max(axis=0), hi[[0, 2]], atol=1e-9)
    np.testing.assert_allclose(sl.points, hm.map(rest), atol=1e-12)
    det, cond = _det_cond(_fd_jacobian(hm, rest))
    assert np.ptp(det) > 0.01  # the bend changes volumes
    np.testing.assert_allclose(sl.point_data["jacobian_determinant"], det, rtol=1e-7)
    np.testing.assert_allclose(sl.point_data["condition_number"], cond, rtol=1e-7)


@pytest.mark.parametrize("which", ["bend", "stretch"])
def test_figure4_colours_are_the_det_and_cond_of_the_map(bar_and_map, tmp_path, which):
    bar, bent = bar_and_map
    hm = bent if which == "bend" else _stretched_map()
    sl = plotting.jacobian_slice(bar, hm, resolution=80)
    # the data's ranges, computed independently (finite differences of the positions)
    det, cond = _det_cond(_fd_jacobian(hm, sl.point_data["rest_points"]))
    half = max(0.5, np.abs(det - 1).max())
    det_range = (1 - half, 1 + half)
    cond_range = (1.0, max(2.0, np.percentile(cond, 99)))
    if which == "stretch":
        assert half > 0.7  # the range comes from the data, not from the 0.5 floor

    path = tmp_path / "fig4.png"
    pl = plotting.figure4(sl, filename=path, window_size=(900, 400))
    bars = {k: v.GetLookupTable().GetRange() for k, v in pl.scalar_bars.items()}
    pl.close()
    assert set(bars) == {"det J", "cond J"}
    np.testing.assert_allclose(bars["det J"], det_range, rtol=1e-7)
    np.testing.assert_allclose(bars["cond J"], cond_range, rtol=1e-7)

    img = _png(path)
    assert img.shape[:2] == (400, 900)
    # The slice above the colour bars (whose labels start at 85% of the height; the bars
    # hide the bottom of the slice): its colours are the colour maps at the data's values.
    # Pixels interpolate between vertices and the lowest or highest value can sit at a
    # hidden vertex, so the pixels' range lies within the data's normalised range (to the
    # 256-colour table's step) and covers most of it.
    for col, cmap, values, (lo, hi) in (
        (slice(0, 450), "coolwarm", det, det_range),
        (slice(450, 900), "viridis", cond, cond_range),
    ):
        t, ok = _colormap_positions(_coloured(img[:336, col]), cmap)
        assert ok.sum() > 5000 and ok.mean() > 0.95
        e_lo, e_hi = np.clip((np.array([values.min(), values.max()]) - lo) / (hi - lo), 0, 1)
        assert e_lo - 0.006 <= t[ok].min() and t[ok].max() <= e_hi + 0.006
        assert t[ok].max() - t[ok].min() > 0.75 * (e_hi - e_lo)
        # the colour bar below shows the whole map
        t, ok = _colormap_positions(_coloured(img[336:, col]), cmap)
        assert t[ok].min() < 0.01 and t[ok].max() > 0.99


def test_figure4_of_a_uniform_stretch_is_one_colour_per_panel(bar_and_map, tmp_path):
    from matplotlib import colormaps

    bar, bent = bar_and_map
    hm = HarmonicMap.affine(bent.cage, np.diag([1.3, 1.0, 1.0]), [0.1, 0.0, 0.0])
    sl = plotting.jacobian_slice(bar, hm, normal=(0, 1, 0), resolution=60)
    path = tmp_path / "uniform.png"
    plotting.figure4(sl, filename=path, window_size=(600, 300)).close()
    img = _png(path)
    assert img.shape[:2] == (300, 600)
    # det J = 1.3 in (0.5, 1.5); cond J = 1.3 in (1, 2)
    for col, expected in (
        (slice(0, 300), colormaps["coolwarm"](0.8)[:3]),
        (slice(300, 600), colormaps["viridis"](0.3)[:3]),
    ):
        panel = img[:225, col].reshape(-1, 3)
        hit = np.abs(panel - expected).max(axis=1) < 3 / 255
        assert hit.mean() > 0.2  # the slice fills a good part of its panel in that colour
        white = (panel > 0.98).all(axis=1)
        assert (hit | white).mean() > 0.97  # and nothing else but the background


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
