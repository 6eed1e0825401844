"""Figures of deformation quality, off-screen capable (PNG export).

* :func:`jacobian_slice` + :func:`figure4` -- the paper's Figure 4: a planar slice through
  the *rest* shape, mapped into the deformed shape, coloured by the Jacobian determinant
  and by the condition number, side by side with colour bars (a PyVista ``Plotter``).
* :func:`figure12` -- the paper's Figure 12: histogram of condition numbers (a matplotlib
  ``Figure``), optionally comparing several deformations.
* :func:`energy_plot` -- energy against iteration (the paper's Figure 7).
* :func:`deformation_view` -- a 3D picture of the rest shape (grey, translucent) and the
  deformed shape coloured by det J, with the cage's wireframe.
* :func:`injectivity_figure` -- the answer of :func:`vhm_viz.certify_injectivity` on the
  Figure 4 slice: witnesses of folds and the cubes left undecided, mapped into the
  deformed shape.

Every function takes ``filename`` to save a PNG and returns the Plotter/Figure. Matplotlib
figures are created without pyplot (no GUI backend needed).
"""

from __future__ import annotations

import os

import numpy as np

from vhm_viz.atomic import atomic_path
from vhm_viz.colours import cond_range, histogram, measure_style
from vhm_viz.core.metrics import condition_number, jacobian_determinant

__all__ = [
    "measure_mesh_kwargs",
    "jacobian_slice",
    "figure4",
    "figure12",
    "energy_plot",
    "injectivity_figure",
    "deformation_view",
    "mapped_boxes",
    "default_slice_normal",
]

_AXES = np.eye(3)


def measure_mesh_kwargs(measure: str, values, *, clim=None, scalar_bar_args=None) -> dict:
    """``Plotter.add_mesh`` keyword arguments that draw a Jacobian measure by the convention.

    The one colour convention of :mod:`vhm_viz.colours`: det J in ``coolwarm`` on a log
    scale centred on 1 over ``(1/r, r)``, folds (``det J <= 0``) in
    :data:`~vhm_viz.colours.FOLD_COLOUR`; cond J in ``viridis`` from 1.

    Parameters
    ----------
    measure : {"determinant", "condition_number"}
    values : array_like
        The values drawn (set the range unless ``clim`` is given).
    clim : (float, float), optional
        Colour range instead of the convention's (for det J, keep it positive: it is drawn
        on a log scale).
    scalar_bar_args : dict, optional
        Merged over the defaults (black text, the measure's title).

    Returns
    -------
    dict
        ``scalars`` is not included: pass it yourself.
    """
    style = measure_style(measure, values)
    if clim is not None:
        style["clim"] = tuple(float(c) for c in clim)
    kwargs = {
        "cmap": style["cmap"],
        "clim": style["clim"],
        "log_scale": style["log_scale"],
        "nan_color": "lightgrey",
        "scalar_bar_args": {"title": style["title"], "color": "black", **(scalar_bar_args or {})},
    }
    if style["below_color"] is not None:
        kwargs["below_color"] = style["below_color"]
        kwargs["scalar_bar_args"].setdefault("below_label", "fold")
    return kwargs


def _write_image(filename, write) -> None:
    """Write a figure with ``write(name)`` atomically: the old image or the whole new one."""
    with atomic_path(filename) as tmp:
        write(os.fspath(tmp))


def default_slice_normal(points, deformed) -> np.ndarray:
    """The coordinate axis along which the points move least (RMS displacement).

    For a bend this is the normal of the bending plane, so the slice shows the bend.
    """
    d = np.asarray(deformed) - np.asarray(points)
    rms = np.sqrt(np.mean(d**2, axis=0)) if len(d) else np.zeros(3)
    return _AXES[int(np.argmin(rms))].copy()


def _surface(ds):
    """Polygonal surface of a dataset (VTK's dataset surface filter, no warnings)."""
    import pyvista as pv
    from vtkmodules.vtkFiltersGeometry import vtkDataSetSurfaceFilter

    f = vtkDataSetSurfaceFilter()
    f.SetInputData(ds)
    f.Update()
    return pv.wrap(f.GetOutput())


def _plane_grid(bounds, normal, origin, resolution):
    import pyvista as pv

    lo, hi = np.asarray(bounds[0::2]), np.asarray(bounds[1::2])
    axis = int(np.argmax(np.abs(normal)))
    u, v = [a for a in range(3) if a != axis]
    size = hi - lo
    pad = 0.02 * size
    nu = max(2, int(resolution))
    nv = max(2, int(round(nu * size[v] / max(size[u], 1e-12))))
    if size[v] > size[u]:
        nv = max(2, int(resolution))
        nu = max(2, int(round(nv * size[u] / max(size[v], 1e-12))))
    dims = [1, 1, 1]
    dims[u], dims[v] = nu, nv
    spacing = [1.0, 1.0, 1.0]
    spacing[u] = (size[u] + 2 * pad[u]) / (nu - 1)
    spacing[v] = (size[v] + 2 * pad[v]) / (nv - 1)
    org = lo - pad
    org[axis] = origin[axis]
    return pv.ImageData(dimensions=dims, spacing=spacing, origin=org).cast_to_unstructured_grid()


def jacobian_slice(mesh, harmonic_map, *, normal=None, origin=None, resolution: int = 160):
    """A planar slice of the rest shape, mapped by the deformation, with Jacobian arrays.

    The slice is taken in the *rest* shape: for datasets with 3D cells (tet meshes,
    volumes) with :meth:`pyvista.DataSet.slice`; for a closed surface, a regular grid on
    the plane keeps the points inside the surface; for anything else (point clouds, open
    surfaces) the grid keeps the points inside the cage. Its points are then mapped by
    ``harmonic_map`` (points outside the cage are dropped) and the closed-form Jacobian at
    the rest points gives ``jacobian_determinant`` and ``condition_number``.

    Parameters
    ----------
    mesh : pyvista.DataSet
        The rest shape.
    harmonic_map : HarmonicMap
        E.g. ``deformer.harmonic_map``.
    normal : (3,) array_like, optional
        Slice normal; default :func:`default_slice_normal` of the mesh points.
    origin : (3,) array_like, optional
        A point of the plane; default the centre of the mesh's bounds within the cage's box.
    resolution : int
        Grid points along the longer side (surface / point-cloud input).

    Returns
    -------
    pyvista.DataSet
        The deformed slice, with point arrays ``jacobian_determinant``,
        ``condition_number`` and ``rest_points``.
    """
    import pyvista as pv

    from vhm_viz.filters._vtk import numpy_points

    mesh = pv.wrap(mesh)
    pts = numpy_points(mesh)  # an image's without VTK's meshgrids
    # the slice lies inside the cage: data left outside it (--outside passthrough), however
    # far, neither stretches the plane's grid nor moves its centre
    cage = np.asarray(harmonic_map.cage.vertices, dtype=np.float64)
    lo = np.maximum(np.asarray(mesh.bounds[0::2], dtype=np.float64), cage.min(axis=0))
    hi = np.minimum(np.asarray(mesh.bounds[1::2], dtype=np.float64), cage.max(axis=0))
    if np.any(lo > hi):
        raise ValueError("the data lies wholly outside the cage: no slice to show")
    bounds = np.ravel(np.column_stack([lo, hi]))
    if origin is None:
        origin = (lo + hi) / 2
    origin = np.asarray(origin, dtype=np.float64)
    if normal is None:
        sample = pts[:: max(1, len(pts) // 4000)]
        normal = default_slice_normal(sample, harmonic_map.map(sample, outside="passthrough"))
    normal = np.asarray(normal, dtype=np.float64)
    normal = normal / np.linalg.norm(normal)
    has_3d_cells = isinstance(mesh, (pv.ImageData, pv.RectilinearGrid, pv.StructuredGrid)) or (
        isinstance(mesh, pv.UnstructuredGrid) and mesh.n_cells and mesh.get_cell(0).dimension == 3
    )
    if has_3d_cells:
        sl = mesh.slice(normal=normal, origin=origin)
    else:
        grid = _plane_grid(bounds, normal, origin, resolution)
        closed = (
            isinstance(mesh, pv.PolyData)
            and mesh.n_cells > 0
            and mesh.GetNumberOfPolys() > 0
            and mesh.n_open_edges == 0
        )
        if closed:
            grid = grid.compute_implicit_distance(mesh)
            d = np.asarray(grid.point_data["implicit_distance"])
            sl = grid.threshold(
                (float(d.min()) - 1.0, 0.0), scalars="implicit_distance", all_scalars=True
            )
        else:
            inside = harmonic_map.inside(np.asarray(grid.points))
            grid.point_data["inside"] = inside.astype(np.float64)
            sl = grid.threshold((0.5, 1.5), scalars="inside", all_scalars=True)
        sl = _surface(sl)
    rest = np.asarray(sl.points, dtype=np.float64)
    keep = harmonic_map.inside(rest)
    if not keep.all():
        sl = _surface(sl.extract_points(keep, adjacent_cells=False))
        rest = np.asarray(sl.points, dtype=np.float64)
    if sl.n_points == 0:
        raise ValueError("the slice plane does not cut the shape inside the cage (empty slice)")
    f, jac, _ = harmonic_map.evaluate(rest, order=1, outside="passthrough")
    out = sl.copy()
    out.points = f
    out.point_data["rest_points"] = rest
    out.point_data["jacobian_determinant"] = jacobian_determinant(jac)
    out.point_data["condition_number"] = condition_number(jac)
    out.field_data["slice_normal"] = normal
    return out


def figure4(
    deformed_slice,
    *,
    deformed_surface=None,
    window_size=(1600, 700),
    det_range=None,
    cond_range=None,
    filename=None,
    off_screen: bool = True,
    title: str | None = None,
):
    """The paper's Figure 4: the slice coloured by det J (left) and cond J (right).

    Parameters
    ----------
    deformed_slice : pyvista.DataSet
        From :func:`jacobian_slice`.
    deformed_surface : pyvista.DataSet, optional
        Drawn as a faint silhouette in both views.
    window_size : (int, int)
        Pixels (width, height) of the PNG.
    det_range, cond_range : (float, float), optional
        Colour ranges; default the convention of :mod:`vhm_viz.colours`: ``(1/r, r)`` on
        a log scale for the determinant (:func:`~vhm_viz.colours.det_range`; folds,
        ``det J <= 0``, in :data:`~vhm_viz.colours.FOLD_COLOUR`) and ``(1, max(2, p99))``
        for the condition number (:func:`~vhm_viz.colours.cond_range`).
    filename : str or path-like, optional
        Save a PNG there.
    off_screen : bool
        Render off-screen (no window).
    title : str, optional

    Returns
    -------
    pyvista.Plotter
    """
    import pyvista as pv

    normal = _slice_normal(deformed_slice)
    pl = pv.Plotter(
        shape=(1, 2), off_screen=off_screen, window_size=list(window_size), border=False
    )
    pl.set_background("white")
    views = (
        ("jacobian_determinant", "det J", "determinant", det_range),
        ("condition_number", "cond J", "condition_number", cond_range),
    )
    for col, (name, label, measure, clim) in enumerate(views):
        pl.subplot(0, col)
        pl.add_mesh(
            deformed_slice.copy(),
            scalars=name,
            show_edges=False,
            lighting=False,
            **measure_mesh_kwargs(
                measure,
                deformed_slice.point_data[name],
                clim=clim,
                scalar_bar_args={
                    "title": label,
                    # the panel's heading says what black is: VTK draws a horizontal bar's
                    # below-range label over its swatch (a label, even empty, draws one)
                    **({"below_label": ""} if measure == "determinant" else {}),
                    "vertical": False,
                    "position_x": 0.2,
                    "position_y": 0.09,
                    "width": 0.6,
                    "height": 0.07,
                    "title_font_size": 22,
                    "label_font_size": 18,
                    "fmt": "%.3g",
                },
            ),
        )
        if deformed_surface is not None:
            pl.add_mesh(deformed_surface, color="lightgrey", opacity=0.15, lighting=False)
        if measure == "determinant":
            label += " (log scale, folds black)"
        pl.add_text(label if title is None else f"{title}: {label}", font_size=12, color="black")
        pl.camera_position = _view_along(deformed_slice, normal)
        pl.reset_camera()
        pl.camera.zoom(1.1)
    if filename is not None:
        _write_image(filename, pl.screenshot)
    return pl


def _slice_normal(deformed_slice) -> np.ndarray:
    """The normal :func:`jacobian_slice` stored with the slice (default +y)."""
    stored = deformed_slice.field_data.get("slice_normal", [0.0, 1.0, 0.0])
    return np.asarray(stored, dtype=np.float64).ravel()[:3]


def _view_along(mesh, normal):
    c = np.asarray(mesh.center)
    d = float(np.linalg.norm(np.asarray(mesh.bounds[1::2]) - np.asarray(mesh.bounds[0::2])))
    up = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    return [tuple(c + 2.5 * max(d, 1e-9) * normal), tuple(c), tuple(up)]


def figure12(
    condition_numbers,
    *,
    bins: int = 60,
    value_range=None,
    filename=None,
    figsize=(6.4, 4.0),
    dpi: int = 100,
    title: str = "Condition number of J",
):
    """The paper's Figure 12: histogram(s) of condition numbers, every value shown.

    Values beyond the drawn range are not cut: they are counted in an **overflow bin**
    drawn (hatched) to the right of the range and labelled with its count (an infinite
    cond J, a singular Jacobian, counts there too); values under the range, if any, in an
    underflow bin on the left. NaN values (no Jacobian, e.g. outside the cage) are counted
    in the legend. Bins come from :func:`vhm_viz.colours.histogram`; heights are percent
    of all values of the set.

    Parameters
    ----------
    condition_numbers : array_like or dict of label -> array_like
        One or several sets (e.g. ``{"rigid": c1, "similar": c2}``).
    bins : int
    value_range : (float, float), optional
        Default :func:`vhm_viz.colours.cond_range` over all sets: ``(1, max(2, p99))``,
        the range of the cond J colour bar.
    filename : str or path-like, optional
        Save a PNG there.
    figsize, dpi
        Figure size in inches and resolution (pixels = ``figsize * dpi``).
    title : str

    Returns
    -------
    matplotlib.figure.Figure
        ``fig.histograms`` holds the :class:`vhm_viz.colours.Histogram` of each set.
    """
    from matplotlib.figure import Figure

    sets = condition_numbers if isinstance(condition_numbers, dict) else {"": condition_numbers}
    data = {k: np.asarray(v, dtype=np.float64).ravel() for k, v in sets.items()}
    if value_range is None:
        value_range = cond_range(np.concatenate([*data.values(), np.zeros(0)]))
    fig = Figure(figsize=figsize, dpi=dpi)
    ax = fig.add_subplot(1, 1, 1)
    colors = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple"]
    hists = {label: histogram(v, value_range, bins) for label, v in data.items()}
    lo, hi = (float(e) for e in next(iter(hists.values())).edges[[0, -1]])
    side = 4 * (hi - lo) / bins  # width of the under/overflow bins, half of it as a gap
    over_x = (hi + 0.5 * side, hi + 1.5 * side)
    under_x = (lo - 1.5 * side, lo - 0.5 * side)
    any_under = any(h.below for h in hists.values())
    alpha = 0.6 if len(data) > 1 else 0.9
    notes = []
    for i, (label, h) in enumerate(hists.items()):
        vals = data[label]
        colour = colors[i % len(colors)]
        pct = 100.0 / max(h.total, 1)
        n_nan = int(np.isnan(vals).sum())
        over = h.above + (h.nonfinite - n_nan)  # +-inf: a singular J is beyond any range
        text = label or None
        if n_nan:
            text = f"{label + ': ' if label else ''}{n_nan} NaN (no Jacobian)"
        ax.stairs(h.counts * pct, h.edges, fill=True, alpha=alpha, color=colour, label=text)
        ax.stairs(
            [over * pct], over_x, fill=True, alpha=alpha, color=colour, hatch="//", ec="black"
        )
        notes.append((over, over * pct, colour))
        if any_under:
            ax.stairs([h.below * pct], under_x, fill=True, alpha=alpha, color=colour, hatch="\\\\")
    top = max(n for _, n, _ in notes)
    for h in hists.values():
        top = max(top, float(h.counts.max()) * 100.0 / max(h.total, 1))
    over_top = max(n for _, n, _ in notes)
    for k, (count, _, colour) in enumerate(notes):  # stacked above the tallest overflow bar
        ax.annotate(
            f"{count:,}",
            (0.5 * sum(over_x), over_top),
            xytext=(0, 3 + 12 * (len(notes) - 1 - k)),
            textcoords="offset points",
            ha="center",
            va="bottom",
            color=colour if len(notes) > 1 else "black",
            fontsize=9,
        )
    ax.set_ylim(0, 1.15 * top + 1e-9 + 0.06 * top * len(notes))
    ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
    ax.set_xticks([*ticks, 0.5 * sum(over_x)], [f"{t:g}" for t in ticks] + [f"> {hi:.3g}"])
    ax.set_xlim(under_x[0] if any_under else lo, over_x[1] + 0.25 * side)
    ax.set_xlabel("condition number  s_max / s_min  (hatched: beyond the range, with its count)")
    ax.set_ylabel("% of points")
    ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.histograms = hists
    if filename is not None:
        _write_image(filename, lambda name: fig.savefig(name, dpi=dpi))
    return fig


def _energy_series(item):
    """Energy array of a SolveReport, a list of them (concatenated) or an array."""
    if hasattr(item, "energy"):
        return np.asarray(item.energy, dtype=np.float64)
    if isinstance(item, (list, tuple)) and item and hasattr(item[0], "energy"):
        parts = [np.asarray(r.energy, dtype=np.float64) for r in item]
        return np.concatenate([parts[0]] + [p[1:] for p in parts[1:]])
    return np.asarray(item, dtype=np.float64).ravel()


def energy_plot(
    reports,
    *,
    filename=None,
    figsize=(6.4, 4.0),
    dpi: int = 100,
    log: bool = True,
    title: str = "Energy vs. iteration",
):
    """Energy against iteration (the paper's Figure 7).

    Parameters
    ----------
    reports : SolveReport, list of SolveReport, array, or dict of label -> any of these
        A list of reports (ramped solves) is drawn as one continuous curve.
    filename : str or path-like, optional
    figsize, dpi
    log : bool
        Logarithmic energy axis.
    title : str

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    sets = reports if isinstance(reports, dict) else {"": reports}
    fig = Figure(figsize=figsize, dpi=dpi)
    ax = fig.add_subplot(1, 1, 1)
    for label, item in sets.items():
        e = _energy_series(item)
        ax.plot(np.arange(len(e)), e, label=label or None, lw=1.8)
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("energy E")
    ax.set_title(title)
    if len(sets) > 1 or next(iter(sets)):
        ax.legend()
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    if filename is not None:
        _write_image(filename, lambda name: fig.savefig(name, dpi=dpi))
    return fig


def deformation_view(
    rest,
    deformed,
    *,
    cage=None,
    window_size=(1000, 700),
    view: str = "xz",
    filename=None,
    off_screen: bool = True,
    title: str | None = None,
):
    """A 3D picture of a deformation: the rest shape and the deformed one, side by side.

    The rest shape is drawn translucent light grey, the deformed shape lit and coloured by
    its point array ``jacobian_determinant`` when it has one (the det J convention of
    :mod:`vhm_viz.colours`: log scale centred on 1, folds black), else plain.

    Parameters
    ----------
    rest, deformed : pyvista.DataSet
        Same points, before and after (their surfaces are drawn).
    cage : Cage or pyvista.PolyData, optional
        Drawn as a faint wireframe (the rest cage).
    window_size : (int, int)
        Pixels (width, height) of the PNG.
    view : {"xz", "xy", "yz"}
        The coordinate plane looked at (``"xz"``: along -y, z up).
    filename : str or path-like, optional
        Save a PNG there.
    off_screen : bool
    title : str, optional

    Returns
    -------
    pyvista.Plotter
    """
    import pyvista as pv

    def surface(ds):
        ds = pv.wrap(ds)
        return ds if isinstance(ds, pv.PolyData) else _surface(ds)

    pl = pv.Plotter(off_screen=off_screen, window_size=list(window_size))
    pl.set_background("white")
    pl.add_mesh(surface(rest), color="lightgrey", opacity=0.35, label="rest")
    bent = surface(deformed)
    if "jacobian_determinant" in bent.point_data:
        pl.add_mesh(
            bent,
            scalars="jacobian_determinant",
            **measure_mesh_kwargs(
                "determinant",
                bent.point_data["jacobian_determinant"],
                scalar_bar_args={
                    "title": "det J (log)\nblack: fold",
                    "below_label": "",
                    "fmt": "%.3g",
                    "vertical": True,
                    "position_x": 0.8,
                    "position_y": 0.15,
                    "width": 0.08,
                    "height": 0.7,
                },
            ),
        )
    else:
        pl.add_mesh(bent, color="tan")
    if cage is not None:
        if not isinstance(cage, pv.DataSet):
            cage = pv.PolyData.from_regular_faces(np.asarray(cage.vertices), np.asarray(cage.faces))
        pl.add_mesh(cage, style="wireframe", color="black", opacity=0.25, lighting=False)
    if title:
        pl.add_text(title, font_size=12, color="black")
    {"xz": pl.view_xz, "xy": pl.view_xy, "yz": pl.view_yz}[view]()
    pl.reset_camera()
    pl.camera.zoom(0.9)  # room for the colour bar on the right
    if filename is not None:
        _write_image(filename, pl.screenshot)
    return pl


def mapped_boxes(boxes, harmonic_map):
    """Axis-aligned boxes ``(lo, hi)`` as hexahedra with their corners mapped.

    Parameters
    ----------
    boxes : (k, 2, 3) array_like
        E.g. :attr:`InjectivityCertificate.undecided`.
    harmonic_map : HarmonicMap

    Returns
    -------
    pyvista.UnstructuredGrid
    """
    import pyvista as pv

    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 2, 3)
    lo, hi = boxes[:, 0], boxes[:, 1]
    # VTK hexahedron corner order: bottom face counter-clockwise, then the top face
    sel = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
    )
    corners = np.where(sel[None].astype(bool), hi[:, None], lo[:, None]).reshape(-1, 3)
    mapped = harmonic_map.map(corners, outside="passthrough")
    k = len(boxes)
    cells = np.hstack([np.full((k, 1), 8), np.arange(8 * k).reshape(k, 8)]).ravel()
    return pv.UnstructuredGrid(cells, np.full(k, pv.CellType.HEXAHEDRON), mapped)


def injectivity_figure(
    deformed_slice,
    certificate,
    harmonic_map,
    *,
    deformed_surface=None,
    window_size=(1000, 800),
    max_cubes: int = 20000,
    filename=None,
    off_screen: bool = True,
):
    """The injectivity certificate on the Figure 4 slice, in the deformed shape.

    The slice is coloured by ``det J`` by the convention of :mod:`vhm_viz.colours` (blue
    to red on a log scale, white at 1; folds, ``det J <= 0``, black); witnesses (points
    with ``det J <= 0``) are red spheres and the cubes left
    undecided are orange wireframes, both mapped by the deformation. The title states the
    answer: certified, not injective, or undecided.

    Parameters
    ----------
    deformed_slice : pyvista.DataSet
        From :func:`jacobian_slice`.
    certificate : InjectivityCertificate
        From :func:`vhm_viz.certify_injectivity`.
    harmonic_map : HarmonicMap
        The map certified (maps the witnesses and cubes).
    deformed_surface : pyvista.DataSet, optional
        The deformed data; its surface is drawn as a faint silhouette.
    window_size : (int, int)
    max_cubes : int
        Undecided cubes drawn at most (those nearest the slice plane).
    filename : str or path-like, optional
        Save a PNG there.
    off_screen : bool

    Returns
    -------
    pyvista.Plotter
    """
    import pyvista as pv

    normal = _slice_normal(deformed_slice)
    pl = pv.Plotter(off_screen=off_screen, window_size=list(window_size))
    pl.set_background("white")
    pl.add_mesh(
        deformed_slice.copy(),
        scalars="jacobian_determinant",
        lighting=False,
        **measure_mesh_kwargs(
            "determinant",
            deformed_slice.point_data["jacobian_determinant"],
            scalar_bar_args={"title": "det J (log; black: <= 0)", "fmt": "%.3g", "vertical": False},
        ),
    )
    if deformed_surface is not None:
        outline = deformed_surface
        if not isinstance(outline, pv.PolyData):
            outline = _surface(outline)
        pl.add_mesh(outline, color="lightgrey", opacity=0.15, lighting=False)
    boxes = np.asarray(certificate.undecided, dtype=np.float64).reshape(-1, 2, 3)
    if len(boxes):
        if len(boxes) > max_cubes:
            rest = np.asarray(deformed_slice.point_data["rest_points"])
            origin = rest.mean(axis=0)
            gap = np.abs((boxes.mean(axis=1) - origin) @ normal)
            boxes = boxes[np.argsort(gap)[:max_cubes]]
        pl.add_mesh(
            mapped_boxes(boxes, harmonic_map),
            style="wireframe",
            color="darkorange",
            line_width=1,
            lighting=False,
            label="undecided",
        )
    witnesses = np.asarray(certificate.witnesses, dtype=np.float64).reshape(-1, 3)
    if len(witnesses):
        pl.add_mesh(
            pv.PolyData(harmonic_map.map(witnesses, outside="passthrough")),
            color="red",
            point_size=14,
            render_points_as_spheres=True,
            label="witness (det J <= 0)",
        )
    pl.add_text(certificate.summary(), font_size=10, color="black")
    pl.camera_position = _view_along(deformed_slice, normal)
    pl.reset_camera()
    if filename is not None:
        _write_image(filename, pl.screenshot)
    return pl
