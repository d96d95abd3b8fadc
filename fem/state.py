"""The record the engine's parts share: the current equilibrium, the settings in force and
what the current solve did (`EquilibriumState`, with its `SolveStats`).

`fem.equilibrium.Equilibrium` makes one and hands it to each part (`fem.factorisation.
Refactorisation`, `fem.tangent.TangentSolves`, `fem.path.PathFollower`, `fem.nonlinear.
NonlinearSolver`). A part reads the fields it needs there; only the nonlinear solver moves
the equilibrium (``p``, ``u_eq``, ``solved_xtol``: a solve, `restore`); the facade replaces
the settings whole (frozen `fem.policy.EquilibriumOptions`), never writing into them.
"""

from __future__ import annotations

from mpi4py import MPI  # noqa: F401 (first: it loads the MPI library PETSc links)
from petsc4py import PETSc

import dataclasses

import numpy as np


@dataclasses.dataclass
class SolveStats:
    """What one equilibrium solve did. Times in seconds: ``assemble`` every assembly of the
    energy, f and K during it (the prediction's K at the equilibrium included),
    ``linear_solve`` the rest of ``total``, of which ``factor`` factorising. ``iterations``:
    nonlinear iterations of whichever method ran (quasi-Newton, Newton, the path's)."""

    iterations: int = 0
    shifts: list = dataclasses.field(default_factory=list)
    continuation_steps: int = 0
    residual_history: list = dataclasses.field(default_factory=list)
    factorisations: int = 0
    linear_iterations: int = 0
    lagged: int = 0
    assemble: float = 0.0
    factor: float = 0.0
    linear_solve: float = 0.0
    total: float = 0.0
    goal_error: float = 0.0   # max |u - B p| over active vertices, mm
    min_det_F: float = 1.0    # smallest volume ratio J at the equilibrium
    min_det_F_at: tuple | None = None   # the rest centroid (x, y, z) mm of its cell
    warnings: list = dataclasses.field(default_factory=list)   # goal error, compression

    @property
    def newton_iterations(self) -> int:
        """``iterations`` (its name before it counted quasi-Newton too; kept for callers)."""
        return self.iterations


@dataclasses.dataclass
class EquilibriumState:
    """The current equilibrium and the settings in force.

    Attributes:
        settings: `fem.policy.EquilibriumOptions` (frozen; replaced whole).
        xtol: the step tolerance of the next solves, mm (a plan tightens it).
        p: (Np,) parameters of the current equilibrium; ``u_eq``: its displacement (mm,
            the warm start of the next solve); ``solved_xtol``: the xtol it was solved to
            (0 for an exact rest, inf for no equilibrium yet).
        stats: what the current solve did (a fresh `SolveStats` per solve).
        last_its: iterations of the last SNES solve (how far the kept factor was).
    """

    settings: object
    xtol: float
    p: np.ndarray
    u_eq: PETSc.Vec
    solved_xtol: float
    stats: SolveStats = dataclasses.field(default_factory=SolveStats)
    last_its: int = 0

    @property
    def policy(self):
        """The `fem.policy.SolverPolicy` in force."""
        return self.settings.policy

    @property
    def method(self) -> str:
        """``qn`` or ``newton`` (`fem.policy.METHODS`)."""
        return self.settings.method
