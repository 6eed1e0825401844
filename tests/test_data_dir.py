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
    deep = tmp_path / "a" / "b"
    deep.mkdir(parents=True)
    if DATA.is_dir():  # the repository's sibling comes first, from any folder
        monkeypatch.chdir(tmp_path)
        assert examples.data_dir() == DATA.resolve()
        assert examples.data_dir(cwd=deep) == DATA.resolve()
    if Path("/shared/data").is_dir():
        pytest.skip("/shared/data exists here: the search would stop there")
    # a package installed away from the data: ../shared/data of the package's folder, then
    # of the current folder and of each of its parents, in that order
    package = tmp_path / "site" / "lib"
    monkeypatch.setattr(examples, "__file__", str(package / "vhm_viz" / "examples.py"))
    with pytest.raises(examples.DataNotFound) as exc:
        examples.data_dir(cwd=deep)
    looked = str(exc.value).split("looked in ")[1].split("; set ")[0].split(", ")
    expected = [tmp_path / "site" / "shared" / "data", tmp_path / "a" / "shared" / "data"]
    expected += [p.parent / "shared" / "data" for p in deep.parents]
    assert looked == [str(p) for p in dict.fromkeys(expected)]
    assert looked[-1] == "/shared/data"
    (tmp_path / "shared" / "data").mkdir(parents=True)
    assert examples.data_dir(cwd=deep) == (tmp_path / "shared" / "data").resolve()
    (tmp_path / "a" / "shared" / "data").mkdir(parents=True)
    assert examples.data_dir(cwd=deep) == (tmp_path / "a" / "shared" / "data").resolve()
    (package.parent / "shared" / "data").mkdir(parents=True)
    assert examples.data_dir(cwd=deep) == (package.parent / "shared" / "data").resolve()
