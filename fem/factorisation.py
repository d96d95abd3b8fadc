"""The kept factorisation of K: `KeptFactor`, the part that owns it (the shared KSP, MUMPS
set-up and workspace retries, the inertia check and its diagonal shifts, its `FactorState`),
the SNES objects that share it (`SnesSet`, a part), and when K is assembled and refactorised
(`Refactorisation`, a part).
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dataclasses
import enum
import logging
import time
from typing import Callable

import numpy as np

from fem.policy import METHODS, PRESETS

log = logging.getLogger(__name__)


#: The PETSc objects' options prefixes, after the equilibrium's own (``orthodiff_fwd_``):
#: Newton's SNES and the shared KSP (its factorisation) take ``<prefix>``, each quasi-Newton
#: SNES ``<prefix>qn_``, the tangent solves' KSP ``<prefix>tangent_`` (`fem.tangent`;
#: docs/solver.md).
QN_PREFIX = "qn_"
#: MUMPS errors (INFOG(1)) of a too small workspace (ICNTL(14) is then doubled).
MUMPS_WORKSPACE_ERRORS = {-8, -9, -11, -12, -14, -15, -17, -20}


class FactorState(enum.Enum):
    """What the kept factorisation (`KeptFactor`, the shared KSP's PC) holds: a
    factorisation at an iterate (`KeptFactor.factorise`) gives ITERATE, one at the
    equilibrium (`Refactorisation.at_equilibrium`, then `KeptFactor.at_equilibrium`)
    EQUILIBRIUM or SHIFTED, a new equilibrium (`KeptFactor.moved`) turns EQUILIBRIUM into
    ITERATE, and a slow tangent solve (`fem.tangent`, `KeptFactor.slowed`) gives STALE."""

    NONE = "none"                  # nothing factorised yet
    ITERATE = "iterate"            # K at an iterate, or at a former equilibrium
    EQUILIBRIUM = "equilibrium"    # K at the current equilibrium, unshifted
    SHIFTED = "shifted"            # K at the equilibrium plus a diagonal shift (not PD there)
    STALE = "stale"                # it slowed the last tangent solve: refactorise first


class KeptFactor:
    """The factorisation every solve shares, a part that owns its state: the KSP (Newton's
    SNES's, shared by the quasi-Newton ones), its MUMPS set-up and workspace retries, the
    inertia check and the diagonal shift, and what it holds (`state`, a `FactorState`).

    Attributes:
        state: what the factor holds; ``refactor``: the next Jacobian must refactorise (a
            request: a factor of K elsewhere, e.g. after path following, or a stall).
        shift: the diagonal shift the next factorisation starts from (decays after a PD
            one), in K's units; ``step_shift``: the shift of the last factorised matrix;
            ``diag_scale``: the median diagonal of the first K (shift units).
    """

    def __init__(self, ksp, comm, settings: dict, prefix: str, shift_max: float, policy):
        self.ksp, self.comm, self.shift_max, self.policy = ksp, comm, shift_max, policy
        self.prefix = prefix
        self.state, self.refactor = FactorState.NONE, False
        self.shift, self.step_shift, self.diag_scale = 0.0, 0.0, None
        pc = ksp.getPC()
        self.check_inertia = pc.getType() == "cholesky" and pc.getFactorSolverType() == "mumps"
        self.icntl = {}
        if self.check_inertia:
            opts = PETSc.Options()
            self.icntl = {int(k.rsplit("_", 1)[1]): opts.getInt(prefix + k, int(v))
                          for k, v in settings.items() if k.startswith("mat_mumps_icntl_")}
            self.new_mumps_factor(pc)

    def set_policy(self, policy):
        """The `fem.policy.SolverPolicy` of the next operations (the equilibrium's, when it
        is replaced)."""
        self.policy = policy

    @property
    def ready(self) -> bool:
        """A factorisation of some K is held."""
        return self.state is not FactorState.NONE

    def new_mumps_factor(self, pc):
        """A new MUMPS factor in ``pc`` with our ICNTL settings (MUMPS reads them at
        factorisation time, after the options database lost them: they are set here)."""
        pc.setFactorSetUpSolverType()
        factor = pc.getFactorMatrix()
        for k, v in self.icntl.items():
            factor.setMumpsIcntl(k, v)

    def factorise(self, A, stats, reuse: bool = False):
        """Factorise A (assembled K) plus the current shift; with MUMPS's inertia check the
        shift is raised until A is positive definite (or `shift_max` x the diagonal scale).
        ``reuse``: keep the old factor as the preconditioner of the new A (Newton lagging).
        Counts in ``stats`` (`SolveStats`)."""
        if self.diag_scale is None:   # typical elastic diagonal, for shift sizes
            d = A.getDiagonal()
            med = np.median(d.array_r) if d.getLocalSize() else 0.0
            self.diag_scale = self.comm.allreduce(med, op=MPI.MAX)
            d.destroy()
        if self.shift > 0:
            A.shift(self.shift)
        self.step_shift = self.shift
        pc = self.ksp.getPC()
        pc.setReusePreconditioner(reuse)   # lagging: CG on the new K, the old factor as PC
        self.refactor = False
        if reuse:
            stats.lagged += 1
            return
        stats.factorisations += 1
        self.state = FactorState.ITERATE
        if pc.getType() != "cholesky":
            return
        while True:   # factorise; shift until PD (MUMPS: inertia; CHOLMOD: failed Cholesky)
            t = time.perf_counter()
            self.ksp.setOperators(A)
            try:
                pc.setUp()
                n_neg = self.inertia(pc, A) if self.check_inertia else 0
            except PETSc.Error:
                n_neg = -1
            stats.factor += time.perf_counter() - t
            if n_neg == 0:
                break
            if self.shift >= self.shift_max * self.diag_scale:
                break   # give up on PD; the line search and the caller decide
            new = max(4 * self.shift, 1e-2 * self.diag_scale)
            A.shift(new - self.shift)
            self.shift = new
            stats.shifts.append(new)
            log.debug("%d negative pivots: diagonal shift %.3g", n_neg, new)
        self.step_shift = self.shift
        # let the shift decay once a step is accepted with a PD matrix
        self.shift = 0.0 if self.shift < 0.04 * self.diag_scale else self.shift / 4

    def inertia(self, pc, A) -> int:
        """Negative pivots of MUMPS's LDLᵀ factor of A, or -1 when the factorisation failed.
        PETSc 3.18 does not raise on a failed MUMPS factorisation: it leaves INFOG(1) < 0 and
        skips every later numeric factorisation of that factor, so a failed one is replaced
        by a new factor (a new analysis). Where the workspace was too small (delayed pivots
        filled beyond the analysis's estimate; on 2 ranks this varies from run to run),
        ICNTL(14) is doubled and A factorised again."""
        for attempt in range(self.policy.mumps_workspace_retries + 1):
            F = pc.getFactorMatrix()
            err = F.getMumpsInfog(1)
            if err >= 0:
                return F.getInertia()[0]
            workspace = err in MUMPS_WORKSPACE_ERRORS and \
                attempt < self.policy.mumps_workspace_retries
            if workspace:
                self.icntl[14] = 2 * max(F.getMumpsIcntl(14), 10)
                self._outgrow_option(14)
            pc.reset()
            self.ksp.setOperators(A)
            self.new_mumps_factor(pc)
            if not workspace:
                break
            log.info("MUMPS workspace too small (INFOG(1) = %d): factorising again with "
                     "ICNTL(14) = %d %%", err, self.icntl[14])
            pc.setUp()
        log.warning("MUMPS factorisation failed (INFOG(1) = %d)", err)
        return -1

    def _outgrow_option(self, k: int):
        """ICNTL(k) as raised here, also where the command line set it: PETSc reads the
        options again at every new factor, and a user's too small ICNTL(14) undid each
        retry (fine, ``-orthodiff_fwd_mat_mumps_icntl_14 5``: 28 failed factorisations,
        22 GB, until stopped)."""
        opts, key = PETSc.Options(), f"{self.prefix}mat_mumps_icntl_{k}"
        if opts.hasName(key):
            opts[key] = self.icntl[k]

    def serves(self, its: int, lag_its: int, unshifted: bool = False) -> bool:
        """The factorisation held may serve the next Jacobian instead of a new one: one is
        held, no refactorisation was asked for, no shift is pending, the solve that used it
        last needed at most ``lag_its`` iterations (``its``), and, ``unshifted``, it was not
        shifted (quasi-Newton's inverse Hessian; Newton's lagged CG only preconditions)."""
        return (self.ready and not self.refactor and self.shift == 0 and its <= lag_its
                and not (unshifted and self.step_shift != 0))

    def at_equilibrium(self):
        """The factor just made was of K at the equilibrium: EQUILIBRIUM, or SHIFTED."""
        self.state = FactorState.EQUILIBRIUM if self.step_shift == 0 else FactorState.SHIFTED

    def moved(self):
        """A new equilibrium: a factorisation of K at the former one is now an iterate's."""
        if self.state is FactorState.EQUILIBRIUM:
            self.state = FactorState.ITERATE

    def slowed(self):
        """It slowed a tangent solve (more CG iterations than `tangent_lag_its`): STALE."""
        self.state = FactorState.STALE

    def request_refactor(self, refactor: bool = True):
        """Whether the next Jacobian must refactorise (e.g. the state moved along a path, or
        a solve stalled)."""
        self.refactor = refactor

    def set_shift(self, shift: float):
        """The diagonal shift (K's units) the next factorisation starts from."""
        self.shift = shift


@dataclasses.dataclass(frozen=True)
class SnesCallbacks:
    """What every SNES calls, as functions of their arguments: ``residual(x, out)``,
    ``jacobian(snes, x, A)`` (assemble and factorise, or keep the factor),
    ``converged(snes, it, norms)`` (the stopping test), ``line_search(x, y)`` (quasi-Newton's
    critical-point search, run as the pre-check of SNES's "basic" line search; scales y) and
    ``guard(x, y)`` (Newton's pre-check: y halved until x - y inverts no element)."""

    residual: Callable
    jacobian: Callable
    converged: Callable
    line_search: Callable
    guard: Callable


class SnesSet:
    """The SNES objects of one equilibrium, a part that owns them, each under its options
    prefix (docs/solver.md): Newton's (``<prefix>``), which owns the KSP that every solve
    shares (`ksp`, the kept factorisation's); the quasi-Newton one of the current solve
    (``<prefix>qn_``, fresh per solve: `method`); relaxation's (`relaxation`, its L-BFGS pairs
    kept until `drop_relaxation`). Preset options under the prefixes, the command line wins;
    ``options`` (PETSc options without a prefix) reach whichever SNES runs.

    Args:
        comm: the scene's communicator; A, b: the Jacobian matrix and function vector
            (`fem.forms.EnergyForms`); callbacks: `SnesCallbacks`; solver: a `PRESETS` key;
            newton_max_it: Newton's iteration cap.
    """

    #: Newton's line search: backtracking on the residual's norm (no objective is set: on the
    #: energy, `bt` refused steps whose energy change was its roundoff, docs/decisions.md),
    #: after `SnesCallbacks.guard`; one failed linear solve per step.
    SEARCH = {"snes_linesearch_type": "bt", "snes_linesearch_max_it": 40,
              "snes_max_linear_solve_fail": 1}

    def __init__(self, comm, A, b, callbacks: SnesCallbacks, prefix: str, solver: str,
                 options: dict, newton_max_it: int):
        self.comm, self.A, self.b, self.callbacks = comm, A, b, callbacks
        self.prefix, self.options, self.solver = prefix, dict(options), solver
        #: Newton's options as set (the kept factorisation reads its MUMPS ICNTL from them)
        self.settings = {**METHODS["newton"], **self.SEARCH, **PRESETS[solver], **options}
        self.newton = self._build(self.settings, newton_max_it)
        self.qn = None            # the current solve's quasi-Newton SNES
        self.relaxation = None    # relaxation's, its L-BFGS pairs kept until a solve iterates
        self.ksp = self.newton.getKSP()
        self.ksp.setOperators(A)

    def _build(self, settings: dict, max_it: int, ksp=None, prefix: str | None = None):
        """A SNES with the callbacks, configured from ``settings`` (PETSc options under
        ``prefix``, default the equilibrium's; the command line wins), which are removed from
        the global database afterwards. ``ksp``: share this KSP and its factorisation, as
        set up (its options are not read again)."""
        opts = PETSc.Options()
        prefix = self.prefix if prefix is None else prefix
        cb = self.callbacks
        snes = PETSc.SNES().create(self.comm)
        snes.setOptionsPrefix(prefix)
        mine = [k for k in settings if not opts.hasName(prefix + k)]
        for k in mine:
            opts[prefix + k] = settings[k]
        snes.setFunction(lambda s, x, b: cb.residual(x, b), self.b)
        snes.setJacobian(lambda s, x, A, P: cb.jacobian(s, x, A), self.A)
        snes.setConvergenceTest(lambda s, it, norms: cb.converged(s, it, norms))
        snes.setTolerances(max_it=max_it)
        snes.setFromOptions()
        snes.setLineSearchPreCheck(
            (lambda x, y, *a: cb.line_search(x, y)) if snes.getType() == "qn"
            else lambda x, y, *a: cb.guard(x, y))
        if ksp is not None:   # after setFromOptions: re-reading options would reset MUMPS
            snes.setKSP(ksp)
        for k in mine:
            opts.delValue(prefix + k)
        return snes

    def _new_qn(self, max_it: int):
        """A new quasi-Newton SNES on the shared KSP, its options under ``<prefix>qn_``
        (`QN_PREFIX`), the API's ``options`` with them."""
        return self._build({**self.SEARCH, **METHODS["qn"], **self.options}, max_it,
                           self.ksp, self.prefix + QN_PREFIX)

    def method(self, newton: bool, max_it: int):
        """The SNES for the next solve: Newton's, or a fresh quasi-Newton one (PETSc 3.18's
        SNESQN keeps its L-BFGS pairs from one solve to the next, pairs across different
        goals: wrong curvature; a new one on the shared KSP costs a few ms), the previous
        one destroyed."""
        if newton:
            return self.newton
        self._drop(self.qn)
        self.qn = self._new_qn(max_it)
        return self.qn

    def relax(self, iterations: int, resume: bool):
        """Relaxation's quasi-Newton SNES with ``iterations`` steps at most, on the kept
        factor (its Jacobian callback does nothing); ``resume``: the last one, with its
        L-BFGS pairs, where no solve iterated since."""
        if not resume or self.relaxation is None:
            self.drop_relaxation()
            self.relaxation = self._new_qn(iterations)
            self.relaxation.setJacobian(lambda s, x, A, P: None, self.A)   # keep the factor
        self.relaxation.setTolerances(max_it=iterations)
        return self.relaxation

    def drop_relaxation(self):
        """Relaxation's L-BFGS pairs do not outlive a path: a solve drops them."""
        self._drop(self.relaxation)
        self.relaxation = None

    def _drop(self, snes):
        """Destroy a quasi-Newton SNES (None: nothing); first hand it a KSP of its own:
        destroying a SNES resets its KSP, which would throw away the shared factorisation."""
        if snes is not None:
            snes.setKSP(PETSc.KSP().create(self.comm))
            snes.destroy()

    def destroy(self):
        for snes in (self.qn, self.relaxation):
            self._drop(snes)
        self.newton.destroy()


class Refactorisation:
    """When K is assembled and the kept factorisation refactorised, a part: the SNES Jacobian
    callback (`jacobian`), the choice of SNES for a solve (`method_snes`) and the
    factorisation at the equilibrium itself (`at_equilibrium`).

    Args:
        forms: `fem.forms.EnergyForms`; kept: `KeptFactor`; snes_set: `SnesSet`;
            linearisation: `fem.tangent.Linearisation` (K at the equilibrium, assembled once);
            state: `fem.state.EquilibriumState` (the equilibrium, settings, stats).
    """

    def __init__(self, forms, kept: KeptFactor, snes_set: SnesSet, linearisation, state):
        self.forms, self.kept, self.snes_set = forms, kept, snes_set
        self.linearisation, self.state = linearisation, state

    def method_snes(self):
        """The SNES for the next solve: Newton when asked for, or when xtol is below
        `SolverPolicy.qn_min_xtol`; else a fresh quasi-Newton one (`SnesSet.method`)."""
        st = self.state
        return self.snes_set.method(
            st.method == "newton" or st.xtol < st.policy.qn_min_xtol, st.settings.max_it)

    def jacobian(self, snes, x, A):
        """Assemble K at x plus the current diagonal shift. With a direct LDL^T solver the
        inertia is checked right after factorisation, and the shift raised until K is PD.
        Quasi-Newton keeps the last factorisation (nothing assembled) while it serves
        (`KeptFactor.serves`: unshifted, the last solve within ``lag_its`` iterations);
        Newton with ``lag_its`` > 0 keeps it as CG's preconditioner while it serves."""
        kept, st = self.kept, self.state
        lag_its = st.settings.lag_its
        if snes.getType() == "qn" and kept.serves(st.last_its, lag_its, True):
            st.stats.lagged += 1
            return
        # K at the equilibrium: assembled once, copied (MatCopy into a matrix never
        # assembled leaves it flagged unassembled: the first one is assembled)
        at_eq = x is st.u_eq   # K at the equilibrium: its p's normals, not the goals set
        if at_eq and A.assembled:
            self.linearisation.matrix(st.p, st.u_eq).copy(
                A, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        else:
            self.forms.jacobian(x, A, turns_at=st.p if at_eq else None)
        kept.factorise(A, st.stats, reuse=st.method == "newton" and lag_its > 0 and
                       kept.serves(self.snes_set.ksp.getIterationNumber(), lag_its))

    def at_equilibrium(self):
        """Rebuild the kept factorisation (or preconditioner) with K at the equilibrium (a
        diagonal shift only where K is not positive definite there); K is assembled once."""
        st, ksp = self.state, self.snes_set.ksp
        self.kept.request_refactor()
        self.jacobian(self.snes_set.newton, st.u_eq, self.forms.A)
        ksp.setOperators(self.forms.A)
        ksp.getPC().setUp()
        self.forms.set_state(st.u_eq)
        self.kept.at_equilibrium()
