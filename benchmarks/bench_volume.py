"""Volumes at real size: forward warp and resampling of the CT head and the 256^3 embryo.

For each volume: an automatic cage from a threshold (``vhm_viz.auto_cage(...,
threshold=...)``), 24 automatic anchors and a bend (one end held, the other turned by
35 degrees about the middle), solved once. Then, with the compiled code cached:

* forward warp and resample wall times (median and min-max of ``--repeats``), each with
  the lattice built from scratch (the lattice alone is reported too, with its exact map
  evaluations);
* the peak resident memory of each, measured in a fresh process that reads the volume,
  loads the solved map and runs the operation once: its ``VmHWM`` (the high-water mark of
  its own address space; ``ru_maxrss`` would also count the benchmark process it was
  forked from, which holds 2 GB by then);
* the largest position error of warped voxels against the exact map (random inside
  voxels and voxels within two voxels of the cage), and the largest pre-image error of
  at least 20,000 random output voxels against Newton's method on the exact map, in
  voxels (pre-images in folds, where the map is not invertible, are counted apart);
* SimpleITK's ``Resample`` of the same volume (trilinear, 2 threads) with a
  ``DisplacementFieldTransform`` of the same size, made from the engine's own pre-images
  on the input grid (so both produce the same image): the anchor of a tool that is given
  the deformation instead of computing it.

Timings on a shared machine are noisy: the load average seen is printed with the table.

Run: ``python benchmarks/bench_volume.py [--repeats 3] [--only head|embryo]``
(SimpleITK is the ``bench`` extra: ``pip install vhm_viz[bench]``). ``--figure PNG``
renders the embryo and its resampled bend side by side, off screen (the README's picture).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import data, print_table, simpleitk_resample, summary, timed

VOLUMES = {
    "head": ("CT head", ("volumes", "headsq_64x64x93.vti"), "otsu"),
    "embryo": ("embryo", ("volumes", "embryo.slc"), "otsu"),
}
SAMPLES = 20_000
BEND_DEGREES = 35.0


# ----------------------------------------------------------------------------- set-up
def bend_deformer(img, cage, threshold):
    """24 automatic anchors; hold one end of the anchors' main axis, turn the other."""
    import vhm_viz
    from vhm_viz.core.deformer import Deformer

    anchors = vhm_viz.auto_anchors(img, cage, 24, threshold=threshold)
    # bend the largest part: an automatic cage can have several shells (the embryo's has
    # a 14-vertex one around a separate blob), and an end on a small shell would only
    # move that shell rigidly, leaving the map the identity elsewhere
    main = _main_shell_anchors(cage, anchors)
    centre = main.mean(0)
    _, _, vt = np.linalg.svd(main - centre)
    t = (main - centre) @ vt[0]
    lo, hi = main[np.argmin(t)], main[np.argmax(t)]
    axis = np.cross(vt[0], vt[1])
    a = np.radians(BEND_DEGREES)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turn = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k
    dfm = Deformer(cage, anchors)
    dfm.set_constraints(
        positions=np.array([lo, hi]),
        targets=np.array([lo, lo + turn @ (hi - lo)]),
        jacobian_points=np.array([lo, hi]),
        jacobians=np.array([np.eye(3), turn]),
    )
    report = dfm.solve()
    return dfm, report


def _main_shell_anchors(cage, anchors):
    """The anchors inside the outward shell of the cage with the most vertices."""
    from vhm_viz.core.basis import domain_columns, inside_cage, winding_number

    n = len(cage.vertices)
    main = max(domain_columns(cage.vertices, cage.faces), key=lambda cols: (cols < n).sum())
    shell = np.asarray(cage.faces)[main[main >= n] - n]
    return anchors[inside_cage(winding_number(anchors, cage.vertices, shell))]


def prepare(key, cache: Path):
    """Volume, solved map (cached on disk for the memory runs), cage seconds, solve report."""
    from vhm_viz import Cage, HarmonicMap, auto_cage
    from vhm_viz.io import read_dataset

    name, parts, threshold = VOLUMES[key]
    img = read_dataset(data(*parts))
    path = cache / f"{key}.npz"
    if path.exists():
        saved = np.load(path)
        cage = Cage(saved["vertices"], saved["faces"])
        return img, HarmonicMap(cage, saved["z"]), float(saved["cage_seconds"]), None
    t0 = time.perf_counter()
    cage = auto_cage(img, threshold=threshold)
    cage_seconds = time.perf_counter() - t0
    dfm, report = bend_deformer(img, cage, threshold)
    hm = dfm.harmonic_map
    np.savez(path, vertices=cage.vertices, faces=cage.faces, z=hm.coefficients,
             cage_seconds=cage_seconds)  # fmt: skip
    return img, hm, cage_seconds, report


def geometry_of(img):
    from vhm_viz.core.image import ImageGeometry

    return ImageGeometry(img.origin, img.spacing, img.dimensions, img.direction_matrix)


def engine(hm, img):
    from vhm_viz.core.volume import VolumeDeformation

    return VolumeDeformation(hm, geometry_of(img), outside="passthrough")


# ------------------------------------------------------------------------- peak memory
CHILD = """
import resource, sys, numpy as np
sys.path.insert(0, {bench!r})
from bench_volume import prepare, engine
from pathlib import Path
img, hm, _, _ = prepare({key!r}, Path({cache!r}))
vol = engine(hm, img)
if {op!r} == "warp":
    vol.warp()
else:
    vol.resample({{img.active_scalars_name: np.asarray(img.active_scalars)}})
try:  # the high-water mark of this process's own memory (not inherited across exec)
    with open("/proc/self/status") as fh:
        hwm = [line for line in fh if line.startswith("VmHWM:")][0]
    print(int(hwm.split()[1]) * 1024)
except (OSError, IndexError):
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
"""


def peak_rss(key, op, cache: Path) -> int:
    """Peak resident bytes of a fresh process reading the volume and running ``op``."""
    code = CHILD.format(bench=os.path.dirname(os.path.abspath(__file__)), key=key,
                        cache=str(cache), op=op)  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return int(out.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------- accuracy
def position_errors(vol, hm, rng):
    """Largest warp error (voxels) at random inside voxels and next to the cage."""
    from scipy.ndimage import binary_erosion

    geo = vol.geometry
    nx, ny, nz = geo.dimensions
    inside = vol.lattice.inside((0, nx - 1, 0, ny - 1, 0, nz - 1))
    band = inside & ~binary_erosion(inside, iterations=2, border_value=1)
    warped = vol.warp()
    result = {}
    for label, mask in (("random", inside), ("near cage", band)):
        ijk = np.argwhere(mask)[:, ::-1]
        ijk = ijk[rng.choice(len(ijk), min(SAMPLES, len(ijk)), replace=False)]
        got = warped[ijk[:, 0] + nx * (ijk[:, 1] + ny * ijk[:, 2])]
        exact = hm.map(geo.points(ijk))
        err = np.linalg.norm((got - exact) @ geo.world_to_index.T, axis=1)
        result[label] = (float(err.max()), len(ijk))
    return result


def preimage_errors(vol, hm, out_geo, rng):
    """Largest pre-image error (voxels) of random output voxels vs Newton on the exact map."""
    from vhm_viz.core.volume import exact_preimages

    geo = vol.geometry
    nx, ny, nz = out_geo.dimensions
    tried = rng.integers(0, [nx, ny, nz], (20 * SAMPLES, 3))
    u, kind, fold = vol.preimages(out_geo, tried)
    pick = np.nonzero(kind == 1)[0]
    pick = pick[rng.choice(len(pick), min(SAMPLES, len(pick)), replace=False)]
    y = out_geo.points(tried[pick].astype(float))
    x, ok = exact_preimages(hm, y, geo.points(u[pick]), tolerance=1e-9 * geo.spacing.min())
    err = np.linalg.norm(geo.continuous_index(x) - u[pick], axis=1)
    folded = fold[pick].astype(bool)
    plain = err[ok & ~folded]
    return {
        "samples": len(pick),
        "max": float(plain.max()),
        "p999": float(np.percentile(plain, 99.9)),
        "folds": int(folded.sum()),
        "max_in_folds": float(err[ok & folded].max()) if (ok & folded).any() else 0.0,
        "not_converged": int((~ok).sum()),
    }


# ---------------------------------------------------------------------------- SimpleITK
def simpleitk_resample_check(img, vol, repeats):
    """SimpleITK Resample with a displacement field of the volume's size (the engine's own
    pull-back field on the input grid, ``VolumeDeformation.displacement_field``),
    trilinear, 2 threads; and its largest difference from the engine's resampling onto the
    same grid."""
    try:
        import SimpleITK as sitk
    except ImportError:
        return None
    from vhm_viz.io.itk_images import sitk_from_image

    geo = vol.geometry
    pulled = vol.displacement_field(geo)
    name = img.active_scalars_name
    values = np.asarray(img.active_scalars)
    field = sitk_from_image(img, np.asarray(pulled.vectors, dtype=np.float64))
    times, result = simpleitk_resample(sitk_from_image(img, values), field, repeats, 2)
    ours = vol.resample({name: values}, geo).arrays[name]
    theirs = sitk.GetArrayFromImage(result).ravel()
    inside = pulled.valid.astype(bool)
    diff = np.abs(theirs[inside].astype(np.float64) - ours[inside].astype(np.float64))
    return times, float(diff.max()), int(inside.sum())


# ------------------------------------------------------------------------------ figure
def figure(path, cache: Path, key="embryo"):
    """The volume's three middle planes and the same world planes of its resampled bend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    img, hm, _, _ = prepare(key, cache)
    name = img.active_scalars_name
    vol = engine(hm, img)
    geo = vol.geometry
    res = vol.resample({name: np.asarray(img.active_scalars)})
    out = res.geometry
    before = np.asarray(img.active_scalars).reshape(geo.dimensions[::-1])
    after = res.arrays[name].reshape(out.dimensions[::-1])
    shift = np.rint(geo.continuous_index(out.origin[None])[0]).astype(int)  # whole voxels
    lo = np.minimum(0, shift)
    hi = np.maximum(np.asarray(geo.dimensions), shift + np.asarray(out.dimensions))
    fig, axes = plt.subplots(2, 3, figsize=(10.5, 7.2))
    labels = "xyz"
    for a in range(3):
        u, v = [b for b in range(3) if b != a]
        mid = geo.dimensions[a] // 2
        for row, (values, start, title) in enumerate(
            ((before, np.zeros(3, int), "input"), (after, shift, "resampled bend"))
        ):
            # values are (z, y, x): the plane keeps rows along v, columns along u (u < v)
            plane = np.take(values, mid - start[a], axis=2 - a)
            ext = (start[u], start[u] + plane.shape[1], start[v], start[v] + plane.shape[0])
            ax = axes[row, a]
            ax.imshow(plane, cmap="gray", origin="lower", extent=ext, vmin=0, vmax=160)
            ax.set_xlim(lo[u], hi[u])
            ax.set_ylim(lo[v], hi[v])
            ax.set_title(f"{title}, {labels[a]} = {mid} (voxels)", fontsize=10)
            ax.set_xlabel(labels[u])
            ax.set_ylabel(labels[v])
    fig.suptitle(
        f"{img.dimensions[0]}x{img.dimensions[1]}x{img.dimensions[2]} embryo bent by "
        f"{BEND_DEGREES:.0f} degrees: resampled onto "
        f"{'x'.join(str(d) for d in out.dimensions)} voxels, tolerance 0.05 voxel",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)


# --------------------------------------------------------------------------------- main
def run_volume(key, repeats, cache: Path):
    name = VOLUMES[key][0]
    img, hm, cage_seconds, report = prepare(key, cache)
    values = {img.active_scalars_name: np.asarray(img.active_scalars)}
    # warm the compiled code (cached on disk after the first run)
    engine(hm, img).resample(values)
    builds, warps, resamples = [], [], []

    def warp():
        t0 = time.perf_counter()
        vol = engine(hm, img)
        vol.build()
        builds.append(time.perf_counter() - t0)
        vol.warp()

    def resample():
        engine(hm, img).resample(values)

    warps = timed(warp, repeats)
    resamples = timed(resample, repeats)
    vol = engine(hm, img)
    res = vol.resample(values)
    stats = vol.lattice.stats
    rng = np.random.default_rng(0)
    pos = position_errors(vol, hm, rng)
    pre = preimage_errors(vol, hm, res.geometry, rng)
    itk = simpleitk_resample_check(img, vol, repeats)
    rss_warp = peak_rss(key, "warp", cache)
    rss_resample = peak_rss(key, "resample", cache)
    return {
        "name": name,
        "voxels": img.n_points,
        "dims": "x".join(str(d) for d in img.dimensions),
        "faces": len(hm.cage.faces),
        "cage_seconds": cage_seconds,
        "solve": None if report is None else report.iterations,
        "warp": warps,
        "resample": resamples,
        "build": builds,
        "evaluations": stats["evaluations"],
        "leaves": stats["leaves_per_size"],
        "lattice_mb": vol.lattice.nbytes / 1e6,
        "output": "x".join(str(d) for d in res.geometry.dimensions),
        "counts": res.counts,
        "rss_warp": rss_warp,
        "rss_resample": rss_resample,
        "position": pos,
        "preimage": pre,
        "itk": itk,
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--only", choices=sorted(VOLUMES), default=None)
    parser.add_argument("--cache", default=None, help="folder for the solved maps")
    parser.add_argument("--json", default=None, help="also write the results here")
    parser.add_argument("--figure", default=None, help="only render the picture to this PNG")
    args = parser.parse_args()
    cache = Path(args.cache or tempfile.mkdtemp(prefix="bench_volume_"))
    cache.mkdir(parents=True, exist_ok=True)
    if args.figure:
        figure(args.figure, cache)
        return
    keys = [args.only] if args.only else list(VOLUMES)
    load0 = os.getloadavg()
    results = [run_volume(k, args.repeats, cache) for k in keys]
    load1 = os.getloadavg()
    rows = []
    for r in results:
        gb = lambda b: f"{b / 2**30:.2f} GB"  # noqa: E731
        itk = r["itk"]
        rows.append([
            f"{r['name']} {r['dims']}",
            f"{r['faces']}",
            summary(r["warp"]),
            summary(r["resample"]),
            f"{summary(r['build'])}, {r['evaluations']:,} evaluations",
            f"{gb(r['rss_warp'])} / {gb(r['rss_resample'])}",
            f"{r['position']['random'][0]:.4f} / {r['position']['near cage'][0]:.4f}",
            f"{r['preimage']['max']:.4f} ({r['preimage']['samples']:,})",
            "-" if itk is None else summary(itk[0]),
        ])  # fmt: skip
    print_table(
        [
            "volume",
            "cage faces",
            "forward warp",
            "resample",
            "lattice (in both)",
            "peak RSS warp / resample",
            "position error random / near cage (voxels)",
            "pre-image error (samples)",
            "SimpleITK Resample",
        ],
        rows,
    )
    print()
    for r in results:
        pre = r["preimage"]
        print(
            f"{r['name']}: cage {r['cage_seconds']:.1f} s; leaves per size {r['leaves']}; "
            f"lattice {r['lattice_mb']:.0f} MB; output grid {r['output']}, {r['counts']}; "
            f"pre-image p99.9 {pre['p999']:.4f}, {pre['folds']} samples in folds (max "
            f"{pre['max_in_folds']:.3f}), {pre['not_converged']} exact Newton not converged"
            + ("" if r["itk"] is None else
               f"; SimpleITK vs engine on the input grid: max |difference| {r['itk'][1]:.3g} "
               f"over {r['itk'][2]:,} voxels")
        )  # fmt: skip
    print(f"load average (1 min) {load0[0]:.2f} before, {load1[0]:.2f} after; "
          f"{os.cpu_count()} CPUs; peak RSS: VmHWM of a fresh process")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))


if __name__ == "__main__":
    main()
