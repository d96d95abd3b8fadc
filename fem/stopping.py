"""The stopping test of every equilibrium SNES solve, a part that owns its state: the residual
norms of the solve, the previous iterate (step sizes), the last search direction's size, and
why a quasi-Newton solve stopped early to refactorise (`StoppingTest.refresh`).
"""

from __future__ import annotations

from mpi4py import MPI  # noqa: F401 (first: it loads the MPI library PETSc links)
from petsc4py import PETSc

import numpy as np

Reason = PETSc.SNES.ConvergedReason
#: A residual norm that is NaN or infinite (DIVERGED_FUNCTION_NANORINF in newer PETSc).
DIVERGED_NAN = getattr(Reason, "DIVERGED_FNORM_NAN", None) or Reason.DIVERGED_FUNCTION_NANORINF


class StoppingTest:
    """SNES's convergence test (``snes.setConvergenceTest(test)``) and the search direction's
    size (``test.precheck``, a line-search pre-check, or called by one).

    A solve stops converged when its last step (mm, inf-norm; quasi-Newton: the larger of
    the step and the search direction, scaled by the error its linear rate leaves) is below
    ``xtol`` and the residual below ``frtol`` x the reference; or when the residual is below
    ``atol`` (mN). A quasi-Newton solve also stops early (DIVERGED_MAX_IT, `refresh` says
    why) where it stalls (``"stalled"``: `SolverPolicy.stall_ratio` over ``stall_its``) or,
    when armed with ``tangent``, once within `SolverPolicy.tangent_refresh_xtols` x xtol
    (``"tangent"``, once per `start`), so that the caller refactorises there.

    Args:
        template: a vector of the solution's layout (the previous iterate is kept in a copy).
        policy: `fem.policy.SolverPolicy`.
        kept: the `fem.factorisation.KeptFactor` (a Newton step counts as full only when its
            matrix was not shifted).
    """

    def __init__(self, template: PETSc.Vec, policy, kept):
        self.policy, self.kept = policy, kept
        self.x_prev = template.duplicate()   # the previous iterate, then its step
        self.norms: list = []                # residual norms of this SNES solve (mN)
        self.direction = np.inf              # inf-norm of the last search direction, mm
        self.refresh = None                  # why it stopped to refactorise, or None
        self.xtol = self.frtol = self.atol = 0.0
        self.f_ref, self.tangent, self.history = None, False, []
        self.f0 = np.inf                     # this solve's residual reference (mN)

    def set_policy(self, policy):
        """The `fem.policy.SolverPolicy` of the next operations (the equilibrium's, when it
        is replaced)."""
        self.policy = policy

    def start(self, xtol: float, frtol: float, atol: float, history: list,
              f_ref: float | None = None, tangent: bool = False):
        """Set the tolerances of the next solves (mm, -, mN), the list every residual norm is
        appended to (a `SolveStats.residual_history`), the residual reference (None: each
        solve's first residual) and whether a tangent refresh is armed."""
        self.xtol, self.frtol, self.atol = xtol, frtol, atol
        self.history, self.f_ref, self.tangent = history, f_ref, tangent

    def run(self, snes, x: PETSc.Vec):
        """``snes.solve`` from x (updated in place), `refresh` cleared first (a solve that
        fails before its first test, e.g. on a NaN residual, leaves none)."""
        self.refresh = None
        snes.solve(None, x)

    def precheck(self, x, y, *args):
        """Remember the search direction's size (a line-search pre-check: changes nothing)."""
        self.direction = y.norm(PETSc.NormType.INFINITY)
        return False

    def __call__(self, snes, it: int, norms) -> int:
        fnorm = norms[2]
        self.history.append(fnorm)
        if it == 0:
            self.norms = []
        self.norms.append(fnorm)
        if not np.isfinite(fnorm):
            return DIVERGED_NAN
        if fnorm <= self.atol:
            return Reason.CONVERGED_FNORM_ABS
        if it == 0:
            self.f0 = fnorm if self.f_ref is None else self.f_ref
            snes.getSolution().copy(self.x_prev)
            return 0
        x = snes.getSolution()
        self.x_prev.axpy(-1.0, x)
        step = self.x_prev.norm(PETSc.NormType.INFINITY)
        x.copy(self.x_prev)
        qn = snes.getType() == "qn"
        if qn:   # a short step AND a short search direction, both scaled to the error they
            # leave at quasi-Newton's observed linear rate
            step, full = max(step, self.direction) * self.error_per_step(it), True
        else:   # a small step proves convergence only if it was a full Newton step (no shift)
            full = self.kept.step_shift == 0
        policy = self.policy
        if step <= self.xtol and fnorm <= self.frtol * self.f0 and full:
            return Reason.CONVERGED_SNORM_RELATIVE
        if qn and self.tangent and it > policy.tangent_lag_its and \
                step <= policy.tangent_refresh_xtols * self.xtol:
            self.tangent, self.refresh = False, "tangent"
            return Reason.DIVERGED_MAX_IT
        if qn and it >= policy.stall_its and \
                fnorm > policy.stall_ratio * self.norms[it - policy.stall_its]:
            self.refresh = "stalled"
            return Reason.DIVERGED_MAX_IT
        if it >= snes.getTolerances()[3]:
            return Reason.DIVERGED_MAX_IT
        return 0

    def error_per_step(self, it: int) -> float:
        """max(1, ρ/(1-ρ)): at a linear rate ρ (the residual's over the last two iterations,
        the first, load-solving one left out, capped at `SolverPolicy.rate_max`) the error
        left after a step of length s is about s ρ/(1-ρ). Slow rates (a factorisation far
        from here) thus stop later; healthy ones (ρ ≤ 1/2) as the step alone says."""
        if it < 3:
            return 1.0
        rate = min(np.sqrt(self.norms[it] / self.norms[it - 2]), self.policy.rate_max)
        return max(1.0, rate / (1.0 - rate))

    def destroy(self):
        self.x_prev.destroy()
