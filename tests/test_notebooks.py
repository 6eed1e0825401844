"""The notebooks execute (nbclient, static PyVista backend) and print the right numbers.

Each notebook is run as is, with a *probe* cell appended (or inserted right after the
cell whose state it needs): the probe recomputes, from the kernel's variables, what the
notebook printed, by independent means (closed-form harmonic map instead of the VTK
filter, hand-written triangle/tetrahedron measures instead of ``vhm_viz.metrics`` and
PyVista, the change-of-variables integral instead of resampling), and prints it as a JSON
line. The test compares the notebook's own outputs with it.
"""

from __future__ import annotations

import base64
import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
PROBE = "VHM-PROBE "

# Helpers defined in the kernel by the probes: no vhm_viz.metrics, no PyVista measures.
_MEASURES = """
import json as _json
import numpy as _np

def _probe_e_rigid(x, y, tri):
    # area-weighted (s1 - 1)^2 + (s2 - 1)^2 of each triangle's map, via QR + SVD
    es = _np.stack([x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]], axis=2)
    ed = _np.stack([y[tri[:, 1]] - y[tri[:, 0]], y[tri[:, 2]] - y[tri[:, 0]]], axis=2)
    _, r = _np.linalg.qr(es)  # es = q r: r is the source triangle in its own plane
    s = _np.linalg.svd(ed @ _np.linalg.inv(r), compute_uv=False)
    area = 0.5 * _np.linalg.norm(_np.cross(es[:, :, 0], es[:, :, 1]), axis=1)
    return float((area * ((s - 1) ** 2).sum(axis=1)).sum() / area.sum())

def _probe_surface_volume(x, tri):
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    return float(_np.einsum("ij,ij->i", a, _np.cross(b, c)).sum() / 6)

def _probe_tet_volume(x, tets):
    a = x[tets[:, 0]]
    m = _np.stack([x[tets[:, k]] - a for k in (1, 2, 3)], axis=1)
    return float(_np.abs(_np.linalg.det(m)).sum() / 6)

def _probe_print(**values):
    print("@PROBE@" + _json.dumps(values))
""".replace("@PROBE@", PROBE)

_PROBE_01 = (
    _MEASURES
    + """
_x = _np.asarray(rest.points, dtype=float)
_tri = _np.asarray(scenario.triangles)
_v0 = _probe_surface_volume(_x, _tri)
_ref = {}
for _mode in ("similar", "rigid"):  # the loop left the deformer solved in "similar"
    if _mode == "rigid":
        deformer.mode = "rigid"
        scenario.solve()
    _y = deformer.harmonic_map.map(_x)  # closed form, not the VTK filter
    _ref[_mode] = [_probe_e_rigid(_x, _y, _tri), abs(_probe_surface_volume(_y, _tri) - _v0) / _v0]
_probe_print(**_ref)
"""
)

# right after the CT is resampled, before `dfm` is reused for the hand
_PROBE_02_CT = (
    _MEASURES
    + """
# resampling pulls values back, so sum(out) * voxel ~ integral of I(f^-1(y)) dy
# = integral of I(x) det J(x) dx: the intensity-weighted mean of det J over the input
_I = _np.asarray(ct[ct.active_scalars_name], dtype=float)
_detJ = _np.linalg.det(dfm.harmonic_map.jacobian(_np.asarray(ct.points)))
_probe_print(ct_ratio=float((_I * _detJ).sum() / _I.sum()), ct_dims=list(ct.dimensions))
"""
)

_PROBE_02_TETS = """
_cells = _np.asarray(tets.cells_dict[pv.CellType.TETRA])
_v0 = _probe_tet_volume(_np.asarray(tets.points), _cells)
_v1 = _probe_tet_volume(_np.asarray(bent_tets.points), _cells)
_probe_print(
    volume_change=abs(_v1 - _v0) / _v0,
    min_det=float(_np.linalg.det(dfm.harmonic_map.jacobian(_np.asarray(tets.points))).min()),
    n_points=int(tets.n_points),
    n_tets=int(len(_cells)),
)
"""


def _execute(name, probes, cwd):
    """Run notebook ``name`` in folder ``cwd``, with probe cells inserted after the given
    cell indices.

    Returns the executed notebook (probe cells included) and the probes' values.
    """
    path = NOTEBOOKS / name
    nb = nbformat.read(path, as_version=4)
    n_original = len(nb.cells)
    at = [(n_original if index is None else index + 1, source) for index, source in probes]
    for position, source in sorted(at, key=lambda p: p[0], reverse=True):
        nb.cells.insert(position, nbformat.v4.new_code_cell(source))
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}
    )
    client.execute()  # raises CellExecutionError on any failing cell
    errors = [o for c in _code_cells(nb) for o in c.outputs if o.output_type == "error"]
    assert not errors
    values = {}
    for text in _streams(nb):
        for line in text.splitlines():
            if line.startswith(PROBE):
                values.update(json.loads(line[len(PROBE) :]))
    return nb, values


def _code_cells(nb):
    return [c for c in nb.cells if c.cell_type == "code"]


def _streams(nb):
    return [o.text for c in _code_cells(nb) for o in c.outputs if o.output_type == "stream"]


def _pngs(nb):
    """The PNG images the notebook displayed, as (height, width, 3) float arrays."""
    from matplotlib.image import imread

    out = []
    for c in _code_cells(nb):
        for o in c.outputs:
            data = o.get("data", {})
            if "image/png" in data:
                img = imread(io.BytesIO(base64.b64decode(data["image/png"])), format="png")
                out.append(img[..., :3])
    return out


def _printed(nb, label):
    """The number printed after ``label:`` by the notebook."""
    for text in _streams(nb):
        m = re.search(re.escape(label) + r":\s*([-+0-9.eE]+)", text)
        if m:
            return float(m.group(1))
    raise AssertionError(f"the notebook printed no {label!r}")


def _assert_figures(images, sizes):
    """One image per expected (width, height) (None: any size), none blank."""
    assert len(images) == len(sizes)
    for img, size in zip(images, sizes, strict=True):
        if size is not None:
            assert img.shape[:2] == (size[1], size[0])
        assert img.std() > 0.05  # not blank
        assert len(np.unique((img * 255).round().reshape(-1, 3), axis=0)) > 50


def test_there_are_notebooks():
    names = {p.name for p in NOTEBOOKS.glob("*.ipynb")}
    assert names == {"01_bar_bend_u.ipynb", "02_volume_and_tets.ipynb"}


def test_notebooks_are_saved_with_their_outputs():
    """Committed with outputs (static PNGs), so they read as they are on a forge; small."""
    for path in sorted(NOTEBOOKS.glob("*.ipynb")):
        assert path.stat().st_size < 1_000_000, path.name
        nb = nbformat.read(path, as_version=4)
        cells = _code_cells(nb)
        assert all(c.execution_count for c in cells), path.name  # every cell was run
        assert _pngs(nb), path.name
        assert not any(o.output_type == "error" for c in cells for o in c.outputs), path.name


@pytest.fixture
def kernel_env(monkeypatch):
    monkeypatch.setenv("PYVISTA_OFF_SCREEN", "true")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.delenv("VHM_VIZ_DATA", raising=False)
    return monkeypatch


def test_notebook_01_bar_bend_u(kernel_env, tmp_path):
    # started from a folder that is neither the repository nor notebooks/
    nb, ref = _execute("01_bar_bend_u.ipynb", [(None, _PROBE_01)], tmp_path)
    # the solve report it prints converged
    assert any("SolveReport(" in t and "converged=True" in t for t in _streams(nb))
    # Table 1 (markdown): E_rigid and E_volume per mode, as recomputed independently
    tables = [
        o.data["text/markdown"]
        for c in _code_cells(nb)
        for o in c.outputs
        if "text/markdown" in o.get("data", {})
    ]
    assert len(tables) == 1
    rows = {}
    for line in tables[0].splitlines():
        cells = [x.strip() for x in line.strip().strip("|").split("|")]
        if cells[0] in ("rigid", "similar"):
            rows[cells[0]] = (float(cells[1]), float(cells[2]), int(cells[3]))
    assert set(rows) == {"rigid", "similar"}
    for mode, (e_rigid, e_volume, iterations) in rows.items():
        # printed with 3 decimals
        assert abs(e_rigid - ref[mode][0]) <= 6e-4, (mode, e_rigid, ref[mode])
        assert abs(e_volume - ref[mode][1]) <= 6e-4, (mode, e_volume, ref[mode])
        assert 0 < iterations <= 5000
    assert 0.022 <= ref["rigid"][0] <= 0.069  # the paper's range for VHM (Table 1)
    # the 3D view (900 x 400), Figure 4 (1200 x 520), Figure 12 and the energy plot
    _assert_figures(_pngs(nb), [(900, 400), (1200, 520), None, None])


def _run_notebook_02(cwd):
    """Notebook 02 run in ``cwd``, its printed numbers checked against the probes."""
    nb, ref = _execute(
        "02_volume_and_tets.ipynb", [(5, _PROBE_02_CT), (None, _PROBE_02_TETS)], cwd
    )
    assert ref["ct_dims"] == [32, 32, 47]  # the real CT subsampled by 2, or the phantom
    # the resampled volume's intensity sum equals the change-of-variables integral (to the
    # discretisation of the resampling)
    ratio = _printed(nb, "voxel sum ratio")
    assert abs(ratio - 1) > 0.01  # the bend does change it
    assert abs(ratio - ref["ct_ratio"]) < 0.005 * ref["ct_ratio"], (ratio, ref["ct_ratio"])
    # the tet mesh: relative volume change and smallest det J, as printed
    np.testing.assert_allclose(_printed(nb, "volume change"), ref["volume_change"], rtol=1e-6)
    np.testing.assert_allclose(_printed(nb, "min det J"), ref["min_det"], rtol=1e-9)
    assert 0 < ref["min_det"] < 1  # no fold-over, but real compression somewhere
    _assert_figures(_pngs(nb), [(1000, 450), (900, 450)])
    return nb, ref


def test_notebook_02_volume_and_tets(kernel_env, tmp_path):
    # started from another folder: the data is still found (shared/data beside the repo)
    nb, ref = _run_notebook_02(tmp_path)
    if (DATA / "hand_tet" / "hand.mesh").exists():
        assert f"data: {DATA.resolve()}" in _streams(nb)[0]
        assert (ref["n_points"], ref["n_tets"]) == (7234, 29998)


def test_notebook_02_says_clearly_when_the_data_is_missing(kernel_env, tmp_path):
    missing = tmp_path / "no such data"
    kernel_env.setenv("VHM_VIZ_DATA", str(missing))
    nb, ref = _run_notebook_02(tmp_path)
    text = "\n".join(_streams(nb))
    # one clear note naming the variable and the folder, then the stand-ins; no traceback
    assert f"VHM_VIZ_DATA={missing} does not exist" in text
    assert "Using generated stand-ins instead" in text
    assert "Traceback" not in text
    assert (ref["n_points"], ref["n_tets"]) != (7234, 29998)  # not the real hand
