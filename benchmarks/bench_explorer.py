"""Frame time of the Qt explorer while dragging one constraint (solve + deform + render).

For the 43k and 173k Armadillo (``cage_500f.obj``, 50 anchors), the explorer window is
opened under a real X display (a private Xvfb is started when ``DISPLAY`` is unset; VTK
renders with Mesa's software OpenGL there), a few position constraints hold the feet and
one on the head is dragged along a circle through the sphere widget's code path (its
``InteractionEvent`` callback, then the interactor's render, as a mouse move). Each frame is a
warm-started solve (the explorer's drag settings: at most 200 iterations, tolerance 1e-6),
the deformation in place and a synchronous render of a 1024 x 768 window.

Level of detail: above ``ExplorerController.lod_points`` points the explorer deforms and
renders a decimated proxy while dragging (``--proxy-triangles``; ``--no-lod`` drags the
full mesh). The "drag mesh" column says what was rendered; "release" is the frame at the
end of the drag (solve to convergence, full deformation and render of the full mesh) and
the time until the deferred shape metrics (E_rigid, E_volume) are shown too; "proxy" the
time to decimate and bind the proxy (part of "bind").

Volumes (``--volume``, default the 256^3 embryo): an automatic cage (Otsu threshold) and
anchors, one end held and the other dragged; each frame deforms the three orthogonal
slices at drag resolution (``app.volume.DRAG_SAMPLES`` per side) with the solve, and
renders. The release deforms the full-resolution slices (every voxel of the plane).

Prints Markdown tables of per-frame medians with the min-max range, and frames/s.

Run: ``python benchmarks/bench_explorer.py [--frames 60] [--sizes 43k 173k] [--no-lod]
[--volume embryo|head|none]``
"""

from __future__ import annotations

import argparse
import atexit
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import data, print_table

MODELS = {"43k": "armadillo_43k.obj", "173k": "armadillo_173k.ply"}


def _stop(proc) -> None:
    proc.terminate()
    proc.wait(timeout=5)


def ensure_display():
    """Use $DISPLAY, or start a private Xvfb (returned, to be terminated)."""
    if os.environ.get("DISPLAY"):
        os.environ.setdefault("QT_QPA_PLATFORM", "xcb")
        return None
    exe = shutil.which("Xvfb")
    if exe is None:
        raise SystemExit("no DISPLAY and no Xvfb (apt-get install xvfb)")
    for num in range(150, 170):
        if Path(f"/tmp/.X{num}-lock").exists():
            continue
        proc = subprocess.Popen(
            [exe, f":{num}", "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for _ in range(100):
            if Path(f"/tmp/.X11-unix/X{num}").exists():
                os.environ["DISPLAY"] = f":{num}"
                os.environ["QT_QPA_PLATFORM"] = "xcb"
                # Stop the server at exit, after Qt has closed its connection: atexit runs
                # last-registered first, and PySide registers its clean-up when the
                # QApplication is made, later than this. Terminating it from main() made
                # Qt report a broken X connection on the way out.
                atexit.register(_stop, proc)
                return proc
            time.sleep(0.05)
        proc.kill()
    raise SystemExit("could not start Xvfb")


def pct(values, q):
    return float(np.percentile(np.asarray(values), q))


def fmt(values) -> str:
    ms = 1e3 * np.asarray(values)
    return f"{statistics.median(ms):.1f} ({ms.min():.1f}-{ms.max():.1f})"


def fps(totals) -> str:
    """Frames per second: median (min-max) over the frames."""
    f = 1.0 / np.asarray(totals)
    return f"{statistics.median(f):.1f} ({f.min():.1f}-{f.max():.1f})"


VOLUMES = {"embryo": "embryo.slc", "head": "headsq_64x64x93.vti"}


def run_volume(win, name: str, frames: int, n_anchors: int) -> dict:
    """Drag one end of a volume: the slices follow (drag resolution), release: full."""
    from PySide6.QtWidgets import QApplication

    from vhm_viz.app.controller import ExplorerController

    ctrl = ExplorerController()
    t0 = time.perf_counter()
    ctrl.load_file(data("volumes", VOLUMES[name]))
    ctrl.threshold = "otsu"
    ctrl.set_cage(ctrl.auto_cage(500))
    ctrl.set_anchors(ctrl.auto_anchors(n_anchors))
    a = np.asarray(ctrl.anchors)
    c = a.mean(axis=0)
    _, _, vt = np.linalg.svd(a - c, full_matrices=False)
    t = (a - c) @ vt[0]
    lo, hi = a[np.argmin(t)], a[np.argmax(t)]
    ctrl.add_position_constraint(lo, lo)
    k = ctrl.add_position_constraint(hi, hi)
    t_setup = time.perf_counter() - t0
    ctrl.prepare()
    ctrl.settle(init="identity")
    ctrl.deform()
    win.ctrl.adopt(ctrl)
    win.volume_display.reset()
    t0 = time.perf_counter()
    win.rebuild_scene(reset_camera=True)
    t_slices = time.perf_counter() - t0
    win.plotter.render()
    QApplication.processEvents()
    diag = float(np.linalg.norm(np.ptp(a, axis=0)))
    u = np.cross(vt[0], vt[1])
    start = ctrl.positions[k].target.copy()
    timings = []
    for f in range(frames + 5):
        ang = 2 * np.pi * f / frames
        goal = start + 0.1 * diag * (np.sin(ang) * u + (np.cos(ang) - 1) * vt[1])
        win.shape_view.handles[k].SetCenter(*goal)
        win.drag.handle_moved(k, goal)
        win.plotter.iren.interactor.Render()
        QApplication.processEvents()
        if f >= 5:
            timings.append(win.drag.last_frame)
    t0 = time.perf_counter()
    win.drag.released()
    release = time.perf_counter() - t0
    if win.errors:
        raise SystemExit(f"explorer errors: {win.errors}")
    drag = win.volume_display.slices[2]["drag"].mesh
    full = win.volume_display.slices[2]["full"].mesh
    return {
        "name": name,
        "dims": "x".join(str(d) for d in ctrl.volume.dimensions),
        "setup": t_setup,
        "slices": t_slices,
        "drag": f"{drag.n_points:,} / {full.n_points:,}",
        "solve": [t.solve for t in timings],
        "update": [t.deform + t.analysis for t in timings],
        "render": [t.render for t in timings],
        "total": [t.total for t in timings],
        "release": release,
    }


def run_model(win, size: str, frames: int, n_anchors: int, lod: bool, triangles: int) -> dict:
    from vhm_viz.app.controller import ExplorerController

    ctrl = ExplorerController()
    ctrl.lod, ctrl.proxy_triangles = lod, triangles
    t0 = time.perf_counter()
    ctrl.load_file(data("armadillo", MODELS[size]))
    ctrl.load_cage(data("armadillo", "cage_500f.obj"))
    ctrl.set_anchors(ctrl.auto_anchors(n_anchors))
    p = ctrl.rest_points
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    axis = vt[0] if (p - c).dot(vt[0]).max() > -(p - c).dot(vt[0]).min() else -vt[0]
    t = (p - c) @ axis
    feet = np.argsort(t)[:3]  # three points at one end of the principal axis: held
    head = int(np.argmax(t))  # the other end: dragged
    for i in feet:
        ctrl.add_position_constraint(p[i], p[i])
    k = ctrl.add_position_constraint(p[head], p[head])
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    t_proxy = []
    ctrl.prepare(lambda f, msg: t_proxy.append(time.perf_counter()) if "proxy" in msg else None)
    t_bind = time.perf_counter() - t0
    t_proxy = time.perf_counter() - t_proxy[0] if t_proxy else 0.0
    ctrl.solve(init="identity")
    ctrl.deform()
    win.ctrl.__dict__.update(ctrl.__dict__)
    win.rebuild_scene(reset_camera=True)
    win.plotter.render()
    from PySide6.QtWidgets import QApplication

    QApplication.processEvents()
    diag = float(np.linalg.norm(p.max(0) - p.min(0)))
    start = ctrl.positions[k].target.copy()
    u = np.cross(axis, [1.0, 0, 0])
    if np.linalg.norm(u) < 0.1:
        u = np.cross(axis, [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    win.drag.frame_times.clear()
    timings = []
    for f in range(frames + 5):
        ang = 2 * np.pi * f / frames
        goal = start + 0.15 * diag * (np.cos(ang) - 1) * u + 0.15 * diag * np.sin(ang) * v
        # what vtkSphereWidget does on a mouse move: its InteractionEvent callback, then a
        # render (the callback leaves rendering to it: one render per frame)
        win.shape_view.handles[k].SetCenter(*goal)
        win.drag.handle_moved(k, goal)
        win.plotter.iren.interactor.Render()
        QApplication.processEvents()
        if f >= 5:  # warm-up frames excluded
            timings.append(win.drag.last_frame)
    drag_mesh = win.lod_label.text()
    release, settled = [], []
    for _ in range(3):
        win.drag.move_handle(k, goal)
        t0 = time.perf_counter()
        win.drag.released()
        release.append(win.drag.last_frame.total)
        QApplication.processEvents()  # the deferred shape metrics
        settled.append(time.perf_counter() - t0)
    if win.errors:
        raise SystemExit(f"explorer errors: {win.errors}")
    if win.shape_view.showing_proxy:
        raise SystemExit("the proxy is still shown after the release")
    return {
        "size": size,
        "points": ctrl.display.n_points,
        "anchors": len(ctrl.anchors),
        "load": t_load,
        "bind": t_bind,
        "proxy": t_proxy,
        "drag_mesh": drag_mesh.replace("drag ", ""),
        "release": release,
        "settled": settled,
        "solve": [t.solve for t in timings],
        "deform": [t.deform for t in timings],
        "render": [t.render + t.analysis for t in timings],
        "total": [t.total for t in timings],
        "iterations": [t.iterations for t in timings],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--sizes", nargs="+", default=list(MODELS), choices=list(MODELS))
    ap.add_argument("--anchors", type=int, default=50)
    ap.add_argument("--no-lod", action="store_true", help="drag the full mesh (no proxy)")
    ap.add_argument("--proxy-triangles", type=int, default=None)
    ap.add_argument("--volume", default="embryo", choices=[*VOLUMES, "none"])
    args = ap.parse_args()
    xvfb = ensure_display()
    try:
        from PySide6.QtWidgets import QApplication
        from threadpoolctl import threadpool_limits

        from vhm_viz.app.window import ExplorerWindow

        threadpool_limits(limits=1, user_api="blas")  # as the app does
        app = QApplication.instance() or QApplication(sys.argv[:1])
        win = ExplorerWindow(dialogs=False)
        win.resize(1024, 768)
        win.show()
        app.processEvents()
        import vtk

        info = win.plotter.ren_win.ReportCapabilities().splitlines()
        renderer = next((s.split(":", 1)[1].strip() for s in info if "OpenGL renderer" in s), "?")
        from vhm_viz.app.lod import PROXY_TRIANGLES

        triangles = args.proxy_triangles or PROXY_TRIANGLES
        rows = []
        for size in args.sizes:
            r = run_model(win, size, args.frames, args.anchors, not args.no_lod, triangles)
            rows.append(
                [
                    f"Armadillo {size} ({r['points']:,} pts)",
                    str(r["anchors"]),
                    f"{r['bind']:.1f} s ({r['proxy']:.1f} s)",
                    r["drag_mesh"],
                    fmt(r["solve"]),
                    fmt(r["deform"]),
                    fmt(r["render"]),
                    fmt(r["total"]),
                    fps(r["total"]),
                    f"{statistics.median(r['iterations']):.0f}",
                    f"{1e3 * statistics.median(r['release']):.0f} / "
                    f"{1e3 * statistics.median(r['settled']):.0f}",
                ]
            )
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        print(
            f"\nExplorer drag frame time ({args.frames} frames, window 1024x768, "
            f"renderer: {renderer}, VTK {vtk.vtkVersion.GetVTKVersion()}, "
            f"{os.cpu_count()} CPUs, load average {load:.1f} at the end; "
            f"level of detail {'off' if args.no_lod else f'on, proxy {triangles} triangles'}; "
            "ms: median (min-max))\n"
        )
        print_table(
            [
                "model",
                "anchors",
                "bind (proxy)",
                "drag mesh",
                "solve ms",
                "deform ms",
                "render ms",
                "frame ms",
                "fps",
                "iterations",
                "release ms (shown / metrics)",
            ],
            rows,
        )
        if args.volume != "none":
            r = run_volume(win, args.volume, args.frames, 24)
            print(
                f"\nVolume slices following a drag ({args.frames} frames; three slices, "
                "points per slice while dragging / at rest; ms: median (min-max))\n"
            )
            print_table(
                ["volume", "cage+anchors s", "slices bind s", "slice points", "solve ms",
                 "slices ms", "render ms", "frame ms", "fps", "release s"],
                [[f"{r['name']} {r['dims']}", f"{r['setup']:.1f}", f"{r['slices']:.2f}",
                  r["drag"], fmt(r["solve"]), fmt(r["update"]), fmt(r["render"]),
                  fmt(r["total"]), fps(r["total"]), f"{r['release']:.2f}"]],
            )  # fmt: skip
        win.close()
    except BaseException:
        if xvfb is not None:
            _stop(xvfb)
        raise


if __name__ == "__main__":
    main()
