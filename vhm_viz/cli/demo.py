"""``vhm-viz demo``: the bundled bar bent into a U, end to end, on generated data.

Runs the paper's bar scenario ``"bend-u"`` (:func:`vhm_viz.examples.bar`): solves the
variational harmonic map, then deforms through the VTK filters

* the bar's surface (``vtkPolyData``, with det/cond/displacement arrays),
* a tetrahedral version of the bar (:func:`vhm_viz.examples.bar_tets`: the same mesh
  on every run and machine, which a mesher such as fTetWild does not promise),
* a voxelised bar volume, as a warped structured grid and resampled back onto a regular
  grid (``.vti``, ready for volume rendering),

and writes the figures (the paper's Figure 4 slices, Figure 12 histogram, energy plot, a
3D view of the rest and the bent bar), the scene file and a metrics summary into the
output directory (a relative one is taken from the current folder).

PyVista and the VTK filters are imported when the demo runs, so that ``vhm-viz --help``
stays quick.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from vhm_viz import plotting
from vhm_viz.atomic import atomic_directory
from vhm_viz.cli._util import (
    CLIError,
    Progress,
    add_quiet_argument,
    quiet_vtk,
    run_filter,
)
from vhm_viz.core.metrics import jacobian_measures, rigidity_distortion, volume_change
from vhm_viz.examples import bar, bar_tets
from vhm_viz.io import json_text, write_dataset, write_text
from vhm_viz.scene import Scene

#: The libraries ``demo`` imports when it runs (not for its help).
RUN_IMPORTS = ("pyvista", "vhm_viz.filters")

#: Grid cells per unit length of the demo's tet bar (:func:`vhm_viz.examples.bar_tets`).
TET_RESOLUTION = 5

#: What ``--timings`` reports, besides "other".
TIMING_STAGES = "demo"

HELP = "run the bundled bar demo end to end (surface, tets, volume, figures)"

DESCRIPTION = (
    "Bend the bundled bar into a U (the paper's Figure 4 scenario) and write "
    "the deformed surface, a deformed tet mesh, a deformed voxel volume (warped and "
    "resampled), the figures, the scene and the metrics into DIR."
)


def add_arguments(p) -> None:
    """The ``demo`` subcommand's arguments."""
    p.add_argument(
        "-o",
        "--output",
        default="vhm_viz_demo",
        metavar="DIR",
        help="output directory, relative to the current folder (default: vhm_viz_demo)",
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=39,
        metavar="N",
        help="bar surface grid cells per unit length (the bar is 1 x 1 x 5) (default: 39, "
        "33,464 vertices)",
    )
    p.add_argument(
        "--voxel",
        type=float,
        default=0.08,
        metavar="SIZE",
        help="voxel size of the bar volume, in the bar's units (it is 1 wide) (default: 0.08)",
    )
    p.add_argument("--no-tets", action="store_true", help="skip the tetrahedral mesh")
    add_quiet_argument(p)


def run(args: argparse.Namespace) -> int:
    """Run the demo; returns the exit status."""
    quiet_vtk()
    with args.timer.stage("demo"):
        for line in demo(args):
            print(line)
    return 0


def bar_volume(voxel: float = 0.08):
    """A voxelised bar: density 1000 inside the bar with bands every 0.5 along z.

    The grid covers ``[-0.6, 0.6]^2 x [-0.1, 5.1]`` (inside the bar's cage); values fall
    off linearly over one voxel at the bar's sides, so resampling stays smooth.

    Returns
    -------
    pyvista.ImageData
        With point array ``density`` (float32).
    """
    import pyvista as pv

    lo = np.array([-0.6, -0.6, -0.1])
    hi = np.array([0.6, 0.6, 5.1])
    dims = np.floor((hi - lo) / voxel + 1e-9).astype(int) + 1
    img = pv.ImageData(dimensions=dims, spacing=(voxel,) * 3, origin=lo)
    p = np.asarray(img.points)
    # distance inside the bar (positive inside), clipped to one voxel
    d = np.minimum.reduce([0.5 - np.abs(p[:, 0]), 0.5 - np.abs(p[:, 1]), p[:, 2], 5.0 - p[:, 2]])
    occupancy = np.clip(0.5 + d / voxel, 0.0, 1.0)
    bands = 0.75 + 0.25 * np.cos(2 * np.pi * p[:, 2] / 0.5)
    img.point_data["density"] = (1000.0 * occupancy * bands).astype(np.float32)
    return img


def demo(args: argparse.Namespace):
    """Run the demo, yielding the lines to print."""
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise CLIError(f"output {out} exists and is not a directory")
    t_start = time.perf_counter()
    written: list[tuple[str, Path]] = []
    # every file appears at the end, as one set: an error or interrupt part-way leaves
    # the folder's previous files as they were
    with atomic_directory(out, last="metrics.json"):
        metrics, lines = _make_files(args, out, written)

    seconds = time.perf_counter() - t_start
    yield from lines
    yield f"wrote {len(written)} files to {out.resolve()} in {seconds:.1f} s:"
    for what, path in written:
        yield f"  {path.name:<34} {what}"
    yield (
        "open them in ParaView, or try: vhm-viz deform "
        f"{out / 'bar_rest.vtp'} --scene {out / 'scene.json'} -o bent.vtp"
    )


def _make_files(args: argparse.Namespace, out: Path, written: list):
    """Solve the demo's scene and write its files into ``out``; returns the metrics and lines.

    ``written`` gets ``(what, path)`` for each file.
    """
    import pyvista as pv

    from vhm_viz.filters import HarmonicDeformationFilter, HarmonicResampleFilter, update

    quiet = args.quiet

    def save(mesh, name, what):
        path = out / name
        write_dataset(path, mesh)
        written.append((what, path))

    # 1. the scenario and its solve ------------------------------------------------------
    scenario = bar("bend-u", resolution=args.resolution)
    dfm = scenario.deformer
    scene = Scene.from_deformer(dfm)
    bar_progress = Progress("solving", enabled=not quiet)
    reports = scene.solve(dfm, progress=bar_progress)
    bar_progress.finish()
    scene.save(out / "scene.json")
    written.append(("scene (cage, anchors, constraints)", out / "scene.json"))

    # 2. the surface -----------------------------------------------------------------------
    rest = scenario.surface
    save(rest, "bar_rest.vtp", "rest surface")
    surface_filter = HarmonicDeformationFilter()
    surface_filter.SetComputeDisplacement(True)
    surface_filter.SetComputeJacobianDeterminant(True)
    surface_filter.SetComputeConditionNumber(True)
    bent = run_filter(surface_filter, rest, dfm, "surface", quiet=quiet)
    save(bent, "bar_bent.vtp", "deformed surface")
    tris = scenario.triangles
    e_rigid = rigidity_distortion(scenario.points, bent.points, tris)
    e_volume = volume_change(scenario.points, bent.points, tris)

    # 3. a tetrahedral bar -----------------------------------------------------------------
    tet_line = None
    if not args.no_tets:
        tet_points, tet_ids = bar_tets(TET_RESOLUTION)
        tets = pv.UnstructuredGrid({pv.CellType.TETRA: tet_ids}, tet_points)
        save(tets, "bar_tets_rest.vtu", "rest tet mesh")
        tet_filter = HarmonicDeformationFilter()
        tet_filter.SetInputData(tets)
        tet_filter.SetDeformer(dfm)
        tet_filter.SetComputeJacobianDeterminant(True)
        tet_filter.SetComputeCellQuality(True)
        tet_bent = pv.wrap(update(tet_filter))
        save(tet_bent, "bar_tets_bent.vtu", "deformed tet mesh (with cell quality arrays)")
        v0, v1 = tets.volume, tet_bent.volume
        tet_line = (
            f"tets: {tets.n_cells} tetrahedra, volume change {abs(v1 - v0) / v0:.4f}, "
            f"{tet_filter.cell_summary['inverted']} inverted"
        )

    # 4. a voxelised bar ---------------------------------------------------------------------
    vol = bar_volume(args.voxel)
    save(vol, "bar_volume_rest.vti", "rest volume")
    warp = HarmonicDeformationFilter()
    warp.SetInputData(vol)
    warp.SetDeformer(dfm)
    save(pv.wrap(update(warp)), "bar_volume_bent.vts", "deformed volume (warped grid)")
    resampled = run_filter(HarmonicResampleFilter(), vol, dfm, "resample", quiet=quiet)
    save(resampled, "bar_volume_bent.vti", "deformed volume (resampled, .vti)")
    mass0 = float(np.asarray(vol.point_data["density"], dtype=np.float64).sum())
    mass1 = float(np.asarray(resampled.point_data["density"], dtype=np.float64).sum())

    # 5. figures and metrics ---------------------------------------------------------------
    hm = dfm.harmonic_map
    slice_ = plotting.jacobian_slice(rest, hm)
    pl = plotting.figure4(
        slice_, deformed_surface=bent, filename=out / "figure4_slices.png", title="bend-u"
    )
    pl.close()
    written.append(("Figure 4: det J / cond J slices", out / "figure4_slices.png"))
    cond = np.asarray(bent.point_data["condition_number"])
    plotting.figure12(
        {"surface": cond, "slice": slice_.point_data["condition_number"]},
        filename=out / "figure12_condition_histogram.png",
    )
    written.append(("Figure 12: condition numbers", out / "figure12_condition_histogram.png"))
    plotting.energy_plot(reports, filename=out / "energy.png")
    written.append(("energy vs iteration", out / "energy.png"))
    pl = plotting.deformation_view(
        rest, bent, cage=dfm.cage, filename=out / "bar_bent.png", title="bar bent into a U"
    )
    pl.close()
    written.append(("3D view: rest (grey) and bent bar by det J", out / "bar_bent.png"))

    jm = jacobian_measures(hm.jacobian(slice_.point_data["rest_points"]))
    metrics = {
        "scenario": "bar bend-u",
        "surface_points": int(rest.n_points),
        "iterations": int(sum(r.iterations for r in reports)),
        "converged": bool(reports[-1].converged),
        "energy": float(reports[-1].final_energy),
        "E_rigid": float(e_rigid),
        "E_volume": float(e_volume),
        "slice_det_min": float(jm["determinant"].min()),
        "slice_det_max": float(jm["determinant"].max()),
        "slice_cond_max": float(jm["condition_number"].max()),
        "foldovers": int(jm["foldovers"]),
        "volume_voxel_sum_ratio": mass1
        * float(np.prod(resampled.spacing))
        / (mass0 * float(np.prod(vol.spacing))),
    }
    write_text(out / "metrics.json", json_text(metrics))
    written.append(("metrics", out / "metrics.json"))
    lines = [
        f"bar bend-u: {rest.n_points} surface points, {metrics['iterations']} iterations, "
        f"E_rigid {e_rigid:.3f}, E_volume {e_volume:.3f}, foldovers {metrics['foldovers']}"
    ]
    if tet_line:
        lines.append(tet_line)
    lines.append(
        f"volume: {vol.n_points} voxels resampled onto {resampled.n_points} "
        f"(voxel-sum ratio {metrics['volume_voxel_sum_ratio']:.3f})"
    )
    return metrics, lines
