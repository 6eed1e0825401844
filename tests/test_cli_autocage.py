"""``vhm-viz cage`` and ``vhm-viz anchors`` end to end, and their bad-input paths."""

from __future__ import annotations

import json

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from vhm_viz.cli import main  # noqa: E402
from vhm_viz.io import read_cage  # noqa: E402


@pytest.fixture(scope="module")
def capsule(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "capsule.vtp"
    pv.Capsule(radius=0.4, cylinder_length=2.0, resolution=24).triangulate().save(path)
    return path


def test_cage_then_anchors(capsule, tmp_path, capsys):
    cage_path = tmp_path / "cage.obj"
    assert main(["cage", str(capsule), "-o", str(cage_path), "--max-faces", "200"]) == 0
    cage = read_cage(cage_path)  # validates: closed, manifold, outward, no intersections
    assert cage.n_faces <= 200
    pts = np.asarray(pv.read(capsule).points)
    assert cage.contains(pts).all()
    out = tmp_path / "anchors.json"
    assert main(["anchors", str(capsule), "--cage", str(cage_path), "-o", str(out), "-n", "6"]) == 0
    anchors = np.asarray(json.loads(out.read_text())["anchors"])
    assert anchors.shape == (6, 3) and cage.contains(anchors).all()
    # on the capsule's axis (the x axis of pv.Capsule), i.e. on its medial axis
    assert np.abs(anchors[:, 1:]).max() < 0.15
    assert "faces" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv,message",
    [
        (["cage", "{missing}", "-o", "{tmp}/c.obj"], "not found"),
        (["cage", "{capsule_obj}", "-o", "{capsule_obj}"], "refusing to overwrite"),
        (["cage", "{capsule}", "-o", "{tmp}/c.txt"], "must end with"),
        (["anchors", "{capsule}", "--cage", "{missing}", "-o", "{tmp}/a.json"], "not found"),
    ],
)
def test_bad_input_is_one_line_and_nonzero(argv, message, capsule, tmp_path, capsys):
    capsule_obj = tmp_path / "capsule.obj"
    pv.read(capsule).save(capsule_obj)
    fill = {"missing": tmp_path / "nope.obj", "tmp": tmp_path, "capsule": capsule}
    fill["capsule_obj"] = capsule_obj
    before = capsule.read_bytes(), capsule_obj.read_bytes()
    rc = main([a.format(**fill) for a in argv])
    err = capsys.readouterr().err.strip()
    assert rc != 0
    assert message in err and len(err.splitlines()) == 1
    assert (capsule.read_bytes(), capsule_obj.read_bytes()) == before  # inputs untouched
