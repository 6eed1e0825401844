"""Atomic outputs: complete or absent, never half-written; ordinary permissions."""

from __future__ import annotations

import os

import pytest

from vhm_viz.atomic import atomic_path
from vhm_viz.io import write_text


def test_written_file_has_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        write_text(tmp_path / "a.json", "{}\n")
    finally:
        os.umask(old)
    assert (tmp_path / "a.json").read_text() == "{}\n"
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o644


def test_failure_leaves_existing_file_and_no_temporaries(tmp_path):
    target = tmp_path / "out.vtp"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        assert tmp.suffix == ".vtp" and tmp.parent == tmp_path
        tmp.write_text("half")
        raise RuntimeError("writer crashed")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.vtp"]
