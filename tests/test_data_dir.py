"""Where the real models are found: $VHM_VIZ_DATA, or shared/data beside the repository."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import DATA

from vhm_viz import examples

REPO = Path(__file__).resolve().parents[1]


def test_the_variable_names_the_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("VHM_VIZ_DATA", str(tmp_path))
    assert examples.data_dir() == tmp_path.resolve()


def test_a_variable_pointing_nowhere_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.setenv("VHM_VIZ_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(examples.DataNotFound) as exc:
        examples.data_dir()
    text = str(exc.value)
    assert f"VHM_VIZ_DATA={tmp_path / 'nowhere'} does not exist" in text
    assert "\n" not in text
    assert isinstance(exc.value, FileNotFoundError)


def test_found_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("VHM_VIZ_DATA", raising=False)
    # the repository's sibling comes first, then ../shared/data of the folder and its parents
    deep = tmp_path / "a" / "b"
    found = examples._data_candidates(deep)
    assert found[0] == REPO.parent / "shared" / "data"
    assert found[1:3] == [tmp_path / "a" / "shared" / "data", tmp_path / "shared" / "data"]
    assert found[-1] == Path("/shared/data") and len(set(found)) == len(found)
    if DATA.is_dir():
        monkeypatch.chdir(tmp_path)
        assert examples.data_dir() == DATA.resolve()
        assert examples.data_dir(cwd=deep) == DATA.resolve()
