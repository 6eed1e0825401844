"""Figures: off-screen rendering to non-blank PNGs of the expected size and colours."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
pytest.importorskip("matplotlib")

from conftest import box_cage, fd_jacobian  # noqa: E402

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
    """Bent and stretched along z, non-uniformly: det J up to about 3 (beyond the range's
    floor of (1/2, 2))."""
    v, f = box_cage((-0.7, -0.7, -0.2), (0.7, 0.7, 2.2), 2)
    cage = Cage(v, f)
    tgt = cage.vertices.copy()
    tgt[:, 2] *= 1 + 1.2 * (tgt[:, 2] + 0.2) / 2.4
    tgt[:, 0] += 0.3 * (tgt[:, 2] / 2.2) ** 2
    return HarmonicMap.from_target_cage(cage, tgt)


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
    det, cond = _det_cond(fd_jacobian(hm.map, rest))
    assert np.ptp(det) > 0.01  # the bend changes volumes
    np.testing.assert_allclose(sl.point_data["jacobian_determinant"], det, rtol=1e-7)
    np.testing.assert_allclose(sl.point_data["condition_number"], cond, rtol=1e-7)


def _log_det_range(det):
    """The det J colour range by the convention, recomputed: (1/r, r), r from the 99th
    percentile of |log det| of the positive values, at least 2."""
    det = det[det > 0]
    r = max(2.0, float(np.exp(np.percentile(np.abs(np.log(det)), 99))))
    return (1 / r, r)


@pytest.mark.parametrize("which", ["bend", "stretch"])
def test_figure4_colours_are_the_det_and_cond_of_the_map(bar_and_map, tmp_path, which):
    bar, bent = bar_and_map
    hm = bent if which == "bend" else _stretched_map()
    sl = plotting.jacobian_slice(bar, hm, resolution=80)
    # the data's ranges, computed independently (finite differences of the positions)
    det, cond = _det_cond(fd_jacobian(hm.map, sl.point_data["rest_points"]))
    det_range = _log_det_range(det)
    cond_range = (1.0, max(2.0, np.percentile(cond, 99)))
    if which == "stretch":
        assert det_range[1] > 2.0  # the range comes from the data, not from the floor of 2

    path = tmp_path / "fig4.png"
    pl = plotting.figure4(sl, filename=path, window_size=(900, 400))
    luts = {k: v.GetLookupTable() for k, v in pl.scalar_bars.items()}
    bars = {k: lut.GetRange() for k, lut in luts.items()}
    log_scales = {k: bool(lut.GetScale()) for k, lut in luts.items()}
    pl.close()
    assert set(bars) == {"det J", "cond J"}
    np.testing.assert_allclose(bars["det J"], det_range, rtol=1e-7)
    np.testing.assert_allclose(bars["cond J"], cond_range, rtol=1e-7)
    assert log_scales == {"det J": True, "cond J": False}

    img = _png(path)
    assert img.shape[:2] == (400, 900)
    # The slice above the colour bars (whose labels start at 80% of the height; the bars
    # hide the bottom of the slice): its colours are the colour maps at the data's values,
    # det J by log det. Pixels interpolate between vertices and the lowest or highest value
    # can sit at a hidden vertex, so the pixels' range lies within the data's normalised
    # range (to the 256-colour table's step) and covers most of it.
    for col, cmap, values, (lo, hi), scale in (
        (slice(0, 450), "coolwarm", det, det_range, np.log),
        (slice(450, 900), "viridis", cond, cond_range, lambda x: x),
    ):
        t, ok = _colormap_positions(_coloured(img[:315, col]), cmap)
        assert ok.sum() > 5000 and ok.mean() > 0.95
        ends = (scale(np.array([values.min(), values.max()])) - scale(lo)) / (scale(hi) - scale(lo))
        e_lo, e_hi = np.clip(ends, 0, 1)
        assert e_lo - 0.006 <= t[ok].min() and t[ok].max() <= e_hi + 0.006
        assert t[ok].max() - t[ok].min() > 0.75 * (e_hi - e_lo)
        # the colour bar below shows the whole map
        t, ok = _colormap_positions(_coloured(img[340:, col]), cmap)
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
    # det J = 1.3 on the log scale of (1/2, 2); cond J = 1.3 in (1, 2)
    for col, expected in (
        (slice(0, 300), colormaps["coolwarm"](np.log(1.3 / 0.5) / np.log(4.0))[:3]),
        (slice(300, 600), colormaps["viridis"](0.3)[:3]),
    ):
        panel = img[:225, col].reshape(-1, 3)
        hit = np.abs(panel - expected).max(axis=1) < 3 / 255
        assert hit.mean() > 0.2  # the slice fills a good part of its panel in that colour
        white = (panel > 0.98).all(axis=1)
        assert (hit | white).mean() > 0.97  # and nothing else but the background


def _folding_map():
    """The box cage's top face pushed down to its bottom: the bar's top folds over."""
    v, f = box_cage((-0.7, -0.7, -0.2), (0.7, 0.7, 2.2), 2)
    cage = Cage(v, f)
    tgt = cage.vertices.copy()
    tgt[tgt[:, 2] > 2.0, 2] = 0.0
    return HarmonicMap.from_target_cage(cage, tgt)


def test_figure4_draws_folds_in_the_fold_colour(bar_and_map, tmp_path):
    from vhm_viz.colours import FOLD_COLOUR

    bar, bent = bar_and_map
    fold = np.asarray(FOLD_COLOUR)
    # a reflection folds everywhere (det J = -1): the whole det J slice is the fold colour,
    # and the cond J slice (cond = 1) the bottom of viridis
    hm = HarmonicMap.affine(bent.cage, np.diag([-1.0, 1.0, 1.0]), [0.0, 0.0, 0.0])
    sl = plotting.jacobian_slice(bar, hm, normal=(0, 1, 0), resolution=60)
    path = tmp_path / "mirror.png"
    plotting.figure4(sl, filename=path, window_size=(600, 300)).close()
    img = _png(path)
    panel = img[:225, :300].reshape(-1, 3)
    hit = np.abs(panel - fold).max(axis=1) < 3 / 255
    white = (panel > 0.98).all(axis=1)
    assert hit.mean() > 0.2 and (hit | white).mean() > 0.97

    # a map that folds in part: black where det J <= 0, the ramp elsewhere; the range is
    # set by the positive values alone
    hm = _folding_map()
    sl = plotting.jacobian_slice(bar, hm, normal=(0, 1, 0), resolution=80)
    det, _ = _det_cond(fd_jacobian(hm.map, sl.point_data["rest_points"]))
    assert 0.1 < (det <= 0).mean() < 0.9
    path = tmp_path / "fold.png"
    pl = plotting.figure4(sl, filename=path, window_size=(900, 400))
    det_bar = pl.scalar_bars["det J"].GetLookupTable()
    np.testing.assert_allclose(det_bar.GetRange(), _log_det_range(det), rtol=1e-6)
    np.testing.assert_allclose(det_bar.GetBelowRangeColor()[:3], fold)
    # the swatch is drawn, unlabelled: a horizontal bar's label would be drawn over it (the
    # panel's heading says what black is)
    assert pl.scalar_bars["det J"].GetDrawBelowRangeSwatch()
    assert pl.scalar_bars["det J"].GetBelowRangeAnnotation() == ""
    assert not pl.scalar_bars["cond J"].GetDrawBelowRangeSwatch()  # cond J has no folds
    pl.close()
    img = _png(path)
    black = lambda region: (np.abs(region - fold).max(axis=-1) < 3 / 255).sum()  # noqa: E731
    assert black(img[40:315, :450]) > 2000  # the folded sheet, drawn in the fold colour
    assert black(img[40:315, 450:]) == 0  # cond J has no fold colour
    t, ok = _colormap_positions(_coloured(img[40:315, :450]), "coolwarm")
    assert ok.sum() > 5000


def test_injectivity_figure_uses_the_det_convention(bar_and_map, tmp_path):
    from vhm_viz.colours import FOLD_COLOUR

    class NoFolds:  # the certificate's interface the figure reads
        undecided = np.zeros((0, 2, 3))
        witnesses = np.zeros((0, 3))

        def summary(self):
            return "certified"

    bar, _ = bar_and_map
    hm = _folding_map()
    sl = plotting.jacobian_slice(bar, hm, normal=(0, 1, 0), resolution=80)
    det, _ = _det_cond(fd_jacobian(hm.map, sl.point_data["rest_points"]))
    pl = plotting.injectivity_figure(sl, NoFolds(), hm, filename=tmp_path / "inj.png")
    (lut,) = [b.GetLookupTable() for b in pl.scalar_bars.values()]
    np.testing.assert_allclose(lut.GetRange(), _log_det_range(det), rtol=1e-6)
    assert lut.GetScale() == 1  # VTK_SCALE_LOG10
    np.testing.assert_allclose(lut.GetBelowRangeColor()[:3], FOLD_COLOUR)
    pl.close()


def test_figure12_shows_every_value(tmp_path):
    rng = np.random.default_rng(2)
    sets = {
        "rigid": 1 + rng.gamma(2, 0.5, 4000),
        "similar": np.r_[1 + rng.gamma(2, 0.3, 3000), np.inf, np.inf, np.nan],
    }
    fig = plotting.figure12(sets, bins=30, filename=tmp_path / "h.png")
    ax = fig.axes[0]
    allv = np.concatenate(list(sets.values()))
    fin = allv[np.isfinite(allv)]
    hi = max(2.0, np.percentile(fin, 99))  # the cond J colour bar's range, recomputed
    edges = np.linspace(1.0, hi, 31)
    steps = [p for p in ax.patches if type(p).__name__ == "StepPatch"]
    # per set: 30 bins, then its overflow bin
    assert len(steps) == 2 * len(sets)
    annotations = [t.get_text() for t in ax.texts]
    for k, v in enumerate(sets.values()):
        pct = 100.0 / v.size
        values, drawn_edges, _ = steps[2 * k].get_data()
        np.testing.assert_allclose(drawn_edges, edges)
        brute = [
            np.count_nonzero((v >= a) & ((v <= b) if j == 29 else (v < b)))
            for j, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True))
        ]
        np.testing.assert_allclose(values, np.array(brute) * pct)
        over = int(np.count_nonzero(v > hi))  # +inf included: a singular J
        assert over > 0
        (over_value,), over_edges, _ = steps[2 * k + 1].get_data()
        assert over_edges[0] > hi and over_value == pytest.approx(over * pct)
        assert f"{over:,}" in annotations
        # every value is in a bin or the overflow bin, or counted as NaN in the legend
        assert sum(brute) + over + np.isnan(v).sum() == v.size
    assert any("1 NaN" in t.get_text() for t in ax.get_legend().get_texts())
    assert ax.get_xlim()[1] > steps[1].get_data()[1][1]  # the overflow bin is in view
    assert ax.get_xticklabels()[-1].get_text() == f"> {hi:.3g}"
    img = _png(tmp_path / "h.png")
    assert img.shape[:2] == (400, 640) and img.std() > 0.05


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


_PLOT_UNDER_LIMIT = """
import resource, sys
import numpy as np
from vhm_viz import plotting
resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))
try:
    plotting.energy_plot(np.linspace(1.0, 0.1, 50), filename=sys.argv[1])
except OSError as exc:
    sys.exit(f"OSError {exc}")
"""


def test_a_figure_that_cannot_be_written_whole_keeps_the_old_image(tmp_path):
    # a full disk or file-size limit part-way through the PNG: the old image stays
    out = tmp_path / "energy.png"
    out.write_bytes(b"the previous figure")
    proc = subprocess.run(
        [sys.executable, "-c", _PLOT_UNDER_LIMIT, str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == f"OSError could not write {out}: File too large"
    assert out.read_bytes() == b"the previous figure"
    assert [p.name for p in tmp_path.iterdir()] == ["energy.png"]
