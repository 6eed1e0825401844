"""MPI faults in the ParaView plugin: an error on one rank ends the request on every rank.

A real fault on one rank only: a cage that stops short of the CT head's top planes, so
that (with the default outside policy, "error") only the rank whose piece holds those
planes fails. Every rank must end the request with the same one-line error and an empty
output, and the run must end (no rank left waiting in a collective): 3 ranks and 2 ranks
(uneven pieces: 93 planes), for the three filters, and 3 ranks on a 2-plane volume (a
rank with an empty piece). ``tests/paraview/rank_errors.py`` prints each rank's state.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
import test_paraview
from conftest import DATA, data_path

paraview_env = test_paraview.paraview_env  # the fixture: ParaView with the plugin

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "paraview" / "rank_errors.py"
TOP = 110.0  # the cage's top (mm): the head's planes above it (z > 110) are outside


@pytest.fixture(scope="module")
def short_scene(tmp_path_factory) -> tuple[Path, Path]:
    """A scene on a box cage that covers the CT head's planes 0 to 73 of 93."""
    tmp = tmp_path_factory.mktemp("pv_faults")
    lo, hi = -3.17, 204.77
    v = [(x, y, z) for x in (lo, hi) for y in (lo, hi) for z in (lo, TOP)]
    f = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7),
         (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]  # fmt: skip
    cage = tmp / "short_cage.obj"
    cage.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f))  # fmt: skip
    scene = {
        "format": "vhm_viz.scene", "version": 1, "cage": str(cage),
        "anchors": [[100.8, 100.8, 20.0], [100.8, 100.8, 60.0], [100.8, 100.8, 95.0],
                    [50.0, 50.0, 50.0], [150.0, 150.0, 50.0]],
        "constraints": {"positions": [[100.8, 100.8, 13.8], [100.8, 100.8, 100.0]],
                        "targets": [[100.8, 100.8, 13.8], [110.0, 100.8, 98.0]]},
    }  # fmt: skip
    (tmp / "scene.json").write_text(json.dumps(scene))
    return tmp / "scene.json", cage


def _ranks_end(env, config: dict, ranks: int, tmp_path: Path, states=None) -> list[str]:
    """Each rank's ``last_error`` after the update (the run must end, exit 0).

    ``states``, a list: each rank's ``(warnings, has a fold summary)`` is added to it.
    """
    path = tmp_path / f"{config['filter']}{ranks}.json"
    path.write_text(json.dumps(config))
    from vhm_viz.filters.mpi import mpi_command

    cmd, env = mpi_command(["pvbatch", "--symmetric", str(SCRIPT), str(path)], ranks, env)
    cmd.insert(1, "--oversubscribe")  # more ranks than this machine's cores
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-3000:]
    assert "Traceback" not in log
    found = sorted(re.findall(r"vhm-rank (\d+): points (\d+) error (.*?) vhm-end", done.stdout))
    assert [int(r) for r, _, _ in found] == list(range(ranks)), log[-3000:]
    assert all(n == "0" for _, n, _ in found), found  # an empty output everywhere
    if states is not None:
        state = sorted(re.findall(r"vhm-state (\d+): warnings (\d+) folds (\w+) vhm-end", log))
        states.extend((int(w), f == "True") for _, w, f in state)
    return [text for _, _, text in found]


def _config(scene, cage, flt: str, **extra) -> dict:
    return {"input": str(data_path("volumes", "headsq_64x64x93.vti")), "filter": flt,
            "scene": str(scene), "cage": str(cage), **extra}  # fmt: skip


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
@pytest.mark.parametrize(
    "flt", ["VHMHarmonicDeformation", "VHMJacobianAnalysis", "VHMResampleToImage"]
)
def test_a_failing_piece_ends_every_rank_with_its_error(paraview_env, short_scene, flt, tmp_path):
    """3 ranks, the top piece outside the cage: every rank ends with the same one line."""
    scene, cage = short_scene
    errors = _ranks_end(paraview_env, _config(scene, cage, flt), 3, tmp_path)
    assert len(set(errors)) == 1, errors
    assert "outside the cage" in errors[0] and "\n" not in errors[0]


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_two_ranks_uneven_pieces_agree(paraview_env, short_scene, tmp_path):
    """2 ranks on 93 planes (47 and 46): the top half fails, both end with its error."""
    scene, cage = short_scene
    errors = _ranks_end(paraview_env, _config(scene, cage, "VHMHarmonicDeformation"), 2,
                        tmp_path)  # fmt: skip
    assert len(set(errors)) == 1 and "outside the cage" in errors[0], errors


@pytest.mark.skipif(not DATA.is_dir(), reason="needs ../shared/data")
def test_a_rank_with_an_empty_piece_ends_with_the_error_too(paraview_env, short_scene, tmp_path):
    """3 ranks on 2 planes (one inside the cage, one above it): one rank fails, one has
    an empty piece; all three end with the failing rank's error."""
    scene, cage = short_scene
    config = _config(scene, cage, "VHMHarmonicDeformation", voi=[30, 30, 30, 30, 73, 74])
    errors = _ranks_end(paraview_env, config, 3, tmp_path)
    assert len(set(errors)) == 1 and "outside the cage" in errors[0], errors


def test_an_update_that_fails_before_its_work_leaves_no_warnings_of_the_last(
    paraview_env, tmp_path
):
    """The warp of a folding volume says its folds; the next update, whose cage reaches
    rank 0 only, fails on every rank before any work: every rank ends with an empty
    output and no warning or fold summary left over from the output before."""
    from conftest import write_folding_volume

    from vhm_viz.scene import Scene

    write_folding_volume(tmp_path, record_map=True)
    cage = Scene.load(tmp_path / "scene.json").build_cage()
    path = tmp_path / "cage.obj"
    faces = "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in cage.faces)
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in cage.vertices) + faces)
    config = {"input": str(tmp_path / "image.vti"), "filter": "VHMHarmonicDeformation",
              "scene": str(tmp_path / "scene.json"), "cage": str(path),
              "cage_on_rank_0_only": True}  # fmt: skip
    states = []
    errors = _ranks_end(paraview_env, config, 2, tmp_path, states)
    assert len(set(errors)) == 1 and "every rank needs the whole cage" in errors[0], errors
    assert states == [(0, False), (0, False)]
