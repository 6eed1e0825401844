"""Machine anchors: two fixed jobs of other tools that say how fast this machine is.

The goals of issue #34 were set on one machine; these two jobs, timed there, scale them to
the machine at hand (``ratio = this machine / the goals' machine``):

* ``vtk``: VTK's ``vtkDeformPointSet`` computing its mean-value weights of the 173k
  Armadillo (``armadillo_173k.ply``) in ``cage_500f.obj``: the cage is the control mesh,
  the Armadillo the input, and the first ``Update`` (with the control mesh still the cage
  itself, so the deformation is the identity) computes every point's weights;
* ``simpleitk``: SimpleITK's ``Resample`` of the 256³ embryo (trilinear, onto the
  embryo's own grid) through a ``DisplacementFieldTransform`` holding a given pull-back
  field of the volume's size (the box scene's, written by ``vhm-viz deform
  --write-field``).

Each run is a fresh process (``python machine_anchors.py vtk|simpleitk ...``) that reads
its inputs, then times the job alone; it prints one JSON line. :func:`time_anchors` runs
them ``repeats`` times from the benchmarks.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import data, simpleitk_resample  # noqa: E402

#: Seconds of each anchor on the machine where issue #34's goals were measured.
ISSUE_SECONDS = {"vtk": 15.1, "simpleitk": 0.82}

#: What each anchor times, for the tables.
LABELS = {
    "vtk": "vtkDeformPointSet weights, Armadillo 173k in cage_500f",
    "simpleitk": "SimpleITK Resample, embryo 256^3, given displacement field",
}


def vtk_weights_seconds(mesh: Path, cage: Path) -> dict:
    """Seconds of ``vtkDeformPointSet``'s first ``Update`` (its weights) of ``mesh`` in ``cage``."""
    from vtkmodules.vtkCommonCore import vtkSMPTools
    from vtkmodules.vtkFiltersGeneral import vtkDeformPointSet
    from vtkmodules.vtkIOGeometry import vtkOBJReader
    from vtkmodules.vtkIOPLY import vtkPLYReader

    points = vtkPLYReader()
    points.SetFileName(str(mesh))
    points.Update()
    control = vtkOBJReader()
    control.SetFileName(str(cage))
    control.Update()
    deform = vtkDeformPointSet()
    deform.SetInputData(points.GetOutput())
    deform.SetControlMeshData(control.GetOutput())
    deform.InitializeWeightsOn()
    t0, c0 = time.perf_counter(), time.process_time()
    deform.Update()
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "seconds": seconds,
        "cpu": cpu,
        "points": points.GetOutput().GetNumberOfPoints(),
        "cage_faces": control.GetOutput().GetNumberOfCells(),
        "threads": f"vtkSMPTools {vtkSMPTools.GetBackend()}, "
        f"{vtkSMPTools.GetEstimatedNumberOfThreads()} thread(s)",
    }


def simpleitk_seconds(volume: Path, field: Path) -> dict:
    """Seconds of SimpleITK's ``Resample`` of ``volume`` through the displacement ``field``."""
    import numpy as np
    import SimpleITK as sitk

    from vhm_viz.io import read_dataset
    from vhm_viz.io.itk_images import sitk_from_image

    img = read_dataset(str(volume))
    image = sitk_from_image(img, np.asarray(img.active_scalars))
    displacement = sitk.ReadImage(str(field), sitk.sitkVectorFloat64)
    threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    c0 = time.process_time()
    times, _ = simpleitk_resample(image, displacement, 1, threads)
    return {
        "seconds": times[0],
        "cpu": time.process_time() - c0,
        "voxels": int(img.n_points),
        "threads": f"{threads} thread(s)",
    }


def make_field(volume: Path, scene: Path, field: Path, env: dict) -> None:
    """Write ``scene``'s pull-back field on ``volume``'s own grid to ``field`` (``.mha``)."""
    resampled = field.with_name("anchor_resampled.vti")
    cmd = [sys.executable, "-m", "vhm_viz.cli", "deform", str(volume), "--scene", str(scene)]
    cmd += ["-o", str(resampled), "--reference", str(volume), "--write-field", str(field), "-q"]
    cmd += ["--allow-folds"]  # the anchor times a resample through the field, folds or not
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"making the anchor's displacement field failed: {done.stderr[-400:]}")
    resampled.unlink(missing_ok=True)


def time_anchors(which, repeats: int, scratch: Path, env: dict, scene_of) -> dict:
    """Median, spread and ratio of each anchor in ``which``, ``repeats`` fresh processes each.

    ``scene_of(path)`` gives the scene (a dict) whose pull-back field the SimpleITK anchor
    applies. Returns ``{name: {"times", "median", "runs", "ratio", "detail"}}``: wall
    seconds of each run, their median, each run's JSON, median / the issue machine's
    seconds, and the last run's JSON.
    """
    here = Path(__file__).resolve()
    jobs = {}
    if "vtk" in which:
        jobs["vtk"] = [str(data("armadillo", "armadillo_173k.ply")),
                       str(data("armadillo", "cage_500f.obj"))]  # fmt: skip
    if "simpleitk" in which:
        embryo = data("volumes", "embryo.slc")
        scene = scratch / "anchor_scene.json"
        scene.write_text(json.dumps(scene_of(embryo)))
        field = scratch / "anchor_field.mha"
        if not field.exists():
            make_field(embryo, scene, field, env)
        jobs["simpleitk"] = [str(embryo), str(field)]
    out = {}
    for name, paths in jobs.items():
        runs = []
        for _ in range(repeats):
            done = subprocess.run([sys.executable, str(here), name, *paths], env=env,
                                  capture_output=True, text=True)  # fmt: skip
            if done.returncode != 0:
                raise SystemExit(f"anchor {name} failed: {done.stderr.strip()[-400:]}")
            runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
        times = [r["seconds"] for r in runs]
        median = statistics.median(times)
        out[name] = {"times": times, "median": median, "runs": runs,
                     "ratio": median / ISSUE_SECONDS[name], "detail": runs[-1]}  # fmt: skip
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="time one machine anchor once (one JSON line)")
    ap.add_argument("anchor", choices=sorted(ISSUE_SECONDS))
    ap.add_argument("paths", nargs=2, type=Path, help="vtk: MESH CAGE; simpleitk: VOLUME FIELD")
    args = ap.parse_args(argv)
    job = vtk_weights_seconds if args.anchor == "vtk" else simpleitk_seconds
    print(json.dumps(job(*args.paths)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
