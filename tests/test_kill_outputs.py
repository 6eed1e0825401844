"""A command killed outright (SIGKILL) leaves the complete old output set or the complete new one.

A ``deform`` to ``.vts`` (one file) and to ``.mhd`` (headers and voxels of the scan and of
its mask arrays), and an
``analyze`` report (five files), are killed at random moments, most of them while the
outputs are being written (from when the first temporary appears), some anywhere in the
run. After each kill the output files must be byte for byte the previous set or the set
a complete run writes, never a mix. A set killed between its renames leaves a journal,
which the next write in the folder completes (:func:`vhm_viz.atomic.remove_stale_temporaries`,
called here as that next run would). Then one normal run: it must write the new set and
leave no temporary of the killed runs behind.

The suite kills the MetaImage ``deform`` three times; ``VHM_VIZ_KILLS=20`` runs the full
check, 20 kills of each of the three commands (some minutes).
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import data_path

from vhm_viz.atomic import remove_stale_temporaries

SCENE = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"
REPORT = ("analysis.vti", "energy.png", "figure12_condition_histogram.png",
          "figure4_slices.png", "metrics.json")  # fmt: skip
#: (command, output, the files of its set, seconds a write may take: kills land within)
CASES = {
    "vts": ("deform", "out.vts", ("out.vts",), 0.5),
    # the scan, and each other point array in a MetaImage pair beside it
    "mhd": ("deform", "out.mhd", tuple(f"out{a}.{s}" for a in ("", "_vtkValidPointMask",
            "_vhm_foldover") for s in ("mhd", "raw")), 0.3),  # fmt: skip
    "analyze": ("analyze", "report", REPORT, 4.0),
}


def _set_of(folder: Path, names) -> dict:
    return {n: (folder / n).read_bytes() if (folder / n).is_file() else None for n in names}


def _writing(folder: Path) -> bool:
    return any(".vhm-tmp-" in p.name or ".vhm-staging." in p.name for p in folder.rglob(".*"))


def _kill_at_random(command: list, folder: Path, rng: random.Random, write_seconds: float):
    """Run ``command`` and SIGKILL it: in its write stage (3 in 4), or anywhere."""
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    if rng.random() < 0.75:
        while proc.poll() is None and not _writing(folder):
            time.sleep(0.001)
        time.sleep(rng.uniform(0.0, write_seconds))
    else:
        time.sleep(rng.uniform(0.0, 6.0))
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=600)


#: Kills per case of the full run (``VHM_VIZ_KILLS=20``: 60 runs, minutes); the suite
#: kills the MetaImage pair's ``deform`` a few times.
FULL_KILLS = int(os.environ.get("VHM_VIZ_KILLS", "0"))
_FULL = [
    pytest.mark.slow,
    pytest.mark.skipif(not FULL_KILLS, reason="set VHM_VIZ_KILLS=20 for the full run"),
]


@pytest.mark.parametrize(
    ("case", "kills"),
    [("mhd", 3), pytest.param("mhd", FULL_KILLS, marks=_FULL),
     pytest.param("vts", FULL_KILLS, marks=_FULL),
     pytest.param("analyze", FULL_KILLS, marks=_FULL)],
)  # fmt: skip
def test_a_killed_command_leaves_the_old_set_or_the_new_one(tmp_path, case, kills):
    command_name, output, names, write_seconds = CASES[case]
    head = data_path("volumes", "headsq_64x64x93.vti")
    out = tmp_path / output
    folder = out if command_name == "analyze" else tmp_path
    folder.mkdir(exist_ok=True)
    command = [sys.executable, "-m", "vhm_viz.cli", command_name, str(head), "--scene",
               str(SCENE), "-o", str(out), "-q"]  # fmt: skip
    old = {n: f"the previous {n}\n".encode() for n in names}
    rng = random.Random(36)
    states = []
    for _ in range(kills):
        for name, blob in old.items():
            (folder / name).write_bytes(blob)
        _kill_at_random(command, folder, rng, write_seconds)
        if any(p.name.startswith(".vhm-set-") for p in folder.iterdir()):
            remove_stale_temporaries(folder)  # what the next write there does first
        states.append(_set_of(folder, names))
    for name, blob in old.items():
        (folder / name).write_bytes(blob)
    subprocess.run(command, check=True, capture_output=True, timeout=600)
    new = _set_of(folder, names)
    assert all(v is not None and v != old[n] for n, v in new.items())
    # the killed runs' temporaries are gone after the normal run
    assert sorted(p.name for p in folder.iterdir()) == sorted(names)
    for k, state in enumerate(states):
        assert state in (old, new), f"kill {k}: a mix of old and new files"
