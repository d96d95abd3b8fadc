"""The nonlinear strategies: quasi-Newton on the kept factorisation with its critical-point
line search (the stopping test: `fem.stopping`), stall refreshes, bisection of the step in p,
Newton taking over (`NonlinearSolver`, a part).
"""

from __future__ import annotations

from mpi4py import MPI  # noqa: F401 (first: it loads the MPI library PETSc links)
from petsc4py import PETSc

import logging
import time

import numpy as np

from fem.limits import COMPRESSION_WARN, FRTOL_FLOOR, check
from fem.state import SolveStats
from meshes.errors import SolverError

log = logging.getLogger(__name__)


class NonlinearSolver:
    """One equilibrium solve and its fallbacks, a part: `solve` (prediction, quasi-Newton,
    bisection of the step in p, Newton with diagonal shifts), one SNES solve at a p
    (`solve_at`), quasi-Newton's line search (`critical_step`, a SNES callback), and
    `snapshot` / `restore` of the equilibrium. It alone moves the equilibrium
    (``state.p``, ``u_eq``, ``solved_xtol``).

    Args:
        forms: `fem.forms.EnergyForms`; kept: `fem.factorisation.KeptFactor`; snes_set:
            `fem.factorisation.SnesSet`; stop: `fem.stopping.StoppingTest`; linearisation:
            `fem.tangent.Linearisation`; refactorisation:
            `fem.factorisation.Refactorisation`; path: `fem.path.PathFollower`; state:
            `fem.state.EquilibriumState`.
    """

    def __init__(self, forms, kept, snes_set, stop, linearisation, refactorisation, path,
                 state):
        self.forms, self.kept, self.snes_set, self.stop = forms, kept, snes_set, stop
        self.linearisation, self.refactorisation = linearisation, refactorisation
        self.path, self.state = path, state
        self._x = forms.uvec.duplicate()  # SNES iterate; callbacks copy trial points into u
        self._w, self._r = self._x.duplicate(), forms.b.duplicate()   # line-search trial

    def critical_step(self, x, y, *args):
        """Quasi-Newton's line search, run as the pre-check of SNES's "basic" one, which then
        takes the step x - y: y is scaled to the critical point of the energy along it, by
        one secant step on s(λ) = F(x - λy)·y between λ = 0 and a trial λ = t, the full
        step halved until it inverts no element; the secant root is taken up to 2t, where
        it is checked too. On an energy with L-BFGS's full step this cut paper-size
        iterations 24 -> 16 against a backtracking search (BENCHMARKS.md). One residual
        per iteration besides SNES's own; a step that still inverts an element fails the
        solve (a NaN residual), which falls back as any failure does."""
        self.stop.precheck(x, y)
        s0 = self.forms.b.dot(y)   # the SNES function vector holds F(x)
        t = 1.0
        for _ in range(self.state.policy.max_halvings):
            s1 = self.slope(x, y, t)
            if s1 is not None:
                break
            t /= 2
        lam = t
        if s1 is not None and s0 > 0 and s0 - s1 > 0:
            lam = min(t * s0 / (s0 - s1), 2 * t)
            if lam > t and not self.forms.sound(self._trial_point(x, y, lam)):
                lam = t
        y.scale(lam)
        return True

    def newton_guard(self, x, y, *args):
        """Newton's line-search pre-check: y halved until x - y inverts no element (at most
        `SolverPolicy.max_halvings` times); PETSc's backtracking on the residual's norm then
        takes that step or shortens it. A full step stays full, so Newton stays quadratic."""
        self.stop.precheck(x, y)
        for _ in range(self.state.policy.max_halvings):
            if self.forms.sound(self._trial_point(x, y, 1.0)):
                break
            y.scale(0.5)
        return True

    def _trial_point(self, x, y, lam: float) -> PETSc.Vec:
        """x - λy in the line search's work vector."""
        x.copy(self._w)
        self._w.axpy(-lam, y)
        return self._w

    def slope(self, x, y, lam: float):
        """F(x - λy)·y (mN·mm), or None where x - λy inverts an element (P1: the residual is
        NaN; P2 is also checked at the vertices). Collective."""
        self.forms.residual(self._trial_point(x, y, lam), self._r)
        val = self._r.dot(y)   # the same on every rank (a global dot)
        ok = np.isfinite(val) and (self.forms.domain.degree == 1 or self.forms.min_det_F() > 0)
        return val if ok else None

    def solve(self, p, max_bisections: int = 6, predict: bool = True,
              quick: bool = False, tangent: bool = False,
              start: PETSc.Vec | None = None) -> SolveStats:
        """Equilibrium at parameters p (Np,), warm-started from the current one (at the
        current p, only when ``xtol`` is now tighter than `solved_xtol`: it refines).
        ``quick``: quasi-Newton only, from an admissible first-order prediction; where that
        prediction inverts an element or quasi-Newton fails, raise `SolverError` at once (no
        Newton, no continuation), e.g. for a line-search trial that may be shortened.
        ``tangent``: a few tangent solves (an adjoint gradient) follow at this equilibrium;
        a slow quasi-Newton solve then refactorises once near convergence
        (`SolverPolicy.tangent_refresh_xtols`), and they reuse that factorisation.

        ``start``: a state to start from instead of a prediction (e.g. the explorer's
        first-order state from its p0, which costs no tangent solve), where it inverts no
        element; it is not changed. With ``predict``, the solve starts from the first-order
        prediction ``x(p0) + dx/dp (p - p0)`` (one solve with the kept factorisation, made
        first at the equilibrium if there is none yet; free when the sensitivities are
        cached) when it inverts no element; where it does (and the solve is not quick),
        from the state `follow` reaches along the path, with K refactorised there. A
        quasi-Newton failure bisects the step in p (continuation, up to `SolverPolicy.qn_bisections`
        times), then Newton takes over;
        ``max_bisections`` bounds all bisections. Returns `SolveStats`; raises `SolverError`
        when even continuation fails, leaving the last good equilibrium.
        """
        st, forms = self.state, self.forms
        p = np.asarray(p, dtype=float).reshape(-1)
        forms.set_params(p)  # validates
        max_bisections = check("max_bisections", max_bisections)
        st.stats = SolveStats()
        quick = quick and st.method != "newton"
        if quick:
            max_bisections = 0
        if np.array_equal(p, st.p) and st.xtol >= st.solved_xtol:   # already there
            forms.set_state(st.u_eq)
            return st.stats
        clock = (time.perf_counter(), forms.assemble_s)
        if start is not None:   # a copy of it where it is sound
            start = start.copy()
            if not forms.sound(start):
                start.destroy()
                start = None
            forms.set_state(st.u_eq)
        if start is None:
            start = self.path.first_order(p, follow=not quick) if predict else None
        if quick and start is None and predict and self.path.can_predict(p):
            forms.set_params(st.p)   # the scene stays at its equilibrium
            forms.set_state(st.u_eq)
            raise SolverError(f"the first-order prediction at p = {np.round(p, 4).tolist()} "
                              "inverts an element: no quick solve is tried")
        p_done, p_start = st.p.copy(), st.p.copy()
        u_good = st.u_eq.copy()   # u may have been changed by the caller
        forms.set_state(start or u_good)
        if start is not None:
            start.destroy()
        todo = [p]
        depth = 0
        while todo:
            p_next = todo[-1]
            try:
                self.solve_at(p_next, p_done, quick,
                              qn_only=quick or depth < st.policy.qn_bisections,
                              tangent=tangent and len(todo) == 1)   # at p itself only
            except SolverError:
                forms.set_state(u_good)
                depth += 1
                if depth > max_bisections:   # keep the largest step reached
                    self._commit(p_done, clock, moved=not np.array_equal(p_done, p_start))
                    u_good.destroy()
                    raise SolverError(
                        f"equilibrium failed at p = {np.round(p_next, 4).tolist()} even after "
                        f"{max_bisections} bisections; the largest step reached is p = "
                        f"{np.round(p_done, 4).tolist()}, where the scene is left") from None
                todo.append(0.5 * (p_done + p_next))
                st.stats.continuation_steps += 1
                log.info("continuation: bisecting to p = %s", todo[-1])
                continue
            todo.pop()
            p_done = p_next
            forms.uvec.copy(u_good)
        u_good.destroy()
        return self._commit(p_done, clock)

    def _commit(self, p, clock, moved: bool = True) -> SolveStats:
        """Make the current state u the equilibrium at p; finish the stats (``clock``: the
        solve's start, and the forms' assembly seconds then); report a goal the tissue did
        not let the bone reach. ``moved=False`` (a failed solve that made no step): the
        equilibrium, its accuracy, K and dx/dp there are kept."""
        state, forms, policy = self.state, self.forms, self.state.policy
        forms.set_params(p)
        state.p = p.copy()
        forms.uvec.copy(state.u_eq)
        if moved:
            state.solved_xtol = state.xtol
            self.linearisation.moved()
            self.kept.moved()
        st = state.stats
        st.goal_error = forms.active_goal_error()
        st.min_det_F, where = forms.min_det_F_at()
        st.min_det_F_at = tuple(float(c) for c in where)
        if st.goal_error > policy.goal_tolerance_mm:
            st.warnings.append(
                f"active vertices end {st.goal_error:.3f} mm from their goals (> "
                f"{policy.goal_tolerance_mm:g} mm) at p = {np.round(p, 3).tolist()}: the "
                "tissue resists "
                f"(min det F = {st.min_det_F:.2g}) or the penalty k is too soft")
        if st.min_det_F < COMPRESSION_WARN:
            st.warnings.append(
                f"tissue compressed to {100 * st.min_det_F:.0f} % of its volume (min det F "
                f"{st.min_det_F:.2f} < {COMPRESSION_WARN:g}) in the cell at rest at "
                f"({', '.join(f'{c:.1f}' for c in where)}) mm: the treatment is beyond what the "
                "soft tissue plausibly follows")
        if forms.domain.comm.rank == 0:
            for w in st.warnings:
                log.warning(w)
        st.total = time.perf_counter() - clock[0]
        st.assemble = forms.assemble_s - clock[1]
        st.linear_solve = max(st.total - st.assemble, 0.0)
        state.stats = SolveStats()   # later tangent work must not change what was returned
        return st

    def solve_at(self, p, p_from, quick: bool = False, qn_only: bool = False,
                 tangent: bool = False):
        """One SNES solve at p from the equilibrium at p_from (or a prediction of it). When
        quasi-Newton fails and ``qn_only``, `SolverError` (the caller bisects the step);
        else Newton goes on from its iterate where that is sound (finite, nothing inverted,
        bone not held back), else from the same start; when Newton fails, the diagonal
        shift is raised and it resumes. The residual tolerance is relative to the
        load of the step, |df/dp (p - p_from)|, not to the (maybe predicted) start, and at
        least `fem.limits.FRTOL_FLOOR` of the goals' whole load |df/dg g(p)| (a tiny step
        cannot ask for a residual below roundoff); with no load (a refinement) only the step
        counts. ``tangent``: arm the stopping test's tangent refresh (`solve`)."""
        st, forms = self.state, self.forms
        forms.set_params(p)
        self.kept.set_shift(0.0)
        load = forms.load(p - p_from, st.p, st.u_eq)
        # |df/dg g(p)|: a scale (sliding: df/dg of the last p0). No load: refining the
        # current equilibrium to a tighter xtol, where only steps count
        frtol = st.settings.frtol
        f_ref = max(load.norm(), FRTOL_FLOOR / frtol * forms.goal_load_norm()) or np.inf
        self.stop.start(st.xtol, frtol, st.settings.atol, st.stats.residual_history, f_ref,
                        tangent)
        load.destroy()
        forms.uvec.copy(self._x)
        start = self._x.copy()
        try:
            self._iterate(p, start, quick, qn_only)
        finally:
            start.destroy()
            self.kept.set_shift(0.0)

    def _iterate(self, p, start, quick: bool, qn_only: bool):
        """The SNES solves of `solve_at`, from ``start`` (in ``self._x``); raises
        `SolverError` when Newton fails even with the largest retry shift, or when
        quasi-Newton fails and ``qn_only``. ``quick``: at most
        `SolverPolicy.quick_refreshes` stall refreshes."""
        st, forms, policy, kept = self.state, self.forms, self.state.policy, self.kept
        self.snes_set.drop_relaxation()   # a path's relax() pairs do not outlive its solve
        snes = self.refactorisation.method_snes()
        shift = 0.0   # the Jacobian callback lets kept.shift decay; this one only grows
        refreshes, f_start = 0, None   # f_start: the residual norm at the start
        while True:
            self.stop.run(snes, self._x)
            reason = snes.getConvergedReason()
            st.last_its = snes.getIterationNumber()
            st.stats.iterations += st.last_its
            st.stats.linear_iterations += snes.getLinearSolveIterations()
            forms.set_state(self._x)
            crushed = False
            if reason > 0 and forms.finite(self._x):
                gap = forms.active_goal_error()
                if gap <= policy.goal_failure_mm:
                    return
                crushed = True
                if snes is self.snes_set.newton:
                    raise SolverError(f"at p = {np.round(p, 4).tolist()} the bone stays "
                                      f"{gap:.1f} mm from its goal (tissue crushed, min det F "
                                      f"= {forms.min_det_F():.1e})")
            kept.request_refactor()
            why = self.stop.refresh
            f_start = self.stop.norms[0] if f_start is None else f_start
            if quick:
                refresh = refreshes < policy.quick_refreshes and \
                    self.stop.norms[-1] <= policy.quick_refresh_progress * f_start
            else:
                refresh = refreshes < policy.qn_refreshes
            if snes is not self.snes_set.newton and (why == "tangent" or why == "stalled" and
                                                  refresh):
                refreshes += why == "stalled"   # K at the current iterate, fresh pairs, go on
                log.info("qn %s after %d iterations: refactorising there", why, st.last_its)
                snes = self.refactorisation.method_snes()
                continue
            if snes is not self.snes_set.newton and qn_only:
                raise SolverError(f"quasi-Newton failed (SNES reason {reason}) at p = {p}")
            if snes is not self.snes_set.newton:   # Newton from quasi-Newton's iterate if sound
                sound = not crushed and forms.sound(self._x)
                log.info("%s: SNES reason %d after %d iterations%s: Newton takes over from %s",
                         snes.getType(), reason, st.last_its,
                         " (tissue crushed)" if crushed else "",
                         "there" if sound else "the start")
                snes = self.snes_set.newton
                if not sound:
                    start.copy(self._x)
                continue
            if shift >= st.settings.shift_retry * kept.diag_scale:   # continuation takes over
                raise SolverError(f"Newton failed (SNES reason {reason}) at p = {p}")
            shift = max(100 * shift, 1e-2 * kept.diag_scale)
            kept.set_shift(shift)
            st.stats.shifts.append(shift)
            log.info("SNES reason %d after %d iterations: diagonal shift %.3g", reason,
                     st.last_its, shift)

    def snapshot(self):
        """(p, u, solved_xtol) of the current equilibrium, for `restore`."""
        st = self.state
        return st.p.copy(), st.u_eq.copy(), st.solved_xtol

    def restore(self, snap):
        """Return to an equilibrium saved by `snapshot` (no solve)."""
        st = self.state
        p, u, st.solved_xtol = snap
        self.forms.set_params(p)
        st.p = p.copy()
        u.copy(st.u_eq)
        self.forms.set_state(st.u_eq)
        self.linearisation.moved()
        self.kept.moved()

    def material_changed(self):
        """The forms' material changed (`fem.forms.EnergyForms.set_material`): the state is
        an equilibrium no more (unless the exact rest), so the next solve solves; K and
        dx/dp are forgotten, and the kept factor is an iterate's."""
        st = self.state
        if st.solved_xtol > 0:
            st.solved_xtol = np.inf
        self.linearisation.moved()
        self.kept.moved()

    def destroy(self):
        for v in (self._x, self._w, self._r):
            v.destroy()
