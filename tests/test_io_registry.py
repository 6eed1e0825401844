"""The format table: every suffix it lists round-trips, or is refused in one clear line."""

from __future__ import annotations

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from scipy.spatial.transform import Rotation  # noqa: E402

from vhm_viz.io import (  # noqa: E402
    CAGE_SUFFIXES,
    DATASET_SUFFIXES,
    FORMATS,
    ReadError,
    format_of,
    is_image_format,
    keeps_arrays,
    output_suffixes,
    read_cage,
    read_dataset,
    write_cage,
    write_dataset,
)
from vhm_viz.io.registry import DATASET_TYPES, dataset_type  # noqa: E402

IMAGE_SUFFIXES = (".vti", ".mhd", ".mha", ".nii", ".nii.gz", ".nrrd")


def sample(kind: str, *, oriented: bool = False):
    """A small dataset of each type, with one point array."""
    if kind == "PolyData":
        data = pv.Sphere(theta_resolution=8, phi_resolution=6)
        data.clear_data()
    elif kind == "UnstructuredGrid":
        data = pv.ImageData(dimensions=(3, 3, 4), spacing=(0.5, 1.0, 0.25)).triangulate()
    elif kind == "StructuredGrid":
        data = pv.ImageData(dimensions=(3, 4, 2)).cast_to_structured_grid()
    elif kind == "RectilinearGrid":
        data = pv.RectilinearGrid([0.0, 1.0, 3.0], [0.0, 2.0], [0.0, 1.0, 2.0, 4.0])
    else:
        data = pv.ImageData(dimensions=(4, 5, 6), spacing=(0.5, 0.75, 1.25), origin=(1, -2, 3))
        if oriented:
            data.direction_matrix = Rotation.from_euler("xyz", [20, -35, 50], True).as_matrix()
    data.point_data["v"] = np.arange(data.n_points, dtype=np.float32)
    return data


def test_image_formats_are_the_resampled_ones():
    assert all(is_image_format(f"volume{s}") for s in IMAGE_SUFFIXES)
    assert is_image_format("out/VOLUME.NII.GZ") and is_image_format("no/such/folder/x.mha")
    others = set(DATASET_SUFFIXES) - set(IMAGE_SUFFIXES)
    assert not any(is_image_format(f"volume{s}") for s in others | {"", ".json"})
    # an image written anywhere else is a grid: each image format writes only images
    for s in IMAGE_SUFFIXES:
        assert format_of(f"v{s}").writes == ("ImageData",)


def test_suffix_queries_agree_with_the_table():
    assert len(set(DATASET_SUFFIXES)) == len(DATASET_SUFFIXES)
    listed = [s for f in FORMATS for s in f.suffixes]
    assert len(set(listed)) == len(listed), "a suffix belongs to one format"
    assert set(CAGE_SUFFIXES) <= set(DATASET_SUFFIXES)
    assert set(output_suffixes()) <= set(DATASET_SUFFIXES)
    for s in listed:
        assert format_of(f"x{s.upper()}").suffixes == format_of(f"x{s}").suffixes
    with pytest.raises(ValueError, match="unknown dataset type"):
        output_suffixes("MultiBlock")
    for fmt in FORMATS:  # every function a row names exists
        for role in ("read", "check", "write", "cage", "lines"):
            assert getattr(fmt, role) is None or callable(fmt.function(role)), (fmt.name, role)


@pytest.mark.parametrize("kind", DATASET_TYPES)
def test_output_suffixes_are_what_the_writers_accept(kind, tmp_path):
    """Each type written to each of its suffixes reads back as the same geometry."""
    writers = set(getattr(pv, kind)._WRITERS)  # PyVista's writers for the type
    for suffix in output_suffixes(kind):
        fmt = format_of(f"x{suffix}")
        assert fmt.write is not None or suffix in writers, (kind, suffix)
        data = sample(kind, oriented=fmt.image)
        path = tmp_path / f"{kind}{suffix}"
        write_dataset(path, data)
        back = read_dataset(path)
        assert dataset_type(back) in fmt.reads, (suffix, type(back))
        if kind == "ImageData":
            assert type(back) is pv.ImageData and back.dimensions == data.dimensions
            np.testing.assert_allclose(back.origin, data.origin, atol=1e-6)
            np.testing.assert_allclose(back.spacing, data.spacing, rtol=1e-6)
            np.testing.assert_allclose(back.direction_matrix, data.direction_matrix, atol=1e-6)
            values = np.asarray(back.point_data[back.array_names[0]]).ravel()
            np.testing.assert_array_equal(values, data.point_data["v"])
        else:  # the same points (some formats renumber them, or store float32)
            assert back.n_points == data.n_points, suffix
            # the point array is kept where the table says so, and only there
            assert ("v" in back.point_data) == keeps_arrays(path), suffix
            key = lambda p: np.unique(np.round(np.asarray(p, float), 4), axis=0)  # noqa: E731
            np.testing.assert_allclose(key(back.points), key(data.points), atol=1e-4)


@pytest.mark.parametrize("kind", DATASET_TYPES)
def test_every_other_suffix_is_refused_in_one_line(kind, tmp_path):
    data = sample(kind)
    for fmt in FORMATS:
        for suffix in fmt.suffixes:
            if kind in fmt.writes:
                continue
            path = tmp_path / f"x{suffix}"
            with pytest.raises(ValueError) as exc:
                write_dataset(path, data)
            message = str(exc.value)
            assert "\n" not in message and suffix in message, message
            assert not path.exists()
    with pytest.raises(ValueError, match="cannot write '.png' files"):
        write_dataset(tmp_path / "x.png", data)


@pytest.mark.parametrize("suffix", DATASET_SUFFIXES)
def test_every_read_suffix_refuses_an_empty_file_in_one_line(suffix, tmp_path):
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(ReadError) as exc:
        read_dataset(path)
    assert "\n" not in str(exc.value) and str(path) in str(exc.value)
    # one wording for every format: nothing of a reader's own (a header's size, a count)
    assert str(exc.value) == f"{path}: empty file (0 bytes); copy or export it again"


@pytest.mark.parametrize(
    ("suffix", "read"),
    [(".obj", "read_cage"), (".off", "read_cage"), (".json", "read_anchors")],
)
def test_an_empty_cage_or_anchors_file_is_said_to_be_empty(suffix, read, tmp_path):
    import vhm_viz.io as io

    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(ReadError) as exc:
        getattr(io, read)(path)
    assert str(exc.value) == f"{path}: empty file (0 bytes); copy or export it again"


def test_unknown_suffixes_are_refused_in_one_line(tmp_path):
    (tmp_path / "x.foo").write_text("1 2 3\n")
    with pytest.raises(ReadError, match=r"unsupported file type '\.foo'; use one of \.vtu"):
        read_dataset(tmp_path / "x.foo")


@pytest.mark.parametrize("suffix", [s for s in CAGE_SUFFIXES if s not in (".off", ".vtu")])
def test_cage_formats_round_trip(suffix, tmp_path):
    cube = pv.Cube().triangulate().clean()
    cage = read_cage(_saved(cube, tmp_path / "cube.vtp"))
    write_cage(tmp_path / f"cage{suffix}", cage)
    back = read_cage(tmp_path / f"cage{suffix}")
    assert back.faces.shape == cage.faces.shape
    np.testing.assert_allclose(back.volume, cage.volume, rtol=1e-6)


def _saved(data, path):
    data.save(path)
    return path


@pytest.mark.parametrize(
    "name, text",
    [
        ("names.csv", "x,y,z\n0,1,2\n3,4,5.5\n"),
        ("names.xyz", "# scanned\nx y z\n0 1 2\n3 4 5.5\n"),
        ("plain.txt", "0 1 2\n3 4 5.5\n"),
    ],
)
def test_a_point_list_with_a_row_of_column_names_reads_its_numbers(name, text, tmp_path):
    (tmp_path / name).write_text(text)
    np.testing.assert_array_equal(read_dataset(tmp_path / name).points, [[0, 1, 2], [3, 4, 5.5]])


def test_a_point_list_with_a_word_among_its_numbers_is_one_line(tmp_path):
    (tmp_path / "bad.csv").write_text("0,0,0\n1,a,0\n")
    with pytest.raises(ReadError) as err:
        read_dataset(tmp_path / "bad.csv")
    assert str(err.value).count("\n") == 0 and "'a'" in str(err.value) and "row 1" in str(err.value)
    assert str(err.value).endswith("expected numbers, one point (x y z ...) per row")


def test_a_binary_file_under_a_point_list_suffix_says_it_is_not_text(tmp_path):
    """Binary content under a point-list suffix (another format saved as .txt) is refused
    as not a text file, rather than with the codec's byte position."""
    path = tmp_path / "points.txt"
    path.write_bytes(b"0 0 0\n" + bytes(range(128, 256)) + b"\n")
    with pytest.raises(ReadError) as err:
        read_dataset(path)
    assert str(err.value) == (
        f"{path}: not a text file; expected numbers, one point (x y z ...) per row"
    )
