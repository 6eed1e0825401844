"""Surface and mesh formats parsed or checked here: PLY, STL, OFF, MEDIT, Gmsh, point lists.

PLY and STL headers are checked against the file (:func:`check_ply`, :func:`check_stl`)
before VTK reads them; OFF is parsed here (:func:`parse_off`, the one OFF parser, also
for cages and rigidity lines); MEDIT and Gmsh are checked here (:func:`check_medit`,
:func:`check_gmsh`), then read by meshio; point lists through NumPy.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

import numpy as np

from vhm_viz.io.errors import (
    AGAIN,
    ReadError,
    TruncatedError,
    check_count,
    cut_short,
    first_line,
    need,
)
from vhm_viz.io.registry import format_of, suffix_of

__all__ = [
    "check_ply",
    "check_stl",
    "check_medit",
    "check_gmsh",
    "parse_off",
    "read_off_dataset",
    "read_meshio",
    "read_point_list",
]


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def check_ply(p: Path) -> None:
    """PLY: header, element counts and list lengths against the file's bytes or values."""
    blob = p.read_bytes()
    if not blob.startswith(b"ply"):
        raise ReadError(f"{p}: not a PLY file (no 'ply' magic)")
    at = blob.find(b"end_header", 0, 1 << 16)
    if at < 0:
        raise ReadError(f"{p}: PLY header has no 'end_header' line")
    nl = blob.find(b"\n", at)
    body = len(blob) if nl < 0 else nl + 1
    fmt, elements = None, []
    for raw in blob[:at].decode("latin-1").splitlines()[1:]:
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        try:
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                count = int(tok[2])
                if count < 0:
                    raise ValueError
                elements.append((tok[1], count, []))
            elif tok[0] == "property" and elements:
                if tok[1] == "list":
                    elements[-1][2].append((tok[-1], _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
                else:
                    elements[-1][2].append((tok[-1], _PLY_TYPES[tok[1]], None))
            else:
                raise ValueError
        except (IndexError, KeyError, ValueError):
            raise ReadError(f"{p}: malformed PLY header line {raw.strip()!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ReadError(f"{p}: unknown PLY format {fmt!r}")
    n_vertices = next((c for name, c, _ in elements if name == "vertex"), 0)
    if fmt == "ascii":
        _check_ply_ascii(p, blob[body:], elements, n_vertices)
    else:
        _check_ply_binary(p, blob, body, elements, n_vertices, "<" if "little" in fmt else ">")


def _check_ply_binary(p, blob, pos, elements, n_vertices, order) -> None:
    for name, count, props in elements:
        if all(kind is None for _, _, kind in props):
            row = sum(np.dtype(t).itemsize for _, t, _ in props)
            need(p, f"element '{name}' ({count} x {row} bytes)", count * row, len(blob) - pos)
            pos += count * row
            continue
        if len(props) == 1 and count:
            # one list per row (faces): usually all of one length -- check it vectorised
            _, count_type, item_type = props[0]
            ct, it = (
                np.dtype(count_type).newbyteorder(order),
                np.dtype(item_type).newbyteorder(order),
            )
            need(p, f"element '{name}'", ct.itemsize, len(blob) - pos)
            k = int(np.frombuffer(blob, ct, 1, pos)[0])
            if k >= 0:
                rec = np.dtype([("k", ct), ("ids", it, (k,))])
                if len(blob) - pos >= count * rec.itemsize:
                    rows = np.frombuffer(blob, rec, count, pos)
                    if (rows["k"] == k).all():
                        _check_ids(p, name, rows["ids"], n_vertices)
                        pos += count * rec.itemsize
                        continue
        pos = _walk_ply_rows(p, blob, pos, name, count, props, order, n_vertices)
    return None


def _walk_ply_rows(p, blob, pos, name, count, props, order, n_vertices) -> int:
    """Row by row (lists of varying length): every list inside the file, ids in range."""
    size = len(blob)
    for _ in range(count):
        for prop, scalar_or_count, item in props:
            ct = np.dtype(scalar_or_count).newbyteorder(order)
            need(p, f"element '{name}'", pos + ct.itemsize, size)
            if item is None:
                pos += ct.itemsize
                continue
            k = int(np.frombuffer(blob, ct, 1, pos)[0])
            pos += ct.itemsize
            it = np.dtype(item).newbyteorder(order)
            if k < 0:
                raise ReadError(f"{p}: corrupt PLY: a list of length {k} in element '{name}'")
            need(p, f"element '{name}'", pos + k * it.itemsize, size)
            if prop in ("vertex_indices", "vertex_index"):
                _check_ids(p, name, np.frombuffer(blob, it, k, pos), n_vertices)
            pos += k * it.itemsize
    return pos


def _check_ids(p, element, ids, n_vertices) -> None:
    ids = np.asarray(ids)
    if ids.size and (ids.min() < 0 or ids.max() >= n_vertices):
        raise ReadError(
            f"{p}: corrupt PLY: element '{element}' refers to vertex {int(ids.max())} "
            f"(or {int(ids.min())}); there are {n_vertices} vertices"
        )


def _check_ply_ascii(p, body: bytes, elements, n_vertices) -> None:
    tokens = body.split()
    pos = 0
    for name, count, props in elements:
        for row in range(count):
            for prop, _t, item in props:
                if pos >= len(tokens):
                    check_count(p, f"element '{name}'", count, row, unit="rows", ends=True)
                if item is None:
                    pos += 1
                    continue
                try:
                    k = int(tokens[pos])
                    ids = [int(t) for t in tokens[pos + 1 : pos + 1 + k]]
                except ValueError:
                    raise ReadError(f"{p}: corrupt PLY: non-integer list in '{name}'") from None
                if k < 0:
                    raise ReadError(f"{p}: corrupt PLY: a list of length {k} in element '{name}'")
                if len(ids) < k:  # the file ends inside this row's list
                    check_count(p, f"element '{name}'", count, row, unit="rows", ends=True)
                if prop in ("vertex_indices", "vertex_index"):
                    _check_ids(p, name, ids, n_vertices)
                pos += 1 + k


def check_stl(p: Path) -> None:
    """STL: binary -- 84 + 50 n bytes for n triangles; ASCII -- ends with ``endsolid``."""
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(84)
    if len(head) == 84 and 84 + 50 * int.from_bytes(head[80:84], "little") == size:
        return
    if head.lstrip().lower().startswith(b"solid"):
        with open(p, "rb") as fh:
            fh.seek(max(0, size - 1024))
            if b"endsolid" in fh.read().lower():
                return
        raise TruncatedError(f"{p}: truncated ASCII STL (no 'endsolid' at the end); {AGAIN}")
    n = int.from_bytes(head[80:84], "little") if len(head) == 84 else 0
    raise TruncatedError(
        f"{p}: truncated or corrupt binary STL: {n} triangles need {84 + 50 * n} bytes, the "
        f"file has {size}"
    )


#: The MEDIT blocks meshio reads: values per entry ("d": the dimension; "d+1": with the
#: reference number), or None for the blocks it skips a line per entry of.
_MEDIT_BLOCKS = {
    "Vertices": "d+1", "Edges": 3, "Triangles": 4, "Quadrilaterals": 5, "Tetrahedra": 5,
    "Prisms": 7, "Pyramids": 6, "Hexahedra": 9, "Hexaedra": 9, "Corners": 1, "Normals": "d",
    "NormalAtVertices": 2, "SubDomainFromMesh": 4, "VertexOnGeometricVertex": 2,
    "VertexOnGeometricEdge": 3, "EdgeOnGeometricEdge": 2, "RequiredVertices": None,
    "TangentAtVertices": None, "Tangents": None, "Ridges": None,
}  # fmt: skip

#: A MEDIT keyword line: a word at the start of a line (never a number, nan or inf).
_MEDIT_KEYWORD = re.compile(rb"^[ \t]*(?!(?:nan|inf)\b)([A-Za-z]\w*)[^\n]*", re.M | re.I)


def check_medit(p: Path) -> None:
    """MEDIT ``.mesh`` (text): every block holds the entries its count lists.

    Entries are counted as meshio reads them: values for vertices and elements, lines for
    the blocks it skips.

    meshio reshapes what it read to the count and fails with NumPy's words; a file cut
    short is refused here with the block, its count and what the file holds.
    """
    blob = p.read_bytes()
    keywords = [m for m in _MEDIT_KEYWORD.finditer(blob) if not _comment(blob, m.start())]
    dim, skip_to = 0, 0
    for k, m in enumerate(keywords):
        if m.start() < skip_to:
            continue  # the line after Identifier or Geometry: text, not a keyword
        word = m.group(1).decode("ascii")
        end = keywords[k + 1].start() if k + 1 < len(keywords) else len(blob)
        body = blob[m.end() : end]
        if word == "End":
            return
        if word in ("Identifier", "Geometry"):
            skip_to = blob.find(b"\n", m.end() + 1) + 1 or len(blob)
            continue
        if word == "MeshVersionFormatted":
            continue
        if word == "Dimension":  # "Dimension 3", or the 3 on the next line
            inline = m.group(0).split()[1:]
            dim = _medit_int(p, (inline or body.split() or [b""])[0], "Dimension")
            continue
        if word not in _MEDIT_BLOCKS:
            line = blob.count(b"\n", 0, m.start()) + 1
            raise ReadError(f"{p}: line {line}: unknown MEDIT keyword {word!r}")
        width = _MEDIT_BLOCKS[word]
        if width in ("d", "d+1"):
            if dim not in (2, 3):
                raise ReadError(f"{p}: malformed MEDIT file: {word} before a Dimension of 2 or 3")
            width = dim + (width == "d+1")
        last = k + 1 == len(keywords)
        head, _, rest = body.removeprefix(b"\n").partition(b"\n")  # the count's line
        if last and not body.strip():
            raise cut_short(p, f"its {word} block")
        count = _medit_int(p, head.strip(), f"the {word} count")
        if width is None:
            held = _count_lines(rest)
        else:
            values = _count_tokens(rest)
            held = values // width if values < count * width else -(-values // width)
        check_count(p, f"its {word} block", count, held, ends=last, exact=True)


def _comment(blob: bytes, at: int) -> bool:
    """Whether the line of ``blob`` holding offset ``at`` starts with ``#``."""
    start = blob.rfind(b"\n", 0, at) + 1
    return blob[start:at].lstrip().startswith(b"#")


def _medit_int(p: Path, text: bytes, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise ReadError(f"{p}: malformed MEDIT file: {what} is {text[:20].decode('latin-1')!r}")
    return value


def _count_tokens(blob: bytes) -> int:
    """Whitespace-separated words in ``blob`` (``#`` comment lines left out)."""
    if b"#" in blob:
        blob = re.sub(rb"(?m)^[ \t]*#[^\n]*", b"", blob)
    a = np.frombuffer(blob, np.uint8)
    if not a.size:
        return 0
    word = a > 32
    return int(np.count_nonzero(word[1:] & ~word[:-1])) + int(word[0])


def _count_lines(blob: bytes) -> int:
    """Lines of ``blob`` that hold a word (``#`` comment lines left out)."""
    if b"#" in blob:
        blob = re.sub(rb"(?m)^[ \t]*#[^\n]*", b"", blob)
    a = np.frombuffer(blob, np.uint8)
    if not a.size:
        return 0
    starts = np.flatnonzero(a == 10) + 1
    starts = np.concatenate(([0], starts[starts < a.size]))
    # one flag a line, not a count a byte: whether any byte of it is a word's
    return int(np.count_nonzero(np.logical_or.reduceat(a > 32, starts)))


#: A Gmsh section's first line (``$Nodes``): its end is ``$EndNodes``.
_GMSH_SECTION = re.compile(rb"^\$(\w+)[ \t\r]*$", re.M)


def check_gmsh(p: Path) -> None:
    """Gmsh ``.msh`` (text or binary, versions 2 and 4): every section has its end.

    In text files, ``$Nodes`` and ``$Elements`` hold the entries their counts list too.

    meshio reads a section cut short into arrays it then reshapes, and fails with NumPy's
    words; here such a file is refused with the section it ends in.
    """
    blob = p.read_bytes()
    pos, version, text = 0, "", True
    while (m := _GMSH_SECTION.search(blob, pos)) is not None:
        name = m.group(1)
        if name.startswith(b"End"):
            pos = m.end()
            continue
        end = re.compile(rb"^\$End" + re.escape(name) + rb"\b", re.M).search(blob, m.end())
        if end is None:
            raise cut_short(p, f"its ${name.decode('latin-1')} section")
        body = blob[m.end() : end.start()]
        if name == b"MeshFormat":
            head = body.strip().split(b"\n", 1)[0].split()  # version, 0 (text) or 1, size
            if len(head) > 1:
                version, text = head[0].decode("latin-1"), head[1] == b"0"
        elif text and name in (b"Nodes", b"Elements"):
            _check_gmsh_counts(p, name.decode("ascii"), body, version)
        pos = end.end()


def _check_gmsh_counts(p: Path, name: str, body: bytes, version: str) -> None:
    """A text ``$Nodes`` or ``$Elements`` section: its entries against its count.

    Version 2: a count line, then one line per entry. Version 4: a line of the block count
    B and the entry count N, then B blocks of a header line and their entries -- one line
    each, and in version 4.1 nodes a line of tags before their coordinates (two lines).
    """
    head, _, rest = body.strip().partition(b"\n")
    words = head.split()
    try:
        numbers = [int(w) for w in words[:2]]
    except ValueError:
        numbers = []
    v4 = version.startswith("4")
    if len(numbers) < (2 if v4 else 1) or min(numbers) < 0:
        raise ReadError(
            f"{p}: malformed Gmsh file: ${name} starts with {head[:40].decode('latin-1')!r}"
        )
    lines = _count_lines(rest)
    if not v4:
        count, held = numbers[0], lines
    else:
        blocks, count = numbers
        held = max(lines - blocks, 0)
        if name == "Nodes" and not version.startswith("4.0"):
            held //= 2
    check_count(p, f"its ${name} section", count, held, ends=False, exact=True)


def parse_off(path: Path) -> tuple[np.ndarray, list[np.ndarray], int]:
    """The one OFF parser: points, every record after them, and the header's face count.

    Records are index lists (``k i j ...``): faces, and -- in rigidity-line files such as
    the hand's ``polylines.off`` -- edges (``k = 2``) after the faces. Refuses a file whose
    header announces more points or faces than it holds, and indices out of range.
    """
    with open(path, encoding="utf-8", errors="replace") as fh:
        lines = [t for t in (ln.split("#", 1)[0].split() for ln in fh) if t]
    if not lines or not lines[0][0].upper().endswith("OFF"):
        raise ReadError(f"{path}: not an OFF file (no OFF header)")
    head, rest = lines[0][1:], lines[1:]
    if not head:
        if not rest:
            raise TruncatedError(f"{path}: truncated OFF file (no counts line)")
        head, rest = rest[0], rest[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
        if nv < 0 or nf < 0:
            raise ValueError(f"negative count in {' '.join(head)!r}")
        check_count(path, "the header", nv, len(rest), unit="points", ends=True)
        short = next((i for i, t in enumerate(rest[:nv]) if len(t) < 3), None)
        if short is not None:
            if short == len(rest) - 1:  # the file's last line, cut inside
                check_count(path, "the header", nv, short, unit="points", ends=True)
            raise ValueError(f"point {short} has fewer than 3 coordinates")
        verts = np.array([[float(x) for x in t[:3]] for t in rest[:nv]], dtype=np.float64)
        records = []
        for line, t in enumerate(rest[nv:], nv):
            k = int(t[0])
            ids = np.array([int(x) for x in t[1 : 1 + k]], dtype=np.int64)
            if k < 1 or len(ids) != k:
                if line == len(rest) - 1 and len(ids) < k:  # the file's last line, cut inside
                    check_count(path, "the header", nf, len(records), unit="faces", ends=True)
                raise ValueError(f"bad record {' '.join(t)[:40]!r}")
            records.append(ids)
    except ReadError:
        raise
    except (ValueError, IndexError) as exc:
        raise ReadError(f"{path}: malformed OFF file: {exc}") from None
    check_count(path, "the header", nf, len(records), unit="faces", ends=True)
    bad = [i for i, r in enumerate(records) if r.min() < 0 or r.max() >= nv]
    if bad:
        raise ReadError(f"{path}: record {bad[0]} refers to a point outside [0, {nv})")
    return verts.reshape(-1, 3), records, nf


def read_off_dataset(path):
    """An OFF file as PolyData: polygons, and any edge (2) or vertex (1) records."""
    import pyvista as pv

    points, records, _ = parse_off(Path(path))
    by_kind: dict[str, list] = {"faces": [], "lines": [], "verts": []}
    for r in records:
        kind = "faces" if len(r) >= 3 else ("lines" if len(r) == 2 else "verts")
        by_kind[kind].append(np.concatenate([[len(r)], r]))
    cells = {k: np.concatenate(v) for k, v in by_kind.items() if v}
    return pv.PolyData(points, **cells)


def read_meshio(path):
    """A MEDIT ``.mesh`` or Gmsh ``.msh`` file through meshio (complaints, sys.exit caught)."""
    import meshio
    import pyvista as pv

    p = Path(path)
    printed = io.StringIO()  # meshio prints (and logs) its complaints: keep them
    try:
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
            mesh = meshio.read(os.fspath(p))
    except SystemExit as exc:  # meshio's readers call sys.exit on some malformed files
        said = printed.getvalue().strip().splitlines()
        raise ReadError(
            f"{p}: malformed {suffix_of(p)} file" + (f" ({said[0]})" if said else "")
        ) from exc
    except meshio.ReadError as exc:  # meshio's own words, meant for its users
        raise ReadError(f"{p}: malformed {suffix_of(p)} file ({first_line(exc)})") from None
    except (ValueError, IndexError, KeyError, TypeError, AttributeError) as exc:
        # what the checks above missed fails inside meshio, in NumPy's or Python's words
        kind = format_of(p).name
        raise ReadError(
            f"{p}: corrupt {kind} file: its data do not follow its counts and keywords; "
            "export it again"
        ) from exc
    return pv.from_meshio(mesh)


def read_point_list(path):
    """A file of one point per row (the first three columns are x, y, z) as PolyData.

    ``.npy`` (a NumPy array), ``.csv`` (comma-separated) or whitespace-separated text; a
    first row of column names (``x,y,z``, as spreadsheets and pandas write them) is
    skipped, and ``#`` starts a comment.
    """
    import pyvista as pv

    p, suffix = Path(path), suffix_of(path)
    if suffix == ".npy":
        pts = np.load(p, allow_pickle=False)
    else:
        delimiter = "," if suffix == ".csv" else None
        try:
            pts = np.loadtxt(p, delimiter=delimiter, ndmin=2, skiprows=_names_row(p, delimiter))
        except ValueError as exc:
            # binary content (another format under a text suffix) says so, not the codec
            what = "not a text file" if isinstance(exc, UnicodeDecodeError) else first_line(exc)
            raise ReadError(
                f"{p}: {what.rstrip('.')}; expected numbers, one point (x y z ...) per row"
            ) from None
    pts = np.asarray(pts, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ReadError(f"{p}: expected one point per row (x y z ...), got shape {pts.shape}")
    return pv.PolyData(np.ascontiguousarray(pts[:, :3]))


def _names_row(path: Path, delimiter) -> int:
    """1 when the first row that is not a comment holds column names, not numbers; else 0."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for k, line in enumerate(fh):
            text = line.split("#", 1)[0].strip()
            if not text:
                continue
            try:
                [float(word) for word in text.split(delimiter)]
            except ValueError:
                return k + 1  # the names and any comments before them
            return 0
    return 0
