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

The engine's rooms, one job each (mixins of `Equilibrium`, which owns the state):
`fem.forms` (the energy and its forms), `fem.factorisation` (the kept factorisation),
`fem.nonlinear` (the nonlinear strategies, `SolveStats`), `fem.path` (path following and
predictions), `fem.tangent` (tangent and sensitivity solves); and two parts that own their
state: `fem.factorisation.KeptFactor` (what the kept factorisation holds) and
`fem.stopping.StoppingTest` (every SNES solve's stopping test). Their tuned settings are one
`fem.policy.SolverPolicy`.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import contextlib
import time

import dolfinx
import numpy as np
import ufl

from fem import compat
from fem.domain import Domain
from fem.factorisation import Factorisation
from fem.forms import DEFAULT_PENALTY, Forms
from fem.limits import check
from fem.material import HOMOGENEOUS, NeoHookean, Tissues, neo_hookean
from fem.nonlinear import NonlinearSolves, SolveStats
from fem.path import PathFollowing
from fem.policy import EquilibriumOptions
from fem.stopping import StoppingTest
from fem.tangent import TangentSolves
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


class Equilibrium(Forms, Factorisation, NonlinearSolves, PathFollowing, TangentSolves):
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
        V = domain.V
        self.u = dolfinx.fem.Function(V, name="displacement")
        self._uvec = compat.petsc_vec(self.u)
        self._x = self._uvec.duplicate()  # SNES iterate; callbacks copy trial points into u
        self.goal = dolfinx.fem.Function(V, name="goal")
        self.goals = goals if hasattr(goals, "goal") else LinearGoals(goals)
        n_local = self.u.x.array.size
        self.n_params = self.goals.n_params
        g0 = np.asarray(self.goals.goal(np.zeros(self.n_params)))
        if g0.shape != (n_local,):
            raise InputError(f"goals must be ({n_local},) per p, got {g0.shape}")
        active_tags, sliding_tags = tuple(active_tags), tuple(sliding_tags)
        if not active_tags and not sliding_tags:
            raise InputError("no facets are held to a goal: give active or sliding tags")
        # owned vertices held to their goals (checked after every solve)
        self._active = np.zeros(domain.n_owned, dtype=bool)
        if active_tags:
            blocks = domain.facet_blocks(active_tags)
            self._active[blocks[blocks < domain.n_owned]] = True
        v, du = ufl.TestFunction(V), ufl.TrialFunction(V)
        F = ufl.Identity(3) + ufl.grad(self.u)
        ds = domain.ds()
        md = {"quadrature_degree": opts.quadrature_degree}
        gap = self.u - self.goal
        # material and penalty are constants (or cell fields), not numbers: the forms
        # compile once for all values
        k = dolfinx.fem.Constant(domain.mesh, PETSc.ScalarType(penalty))
        mu, lmbda = self._lame(material)
        qd = 2 * (domain.degree - 1) if opts.volume_quadrature_degree is None else \
            opts.volume_quadrature_degree
        dx = ufl.dx(domain=domain.mesh, metadata={"quadrature_degree": qd})
        contact = 0
        if active_tags:
            contact = 0.5 * k * ufl.inner(gap, gap) * ds(active_tags, metadata=md)
        self.turn = None   # R(p) on the sliding facets' cells
        self._sliding_tags = sliding_tags
        if sliding_tags:
            self._setup_turns(sliding_tags)
            n = ufl.dot(self.turn, ufl.FacetNormal(domain.mesh))
            contact = contact + 0.5 * k * ufl.inner(gap, n) ** 2 * ds(sliding_tags, metadata=md)
        energy = neo_hookean(F, mu, lmbda) * dx + contact
        residual = ufl.derivative(energy, self.u, v)
        jacobian = ufl.derivative(residual, self.u, du)
        coupling = ufl.derivative(residual, self.goal, du)  # df/dg, constant when glued
        self.ufl_forms = dict(energy=energy, residual=residual, jacobian=jacobian,
                              coupling=coupling,   # also for peers (``bench.py peers``)
                              contact=ufl.derivative(contact, self.u, v))
        if self.turn is not None:   # df/dR, for df/dp = df/dg dg/dp + df/dR dR/dp
            self.ufl_forms["turn_coupling"] = ufl.derivative(
                residual, self.turn, ufl.TrialFunction(self.turn.function_space))
            # per cell: the sliding facets' ∫ ((u - g)·n)² ds and their area (the gap check)
            w = ufl.TestFunction(compat.scalar_space(domain.mesh))
            sliding_ds = ds(sliding_tags, metadata=md)
            self.ufl_forms["normal_gap"] = ufl.inner(gap, n) ** 2 * w * sliding_ds
            self.ufl_forms["sliding_area"] = w * sliding_ds
        self.forms = {k: compat.form(f) for k, f in self.ufl_forms.items()}
        self.bcs = domain.dirichlet_bcs()
        self.A = compat.create_matrix(self.forms["jacobian"])
        self.A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self.A.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)
        self.b = compat.create_vector(self.forms["residual"])
        self._set_near_nullspace()
        self.dfdg = compat.create_matrix(self.forms["coupling"])
        self.dfdR = None if self.turn is None else \
            compat.create_matrix(self.forms["turn_coupling"])
        if self.turn is not None:
            self._sliding_area = self._cell_sums("sliding_area")
        self.set_params(np.zeros(self.n_params))
        self._assemble_couplings()
        self._dfdp = [self.dfdg.createVecLeft() for _ in range(self.n_params)]
        self._dfdp_at = None   # the p of self._dfdp
        self.shift_retry = opts.shift_retry
        self._stats = SolveStats()
        self.ksp, self.kept = self._make_snes(opts.prefix, opts.solver, opts.options)
        self.stop = StoppingTest(self._uvec, self.policy, self.kept)
        self._obj_x = self._uvec.duplicate()  # the point of the last energy evaluation
        self._obj_val = None                 # its energy (None: not valid)
        self._w, self._r = self._uvec.duplicate(), self.b.duplicate()   # line-search trial
        self._last_its = 0                   # iterations of the last SNES solve
        self.p = np.zeros(self.n_params)  # parameters of the current equilibrium
        # the xtol it was solved to, mm: rest is exact where the goals at p = 0 are the rest
        # (else, e.g. a mandible held in an occlusion, rest is no equilibrium: inf)
        moved = np.abs(g0).max(initial=0.0)
        self.solved_xtol = 0.0 if domain.comm.allreduce(moved, op=MPI.MAX) == 0 else np.inf
        self.u_eq = self._uvec.copy()       # its displacement; warm start of the next solve
        self.K = self.A.duplicate()          # K at the equilibrium, assembled on demand
        self._K_ready = False
        self._sens = None                    # cached dx/dp columns at the equilibrium
        self.tangent_ksp = self._make_tangent_ksp(opts.prefix)
        # det F at the vertices of each cell (constant on P1 cells, so its centroid)
        pts = np.array([[0.25] * 3] if domain.degree == 1 else
                       [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.25] * 3], dtype=float)
        self._det_F = compat.eval_expression(ufl.det(F), pts, domain.mesh)
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

    def _lame(self, material):
        """UFL (mu, lmbda), kPa: constants for one material, DG0 fields for `Tissues`."""
        mesh = self.domain.mesh
        if isinstance(material, NeoHookean):
            return (dolfinx.fem.Constant(mesh, PETSc.ScalarType(v))
                    for v in (material.mu, material.lmbda))
        if self.domain.tissues is None:
            raise InputError(f"anatomy {self.domain.name!r} has no tissue classes: use the "
                             "homogeneous material")
        out = []
        space = compat.scalar_space(mesh)
        dofs = space.dofmap.list.array   # one dof per local cell, in cell order
        for name, values in zip(("mu", "lambda"), material.lame(self.domain.tissues)):
            f = dolfinx.fem.Function(space, name=name)
            f.x.array[dofs] = values
            out.append(f)
        return out

    def _setup_turns(self, tags):
        """The DG0 rotation field of the sliding facets' cells, and the dof blocks of each
        tag's cells."""
        domain = self.domain
        tdim = domain.mesh.topology.dim
        self.turn = dolfinx.fem.Function(compat.tensor_space(domain.mesh), name="turn")
        f2c = domain.mesh.topology.connectivity(tdim - 1, tdim)
        cell_block = self.turn.function_space.dofmap.list.array
        self._turn_blocks = []
        for tag in tags:
            facets = domain.facet_tags.indices[domain.facet_tags.values == tag]
            cells = np.array([f2c.links(f)[0] for f in facets], dtype=np.int64)
            self._turn_blocks.append(cell_block[cells])
        self._R = np.tile(np.eye(3), (len(tags), 1, 1))

    def destroy(self):
        self._invalidate()
        for snes in (self._qn_snes, self._relax_snes):
            self._drop_snes(snes)
        for obj in [self._newton_snes, self.tangent_ksp, self.A, self.K, self.b,
                    self._x, self.stop, self._obj_x, self._w, self._r, self.u_eq,
                    self.dfdg, self.dfdR,
                    *self._dfdp]:
            if obj is not None:
                obj.destroy()
