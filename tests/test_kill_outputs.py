"""A command killed outright (SIGKILL) leaves the complete old output set or the complete new one.

A ``deform`` to ``.vts`` (one file), to ``.mhd`` (headers and voxels of the scan and of
its mask arrays) and to ``.nii.gz`` with its displacement field and their masks, and an
``analyze`` report (five files), are killed at random moments, most of them while the
outputs are being written (from when the first temporary appears), some anywhere in the
run. After each kill the output files must be byte for byte the previous set or the set
a complete run writes, never a mix. A set killed between its renames leaves a journal,
which the next write in the folder completes (:func:`vhm_viz.atomic.remove_stale_temporaries`,
called here as that next run would). Then one normal run: it must write the new set and
leave no temporary of the killed runs behind.

Each command is killed 20 times (``VHM_VIZ_KILLS`` sets another count): a ``deform`` to
``.vts``, to ``.mhd`` and to ``.nii.gz`` with ``--write-field``, and an ``analyze``.
"""

from __future__ import annotations

import gzip
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
    # a resample with its displacement field: the image, its mask array, the field, its mask
    "field": ("deform", "out.nii.gz", ("out.nii.gz", "out_vtkValidPointMask.nii.gz",
              "out_vhm_foldover.nii.gz", "field.nii.gz", "field_mask.nii.gz"), 1.5),
}
#: Extra arguments of a case's command.
EXTRA = {"field": lambda folder: ["--write-field", str(folder / "field.nii.gz")]}


def _content(path: Path):
    """A file's bytes (a gzip file's uncompressed bytes: its header holds a name and a time)."""
    if not path.is_file():
        return None
    blob = path.read_bytes()
    return gzip.decompress(blob) if blob[:2] == b"\x1f\x8b" else blob


def _set_of(folder: Path, names) -> dict:
    return {n: _content(folder / n) for n in names}


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


#: Kills per command (``VHM_VIZ_KILLS`` sets another count).
KILLS = int(os.environ.get("VHM_VIZ_KILLS", "20"))


@pytest.mark.parametrize("case", list(CASES))
def test_a_killed_command_leaves_the_old_set_or_the_new_one(tmp_path, case):
    kills = KILLS
    command_name, output, names, write_seconds = CASES[case]
    head = data_path("volumes", "headsq_64x64x93.vti")
    out = tmp_path / output
    folder = out if command_name == "analyze" else tmp_path
    folder.mkdir(exist_ok=True)
    extra = EXTRA[case](folder) if case in EXTRA else []
    command = [sys.executable, "-m", "vhm_viz.cli", command_name, str(head), "--scene",
               str(SCENE), "-o", str(out), "-q", *extra]  # fmt: skip
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
