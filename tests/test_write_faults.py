"""Writes that fail for space: one line, a non-zero exit, the old output intact."""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import data_path

SCENE = Path(__file__).resolve().parents[1] / "vhm_viz" / "scenes" / "head_scene.json"


def _limited(limit_bytes: int):
    def set_limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return set_limit


@pytest.mark.parametrize("suffix", [".vti", ".mha", ".vts"])
def test_a_write_past_the_file_size_limit_fails_and_keeps_the_old_file(tmp_path, suffix):
    head = data_path("volumes", "headsq_64x64x93.vti")
    out = tmp_path / "run" / f"out{suffix}"
    out.parent.mkdir()
    command = [sys.executable, "-m", "vhm_viz.cli", "deform", str(head), "--scene", str(SCENE),
               "-o", str(out), "-q"]  # fmt: skip
    # a run without the limit first: compiled kernels are cached, so only the output is
    # written under it
    subprocess.run(command, capture_output=True, check=True, timeout=600)
    old = b"the previous output, which must survive\n" * 10
    out.write_bytes(old)
    before = sorted(p.name for p in out.parent.iterdir())  # with the masks' files beside .mha
    # what a full quota or disk looks like to a writer: EFBIG past 64 kB
    proc = subprocess.run(
        command, capture_output=True, text=True, preexec_fn=_limited(64 * 1024), timeout=600
    )
    assert proc.returncode != 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("vhm-viz deform")]
    assert len(lines) == 1 and "error:" in lines[0] and "Traceback" not in proc.stderr
    assert "write" in lines[0] or "large" in lines[0], lines[0]
    assert out.read_bytes() == old
    assert sorted(p.name for p in out.parent.iterdir()) == before
