"""CPU against GPU: the closed-form map with Jacobians, the volume warp and the resample.

The numeric core alone (no VTK), on synthetic data, since a machine with a GPU may have
neither VTK nor ``../shared``: the bar's box cage of
:func:`vhm_viz.examples.bar_cage` with 4 x 4 x 14 cells (258 vertices, 512 faces), bent
and swollen (a Green Coordinates map of the moved cage, so no solve is needed), and

* **map + J**: :func:`~vhm_viz.core.basis.evaluate_map` of ``--points`` random points
  inside the cage (default 172,966, the Armadillo's count), values and Jacobians, on each
  device (the GPU time includes the transfers both ways and the CPU's per-point kernel
  for the few points next to a cage edge);
* **warp**: :class:`~vhm_viz.core.volume.VolumeDeformation` of a ``--volume``^3 grid
  (default 256) inside the cage, a lattice without pre-images and the forward warp of
  every voxel, as the warp filter runs it; ``device="cuda"`` evaluates the lattice's
  exact points on the GPU, the rest runs on the CPU;
* **resample**: :meth:`~vhm_viz.core.volume.VolumeDeformation.resample` end to end
  (lattice with pre-images, pull-back, sampling; no file I/O), every run with a fresh
  engine, of the 256^3 embryo's box-cage bend scene (``bench_scaling.py``'s) given by
  ``--embryo NPZ``, else of the ``--volume``^3 grid in the bar's cage with synthetic
  values. ``device="cuda"`` also runs the pull-back's Newton solves on the GPU. The
  difference column gives the largest value difference relative to the value range, and
  how many voxels' masks differ. The NPZ (the embryo's grid, voxels and solved map) is
  written by ``--prepare-embryo NPZ`` on a machine with VTK and ``../shared``;
  ``benchmarks/gpu_check.sh`` uses ``benchmarks/out/embryo_scene.npz`` when it is there
  (carry it to the GPU machine).

Each row gives the median and the spread (min-max) of ``--repeats`` timed runs after one
untimed run (which compiles, or loads from the cache, every kernel; its time is the
"first" column), and the largest difference between the devices' results relative to the
largest CPU value. ``--out FILE`` writes the table there too. ``--quick`` takes tiny sizes
(for a dry run under numba's CUDA simulator, ``NUMBA_ENABLE_CUDASIM=1``).

    python benchmarks/bench_gpu.py                 # 173k points, 256^3, -r 5
    python benchmarks/bench_gpu.py --devices cpu   # the CPU rows only
    python benchmarks/bench_gpu.py --prepare-embryo benchmarks/out/embryo_scene.npz
    python benchmarks/bench_gpu.py --only resample --embryo benchmarks/out/embryo_scene.npz
    NUMBA_ENABLE_CUDASIM=1 python benchmarks/bench_gpu.py --quick
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
import time
from pathlib import Path

import numpy as np
from _common import print_table, summary, timed

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vhm_viz.core.basis import evaluate_map  # noqa: E402
from vhm_viz.core.cage import Cage  # noqa: E402
from vhm_viz.core.devices import require_device  # noqa: E402
from vhm_viz.core.errors import DeviceUnavailableError  # noqa: E402
from vhm_viz.core.harmonic_map import HarmonicMap  # noqa: E402
from vhm_viz.core.image import ImageGeometry  # noqa: E402
from vhm_viz.core.threads import use_threads  # noqa: E402
from vhm_viz.core.volume import VolumeDeformation  # noqa: E402
from vhm_viz.examples import bar_cage  # noqa: E402


def bent_map(cage) -> HarmonicMap:
    """The cage's Green Coordinates map after bending its long (z) axis and swelling it."""
    v = np.asarray(cage.vertices, dtype=np.float64)
    t = v.copy()
    s = (v[:, 2] - v[:, 2].min()) / np.ptp(v[:, 2])  # 0..1 along the bar
    angle = 0.8 * s  # the bar's end turned 0.8 rad about y
    radius = np.ptp(v[:, 2]) / 0.8
    t[:, 0] = v[:, 0] * np.cos(angle) + radius * (1.0 - np.cos(angle))
    t[:, 2] = v[:, 2].min() - v[:, 0] * np.sin(angle) + radius * np.sin(angle)
    t[:, 1] = v[:, 1] * (1.0 + 0.3 * np.sin(np.pi * s))
    return HarmonicMap.from_target_cage(cage, t)


def inside_box(cage, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the cage's bounding box shrunk by ``margin`` of its size."""
    lo, hi = cage.vertices.min(axis=0), cage.vertices.max(axis=0)
    pad = margin * (hi - lo)
    return lo + pad, hi - pad


def relative_difference(a, b) -> float:
    """``max |a - b| / max |b|``."""
    return float(np.abs(a - b).max() / np.abs(b).max())


def map_rows(hm, n_points: int, devices, repeats: int) -> list[list[str]]:
    """Rows of the map + Jacobians benchmark."""
    lo, hi = inside_box(hm.cage, 0.02)
    p = np.random.default_rng(1).uniform(lo, hi, (n_points, 3))
    V, F, z = hm.cage.vertices, hm.cage.faces, hm.coefficients
    rows, reference = [], None
    for device in devices:
        t0 = time.perf_counter()
        f, jac, _ = evaluate_map(p, V, F, z, order=1, device=device)
        first = time.perf_counter() - t0
        times = timed(lambda d=device: evaluate_map(p, V, F, z, order=1, device=d), repeats)
        result = np.concatenate([f.ravel(), jac.ravel()])
        reference = result if reference is None else reference
        diff = "-" if device == devices[0] else f"{relative_difference(result, reference):.1e}"
        rows.append([f"map + J, {n_points} points", device, f"{first:.3g} s", summary(times), diff])
    return rows


def warp_rows(hm, size: int, devices, repeats: int) -> list[list[str]]:
    """Rows of the volume warp benchmark."""
    lo, hi = inside_box(hm.cage, 0.02)
    geo = ImageGeometry(lo, (hi - lo) / (size - 1), (size, size, size))
    rows, reference = [], None
    for device in devices:
        t0 = time.perf_counter()
        vol = VolumeDeformation(hm, geo, pre_images=False, device=device)
        out = vol.warp()
        first = time.perf_counter() - t0
        evaluations = int(vol.lattice.stats["evaluations"])
        del vol
        times = timed(
            lambda d=device: VolumeDeformation(hm, geo, pre_images=False, device=d).warp(),
            repeats,
        )
        reference = out if reference is None else reference
        diff = "-" if device == devices[0] else f"{relative_difference(out, reference):.1e}"
        label = f"warp {size}^3 ({evaluations} exact points)"
        rows.append([label, device, f"{first:.3g} s", summary(times), diff])
        del out
    return rows


def prepare_embryo(path: Path) -> None:
    """Write the embryo's grid, voxels and solved box-cage bend map to ``path`` (NPZ)."""
    from _common import data
    from bench_scaling import solve

    from vhm_viz.io import read_dataset

    embryo = data("volumes", "embryo.slc")
    path.parent.mkdir(parents=True, exist_ok=True)
    solve(embryo, path.with_suffix(".map.npz"))
    saved = dict(np.load(path.with_suffix(".map.npz")))
    path.with_suffix(".map.npz").unlink()
    img = read_dataset(str(embryo))
    np.savez_compressed(
        path, **saved, origin=img.origin, spacing=img.spacing, dimensions=img.dimensions,
        direction=img.direction_matrix, values=np.asarray(img.active_scalars),
    )  # fmt: skip


def resample_case(hm, size: int, embryo: Path | None):
    """``(label, map, grid, values)`` of the resample rows: the embryo's, or synthetic."""
    if embryo is not None:
        z = np.load(embryo)
        emb = HarmonicMap(Cage(z["vertices"], z["faces"]), z["z"])
        geo = ImageGeometry(z["origin"], z["spacing"], z["dimensions"], z["direction"])
        dims = "x".join(str(int(d)) for d in geo.dimensions)
        return f"resample embryo {dims}, {len(z['faces'])} faces", emb, geo, z["values"]
    lo, hi = inside_box(hm.cage, 0.02)
    geo = ImageGeometry(lo, (hi - lo) / (size - 1), (size, size, size))
    x = geo.points(np.indices((size,) * 3)[::-1].reshape(3, -1).T.astype(np.float64))
    values = (np.sin(x @ np.array([3.0, 2.0, 1.0]) / np.ptp(x)) * 1000).astype(np.int16)
    return f"resample {size}^3 (synthetic)", hm, geo, values


def resample_rows(hm, size: int, embryo, devices, repeats: int) -> list[list[str]]:
    """Rows of the resample benchmark (end to end, a fresh engine per run)."""
    label, hm, geo, values = resample_case(hm, size, embryo)
    arrays = {"values": values}
    rows, reference = [], None
    for device in devices:
        t0 = time.perf_counter()
        res = VolumeDeformation(hm, geo, device=device).resample(arrays)
        first = time.perf_counter() - t0
        times = timed(lambda d=device: VolumeDeformation(hm, geo, device=d).resample(arrays),
                      repeats)  # fmt: skip
        out = res.arrays["values"].astype(np.float64)
        if reference is None:
            reference, diff = (out, res.valid), "-"
        else:
            span = max(float(np.ptp(reference[0])), 1e-300)
            masks = int((res.valid != reference[1]).sum())
            diff = f"{np.abs(out - reference[0]).max() / span:.1e}, {masks} masks"
        rows.append([label, device, f"{first:.3g} s", summary(times), diff])
        del res, out
    return rows


def main(argv=None) -> int:
    """Run the benchmark and print (and optionally write) its table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=172_966)
    parser.add_argument("--volume", type=int, default=256, metavar="SIZE")
    parser.add_argument("-r", "--repeats", type=int, default=5)
    parser.add_argument("--devices", nargs="+", default=["cpu", "cuda"], choices=["cpu", "cuda"])
    parser.add_argument("--only", choices=["map", "warp", "resample"], default=None)
    parser.add_argument("--embryo", type=Path, default=None, metavar="NPZ",
                        help="resample this scene (--prepare-embryo writes it)")
    parser.add_argument("--prepare-embryo", type=Path, default=None, metavar="NPZ",
                        help="write the embryo scene for --embryo, then stop")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (simulator dry run)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    if args.prepare_embryo is not None:
        prepare_embryo(args.prepare_embryo)
        print(f"wrote {args.prepare_embryo}")
        return 0
    if args.quick:
        args.points, args.volume, args.repeats = 32, 4, 1
    if "cuda" in args.devices:
        try:
            require_device("cuda")
        except DeviceUnavailableError as exc:
            raise SystemExit(f"bench_gpu: {exc} (or pass --devices cpu)") from None
    threads = use_threads(None)
    cage = bar_cage((4, 4, 14))
    hm = bent_map(cage)
    header = (
        f"cage {len(cage.vertices)} vertices, {len(cage.faces)} faces; {threads} CPU threads; "
        f"load {os.getloadavg()[0]:.2f}; GPU: {_gpu_name() if 'cuda' in args.devices else '-'}"
    )
    print(header, flush=True)
    rows = []
    if args.only in (None, "map"):
        rows += map_rows(hm, args.points, args.devices, args.repeats)
    if args.only in (None, "warp"):
        rows += warp_rows(hm, args.volume, args.devices, args.repeats)
    if args.only in (None, "resample"):
        embryo = None if args.quick else args.embryo
        rows += resample_rows(hm, args.volume, embryo, args.devices, args.repeats)
    headers = ["what", "device", "first", "median (min-max, n)", "max rel. diff"]
    table = io.StringIO()
    with contextlib.redirect_stdout(table):
        print_table(headers, rows)
    print(table.getvalue(), end="")
    if args.out is not None:
        args.out.write_text(f"{header}\n\n{table.getvalue()}")
    return 0


def _gpu_name() -> str:
    """The GPU numba-cuda sees (``simulator`` under ``NUMBA_ENABLE_CUDASIM=1``)."""
    from numba import cuda

    if os.environ.get("NUMBA_ENABLE_CUDASIM") == "1":
        return "numba CUDA simulator"
    name = cuda.get_current_device().name
    return name.decode() if isinstance(name, bytes) else str(name)


if __name__ == "__main__":
    raise SystemExit(main())
