"""Data fuzz: mutated data and cage files through ``read_dataset`` and ``read_cage``.

Small files of every format :mod:`vhm_viz.io` reads for data or cages (VTK XML image and
unstructured grid, legacy VTK, MetaImage ``.mha`` and ``.mhd`` + ``.raw``, NIfTI, OBJ,
OFF, PLY binary and ASCII, STL binary and ASCII) are truncated, bit-flipped, given huge
counts in their headers and wrong magic. Each read ends in a dataset or in a one-line
:class:`~vhm_viz.io.ReadError` (a :class:`~vhm_viz.CageError` for cages), never another
exception, never a crash of this process; no input changes. A few go through the CLI. A
MetaImage header claiming 10**12 voxels is refused from its header, in a child whose
address space could not hold them.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from conftest import UTF8, subprocess_env  # noqa: E402

from vhm_viz import read_cage, read_dataset  # noqa: E402
from vhm_viz.core.errors import CageError  # noqa: E402
from vhm_viz.io import ReadError, write_dataset  # noqa: E402


def _digest(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def _bases(folder: Path) -> list[Path]:
    """Small files of each format (a 6 x 5 x 4 image, an 80-face sphere, a tet grid)."""
    img = pv.ImageData(dimensions=(6, 5, 4), spacing=(1.0, 2.0, 3.0), origin=(1.0, 0.0, -1.0))
    img.point_data["density"] = np.arange(img.n_points, dtype=np.float32)
    sphere = pv.Sphere(theta_resolution=8, phi_resolution=6).triangulate().clean()
    tets = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    files = []
    named = [("img.vti", img), ("img.vtk", img), ("img.mha", img), ("img.mhd", img),
             ("img.nii", img), ("tets.vtu", tets), ("tets.vtk", tets),
             ("sphere.obj", sphere), ("sphere.ply", sphere), ("sphere.stl", sphere)]  # fmt: skip
    for name, data in named:
        if name.endswith((".mha", ".mhd", ".nii")):
            write_dataset(folder / name, data)
        else:
            data.save(folder / name)
        files.append(folder / name)
    sphere.save(folder / "ascii.ply", binary=False)
    sphere.save(folder / "ascii.stl", binary=False)
    faces = sphere.faces.reshape(-1, 4)[:, 1:]
    (folder / "sphere.off").write_text(
        f"OFF\n{sphere.n_points} {len(faces)} 0\n"
        + "".join(f"{x} {y} {z}\n" for x, y, z in sphere.points)
        + "".join(f"3 {a} {b} {c}\n" for a, b, c in faces)
    )
    files += [folder / "ascii.ply", folder / "ascii.stl", folder / "sphere.off",
              folder / "img.raw"]  # fmt: skip
    return files


def _mutations(blob: bytes, rng) -> list[tuple[str, bytes]]:
    """Truncations, bit flips, huge header counts and a wrong magic: 26 per file."""
    out = [(f"cut{f}", blob[: int(len(blob) * f)]) for f in (0.0, 0.05, 0.3, 0.6, 0.9, 0.99)]
    for k in range(12):
        b = bytearray(blob)
        flips = (1, 2, 4, 16)[k % 4]
        pos = rng.integers(0, min(len(b), 512) if k % 2 else len(b), flips)
        for p, bit in zip(pos, rng.integers(0, 8, flips), strict=True):
            b[p] ^= 1 << int(bit)
        out.append((f"flip{k}", bytes(b)))
    head = blob[:1024]
    numbers = list(re.finditer(rb"\d+", head))
    for k in range(6):  # a number of the header made huge (counts, dimensions, offsets)
        if not numbers:
            break
        m = numbers[int(rng.integers(len(numbers)))]
        huge = (b"10000000", b"4294967295", b"1000000000000", b"99999", b"0", b"-1")[k]
        out.append((f"count{k}", blob[: m.start()] + huge + blob[m.end() :]))
    out.append(("magic", b"\x00\xffJUNK" + blob[6:]))
    out.append(("text", blob.decode("latin-1").upper().encode("latin-1")))
    return out


def _read(path: Path) -> str:
    """``"ok"`` or the one-line error of reading ``path`` as data, and as a cage."""
    outcome = []
    readers = [read_dataset]
    if path.suffix in (".obj", ".off", ".ply", ".stl"):
        readers.append(read_cage)
    for reader in readers:
        try:
            reader(path)
            outcome.append("ok")
        except (ReadError, CageError) as exc:
            text = str(exc).strip()
            assert text and "\n" not in text, f"{path.name}: not one line: {text!r}"
            outcome.append(text)
        except Exception as exc:  # noqa: BLE001 -- what the fuzz is for: name the case
            pytest.fail(f"{path.name} ({reader.__name__}): {type(exc).__name__}: {exc}")
    return outcome[0]


def test_mutated_data_files_read_or_one_read_error(tmp_path):
    """26 mutations of each of 15 files: a dataset or a one-line ReadError, inputs kept."""
    base = tmp_path / "base"
    base.mkdir()
    files = _bases(base)
    for f in files:
        if f.suffix != ".raw":
            assert _read(f) == "ok", f
    rng = np.random.default_rng(360)
    cases = tmp_path / "cases"
    cases.mkdir()
    before, n, errors = _digest(base), 0, 0
    for f in files:
        for kind, blob in _mutations(f.read_bytes(), rng):
            d = cases / f"{f.stem}_{f.suffix[1:]}_{kind}"
            d.mkdir()
            if f.suffix in (".mhd", ".raw"):  # the header and its voxels, one mutated
                for part in ("img.mhd", "img.raw"):
                    (d / part).write_bytes((base / part).read_bytes())
                (d / f.name).write_bytes(blob)
                target = d / "img.mhd"
            else:
                target = d / f.name
                target.write_bytes(blob)
            inputs = _digest(d)
            errors += _read(target) != "ok"
            assert _digest(d) == inputs, f"{d.name}: an input changed"
            n += 1
    assert n >= 300 and errors > n // 2, (n, errors)
    assert _digest(base) == before


def test_a_header_claiming_a_trillion_voxels_is_refused_unallocated(tmp_path):
    """DimSize 10**4 cubed over a 120-byte .raw: refused from the header, in a child that
    could not allocate a thousandth of it."""
    img = pv.ImageData(dimensions=(6, 5, 4))
    img.point_data["v"] = np.zeros(img.n_points, dtype=np.uint8)
    write_dataset(tmp_path / "big.mhd", img)
    header = (tmp_path / "big.mhd").read_text()
    header = re.sub(r"DimSize = .*", "DimSize = 10000 10000 10000", header)
    (tmp_path / "big.mhd").write_text(header)
    code = (
        "import resource, sys\n"
        "from pathlib import Path\n"
        "from vhm_viz import read_dataset\n"
        "status = Path('/proc/self/status').read_text().split('VmSize:')[1].split()[0]\n"
        "limit = int(status) * 1024 + 256 * 2**20\n"
        "resource.setrlimit(resource.RLIMIT_AS, (limit, limit))\n"
        "try:\n"
        "    read_dataset(sys.argv[1])\n"
        "except ValueError as exc:\n"
        "    print(type(exc).__name__, exc)\n"
    )
    argv = [sys.executable, "-c", code, str(tmp_path / "big.mhd")]
    done = subprocess.run(argv, capture_output=True, env=subprocess_env(), timeout=120, **UTF8)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    # refused by the memory it would need or by the data it lacks, named from the header
    assert done.stdout.startswith(("ReadError", "TruncatedError")), done.stdout
    assert len(done.stdout.strip().splitlines()) == 1, done.stdout
    assert any(s in done.stdout for s in ("10000 10000 10000", "1000000000000 voxels")), done.stdout


def test_cli_sample_of_mutated_files(tmp_path):
    """Six mutated inputs through ``vhm-viz deform``: one line on stderr, no traceback."""
    base = tmp_path / "base"
    base.mkdir()
    files = {f.suffix: f for f in _bases(base)}
    scene = tmp_path / "scene.json"
    scene.write_text(
        '{"format": "vhm_viz.scene", "version": 1, "cage": "auto", "anchors": {"auto": 5},'
        ' "constraints": {"positions": [[0, 0, 0]], "targets": [[0, 0, 0]]}}'
    )
    rng = np.random.default_rng(7)
    for suffix in (".vti", ".mha", ".nii", ".ply", ".stl", ".vtu"):
        kind, blob = _mutations(files[suffix].read_bytes(), rng)[[2, 9, 20][len(suffix) % 3]]
        bad = tmp_path / f"bad{suffix}"
        bad.write_bytes(blob)
        out = tmp_path / f"out{suffix}"
        argv = [sys.executable, "-m", "vhm_viz.cli", "deform", str(bad), "--scene", str(scene),
                "-o", str(out), "-q"]  # fmt: skip
        done = subprocess.run(argv, capture_output=True, env=subprocess_env(), **UTF8,
                              timeout=300)  # fmt: skip
        lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
        assert "Traceback" not in done.stderr, (suffix, kind, done.stderr)
        if done.returncode:
            assert len(lines) == 1, (suffix, kind, done.stderr)
            assert not out.exists()
        assert bad.read_bytes() == blob


def test_a_cage_of_ten_million_faces_is_refused_unread(tmp_path):
    """An OBJ cage of 10**7 faces (80 MB), and an anchors file as large: refused from
    their size, before a line is parsed."""
    from vhm_viz.io import read_anchors

    cage = tmp_path / "big.obj"
    cage.write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 10**7)
    with pytest.raises(ReadError, match="cage files may hold at most"):
        read_cage(cage)
    anchors = tmp_path / "big.json"
    anchors.write_bytes(b"[" + b"[0, 0, 0], " * 10**7 + b"[0, 0, 0]]")
    with pytest.raises(ReadError, match="anchors files may hold at most"):
        read_anchors(anchors)


def test_a_compressed_image_larger_than_the_fixed_cap_reads_back(tmp_path):
    """A 1.1 GB image that compresses to a few MB (what a resample at 512^3 writes) reads
    back whole: the reading child's cap grows with the memory there is, since the child
    holds the dataset and its pickled copy at once (2.2 GB, beyond a fixed 2 GiB)."""
    shape = (1100, 1000, 1000)
    img = pv.ImageData(dimensions=shape, spacing=(0.5, 0.5, 0.5))
    values = np.zeros(img.n_points, dtype=np.uint8)
    values[::997] = 7
    img.point_data["v"] = values
    path = tmp_path / "big.vti"
    img.save(path)
    del img, values
    assert path.stat().st_size < 64 << 20  # far below what it expands to
    back = read_dataset(path)
    assert back.dimensions == shape
    got = np.asarray(back.point_data["v"])
    assert got.size == np.prod(shape) and got[::997].min() == 7
    assert int(np.count_nonzero(got)) == len(range(0, got.size, 997))
