"""Slivers: cage triangles too thin for the solve, and their repair.

A sliver is a face whose smallest angle is below :data:`MIN_FACE_ANGLE` (a needle with one
very short edge, or a cap with one angle near 180 degrees). :func:`repair_slivers`
removes them by edge flips and collapses that keep the cage a closed manifold and move no
part of its surface inward. :func:`reduce_slivers` takes the same steps as far as they go,
and optionally also steps that move the surface inward, for the automatic cage, which
pushes its surface back out to the clearance afterwards.
"""

from __future__ import annotations

import numpy as np

from vhm_viz.core.errors import CageError
from vhm_viz.core.geometry import face_normals_and_areas

__all__ = ["MIN_FACE_ANGLE", "SliverError", "face_angles", "reduce_slivers", "repair_slivers"]

#: Smallest angle (degrees) a cage triangle may have. Thinner triangles ("slivers": a needle
#: with one very short edge, or a cap with one angle near 180 degrees) ruin the solve: the
#: smoothness samples on them see huge Hessians, the smoothness weight lambda (normalised by
#: the largest Hessian row) collapses, and the result is garbage while the solver reports
#: convergence. Three degrees is the smallest angle at which a needle inserted into a clean
#: cage still leaves the rigidity energy and the map close to the clean cage's; below it
#: the solve first stops converging, then goes wrong by a large fraction of the diagonal.
MIN_FACE_ANGLE = 3.0


class SliverError(CageError):
    """Faces whose smallest angle is below the minimum; ``indices``: those faces."""


def face_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Interior angles of triangles, in degrees.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int

    Returns
    -------
    (m, 3) float64
        Angle at each corner; 0 at a corner of a zero-length edge.
    """
    x = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    out = np.zeros(x.shape[:2])
    for i in range(3):
        a = x[:, (i + 1) % 3] - x[:, i]
        b = x[:, (i + 2) % 3] - x[:, i]
        # atan2 of |a x b| and a.b: accurate for angles near 0 and 180 degrees
        out[:, i] = np.degrees(
            np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
        )
    return out


def repair_slivers(
    vertices,
    faces,
    min_angle: float = MIN_FACE_ANGLE,
    *,
    error: SliverError | None = None,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Remove slivers from a closed, consistently oriented triangle mesh.

    Worst face first: the edge opposite the largest angle is flipped, or the shortest edge
    collapsed (to an end point or the midpoint), whichever leaves the larger smallest angle.
    A step is taken only if it keeps the mesh a closed manifold (no duplicate edge, the
    link condition for collapses), turns no face over (each changed face's normal within
    90 degrees of the old ones), improves the smallest angle where it acts, and moves no
    part of the surface inward (a flip adds volume or none, a collapse moves no vertex
    through a face around it): the repaired cage holds everything the input held, so a
    cage that enclosed the data still does. The caller validates the result
    (self-intersection).

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
    min_angle : float
        Degrees.
    error : SliverError, optional
        Re-raised (with the faces still thin) when a sliver cannot be repaired.

    Returns
    -------
    vertices, faces, notes
        As :func:`reduce_slivers` gives them, with no face left thin.

    Raises
    ------
    SliverError
        A sliver that no flip or collapse can remove; the message names it.
    """
    v, f, notes = reduce_slivers(vertices, faces, min_angle)
    thin = np.flatnonzero(face_angles(v, f).min(axis=1) < min_angle)
    if len(thin):
        t = int(thin[0])
        msg = (
            f"{len(thin)} slivers left: face {t} has an angle of "
            f"{face_angles(v, f[[t]]).min():.3g} degrees, below the {min_angle:g} degree "
            "minimum (vhm_viz.core.cage.MIN_FACE_ANGLE), and no edge flip or collapse "
            "removes it without moving the cage into what it encloses; move its vertices "
            f"{', '.join(str(int(i)) for i in f[t])}"
        )
        raise SliverError(msg if error is None else f"{error} -- {msg}", thin)
    return v, f, notes


def reduce_slivers(
    vertices,
    faces,
    min_angle: float = MIN_FACE_ANGLE,
    *,
    inward: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The steps of :func:`repair_slivers`, as many as can be taken; thin faces may remain.

    Parameters
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
        A closed, consistently oriented triangle mesh.
    min_angle : float
        Degrees: faces with a smaller angle are worked on, worst first.
    inward : float
        How far (world units) a step may move the surface inward: a flip whose new edge
        passes at most this far inside the old one, a collapse that moves a vertex at
        most this far through a face around it. 0 (the default) moves nothing inward,
        as :func:`repair_slivers`; more is for callers that restore the clearance
        afterwards, as the automatic cage's push-out does: the result may then no longer
        hold all that the input held.

    Returns
    -------
    vertices : (n', 3) float64
        Collapsed vertices removed; the others keep their order.
    faces : (m', 3) int64
    notes : list of str
        One line per step, with the input's vertex numbers.
    """
    v = np.array(vertices, dtype=np.float64)
    f = np.array(faces, dtype=np.int64)
    alive = np.ones(len(v), dtype=bool)
    notes: list[str] = []
    stuck: set[tuple] = set()  # slivers no step removes (by their corners)
    for _ in range(2 * len(f)):  # each step removes a face or improves one: a bound
        ang = face_angles(v, f)
        smallest = ang.min(axis=1)
        worst = (int(u) for u in np.argsort(smallest) if tuple(sorted(f[u])) not in stuck)
        t = next(worst, None)
        if t is None or smallest[t] >= min_angle:
            break
        # of the flip and the collapse that are allowed, the one leaving the larger angle
        steps = [
            x for x in (_flip_cap(v, f, t, ang, inward), _collapse_needle(v, f, t, inward)) if x
        ]
        if not steps:
            stuck.add(tuple(sorted(f[t])))
            continue
        f, note, _, collapse = max(steps, key=lambda x: x[2])
        if collapse is not None:
            a, b, point = collapse
            v[a] = point
            alive[b] = False
        notes.append(f"{note} (face {t} had an angle of {smallest[t]:.3g} degrees)")
    keep = np.flatnonzero(alive)
    renumber = np.full(len(v), -1, dtype=np.int64)
    renumber[keep] = np.arange(len(keep))
    return v[keep], renumber[f], notes


def _faces_with_edge(f: np.ndarray, a: int, b: int) -> np.ndarray:
    return np.flatnonzero((f == a).any(axis=1) & (f == b).any(axis=1))


def _normals_kept(v, old_faces, new_faces) -> bool:
    """Whether every new face is non-degenerate and within 90 degrees of an old face."""
    n_old, _ = face_normals_and_areas(v, old_faces)
    n_new, a_new = face_normals_and_areas(v, new_faces)
    if (a_new <= 0).any():
        return False
    return bool(((n_new @ n_old.T) > 0).any(axis=1).all())


def _flat(v, faces) -> float:
    """What counts as no volume next to ``faces``: rounding of their size cubed."""
    x = v[faces]
    size = float(np.linalg.norm(x.max(axis=(0, 1)) - x.min(axis=(0, 1))))
    return 1e-9 * size**3


def _volume_change(v_old, old_faces, v_new, new_faces) -> float:
    """Volume the replacement of ``old_faces`` by ``new_faces`` adds (both closing a patch)."""
    origin = v_old[old_faces].reshape(-1, 3).mean(axis=0)  # origin-free, like signed_volume

    def cones(v, faces):
        x = v[faces] - origin
        return float(np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() / 6.0)

    return cones(v_new, new_faces) - cones(v_old, old_faces)


def _moves_outward(v, f, moves: dict, inward: float = 0.0) -> bool:
    """Whether moving vertices (``{vertex: new position}``) keeps the surface outside.

    Every moved vertex must not go inward through any face around it (beyond rounding,
    or beyond ``inward``, a distance): the repaired cage then still holds all it held,
    which a cage around data must.
    """
    for vid, point in moves.items():
        normals, _ = face_normals_and_areas(v, f[(f == vid).any(axis=1)])
        step = np.asarray(point) - v[vid]
        if (normals @ step < -max(inward, 1e-9 * np.linalg.norm(step)) - 1e-300).any():
            return False
    return True


def _segment_distance(p0, p1, q0, q1) -> float:
    """Smallest distance between the segments ``p0-p1`` and ``q0-q1``.

    The farthest an edge flip moves the surface: the two diagonals of the quad it
    re-triangulates.
    """
    u, w, r = p1 - p0, q1 - q0, p0 - q0
    a, b, c, d, e = u @ u, u @ w, w @ w, u @ r, w @ r
    den = a * c - b * b
    # the closest parameters of the lines, clamped to the segments (each in turn)
    s = np.clip((b * e - c * d) / den, 0.0, 1.0) if den > 1e-300 * a * c else 0.0
    t = np.clip((b * s + e) / c, 0.0, 1.0) if c > 0 else 0.0
    s = np.clip((b * t - d) / a, 0.0, 1.0) if a > 0 else 0.0
    return float(np.linalg.norm(p0 + s * u - (q0 + t * w)))


def _flip_cap(v, f, t, ang, inward=0.0):
    """Flip the edge opposite face ``t``'s largest angle; None if that is not allowed.

    Returns the new faces, a note, the smallest angle of the changed faces and None (no
    vertex moves).
    """
    k = int(np.argmax(ang[t]))
    c, a, b = f[t, k], f[t, (k + 1) % 3], f[t, (k + 2) % 3]  # face (c, a, b), edge a-b
    other = [u for u in _faces_with_edge(f, a, b) if u != t]
    if len(other) != 1:
        return None
    u = other[0]
    d = int(next(x for x in f[u] if x not in (a, b)))
    if d == c or len(_faces_with_edge(f, c, d)):
        return None
    new = np.array([[c, a, d], [d, b, c]])  # keeps the orientation of (c, a, b), (b, a, d)
    if not _normals_kept(v, f[[t, u]], new):
        return None
    worst = face_angles(v, new).min()
    if worst <= min(ang[t].min(), face_angles(v, f[[u]]).min()):
        return None
    if _volume_change(v, f[[t, u]], v, new) < -_flat(v, f[[t, u]]) and (
        _segment_distance(v[a], v[b], v[c], v[d]) > inward
    ):
        return None  # the new edge would cut into the cage: what it held could be lost
    g = f.copy()
    g[t], g[u] = new
    return g, f"flipped edge ({a}, {b}) to ({c}, {d})", worst, None


def _collapse_needle(v, f, t, inward=0.0):
    """Collapse face ``t``'s shortest edge; None if no position keeps the cage valid.

    Returns the new faces, a note, the smallest angle of the changed faces and the move
    ``(a, b, point)``: vertex ``a`` goes to ``point``, vertex ``b`` is gone.
    """
    x = v[f[t]]
    lengths = np.linalg.norm(x[[1, 2, 0]] - x, axis=1)
    k = int(np.argmin(lengths))
    a, b = int(f[t, k]), int(f[t, (k + 1) % 3])
    shared = _faces_with_edge(f, a, b)
    ring = lambda p: set(f[(f == p).any(axis=1)].ravel()) - {p}  # noqa: E731
    opposite = {int(i) for s in shared for i in f[s] if i not in (a, b)}
    if len(shared) != 2 or (ring(a) & ring(b)) != opposite or len(f) < 6:
        return None  # the link condition (a collapse would pinch the surface); a tetrahedron
    moved = np.flatnonzero((f == a).any(axis=1) | (f == b).any(axis=1))
    kept = np.setdiff1d(moved, shared)
    before = face_angles(v, f[moved]).min()
    best = None
    for where, point in (("midpoint", 0.5 * (v[a] + v[b])), (str(a), v[a]), (str(b), v[b])):
        w = v.copy()
        w[a] = point
        g = np.where(f == b, a, f)
        new = g[kept]
        if not _normals_kept(w, f[kept], new):
            continue
        # normals of the kept faces against their own old normals, one by one
        n_old, _ = face_normals_and_areas(v, f[kept])
        n_new, _ = face_normals_and_areas(w, new)
        if (np.einsum("ij,ij->i", n_old, n_new) <= 0).any():
            continue
        worst = face_angles(w, new).min()
        if worst <= before or (best is not None and worst <= best[0]):
            continue
        if not _moves_outward(v, f, {a: point, b: point}, inward):
            continue  # the surface would move inward: what it held could be lost
        best = (worst, where, point, g)
    if best is None:
        return None
    worst, where, point, g = best
    return (
        np.delete(g, shared, axis=0),
        f"collapsed edge ({a}, {b}) to {where}",
        worst,
        (a, b, point),
    )
