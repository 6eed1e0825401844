"""The record of one solve of the deformer: iterations, energies, convergence."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["SolveReport"]


@dataclass
class SolveReport:
    """Outcome of :meth:`Deformer.solve`.

    Attributes
    ----------
    iterations : int
        Local/global iterations performed (accelerated or plain, each one local + global
        step; rejected accelerated candidates are not counted separately).
    converged : bool
        Whether the stopping rule was met before ``max_iterations``.
    energy, rigidity, smoothness : (iterations + 1,) float64
        Energy history: total ``E`` and its two parts ``sum |J - R|^2`` and
        ``lambda^2 sum |H|^2``, for the initial iterate and after each iteration; the last
        entry is the energy of the returned solution. Never increasing (up to rounding).
    residuals : (iterations + 1,) float64
        Fixed-point residual ``|T(u) - u|`` (RMS per anchor) of each iterate.
    seconds : float
        Wall time of the iteration (excluding the O(d) set-up).
    rejected_steps : int
        Anderson-extrapolated iterates rejected by the energy safeguard.
    init : str
        The initialisation used.
    contraction : float
        The last estimate of the iteration's contraction rate ``rho`` (NaN when fewer than
        three iterates were seen); stored with a saved solution (see ``Deformer.solve``).
    max_iterations : int
        The iteration cap of the solve.
    tolerance : float
        The stopping tolerance of the solve (see :attr:`distance_estimate`).
    """

    iterations: int
    converged: bool
    energy: np.ndarray
    rigidity: np.ndarray
    smoothness: np.ndarray
    residuals: np.ndarray
    seconds: float
    rejected_steps: int = 0
    init: str = "previous"
    contraction: float = float("nan")
    extra: dict = field(default_factory=dict)
    max_iterations: int = 0
    tolerance: float = float("nan")

    @property
    def energy_history(self) -> np.ndarray:
        """(iterations + 1, 3): columns total, rigidity, smoothness."""
        return np.column_stack([self.energy, self.rigidity, self.smoothness])

    @property
    def distance_estimate(self) -> float:
        """Estimated distance of the returned local matrices to the fixed point.

        ``|T(u) - u| / (1 - rho)`` (RMS per anchor), the quantity compared with the
        tolerance; with no contraction estimate, the last residual itself.
        """
        rho = self.contraction if np.isfinite(self.contraction) else 0.0
        return float(self.residuals[-1] / (1.0 - rho))

    def shortfall(self) -> str:
        """Why an unconverged solve stopped, in words (empty when it converged)."""
        if self.converged:
            return ""
        return (
            f"the solver stopped at max_iterations = {self.max_iterations} with the "
            f"estimated distance to the solution {self.distance_estimate:.3g} above the "
            f"tolerance {self.tolerance:g}"
        )

    @property
    def final_energy(self) -> float:
        """Total energy of the returned solution."""
        return float(self.energy[-1])

    def __repr__(self) -> str:
        return (
            f"SolveReport(iterations={self.iterations}, converged={self.converged}, "
            f"energy={self.energy[-1]:.6g} (rigidity {self.rigidity[-1]:.6g}, smoothness "
            f"{self.smoothness[-1]:.6g}), seconds={self.seconds:.3g})"
        )
