"""Displacement fields out: what SimpleITK/ITK, ANTs and 3D Slicer apply (issue 35).

On the 64x64x93 CT head bent by the head scene (one end held, the other moved 50 mm and
turned): the pull-back field that ``vhm-viz deform --write-field`` writes, applied by
SimpleITK's own ``Resample`` through its ``DisplacementFieldTransform``, reproduces the
image vhm_viz resampled; the forward field moves points where ``vhm-viz deform`` (the
exact map) moves them. Files are read back with SimpleITK and nibabel, the references.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
sitk = pytest.importorskip("SimpleITK")
nib = pytest.importorskip("nibabel")

from conftest import box_cage, data_path  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

import vhm_viz  # noqa: E402
from vhm_viz import Cage, HarmonicMap  # noqa: E402
from vhm_viz.cli import main  # noqa: E402
from vhm_viz.core.image import ImageGeometry  # noqa: E402
from vhm_viz.core.volume import VolumeDeformation  # noqa: E402
from vhm_viz.io import read_dataset  # noqa: E402
from vhm_viz.io.fields import write_displacement_field  # noqa: E402
from vhm_viz.scene import Scene  # noqa: E402

SCENE = Path(vhm_viz.__file__).parent / "scenes" / "head_scene.json"


def _cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _itk_image(values, geo: ImageGeometry):
    """The volume as SimpleITK holds it: (z, y, x) voxels with the grid's frame."""
    image = sitk.GetImageFromArray(
        np.asarray(values, dtype=np.float64).reshape(geo.dimensions[::-1])
    )
    image.SetOrigin(tuple(geo.origin))
    image.SetSpacing(tuple(geo.spacing))
    image.SetDirection(tuple(geo.direction.ravel()))
    return image


@pytest.fixture(scope="module")
def head():
    path = data_path("volumes", "headsq_64x64x93.vti")
    img = read_dataset(path)
    geo = ImageGeometry(img.origin, img.spacing, img.dimensions, img.direction_matrix)
    return path, img, geo


@pytest.fixture(scope="module")
def pulled(head, tmp_path_factory):
    """``vhm-viz deform`` of the head to NIfTI with its pull-back field, and its summary."""
    path, img, geo = head
    folder = tmp_path_factory.mktemp("fields")
    out, field = folder / "bent.nii.gz", folder / "field.nii.gz"
    argv = ["deform", path, "-s", SCENE, "-o", out, "--write-field", field, "-q"]
    assert main([str(a) for a in argv]) == 0
    return folder, out, field


@pytest.fixture(scope="module")
def engine(head):
    """The library's volume engine of the same scene on the head."""
    path, img, geo = head
    return VolumeDeformation(Scene.load(SCENE).solve_map(img).deformer.harmonic_map, geo)


def test_simpleitk_applies_the_pullback_field_as_vhm_viz_resamples(head, pulled):
    path, img, geo = head
    folder, out, field_path = pulled
    field = sitk.ReadImage(str(field_path))
    assert (
        field.GetPixelID() == sitk.sitkVectorFloat64 and field.GetNumberOfComponentsPerPixel() == 3
    )
    bent = sitk.ReadImage(str(out))  # vhm_viz's resampled image, as ITK reads it
    assert bent.GetSize() == field.GetSize()
    np.testing.assert_allclose(bent.GetOrigin(), field.GetOrigin(), atol=1e-4)
    np.testing.assert_allclose(bent.GetSpacing(), field.GetSpacing(), atol=1e-6)
    np.testing.assert_allclose(bent.GetDirection(), field.GetDirection(), atol=1e-6)
    values = np.asarray(img.active_scalars, dtype=np.float64)
    moved = sitk.Resample(
        _itk_image(values, geo), referenceImage=field,
        transform=sitk.DisplacementFieldTransform(sitk.Image(field)),  # (it takes the image)
        interpolator=sitk.sitkLinear, defaultPixelValue=0.0,
    )  # fmt: skip
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(folder / "field_mask.nii.gz"))).ravel()
    assert set(np.unique(mask)) <= {0, 1, 2}
    valid = mask > 0
    assert 0.3 < valid.mean() < 0.9  # the bent head fills part of its grid
    ours = sitk.GetArrayFromImage(bent).ravel()[valid].astype(np.float64)
    theirs = sitk.GetArrayFromImage(moved).ravel()[valid]
    diff = np.abs(theirs - ours) / np.ptp(values)
    assert np.median(diff) <= 2e-3 and np.percentile(diff, 99.9) <= 2e-2
    vectors = sitk.GetArrayFromImage(field).reshape(-1, 3)
    assert np.abs(vectors[~valid]).max() == 0.0  # the identity where there is no pre-image
    assert np.linalg.norm(vectors[valid], axis=1).max() > 40.0  # a real bend (millimetres)


def test_the_field_files_are_what_itk_and_nibabel_read(head, pulled, engine, tmp_path):
    """NIfTI intent 1007 with LPS vectors as ITK/ANTs write them; MHA and NRRD alike."""
    path, img, geo = head
    folder, out, field_path = pulled
    nii = nib.load(str(field_path))
    assert int(nii.header["intent_code"]) == 1007
    nx, ny, nz = sitk.ReadImage(str(field_path)).GetSize()
    assert nii.shape == (nx, ny, nz, 1, 3)
    reference = sitk.ReadImage(str(field_path))
    ref_vectors = sitk.GetArrayFromImage(reference)
    # the vectors are stored as they are in ITK's LPS world (not negated for RAS)
    np.testing.assert_array_equal(
        np.asarray(nii.dataobj)[:, :, :, 0, :], ref_vectors.transpose(2, 1, 0, 3)
    )
    # the library's field, written to the other formats, reads back the same
    field = engine.displacement_field()
    assert field.geometry.dimensions == (nx, ny, nz)
    np.testing.assert_allclose(field.vectors, ref_vectors.reshape(-1, 3), rtol=0, atol=1e-9)
    for suffix in (".mha", ".nrrd", ".nii"):
        written, mask = write_displacement_field(tmp_path / f"f{suffix}", field)
        assert mask == tmp_path / f"f_mask{suffix}" and mask.exists()
        back = sitk.ReadImage(str(written))
        np.testing.assert_array_equal(sitk.GetArrayFromImage(back), ref_vectors)
        np.testing.assert_allclose(back.GetOrigin(), reference.GetOrigin(), atol=1e-6)
        np.testing.assert_allclose(back.GetDirection(), reference.GetDirection(), atol=1e-9)
        np.testing.assert_array_equal(
            sitk.GetArrayFromImage(sitk.ReadImage(str(mask))).ravel(), field.mask
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"f{m}{s}" for m in ("", "_mask") for s in (".mha", ".nrrd", ".nii")
    )  # nothing else left behind


def test_forward_field_moves_points_as_vhm_viz_deform(head, tmp_path, capsys):
    path, img, geo = head
    field_path = tmp_path / "forward.mha"
    rc, out, err = _cli(capsys, "deform", path, "-s", SCENE, "-o", tmp_path / "bent.vts",
                        "--write-field", field_path, "--field-kind", "forward", "-q")  # fmt: skip
    assert rc == 0, err
    assert f"forward field -> {field_path}" in out and str(tmp_path / "forward_mask.mha") in out
    field = sitk.ReadImage(str(field_path))
    assert field.GetSize() == tuple(img.dimensions)  # on the input grid
    transform = sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))
    rng = np.random.default_rng(3)
    ijk = rng.integers(0, img.dimensions, (400, 3))
    points = geo.points(ijk)
    np.save(tmp_path / "points.npy", points)
    rc, out, err = _cli(capsys, "deform", tmp_path / "points.npy", "-s", SCENE,
                        "-o", tmp_path / "moved.vtp", "-q")  # fmt: skip
    assert rc == 0, err
    exact = np.asarray(read_dataset(tmp_path / "moved.vtp").points, dtype=np.float64)
    by_field = np.array([transform.TransformPoint(tuple(p)) for p in points])
    # the volume engine's lattice is within its tolerance (0.05 voxel) of the exact map
    err_voxels = np.abs((by_field - exact) @ geo.world_to_index.T)
    assert err_voxels.max() <= 0.05
    assert np.linalg.norm(exact - points, axis=1).max() > 40.0  # they really moved


def test_accessor_gives_the_library_fields(head, pulled, engine):
    path, img, geo = head
    folder, out, field_path = pulled
    scene = Scene.load(SCENE)
    image = img.vhm.displacement_field(scene)
    reference = sitk.GetArrayFromImage(sitk.ReadImage(str(field_path))).reshape(-1, 3)
    np.testing.assert_allclose(image.point_data["vhm_displacement_field"], reference, atol=1e-9)
    assert image.point_data.active_vectors_name == "vhm_displacement_field"
    mask = sitk.GetArrayFromImage(sitk.ReadImage(str(folder / "field_mask.nii.gz"))).ravel()
    np.testing.assert_array_equal(image.point_data["vtkValidPointMask"], mask > 0)
    forward = img.vhm.displacement_field(scene, kind="forward")
    assert forward.dimensions == img.dimensions
    library = engine.displacement_field(kind="forward")
    np.testing.assert_allclose(forward.point_data["vhm_displacement_field"], library.vectors,
                               rtol=0, atol=1e-9)  # fmt: skip
    assert library.valid.all() and np.asarray(forward.point_data["vtkValidPointMask"]).all()
    np.testing.assert_array_equal(forward.point_data["vhm_foldover"], library.foldover)


def test_fields_of_an_affine_map_on_an_oblique_grid_are_exact():
    """``f(x) = A x + t``: the pull-back is ``A^-1 (y - t) - y``, the forward ``A x + t - x``.

    An oblique, reflected (det D = -1), anisotropic grid; the cage holds part of it only,
    so the outside policies show: passthrough leaves voxels in place (zero vectors, valid),
    ``"nan"`` gives them none (zero vectors, not valid).
    """
    direction = Rotation.from_rotvec([0.2, -0.3, 0.5]).as_matrix() @ np.diag([1.0, -1.0, 1.0])
    geo = ImageGeometry((5.0, -3.0, 2.0), (1.0, 0.8, 1.3), (14, 12, 10), direction)
    corners = geo.points(np.array([[0, 0, 0], [13, 11, 9]], dtype=float))
    centre = geo.points(np.array([[6.5, 5.5, 4.5]]))[0]
    cage = Cage(*box_cage(centre - 5.0, centre + 5.0, 1))  # smaller than the grid
    assert not np.all(np.abs(corners - centre) < 5.0)
    a = Rotation.from_rotvec([0.0, 0.0, 0.25]).as_matrix() * [1.1, 0.9, 1.0]
    t = centre - a @ centre + [0.7, -0.4, 0.2]
    hm = HarmonicMap.affine(cage, a, t)
    for outside in ("passthrough", "nan"):
        vol = VolumeDeformation(hm, geo, outside=outside, tolerance=0.01)
        pulled = vol.displacement_field()
        y = pulled.geometry.points()
        found = pulled.valid.astype(bool)
        x = np.linalg.solve(a, (y - t).T).T
        in_cage = np.all(np.abs(x - centre) < 5.0 - 1e-6, axis=1)
        # the map's own pre-images (not left in place), where the grid has voxels
        exact = found & in_cage & geo.bounds_contain(x, tol=0.0)
        assert exact.sum() > 200
        np.testing.assert_allclose(pulled.vectors[exact], (x - y)[exact], atol=0.01 * 1.3)
        assert np.abs(pulled.vectors[~found]).max(initial=0.0) == 0.0
        assert not pulled.foldover.any() and set(np.unique(pulled.mask)) <= {0, 1}
        forward = vol.displacement_field(kind="forward")
        p = geo.points()
        inside = np.all(np.abs(p - centre) < 5.0, axis=1)
        np.testing.assert_allclose(forward.vectors[inside], (p @ a.T + t - p)[inside], atol=1e-9)
        assert np.abs(forward.vectors[~inside]).max() < 1e-9  # left in place, or none
        np.testing.assert_array_equal(forward.valid, inside | (outside == "passthrough"))
        if outside == "passthrough":  # the outside voxels stayed: zero vectors, valid
            assert (found & ~in_cage).sum() > 100
            assert np.abs(pulled.vectors[found & ~in_cage]).max() < 1e-9
    # a box of the grid: the same vectors as the whole grid's there
    box = (2, 9, 1, 7, 3, 6)
    part = vol.displacement_field(pulled.geometry, box=box)
    nx, ny, nz = pulled.geometry.dimensions
    whole = pulled.vectors.reshape(nz, ny, nx, 3)
    inner = whole[box[4] : box[5] + 1, box[2] : box[3] + 1, box[0] : box[1] + 1]
    np.testing.assert_allclose(part.vectors, inner.reshape(-1, 3), rtol=0, atol=1e-9)
    np.testing.assert_allclose(part.geometry.origin, pulled.geometry.points([box[0::2]])[0])
    with pytest.raises(ValueError, match="input grid"):
        vol.displacement_field(pulled.geometry, kind="forward")


def test_bad_field_arguments_are_one_line(head, tmp_path, capsys):
    path, img, geo = head
    for field, why in ((tmp_path / "field.vti", ".nii, .nii.gz, .mha, .nrrd"),
                       (tmp_path / "o.nii.gz", "is the output")):  # fmt: skip
        rc, out, err = _cli(capsys, "deform", path, "-s", SCENE, "-o", tmp_path / "o.nii.gz",
                            "--write-field", field, "-q")  # fmt: skip
        assert rc != 0 and len(err.strip().splitlines()) == 1 and why in err
    # a file the output writes beside itself (its valid-voxel mask): not overwritten
    rc, _, err = _cli(capsys, "deform", path, "-s", SCENE, "-o", tmp_path / "o.nii.gz",
                      "--write-field", tmp_path / "o_vtkValidPointMask.nii.gz", "-q")  # fmt: skip
    assert rc != 0 and len(err.strip().splitlines()) == 1, err
    assert "o_vtkValidPointMask.nii.gz is also a file of the output" in err
    assert list(tmp_path.iterdir()) == []
    pts = tmp_path / "p.npy"
    np.save(pts, np.asarray(img.center)[None])
    rc, out, err = _cli(capsys, "deform", pts, "-s", SCENE, "-o", tmp_path / "o.vtp",
                        "--write-field", tmp_path / "f.nii.gz", "-q")  # fmt: skip
    assert rc != 0 and len(err.strip().splitlines()) == 1 and "volume" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.npy"]


def test_a_field_or_mask_that_is_an_input_says_to_change_write_field(head, tmp_path, capsys):
    # the refusal names the option that chose the file, not -o
    path, img, geo = head
    (tmp_path / "in.mha").symlink_to(path.resolve())
    rc, _, err = _cli(capsys, "deform", path, "-s", SCENE, "-o", tmp_path / "o.vti",
                      "--write-field", tmp_path / "in.mha", "-q")  # fmt: skip
    assert rc == 1 and err.strip().endswith("; choose another output (--write-field)"), err
    (tmp_path / "f_mask.mha").symlink_to(path.resolve())
    rc, _, err = _cli(capsys, "deform", path, "-s", SCENE, "-o", tmp_path / "o.vti",
                      "--write-field", tmp_path / "f.mha", "-q")  # fmt: skip
    assert rc == 1 and err.strip().endswith("; choose another output (--write-field)"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f_mask.mha", "in.mha"]
