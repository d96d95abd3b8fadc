"""Quasi-static equilibrium, solved with PETSc SNES:
x(p) = argmin E_NH(x) + k/2 |x_A - x̂_A(p)|² + k/2 ((x_S - x̂_S(p))·n(p))².

The second penalty is the sliding contact of tissue on teeth (facets S, ``sliding_tags``):
only the normal gap is held, ``n(p) = R(p) n₀`` each facet's rest normal turned with its
segment (``goals.turns``: R is a DG0 tensor on the facets' cells, so df/dp = df/dg dg/dp +
df/dR dR/dp, both analytic); the tangential motion is free. It is bilateral: the lip may not lift
off the teeth (a closed lip at rest stays closed in a planned motion of a few mm).

The energy is UFL; residual f = dE/du, Jacobian K = df/du and the goal coupling df/dg come from
``ufl.derivative``. The goal displacement of the active bone is ``g(p)`` (`LinearGoals`: a
blendshape matrix, ``g = B p``; or any map with the same interface, such as exact rigid
motions), so ``df/dp = (df/dg) dg/dp``: df/dg is assembled once (the penalty is quadratic),
dg/dp is taken at the current equilibrium's p.

The default method is quasi-Newton (SNESQN, L-BFGS) whose initial inverse Hessian is the kept
factorisation of K: one factorisation serves many solves. Newton (SNES newtonls, a
factorisation per step) takes over when it fails.

Robustness: quasi-Newton's line search steps to the energy's critical point along its
direction, halving a trial that inverts an element (a NaN residual); Newton's halves its step
until it inverts no element, then backtracks on the residual's norm. No NaN is ever taken. A step
whose first-order start inverts an element starts where `fem.path.PathFollower.follow` gets
along the path (secant continuation relaxed on the kept factorisation). A failed
quasi-Newton solve first bisects the step in p (`SolverPolicy.qn_bisections`), then hands over to
Newton; when a Newton solve fails (indefinite K, KSP or line-search failure) a diagonal
shift is added and raised; when that fails too, the step in p is bisected (continuation).
`Equilibrium` keeps K and its factorisation/preconditioner (``self.ksp``) for adjoint and
sensitivity solves.

The engine's parts, each owning its state, built and wired by the `Equilibrium` facade:
`fem.forms.EnergyForms` (the energy, its forms and the fields they are evaluated at,
``.forms``), `fem.factorisation.KeptFactor` (what the kept factorisation holds, ``.kept``),
`fem.factorisation.SnesSet` (the SNES objects that share it, ``.snes_set``),
`fem.stopping.StoppingTest` (every SNES solve's stopping test, ``.stop``),
`fem.tangent.Linearisation` (K and dx/dp at the equilibrium, the tangent KSP,
``.linearisation``), `fem.factorisation.Refactorisation` (when K is assembled and refactorised,
``.refactorisation``), `fem.tangent.TangentSolves` (tangent and sensitivity solves,
``.tangents``), `fem.path.PathFollower` (predictions and path following, ``.path``) and
`fem.nonlinear.NonlinearSolver` (the nonlinear strategies, ``.solver``). They share one
`fem.state.EquilibriumState` (the equilibrium, the settings in force, the solve's
`SolveStats`); their tuned settings are one `fem.policy.SolverPolicy`.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import contextlib
import dataclasses
import time

import numpy as np

from fem.domain import Domain
from fem.factorisation import FactorState, KeptFactor, Refactorisation, SnesCallbacks, SnesSet
from fem.forms import DEFAULT_PENALTY, EnergyForms
from fem.limits import check
from fem.material import HOMOGENEOUS, NeoHookean, Tissues
from fem.nonlinear import NonlinearSolver
from fem.path import PathFollower
from fem.policy import METHOD_DEFAULTS, EquilibriumOptions
from fem.state import EquilibriumState, SolveStats
from fem.stopping import StoppingTest
from fem.tangent import Linearisation, TangentSolves
from meshes.errors import InputError

__all__ = ["Equilibrium", "LinearGoals", "SolveStats"]


class LinearGoals:
    """Goal displacements linear in p: ``g = B p`` for blendshapes B (n_local_blocks * 3,
    Np), mm per unit (paper eq. 1). The interface `Equilibrium` takes: ``n_params``,
    ``linear``, ``goal(p)`` (n_local_blocks * 3,) and ``jacobian(p)`` (its B); with sliding
    facets also ``turns(p, tags)`` and ``turns_jacobian(p, tags)``."""

    linear = True

    def __init__(self, B):
        self.B = np.asarray(B, dtype=float)
        if self.B.ndim != 2:
            raise InputError(f"blendshapes must be a 2-d array, got shape {self.B.shape}")
        self.n_params = self.B.shape[1]

    def goal(self, p) -> np.ndarray:
        return self.B @ p

    def jacobian(self, p) -> np.ndarray:
        return self.B

    def turns(self, p, tags) -> np.ndarray:
        """The rotation (len(tags), 3, 3) of the sliding facets with each tag at p:
        blendshapes do not say how a surface turns, so the identity."""
        return np.tile(np.eye(3), (len(tags), 1, 1))

    def turns_jacobian(self, p, tags):
        """d(turns)/dp (len(tags), Np, 3, 3), or None where they do not depend on p."""
        return None


class Equilibrium:
    """The engine of one scene, a facade over its parts (the module docstring), which it
    builds, wires and destroys; the public API.

    Args:
        domain: the distributed anatomy.
        goals: the goal displacement g(p) of the active vertices: `LinearGoals` (or its
            blendshape matrix (n_local_blocks * 3, Np), ghosts included), or a map with the
            same interface (e.g. `inverse.treatment.GoalMap`); zero off the active facets.
        active_tags: facet tags held to their goals by the penalty (glued).
        sliding_tags: facet tags held to their goals in the normal direction only (tissue
            that slides on teeth).
        material: Neo-Hookean soft tissue: one `NeoHookean` for all cells, or `Tissues`,
            one per tissue class, mixed per cell by the domain's ``tissues`` fractions.
        penalty: k, kPa/mm, weight of the active-vertex penalty per unit area.
        solver: a key of `PRESETS`; any PETSc option can be overridden on the command line
            under its object's prefix (``-<prefix>ksp_type ...``; quasi-Newton's SNES
            ``<prefix>qn_``, the tangent KSP ``<prefix>tangent_``: docs/solver.md) or, for
            whichever SNES runs and the shared KSP, in ``options`` (no prefix).
        method: a key of `METHODS`: ``qn`` (default; one factorisation serves many solves)
            or ``newton``.
        xtol: stop when a full step is below xtol (inf-norm, mm) and the residual is below
            ``frtol`` x the load of the step; or when the residual norm is below ``atol``
            (mN). Newton: a full, unshifted step; its default 0.1 mm keeps landmarks within
            1e-3 mm of a 1e-10 mm solve (BENCHMARKS.md, tolerance curve: ~1e-7 mm, Newton
            converges quadratically), and a treatment smaller than 0.1 mm, which stops
            after its first, linear step, errs ~3e-4 mm. Quasi-Newton converges linearly,
            so both its last step and its search direction must be below xtol (default
            0.005 mm: at most 3.6e-4 mm at the landmarks in the tests; 0.01 mm left
            1.8e-3 mm on a tiny mesh's return to rest).
        max_it: iterations per SNES solve (default per method, `METHOD_DEFAULTS`).
        shift_max: largest diagonal shift of the inertia check, in units of the median
            diagonal of K.
        shift_retry: after a failed SNES solve, Newton is resumed with shifts 0.01, 1, ...
            up to this (same units); then the step in p is bisected.
        lag_its: reuse of the kept factorisation. Newton: K is refactorised only when the
            previous step's CG needed more than this many iterations with the kept factor
            (or after a failure); 0 (Newton's default) refactorises every step: without the
            inertia check, lagged CG on an indefinite K made paper-size Newton take 17 steps,
            not 7. Quasi-Newton: a solve starts from the kept factorisation unless it was
            shifted or the previous solve needed more than lag_its iterations (default 30).
        policy: when to refactorise, bisect, hand over and give up (`fem.policy`).
        settings: all of the above from ``solver`` on, as one `fem.policy.EquilibriumOptions`
            (frozen, validated where made); or its fields as keywords, not both.
    """

    def __init__(self, domain: Domain, goals, active_tags, sliding_tags=(),
                 material: NeoHookean | Tissues = HOMOGENEOUS, penalty: float = DEFAULT_PENALTY,
                 settings: EquilibriumOptions | None = None, **kw):
        if settings is not None and kw:
            raise InputError(f"give the equilibrium's options once: EquilibriumOptions or "
                             f"keywords ({sorted(kw)}), not both")
        opts = settings if settings is not None else EquilibriumOptions(**kw)
        penalty = check("penalty", penalty)
        t0 = time.perf_counter()
        self.domain, self.material, self.penalty = domain, material, penalty
        self.goals = goals if hasattr(goals, "goal") else LinearGoals(goals)
        self.n_params = self.goals.n_params
        self.forms = forms = EnergyForms(domain, self.goals, active_tags, sliding_tags,
                                         material, penalty, opts.quadrature_degree,
                                         opts.volume_quadrature_degree)
        # rest is exact where the goals at p = 0 are the rest (else, e.g. a mandible held in
        # an occlusion, rest is no equilibrium: solved_xtol inf)
        moved = np.abs(forms.goal.x.array).max(initial=0.0)
        self.state = EquilibriumState(
            settings=opts, xtol=opts.xtol, p=np.zeros(self.n_params), u_eq=forms.uvec.copy(),
            solved_xtol=0.0 if domain.comm.allreduce(moved, op=MPI.MAX) == 0 else np.inf)
        # SNES callbacks, late-bound to the parts built below
        self.snes_set = SnesSet(domain.comm, forms.A, forms.b, SnesCallbacks(
            residual=lambda x, b: forms.residual(x, b),
            jacobian=lambda snes, x, A: self.refactorisation.jacobian(snes, x, A),
            converged=lambda snes, it, norms: self.stop(snes, it, norms),
            line_search=lambda x, y: self.solver.critical_step(x, y),
            guard=lambda x, y: self.solver.newton_guard(x, y)),
            opts.prefix, opts.solver, opts.options,
            METHOD_DEFAULTS["newton"]["max_it"] if opts.method != "newton" else opts.max_it)
        self.kept = KeptFactor(self.snes_set.ksp, domain.comm, self.snes_set.settings,
                               opts.prefix, opts.shift_max, opts.policy)
        self.stop = StoppingTest(forms.uvec, opts.policy, self.kept)
        self.linearisation = Linearisation(forms, self.kept, opts.prefix, opts.policy)
        self.refactorisation = Refactorisation(forms, self.kept, self.snes_set,
                                               self.linearisation, self.state)
        self.tangents = TangentSolves(forms, self.kept, self.linearisation,
                                      self.refactorisation, self.state)
        self.path = PathFollower(forms, self.kept, self.snes_set, self.stop, self.tangents,
                                 self.refactorisation, self.state)
        self.solver = NonlinearSolver(forms, self.kept, self.snes_set, self.stop,
                                      self.linearisation, self.refactorisation, self.path,
                                      self.state)
        self.setup_time = time.perf_counter() - t0

    # the settings in force (`EquilibriumState.settings`: replaced whole, validated)

    @property
    def settings(self) -> EquilibriumOptions:
        """The `fem.policy.EquilibriumOptions` in force."""
        return self.state.settings

    @property
    def policy(self):
        """The `fem.policy.SolverPolicy` in force; set: the settings with another one."""
        return self.state.policy

    @policy.setter
    def policy(self, policy):
        self.state.settings = dataclasses.replace(self.state.settings, policy=policy)
        for part in (self.kept, self.stop, self.linearisation):   # made with one
            part.set_policy(policy)

    @property
    def method(self) -> str:
        """``qn`` or ``newton``; set: the settings with the other (its iteration caps kept)."""
        return self.state.method

    @method.setter
    def method(self, method: str):
        self.state.settings = dataclasses.replace(self.state.settings, method=method)

    @property
    def max_it(self) -> int:
        """Iterations per SNES solve (`EquilibriumOptions.max_it`)."""
        return self.state.settings.max_it

    @property
    def lag_its(self) -> int:
        """Reuse of the kept factorisation (`EquilibriumOptions.lag_its`)."""
        return self.state.settings.lag_its

    @property
    def xtol(self) -> float:
        """The step tolerance of the next solves, mm."""
        return self.state.xtol

    def set_xtol(self, xtol: float) -> None:
        """The step tolerance (mm) of the next solves, validated (`fem.limits`)."""
        self.state.xtol = check("xtol", xtol)

    @contextlib.contextmanager
    def keeping_xtol(self):
        """A block after which the step tolerance is back as it was (a plan tightens it)."""
        xtol = self.state.xtol
        try:
            yield
        finally:
            self.state.xtol = xtol

    # the current equilibrium (`fem.state.EquilibriumState`)

    @property
    def p(self) -> np.ndarray:
        """(Np,) parameters of the current equilibrium."""
        return self.state.p

    @property
    def u_eq(self) -> PETSc.Vec:
        """Its displacement, mm (the warm start of the next solve)."""
        return self.state.u_eq

    @property
    def solved_xtol(self) -> float:
        """The xtol it was solved to, mm (0: an exact rest; inf: none yet)."""
        return self.state.solved_xtol

    @property
    def stats(self) -> SolveStats:
        """What the last solve did, with the relax iterations of corrections since."""
        return self.state.stats

    # solves (`fem.nonlinear.NonlinearSolver`, `fem.path.PathFollower`)

    def solve(self, p, max_bisections: int = 6, predict: bool = True, quick: bool = False,
              tangent: bool = False, start: PETSc.Vec | None = None) -> SolveStats:
        """The equilibrium at p (Np,): `fem.nonlinear.NonlinearSolver.solve`."""
        return self.solver.solve(p, max_bisections, predict, quick, tangent, start)

    def snapshot(self):
        """(p, u, solved_xtol) of the current equilibrium, for `restore`."""
        return self.solver.snapshot()

    def restore(self, snap):
        """Return to an equilibrium saved by `snapshot` (no solve)."""
        self.solver.restore(snap)

    def first_order(self, p, follow: bool = False):
        """x(p0) + dx/dp (p - p0), or None: `fem.path.PathFollower.first_order`."""
        return self.path.first_order(p, follow)

    def follow(self, p0, x0: PETSc.Vec, step: PETSc.Vec, p, iterations: int | None = None,
               substep_mm: float | None = None):
        """A state near the equilibrium at p by continuation: `fem.path.PathFollower.follow`."""
        return self.path.follow(p0, x0, step, p, iterations, substep_mm)

    def admissible(self, x0: PETSc.Vec, step: PETSc.Vec):
        """x0 + step, or None where it inverts an element (`fem.path.PathFollower`)."""
        return self.path.admissible(x0, step)

    def relax(self, p, x: PETSc.Vec, iterations: int, resume: bool = False) -> SolveStats:
        """Quasi-Newton steps on the kept factorisation: `fem.path.PathFollower.relax`."""
        return self.path.relax(p, x, iterations, resume)

    # tangent solves (`fem.tangent.TangentSolves`) and the kept factorisation

    def solve_tangent(self, rhs: PETSc.Vec, out: PETSc.Vec) -> int:
        """out = K⁻¹ rhs at the equilibrium; CG iterations (`fem.tangent.TangentSolves`)."""
        return self.tangents.solve(rhs, out)

    def sensitivity(self) -> list:
        """dx/dp at the equilibrium, Np PETSc vectors, cached (`TangentSolves.sensitivity`)."""
        return self.tangents.sensitivity()

    def material_sensitivity(self, rtol: float | None = None) -> list:
        """dx/dθ at the equilibrium: one new PETSc vector per material parameter
        (`fem.material.theta_names`), mm per unit of θ, ``-K⁻¹ df/dθ`` with the kept
        factorisation (`TangentSolves.responses`; ``rtol``: a loose relative residual
        that block CG on any iterate's factor may stop at). Collective."""
        loads = self.forms.material_loads(self.u_eq)
        try:
            return self.tangents.responses(loads, rtol)
        finally:
            for v in loads:
                v.destroy()

    def set_material(self, material):
        """The material (``material``) from now on (`fem.forms.EnergyForms.set_material`);
        the next solve finds its equilibrium (`fem.nonlinear.NonlinearSolver.
        material_changed`)."""
        self.forms.set_material(material)
        self.material = material
        self.solver.material_changed()

    def tangent_step(self, dp, rhs: PETSc.Vec | None = None) -> PETSc.Vec:
        """dx/dp · dp, a new PETSc vector, mm (`fem.tangent.TangentSolves.step`)."""
        return self.tangents.step(dp, rhs)

    @property
    def has_sensitivity(self) -> bool:
        """dx/dp is cached for the current equilibrium."""
        return self.tangents.has_sensitivity

    @property
    def own_tangent_pc(self) -> bool:
        """The tangent solves have a preconditioner of their own (`Linearisation.own_pc`)."""
        return self.linearisation.own_pc

    @property
    def tangent_ksp(self) -> PETSc.KSP:
        """The tangent solves' KSP (`Linearisation.ksp`), to read, not to change."""
        return self.linearisation.ksp

    def tangent_matrix(self) -> PETSc.Mat:
        """K = df/du at the equilibrium (N×N, kPa·mm; Dirichlet rows identity), assembled
        once per equilibrium and owned by the engine (do not destroy or change it)."""
        return self.linearisation.matrix(self.p, self.u_eq)

    def forget_sensitivities(self):
        """Drop the cached dx/dp: its next use, or `tangent_step`'s, solves."""
        self.linearisation.forget_sensitivities()

    def factorise_at_equilibrium(self):
        """Rebuild the kept factorisation with K at the equilibrium (tests, timing; the
        tangent solves do so when they need to): `Refactorisation.at_equilibrium`."""
        self.refactorisation.at_equilibrium()

    @property
    def factor(self) -> FactorState:
        """What the kept factorisation holds (`KeptFactor.state`)."""
        return self.kept.state

    @property
    def snes(self) -> dict:
        """The PETSc SNES objects, ``{"newton": ..., "qn": ...}`` (the quasi-Newton one of the
        last solve, None before one), to read their options and tolerances, not to change."""
        return {"newton": self.snes_set.newton, "qn": self.snes_set.qn}

    @property
    def ksp(self) -> PETSc.KSP:
        """The KSP every solve shares (Newton's; its PC is the kept factorisation)."""
        return self.snes_set.ksp

    @property
    def solver_name(self) -> str:
        """The linear solver preset (a `PRESETS` key)."""
        return self.snes_set.solver

    # the forms' fields and evaluations (`fem.forms.EnergyForms`), as the API gives them

    @property
    def u(self):
        """The displacement (dolfinx Function, mm) the forms are at: the equilibrium after a
        solve."""
        return self.forms.u

    @property
    def goal(self):
        """The goal field g(p) of the parameters last set (dolfinx Function, mm)."""
        return self.forms.goal

    @property
    def turn(self):
        """The sliding facets' rotations R(p) (DG0 dolfinx Function; None: nothing slides)."""
        return self.forms.turn

    @property
    def A(self) -> PETSc.Mat:
        """The SNES's Jacobian matrix (K's layout, with the rigid-body near-nullspace)."""
        return self.forms.A

    @property
    def b(self) -> PETSc.Vec:
        """The SNES's function vector."""
        return self.forms.b

    @property
    def bcs(self) -> list:
        """The Dirichlet conditions (the skull's fixed vertices)."""
        return self.forms.bcs

    @property
    def ufl_forms(self) -> dict:
        """The UFL forms by name (energy, residual, jacobian, coupling, contact, ...)."""
        return self.forms.ufl

    @property
    def dfdp(self) -> list:
        """df/dp at the equilibrium: Np PETSc vectors, mN per unit (`EnergyForms.dfdp`)."""
        return self.forms.dfdp(self.p, self.u_eq)

    def set_params(self, p) -> np.ndarray:
        """Validate p (Np,) and set the goal field g(p) (and the sliding facets' turns R(p))."""
        return self.forms.set_params(p)

    def energy(self, x: PETSc.Vec) -> float:
        """E_NH + E_A at the state x (displacement, mm), µJ; +inf where x inverts an
        element. u is left at x. Collective."""
        return self.forms.energy(x)

    def residual(self, x: PETSc.Vec, out: PETSc.Vec) -> None:
        """out = f(x) = dE/dx at the state x (mN); Dirichlet rows hold x minus its boundary
        value. u is left at x. Collective."""
        self.forms.residual(x, out)

    def jacobian(self, x: PETSc.Vec, out: PETSc.Mat) -> None:
        """out = K(x) = df/dx at the state x (mN/mm), Dirichlet rows and columns identity.
        u is left at x. Collective."""
        self.forms.jacobian(x, out)

    def load(self, dp) -> PETSc.Vec:
        """df/dp · dp (dp: (Np,)) as a new PETSc vector, mN: the load a step in p puts on
        the tissue at the current equilibrium. Collective."""
        return self.forms.load(dp, self.p, self.u_eq)

    def coupling_transpose(self, lam: PETSc.Vec) -> np.ndarray:
        """(df/dp)ᵀ λ, shape (Np,) (collective). With λ = K⁻¹ ∂T/∂x, dT/dp = -(df/dp)ᵀ λ."""
        return np.array([g.dot(lam) for g in self.dfdp])

    def min_det_F(self) -> float:
        """Smallest det F of the current displacement over all cells (collective)."""
        return self.forms.min_det_F()

    def active_goal_error(self) -> float:
        """max over active vertices of |u - g|, and over the cells on sliding facets of the
        root mean square of (u - g)·n on them, mm (collective)."""
        return self.forms.active_goal_error()

    def destroy(self):
        for obj in [self.snes_set, self.linearisation, self.solver, self.stop, self.u_eq,
                    self.forms]:
            if obj is not None:
                obj.destroy()
