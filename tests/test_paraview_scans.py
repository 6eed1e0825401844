"""ParaView's "VHM Medical Image Reader": the scan where read_dataset puts it, resampled as
the command line and the Python accessor resample it (pvpython, set up by
``plugins/paraview-env.sh``)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import box_cage, data_path
from test_paraview import paraview_env  # noqa: F401 - the pvpython environment

from vhm_viz.cli import main
from vhm_viz.io import read_dataset

pv = pytest.importorskip("pyvista")

ROOT = Path(__file__).resolve().parents[1]
NIFTI = data_path("volumes", "avg152T1_RL_nifti.nii.gz")
META = data_path("volumes", "HeadMRVolume.mhd")


def _ras_scene(image) -> dict:
    """A bend of the scan's box, written in RAS (Slicer's frame) from LPS by hand."""
    lo, hi = np.reshape(image.bounds, (3, 2)).T
    v, f = box_cage(lo - 4.0, hi + 4.0)
    c, size = (lo + hi) / 2, hi - lo
    anchors = [c + size * [x, y, z] for x in (-0.3, 0.3) for y in (-0.3, 0.3) for z in (-0.3, 0.3)]
    positions = np.array([c - size * [0.0, 0.0, 0.4], c + size * [0.0, 0.0, 0.4]])
    targets = positions + [[0.0, 0.0, 0.0], [0.08 * size[0], 0.0, 0.0]]
    flip = np.array([-1.0, -1.0, 1.0])
    return {"format": "vhm_viz.scene", "version": 1, "space": "RAS",
            "cage": {"vertices": (v * flip).tolist(), "faces": f.tolist()},
            "anchors": (np.array(anchors) * flip).tolist(),
            "constraints": {"positions": (positions * flip).tolist(),
                            "targets": (targets * flip).tolist()},
            "solver": {"tolerance": 1e-12, "max_iterations": 20000}}  # fmt: skip


def _small_radiological_nifti(path: Path) -> Path:
    """Every fourth voxel of the RL-flipped NIfTI, written by nibabel (23 x 28 x 23)."""
    nib = pytest.importorskip("nibabel")
    ref = nib.load(NIFTI)
    affine = ref.affine.copy()
    affine[:3, :3] *= 4
    nib.save(nib.Nifti1Image(np.asarray(ref.dataobj)[::4, ::4, ::4], affine), path)
    return path


def _oblique_scans(tmp_path: Path):
    """An oblique, anisotropic int16 image written by SimpleITK as NRRD and as a DICOM series."""
    sitk = pytest.importorskip("SimpleITK")
    rng = np.random.default_rng(35)
    image = sitk.GetImageFromArray(rng.integers(-900, 1500, size=(6, 8, 10)).astype(np.int16))
    image.SetSpacing((0.7, 1.1, 2.3))
    image.SetOrigin((-12.0, 30.0, 5.0))
    turn = sitk.VersorTransform((0.3, -0.2, 0.9), np.radians(25.0)).GetMatrix()
    image.SetDirection(turn)
    sitk.WriteImage(image, str(tmp_path / "oblique.nrrd"))
    folder = tmp_path / "dicom"
    folder.mkdir()
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    d = np.reshape(turn, (3, 3))
    cosines = "\\".join(f"{v:.9f}" for v in (*d[:, 0], *d[:, 1]))
    for k in range(image.GetDepth()):
        piece = image[:, :, k]
        corner = image.TransformIndexToPhysicalPoint((0, 0, k))
        for tag, value in {
            "0008|0060": "CT", "0020|000d": "1.2.826.0.1.3680043.2.1125.35.1",
            "0020|000e": "1.2.826.0.1.3680043.2.1125.35.2", "0020|0037": cosines,
            "0020|0032": "\\".join(f"{v:.9f}" for v in corner), "0020|0013": str(k + 1),
            "0018|0050": "2.3",
        }.items():  # fmt: skip
            piece.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"slice{k:03d}.dcm"))
        writer.Execute(piece)
    return image, [tmp_path / "oblique.nrrd", folder / "slice003.dcm"]


def _check_at_physical_points(got, ref) -> None:
    """``got`` (a vtkImageData read back) holds SimpleITK image ``ref``'s voxels where
    SimpleITK places them."""
    dims = np.array(ref.GetSize())
    assert tuple(got.dimensions) == tuple(dims)
    rng = np.random.default_rng(1)
    ijk = np.vstack([rng.integers(0, dims, size=(60, 3)), [0, 0, 0], dims - 1])
    flat = ijk[:, 0] + dims[0] * (ijk[:, 1] + dims[1] * ijk[:, 2])
    where = [ref.TransformIndexToPhysicalPoint([int(v) for v in i]) for i in ijk]
    np.testing.assert_allclose(np.asarray(got.points)[flat], where, atol=1e-4)
    values = [ref[[int(v) for v in i]] for i in ijk]
    np.testing.assert_array_equal(np.asarray(got.active_scalars)[flat], values)


def test_paraview_reader_and_resample_match_read_dataset_and_the_cli(paraview_env, tmp_path):  # noqa: F811
    oblique, others = _oblique_scans(tmp_path)
    small = _small_radiological_nifti(tmp_path / "small_rl.nii.gz")
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(_ras_scene(read_dataset(small))))
    config = {
        "scans": [[str(NIFTI), str(tmp_path / "nii.vti")], [str(META), str(tmp_path / "mhd.vti")]],
        "resample": [str(small), str(scene), str(tmp_path / "paraview.vti")],
    }
    config["scans"] += [[str(p), str(tmp_path / f"{p.stem}.vti")] for p in others]
    (tmp_path / "config.json").write_text(json.dumps(config))
    script = ROOT / "tests" / "paraview" / "scan_check.py"
    done = subprocess.run(
        ["pvpython", str(script), str(tmp_path / "config.json")],
        capture_output=True, text=True, env=paraview_env, timeout=900,
    )  # fmt: skip
    assert "vhm-scan-check: done" in done.stdout, done.stdout + done.stderr
    for _, out in config["scans"][2:]:  # NRRD and DICOM: SimpleITK is the reference
        _check_at_physical_points(pv.read(out), oblique)
    for path, out in config["scans"][:2]:
        ref, got = read_dataset(path), pv.read(out)
        assert got.dimensions == ref.dimensions
        np.testing.assert_allclose(got.origin, ref.origin, atol=1e-9)
        np.testing.assert_allclose(got.spacing, ref.spacing, atol=1e-9)
        np.testing.assert_allclose(got.direction_matrix, ref.direction_matrix, atol=1e-9)
        np.testing.assert_array_equal(got.active_scalars, ref.active_scalars)
    field = tmp_path / "field.nii.gz"
    cli_args = ["deform", str(small), "--scene", str(scene), "-o", str(tmp_path / "cli.vti")]
    assert main([*cli_args, "--write-field", str(field), "-q"]) == 0
    cli, para = pv.read(tmp_path / "cli.vti"), pv.read(tmp_path / "paraview.vti")
    assert para.dimensions == cli.dimensions
    np.testing.assert_allclose(para.origin, cli.origin, atol=1e-6)
    np.testing.assert_allclose(para.direction_matrix, cli.direction_matrix, atol=1e-12)
    a, b = np.asarray(cli.active_scalars, float), np.asarray(para.active_scalars, float)
    np.testing.assert_array_equal(para["vtkValidPointMask"], cli["vtkValidPointMask"])
    assert np.abs(a - b).max() <= 1e-6 * np.ptp(a)
    # the pull-back displacement field: ParaView's array is the command line's file
    sitk = pytest.importorskip("SimpleITK")
    from_cli = sitk.GetArrayFromImage(sitk.ReadImage(str(field))).reshape(-1, 3)
    np.testing.assert_allclose(para["vhm_displacement_field"], from_cli, atol=1e-9)
    assert np.abs(from_cli).max() > 1.0  # millimetres: a real bend
    # the explorer: the scan opened, the scene loaded and the deformed scan exported
    from vhm_viz.app.controller import ExplorerController

    explorer = ExplorerController()
    explorer.load_file(small)
    explorer.load_scene(scene)
    explorer.prepare()  # what the window's load job runs after loading
    explorer.deform()
    explorer.export(tmp_path / "explorer.vti")
    shown = pv.read(tmp_path / "explorer.vti")
    assert shown.dimensions == cli.dimensions
    np.testing.assert_allclose(shown.origin, cli.origin, atol=1e-6)
    e = np.asarray(shown.active_scalars, float)
    assert np.abs(a - e).max() <= 1e-6 * np.ptp(a)
    # Python: the accessor on the scan read_dataset opens
    python = read_dataset(small).vhm.resample(str(scene))
    assert python.dimensions == cli.dimensions
    np.testing.assert_allclose(python.origin, cli.origin, atol=1e-6)
    c = np.asarray(python.active_scalars, float)
    assert np.abs(a - c).max() <= 1e-6 * np.ptp(a)
    # a real bend: the deformed scan needs a wider grid than the scan
    assert np.ptp(cli.bounds[:2]) > np.ptp(read_dataset(small).bounds[:2]) + 1.0


def test_paraview_reader_of_an_unreadable_scan_says_why_in_one_line(paraview_env, tmp_path):  # noqa: F811
    """A missing or unreadable scan: the reader's one line names the file and the cause
    (not SimpleITK's source file), once from two ranks, and leaves an empty image: no
    traceback, no executive error."""
    from vhm_viz.filters.mpi import mpi_command

    garbage = tmp_path / "garbage.nii.gz"
    garbage.write_bytes(b"not a scan")
    script = tmp_path / "read.py"
    script.write_text(
        "import sys\n"
        "import paraview.simple as s\n"
        "r = s.VHMMedicalImageReader(FileName=sys.argv[1])\n"
        "s.UpdatePipeline(proxy=r)\n"
        "print('vhm-reader-points:', r.GetDataInformation().GetNumberOfPoints())\n"
    )
    cases = {tmp_path / "missing.nii.gz": "missing.nii.gz: no such file or folder",
             garbage: "garbage.nii.gz: Unable to determine ImageIO reader for"}  # fmt: skip
    for path, cause in cases.items():
        for ranks in (1, 2):
            cmd, env = mpi_command(["pvbatch", str(script), str(path)], ranks, paraview_env)
            done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
            log = done.stdout + done.stderr
            assert done.returncode == 0, log
            lines = [ln for ln in log.splitlines() if "VHM Medical Image Reader" in ln]
            assert len(lines) == 1 and f"VHM Medical Image Reader: {path.parent}" in lines[0]
            assert cause in lines[0], log
            assert "Traceback" not in log and "ERR|" not in log, log
            assert "vhm-reader-points: 0" in log
