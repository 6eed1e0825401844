"""Scans land where SimpleITK and nibabel put them: NIfTI, MetaImage, NRRD, DICOM series.

Every image is made here with SimpleITK (or nibabel, or by hand for a RAS-space NRRD),
small, with reflections (det D = -1), rotations, anisotropic spacing, int16 and float32
voxels, 1 and 3 components. :func:`vhm_viz.read_dataset` (and SimpleITK reading what
:func:`vhm_viz.io.write_dataset` wrote) is compared with the independent readers at random
physical points -- interpolated values, not header fields -- to 1e-5 of the intensity
range. The command line then deforms an oblique NRRD and DICOM series by a translation and
its output is compared with SimpleITK's own resampling under that translation.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

pv = pytest.importorskip("pyvista")
sitk = pytest.importorskip("SimpleITK")
nib = pytest.importorskip("nibabel")

from test_inputs import box_scene  # noqa: E402

from vhm_viz.cli import main  # noqa: E402
from vhm_viz.io import ReadError, read_dataset, write_dataset  # noqa: E402

SIZE = (20, 24, 16)  # x, y, z
SPACING = (0.8, 1.3, 2.0)
ORIGIN = (3.0, -4.0, 5.0)
TURN = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
DIRECTIONS = {
    "radiological": np.diag([-1.0, 1.0, 1.0]),  # x flipped: det -1
    "oblique": TURN,
    "oblique reflected": TURN @ np.diag([1.0, -1.0, 1.0]),  # det -1
}
LPS_RAS = np.diag([-1.0, -1.0, 1.0])  # nibabel's world is RAS, ITK's (and ours) LPS


def sitk_image(direction: str, dtype, components: int = 1, seed: int = 0):
    """A SIZE image with random voxels, SPACING, ORIGIN and one of DIRECTIONS."""
    rng = np.random.default_rng(seed)
    shape = (*SIZE[::-1], components) if components > 1 else SIZE[::-1]
    if np.dtype(dtype).kind in "iu":
        low = 0 if np.dtype(dtype).kind == "u" else -1000
        values = rng.integers(low, 3000, size=shape).astype(dtype)
    else:
        values = (100 * rng.normal(size=shape)).astype(dtype)
    image = sitk.GetImageFromArray(values, isVector=components > 1)
    image.SetSpacing(SPACING)
    image.SetOrigin(ORIGIN)
    image.SetDirection(DIRECTIONS[direction].ravel().tolist())
    return image


def write_dicom_series(folder: Path, image, uid: str, shifts=None) -> None:
    """A DICOM series of ``image`` (one file a slice, position and orientation per slice),
    each slice's position moved by its row of ``shifts`` (mm) if given."""
    folder.mkdir(exist_ok=True)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    d = np.reshape(image.GetDirection(), (3, 3))
    orientation = "\\".join(f"{v:.12f}" for v in (*d[:, 0], *d[:, 1]))
    for k in range(image.GetDepth()):
        plane = image[:, :, k]
        position = np.add(image.TransformIndexToPhysicalPoint((0, 0, k)), 0.0)
        if shifts is not None:
            position += shifts[k]
        for tag, value in {
            "0008|0060": "CT",
            "0020|000e": uid,
            "0008|0018": f"{uid}.{k + 1}",
            "0020|0013": str(image.GetDepth() - k),  # numbered against the slice order
            "0020|0032": "\\".join(f"{v:.12f}" for v in position),
            "0020|0037": orientation,
            "0008|103e": f"series {uid[-1]}",
        }.items():
            plane.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"{uid}_{k:03d}.dcm"))
        writer.Execute(plane)


def read_series(folder: Path, uid: str | None = None):
    files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), *([uid] if uid else []))
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    return reader.Execute()


def probe_points(reference, n: int = 200, seed: int = 1) -> np.ndarray:
    """Random physical points well inside ``reference`` (a SimpleITK image), (n, 3) mm."""
    rng = np.random.default_rng(seed)
    size = np.asarray(reference.GetSize(), dtype=float)
    index = rng.uniform(1.0, size - 2.0, size=(n, 3))
    return np.array([reference.TransformContinuousIndexToPhysicalPoint(i.tolist()) for i in index])


def sitk_values(reference, points: np.ndarray) -> np.ndarray:
    """SimpleITK's trilinear values at physical points, (n,) or (n, components)."""
    return np.array(
        [reference.EvaluateAtPhysicalPoint(p.tolist(), sitk.sitkLinear) for p in points]
    )


def our_values(image, points: np.ndarray) -> np.ndarray:
    """VTK's trilinear values of a vhm_viz image at physical points (in float64)."""
    name = image.active_scalars_name or image.array_names[0]
    probe = pv.ImageData(dimensions=image.dimensions, spacing=image.spacing, origin=image.origin)
    probe.direction_matrix = image.direction_matrix
    probe.point_data["v"] = np.asarray(image.point_data[name], dtype=np.float64)
    return np.asarray(pv.PolyData(points).sample(probe).point_data["v"])


def nibabel_values(path: Path, points: np.ndarray) -> np.ndarray:
    """nibabel's voxels, scaled, interpolated at LPS points (mm) through its affine."""
    img = nib.load(str(path))
    unit = {"meter": 1e3, "micron": 1e-3}.get(img.header.get_xyzt_units()[0], 1.0)
    affine = img.affine.copy()
    affine[:3] *= unit  # nibabel leaves the spatial unit to the reader
    data = np.asarray(img.get_fdata(), dtype=np.float64)
    ras = (LPS_RAS @ points.T).T
    index = (np.linalg.inv(affine) @ np.c_[ras, np.ones(len(ras))].T)[:3]
    if data.ndim == 3:
        return map_coordinates(data, index, order=1)
    vectors = data.reshape(*data.shape[:3], -1)
    return np.stack([map_coordinates(vectors[..., c], index, order=1) for c in range(3)], 1)


def assert_same_image(ours, reference, points=None, others=()) -> None:
    """``ours`` holds ``reference``'s voxels at the same physical points (1e-5 of range)."""
    expected = np.asarray(sitk.GetArrayViewFromImage(reference))
    name = ours.active_scalars_name or ours.array_names[0]
    assert np.asarray(ours.point_data[name]).dtype == expected.dtype
    points = probe_points(reference) if points is None else points
    want = sitk_values(reference, points)
    scale = float(expected.max() - expected.min())
    for got in (our_values(ours, points), *others):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * scale)


# ------------------------------------------------------------------ files made by the others


@pytest.mark.parametrize(
    ("name", "direction", "dtype", "components"),
    [
        ("a.nii.gz", "radiological", np.int16, 1),
        ("b.nii", "oblique", np.float32, 1),
        ("c.nii.gz", "oblique reflected", np.float32, 3),
        ("d.mha", "oblique reflected", np.int16, 1),
        ("e.mhd", "oblique", np.float32, 3),
        ("f.nrrd", "oblique reflected", np.int16, 1),
        ("g.nhdr", "oblique", np.float32, 3),
        ("h.mha", "oblique reflected", np.int64, 1),  # VTK's reader took these for int16
        ("i.mhd", "oblique", np.uint64, 1),
        ("j.nrrd", "oblique", np.int64, 1),  # "long long int"
    ],
)
def test_files_written_by_simpleitk_are_read_where_it_reads_them(
    tmp_path, name, direction, dtype, components
):
    path = tmp_path / name
    sitk.WriteImage(sitk_image(direction, dtype, components), str(path))
    reference = sitk.ReadImage(str(path))
    ours = read_dataset(path)
    others = [nibabel_values(path, probe_points(reference))] if ".nii" in name else []
    assert_same_image(ours, reference, others=others)


def test_nifti_scaling_and_units_are_applied_as_simpleitk_and_nibabel_read_them(tmp_path):
    """int16 with scl_slope/scl_inter, in micrometres, oblique: float32 in mm."""
    values = sitk.GetArrayFromImage(sitk_image("oblique", np.int16))
    affine = np.eye(4)
    affine[:3, :3] = LPS_RAS @ DIRECTIONS["oblique reflected"] * SPACING
    affine[:3, 3] = LPS_RAS @ ORIGIN
    img = nib.Nifti1Image(values.T, affine)
    img.header.set_xyzt_units("micron")
    path = tmp_path / "scaled.nii"
    nib.save(img, str(path))
    blob = bytearray(path.read_bytes())  # nibabel rescales arrays it saves: set it after
    struct.pack_into("<2f", blob, 112, 0.25, -40.0)  # scl_slope, scl_inter
    path.write_bytes(bytes(blob))
    scaled = nib.load(str(path)).dataobj
    assert (scaled.slope, scaled.inter) == (0.25, -40.0)
    reference = sitk.ReadImage(str(path))
    ours = read_dataset(path)
    np.testing.assert_allclose(ours.spacing, np.asarray(SPACING) * 1e-3, rtol=1e-6)
    assert_same_image(ours, reference, others=[nibabel_values(path, probe_points(reference))])


@pytest.mark.parametrize(
    ("qform_code", "sform_code", "sform"),
    [
        (1, 2, "other"),  # FSL's registered images: scanner qform, aligned sform
        (2, 4, "other"),  # an MNI sform beside an aligned qform
        (1, 1, "other"),  # a scanner sform wins
        (0, 2, "other"),  # the sform alone
        (1, 0, "other"),  # the qform alone
        (1, 2, "same"),
        (1, 1, "sheared"),  # ITK cannot hold a shear: the qform
    ],
)
def test_nifti_placed_by_the_sform_or_qform_simpleitk_chooses(
    tmp_path, qform_code, sform_code, sform
):
    """Differing qform and sform: the voxels land where SimpleITK (ITK, ANTs, Slicer) puts them."""
    values = sitk.GetArrayFromImage(sitk_image("oblique", np.int16)).T
    qform = np.eye(4)
    qform[:3, :3] = LPS_RAS @ DIRECTIONS["oblique"] * SPACING
    qform[:3, 3] = LPS_RAS @ ORIGIN
    other = np.eye(4)
    other[:3, :3] = LPS_RAS @ DIRECTIONS["oblique reflected"] * SPACING
    other[:3, 3] = [7.0, -9.0, 11.0]
    sheared = qform.copy()
    sheared[:3, 1] += 0.4 * qform[:3, 0]
    img = nib.Nifti1Image(values, None)
    img.set_qform(qform, code=qform_code)
    img.set_sform({"other": other, "same": qform, "sheared": sheared}[sform], code=sform_code)
    img.header.set_zooms(SPACING)
    path = tmp_path / "forms.nii"
    nib.save(img, str(path))
    header = nib.load(str(path)).header
    assert (int(header["qform_code"]), int(header["sform_code"])) == (qform_code, sform_code)
    reference = sitk.ReadImage(str(path))
    assert_same_image(read_dataset(path), reference)


def test_ras_space_nrrd_is_converted_to_lps(tmp_path):
    """A hand-written RAS NRRD: the exact affine of its header, negated in x and y."""
    values = sitk.GetArrayFromImage(sitk_image("oblique", np.int16, seed=3))
    columns = DIRECTIONS["oblique reflected"] * SPACING  # RAS axis vectors, one a column
    origin = np.array([10.0, -20.0, 30.0])
    fmt = lambda v: "(" + ",".join(f"{x:.17g}" for x in v) + ")"  # noqa: E731
    header = (
        "NRRD0004\ntype: short\ndimension: 3\nspace: right-anterior-superior\n"
        f"sizes: {SIZE[0]} {SIZE[1]} {SIZE[2]}\n"
        f"space directions: {' '.join(fmt(c) for c in columns.T)}\n"
        "kinds: domain domain domain\nendian: little\nencoding: raw\n"
        f"space origin: {fmt(origin)}\n\n"
    )
    path = tmp_path / "ras.nrrd"
    path.write_bytes(header.encode() + values.astype("<i2").tobytes())
    ours = read_dataset(path)
    reference = sitk.ReadImage(str(path))
    assert_same_image(ours, reference)
    # voxel (i, j, k) at LPS (origin + columns @ index) with x and y negated
    rng = np.random.default_rng(5)
    flat = np.asarray(ours.active_scalars)
    for i, j, k in rng.integers(0, SIZE, size=(30, 3)):
        lps = LPS_RAS @ (origin + columns @ [i, j, k])
        found = ours.FindPoint(lps)
        np.testing.assert_allclose(ours.points[found], lps, atol=1e-6)
        assert flat[found] == values[k, j, i]


@pytest.mark.parametrize(
    ("dtype", "components"), [(np.float32, 1), (np.int16, 3), (np.int64, 1), (np.uint64, 1)]
)
def test_nrrd_written_here_is_read_by_simpleitk_where_it_was(tmp_path, dtype, components):
    """Also 64-bit integers, which SimpleITK writes as ``long long int`` and the like."""
    source = tmp_path / "source.mha"
    sitk.WriteImage(sitk_image("oblique reflected", dtype, components, seed=4), str(source))
    image = read_dataset(source)
    image.point_data["mask"] = (np.arange(image.n_points) % 3 == 0).astype(np.uint8)
    written = write_dataset(tmp_path / "out.nrrd", image)
    assert written == [tmp_path / "out.nrrd", tmp_path / "out_mask.nrrd"]
    reference = sitk.ReadImage(str(source))
    back = sitk.ReadImage(str(tmp_path / "out.nrrd"))
    assert_same_image(image, back)
    assert_same_image(read_dataset(tmp_path / "out.nrrd"), reference)
    mask = sitk.ReadImage(str(tmp_path / "out_mask.nrrd"))
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(mask).ravel(), image["mask"])
    assert mask.GetDirection() == pytest.approx(back.GetDirection(), abs=1e-12)


@pytest.mark.parametrize("name", ["a.nii.gz", "b.mha", "c.mhd", "d.nrrd"])
def test_image_whose_extent_starts_past_zero_is_written_where_its_voxels_are(tmp_path, name):
    """A piece of a grid (``extract_subset``, a pipeline's piece) starts at a voxel other
    than (0, 0, 0): every file written holds each voxel at that voxel's point, as SimpleITK
    reads it, the array beside the main one too."""
    piece = pv.ImageData()
    piece.SetExtent(5, 16, -3, 10, 2, 9)
    piece.spacing, piece.origin = SPACING, ORIGIN
    piece.direction_matrix = DIRECTIONS["oblique reflected"]
    rng = np.random.default_rng(9)
    piece.point_data["v"] = rng.integers(-1000, 3000, piece.n_points).astype(np.int16)
    piece.point_data["mask"] = (np.arange(piece.n_points) % 3 == 0).astype(np.uint8)
    piece.set_active_scalars("v")
    written = write_dataset(tmp_path / name, piece)
    assert len(written) == 2
    points = np.asarray(piece.points)  # PyVista's: origin + D @ ((extent start + ijk) * s)
    for path, array in zip(written, ("v", "mask"), strict=True):
        back = sitk.ReadImage(str(path))
        assert back.GetSize() == tuple(piece.dimensions)
        index = np.array([back.TransformPhysicalPointToContinuousIndex(p.tolist()) for p in points])
        ijk = np.rint(index).astype(int)
        np.testing.assert_allclose(index, ijk, atol=1e-4)  # on the file's voxels
        values = sitk.GetArrayViewFromImage(back)[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        np.testing.assert_array_equal(values, piece.point_data[array])


def test_oblique_dicom_series_lands_where_simpleitk_reads_it(tmp_path):
    """Two series in one folder: the larger by default, the other through one of its files."""
    folder = tmp_path / "dicom"
    source = sitk_image("oblique", np.int16, seed=6)
    write_dicom_series(folder, source, "1.2.826.0.1.3680043.9.7.1")
    small = sitk_image("oblique", np.int16, seed=7)[:, :, :5]
    write_dicom_series(folder, small, "1.2.826.0.1.3680043.9.7.2")
    ours = read_dataset(folder)
    assert ours.dimensions == SIZE
    assert_same_image(ours, read_series(folder, "1.2.826.0.1.3680043.9.7.1"))
    assert_same_image(ours, source)  # slices in the order of their positions
    other = read_dataset(folder / "1.2.826.0.1.3680043.9.7.2_002.dcm")
    assert other.dimensions == (SIZE[0], SIZE[1], 5)
    assert_same_image(other, read_series(folder, "1.2.826.0.1.3680043.9.7.2"))
    # two series of one size: which one is meant is not guessed
    write_dicom_series(folder, small, "1.2.826.0.1.3680043.9.7.3")
    for k in range(5, SIZE[2]):  # the first series down to 5 slices too
        (folder / f"1.2.826.0.1.3680043.9.7.1_{k:03d}.dcm").unlink()
    with pytest.raises(ReadError, match=r"3 DICOM series of 5 slices.*give one file"):
        read_dataset(folder)
    # a file without a suffix is known by its DICOM preamble
    bare = folder / "slice"
    (folder / "1.2.826.0.1.3680043.9.7.3_001.dcm").rename(bare)
    assert_same_image(read_dataset(bare), read_series(folder, "1.2.826.0.1.3680043.9.7.3"))


@pytest.mark.parametrize("fault", ["missing slice", "gantry tilt", "rounded positions"])
def test_dicom_series_off_a_regular_grid_is_refused_not_misplaced(tmp_path, fault, capsys):
    """SimpleITK puts a series' slices on one regular grid whatever their positions say: a
    missing slice or a gantry tilt (slices shifted in-plane) would be bent and written a
    slice or more from where the scanner saw it. Refused in one line naming a slice; a
    series whose positions are merely rounded is read as SimpleITK reads it."""
    folder = tmp_path / "series"
    source = sitk_image("oblique", np.int16, seed=5)
    depth = source.GetDepth()
    shifts = np.zeros((depth, 3))
    if fault == "gantry tilt":  # each slice 0.4 mm further along its rows
        shifts = np.outer(np.arange(depth), 0.4 * DIRECTIONS["oblique"][:, 1])
    elif fault == "rounded positions":
        shifts = np.random.default_rng(3).uniform(-4e-4, 4e-4, (depth, 3))
    write_dicom_series(folder, source, "1.2.826.0.1.3680043.9.7.5", shifts)
    files = sorted(folder.glob("*.dcm"))
    if fault == "missing slice":
        files.pop(6).unlink()
    theirs = read_series(folder)
    placed = [theirs.TransformIndexToPhysicalPoint((0, 0, k)) for k in range(len(files))]
    found = [sitk.ReadImage(str(f)).GetOrigin() for f in files]  # each file's position
    worst = np.linalg.norm(np.subtract(found, placed), axis=1).max()
    if fault == "rounded positions":
        assert worst < 1e-3
        assert_same_image(read_dataset(folder), theirs)
        return
    assert worst > 1.0  # SimpleITK's grid moves a slice by more than a millimetre
    with pytest.raises(ReadError, match=r"not evenly spaced.*slice \d+ \(.*\.dcm\)"):
        read_dataset(folder)
    with pytest.raises(ReadError, match="not evenly spaced"):
        read_dataset(files[2])  # one file of the series
    scene = translation_scene(tmp_path, theirs, [0.0, 0.0, 0.0])
    out = tmp_path / "out.nii.gz"
    assert main(["deform", str(folder), "-s", str(scene), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err.strip()
    assert "not evenly spaced" in err and len(err.splitlines()) == 1 and not out.exists()


def test_nrrd_whose_dimension_and_sizes_disagree_is_refused_naming_them(tmp_path):
    path = tmp_path / "two.nrrd"
    sitk.WriteImage(sitk_image("oblique", np.int16), str(path), False)
    header = path.read_bytes()
    assert header.count(b"sizes: 20 24 16") == 1
    path.write_bytes(header.replace(b"sizes: 20 24 16", b"sizes: 20 24", 1))
    with pytest.raises(ReadError, match="corrupt NRRD header: dimension 3 but sizes 20 24$"):
        read_dataset(path)


def test_nrrd_promising_more_voxels_than_it_holds_is_refused_before_simpleitk(tmp_path):
    for name in ("a.nrrd", "b.nhdr"):
        path = tmp_path / name
        sitk.WriteImage(sitk_image("oblique", np.int16), str(path), False)
        data = tmp_path / "b.raw" if name.endswith(".nhdr") else path
        data.write_bytes(data.read_bytes()[:-2])
        with pytest.raises(ReadError, match=r"truncated or corrupt: .*voxels.* needs 15360 bytes"):
            read_dataset(path)


@pytest.mark.parametrize("name", ["plane.mha", "plane.mhd", "plane.nii", "plane.nrrd"])
def test_oblique_2d_image_lands_where_simpleitk_reads_it(tmp_path, name):
    """A rotated 2-D image: every voxel at SimpleITK's physical point, with its value."""
    values = np.arange(9 * 7, dtype=np.int16).reshape(9, 7)
    image = sitk.GetImageFromArray(values)
    image.SetDirection([0.6, -0.8, 0.8, 0.6])  # row by row: the x axis is (0.6, 0.8)
    image.SetOrigin([5.0, -3.0])
    image.SetSpacing([0.5, 2.0])
    sitk.WriteImage(image, str(tmp_path / name))
    reference = sitk.ReadImage(str(tmp_path / name))
    ours = read_dataset(tmp_path / name)
    assert tuple(ours.dimensions) == (7, 9, 1)
    want = [
        [*reference.TransformIndexToPhysicalPoint((i, j)), 0.0] for j in range(9) for i in range(7)
    ]
    np.testing.assert_allclose(ours.points, want, atol=1e-5)
    np.testing.assert_array_equal(ours.active_scalars, values.ravel())


@pytest.mark.parametrize(
    ("dtype", "met", "long"),
    [(np.int32, b"MET_INT", b"MET_LONG"), (np.uint32, b"MET_UINT", b"MET_ULONG")],
)
def test_metaimage_of_met_long_voxels_is_read_as_simpleitk_reads_it(tmp_path, dtype, met, long):
    """MET_LONG is 32 bits in MetaIO: VTK read it as 64 (and the size check refused it)."""
    path = tmp_path / "long.mha"
    sitk.WriteImage(sitk_image("oblique", dtype), str(path))
    header = path.read_bytes()
    assert header.count(b"ElementType = " + met + b"\n") == 1
    path.write_bytes(header.replace(b"ElementType = " + met, b"ElementType = " + long, 1))
    reference = sitk.ReadImage(str(path))
    assert reference.GetPixelID() in (sitk.sitkInt32, sitk.sitkUInt32)
    assert_same_image(read_dataset(path), reference)


@pytest.mark.parametrize("name", ["flipped.mha", "flipped.mhd"])
def test_metaimage_negative_spacing_turns_its_axis_over_as_in_simpleitk(tmp_path, name):
    """``ElementSpacing = -0.8 1.3 -2``: ITK reads +0.8 and +2 along reversed axes."""
    path = tmp_path / name
    sitk.WriteImage(sitk_image("oblique", np.int16), str(path))
    header = path.read_bytes()
    spacing = " ".join(f"{v:.17g}" for v in SPACING).encode()
    assert header.count(b"ElementSpacing = " + spacing) == 1
    path.write_bytes(header.replace(spacing, b"-0.8 1.3 -2", 1))
    reference = sitk.ReadImage(str(path))
    assert np.linalg.det(np.reshape(reference.GetDirection(), (3, 3))) > 0  # two axes over
    assert_same_image(read_dataset(path), reference)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (b"DimSize = 20 24 16", b"DimSize = 20 24", "NDims 3 but DimSize 20 24"),
        (b"NDims = 3", b"NDims = 2", "NDims 2 but DimSize 20 24 16"),
        (b"TransformMatrix = ", b"TransformMatrix = 1 0 ", "TransformMatrix has 11 values"),
    ],
)
def test_metaimage_header_contradicting_itself_is_refused(tmp_path, old, new, message):
    """VTK read such a header as a 1-voxel image, or without its direction."""
    path = tmp_path / "scan.mha"
    sitk.WriteImage(sitk_image("oblique", np.int16), str(path))
    header = path.read_bytes()
    assert header.count(old) == 1
    path.write_bytes(header.replace(old, new))
    with pytest.raises(ReadError, match=f"corrupt MetaImage header: {message}"):
        read_dataset(path)


def test_images_of_more_than_three_dimensions_are_refused_not_cut(tmp_path, capsys):
    """A time series (4-D) would lose all but one of its volumes: refused in one line."""
    series = np.arange(3 * 9 * 8 * 7, dtype=np.int16).reshape(3, 9, 8, 7)
    series_4d = sitk.GetImageFromArray(series, isVector=False)
    sitk.WriteImage(series_4d, str(tmp_path / "series.mha"))
    affine = np.diag([1.5, 0.7, 2.2, 1.0])
    nib.save(nib.Nifti1Image(series.T, affine), str(tmp_path / "series.nii.gz"))
    for name in ("series.mha", "series.nii.gz"):
        with pytest.raises(ReadError, match=r"a 4-D image.*give a 2-D or 3-D one"):
            read_dataset(tmp_path / name)
        scene = translation_scene(tmp_path, sitk_image("oblique", np.int16), [1.0, 0.0, 0.0])
        out = tmp_path / "out.nii"
        status = main(["deform", str(tmp_path / name), "-s", str(scene), "-o", str(out), "-q"])
        err = capsys.readouterr().err.strip()
        assert status != 0 and "4-D image" in err and len(err.splitlines()) == 1
    # one time point, or a vector per voxel (NIfTI's fifth axis), is a 3-D image
    nib.save(nib.Nifti1Image(series[0].T[..., None], affine), str(tmp_path / "one.nii"))
    vectors = np.moveaxis(series, 0, -1).transpose(2, 1, 0, 3)[:, :, :, None, :]
    vector_image = nib.Nifti1Image(vectors.astype(np.float32), affine)
    vector_image.header.set_intent("vector")
    nib.save(vector_image, str(tmp_path / "vec.nii"))
    for name in ("one.nii", "vec.nii"):
        reference = sitk.ReadImage(str(tmp_path / name))
        ours = read_dataset(tmp_path / name)
        np.testing.assert_allclose(ours.spacing, [1.5, 0.7, 2.2], rtol=1e-6)
        np.testing.assert_array_equal(
            np.asarray(ours.active_scalars).ravel(),
            sitk.GetArrayFromImage(reference).ravel(),
        )


def test_complex_images_are_refused_in_one_line_naming_the_voxel_type(tmp_path, capsys):
    """Complex voxels are no 2-vector: deforming their real and imaginary parts apart would
    be silent nonsense, so NIfTI (nibabel's) and NRRD (SimpleITK's) complex images are
    refused, naming the voxel type as SimpleITK does and what to convert them to."""
    values = (np.arange(4 * 5 * 6) * (1 + 2j)).reshape(4, 5, 6)
    affine = np.diag([1.5, 0.7, 2.2, 1.0])
    paths = {}  # path: the voxel type, as SimpleITK reads it from the NIfTI-1 file
    for dtype in (np.complex64, np.complex128):
        names = [tmp_path / f"{np.dtype(dtype).name}_{name}"
                 for name in ("a.nii", "b.nii.gz", "c.nrrd", "d.nhdr")]  # fmt: skip
        nib.save(nib.Nifti1Image(values.astype(dtype), affine), str(names[0]))
        nib.save(nib.Nifti2Image(values.astype(dtype), affine), str(names[1]))  # not SimpleITK's
        for path in names[2:]:
            sitk.WriteImage(sitk.GetImageFromArray(values.T.astype(dtype)), str(path))
        paths.update(dict.fromkeys(names, sitk.ReadImage(str(names[0])).GetPixelIDTypeAsString()))
    scene = translation_scene(tmp_path, sitk.ReadImage(str(names[0])), [1.0, 0.0, 0.0])
    for path, kind in paths.items():
        assert kind.startswith("complex of "), kind
        if path.suffix in (".nrrd", ".nhdr"):  # the same voxel type in either format
            assert sitk.ReadImage(str(path)).GetPixelIDTypeAsString() == kind
        expected = (
            f"{path}: cannot read (its voxel type is {kind}, which vhm_viz does not deform; "
            "convert it to its magnitude or real part first, e.g. with SimpleITK's "
            "ComplexToModulus or ComplexToReal)"
        )
        with pytest.raises(ReadError) as caught:
            read_dataset(path)
        assert str(caught.value) == expected
        out = tmp_path / "out.nii"
        status = main(["deform", str(path), "-s", str(scene), "-o", str(out), "-q"])
        assert status == 1 and capsys.readouterr().err == f"vhm-viz deform: error: {expected}\n"
        assert not out.exists()


@pytest.mark.parametrize("axis", [1, 3])
def test_nifti_with_a_negative_voxel_size_is_refused_naming_it(tmp_path, axis):
    # the standard wants pixdim[1:4] positive; SimpleITK flips such an axis, nibabel reads
    # the sform: which way the voxels lie is not for the reader to guess
    values = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)
    img = nib.Nifti1Image(values, np.diag([2.0, 3.0, 4.0, 1.0]))
    img.header["pixdim"][axis] *= -1.0
    path = tmp_path / "negative.nii"
    nib.save(img, str(path))
    header = np.frombuffer(path.read_bytes()[76:108], dtype="<f4")
    assert header[axis] < 0  # as written, whatever nibabel says when it reads it back
    with pytest.raises(ReadError, match=rf"voxel size pixdim\[{axis}\] is -\d; NIfTI voxel"):
        read_dataset(path)


def test_arrays_beside_an_output_never_overwrite_an_input(tmp_path):
    image = pv.ImageData(dimensions=(3, 4, 5))
    image.point_data["v"] = np.arange(image.n_points, dtype=np.float32)
    image.point_data["mask"] = np.ones(image.n_points, np.uint8)
    keep = tmp_path / "out_mask.nii.gz"
    keep.write_bytes(b"an input")
    with pytest.raises(ValueError, match="refusing to overwrite the input file"):
        write_dataset(tmp_path / "out.nii.gz", image, inputs=[keep])
    assert keep.read_bytes() == b"an input" and not (tmp_path / "out.nii.gz").exists()


# ---------------------------------------------------------------------------- the command line


def translation_scene(folder: Path, reference, shift) -> Path:
    """A scene: a box cage around ``reference``'s corners, four constraints moved by shift."""
    size = np.asarray(reference.GetSize()) - 1
    corners = np.array([
        reference.TransformContinuousIndexToPhysicalPoint((size * c).tolist())
        for c in np.array(np.meshgrid([0, 1], [0, 1], [0, 1])).reshape(3, -1).T
    ])  # fmt: skip
    lo, hi = corners.min(0), corners.max(0)
    points = 0.5 * (lo + hi) + 0.25 * (hi - lo) * np.vstack([np.zeros(3), np.eye(3)])
    moved = {"positions": points.tolist(), "targets": (points + shift).tolist()}
    return box_scene(folder, lo, hi, constraints=moved)


def test_left_handed_nifti_keeps_its_voxel_order_through_a_deformation(tmp_path, capsys):
    """A NIfTI with qfac -1 (dcm2niix's LAS scans): read in the file's slice order, as
    SimpleITK reads it, and the identity map writes it back voxel for voxel on its grid,
    by default and onto it as a --reference."""
    values = sitk.GetArrayFromImage(sitk_image("oblique", np.int16)).T
    affine = np.eye(4)
    affine[:3, :3] = LPS_RAS @ DIRECTIONS["oblique reflected"] * SPACING  # det < 0
    affine[:3, 3] = LPS_RAS @ ORIGIN
    img = nib.Nifti1Image(values, affine)
    img.set_qform(affine, code=1)
    img.set_sform(affine, code=1)
    path = tmp_path / "las.nii.gz"
    nib.save(img, str(path))
    assert nib.load(str(path)).header["pixdim"][0] == -1.0
    reference = sitk.ReadImage(str(path))
    ours = read_dataset(path)
    np.testing.assert_allclose(ours.origin, reference.GetOrigin(), atol=1e-4)
    np.testing.assert_allclose(np.ravel(ours.direction_matrix), reference.GetDirection(), atol=1e-6)
    np.testing.assert_array_equal(ours.active_scalars, sitk.GetArrayFromImage(reference).ravel())
    lo, hi = np.reshape(ours.bounds, (3, 2)).T
    centre = 0.5 * (lo + hi)
    still = {"positions": [centre.tolist()], "targets": [centre.tolist()]}
    scene = box_scene(tmp_path, lo, hi, constraints=still)
    for extra in ([], ["--reference", str(path)]):
        out = tmp_path / "out.nii.gz"
        args = ["deform", str(path), "-s", str(scene), "-o", str(out), "-q", *extra]
        assert main(args) == 0, capsys.readouterr().err
        again = nib.load(str(out))
        np.testing.assert_allclose(again.affine, affine, atol=1e-4)
        np.testing.assert_array_equal(np.asarray(again.dataobj), values)


def sform_only_nifti(folder: Path, sform: str):
    """An sform-only NIfTI, sheared or with a voxel size other than pixdim, and a scene
    moving it 2 mm along x: (path, values, affine, scene)."""
    rng = np.random.default_rng(4)
    values = (100 * rng.normal(size=(14, 16, 12))).astype(np.float32)
    affine = np.diag([1.5, 0.9, 2.0, 1.0])
    affine[:3, 3] = [5.0, 6.0, 7.0]
    if sform == "sheared":
        affine[0, 1] = 0.4
    img = nib.Nifti1Image(values, None)
    img.set_sform(affine, code=2)
    img.set_qform(None, code=0)
    img.header.set_zooms((1.5, 0.9, 2.0) if sform == "sheared" else (1.0, 1.0, 1.0))
    path = folder / "in.nii"
    nib.save(img, str(path))
    lo, hi = np.reshape(read_dataset(path).bounds, (3, 2)).T
    points = 0.5 * (lo + hi) + 0.2 * (hi - lo) * np.vstack([np.zeros(3), np.eye(3)])
    moved = {"positions": points.tolist(), "targets": (points + [2.0, 0.0, 0.0]).tolist()}
    return path, values, affine, box_scene(folder, lo, hi, constraints=moved)


@pytest.mark.parametrize("sform", ["sheared", "scaled"])
def test_nifti_sform_beyond_a_rotation_survives_a_deformation(tmp_path, sform, capsys):
    """An sform-only NIfTI with a shear, or with a voxel size other than pixdim, moved 2 mm:
    the output's voxels hold the input's (nibabel's placement) 2 mm on, read back by
    vhm_viz, nibabel and SimpleITK, or refused by SimpleITK (which holds no shear)."""
    path, values, affine, scene = sform_only_nifti(tmp_path, sform)
    out = tmp_path / "out.nii.gz"
    assert main(["deform", str(path), "-s", str(scene), "-o", str(out), "-q"]) == 0, capsys

    def expected(lps):  # the input at lps - 2 mm in x, through nibabel's affine
        ras = LPS_RAS @ (lps - [2.0, 0.0, 0.0]).T
        index = (np.linalg.inv(affine) @ np.vstack([ras, np.ones(ras.shape[1])]))[:3]
        inside = np.all((index > 1) & (index < np.array(values.shape)[:, None] - 2), axis=0)
        return map_coordinates(values, index, order=1), inside

    ours = read_dataset(out)
    want, inside = expected(np.asarray(ours.points))
    assert inside.sum() > 500
    got = np.asarray(ours.active_scalars)
    np.testing.assert_allclose(got[inside], want[inside], atol=1e-3)
    theirs = nib.load(str(out))
    ijk = np.indices(theirs.shape).reshape(3, -1)
    lps = LPS_RAS @ (theirs.affine @ np.vstack([ijk, np.ones(ijk.shape[1])]))[:3]
    want, inside = expected(lps.T)
    got = np.asarray(theirs.get_fdata()).reshape(-1)
    np.testing.assert_allclose(got[inside], want[inside], atol=1e-3)
    if sform == "sheared":
        with pytest.raises(RuntimeError, match="orthonormal"):
            sitk.ReadImage(str(out))
    else:
        reference = sitk.ReadImage(str(out))
        assert_same_image(ours, reference)


def test_field_on_a_sheared_grid_is_refused_as_nifti_and_applied_by_simpleitk_as_mha(
    tmp_path, capsys
):
    """ITK's NIfTI writer turns a sheared grid into a rotation: such a field is refused in
    one line (nothing written); as .mha, SimpleITK applies it and gets vhm-viz's output."""
    path, _, _, scene = sform_only_nifti(tmp_path, "sheared")
    out, field = tmp_path / "out.mha", tmp_path / "field.nii.gz"
    args = ["deform", str(path), "-s", str(scene), "-o", str(out), "-q", "--write-field"]
    assert main([*args, str(field)]) == 1
    err = capsys.readouterr().err.strip()
    assert "sheared" in err and ".mha" in err and len(err.splitlines()) == 1
    assert not out.exists() and not field.exists()
    assert main([*args, str(tmp_path / "field.mha")]) == 0
    bent, displacement = sitk.ReadImage(str(out)), sitk.ReadImage(str(tmp_path / "field.mha"))
    assert np.allclose(displacement.GetDirection(), bent.GetDirection())
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "field_mask.mha"))) == 1
    transform = sitk.DisplacementFieldTransform(sitk.Image(displacement))
    ours = read_dataset(path)
    source = sitk.GetImageFromArray(
        np.asarray(ours.active_scalars).reshape(tuple(ours.dimensions)[::-1])
    )
    source.SetOrigin(ours.origin)
    source.SetSpacing(ours.spacing)
    source.SetDirection(np.ravel(ours.direction_matrix).tolist())
    again = sitk.GetArrayFromImage(sitk.Resample(source, bent, transform, sitk.sitkLinear))
    np.testing.assert_allclose(again[mask], sitk.GetArrayFromImage(bent)[mask], atol=1e-2)


@pytest.mark.parametrize("kind", ["nrrd", "dicom", "dicom file without suffix"])
def test_cli_deforms_oblique_scans_in_simpleitks_frame(tmp_path, kind, capsys):
    """A translation by t: the .nrrd output is SimpleITK's resampling of the input at y - t."""
    source = sitk.SmoothingRecursiveGaussian(sitk_image("oblique", np.float32, seed=8), 2.0)
    if kind == "nrrd":
        path = tmp_path / "in.nrrd"
        sitk.WriteImage(source, str(path))
        reference = sitk.ReadImage(str(path))
    else:
        path = tmp_path / "series"
        series = sitk.Cast(source * 10, sitk.sitkInt16)
        write_dicom_series(path, series, "1.2.826.0.1.3680043.9.7.9")
        reference = read_series(path)
        if kind != "dicom":  # one file of the series, named as scanners often name them
            path = path / "IM0003"
            sorted((tmp_path / "series").glob("*.dcm"))[3].rename(path)
    shift = np.array([1.5, -0.7, 0.9])
    scene = translation_scene(tmp_path, reference, shift)
    out = tmp_path / "out.nrrd"
    assert main(["deform", str(path), "-s", str(scene), "-o", str(out), "-q"]) == 0
    summary = capsys.readouterr().out
    mask_file = tmp_path / "out_vtkValidPointMask.nrrd"
    assert str(out) in summary and str(mask_file) in summary
    result = sitk.ReadImage(str(out))  # written here, read by SimpleITK
    inverse = sitk.TranslationTransform(3, (-shift).tolist())
    expected = sitk.Resample(reference, result, inverse, sitk.sitkLinear, 0.0, sitk.sitkFloat64)
    inside = sitk.Resample(reference * 0 + 1, result, inverse, sitk.sitkLinear, 0.0)
    valid = sitk.GetArrayFromImage(sitk.ReadImage(str(mask_file))).astype(bool)
    keep = valid & (sitk.GetArrayFromImage(inside) > 0.999)  # no fill value mixed in
    assert keep.mean() > 0.5  # most of the moved image is compared
    got = sitk.GetArrayFromImage(result).astype(np.float64)
    want = sitk.GetArrayFromImage(expected)
    values = sitk.GetArrayViewFromImage(reference)
    scale = float(values.max() - values.min())
    rounding = 0.5 if values.dtype.kind in "iu" else 0.0  # the output keeps the input's type
    np.testing.assert_allclose(got[keep], want[keep], rtol=0, atol=rounding + 1e-5 * scale)
