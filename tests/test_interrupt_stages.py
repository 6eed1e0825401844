"""A signal in any stage of a volume warp ends the command at once, the old output intact.

Each stage (read, solve, map, checks, write) of ``vhm-viz deform`` on the CT head gets a
signal as soon as the command shows that the stage has begun: the reader's child process
exists (read), it has ended (solve, a moment later), the warp's progress starts (map),
the fold check's progress starts (checks), the output's temporary or staging folder
appears (write). The command must
then stop in that very stage (its ``--timings`` line ends with it), exit with 128 + the
signal, and leave the previous output byte-identical with no temporary beside it.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import data_path

from vhm_viz.scene import Scene

SCENE = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"
OLD = b"the previous output, which must survive\n"


def _has_child(proc) -> bool:
    try:
        return bool(Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split())
    except OSError:
        return False


def _stage_began(stage: str, proc, text: str, folder: Path, seen: dict) -> bool:
    if stage == "read":  # the reader runs in a child process
        return _has_child(proc)
    if stage == "solve":  # a moment after the reader's child has ended: inside the solve
        if "child_gone" not in seen:
            child = _has_child(proc)
            if seen.get("child") and not child:
                seen["child_gone"] = time.monotonic()
            seen["child"] = seen.get("child") or child
            return False
        return time.monotonic() > seen["child_gone"] + 0.1
    if stage == "map":
        return "warping:" in text
    if stage == "checks":
        return "checking:" in text
    # write: the output's temporary, or the staging folder of its set, appears
    return any(".vhm-tmp-" in p.name or ".vhm-staging." in p.name for p in folder.iterdir())


def _signal_in(stage: str, signum: int, command: list, folder: Path):
    proc = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, bufsize=1)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    seen: dict = {}
    while proc.poll() is None and not _stage_began(stage, proc, "".join(lines), folder, seen):
        time.sleep(0.002)
    if proc.poll() is None:
        proc.send_signal(signum)
    status = proc.wait(timeout=600)
    reader.join()
    return status, "".join(lines)


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
@pytest.mark.parametrize(
    ("stage", "signum"),
    [("read", signal.SIGTERM), ("solve", signal.SIGINT), ("map", signal.SIGTERM),
     ("checks", signal.SIGTERM), ("write", signal.SIGINT)],
)  # fmt: skip
def test_a_signal_in_each_stage_stops_it_and_keeps_the_old_output(tmp_path, stage, signum):
    head = data_path("volumes", "headsq_64x64x93.vti")
    scene = Scene.load(SCENE).to_dict()
    if stage == "solve":  # many automatic anchors: a solve stage several times that moment
        scene["anchors"] = {"auto": 256}
    work = tmp_path / "work"
    work.mkdir()
    Scene.from_dict(scene, base_dir=work).save(work / "scene.json")
    for name in ("head_cage.obj", "head_anchors.json"):
        shutil.copy(SCENE.parent / name, work / name)
    out = tmp_path / "bent.vts"
    out.write_bytes(OLD)
    command = [sys.executable, "-m", "vhm_viz.cli", "deform", str(head), "--scene",
               str(work / "scene.json"), "-o", str(out), "--timings"]  # fmt: skip
    status, stderr = _signal_in(stage, signum, command, tmp_path)
    assert status == 128 + signum, stderr
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, stderr
    name = signal.Signals(signum).name
    assert f"vhm-viz deform: interrupted by {name}" in stderr
    timings = next(ln for ln in stderr.splitlines() if "timings:" in ln)
    stages = [p.split()[0] for p in timings.split("timings:")[1].split(",")]
    ran = [s for s in stages if s in ("read", "solve", "map", "checks", "write")]
    assert ran[-1] == stage, timings  # stopped in the stage that got the signal
    assert out.read_bytes() == OLD
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, work.name])


#: Runs the command line with a real SIGINT sent to itself the moment the deform
#: command's module starts importing (the start-up, before any stage).
_INTERRUPTED_START_UP = """
import importlib.abc, os, signal, sys

class SignalOnImport(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "vhm_viz.cli.deform":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None

sys.meta_path.insert(0, SignalOnImport())
from vhm_viz.cli import main
sys.argv = ["vhm-viz", *sys.argv[1:]]
main()
"""


def test_a_signal_during_start_up_is_one_line(tmp_path):
    out = tmp_path / "out.vts"
    proc = subprocess.run(
        [sys.executable, "-c", _INTERRUPTED_START_UP, "deform", str(data_path("volumes",
         "headsq_64x64x93.vti")), "--scene", str(SCENE), "-o", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr == "vhm-viz deform: interrupted by SIGINT\n"
    assert not out.exists()


#: Runs the command line with a real SIGTERM sent to itself as VTK's Python dispatch of a
#: filter's update-extent request begins: between the filter's own methods, which keep
#: their errors (the signal's exception arrives at any instruction).
_SIGNAL_IN_DISPATCH = """
import os, signal, sys
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

dispatch = VTKPythonAlgorithmBase.ProcessRequest.__code__

def hook(frame, event, arg):
    if event == "call" and frame.f_code is dispatch:
        if frame.f_locals["request"].Has(sddp.REQUEST_UPDATE_EXTENT()):
            sys.setprofile(None)
            os.kill(os.getpid(), signal.SIGTERM)

sys.setprofile(hook)
from vhm_viz.cli import main
sys.argv = ["vhm-viz", *sys.argv[1:]]
main()
"""


def test_a_signal_between_a_filters_methods_is_one_line(tmp_path):
    out = tmp_path / "bent.vts"
    out.write_bytes(OLD)
    head = data_path("volumes", "headsq_64x64x93.vti")
    done = subprocess.run(
        [sys.executable, "-c", _SIGNAL_IN_DISPATCH, "deform", str(head), "--scene", str(SCENE),
         "-o", str(out), "-q"], capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 128 + signal.SIGTERM, done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip().splitlines() == ["vhm-viz deform: interrupted by SIGTERM"]
    assert out.read_bytes() == OLD
