"""Quasi-static equilibrium x(p) = argmin E_NH(x) + k/2 |x_A - x̂_A(p)|², solved with PETSc SNES.

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
quasi-Newton solve first bisects the step in p (`QN_BISECTIONS`), then hands over to
Newton; when a Newton solve fails (indefinite K, KSP or line-search failure) a diagonal
shift is added and raised; when that fails too, the step in p is bisected (continuation).
`Equilibrium` keeps K and its factorisation/preconditioner (``self.ksp``) for adjoint and
sensitivity solves.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dataclasses
import logging
import time

import dolfinx
import numpy as np
import ufl

from fem import compat
from fem.domain import Domain
from fem.limits import COMPRESSION_WARN, FRTOL_FLOOR, OPTIONS, check
from fem.material import NeoHookean
from meshes.errors import InputError, SolverError

log = logging.getLogger(__name__)

#: Linear solver presets (PETSc options under the object's prefix); override on the command line.
PRESETS = {
    "direct": {"ksp_type": "cg", "ksp_rtol": 1e-8, "ksp_max_it": 100,
               "ksp_norm_type": "unpreconditioned", "pc_type": "cholesky",
               "pc_factor_mat_solver_type": "mumps", "mat_mumps_icntl_13": 1,
               "mat_mumps_icntl_24": 1},  # inertia (negative pivots) in parallel
    "cholmod": {"ksp_type": "cg", "ksp_rtol": 1e-8, "ksp_max_it": 100,
                "ksp_norm_type": "unpreconditioned", "pc_type": "cholesky",
                "pc_factor_mat_solver_type": "cholmod"},
    "gamg": {"ksp_type": "cg", "ksp_rtol": 1e-8, "ksp_max_it": 1000, "pc_type": "gamg",
             "pc_gamg_type": "agg", "pc_gamg_agg_nsmooths": 1, "mg_levels_ksp_type": "chebyshev",
             "mg_levels_pc_type": "jacobi", "mg_levels_ksp_chebyshev_esteig_steps": 20,
             "ksp_norm_type": "unpreconditioned"},
}
#: Nonlinear methods (SNES options). ``qn``: L-BFGS whose initial inverse Hessian is the kept
#: factorisation of K (scale type "jacobian"), refactorised only when a solve converges slowly;
#: ``newton``: Newton with a factorisation every step (quadratic convergence).
METHODS = {
    "qn": {"snes_type": "qn", "snes_qn_type": "lbfgs", "snes_qn_scale_type": "jacobian",
           "snes_qn_m": 10, "snes_qn_restart_type": "none", "snes_linesearch_type": "basic"},
    "newton": {"snes_type": "newtonls"},
}
#: Per-method defaults of xtol (mm), max_it and lag_its (see `Equilibrium`).
METHOD_DEFAULTS = {"qn": dict(xtol=0.005, max_it=40, lag_its=30),
                   "newton": dict(xtol=0.1, max_it=25, lag_its=0)}
#: Below this xtol (mm) quasi-Newton's linear rate (~10 iterations a decade) loses to Newton's
#: quadratic one: such solves use Newton.
QN_MIN_XTOL = 1e-4
#: Quasi-Newton has stalled when the residual norm fell by less than STALL_RATIO over the last
#: STALL_ITS iterations (healthy: ~10x per 10); then K is refactorised at the current iterate
#: and L-BFGS restarts from there, up to QN_REFRESHES times, before Newton takes over.
STALL_ITS, STALL_RATIO, QN_REFRESHES = 5, 0.5, 3
#: Largest linear rate quasi-Newton's stopping test assumes (`Equilibrium._error_per_step`).
RATE_MAX = 0.9
#: Quasi-Newton's line search (`Equilibrium._critical_step`) halves a trial step that inverts
#: an element at most this many times; then SNES takes the step and a NaN residual fails it.
MAX_HALVINGS = 20
#: MUMPS errors (INFOG(1)) of a too small workspace, and how often ICNTL(14) is doubled.
MUMPS_WORKSPACE_ERRORS, MUMPS_WORKSPACE_RETRIES = {-8, -9, -11, -12, -14, -15, -17, -20}, 4
#: A solve meets its first QN_BISECTIONS quasi-Newton failures by bisecting the step in p
#: (continuation on the cheap solver); later ones hand over to Newton. At paper size a 20 mm
#: advance from rest was solved in 73 s this way; Newton after the first failure ran > 300 s.
QN_BISECTIONS = 3
#: Refreshes allowed in a quick solve (a line-search trial that can be shortened instead).
QUICK_REFRESHES = 1
#: A tangent (adjoint, sensitivity) solve that needs more CG iterations than this with the
#: kept factorisation has the next one refactorise at the equilibrium.
TANGENT_LAG_ITS = 5
#: A quasi-Newton solve told that tangent solves follow (``solve(tangent=True)``), past
#: `TANGENT_LAG_ITS` iterations (its factorisation would not serve them) and within this
#: many xtol of convergence (its error estimate, `_error_per_step`), refactorises once at
#: its iterate: its last iterations and the tangent solves then use a factorisation near
#: the equilibrium instead of the tangent solves making one. Paper size, from rest (plain:
#: forward 11.0 s, adjoint 3.4 s): 10 xtol 12.8 + 1.0 s (4 CG iterations), 30 xtol 11.8 +
#: 1.6 s (8), 100 xtol 11.5 + 1.8 s (10), 300 xtol: refreshed after 7 iterations, too far
#: away (6 more, and the adjoint refactorised: 10.7 + 3.4 s).
TANGENT_REFRESH_XTOLS = 30.0
#: Path following (`Equilibrium.follow`): substeps whose first-order step moves no vertex
#: more than PATH_SUBSTEP_MM (mm), each relaxed by PATH_ITERATIONS quasi-Newton steps; where
#: every start of a substep shorter than MIN_SUBSTEP of the way inverts an element, it gives
#: up. A solve whose first-order start inverts an element starts from there: 20 mm advance
#: and 6 mm lateral shift from rest, class3-asym (BENCHMARKS.md, stress): coarse 2.3 ->
#: 0.85 s, paper 68.6 -> 29.4 s (3 factorisations instead of 8, no continuation).
PATH_SUBSTEP_MM, PATH_ITERATIONS, MIN_SUBSTEP = 4.0, 6, 1.0 / 64
#: Default penalty stiffness k per unit active area, kPa/mm (= mN/mm^3).
DEFAULT_PENALTY = 5.0e4
#: An equilibrium whose active vertices stay farther than this from their goals (mm) is
#: reported: the tissue resists the treatment (or k is too soft).
GOAL_TOLERANCE_MM = 0.05
#: Farther than this (mm), the state is not the treatment's equilibrium but crushed tissue
#: holding the bone back: it counts as a failed solve (continuation, then `SolverError`).
GOAL_FAILURE_MM = 1.0


@dataclasses.dataclass
class SolveStats:
    """What one equilibrium solve did. Times in seconds."""

    newton_iterations: int = 0
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
    warnings: list = dataclasses.field(default_factory=list)   # goal error, compression


class LinearGoals:
    """Goal displacements linear in p: ``g = B p`` for blendshapes B (n_local_blocks * 3,
    Np), mm per unit (paper eq. 1). The interface `Equilibrium` takes: ``n_params``,
    ``linear``, ``goal(p)`` (n_local_blocks * 3,) and ``jacobian(p)`` (its B)."""

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


class _ApplyOther:
    """Python PC context that applies another, already built PC."""

    def __init__(self, pc):
        self.pc = pc

    def apply(self, pc, x, y):
        self.pc.apply(x, y)


class Equilibrium:
    """Owns forms, PETSc objects and the current equilibrium of one scene.

    Args:
        domain: the distributed anatomy.
        goals: the goal displacement g(p) of the active vertices: `LinearGoals` (or its
            blendshape matrix (n_local_blocks * 3, Np), ghosts included), or a map with the
            same interface (e.g. `inverse.treatment.GoalMap`); zero off the active facets.
        active_tags: facet tags held to their goals by the penalty.
        material: Neo-Hookean soft tissue.
        penalty: k, kPa/mm, weight of the active-vertex penalty per unit area.
        solver: a key of `PRESETS`; any PETSc option can be overridden with
            ``-<prefix>ksp_type ...`` on the command line or in ``options``.
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
    """

    def __init__(self, domain: Domain, goals, active_tags,
                 material: NeoHookean = NeoHookean(), penalty: float = DEFAULT_PENALTY,
                 solver: str = "direct", options: dict | None = None,
                 prefix: str = "orthodiff_fwd_", method: str = "qn",
                 xtol: float | None = None, frtol: float = 1e-2, atol: float = 1e-10,
                 max_it: int | None = None, shift_max: float = 1e4, shift_retry: float = 1.0,
                 lag_its: int | None = None, quadrature_degree: int = 2,
                 volume_quadrature_degree: int | None = None):
        if not prefix:
            raise ValueError("an options prefix is required")
        if solver not in PRESETS:
            raise InputError(f"unknown solver preset {solver!r}; choose one of {list(PRESETS)}")
        if method not in METHODS:
            raise InputError(f"unknown method {method!r}; choose one of {list(METHODS)}")
        penalty = check("penalty", penalty)
        t0 = time.perf_counter()
        self.domain, self.material, self.penalty = domain, material, penalty
        given = dict(xtol=xtol, max_it=max_it, lag_its=lag_its)
        for key, default in METHOD_DEFAULTS[method].items():
            value = default if given[key] is None else given[key]
            setattr(self, key, check(key, value) if key in OPTIONS else value)
        self.method, self.frtol, self.atol = method, frtol, atol
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
        # owned vertices held to a goal (checked after every solve)
        self._active = np.zeros(domain.n_owned, dtype=bool)
        blocks = domain.facet_blocks(active_tags)
        self._active[blocks[blocks < domain.n_owned]] = True
        v, du = ufl.TestFunction(V), ufl.TrialFunction(V)
        F = ufl.Identity(3) + ufl.grad(self.u)
        ds = domain.ds()(tuple(active_tags), metadata={"quadrature_degree": quadrature_degree})
        gap = self.u - self.goal
        # material and penalty are constants, not numbers: the forms compile once for all
        mu, lmbda, k = (dolfinx.fem.Constant(domain.mesh, PETSc.ScalarType(v))
                        for v in (material.mu, material.lmbda, penalty))
        qd = 2 * (domain.degree - 1) if volume_quadrature_degree is None else \
            volume_quadrature_degree
        dx = ufl.dx(domain=domain.mesh, metadata={"quadrature_degree": qd})
        energy = (material.energy_density(F, mu, lmbda) * dx
                  + 0.5 * k * ufl.inner(gap, gap) * ds)
        residual = ufl.derivative(energy, self.u, v)
        jacobian = ufl.derivative(residual, self.u, du)
        coupling = ufl.derivative(residual, self.goal, du)  # df/dg, constant
        self.forms = {k: compat.form(f) for k, f in dict(
            energy=energy, residual=residual, jacobian=jacobian, coupling=coupling).items()}
        self.bcs = domain.dirichlet_bcs()
        self.A = compat.create_matrix(self.forms["jacobian"])
        self.A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self.A.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)
        self.b = compat.create_vector(self.forms["residual"])
        self._set_near_nullspace()
        G = compat.create_matrix(self.forms["coupling"])
        compat.assemble_matrix(G, self.forms["coupling"])
        G.assemble()
        self.dfdg = G
        self._dfdp = [G.createVecLeft() for _ in range(self.n_params)]
        self._dfdp_at = None   # the p of self._dfdp
        self.shift_max, self.shift_retry = shift_max, shift_retry
        self._shift, self._diag_scale, self._stats = 0.0, None, SolveStats()
        self._step_shift = 0.0   # the shift of the last Newton step's matrix
        self.ksp = self._make_snes(prefix, solver, options or {})
        self._f_ref = None
        self._refactor = False
        self._obj_x = self._uvec.duplicate()  # the point of the last energy evaluation
        self._obj_val = None                 # its energy (None: not valid)
        self._w, self._r = self._uvec.duplicate(), self.b.duplicate()   # line-search trial
        self._direction = np.inf             # inf-norm of the last search direction, mm
        self._fnorms = []                    # residual norms of this SNES solve
        self._refresh = None                 # why it stopped to refactorise: stalled, tangent
        self._tangent_refresh = False        # armed by solve(tangent=True), see _converged
        self._relaxing = False               # self._qn_snes is relax()'s, pairs kept
        self._last_its = 0                   # iterations of the last SNES solve
        self._pc_ready = False               # the SNES PC holds a factorisation of some K
        self._stale_pc = False               # ... which slowed the last tangent solve
        self._pc_at_eq = False               # ... of K at the equilibrium, unshifted
        self.p = np.zeros(self.n_params)  # parameters of the current equilibrium
        # the xtol it was solved to, mm: rest is exact where the goals at p = 0 are the rest
        # (else, e.g. a mandible held in an occlusion, rest is no equilibrium: inf)
        moved = np.abs(g0).max(initial=0.0)
        self.solved_xtol = 0.0 if domain.comm.allreduce(moved, op=MPI.MAX) == 0 else np.inf
        self.u_eq = self._uvec.copy()       # its displacement; warm start of the next solve
        self.K = self.A.duplicate()          # K at the equilibrium, assembled on demand
        self._K_ready = False
        self._sens = None                    # cached dx/dp columns at the equilibrium
        self.tangent_ksp = self._make_tangent_ksp(prefix)
        # det F at the vertices of each cell (constant on P1 cells, so its centroid)
        pts = np.array([[0.25] * 3] if domain.degree == 1 else
                       [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.25] * 3], dtype=float)
        self._det_F = compat.eval_expression(ufl.det(F), pts, domain.mesh)
        self.setup_time = time.perf_counter() - t0

    # ------------------------------------------------------------------ setup helpers
    @property
    def dfdp(self) -> list:
        """df/dp at the equilibrium's p: Np PETSc vectors (df/dg) dg/dp_i, mN per unit,
        recomputed when p has changed (and g is not linear). Active and Dirichlet vertices
        are disjoint (checked by `Anatomy.validate`), so Dirichlet rows are zero."""
        if self._dfdp_at is None or not (self.goals.linear
                                         or np.array_equal(self._dfdp_at, self.p)):
            J = self.goals.jacobian(self.p)
            g = compat.petsc_vec(self.goal).duplicate()
            for i, y in enumerate(self._dfdp):
                with g.localForm() as gl:
                    gl.array[:] = J[:, i]
                self.dfdg.mult(g, y)
            g.destroy()
            self._dfdp_at = self.p.copy()
        return self._dfdp

    def _set_near_nullspace(self):
        """Rigid-body modes (3 translations, 3 rotations) for GAMG."""
        X = self.domain.X
        n_owned = self.domain.n_owned
        vecs = [self.b.duplicate() for _ in range(6)]
        x = X[:n_owned]
        fields = [np.tile(e, (n_owned, 1)) for e in np.eye(3)]
        fields += [np.stack([-x[:, 1], x[:, 0], 0 * x[:, 0]], 1),
                   np.stack([0 * x[:, 0], -x[:, 2], x[:, 1]], 1),
                   np.stack([x[:, 2], 0 * x[:, 0], -x[:, 0]], 1)]
        for vec, f in zip(vecs, fields):
            vec.setArray(f.ravel())
        dolfinx.la.orthonormalize(vecs)
        ns = PETSc.NullSpace().create(vectors=vecs, comm=self.domain.comm)
        self.A.setNearNullSpace(ns)

    def _make_snes(self, prefix: str, solver: str, options: dict):
        """Newton's SNES, which owns the KSP (factorisation) that every solve shares; preset
        options under ``prefix`` (the command line wins)."""
        self._prefix = prefix
        self._search = {"snes_linesearch_type": "bt", "snes_linesearch_max_it": 40,
                        "snes_max_linear_solve_fail": 1}
        settings = {**METHODS["newton"], **self._search, **PRESETS[solver], **options}
        self._newton_snes = self._build_snes(settings, METHOD_DEFAULTS["newton"]["max_it"]
                                             if self.method != "newton" else self.max_it)
        self._qn_snes = None
        ksp = self._newton_snes.getKSP()
        ksp.setOperators(self.A)
        pc = ksp.getPC()
        self._check_inertia = pc.getType() == "cholesky" and \
            pc.getFactorSolverType() == "mumps"
        if self._check_inertia:
            opts = PETSc.Options()
            self._icntl = {int(k.rsplit("_", 1)[1]): opts.getInt(prefix + k, int(v))
                           for k, v in settings.items() if k.startswith("mat_mumps_icntl_")}
            self._new_mumps_factor(pc)
        self.solver_name = solver
        return ksp

    def _new_mumps_factor(self, pc):
        """A new MUMPS factor in ``pc`` with our ICNTL settings (MUMPS reads them at
        factorisation time, after the options database lost them: they are set here)."""
        pc.setFactorSetUpSolverType()
        factor = pc.getFactorMatrix()
        for k, v in self._icntl.items():
            factor.setMumpsIcntl(k, v)

    def _build_snes(self, settings: dict, max_it: int, ksp=None):
        """A SNES with our callbacks and line search checks, configured from ``settings``
        (PETSc options under the prefix; the command line wins), which are removed from the
        global database afterwards. ``ksp``: share this KSP and its factorisation, as set
        up (its options are not read again)."""
        opts = PETSc.Options()
        snes = PETSc.SNES().create(self.domain.comm)
        snes.setOptionsPrefix(self._prefix)
        mine = [k for k in settings if not opts.hasName(self._prefix + k)]
        for k in mine:
            opts[self._prefix + k] = settings[k]
        # late-bound callbacks: a test may replace a method on the instance
        snes.setFunction(lambda s, x, b: self._residual(s, x, b), self.b)
        snes.setJacobian(lambda s, x, A, P: self._jacobian(s, x, A, P), self.A)
        snes.setObjective(lambda s, x: self._objective(s, x))
        snes.setConvergenceTest(self._converged)
        snes.setTolerances(max_it=max_it)
        snes.setFromOptions()
        snes.setLineSearchPreCheck(self._critical_step if snes.getType() == "qn"
                                   else self._precheck)
        if ksp is not None:   # after setFromOptions: re-reading options would reset MUMPS
            snes.setKSP(ksp)
        for k in mine:
            opts.delValue(self._prefix + k)
        return snes

    def _method_snes(self):
        """The SNES for the next solve: Newton when asked for, or when xtol is below
        `QN_MIN_XTOL`. PETSc 3.18's SNESQN keeps its L-BFGS pairs from one solve to the
        next (pairs across different goals: wrong curvature), so quasi-Newton gets a fresh
        one on the shared KSP each time (a few ms)."""
        if self.method == "newton" or self.xtol < QN_MIN_XTOL:
            return self._newton_snes
        return self._fresh_qn_snes(self.max_it)

    def _fresh_qn_snes(self, max_it: int):
        """A new quasi-Newton SNES on the shared KSP (the previous one destroyed)."""
        self._drop_qn_snes()
        self._relaxing = False   # set by relax() on its own
        self._qn_snes = self._build_snes({**self._search, **METHODS["qn"]}, max_it, self.ksp)
        return self._qn_snes

    def _make_tangent_ksp(self, prefix: str):
        """CG on K at the equilibrium, preconditioned by the kept factorisation (or GAMG
        hierarchy) of the forward solves; `solve_tangent` decides when to rebuild it."""
        ksp = PETSc.KSP().create(self.domain.comm)
        ksp.setOptionsPrefix(prefix + "tangent_")
        ksp.setType("cg")
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        ksp.setTolerances(rtol=1e-11, atol=1e-30, max_it=200)
        ksp.setOperators(self.K)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(_ApplyOther(self.ksp.getPC()))
        ksp.setFromOptions()
        return ksp

    def _drop_qn_snes(self):
        """Destroy the last quasi-Newton SNES; first hand it a KSP of its own: destroying a
        SNES resets its KSP, which would throw away the shared factorisation."""
        if self._qn_snes is not None:
            self._qn_snes.setKSP(PETSc.KSP().create(self.domain.comm))
            self._qn_snes.destroy()
            self._qn_snes = None

    # ------------------------------------------------------------------ SNES callbacks
    def _set_state(self, x):
        x.copy(self._uvec)
        self._uvec.ghostUpdate(PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)

    def min_det_F(self) -> float:
        """Smallest det F of the current displacement over all cells (collective): P1 F is
        constant per cell; for P2, det F at the cell's vertices and centroid."""
        det = self._det_F()
        local = det.min() if det.size else np.inf
        return self.domain.comm.allreduce(local, op=MPI.MIN)

    def _finite(self, x) -> bool:
        """x has no NaN or inf on any rank. Collective."""
        return self.domain.comm.allreduce(bool(np.all(np.isfinite(x.array_r))), op=MPI.LAND)

    def _sound(self, x) -> bool:
        """The state x is finite and inverts no element; u is left at x. Collective."""
        self._set_state(x)
        return self._finite(x) and self.min_det_F() > 0

    def _objective(self, snes, x):
        """Energy at x, mJ; +inf where any cell is inverted (ln det F is NaN at a P1 cell's
        single quadrature point; P2 is also checked at the vertices). The line search asks
        again for the point it accepted last: that value is remembered."""
        if self._obj_val is not None and self._obj_x.equal(x):
            return self._obj_val
        t = time.perf_counter()
        self._set_state(x)
        val = self.domain.comm.allreduce(
            dolfinx.fem.assemble_scalar(self.forms["energy"]), op=MPI.SUM)
        if not np.isfinite(val) or (self.domain.degree > 1 and not self.min_det_F() > 0):
            val = np.inf
        x.copy(self._obj_x)
        self._obj_val = val
        self._stats.assemble += time.perf_counter() - t
        return val

    def _precheck(self, x, y, *args):
        """Remember the search direction's size (inf-norm, mm) for the convergence test."""
        self._direction = y.norm(PETSc.NormType.INFINITY)
        return False

    def _critical_step(self, x, y, *args):
        """Quasi-Newton's line search, run as the pre-check of SNES's "basic" one, which then
        takes the step x - y: y is scaled to the critical point of the energy along it, by
        one secant step on s(λ) = F(x - λy)·y between λ = 0 and a trial λ = t, the full
        step halved until it inverts no element; the secant root is taken up to 2t, where
        it is checked too. On an energy with L-BFGS's full step this cut paper-size
        iterations 24 -> 16 against a backtracking search (BENCHMARKS.md). One residual
        per iteration besides SNES's own; a step that still inverts an element fails the
        solve (a NaN residual), which falls back as any failure does."""
        self._precheck(x, y)
        s0 = self.b.dot(y)   # the SNES function vector holds F(x)
        t = 1.0
        for _ in range(MAX_HALVINGS):
            s1 = self._slope(x, y, t)
            if s1 is not None:
                break
            t /= 2
        lam = t
        if s1 is not None and s0 > 0 and s0 - s1 > 0:
            lam = min(t * s0 / (s0 - s1), 2 * t)
            if lam > t and not self._sound(self._trial_point(x, y, lam)):
                lam = t
        y.scale(lam)
        return True

    def _trial_point(self, x, y, lam: float) -> PETSc.Vec:
        """x - λy in the line search's work vector."""
        x.copy(self._w)
        self._w.axpy(-lam, y)
        return self._w

    def _slope(self, x, y, lam: float):
        """F(x - λy)·y (mN·mm), or None where x - λy inverts an element (P1: the residual is
        NaN; P2 is also checked at the vertices). Collective."""
        self._residual(None, self._trial_point(x, y, lam), self._r)
        val = self._r.dot(y)   # the same on every rank (a global dot)
        ok = np.isfinite(val) and (self.domain.degree == 1 or self.min_det_F() > 0)
        return val if ok else None

    def _residual(self, snes, x, b):
        t = time.perf_counter()
        self._set_state(x)
        with b.localForm() as bl:
            bl.set(0.0)
        compat.assemble_vector(b, self.forms["residual"])
        b.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        compat.set_bc(b, self.bcs, x, -1.0)
        self._stats.assemble += time.perf_counter() - t

    def _jacobian(self, snes, x, A, P):
        """Assemble K at x plus the current diagonal shift. With a direct LDL^T solver the
        inertia is checked right after factorisation, and the shift raised until K is PD.
        Quasi-Newton keeps the last factorisation (nothing assembled) while it serves: it
        was not shifted and the last solve needed at most ``lag_its`` iterations."""
        if (snes is not None and snes.getType() == "qn" and self._pc_ready
                and not self._refactor and self._shift == 0 and self._step_shift == 0
                and self._last_its <= self.lag_its):
            self._stats.lagged += 1
            return
        t = time.perf_counter()
        # K at the equilibrium: assembled once, copied (MatCopy into a matrix never
        # assembled leaves it flagged unassembled: the first one is assembled)
        if x is self.u_eq and A.assembled:
            self._assemble_K()
            self.K.copy(A, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        else:
            self._set_state(x)
            self._assemble_jacobian(A)
        if self._diag_scale is None:   # typical elastic diagonal, for shift sizes
            d = A.getDiagonal()
            med = np.median(d.array_r) if d.getLocalSize() else 0.0
            self._diag_scale = self.domain.comm.allreduce(med, op=MPI.MAX)
            d.destroy()
        self._stats.assemble += time.perf_counter() - t
        if self._shift > 0:
            A.shift(self._shift)
        self._step_shift = self._shift
        pc = self.ksp.getPC()
        reuse = (self.method == "newton" and self.lag_its > 0 and self._pc_ready
                 and not self._refactor and self._shift == 0
                 and self.ksp.getIterationNumber() <= self.lag_its)
        pc.setReusePreconditioner(reuse)   # lagging: CG on the new K, the old factor as PC
        self._pc_ready, self._refactor = True, False
        if reuse:
            self._stats.lagged += 1
            return
        self._stats.factorisations += 1
        self._stale_pc = self._pc_at_eq = False
        if pc.getType() != "cholesky":
            return
        while True:   # factorise; shift until PD (MUMPS: inertia; CHOLMOD: failed Cholesky)
            t = time.perf_counter()
            self.ksp.setOperators(A)
            try:
                pc.setUp()
                n_neg = self._inertia(pc, A) if self._check_inertia else 0
            except PETSc.Error:
                n_neg = -1
            self._stats.factor += time.perf_counter() - t
            if n_neg == 0:
                break
            if self._shift >= self.shift_max * self._diag_scale:
                break   # give up on PD; the line search and the caller decide
            new = max(4 * self._shift, 1e-2 * self._diag_scale)
            A.shift(new - self._shift)
            self._shift = new
            self._stats.shifts.append(new)
            log.debug("%d negative pivots: diagonal shift %.3g", n_neg, new)
        self._step_shift = self._shift
        # let the shift decay once a step is accepted with a PD matrix
        self._shift = 0.0 if self._shift < 0.04 * self._diag_scale else self._shift / 4

    def _inertia(self, pc, A) -> int:
        """Negative pivots of MUMPS's LDLᵀ factor of A, or -1 when the factorisation failed.
        PETSc 3.18 does not raise on a failed MUMPS factorisation: it leaves INFOG(1) < 0 and
        skips every later numeric factorisation of that factor, so a failed one is replaced
        by a new factor (a new analysis). Where the workspace was too small (delayed pivots
        filled beyond the analysis's estimate; on 2 ranks this varies from run to run),
        ICNTL(14) is doubled and A factorised again."""
        for attempt in range(MUMPS_WORKSPACE_RETRIES + 1):
            F = pc.getFactorMatrix()
            err = F.getMumpsInfog(1)
            if err >= 0:
                return F.getInertia()[0]
            workspace = err in MUMPS_WORKSPACE_ERRORS and attempt < MUMPS_WORKSPACE_RETRIES
            if workspace:
                self._icntl[14] = 2 * max(F.getMumpsIcntl(14), 10)
            pc.reset()
            self.ksp.setOperators(A)
            self._new_mumps_factor(pc)
            if not workspace:
                break
            log.info("MUMPS workspace too small (INFOG(1) = %d): factorising again with "
                     "ICNTL(14) = %d %%", err, self._icntl[14])
            pc.setUp()
        log.warning("MUMPS factorisation failed (INFOG(1) = %d)", err)
        return -1

    def _assemble_jacobian(self, M):
        """M = K at the current state u, Dirichlet rows/columns identity."""
        M.zeroEntries()
        compat.assemble_matrix(M, self.forms["jacobian"], self.bcs, 1.0)
        M.assemble()

    def _load(self, dp) -> PETSc.Vec:
        """df/dp · dp (Np,) as a new PETSc vector, mN."""
        out = self.u_eq.duplicate()
        out.set(0.0)
        out.maxpy(np.asarray(dp, dtype=float), self.dfdp)
        return out

    def _converged(self, snes, it, norms):
        xnorm, ynorm, fnorm = norms
        self._stats.residual_history.append(fnorm)
        if it == 0:
            self._fnorms = []
        self._fnorms.append(fnorm)
        if not np.isfinite(fnorm):
            return PETSc.SNES.ConvergedReason.DIVERGED_FNORM_NAN
        if fnorm <= self.atol:
            return PETSc.SNES.ConvergedReason.CONVERGED_FNORM_ABS
        if it == 0:
            self._f0 = fnorm if self._f_ref is None else self._f_ref
            self._x_prev = snes.getSolution().copy()
            return 0
        x = snes.getSolution()
        self._x_prev.axpy(-1.0, x)
        step = self._x_prev.norm(PETSc.NormType.INFINITY)
        x.copy(self._x_prev)
        if snes.getType() == "qn":   # a short step AND a short search direction, both
            # scaled to the error they leave at quasi-Newton's observed linear rate
            step, full = max(step, self._direction) * self._error_per_step(it), True
        else:   # a small step proves convergence only if it was a full Newton step (no shift)
            full = self._step_shift == 0
        if step <= self.xtol and fnorm <= self.frtol * self._f0 and full:
            return PETSc.SNES.ConvergedReason.CONVERGED_SNORM_RELATIVE
        if snes.getType() == "qn" and self._tangent_refresh and it > TANGENT_LAG_ITS and \
                step <= TANGENT_REFRESH_XTOLS * self.xtol:
            self._tangent_refresh, self._refresh = False, "tangent"
            return PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT
        if snes.getType() == "qn" and it >= STALL_ITS and \
                fnorm > STALL_RATIO * self._fnorms[it - STALL_ITS]:
            self._refresh = "stalled"
            return PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT
        if it >= snes.getTolerances()[3]:
            return PETSc.SNES.ConvergedReason.DIVERGED_MAX_IT
        return 0

    def _error_per_step(self, it: int) -> float:
        """max(1, ρ/(1-ρ)): at a linear rate ρ (the residual's over the last two iterations,
        the first, load-solving one left out, capped at `RATE_MAX`) the error left after a
        step of length s is about s ρ/(1-ρ). Slow rates (a factorisation far from here)
        thus stop later; healthy ones (ρ ≤ 1/2) as the step alone says."""
        if it < 3:
            return 1.0
        rate = min(np.sqrt(self._fnorms[it] / self._fnorms[it - 2]), RATE_MAX)
        return max(1.0, rate / (1.0 - rate))

    # ------------------------------------------------------------------ solves
    def set_params(self, p) -> np.ndarray:
        """Validate p (Np,) and set the goal field g = B p."""
        p = np.asarray(p, dtype=float).reshape(-1)
        if p.shape != (self.n_params,):
            raise InputError(f"expected {self.n_params} parameters, got {p.size}")
        if not np.all(np.isfinite(p)):
            raise InputError(f"parameters must be finite, got {p.tolist()}")
        self.goal.x.array[:] = self.goals.goal(p)
        self._obj_val = None   # the energy depends on the goal
        return p

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
        (`TANGENT_REFRESH_XTOLS`), and they reuse that factorisation.

        ``start``: a state to start from instead of a prediction (e.g. the explorer's
        first-order state from its p0, which costs no tangent solve), where it inverts no
        element; it is not changed. With ``predict``, the solve starts from the first-order
        prediction ``x(p0) + dx/dp (p - p0)`` (one solve with the kept factorisation, made
        first at the equilibrium if there is none yet; free when the sensitivities are
        cached) when it inverts no element; where it does (and the solve is not quick),
        from the state `follow` reaches along the path, with K refactorised there. A
        quasi-Newton failure bisects the step in p (continuation, up to `QN_BISECTIONS`
        times), then Newton takes over;
        ``max_bisections`` bounds all bisections. Returns `SolveStats`; raises `SolverError`
        when even continuation fails, leaving the last good equilibrium.
        """
        p = np.asarray(p, dtype=float).reshape(-1)
        self.set_params(p)  # validates
        max_bisections = check("max_bisections", max_bisections)
        self._stats = SolveStats()
        self._relaxing = False   # relax() pairs do not outlive a solve
        quick = quick and self.method != "newton"
        if quick:
            max_bisections = 0
        if np.array_equal(p, self.p) and self.xtol >= self.solved_xtol:   # already there
            self._set_state(self.u_eq)
            return self._stats
        t0 = time.perf_counter()
        if start is not None:   # a copy of it where it is sound
            start = start.copy()
            if not self._sound(start):
                start.destroy()
                start = None
            self._set_state(self.u_eq)
        if start is None:
            start = self.first_order(p, follow=not quick) if predict else None
        if quick and start is None and predict and self._can_predict(p):
            self.set_params(self.p)   # the scene stays at its equilibrium
            self._set_state(self.u_eq)
            raise SolverError(f"the first-order prediction at p = {np.round(p, 4).tolist()} "
                              "inverts an element: no quick solve is tried")
        p_done, p_start = self.p.copy(), self.p.copy()
        u_good = self.u_eq.copy()   # self.u may have been changed by the caller
        self._set_state(start or u_good)
        if start is not None:
            start.destroy()
        todo = [p]
        depth = 0
        while todo:
            p_next = todo[-1]
            self._tangent_refresh = tangent and len(todo) == 1   # at p itself only
            try:
                self._newton(p_next, p_done, quick, qn_only=quick or depth < QN_BISECTIONS)
            except SolverError:
                self._set_state(u_good)
                depth += 1
                if depth > max_bisections:   # keep the largest step reached
                    self._commit(p_done, t0, moved=not np.array_equal(p_done, p_start))
                    u_good.destroy()
                    raise SolverError(
                        f"equilibrium failed at p = {np.round(p_next, 4).tolist()} even after "
                        f"{max_bisections} bisections; the largest step reached is p = "
                        f"{np.round(p_done, 4).tolist()}, where the scene is left") from None
                todo.append(0.5 * (p_done + p_next))
                self._stats.continuation_steps += 1
                log.info("continuation: bisecting to p = %s", todo[-1])
                continue
            todo.pop()
            p_done = p_next
            self._uvec.copy(u_good)
        u_good.destroy()
        return self._commit(p_done, t0)

    def _commit(self, p, t0, moved: bool = True) -> SolveStats:
        """Make the current state u the equilibrium at p; finish the stats; report a goal
        the tissue did not let the bone reach. ``moved=False`` (a failed solve that made no
        step): the equilibrium, its accuracy, K and dx/dp there are kept."""
        self.set_params(p)
        self.p = p.copy()
        self._uvec.copy(self.u_eq)
        if moved:
            self.solved_xtol = self.xtol
            self._invalidate()
            self._pc_at_eq = False
        st = self._stats
        st.goal_error, st.min_det_F = self.active_goal_error(), self.min_det_F()
        if st.goal_error > GOAL_TOLERANCE_MM:
            st.warnings.append(
                f"active vertices end {st.goal_error:.3f} mm from their goals (> "
                f"{GOAL_TOLERANCE_MM:g} mm) at p = {np.round(p, 3).tolist()}: the tissue resists "
                f"(min det F = {st.min_det_F:.2g}) or the penalty k is too soft")
        if st.min_det_F < COMPRESSION_WARN:
            st.warnings.append(
                f"tissue compressed to {100 * st.min_det_F:.0f} % of its volume (min det F "
                f"{st.min_det_F:.2f} < {COMPRESSION_WARN:g}): the treatment is beyond what the "
                "soft tissue plausibly follows")
        if self.domain.comm.rank == 0:
            for w in st.warnings:
                log.warning(w)
        st.total = time.perf_counter() - t0
        st.linear_solve = max(st.total - st.assemble, 0.0)
        self._stats = SolveStats()   # later tangent work must not change what was returned
        return st

    def _newton(self, p, p_from, quick: bool = False, qn_only: bool = False):
        """One SNES solve at p from the equilibrium at p_from (or a prediction of it). When
        quasi-Newton fails and ``qn_only``, `SolverError` (the caller bisects the step);
        else Newton goes on from its iterate where that is sound (finite, nothing inverted,
        bone not held back), else from the same start; when Newton fails, the diagonal
        shift is raised and it resumes. The residual tolerance is relative to the
        load of the step, |df/dp (p - p_from)|, not to the (maybe predicted) start, and at
        least `fem.limits.FRTOL_FLOOR` of the goals' whole load |df/dg g(p)| (a tiny step
        cannot ask for a residual below roundoff); with no load (a refinement) only the step
        counts."""
        self.set_params(p)
        self._shift = 0.0
        load = self._load(p - p_from)
        total = load.duplicate()
        self.dfdg.mult(compat.petsc_vec(self.goal), total)
        # no load: refining the current equilibrium to a tighter xtol, where only steps count
        self._f_ref = max(load.norm(), FRTOL_FLOOR / self.frtol * total.norm()) or np.inf
        load.destroy()
        total.destroy()
        self._uvec.copy(self._x)
        start = self._x.copy()
        try:
            self._iterate(p, start, quick, qn_only)
        finally:
            start.destroy()
            self._shift, self._tangent_refresh = 0.0, False

    def _iterate(self, p, start, quick: bool, qn_only: bool):
        """The SNES solves of `_newton`, from ``start`` (in ``self._x``); raises
        `SolverError` when Newton fails even with the largest retry shift, or when
        quasi-Newton fails and ``qn_only``. ``quick``: one stall refresh only."""
        snes = self._method_snes()
        shift = 0.0   # the Jacobian callback lets self._shift decay; this one only grows
        refreshes = 0
        while True:
            self._refresh = None
            snes.solve(None, self._x)
            reason = snes.getConvergedReason()
            self._last_its = snes.getIterationNumber()
            self._stats.newton_iterations += self._last_its
            self._stats.linear_iterations += snes.getLinearSolveIterations()
            self._set_state(self._x)
            crushed = False
            if reason > 0 and self._finite(self._x):
                gap = self.active_goal_error()
                if gap <= GOAL_FAILURE_MM:
                    return
                crushed = True
                if snes is self._newton_snes:
                    raise SolverError(f"at p = {np.round(p, 4).tolist()} the bone stays "
                                      f"{gap:.1f} mm from its goal (tissue crushed, min det F "
                                      f"= {self.min_det_F():.1e})")
            self._refactor = True
            why = self._refresh
            if snes is not self._newton_snes and (why == "tangent" or why == "stalled" and
                                                  refreshes < (QUICK_REFRESHES if quick
                                                               else QN_REFRESHES)):
                refreshes += why == "stalled"   # K at the current iterate, fresh pairs, go on
                log.info("qn %s after %d iterations: refactorising there", why, self._last_its)
                snes = self._method_snes()
                continue
            if snes is not self._newton_snes and qn_only:
                raise SolverError(f"quasi-Newton failed (SNES reason {reason}) at p = {p}")
            if snes is not self._newton_snes:   # Newton from quasi-Newton's iterate if sound
                sound = not crushed and self._sound(self._x)
                log.info("%s: SNES reason %d after %d iterations%s: Newton takes over from %s",
                         snes.getType(), reason, self._last_its,
                         " (tissue crushed)" if crushed else "",
                         "there" if sound else "the start")
                snes = self._newton_snes
                if not sound:
                    start.copy(self._x)
                continue
            if shift >= self.shift_retry * self._diag_scale:   # continuation takes over
                raise SolverError(f"Newton failed (SNES reason {reason}) at p = {p}")
            shift = self._shift = max(100 * shift, 1e-2 * self._diag_scale)
            self._stats.shifts.append(shift)
            log.info("SNES reason %d after %d iterations: diagonal shift %.3g", reason,
                     self._last_its, shift)

    # ------------------------------------------------------------------ linearisation at x(p)
    def _invalidate(self):
        self._K_ready = False
        for v in self._sens or []:
            v.destroy()
        self._sens = None

    def _assemble_K(self):
        if self._K_ready:
            return
        self._set_state(self.u_eq)
        self._assemble_jacobian(self.K)
        self._K_ready = True

    def solve_tangent(self, rhs: PETSc.Vec, out: PETSc.Vec) -> int:
        """out = K⁻¹ rhs, K = df/du at the current equilibrium (collective; Dirichlet rows
        are identity). CG preconditioned by the kept factorisation; it is rebuilt at the
        equilibrium when the previous tangent solve needed more than `TANGENT_LAG_ITS`
        iterations with it, when the last forward solve did (quasi-Newton from a
        factorisation far from here: at medium size CG then took 63 iterations, 3x a
        factorisation; ``solve(tangent=True)`` avoids that), or when CG fails; it then also
        serves the next solves as quasi-Newton's start. Returns the CG iteration count."""
        self._assemble_K()
        ksp = self.tangent_ksp
        far = not self._pc_at_eq and self._last_its > TANGENT_LAG_ITS
        for attempt in range(2):
            if attempt or not self._pc_ready or self._stale_pc or far:
                self._factorise_at_equilibrium()
            ksp.setType("cg" if attempt == 0 else "gmres")  # GMRES if K is indefinite
            ksp.solve(rhs, out)
            if ksp.getConvergedReason() > 0:
                if attempt:
                    ksp.setType("cg")
                self._stale_pc = ksp.getIterationNumber() > TANGENT_LAG_ITS
                return ksp.getIterationNumber()
        raise SolverError(f"tangent solve with K at p = {np.round(self.p, 4).tolist()} failed "
                          f"(KSP reason {self.tangent_ksp.getConvergedReason()}): K is "
                          "singular or indefinite at this equilibrium")

    def _factorise_at_equilibrium(self):
        """Rebuild the kept factorisation (or preconditioner) with K at the equilibrium (a
        diagonal shift only where K is not positive definite there); K is assembled once."""
        self._refactor = True
        self._jacobian(self._newton_snes, self.u_eq, self.A, self.A)
        self.ksp.setOperators(self.A)
        self.ksp.getPC().setUp()
        self._set_state(self.u_eq)
        self._pc_at_eq = self._step_shift == 0

    def sensitivity(self) -> list:
        """dx/dp at the equilibrium: Np PETSc vectors ``s_i = -K⁻¹ df/dp_i`` (mm per unit),
        computed on first use and cached until the equilibrium changes. With a direct
        solver, one factorisation of K at the equilibrium and one block solve of all Np
        columns (MUMPS: ~ the cost of one column); else Np tangent solves."""
        if self._sens is None:
            self._sens = self._block_sensitivity() or [self.tangent_step(e)
                                                       for e in np.eye(self.n_params)]
        return self._sens

    def _block_sensitivity(self):
        """dx/dp as one MatMatSolve with the factor of K at the equilibrium, or None (not a
        Cholesky preset, no block solve in its package, or K is not positive definite
        there)."""
        pc = self.ksp.getPC()
        if pc.getType() != "cholesky" or self.n_params == 0:
            return None
        if not self._pc_at_eq:
            self._factorise_at_equilibrium()
            if not self._pc_at_eq:   # shifted: the tangent solves handle it
                return None
        n, N = self.u_eq.getLocalSize(), self.u_eq.getSize()
        rhs = PETSc.Mat().createDense([(n, N), (None, self.n_params)], comm=self.domain.comm)
        rhs.setUp()
        rhs.getDenseArray()[:] = -np.stack([g.array_r for g in self.dfdp], axis=1)
        rhs.assemble()
        sol = rhs.duplicate()
        out = []
        try:
            pc.getFactorMatrix().matSolve(rhs, sol)
            cols = sol.getDenseArray()
            for i in range(self.n_params):
                out.append(self.u_eq.duplicate())
                out[-1].array[:] = cols[:, i]
        except PETSc.Error:   # a factorisation package without block solves
            out = None
        finally:
            for m in (rhs, sol):
                m.destroy()
        return out

    @property
    def has_sensitivity(self) -> bool:
        """dx/dp is cached for the current equilibrium (direct mode costs nothing more)."""
        return self._sens is not None

    def coupling_transpose(self, lam: PETSc.Vec) -> np.ndarray:
        """(df/dp)ᵀ λ, shape (Np,) (collective). With λ = K⁻¹ ∂T/∂x, dT/dp = -(df/dp)ᵀ λ."""
        return np.array([g.dot(lam) for g in self.dfdp])

    def _goal_load(self, p) -> PETSc.Vec:
        """-(df/dg) (g(p) - g(p0)) as a new vector, mN: the exact load of moving the goals
        from the equilibrium's p0 to p (for linear goals, the tangent load -df/dp dp)."""
        dg = compat.petsc_vec(self.goal).duplicate()
        with dg.localForm() as gl:
            gl.array[:] = self.goals.goal(self.p) - self.goals.goal(p)
        out = self.dfdg.createVecLeft()
        self.dfdg.mult(dg, out)
        dg.destroy()
        return out

    def tangent_step(self, dp, rhs: PETSc.Vec | None = None) -> PETSc.Vec:
        """dx = dx/dp · dp (a new PETSc vector, mm): from the cached sensitivities, else one
        tangent solve; with no factorisation yet, one is made at the equilibrium, and a
        Cholesky factor of K there is applied once (no K assembled, no CG). ``rhs``: the
        load to respond to instead of -df/dp dp (e.g. `_goal_load`; consumed)."""
        dp = np.asarray(dp, dtype=float)
        out = self.u_eq.duplicate()
        out.set(0.0)
        if self.has_sensitivity and rhs is None:
            out.maxpy(dp, self._sens)
            return out
        rhs = self._load(-dp) if rhs is None else rhs
        if not self._pc_ready:
            self._factorise_at_equilibrium()
        pc = self.ksp.getPC()
        if self._pc_at_eq and pc.getType() == "cholesky":
            pc.apply(rhs, out)
        else:
            self.solve_tangent(rhs, out)
        rhs.destroy()
        return out

    def _can_predict(self, p) -> bool:
        """p differs from the equilibrium's (a solved one: not a rest state whose goals are
        not the rest) and a factorisation (or dx/dp) is at hand, or
        quasi-Newton would make one at the equilibrium first anyway (then it is made for the
        prediction and serves both)."""
        quasi_newton = self.method == "qn" and self.xtol >= QN_MIN_XTOL
        return bool(np.any(p != self.p) and np.isfinite(self.solved_xtol)
                    and (self._pc_ready or self.has_sensitivity or quasi_newton))

    def first_order(self, p, follow: bool = False):
        """The first-order state x(p0) + dx/dp (p - p0) (a new PETSc vector, mm), or None
        when it inverts an element, there is no factorisation yet, or p is p0. ``follow``:
        where it inverts an element, the state `follow` reaches instead; the kept
        factorisation, of K at p0, is then refactorised at the next solve's start.
        Collective."""
        if not self._can_predict(p):
            return None
        try:
            # nonlinear goals: the tissue's response to the exact goals at p (one solve
            # pair, not the free S dp): a rigid-motion plan's full trial at paper size, 2.7°
            # to 5° of rotation, then failed from S dp after 20 s (class3-asym, GN step 1)
            step = self.tangent_step(p - self.p, None if self.goals.linear
                                     else self._goal_load(p))
        except SolverError:
            return None
        try:
            x = self.admissible(self.u_eq, step)
            if x is None and follow:
                x = self.follow(self.p, self.u_eq, step, p)
                self._refactor = x is not None
            return x
        finally:
            step.destroy()

    def follow(self, p0, x0: PETSc.Vec, step: PETSc.Vec, p, iterations: int = PATH_ITERATIONS,
               substep_mm: float = PATH_SUBSTEP_MM):
        """A state near the equilibrium at p (a new PETSc vector, mm), by continuation from
        the state x0 at p0 along the straight path, with ``step`` = dx/dp (p - p0) its
        first-order step, on the kept factorisation (nothing assembled or factorised). The
        substeps are equal, the fewest whose first-order step moves no vertex more than
        ``substep_mm`` along any axis; the first starts from the first-order state, every
        later one from the secant extrapolation x_j + h/h_prev (x_j - x_(j-1)) of the last
        two states, which follows the path's curvature; each start is relaxed by ``iterations``
        quasi-Newton steps (`relax`), the L-BFGS pairs carried from substep to substep. A
        secant start that inverts an element is replaced by the first-order one; where that
        inverts too, the substep is halved; below `MIN_SUBSTEP` of the way: None. The
        relax iterations (and a factorisation, if there was none) are added to the current
        stats. Collective."""
        p0, p = np.asarray(p0, dtype=float), np.asarray(p, dtype=float)
        stats = self._stats   # relax() keeps its own
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
                    if h < MIN_SUBSTEP:
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
                stats.newton_iterations += st.newton_iterations
                stats.factorisations += st.factorisations
                substeps += 1
            found = True
            return x
        finally:
            self._stats = stats
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
        if not self._sound(x):
            x.destroy()
            x = None
        self._set_state(self.u_eq)
        return x

    def relax(self, p, x: PETSc.Vec, iterations: int, resume: bool = False) -> SolveStats:
        """At most ``iterations`` quasi-Newton (L-BFGS) steps towards the equilibrium at p
        (Np,) from x (updated in place, mm), on the kept factorisation: nothing is assembled
        or factorised; each step is one triangular solve pair and two residuals (its
        critical-point line search, `_critical_step`). Stops early where L-BFGS stalls
        (`STALL_RATIO`); steps that end with a larger residual norm than x had, or with an
        inverted element, are undone. For cheap corrections of a prediction; the scene's
        equilibrium (p, u) is unchanged. x must not invert an element. ``resume``: keep the
        L-BFGS pairs of the previous relax, if no solve came between (a continuation along
        a path: pairs y = F(x + s) - F(x) do not depend on p, the penalty being quadratic,
        and recent ones hold the curvature near x). Collective."""
        p = self.set_params(p)
        self._stats = SolveStats()
        t0 = time.perf_counter()
        if not self._pc_ready:   # no factorisation yet: one at the equilibrium
            self._factorise_at_equilibrium()
        self._f_ref = None   # residual tolerance relative to the start's residual
        if resume and self._relaxing:
            snes = self._qn_snes
            snes.setTolerances(max_it=iterations)
        else:
            snes = self._fresh_qn_snes(iterations)
            snes.setJacobian(lambda s, x, A, P: None, self.A)   # keep the factorisation
            self._relaxing = True
        x0 = x.copy()
        try:
            snes.solve(None, x)
            self._stats.newton_iterations = snes.getIterationNumber()
            if not self._sound(x) or self._fnorms[-1] > self._fnorms[0]:
                x0.copy(x)   # steps that end unsound or with a larger residual: keep x
        finally:
            x0.destroy()
            self.set_params(self.p)
            self._set_state(self.u_eq)
        self._stats.total = time.perf_counter() - t0
        return self._stats

    @property
    def stats(self) -> SolveStats:
        """What the last solve did, with the relax iterations of corrections since."""
        return self._stats

    def snapshot(self):
        """(p, u, solved_xtol) of the current equilibrium, for `restore`."""
        return self.p.copy(), self.u_eq.copy(), self.solved_xtol

    def restore(self, snap):
        """Return to an equilibrium saved by `snapshot` (no solve)."""
        p, u, self.solved_xtol = snap
        self.set_params(p)
        self.p = p.copy()
        u.copy(self.u_eq)
        self._set_state(self.u_eq)
        self._invalidate()
        self._pc_at_eq = False

    # ------------------------------------------------------------------ outputs
    def active_goal_error(self) -> float:
        """max over active vertices of |u - g|, mm (collective)."""
        gap = (self.u.x.array - self.goal.x.array).reshape(-1, 3)[:self.domain.n_owned]
        local = np.linalg.norm(gap[self._active], axis=1).max(initial=0.0)
        return self.domain.comm.allreduce(local, op=MPI.MAX)

    def destroy(self):
        self._invalidate()
        self._drop_qn_snes()
        for obj in [self._newton_snes, self.tangent_ksp, self.A, self.K, self.b,
                    self._x, self._obj_x, self._w, self._r, self.u_eq, self.dfdg, *self._dfdp]:
            obj.destroy()
