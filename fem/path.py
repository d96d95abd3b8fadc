"""Path following and predictions: first-order states x(p0) + dx/dp dp, their admissibility
(no inverted element), secant continuation along a path and quasi-Newton relaxation on the
kept factorisation (no assembly of K).
"""

from __future__ import annotations

from mpi4py import MPI  # noqa: F401 (first: it loads the MPI library PETSc links)
from petsc4py import PETSc

import logging
import time

import numpy as np

from fem.state import SolveStats
from meshes.errors import SolverError

log = logging.getLogger(__name__)


class PathFollower:
    """Predictions and continuation, a part: first-order states (`first_order`), their
    admissibility (`admissible`), secant continuation along a path (`follow`) and
    quasi-Newton relaxation on the kept factorisation (`relax`).

    Args:
        forms: `fem.forms.EnergyForms`; kept: `fem.factorisation.KeptFactor`; snes_set:
            `fem.factorisation.SnesSet`; stop: `fem.stopping.StoppingTest`; tangents:
            `fem.tangent.TangentSolves`; refactorisation: `fem.factorisation.Refactorisation`;
            state: `fem.state.EquilibriumState`.
    """

    def __init__(self, forms, kept, snes_set, stop, tangents, refactorisation, state):
        self.forms, self.kept, self.snes_set, self.stop = forms, kept, snes_set, stop
        self.tangents, self.refactorisation, self.state = tangents, refactorisation, state

    def can_predict(self, p) -> bool:
        """p differs from the equilibrium's (a solved one: not a rest state whose goals are
        not the rest) and a factorisation (or dx/dp) is at hand, or
        quasi-Newton would make one at the equilibrium first anyway (then it is made for the
        prediction and serves both)."""
        st = self.state
        quasi_newton = st.method == "qn" and st.xtol >= st.policy.qn_min_xtol
        return bool(np.any(p != st.p) and np.isfinite(st.solved_xtol) and (
            self.kept.ready or self.tangents.has_sensitivity or quasi_newton))

    def first_order(self, p, follow: bool = False):
        """The first-order state x(p0) + dx/dp (p - p0) (a new PETSc vector, mm), or None
        when it inverts an element, there is no factorisation yet, or p is p0. ``follow``:
        where it inverts an element, the state `follow` reaches instead; the kept
        factorisation, of K at p0, is then refactorised at the next solve's start.
        Collective."""
        if not self.can_predict(p):
            return None
        st = self.state
        try:
            # nonlinear goals: the tissue's response to the exact goals at p (one solve
            # pair, not the free S dp): a rigid-motion plan's full trial at paper size, 2.7°
            # to 5° of rotation, then failed from S dp after 20 s (class3-asym, GN step 1)
            step = self.tangents.step(p - st.p, None if self.forms.linear else
                                      self.forms.goal_load(st.p, st.u_eq, p))
        except SolverError:
            return None
        try:
            x = self.admissible(st.u_eq, step)
            if x is None and follow:
                x = self.follow(st.p, st.u_eq, step, p)
                self.kept.request_refactor(x is not None)
            return x
        finally:
            step.destroy()

    def follow(self, p0, x0: PETSc.Vec, step: PETSc.Vec, p, iterations: int | None = None,
               substep_mm: float | None = None):
        """A state near the equilibrium at p (a new PETSc vector, mm), by continuation from
        the state x0 at p0 along the straight path, with ``step`` = dx/dp (p - p0) its
        first-order step, on the kept factorisation (nothing assembled or factorised). The
        substeps are equal, the fewest whose first-order step moves no vertex more than
        ``substep_mm`` along any axis; the first starts from the first-order state, every
        later one from the secant extrapolation x_j + h/h_prev (x_j - x_(j-1)) of the last
        two states, which follows the path's curvature; each start is relaxed by ``iterations``
        quasi-Newton steps (`relax`), the L-BFGS pairs carried from substep to substep. A
        secant start that inverts an element is replaced by the first-order one; where that
        inverts too, the substep is halved; below `SolverPolicy.min_substep` of the way:
        None. ``iterations`` and ``substep_mm`` default to the policy's path settings. The
        relax iterations (and a factorisation, if there was none) are added to the current
        stats. Collective."""
        pol = self.state.policy
        iterations = pol.path_iterations if iterations is None else iterations
        substep_mm = pol.path_substep_mm if substep_mm is None else substep_mm
        p0, p = np.asarray(p0, dtype=float), np.asarray(p, dtype=float)
        stats = self.state.stats   # relax() keeps its own
        h = 1.0 / max(1, int(np.ceil(step.norm(PETSc.NormType.INFINITY) / substep_mm)))
        x, prev, t, h_prev, substeps = x0.copy(), None, 0.0, 0.0, 0   # t: the way done
        found = False
        try:
            while t < 1.0:
                h = min(h, 1.0 - t)
                start = None
                if prev is not None:   # secant
                    start = self._offset(x, x, prev, h / h_prev)
                if start is None:   # first-order
                    start = self._offset(x, step, None, h)
                if start is None:
                    if h < pol.min_substep:
                        log.info("no path to p = %s: every start from %.3g of the way inverts "
                                 "an element", np.round(p, 3).tolist(), t)
                        return None
                    h /= 2
                    continue
                if prev is not None:
                    prev.destroy()
                prev, x, h_prev = x, start, h
                t = 1.0 if t + h > 1.0 - 1e-12 else t + h
                st = self.relax(p0 + t * (p - p0), x, iterations, resume=substeps > 0)
                stats.iterations += st.iterations
                stats.factorisations += st.factorisations
                substeps += 1
            found = True
            return x
        finally:
            self.state.stats = stats
            for v in (prev, None if found else x):
                if v is not None:
                    v.destroy()

    def _offset(self, x, a, b, c: float):
        """x + c (a - b) (b None: x + c a) as a new vector, or None where it inverts an
        element (`admissible`)."""
        d = a.copy()
        if b is not None:
            d.axpy(-1.0, b)
        d.scale(c)
        try:
            return self.admissible(x, d)
        finally:
            d.destroy()

    def admissible(self, x0: PETSc.Vec, step: PETSc.Vec):
        """x0 + step (a new PETSc vector, mm), or None where it inverts an element. The
        state u is left at the equilibrium. Collective."""
        x = x0.copy()
        x.axpy(1.0, step)
        if not self.forms.sound(x):
            x.destroy()
            x = None
        self.forms.set_state(self.state.u_eq)
        return x

    def relax(self, p, x: PETSc.Vec, iterations: int, resume: bool = False) -> SolveStats:
        """At most ``iterations`` quasi-Newton (L-BFGS) steps towards the equilibrium at p
        (Np,) from x (updated in place, mm), on the kept factorisation: nothing is assembled
        or factorised; each step is one triangular solve pair and two residuals (its
        critical-point line search, `NonlinearSolver.critical_step`). Stops early where
        L-BFGS stalls (`SolverPolicy.stall_ratio`); steps that end with a larger residual
        norm than x had, or with an inverted element, are undone. For cheap corrections of
        a prediction; the scene's equilibrium (p, u) is unchanged. x must not invert an
        element. ``resume``: keep the L-BFGS pairs of the previous relax, if no solve came
        between (a continuation along a path: pairs y = F(x + s) - F(x) do not depend on p,
        the glued penalty being quadratic, and recent ones hold the curvature near x; a
        sliding penalty's turns with
        n(p), by the few degrees of a substep). Collective."""
        st = self.state
        p = self.forms.set_params(p)
        st.stats = stats = SolveStats()
        t0 = time.perf_counter()
        if not self.kept.ready:   # no factorisation yet: one at the equilibrium
            self.refactorisation.at_equilibrium()
        # residual tolerance relative to the start's residual
        self.stop.start(st.xtol, st.settings.frtol, st.settings.atol, stats.residual_history)
        snes = self.snes_set.relax(iterations, resume)
        x0 = x.copy()
        try:
            self.stop.run(snes, x)
            stats.iterations = snes.getIterationNumber()
            if not self.forms.sound(x) or self.stop.norms[-1] > self.stop.norms[0]:
                x0.copy(x)   # steps that end unsound or with a larger residual: keep x
        finally:
            x0.destroy()
            self.forms.set_params(st.p)
            self.forms.set_state(st.u_eq)
        stats.total = time.perf_counter() - t0
        return stats
