"""The equilibrium solver's tuned settings, in one place, each beside its measured reason.

`SolverPolicy` is a frozen dataclass: ``Equilibrium(..., policy=dataclasses.replace(
DEFAULT_POLICY, stall_ratio=1e-3))`` changes one setting for one solver, with no module
global touched. `PRESETS` (PETSc linear-solver options), `METHODS` (SNES options) and
`METHOD_DEFAULTS` (per-method tolerances) are the option sets the policy's solver is built
with. Figures are from BENCHMARKS.md and docs/decisions.md (paper size: 45.6 k vertices).
"""

from __future__ import annotations

import dataclasses

from fem.limits import Range, check

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
#: The PETSc package (its configure name) each factorising preset needs: PyPI's PETSc has
#: no SuiteSparse, hence no CHOLMOD (`available`).
NEEDS = {"direct": "mumps", "cholmod": "suitesparse"}
#: ``amg``: no factor. Quasi-Newton's initial inverse Hessian is CG on K with the tangent's
#: GAMG (`TANGENT_GAMG`), stopped at a relative residual of 1e-2: L-BFGS needs K⁻¹ only
#: roughly. class3, 5 mm advance from rest, 2 ranks (`bench.py forward`, AMD EPYC): fine
#: 45.7 s and 3.5 GB against the factor's 50.7 s and 7.7 GB, the landmarks within 1e-4 mm;
#: paper 6.4 s and 1.0 GB against 3.5 s and 1.4 GB. rtol 1e-1: 230 iterations at fine;
#: without GAMG's threshold 55.9 s against 43.2 s (docs/decisions.md). No inertia: K must
#: stay positive definite on the way (docs/solver.md).
PRESETS["amg"] = {**PRESETS["gamg"], "ksp_rtol": 1e-2, "ksp_max_it": 200,
                  "pc_gamg_threshold": 0.02}
#: The tangent solves' own preconditioner, for scenes too large for a factorisation to serve
#: them (options under ``<prefix>tangent_``, e.g. ``-orthodiff_fwd_tangent_pc_type gamg``;
#: `fem.tangent.Linearisation.own_pc`, docs/solver.md): CG with smoothed-aggregation
#: AMG on K at the equilibrium, with its rigid-body near-nullspace. The threshold drops weak
#: couplings from the aggregation graph: CG to 1e-8 took 26 and 34 iterations at coarse and
#: medium (class3, 5 mm advance), against 53 and 60 without it.
TANGENT_GAMG = {"pc_type": "gamg", "pc_gamg_type": "agg", "pc_gamg_agg_nsmooths": 1,
                "pc_gamg_threshold": 0.02, "mg_levels_ksp_type": "chebyshev",
                "mg_levels_pc_type": "jacobi", "mg_levels_ksp_chebyshev_esteig_steps": 20}
#: Nonlinear methods (SNES options). ``qn``: L-BFGS whose initial inverse Hessian is the kept
#: factorisation of K (scale type "jacobian"), refactorised only when a solve converges slowly;
#: ``newton``: Newton with a factorisation every step (quadratic convergence).
METHODS = {
    "qn": {"snes_type": "qn", "snes_qn_type": "lbfgs", "snes_qn_scale_type": "jacobian",
           "snes_qn_m": 10, "snes_qn_restart_type": "none", "snes_linesearch_type": "basic"},
    "newton": {"snes_type": "newtonls"},
}
#: Per-method defaults of xtol (mm), max_it and lag_its (see `fem.equilibrium.Equilibrium`).
METHOD_DEFAULTS = {"qn": dict(xtol=0.005, max_it=40, lag_its=30),
                   "newton": dict(xtol=0.1, max_it=25, lag_its=0)}


def available(solver: str) -> bool:
    """Whether this PETSc has what the preset ``solver`` needs (`NEEDS`)."""
    from petsc4py import PETSc

    return solver not in NEEDS or PETSc.Sys.hasExternalPackage(NEEDS[solver])


@dataclasses.dataclass(frozen=True)
class SolverPolicy:
    """When the equilibrium solver refactorises, bisects, hands over and gives up.

    Attributes (units in the names: mm, or counts):
        qn_min_xtol: below this xtol (mm) quasi-Newton's linear rate (~10 iterations a
            decade) loses to Newton's quadratic one: such solves use Newton.
        stall_its, stall_ratio: quasi-Newton has stalled when the residual norm fell by less
            than ``stall_ratio`` over the last ``stall_its`` iterations (healthy: ~10x per
            10); then K is refactorised at the current iterate and L-BFGS restarts there,
        qn_refreshes: ... up to this many times, before Newton takes over;
        quick_refreshes: ... and this many in a quick solve (a plan's line-search trial,
            which can be shortened instead; 2: Cranium's sliding-tissue plan solved a half
            step after its second refresh, 4 forward solves instead of 5, docs/decisions.md),
        quick_refresh_progress: ... and only where the residual has fallen below this
            fraction of the quick solve's start: a stall with no progress means the trial is
            far from any state the kept K describes, and a shorter trial is cheaper than
            refactorising there (class3-asym paper plan, 2 ranks: a first full step's trial
            stalled at 0.96 of its start residual, refactorised with shifts and failed
            anyway after 13 s).
        rate_max: largest linear rate quasi-Newton's stopping test assumes (the error a
            step leaves at rate ρ is ρ/(1-ρ) of it): a factorisation from far away converged
            at ρ ≈ 0.7 and stopped 4.7e-3 mm from the equilibrium without the scaling.
        mumps_workspace_retries: MUMPS's workspace (ICNTL(14)) is doubled at most this
            often when it reports a too small one.
        max_halvings: quasi-Newton's line search halves a trial that inverts an element at
            most this often; then SNES takes the step and a NaN residual fails it.
        qn_bisections: a solve meets its first failures of quasi-Newton by bisecting the
            step in p (continuation on the cheap solver); later ones hand over to Newton. At
            paper size a 20 mm advance from rest was solved in 73 s this way; Newton after
            the first failure ran > 300 s.
        tangent_lag_its: a tangent (adjoint, sensitivity) solve that needs more CG
            iterations than this with the kept factorisation has the next one refactorise at
            the equilibrium.
        sensitivity_cg_its: dx/dp where the kept factorisation is of K at an iterate near
            the equilibrium (the solve that reached it needed at most ``tangent_lag_its``
            iterations from it) comes from CG on all Np columns at once, preconditioned by that
            factor, for at most this many iterations; then (or where the factor is farther)
            K is refactorised at the equilibrium for one block solve. Cranium's LeFort I plan
            at paper (1 rank, glued, tissues): its second and third dx/dp by block CG in 0.8
            and 1.4 s (3-7 iterations), against 3.5 and 3.6 s to refactorise; the plan 24.0 s
            against 29.9 s, the same parameters (docs/decisions.md).
        tangent_refresh_xtols: a quasi-Newton solve told that tangent solves follow, past
            ``tangent_lag_its`` iterations and within this many xtol of convergence,
            refactorises once at its iterate, so its last iterations and the tangent solves
            share a factorisation near the equilibrium. Paper size, from rest (plain: forward
            11.0 s, adjoint 3.4 s): 10 xtol 12.8 + 1.0 s, 30 xtol 11.8 + 1.6 s, 100 xtol
            11.5 + 1.8 s, 300 xtol: refreshed too far away (10.7 + 3.4 s).
        path_substep_mm, path_iterations, min_substep: path following (`follow`): substeps
            whose first-order step moves no vertex more than ``path_substep_mm``, each relaxed
            by ``path_iterations`` quasi-Newton steps; where every start of a substep shorter
            than ``min_substep`` of the way inverts an element, it gives up. A 20 mm advance
            and 6 mm lateral shift from rest, class3-asym: coarse 2.3 -> 0.85 s, paper 68.6 ->
            29.4 s (3 factorisations instead of 8); 3 mm substeps on coarse: 0.10 mm in
            0.6 s against 0.19 mm in 0.5 s for 4 mm.
        goal_tolerance_mm: an equilibrium whose active vertices stay farther than this from
            their goals is reported (the tissue resists the treatment, or k is too soft).
        goal_failure_mm: farther than this, the state is not the treatment's equilibrium but
            crushed tissue holding the bone back: it counts as a failed solve.
    """

    qn_min_xtol: float = 1e-4
    stall_its: int = 5
    stall_ratio: float = 0.5
    qn_refreshes: int = 3
    quick_refreshes: int = 2
    quick_refresh_progress: float = 0.1
    rate_max: float = 0.9
    max_halvings: int = 20
    mumps_workspace_retries: int = 4
    qn_bisections: int = 3
    tangent_lag_its: int = 5
    sensitivity_cg_its: int = 30
    tangent_refresh_xtols: float = 30.0
    path_substep_mm: float = 4.0
    path_iterations: int = 6
    min_substep: float = 1.0 / 64
    goal_tolerance_mm: float = 0.05
    goal_failure_mm: float = 1.0

    def __post_init__(self):
        """Every setting in its range (`POLICY_RANGES`, `fem.limits.check`), else
        `InputError` naming it."""
        for f in dataclasses.fields(self):
            check(f.name, getattr(self, f.name), f"SolverPolicy.{f.name}", POLICY_RANGES,
                  numbers_only=True)


#: Each `SolverPolicy` setting's range. Counts of steps that a loop needs at least once
#: (halvings, stall window, path iterations) start at 1.
POLICY_RANGES = {
    name: Range(lo, hi, integer=True) if kind == "count" else Range(lo, hi, open_lo=True)
    for name, (kind, lo, hi) in {
        "qn_min_xtol": ("above", 0.0, 1.0), "stall_its": ("count", 1, 1000),
        "stall_ratio": ("above", 0.0, 1.0), "qn_refreshes": ("count", 0, 100),
        "quick_refreshes": ("count", 0, 100), "quick_refresh_progress": ("above", 0.0, 1.0),
        "rate_max": ("above", 0.0, 0.99), "max_halvings": ("count", 1, 100),
        "mumps_workspace_retries": ("count", 0, 20), "qn_bisections": ("count", 0, 20),
        "tangent_lag_its": ("count", 0, 1000),
        "sensitivity_cg_its": ("count", 0, 1000), "tangent_refresh_xtols": ("above", 0.0, 1e6),
        "path_substep_mm": ("above", 0.0, 100.0), "path_iterations": ("count", 1, 1000),
        "min_substep": ("above", 0.0, 100.0), "goal_tolerance_mm": ("above", 0.0, 100.0),
        "goal_failure_mm": ("above", 0.0, 100.0)}.items()}

DEFAULT_POLICY = SolverPolicy()


@dataclasses.dataclass(frozen=True)
class EquilibriumOptions:
    """How `fem.equilibrium.Equilibrium` solves (its docstring says what each field does):
    frozen, and validated where made (`fem.limits`: one-line `InputError`). ``None``: the
    method's default (`METHOD_DEFAULTS`), filled in here. ``options``: PETSc options without
    a prefix, for whichever SNES runs and the shared KSP."""

    solver: str = "direct"
    options: dict = dataclasses.field(default_factory=dict)
    prefix: str = "orthodiff_fwd_"
    method: str = "qn"
    xtol: float | None = None
    frtol: float = 1e-2
    atol: float = 1e-10
    max_it: int | None = None
    shift_max: float = 1e4
    shift_retry: float = 1.0
    lag_its: int | None = None
    quadrature_degree: int = 2
    volume_quadrature_degree: int | None = None
    policy: SolverPolicy = DEFAULT_POLICY

    def __post_init__(self):
        from meshes.errors import InputError

        if not isinstance(self.prefix, str) or not self.prefix:
            raise InputError(f"an options prefix is required, got {self.prefix!r}")
        if self.solver not in PRESETS:
            raise InputError(f"unknown solver preset {self.solver!r}; choose one of "
                             f"{list(PRESETS)}")
        if not available(self.solver):
            raise InputError(f"solver preset {self.solver!r} needs PETSc with "
                             f"{NEEDS[self.solver]}, which this PETSc lacks: choose one of "
                             f"{[s for s in PRESETS if available(s)]}")
        if self.method not in METHODS:
            raise InputError(f"unknown method {self.method!r}; choose one of {list(METHODS)}")
        if not isinstance(self.options, dict):
            raise InputError(f"options must be a dict of PETSc options, got {self.options!r}")
        if not isinstance(self.policy, SolverPolicy):
            raise InputError(f"policy must be a SolverPolicy, got {self.policy!r}")
        values = {**{k: v for k, v in METHOD_DEFAULTS[self.method].items()
                     if getattr(self, k) is None}, "options": dict(self.options)}
        for key in ("xtol", "frtol", "atol", "max_it", "shift_max", "shift_retry", "lag_its",
                    "quadrature_degree"):
            values[key] = check(key, values.get(key, getattr(self, key)))
        if self.volume_quadrature_degree is not None:
            values["volume_quadrature_degree"] = check(
                "quadrature_degree", self.volume_quadrature_degree, "volume_quadrature_degree")
        for key, value in values.items():
            object.__setattr__(self, key, value)
