"""Where a filter's deformation comes from, resolved to a harmonic map.

A filter's deformation is one of

* a :class:`~vhm_viz.Deformer` with constraints (solved on first use if it never was);
* a :class:`~vhm_viz.scene.Scene`, or a scene file re-read when its content changes,
  solved through :meth:`Scene.solve_map <vhm_viz.scene.Scene.solve_map>`;
* a fixed :class:`~vhm_viz.HarmonicMap`.

The cage on a filter's input port 1, when connected, *is* the cage: a deformer or scene
whose cage differs is rebuilt on it with the same anchors, constraints, mode and alpha
(and solved again); a fixed harmonic map cannot be moved to another cage, so a mismatch
is an error. :class:`MapSource` holds the deformation and what was derived from it; the
filter hands it the port-1 cage already converted (a :class:`~vhm_viz.Cage` and a digest
of its content).
"""

from __future__ import annotations

import hashlib

import numpy as np

from vhm_viz.core.memory import release_free_memory
from vhm_viz.scene import Scene

__all__ = ["MapSource", "same_cage"]

# Relative tolerance (of the cage diagonal) for "the port-1 cage is the deformer's cage".
_CAGE_TOL = 1e-9


def same_cage(a, b) -> bool:
    """Whether two cages have the same faces and vertices (to ``1e-9`` of the diagonal)."""
    va, vb = np.asarray(a.vertices), np.asarray(b.vertices)
    if va.shape != vb.shape or np.shape(a.faces) != np.shape(b.faces):
        return False
    if not np.array_equal(np.asarray(a.faces), np.asarray(b.faces)):
        return False
    diag = float(np.linalg.norm(va.max(0) - va.min(0))) or 1.0
    return bool(np.abs(va - vb).max() <= _CAGE_TOL * diag)


class MapSource:
    """The deformation set on a filter, and the map, deformer and solves derived from it.

    Attributes
    ----------
    deformer : Deformer or None
        The deformer in use: the one set, or the one built from a scene or on the port-1
        cage (None for a fixed map, or when only a solved map is kept).
    scene : Scene or None
        The scene set, or read from :attr:`scene_file`.
    scene_file : str
        The scene file ("" for none).
    solver : dict
        Solver settings that override the scene's.
    solve_reports : list of SolveReport
        Every solve this source ran.
    last_report : SolveReport or None
        The last solve this source ran (a scene's, an unsolved deformer's, or
        :meth:`update_targets`'s): the one whose convergence the filter checks.
    """

    def __init__(self):
        self.deformer = None
        self.scene = None
        self.scene_file = ""
        self.solver: dict = {}
        self.solve_reports: list = []
        self.last_report = None
        self._user_deformer = None
        self._harmonic_map = None
        self._solved_map = None  # a solved scene's map, when its deformer is not kept
        self._scene_stamp = None
        self._derived_from = None  # (the deformer or scene, key) the derived state is for

    # ------------------------------------------------------------------ setting
    def _clear(self) -> None:
        self.deformer = self.scene = self._user_deformer = self._harmonic_map = None
        self._solved_map = self._derived_from = None
        self.scene_file, self._scene_stamp = "", None

    def set_deformer(self, deformer) -> None:
        """Use ``deformer`` (a :class:`~vhm_viz.Deformer` with constraints set)."""
        if deformer is not None and not hasattr(deformer, "bind"):
            raise TypeError(f"SetDeformer needs a vhm_viz Deformer; got {type(deformer).__name__}")
        self._clear()
        self._user_deformer = self.deformer = deformer

    def set_scene(self, scene) -> None:
        """Use a :class:`~vhm_viz.scene.Scene` (or the path of a scene file, read now)."""
        if scene is not None and not isinstance(scene, Scene):
            scene = Scene.load(scene)
        self._clear()
        self.scene = scene

    def set_scene_file(self, path: str) -> bool:
        """Use the scene in ``path``, read at the next :meth:`resolve`; whether it changed.

        The file replaces any deformation set before ("" leaves none: no stale result of
        the previous scene).
        """
        path = "" if path is None else str(path)
        if path == self.scene_file:
            return False
        self._clear()
        self.scene_file = path
        return True

    def set_harmonic_map(self, harmonic_map) -> None:
        """Use a fixed :class:`~vhm_viz.HarmonicMap` (no solver)."""
        if harmonic_map is not None and not hasattr(harmonic_map, "evaluate"):
            raise TypeError(
                f"SetHarmonicMap needs a vhm_viz HarmonicMap; got {type(harmonic_map).__name__}"
            )
        self._clear()
        self._harmonic_map = harmonic_map

    @property
    def is_set(self) -> bool:
        """Whether any deformation is set."""
        return any(
            x is not None for x in (self._harmonic_map, self._user_deformer, self.scene)
        ) or bool(self.scene_file)

    def _load_scene_file(self) -> None:
        """Read :attr:`scene_file` when its content changed since it was last read."""
        if not self.scene_file:
            return
        try:
            with open(self.scene_file, "rb") as fh:
                text = fh.read()
        except OSError:
            raise FileNotFoundError(f"no such scene file: {self.scene_file}") from None
        # by content: a rewrite of the same size within one tick of the file system's
        # clock (a script writing scenes in turn) keeps its modification time and size
        stamp = hashlib.sha256(text).hexdigest()
        if stamp != self._scene_stamp:
            self.scene = Scene.load(self.scene_file)
            self.deformer = self._solved_map = self._derived_from = None
            self._scene_stamp = stamp

    # ------------------------------------------------------------------ resolving
    def _holds(self, source, key) -> bool:
        derived = self._derived_from
        return derived is not None and derived[0] is source and derived[1] == key

    def resolve(self, cage=None, cage_key=None, data=None, data_key=None, *, mpi=False,
                keep_deformer=True):  # fmt: skip
        """The current ``(harmonic_map, deformer_or_None, report_to_check)``.

        Parameters
        ----------
        cage : Cage, optional
            The cage on the filter's port 1.
        cage_key : str, optional
            A digest of that cage's content (what the derived state is kept for).
        data : vtkDataSet, optional
            The data to deform (a scene's automatic cage or anchors are computed from it).
        data_key : hashable, optional
            Changes when the data's geometry changes.
        mpi : bool
            Several processes each hold a piece of the data: a scene that computes its
            cage or anchors from the data is refused.
        keep_deformer : bool
            False: of a solved scene, keep the map only, not the deformer's matrices (a
            front end with no :meth:`update_targets`, such as ParaView); the scene's
            stored map is then used while it holds.

        Returns
        -------
        tuple
            The map, the deformer (None for a fixed or stored map) and the solve whose
            convergence the caller checks (None when the map came from no solve of
            this source).
        """
        self._load_scene_file()
        if self._harmonic_map is not None:
            if cage is not None and not same_cage(cage, self._harmonic_map.cage):
                raise ValueError(
                    "the cage on input port 1 differs from the harmonic map's cage; a fixed "
                    "harmonic map cannot be moved to another cage (use a Deformer or a scene)"
                )
            return self._harmonic_map, None, None
        if self._user_deformer is not None:
            base = self._user_deformer
            if not self._holds(base, cage_key):
                dfm = base
                if cage is not None and not same_cage(cage, base.cage):
                    dfm = Scene.from_deformer(base).build(cage=cage)
                self.deformer = dfm
                self._derived_from = (base, cage_key)
        elif self.scene is not None:
            scene = self.scene
            key = (cage_key, data_key if scene.needs_data else None)
            if not self._holds(scene, key):
                self._solve_scene(scene, key, cage, data, mpi, keep_deformer)
            if self.deformer is None:
                return self._solved_map, None, self.last_report
        else:
            return None, None, None
        dfm = self.deformer
        if dfm.last_report is None:
            self.last_report = dfm.solve(**self.solve_kwargs())
            self.solve_reports.append(self.last_report)
        # a later solve by the caller replaces this source's: that one is theirs to check
        report = self.last_report if dfm.last_report is self.last_report else None
        return dfm.harmonic_map, dfm, report

    def _solve_scene(self, scene, key, cage, data, mpi, keep_deformer) -> None:
        mesh = None
        if scene.needs_data and cage is None:
            if mpi:
                raise RuntimeError(
                    "the scene's automatic cage or anchors would be computed from "
                    "each rank's own piece of the data: compute them once with "
                    "'vhm-viz cage' / 'vhm-viz anchors' and name the files in the scene"
                )
            # PyVista only here: the automatic cage and anchors take PyVista datasets
            import pyvista as pv

            mesh = pv.wrap(data)
        self.deformer = self._solved_map = None  # free the old solver first
        # every rank solves the same scene to the same map (no coefficients to hand out)
        solved = scene.solve_map(mesh, cage, reuse_stored=not keep_deformer, **self.solver)
        self.solve_reports.extend(solved.reports)
        self.last_report = solved.last_report
        if keep_deformer and not solved.reused:
            self.deformer = solved.deformer
        else:
            self._solved_map = solved.harmonic_map
        self._derived_from = (scene, key)
        if not solved.reused:
            del solved
            # the build's transient basis matrices: before the data's own allocations
            release_free_memory()

    def solve_kwargs(self) -> dict:
        """Keyword arguments of :meth:`Deformer.solve` for a solve this source runs."""
        kw = {"init": "previous"}
        if self.scene is not None:
            kw.update(self.scene.solve_kwargs())
        kw.update(self.solver)
        kw.pop("steps", None)
        return kw

    def update_targets(self, targets=None, jacobians=None, *, solve: bool = True):
        """Move the current deformer's constraint targets (and solve); the report or None."""
        dfm = self.deformer or self._user_deformer
        if dfm is None:
            raise RuntimeError("UpdateTargets needs a deformer: call SetDeformer or SetScene")
        dfm.update_targets(targets=targets, jacobians=jacobians)
        if not solve:
            return None
        report = dfm.solve(**self.solve_kwargs())
        self.solve_reports.append(report)
        self.last_report = report
        return report
