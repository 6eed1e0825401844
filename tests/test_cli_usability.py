"""The command line's manners: stated defaults and units, and logs without bar drawing."""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import subprocess_env

pv = pytest.importorskip("pyvista")

from vhm_viz import examples  # noqa: E402
from vhm_viz.cli import build_parser  # noqa: E402

COMMANDS = ("deform", "analyze", "cage", "anchors", "demo")


def _subparsers():
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return {name: sub.choices[name] for name in COMMANDS}


def _valued_options(parser):
    """The options that take a value (not flags, not positionals, not --help)."""
    return [
        a
        for a in parser._actions
        if a.option_strings and a.nargs != 0 and not isinstance(a, argparse._HelpAction)
    ]


def test_every_valued_option_states_its_default(capsys):
    checked = 0
    for name, parser in _subparsers().items():
        parser.print_help()
        # what the user reads, without the wrapping (argparse also breaks after hyphens)
        text = "".join(capsys.readouterr().out.split())
        for action in _valued_options(parser):
            option = "/".join(action.option_strings)
            if action.required:  # nothing to default to
                continue
            helptext = " ".join((action.help or "").split())
            assert "(default: " in helptext, f"{name} {option}: no default stated"
            shown_help = "".join(helptext.replace("%%", "%").split())
            assert shown_help in text, f"{name} {option}: help not shown"
            default = action.default
            if default not in (None, ""):
                shown = f"{default:g}" if isinstance(default, float) else str(default)
                stated = helptext.split("(default: ", 1)[1]
                assert stated.startswith(shown), f"{name} {option}: {shown} not stated"
            checked += 1
    assert checked >= 20


@pytest.mark.parametrize(
    ("command", "option", "unit"),
    [
        ("deform", "--tolerance", "voxels"),
        ("deform", "--fill-value", "units of the data"),
        ("deform", "--spacing", "world units"),
        ("cage", "--offset", "world units"),
        ("cage", "--offset", "of the bounding-box diagonal"),
        ("cage", "--resolution", "voxels"),
        ("cage", "--threshold", "units of the data"),
        ("anchors", "--resolution", "voxels"),
        ("anchors", "--threshold", "units of the data"),
        ("demo", "--voxel", "bar's units"),
        ("demo", "--output", "current folder"),
    ],
)
def test_options_with_units_name_them(command, option, unit):
    parser = _subparsers()[command]
    (action,) = [a for a in parser._actions if option in a.option_strings]
    assert unit in " ".join(action.help.split())


@pytest.mark.parametrize(
    ("command", "argument", "kind"),
    [("cage", "input", "dataset"), ("anchors", "input", "dataset"), ("anchors", "cage", "cage")],
)
def test_input_help_names_the_suffixes_the_command_reads(command, argument, kind):
    """The help of an input lists exactly the suffixes the command accepts (the registry's),
    rather than promising any format PyVista reads, which the command then refuses."""
    from vhm_viz.io import CAGE_SUFFIXES, DATASET_SUFFIXES

    accepted = {"dataset": DATASET_SUFFIXES, "cage": CAGE_SUFFIXES}[kind]
    (action,) = [a for a in _subparsers()[command]._actions if a.dest == argument]
    named = set(re.findall(r"(?<![\w.])(\.[a-z]+(?:\.gz)?)\b", action.help))
    assert named == set(accepted), action.help


@pytest.fixture(scope="module")
def small_bar(tmp_path_factory):
    """A small bar and its bend-u scene, as files."""
    folder = tmp_path_factory.mktemp("bar")
    scenario = examples.bar("bend-u", resolution=8)
    scenario.scene.save(folder / "scene.json")
    pv.PolyData.from_regular_faces(scenario.points, scenario.triangles).save(folder / "bar.vtp")
    return folder


def _deform_command(folder, out):
    return [
        sys.executable,
        "-m",
        "vhm_viz.cli",
        "deform",
        str(folder / "bar.vtp"),
        "--scene",
        str(folder / "scene.json"),
        "-o",
        str(out),
    ]


def test_progress_is_plain_lines_when_piped(small_bar, tmp_path):
    res = subprocess.run(
        _deform_command(small_bar, tmp_path / "bent.vtp"),
        capture_output=True,
        text=True,
        env=subprocess_env(),
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    assert "\r" not in res.stderr
    lines = res.stderr.splitlines()
    progress = [ln for ln in lines if re.fullmatch(r"(solving|binding): +\d+%( [0-9.]+ s)?", ln)]
    assert {ln.split(":")[0] for ln in progress} == {"solving", "binding"}
    # each stage: a line every 10% at most, ending at 100% with the elapsed time
    for stage in ("solving", "binding"):
        mine = [ln for ln in progress if ln.startswith(stage)]
        assert 1 <= len(mine) <= 11
        assert re.fullmatch(rf"{stage}: 100% [0-9.]+ s", mine[-1])
    assert (tmp_path / "bent.vtp").is_file()


def test_progress_is_a_bar_on_a_terminal(small_bar, tmp_path):
    pty = pytest.importorskip("pty")
    master, slave = pty.openpty()
    proc = subprocess.Popen(
        _deform_command(small_bar, tmp_path / "bent.vtp"),
        stdout=subprocess.DEVNULL,
        stderr=slave,
        env=subprocess_env(),
    )
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 4096)
        except OSError:  # the terminal closed with the process
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    assert proc.wait(timeout=600) == 0
    text = b"".join(chunks).decode()
    assert "\rsolving   [" in text and "] 100%" in text


REPO = Path(__file__).resolve().parents[1]


def test_ci_demo_writes_relative_to_the_callers_folder(tmp_path):
    """``bash .ci/demo -o out`` from any folder: set-up runs in the repository, the demo in
    the caller's folder with the arguments as given.

    The script is run for real on a copy of the repository's layout whose set-up step is a
    stand-in (the real one installs system packages and a virtual environment) and whose
    ``.venv/bin/vhm-viz`` records the folder it runs in and its arguments.
    """
    repo = tmp_path / "repo"
    (repo / ".ci").mkdir(parents=True)
    (repo / ".venv" / "bin").mkdir(parents=True)
    shutil.copy2(REPO / ".ci" / "demo", repo / ".ci" / "demo")
    record = tmp_path / "record.txt"
    (repo / ".ci" / "setup").write_text(f'#!/usr/bin/env bash\necho "setup $PWD" >> "{record}"\n')
    exe = repo / ".venv" / "bin" / "vhm-viz"
    exe.write_text(
        f'#!/usr/bin/env bash\necho "vhm-viz $PWD" >> "{record}"\n'
        f'printf "%s\\n" "$@" >> "{record}"\n'
    )
    exe.chmod(0o755)
    caller = tmp_path / "caller"
    caller.mkdir()
    res = subprocess.run(
        ["bash", "../repo/.ci/demo", "-o", "out dir", "-q"],
        cwd=caller,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    assert record.read_text().splitlines() == [
        f"setup {repo}",
        f"vhm-viz {caller}",
        "demo",
        "-o",
        "out dir",
        "-q",
    ]


@pytest.mark.skipif(sys.prefix == sys.base_prefix, reason="not in a virtual environment")
def test_the_console_script_of_the_environment_runs():
    # what .ci/setup's `pip install -e .` puts in .venv/bin, as the README tells to run it
    exe = Path(sys.prefix) / "bin" / "vhm-viz"
    assert exe.is_file(), f"{exe} missing: the project is not installed in this environment"
    res = subprocess.run(
        [str(exe), "--help"], capture_output=True, text=True, env=subprocess_env(), timeout=120
    )
    assert res.returncode == 0, res.stderr
    assert all(name in res.stdout for name in (*COMMANDS, "explore"))
    res = subprocess.run(
        [str(exe), "--version"], capture_output=True, text=True, env=subprocess_env(), timeout=120
    )
    assert res.returncode == 0 and res.stdout.startswith("vhm-viz ")


def test_a_scene_uses_the_anchors_file_vhm_viz_anchors_writes(small_bar, tmp_path, capsys):
    """anchors -> a scene naming the file -> deform, against the same map built directly
    from the file's contents (read with plain json)."""
    import json

    import numpy as np

    from vhm_viz.cli import main
    from vhm_viz.io import read_anchors, write_cage

    bar = small_bar / "bar.vtp"
    work = tmp_path / "scene dir"
    work.mkdir()
    write_cage(work / "cage.obj", examples.bar_cage())  # the bar's box cage, 208 faces
    assert main(["anchors", str(bar), "--cage", str(work / "cage.obj"), "-o",
                 str(work / "anchors.json"), "-n", "10", "-q"]) == 0  # fmt: skip
    capsys.readouterr()
    written = json.loads((work / "anchors.json").read_text())
    anchors = np.array(written["anchors"], dtype=float)
    assert anchors.shape == (10, 3)
    # the explorer's "load anchors" reads the file the same way
    np.testing.assert_array_equal(read_anchors(work / "anchors.json"), anchors)

    constraints = json.loads((small_bar / "scene.json").read_text())["constraints"]
    scene = {
        "format": "vhm_viz.scene",
        "version": 1,
        "cage": "cage.obj",  # relative to the scene file
        "anchors": "anchors.json",
        "constraints": constraints,
    }
    (work / "scene.json").write_text(json.dumps(scene))
    out = tmp_path / "bent.vtp"
    rc = main(["deform", str(bar), "--scene", str(work / "scene.json"), "-o", str(out), "-q"])
    _, err = capsys.readouterr()
    assert rc == 0, err

    rest = pv.read(bar)
    expected = _direct_map(work / "cage.obj", anchors, constraints, rest.points)
    bent = pv.read(out)
    assert np.abs(expected - rest.points).max() > 1.0  # it did bend
    np.testing.assert_allclose(bent.points, expected, atol=1e-6)


def _direct_map(cage_path, anchors, constraints, points):
    """The scene's map at ``points``, built from the files' contents with the API."""
    import numpy as np

    from vhm_viz import Deformer
    from vhm_viz.io import read_cage

    dfm = Deformer(read_cage(cage_path), np.asarray(anchors, dtype=float))
    c = {k: np.array(v, dtype=float) for k, v in constraints.items()}
    dfm.set_constraints(
        positions=c["positions"],
        targets=c["targets"],
        jacobian_points=c.get("jacobian_points", np.zeros((0, 3))),
        jacobians=c.get("jacobians", np.zeros((0, 3, 3))),
    )
    report = dfm.solve(init="identity", max_iterations=1000, tolerance=1e-6)
    assert report.converged
    return dfm.harmonic_map.map(np.asarray(points, dtype=float))


def test_the_readme_scene_is_the_example_file_and_it_works(tmp_path, capsys):
    """The README shows docs/examples/bar_scene.json as it is, explains each of its fields,
    and the scene bends the bar as a Deformer built from its files does."""
    import json

    import numpy as np

    from vhm_viz.cli import main
    from vhm_viz.scene_fields import DEFAULT_SOLVER, SCENE_FIELDS

    readme = (REPO / "README.md").read_text(encoding="utf-8")
    folder = REPO / "vhm_viz" / "scenes"
    text = (folder / "bar_scene.json").read_text()
    assert "```json\n" + text.rstrip("\n") + "\n```" in readme
    section = readme.split("#### A scene, field by field", 1)[1].split("\n### ", 1)[0]
    table = [ln for ln in section.splitlines() if ln.startswith("| `")]
    for name in [*SCENE_FIELDS, *(f"solver.{k}" for k in DEFAULT_SOLVER)]:
        assert any(f"`{name}`" in row or f"`{name}." in row for row in table), name
    for key in ("positions", "targets", "jacobian_points", "jacobians"):
        assert any(f"`constraints.{key}`" in row for row in table), key

    scene = json.loads(text)
    surface = pv.PolyData.from_regular_faces(*examples.bar_surface(12))
    surface.save(tmp_path / "bar.vtp")
    out = tmp_path / "bent.vtp"
    rc = main(["deform", str(tmp_path / "bar.vtp"), "--scene", str(folder / "bar_scene.json"),
               "-o", str(out), "-q"])  # fmt: skip
    _, err = capsys.readouterr()
    assert rc == 0, err
    anchors = json.loads((folder / "bar_anchors.json").read_text())["anchors"]
    expected = _direct_map(folder / "bar_cage.obj", anchors, scene["constraints"], surface.points)
    np.testing.assert_allclose(pv.read(out).points, expected, atol=1e-6)
    # the top's centre went exactly to its target (a hard constraint)
    (top,) = np.nonzero(np.linalg.norm(surface.points - np.array([0, 0, 5.0]), axis=1) < 1e-9)
    np.testing.assert_allclose(pv.read(out).points[top], [[3.18, 0, 0]], atol=1e-6)


def test_explore_refuses_what_it_cannot_open_before_a_window_opens(small_bar, tmp_path):
    """`vhm-viz explore` with a missing FILE, --cage or --scene, or a scene with a typo'd
    field, is one error line naming it and exit status 1, as `deform` says it; without
    the check the window opens with a dialog and the command never returns."""
    import json

    from vhm_viz.cli.first_run import NOTICE

    scene = json.loads((small_bar / "scene.json").read_text())
    scene["alhpa"] = scene.pop("alpha")
    (tmp_path / "typo.json").write_text(json.dumps(scene))
    bar = str(small_bar / "bar.vtp")
    cases = {
        (str(tmp_path / "missing.obj"),): "input file not found: ",
        (bar, "--cage", str(tmp_path / "nocage.obj")): "input file not found: ",
        (bar, "--scene", str(tmp_path / "missing.json")): "scene file not found: ",
        (bar, "--scene", str(tmp_path / "typo.json")): "scene field 'alhpa': unknown field",
    }
    env = subprocess_env()
    env["QT_QPA_PLATFORM"] = "offscreen"  # the window, were one opened, shows nowhere
    for args, message in cases.items():
        try:
            res = subprocess.run(
                [sys.executable, "-m", "vhm_viz.cli", "explore", *args],
                capture_output=True, text=True, env=env, timeout=300,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            pytest.fail(f"explore {' '.join(args)} opened a window instead of refusing")
        lines = [ln for ln in res.stderr.splitlines() if ln.strip() and ln != NOTICE]
        assert res.returncode == 1, res.stderr
        assert len(lines) == 1 and lines[0].startswith("vhm-viz explore: error: "), lines
        assert message in lines[0], lines
    # a bar that does not exist is an argument error (exit 2), with the kinds there are
    try:
        res = subprocess.run(
            [sys.executable, "-m", "vhm_viz.cli", "explore", "--bar", "bend"],
            capture_output=True, text=True, env=env, timeout=300,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail("explore --bar bend opened a window instead of refusing")
    assert res.returncode == 2, res.stderr
    assert res.stderr.splitlines()[-1] == (
        "vhm-viz explore: error: argument --bar: invalid choice: 'bend' (choose from "
        "'bend-u', 'bend-90', 'twist', 'bulge', 'push')"
    )


def test_deform_help_names_the_resampled_suffixes_and_its_example_runs(tmp_path):
    """The help's list of suffixes a volume is resampled to is the registry's, and its
    example command runs as printed in the folder where `vhm-viz demo` was run."""
    import shlex

    from vhm_viz.io import image_suffixes

    parser = _subparsers()["deform"]
    text = " ".join(parser.description.split())
    listed = text.split("written to ", 2)[2].split(" it is resampled")[0]
    assert listed.split(", ") == list(image_suffixes()), listed

    example = " ".join(parser.epilog.split()).split("Example: ", 1)[1]
    example, after = example.split(" (after ")
    env = subprocess_env()
    demo = ["demo", "--resolution", "6", "--voxel", "0.25", "--no-tets", "-q"]
    assert after.rstrip(")").split() == ["vhm-viz", "demo"]
    cli = [sys.executable, "-m", "vhm_viz.cli"]
    res = subprocess.run([*cli, *demo], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    words = shlex.split(example)
    assert words[0] == "vhm-viz"
    res = subprocess.run([*cli, *words[1:]], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / words[words.index("-o") + 1]).is_file()
