"""The README's "Working with scans" example runs as written, on the CT head and its scene."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import data_path, subprocess_env

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "vhm_viz" / "scenes"


def _example_blocks() -> tuple[str, str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    example = text.split("<!-- scans-example-start -->")[1].split("<!-- scans-example-end -->")[0]
    bash = re.search(r"```bash\n(.*?)```", example, re.S).group(1)
    python = re.search(r"```python\n(.*?)```", example, re.S).group(1)
    return bash, python


def test_the_readme_scan_example_runs_and_simpleitk_reproduces_the_output(tmp_path):
    sitk = pytest.importorskip("SimpleITK")
    import vhm_viz
    from vhm_viz.io import write_dataset

    head = vhm_viz.read_dataset(data_path("volumes", "headsq_64x64x93.vti"))
    write_dataset(tmp_path / "scan.nii.gz", head)
    for name in ("head_cage.obj", "head_anchors.json"):
        shutil.copy(SCENES / name, tmp_path / name)
    shutil.copy(SCENES / "head_scene.json", tmp_path / "scene.json")

    bash, python = _example_blocks()
    env = subprocess_env()
    for line in filter(None, (ln.strip() for ln in bash.splitlines())):
        words = shlex.split(line)
        assert words[0] == "vhm-viz"
        run = subprocess.run(
            [sys.executable, "-m", "vhm_viz.cli", *words[1:]],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert run.returncode == 0, run.stderr
        assert "field.nii.gz" in run.stdout and "field_mask.nii.gz" in run.stdout
    run = subprocess.run(
        [sys.executable, "-c", python], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    largest = float(run.stdout.split()[-1])
    assert largest <= 1.0  # integer rounding of the output, nothing more
    # and the example compared something: most of the output is mapped, and it was bent
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "field_mask.nii.gz")))
    assert (mask == 1).mean() > 0.3
    field = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "field.nii.gz")))
    assert abs(field[mask == 1]).max() > 5.0  # millimetres of displacement
