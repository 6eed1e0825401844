"""Outputs of several files appear as one set; what killed processes leave is cleaned up."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from vhm_viz.atomic import atomic_directory, atomic_output_set, remove_stale_temporaries


def _dead_pid() -> int:
    """The PID of a process that has ended."""
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    return int(proc.stdout)


def test_a_set_appears_whole_in_order_with_ordinary_permissions(tmp_path):
    raw, header = tmp_path / "out.raw", tmp_path / "out.mhd"
    with atomic_output_set([raw, header]) as (raw_tmp, header_tmp):
        assert raw_tmp.parent == tmp_path and raw_tmp.name.startswith(".out.vhm-tmp-")
        assert raw_tmp.name.endswith(".raw") and header_tmp.name.endswith(".mhd")
        raw_tmp.write_bytes(b"voxels")
        header_tmp.write_bytes(b"header")
        assert not raw.exists() and not header.exists()
    assert raw.read_bytes() == b"voxels" and header.read_bytes() == b"header"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mhd", "out.raw"]
    assert header.stat().st_mode & 0o777 == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_a_failed_set_keeps_every_old_file_and_leaves_no_temporary(tmp_path):
    raw, header = tmp_path / "out.raw", tmp_path / "out.mhd"
    raw.write_bytes(b"old voxels")
    header.write_bytes(b"old header")
    with pytest.raises(OSError), atomic_output_set([raw, header]) as (raw_tmp, header_tmp):
        raw_tmp.write_bytes(b"new voxels")
        raise OSError("the header could not be written")
    assert raw.read_bytes() == b"old voxels" and header.read_bytes() == b"old header"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mhd", "out.raw"]


def test_temporaries_of_ended_processes_are_removed_and_running_ones_kept(tmp_path):
    dead, alive = _dead_pid(), os.getppid()
    (tmp_path / f".out.vhm-tmp-{dead}-0.vti").write_bytes(b"partial")
    (tmp_path / f".vhm-staging.{dead}-3").mkdir()
    (tmp_path / f".vhm-staging.{dead}-3" / "metrics.json").write_text("{}")
    (tmp_path / f".other.vhm-tmp-{alive}-0.vti").write_bytes(b"being written")
    (tmp_path / "out.vti").write_bytes(b"old")
    with atomic_output_set([tmp_path / "out.vti"]) as (tmp,):
        tmp.write_bytes(b"new")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [f".other.vhm-tmp-{alive}-0.vti", "out.vti"]
    assert (tmp_path / "out.vti").read_bytes() == b"new"


# a child that is killed (SIGKILL) between the renames of a set: after its first rename
_KILLED_BETWEEN_RENAMES = """
import os, signal, sys
from vhm_viz.atomic import atomic_output_set
real_replace, moved = os.replace, []
def replace_then_die(src, dst):
    real_replace(src, dst)
    moved.append(dst)
    if str(dst).endswith(".raw"):
        os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace_then_die
folder = sys.argv[1]
with atomic_output_set([folder + "/out.raw", folder + "/out.mhd"]) as (raw, header):
    raw.write_bytes(b"new voxels")
    header.write_bytes(b"new header")
"""


def test_a_set_whose_process_was_killed_between_renames_is_completed_by_the_next_write(tmp_path):
    (tmp_path / "out.raw").write_bytes(b"old voxels")
    (tmp_path / "out.mhd").write_bytes(b"old header")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(_KILLED_BETWEEN_RENAMES),
                           str(tmp_path)], env=env, capture_output=True)  # fmt: skip
    assert proc.returncode == -9, proc.stderr
    # killed mid-set: the journal names the moves still to do
    assert any(p.name.startswith(".vhm-set-") for p in tmp_path.iterdir())
    handled = remove_stale_temporaries(tmp_path)
    assert handled and (tmp_path / "out.mhd").read_bytes() == b"new header"
    assert (tmp_path / "out.raw").read_bytes() == b"new voxels"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mhd", "out.raw"]


def test_a_report_folder_appears_as_one_set_beside_the_users_other_files(tmp_path):
    (tmp_path / "notes.txt").write_text("the user's")
    (tmp_path / "metrics.json").write_text("old")
    with atomic_directory(tmp_path, last="metrics.json") as stage:
        assert stage.parent == tmp_path and stage.name.startswith(".vhm-staging.")
        (stage / "metrics.json").write_text("new")
        (stage / "a.png").write_bytes(b"png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "metrics.json", "notes.txt"]
    assert (tmp_path / "metrics.json").read_text() == "new"
