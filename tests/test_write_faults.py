"""Writes that fail for space: one line, a non-zero exit, the old output intact."""

from __future__ import annotations

import os
import resource
import shutil
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


@pytest.mark.parametrize("suffix", [".vti", ".mha", ".vts", ".nii.gz", ".mhd", ".nrrd"])
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
    # the output named, not a temporary or staging folder it was written in
    assert lines[0].startswith(f"vhm-viz deform: error: could not write {out}: "), lines[0]
    assert out.read_bytes() == old
    assert sorted(p.name for p in out.parent.iterdir()) == before


def test_a_report_past_the_file_size_limit_names_its_file_not_the_staging_folder(tmp_path):
    head = data_path("volumes", "headsq_64x64x93.vti")
    report = tmp_path / "report"
    command = [sys.executable, "-m", "vhm_viz.cli", "analyze", str(head), "--scene", str(SCENE),
               "-o", str(report), "-q"]  # fmt: skip
    subprocess.run(command, capture_output=True, check=True, timeout=600)
    before = {p.name: p.read_bytes() for p in report.iterdir()}
    proc = subprocess.run(
        command, capture_output=True, text=True, preexec_fn=_limited(64 * 1024), timeout=600
    )
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.splitlines()[-1] == (
        f"vhm-viz analyze: error: could not write {report}/analysis.vti: File too large"
    )
    assert {p.name: p.read_bytes() for p in report.iterdir()} == before


def _unprivileged(command: list) -> list:
    """``command`` run without the superuser's right to write in any folder."""
    if os.geteuid() != 0:
        return command
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root without setpriv: folder permissions do not apply")
    return [setpriv, "--bounding-set=-dac_override,-dac_read_search", "--inh-caps=-all", *command]


@pytest.fixture()
def read_only_folder(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    yield folder
    folder.chmod(0o755)


def test_a_folder_without_write_permission_is_named_before_any_work(read_only_folder):
    head = data_path("volumes", "headsq_64x64x93.vti")
    for command, output in (("deform", "out.vts"), ("analyze", "report")):
        proc = subprocess.run(
            _unprivileged([sys.executable, "-m", "vhm_viz.cli", command, str(head), "--scene",
                           str(SCENE), "-o", str(read_only_folder / output), "-q", "--timings"]),
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert proc.returncode == 1, proc.stderr
        lines = proc.stderr.splitlines()
        assert lines[0] == (
            f"vhm-viz {command}: error: cannot write in {read_only_folder}/ (permission denied); "
            "choose another output folder"
        )
        assert " read " not in lines[-1]  # refused before the input was read
    assert list(read_only_folder.iterdir()) == []


_WRITE_IN = """
import sys
from vhm_viz.atomic import atomic_directory, atomic_path
folder = sys.argv[1]
for block in (lambda: atomic_path(folder + "/one.txt"), lambda: atomic_directory(folder)):
    try:
        with block() as where:
            print("wrote", where)
    except OSError as exc:
        print(type(exc).__name__, exc)
"""


def test_a_write_in_a_folder_it_cannot_write_names_the_folder_not_its_temporary(
    read_only_folder,
):
    proc = subprocess.run(
        _unprivileged([sys.executable, "-c", _WRITE_IN, str(read_only_folder)]),
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    expected = (
        f"UnwritableFolderError cannot write in {read_only_folder}/ (Permission denied); "
        "choose another output folder"
    )
    assert proc.stdout.splitlines() == [expected, expected], proc.stderr
    assert list(read_only_folder.iterdir()) == []


_WRITE_FIELD = """
import sys
from pathlib import Path
import numpy as np
from vhm_viz.core.displacement import DisplacementField
from vhm_viz.core.image import ImageGeometry
from vhm_viz.io.fields import write_displacement_field
geo = ImageGeometry((0, 0, 0), (1, 1, 1), (48, 48, 48))
vectors = np.random.default_rng(0).normal(size=(geo.n_points, 3))
ones = np.ones(geo.n_points, np.uint8)
field = DisplacementField(geo, vectors, ones, np.zeros_like(ones))
try:
    write_displacement_field(Path(sys.argv[1]), field)
except OSError as exc:
    sys.exit(f"OSError {exc}")
"""


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_a_nifti_field_cut_short_by_the_file_size_limit_fails_and_keeps_the_old_one(
    tmp_path, suffix
):
    # ITK's NIfTI writer only prints a failed write; the field (2.6 MB of noise) must
    # not replace the old one cut at the limit
    out = tmp_path / f"field{suffix}"
    old = b"the previous field, which must survive\n"
    out.write_bytes(old)
    proc = subprocess.run(
        [sys.executable, "-c", _WRITE_FIELD, str(out)],
        capture_output=True, text=True, preexec_fn=_limited(256 * 1024), timeout=300,
    )  # fmt: skip
    assert proc.returncode != 0, proc.stderr
    [line] = proc.stderr.strip().splitlines()  # without ITK's own "** ERROR: NWAD: ..."
    assert line.startswith(f"OSError could not write {out}: the file ends early"), proc.stderr
    assert out.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


@pytest.mark.parametrize(
    ("suffix", "reason"),
    [
        (".nii", "; the disk is full or a file-size limit was reached"),
        (".nii.gz", "; the disk is full or a file-size limit was reached"),
        (".mha", ": File too large"),
        (".nrrd", ""),  # teem says where it failed, not why
    ],
)
def test_a_field_past_the_file_size_limit_is_refused_in_our_line_alone(tmp_path, suffix, reason):
    # ITK's writers print their own complaints (NIfTI's "** ERROR: NWAD: wrote only ...",
    # MetaIO's "file stream is fail after write") on stderr: the user reads one line
    head = data_path("volumes", "headsq_64x64x93.vti")
    field = tmp_path / f"field{suffix}"
    command = [sys.executable, "-m", "vhm_viz.cli", "deform", str(head), "--scene", str(SCENE),
               "-o", str(tmp_path / "out.nii.gz"), "--write-field", str(field), "-q"]  # fmt: skip
    subprocess.run(command, capture_output=True, check=True, timeout=600)
    field.write_bytes(b"the previous field, which must survive\n")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    # the output (0.5 MB) fits under the limit, the field (8 to 17 MB) does not; Python
    # ignores SIGXFSZ, so the writes past the limit fail with EFBIG
    proc = subprocess.run(
        command, capture_output=True, text=True, preexec_fn=_limited(1 << 20), timeout=600
    )
    assert proc.returncode == 1
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"vhm-viz deform: error: could not write {field}: "), lines[0]
    assert lines[0].endswith(reason), lines[0]
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_report_that_fails_leaves_no_folder_it_created(tmp_path):
    head = data_path("volumes", "headsq_64x64x93.vti")
    report = tmp_path / "new" / "report"
    proc = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", "analyze", str(head), "--scene", str(SCENE),
         "-o", str(report), "-q"],
        capture_output=True, text=True, preexec_fn=_limited(64 * 1024), timeout=600,
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_demo_that_fails_part_way_writes_none_of_its_files(tmp_path):
    # its scene and first surface fit under the limit, its later files do not
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "vhm_viz.cli", "demo", "-o", str(out), "-q", "--no-tets"],
        capture_output=True, text=True, preexec_fn=_limited(64 * 1024), timeout=600,
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.splitlines()[-1].startswith(f"vhm-viz demo: error: could not write {out}/")
    assert list(tmp_path.iterdir()) == []
