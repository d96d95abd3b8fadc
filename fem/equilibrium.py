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

Robustness: Newton's line search backtracks on the energy, which is +inf where any
tetrahedron has det F <= 0; quasi-Newton's steps to the critical point along its direction,
halving a trial that inverts an element (a NaN residual). No NaN is ever taken. A step
whose first-order start inverts an element starts where `Equilibrium.follow` gets along the
path (secant continuation relaxed on the kept factorisation). A failed
quasi-Newton solve first bisects the step in p (`SolverPolicy.qn_bisections`), then hands over to
Newton; when a Newton solve fails (indefinite K, KSP or line-search failure) a diagonal
shift is added and raised; when that fails too, the step in p is bisected (continuation).
`Equilibrium` keeps K and its factorisation/preconditioner (``self.ksp``) for adjoint and
sensitivity solves.

The engine's parts, which own their state: `fem.forms.EnergyForms` (the energy, its forms and
the fields they are evaluated at, ``Equilibrium.forms``), `fem.factorisation.KeptFactor`
(what the kept factorisation holds, ``.kept``), `fem.factorisation.SnesSet` (the SNES
objects that share it, ``.snes_set``), `fem.tangent.Linearisation` (K and dx/dp at
the equilibrium, the tangent KSP, ``.linearisation``) and `fem.stopping.StoppingTest` (every
SNES solve's stopping test, ``.stop``); and its rooms, mixins of `Equilibrium`, one job each:
`fem.factorisation` (when K is assembled and refactorised), `fem.nonlinear` (the nonlinear
strategies, `SolveStats`), `fem.path` (path following and predictions), `fem.tangent`
(tangent and sensitivity solves). Their tuned settings are one `fem.policy.SolverPolicy`.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import contextlib
import time

import numpy as np

from fem.domain import Domain
from fem.factorisation import Factorisation, KeptFactor, SnesCallbacks, SnesSet
from fem.forms import DEFAULT_PENALTY, EnergyForms
from fem.limits import check
from fem.material import HOMOGENEOUS, NeoHookean, Tissues
from fem.nonlinear import NonlinearSolves, SolveStats
from fem.path import PathFollowing
from fem.policy import METHOD_DEFAULTS, EquilibriumOptions
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


class Equilibrium(Factorisation, NonlinearSolves, PathFollowing, TangentSolves):
    """Owns forms, PETSc objects and the current equilibrium of one scene.

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
        self.settings = opts = settings if settings is not None else EquilibriumOptions(**kw)
        penalty = check("penalty", penalty)
        t0 = time.perf_counter()
        self.policy = opts.policy
        self.domain, self.material, self.penalty = domain, material, penalty
        self.method, self.xtol, self.max_it, self.lag_its = (opts.method, opts.xtol, opts.max_it,
                                                             opts.lag_its)
        self.frtol, self.atol = opts.frtol, opts.atol
        self.goals = goals if hasattr(goals, "goal") else LinearGoals(goals)
        self.n_params = self.goals.n_params
        self.forms = EnergyForms(domain, self.goals, active_tags, sliding_tags, material,
                                 penalty, opts.quadrature_degree, opts.volume_quadrature_degree)
        self._x = self.forms.uvec.duplicate()  # SNES iterate; callbacks copy trial points into u
        self.shift_retry = opts.shift_retry
        self._stats = SolveStats()
        forms = self.forms   # late-bound callbacks: a test may replace a method
        self.snes_set = SnesSet(domain.comm, forms.A, forms.b, SnesCallbacks(
            residual=lambda x, b: forms.residual(x, b), energy=lambda x: forms.energy(x),
            jacobian=lambda snes, x, A: self._jacobian(snes, x, A),
            converged=lambda snes, it, norms: self.stop(snes, it, norms),
            precheck=lambda x, y: self.stop.precheck(x, y),
            line_search=lambda x, y: self._critical_step(x, y)),
            opts.prefix, opts.solver, opts.options,
            METHOD_DEFAULTS["newton"]["max_it"] if self.method != "newton" else self.max_it)
        self.kept = KeptFactor(self.snes_set.ksp, domain.comm, self.snes_set.settings, opts.prefix,
                               opts.shift_max, self.policy)
        self.stop = StoppingTest(self.forms.uvec, self.policy, self.kept)
        self._w, self._r = self._x.duplicate(), self.forms.b.duplicate()   # line-search trial
        self._last_its = 0                   # iterations of the last SNES solve
        self.p = np.zeros(self.n_params)  # parameters of the current equilibrium
        # the xtol it was solved to, mm: rest is exact where the goals at p = 0 are the rest
        # (else, e.g. a mandible held in an occlusion, rest is no equilibrium: inf)
        moved = np.abs(self.forms.goal.x.array).max(initial=0.0)
        self.solved_xtol = 0.0 if domain.comm.allreduce(moved, op=MPI.MAX) == 0 else np.inf
        self.u_eq = self.forms.uvec.copy()   # its displacement; warm start of the next solve
        self.linearisation = Linearisation(self.forms, self.kept, opts.prefix, self.policy)
        self.setup_time = time.perf_counter() - t0

    def set_xtol(self, xtol: float) -> None:
        """The step tolerance (mm) of the next solves, validated (`fem.limits`)."""
        self.xtol = check("xtol", xtol)

    @contextlib.contextmanager
    def keeping_xtol(self):
        """A block after which the step tolerance is back as it was (a plan tightens it)."""
        xtol = self.xtol
        try:
            yield
        finally:
            self.xtol = xtol

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
        for obj in [self.snes_set, self.linearisation, self._x, self.stop, self._w,
                    self._r, self.u_eq, self.forms]:
            if obj is not None:
                obj.destroy()
