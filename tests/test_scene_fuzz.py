"""Scene fuzz: mutated scene files through the scene loader and ``vhm-viz deform``.

Deterministic (seeded) mutations of the bundled scenes and of an inline-cage scene --
wrong types, NaN and infinities, empty and huge arrays, deep nesting, unknown keys,
unicode and odd paths, references to missing and to huge files -- go through the public
loader (``Scene.load`` then ``Scene.build``: the cage and anchor files are read, the
constraints checked), and a sample through the real command line in subprocesses. Every
case is a valid scene or an error of the library's named kinds (a ``ValueError`` naming
the problem, or a missing file) with a one-line message; no input file may change.
Absurd sizes (10**7 anchors, 10**7 cage faces) are refused from their counts, before the
arrays are built.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyvista")

from conftest import UTF8, box_cage, subprocess_env  # noqa: E402

from vhm_viz.core.errors import CageError, ConstraintError, OutsideCageError, SettingError
from vhm_viz.io.errors import ReadError
from vhm_viz.scene import Scene
from vhm_viz.scene_fields import MAX_SCENE_BYTES, SceneError

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "vhm_viz" / "scenes"
#: The errors a bad scene may end in: each names its problem in one line.
NAMED = (SceneError, ReadError, CageError, ConstraintError, OutsideCageError, SettingError,
         FileNotFoundError, IsADirectoryError, PermissionError)  # fmt: skip
ODD_PATHS = ["", " ", "ünïcødé/çage.obj", "кейдж.obj", "\u202ecage.obj", "a" * 5000,
             "/dev/null", "/dev/zero", "/", ".", "..", "~nobody_here/x.obj",
             "C:\\cage\\x.obj", "../../../../../../nonexistent.obj", "cage.obj\n",
             "nul\u0000byte.obj", "\ud800.obj", "missing.obj", "huge.obj", "huge.json",
             "folder.obj", "bar_scene.json", "bar_cage.obj?x=1",
             "file:///bar_cage.obj"]  # fmt: skip
ODD_VALUES = ["x", "", 3, -1, 0, 1.5, 1e308, -0.0, 10**30, 2**63, True, False, None, [], {},
              [1, 2], [[1, 2, 3]], {"a": 1}, "1.0", [None, None, None],
              [[1, 2, 3, 4]], [["a", "b", "c"]], [[[1, 2, 3]]]]  # fmt: skip
ODD_KEYS = ["extra", "", "ü", "\u0000", "constraints ", "Cage", "__proto__", "x" * 300]


def _digest(folder: Path) -> dict:
    """Checksums of the files of ``folder`` (the sparse huge ones by their size)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        if p.stat().st_size < 10**7 else p.stat().st_size
        for p in sorted(folder.rglob("*")) if p.is_file()
    }  # fmt: skip


def _paths(node, prefix=()):
    """Every path (tuple of keys and indices) into a JSON value, the root included."""
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node[:4]):
            yield from _paths(v, (*prefix, i))


def _replace(doc, path, value):
    if not path:
        return value
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    parent[path[-1]] = value
    return doc


def _get(doc, path):
    for key in path:
        doc = doc[key]
    return doc


DEEP = '"@@deep@@"'


def _mutate(base: dict, rng) -> tuple[str, str]:
    """One mutation of ``base``: its kind, and the scene's JSON text."""
    doc = copy.deepcopy(base)
    paths = list(_paths(doc))
    path = paths[int(rng.integers(len(paths)))]
    kind = ["type", "nonfinite", "empty", "huge", "deep", "key", "path", "drop", "text",
            "number", "wrap"][int(rng.integers(11))]  # fmt: skip
    deep_text = None
    if kind == "type":
        doc = _replace(doc, path, copy.deepcopy(ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]))
    elif kind == "nonfinite":
        bad = [math.nan, math.inf, -math.inf][int(rng.integers(3))]
        numeric = [p for p in paths if isinstance(_get(doc, p), (int, float))]
        doc = _replace(doc, numeric[int(rng.integers(len(numeric)))] if numeric else path, bad)
    elif kind == "empty":
        doc = _replace(doc, path, [[], {}, ""][int(rng.integers(3))])
    elif kind == "huge":
        size = int(rng.choice([10**5 + 1, 2 * 10**5 + 1]))
        doc = _replace(doc, path, [[0.125, 0.25, 0.5]] * size)
    elif kind == "deep":
        depth = int(rng.choice([50, 1000, 100000]))
        opener = "[" if rng.integers(2) else '{"a":'
        closer = "]" if opener == "[" else "}"
        deep_text = opener * depth + "1" + closer * depth
        doc = _replace(doc, path, "@@deep@@")
    elif kind == "key":
        dicts = [p for p in paths if isinstance(_get(doc, p), dict)]
        target = _get(doc, dicts[int(rng.integers(len(dicts)))])
        target[ODD_KEYS[int(rng.integers(len(ODD_KEYS)))]] = ODD_VALUES[int(rng.integers(5))]
    elif kind == "path":
        odd = ODD_PATHS[int(rng.integers(len(ODD_PATHS)))]
        where = [("cage",), ("anchors",), ("data",), ("cage", "path"), ("anchors", "path")]
        key = where[int(rng.integers(len(where)))]
        if len(key) == 2:
            doc[key[0]] = {key[1]: odd}
        elif key == ("anchors",) and rng.integers(2):
            doc["anchors"] = {"polylines": odd, "count": 5}
        else:
            doc[key[0]] = odd
    elif kind == "drop":
        if path:
            parent = _get(doc, path[:-1])
            del parent[path[-1]]
    elif kind == "text":
        doc = _replace(doc, path, ["NaN", "1e999", "\u00e9", "\ud83d\ude00", "0x10"][
            int(rng.integers(5))])  # fmt: skip
    elif kind == "number":
        numeric = [p for p in paths if isinstance(_get(doc, p), (int, float))]
        value = [1e308, -1e308, 5e-324, 10**30, -(2**63), 2**64, 0, -1][int(rng.integers(8))]
        doc = _replace(doc, numeric[int(rng.integers(len(numeric)))] if numeric else path, value)
    else:  # wrap a value in a list, or a list's value in another level
        doc = _replace(doc, path, [copy.deepcopy(_get(doc, path))])
    text = json.dumps(doc)
    if deep_text is not None:
        text = text.replace(DEEP, deep_text)
    return kind, text


def _inline_scene() -> dict:
    v, f = box_cage((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    return {
        "format": "vhm_viz.scene", "version": 1,
        "cage": {"vertices": v.tolist(), "faces": f.tolist()},
        "anchors": [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]],
        "constraints": {"positions": [[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]],
                        "targets": [[0.0, 0.0, 0.0], [0.6, 0.5, 0.5]],
                        "jacobian_points": [[0.0, 0.0, 0.0]],
                        "jacobians": [[[1, 0, 0], [0, 1, 0], [0, 0, 1]]]},
        "mode": "similar", "alpha": 0.01,
        "solver": {"max_iterations": 50, "tolerance": 1e-6, "init": "identity", "steps": 1,
                   "anderson_window": 5},
        "solution": {"rotations": [np.eye(3).tolist()] * 4, "contraction": 0.5},
    }  # fmt: skip


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """The bundled scenes and their files, an inline scene, a huge and a missing file."""
    d = tmp_path_factory.mktemp("scene_fuzz")
    for p in SCENES.iterdir():
        shutil.copy(p, d / p.name)
    (d / "inline_scene.json").write_text(json.dumps(_inline_scene()))
    for name in ("huge.obj", "huge.json"):  # sparse: 2**33 bytes of zeros, no disk used
        with open(d / name, "wb") as fh:
            fh.truncate(2**33)
    (d / "folder.obj").mkdir()
    return d


def _bases(folder: Path) -> list[dict]:
    return [json.loads((folder / n).read_text())
            for n in ("bar_scene.json", "head_scene.json", "inline_scene.json")]  # fmt: skip


def _raised_by_vhm_viz(exc: BaseException) -> bool:
    """Whether ``exc`` was raised by vhm_viz's own code (a message written for the user)."""
    tb = exc.__traceback__
    while tb.tb_next is not None:
        tb = tb.tb_next
    return f"{os.sep}vhm_viz{os.sep}" in tb.tb_frame.f_code.co_filename


def _outcome(path: Path, build: bool = True) -> str:
    """``"ok"`` or the error's one line; anything but a named error fails the test.

    Named: the library's error kinds, or a ``ValueError`` raised by vhm_viz itself. The
    scene is loaded, its cage and anchors read; with ``build`` the deformer is built too
    (its constraints checked against the cage).
    """
    try:
        scene = Scene.load(path)
        if build:
            scene.build()
        else:
            scene.build_anchors(scene.build_cage())
    except Exception as exc:  # noqa: BLE001 -- what the fuzz is for: judge the error
        text = str(exc).strip()
        named = isinstance(exc, NAMED) or (type(exc) is ValueError and _raised_by_vhm_viz(exc))
        assert named, f"{path.name}: {type(exc).__name__}: {text[:200]}"
        assert text and "\n" not in text, f"{path.name}: not one line: {text!r}"
        return text
    return "ok"


def test_bundled_scenes_are_valid(folder):
    for name in ("bar_scene.json", "head_scene.json", "inline_scene.json"):
        assert _outcome(folder / name) == "ok"


def test_mutated_scenes_are_valid_or_one_named_error(folder):
    """600 mutations: each loads and builds, or ends in one named, one-line error."""
    rng = np.random.default_rng(36)
    bases = _bases(folder)
    before = _digest(folder)
    cases = folder / "cases"
    cases.mkdir()
    outcomes: dict[str, list[str]] = {}
    for i in range(600):
        kind, text = _mutate(bases[i % len(bases)], rng)
        # the scenes refer to their files relative to their folder: cases sit beside them
        path = folder / f"case{i:03d}_{kind}.json"
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
        # the bar's cage makes a deformer slow to build: its scenes are read, not built
        outcomes.setdefault(kind, []).append(_outcome(path, build=i % len(bases) != 0))
        path.rename(cases / path.name)
    after = {k: v for k, v in _digest(folder).items() if not k.startswith("cases/")}
    assert after == before, "an input file changed"
    # the mutations reach the checks: most kinds give both outcomes over the run
    errors = sum(o != "ok" for v in outcomes.values() for o in v)
    assert 300 < errors < 600, {k: sum(o == "ok" for o in v) for k, v in outcomes.items()}


def test_absurd_counts_are_refused_before_the_arrays_exist(folder):
    """10**7 anchors, 10**7 cage faces, 10**7 constraints: refused from the list's length."""
    base = _bases(folder)[2]
    point = [0.125, 0.25, 0.5]
    for path, value in (
        (("anchors",), [point] * 10**7),
        (("cage", "faces"), [[0, 1, 2]] * 10**7),
        (("cage", "vertices"), [point] * 10**7),
        (("constraints", "positions"), [point] * 10**7),
    ):
        doc = _replace(copy.deepcopy(base), path, value)
        with pytest.raises(SceneError, match="at most") as err:
            Scene.from_dict(doc)
        assert err.value.field == ".".join(path)


def test_a_scene_file_beyond_the_size_limit_is_refused_unread(folder):
    """A scene file larger than MAX_SCENE_BYTES (what 10**7 anchors take) is refused from
    its size, in a child whose address space could not hold its parse."""
    big = folder / "big_scene.json"
    with open(big, "wb") as fh:
        fh.write(b'{"format": "vhm_viz.scene", "version": 1, "anchors": [')
        fh.truncate(MAX_SCENE_BYTES + 1)
    # the child's limit: the address space it uses after the imports, plus half the file
    code = (
        "import resource, sys\n"
        "from pathlib import Path\n"
        "from vhm_viz.scene import Scene\n"
        "status = Path('/proc/self/status').read_text().split('VmSize:')[1].split()[0]\n"
        "limit = int(status) * 1024 + int(sys.argv[2])\n"
        "resource.setrlimit(resource.RLIMIT_AS, (limit, limit))\n"
        "try:\n"
        "    Scene.load(sys.argv[1])\n"
        "except ValueError as exc:\n"
        "    print(type(exc).__name__, exc)\n"
    )
    argv = [sys.executable, "-c", code, str(big), str(MAX_SCENE_BYTES // 2)]
    done = subprocess.run(argv, capture_output=True, env=subprocess_env(), timeout=120, **UTF8)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert done.stdout.startswith("SceneError") and "at most" in done.stdout, done.stdout


CLI_KINDS = ("type", "nonfinite", "path", "deep", "huge", "key")


def test_cli_sample_one_line_or_output(folder, tmp_path):
    """16 mutations through ``vhm-viz deform`` and ``vhm-viz analyze`` in subprocesses:
    exit 0 with an output, or a non-zero exit with one line on stderr; no traceback."""
    rng = np.random.default_rng(3636)
    bases = _bases(folder)[:2]  # the bundled scenes: the bar and the head
    data = {0: "bar", 1: "head"}
    bar = tmp_path / "bar.vtp"
    head = tmp_path / "head.vti"
    import pyvista as pv

    pv.Cylinder(center=(0, 0, 2.5), direction=(0, 0, 1), radius=0.3, height=4.5).triangulate(
    ).save(bar)  # fmt: skip
    pv.ImageData(dimensions=(6, 6, 6), spacing=(36.0, 36.0, 24.0), origin=(10.0, 10.0, 10.0)
                 ).save(head)  # fmt: skip
    before = _digest(folder)
    runs = 0
    while runs < 16:
        which = runs % 2
        kind, text = _mutate(bases[which], rng)
        if kind not in CLI_KINDS and runs % 3:
            continue
        scene = folder / f"cli{runs:02d}.json"
        scene.write_text(text, encoding="utf-8", errors="surrogatepass")
        src = bar if data[which] == "bar" else head
        command = "analyze" if runs % 5 == 4 else "deform"
        out = tmp_path / f"out{runs}{'' if command == 'analyze' else src.suffix}"
        argv = [sys.executable, "-m", "vhm_viz.cli", command, str(src), "--scene", str(scene),
                "-o", str(out), "-q", "--outside", "passthrough"]  # fmt: skip
        done = subprocess.run(argv, capture_output=True, env=subprocess_env(), timeout=300, **UTF8)
        lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
        assert "Traceback" not in done.stderr, (kind, done.stderr)
        if done.returncode == 0:
            assert out.exists(), (kind, done.stderr)
        else:
            assert done.returncode in (1, 2, 3) and len(lines) == 1, (kind, done.stderr)
            assert not out.exists()
        scene.rename(tmp_path / scene.name)
        runs += 1
    assert _digest(folder) == before
