"""Settings outside their documented ranges are refused by name; the solver keeps its cap.

Issue 12, defects 6 (settings) and 7 (not converged reported as success).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from vhm_viz import examples
from vhm_viz.core.basis import chunk_rows, evaluate_basis
from vhm_viz.core.errors import SettingError
from vhm_viz.core.limits import RANGES, check_setting
from vhm_viz.scene import Scene, SceneError


@pytest.fixture(scope="module")
def bar():
    return examples.bar("bend-u", resolution=8)


# ------------------------------------------------------------------ the one check
@pytest.mark.parametrize(
    "kind,value",
    [
        ("max_iterations", 1e12),
        ("max_iterations", 0),
        ("max_iterations", 2.5),
        ("tolerance", 1e6),
        ("tolerance", 0.0),
        ("steps", 1e9),
        ("anderson_window", -3),
        ("alpha", 1e30),
        ("alpha", -1.0),
        ("memory_budget", 0),
        ("memory_budget", -1),
        ("chunk_size", -1),
        ("contraction", 1.0),
        ("alpha", float("nan")),
        ("alpha", True),
        ("steps", "10"),
        ("tolerance", None),
    ],
)
def test_out_of_range_or_wrong_type_is_refused_naming_field_and_range(kind, value):
    with pytest.raises(SettingError) as info:
        check_setting(kind, value, f"solver.{kind}")
    message = str(info.value)
    assert message.startswith(f"solver.{kind} must be ")
    assert RANGES[kind].describe() in message and "got" in message


def test_values_inside_the_ranges_pass_and_keep_their_type():
    assert check_setting("max_iterations", 1e3) == 1000
    assert isinstance(check_setting("max_iterations", 1e3), int)
    assert check_setting("tolerance", 1e-300) == 1e-300  # the benchmark's "never stop"
    assert check_setting("anderson_window", 0) == 0
    assert check_setting("alpha", 0.01) == 0.01


# ------------------------------------------------------------------ the API
def test_api_refuses_what_it_used_to_accept(bar):
    dfm = bar.deformer
    with pytest.raises(SettingError, match=r"anderson_window must be an integer in \[0, 100\]"):
        dfm.solve(anderson_window=-3)
    with pytest.raises(SettingError, match=r"max_iterations must be an integer in \[1, 1000000\]"):
        dfm.solve(max_iterations=10**12)  # was a 29 TiB allocation
    with pytest.raises(SettingError, match=r"tolerance must be a number in \(0, 0.1\]"):
        dfm.solve(tolerance=1e6)
    with pytest.raises(SettingError, match=r"alpha must be a number in \[0.0001, 100\]"):
        type(dfm)(bar.cage, bar.anchors, alpha=1e30)
    with pytest.raises(SettingError, match=r"memory_budget must be an integer in \[1, "):
        dfm.bind(bar.points[:10], memory_budget=-1)  # was NaN results
    with pytest.raises(SettingError, match="memory_budget"):
        chunk_rows(20, 0, 0)
    with pytest.raises(SettingError, match="chunk_size"):
        evaluate_basis(bar.points[:5], bar.cage.vertices, bar.cage.faces, backend="numpy",
                       chunk_size=-1)  # fmt: skip


def test_scene_fields_are_refused_naming_the_field(bar):
    base = bar.scene.to_dict()
    for field, value in [
        ("max_iterations", 1e12),
        ("tolerance", 1e6),
        ("steps", 1e9),
        ("anderson_window", -3),
    ]:
        d = json.loads(json.dumps(base))
        d["solver"][field] = value
        with pytest.raises(SceneError, match=rf"scene field 'solver.{field}': must be "):
            Scene.from_dict(d)
    d = json.loads(json.dumps(base))
    d["alpha"] = 1e30
    with pytest.raises(SceneError, match=r"scene field 'alpha': must be a number in \[0.0001"):
        Scene.from_dict(d)
    # overrides given to Scene.solve go through the same ranges (steps = 1e9 used to hang)
    with pytest.raises(SceneError, match="solver.steps"):
        bar.scene.solve(bar.scene.build(), steps=10**9)


# ------------------------------------------------------------------ the cap
@pytest.mark.parametrize("window", [0, 10])
@pytest.mark.parametrize("cap", [1, 2, 7])
def test_iterations_never_exceed_the_cap(bar, cap, window):
    rep = bar.deformer.solve(max_iterations=cap, init="identity", anderson_window=window)
    assert not rep.converged
    assert rep.iterations == cap  # was cap + 1 (the final plain step)
    assert len(rep.energy) == rep.iterations + 1
    assert np.isfinite(rep.energy).all()


def test_converged_solves_report_the_same_count_as_before(bar):
    rep = bar.deformer.solve(init="identity")
    assert rep.converged and rep.iterations < 1000
    again = bar.deformer.solve(init="identity", max_iterations=rep.iterations)
    assert again.converged and again.iterations == rep.iterations


# ------------------------------------------------------------------ the command line
@pytest.fixture(scope="module")
def capped_scene(bar, tmp_path_factory):
    """The bar and a scene whose solver stops at 20 iterations (bend-u needs ~180)."""
    folder = tmp_path_factory.mktemp("capped")
    bar.surface.save(folder / "bar.vtp")
    scene = Scene.from_dict(bar.scene.to_dict())
    scene.solver["max_iterations"] = 20
    scene.save(folder / "scene.json")
    return folder


def test_not_converged_is_a_distinct_exit_status_and_writes_nothing(capped_scene, capsys):
    from vhm_viz.cli import EXIT_NOT_CONVERGED, main

    folder = capped_scene
    (folder / "old.vtp").write_bytes(b"previous output")
    args = ["deform", str(folder / "bar.vtp"), "-s", str(folder / "scene.json"), "-q"]
    assert main([*args, "-o", str(folder / "old.vtp")]) == EXIT_NOT_CONVERGED == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not converged" in err and "max_iterations = 20" in err
    assert (folder / "old.vtp").read_bytes() == b"previous output"

    # (stopped that early, the map folds the bar too: that needs its own consent)
    assert main([*args, "-o", str(folder / "new.vtp"), "--allow-unconverged"]) == 4
    assert not (folder / "new.vtp").exists()
    capsys.readouterr()
    allowed = ["--allow-unconverged", "--allow-folds"]
    assert main([*args, "-o", str(folder / "new.vtp"), *allowed]) == 0
    out = capsys.readouterr().out
    assert "20 iterations (not converged)" in out  # never 21: the cap holds
    assert (folder / "new.vtp").stat().st_size > 0

    report = folder / "report"
    args = ["analyze", str(folder / "bar.vtp"), "-s", str(folder / "scene.json"), "-q"]
    assert main([*args, "-o", str(report)]) == EXIT_NOT_CONVERGED
    assert not report.exists() or not list(report.iterdir())
    capsys.readouterr()
    assert main([*args, "-o", str(report), "--allow-unconverged"]) == 0
    metrics = json.loads((report / "metrics.json").read_text())
    assert metrics["iterations"] == 20 and metrics["converged"] is False


def test_bad_arguments_exit_2(capsys):
    from vhm_viz.cli import main

    with pytest.raises(SystemExit) as info:
        main(["deform"])  # INPUT, --scene and -o missing: argparse's usage error
    assert info.value.code == 2
    assert main([]) == 2  # no command
    capsys.readouterr()


def test_an_allowed_unconverged_ramp_says_so_in_both_commands(tmp_path, capsys):
    """analyze, like deform, says "(not converged)" on its line and warns on stderr; the
    cap holds for each step of a ramp, and the count adds up the steps."""
    from conftest import box_cage, data_path

    from vhm_viz.cli import main
    from vhm_viz.io import read_dataset

    src = data_path("hand_tet", "hand.mesh")
    mesh = read_dataset(src)
    p = np.asarray(mesh.points)
    lo, hi = p.min(0), p.max(0)
    verts, faces = box_cage(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo), 2)
    axis = int(np.argmax(hi - lo))
    positions = np.vstack([p[np.argmin(p[:, axis])], p[np.argmax(p[:, axis])]])
    targets = positions.copy()
    targets[1, (axis + 1) % 3] += 0.3 * (hi - lo)[axis]
    scene = Scene.from_dict({
        "format": "vhm_viz.scene", "version": 1,
        "cage": {"vertices": verts.tolist(), "faces": faces.tolist()},
        "anchors": {"auto": 8},
        "constraints": {"positions": positions.tolist(), "targets": targets.tolist()},
        "solver": {"max_iterations": 5, "tolerance": 1e-9, "steps": 2},
    })  # fmt: skip
    scene.save(tmp_path / "scene.json")
    reports = Scene.load(tmp_path / "scene.json").solve_map(mesh).reports
    assert [r.iterations for r in reports] == [5, 5] and not reports[-1].converged

    args = [str(src), "-s", str(tmp_path / "scene.json"), "-q", "--allow-unconverged"]
    for command, out in (("analyze", tmp_path / "report"), ("deform", tmp_path / "out.vtu")):
        assert main([command, *args, "-o", str(out)]) == 0
        line, err = capsys.readouterr()
        assert "10 iterations in 2 steps (not converged)" in line
        assert err.count("\n") == 1 and err.startswith(
            f"vhm-viz {command}: warning: not converged: the solver stopped at "
            "solver.max_iterations = 5 in the last of its 2 solver.steps with the estimated "
            "distance to the solution "
        ), err
    metrics = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert metrics["iterations"] == 10 and metrics["converged"] is False
