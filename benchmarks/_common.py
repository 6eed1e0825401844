"""Helpers shared by the benchmarks: data location, timing statistics, table printing."""

from __future__ import annotations

import statistics
import time
from pathlib import Path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def data(*parts: str) -> Path:
    """Path in ``../shared/data``; exits with a message when it is missing."""
    path = DATA.joinpath(*parts)
    if not path.exists():
        raise SystemExit(f"benchmark data not found: {path}")
    return path


def timed(fn, repeats: int) -> list[float]:
    """Wall times (s) of ``repeats`` calls of ``fn``."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def summary(times: list[float]) -> str:
    """``median (min-max, n=k)`` of a list of times in seconds, in a readable unit."""
    med = statistics.median(times)
    unit, scale = ("s", 1.0) if med >= 1 else ("ms", 1e3) if med >= 1e-3 else ("us", 1e6)
    lo, hi = min(times) * scale, max(times) * scale
    return f"{med * scale:.3g} {unit} ({lo:.3g}-{hi:.3g}, n={len(times)})"


def print_table(headers: list[str], rows: list[list[str]]) -> None:
    """Print a Markdown table."""
    widths = [max(len(str(x)) for x in col) for col in zip(headers, *rows, strict=True)]

    def line(r):
        return "| " + " | ".join(str(x).ljust(w) for x, w in zip(r, widths, strict=True)) + " |"

    print(line(headers))
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        print(line(r))


def simpleitk_resample(image, field, repeats: int, threads: int):
    """Time SimpleITK's ``Resample`` of ``image`` through the displacement ``field``.

    Parameters
    ----------
    image : SimpleITK.Image
        The volume to resample (3-D, scalar).
    field : SimpleITK.Image
        A pull-back displacement field (3 float64 components, world units), on the grid
        resampled onto; the transform takes its pixels (``field`` is left empty).
    repeats : int
        Number of timed calls.
    threads : int
        SimpleITK's global default number of threads.

    Returns
    -------
    times : list of float
        Wall seconds of each ``Resample`` (trilinear, 0 outside the image), ``(repeats,)``.
    result : SimpleITK.Image
        The last call's output, on ``field``'s grid.
    """
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(int(threads))
    grid = sitk.Image(field.GetSize(), sitk.sitkUInt8)
    grid.CopyInformation(field)
    transform = sitk.DisplacementFieldTransform(field)
    result = []

    def run():
        result.append(sitk.Resample(image, grid, transform, sitk.sitkLinear, 0.0))
        del result[:-1]

    return timed(run, repeats), result[-1]
