"""Sparse Gauss-Newton planning (paper eq. 6; Zehnder, Coros & Thomaszewski 2022).

The Gauss-Newton step minimises the linearised objective subject to the linearised
equilibrium, the sparse KKT system

    [ Lᵀ W L      0        K  ] [dx]   [-Lᵀ W r]
    [ 0        αI + D      Gᵀ ] [dp] = [-α p   ]
    [ K           G        0  ] [λ ]   [ 0     ]

Eliminating dx = -K⁻¹ G dp = S dp and λ gives the reduced system with ``S_T = L S``:

    (S_Tᵀ W S_T + αI + D) dp = -(S_Tᵀ W r + α p),

which is what we solve (Np is small); D is Levenberg-Marquardt damping. Box bounds are
handled by freezing parameters at a bound whose gradient points outward and projecting trial
points. An Armijo backtracking line search on T accepts the step; every trial is a forward
solve warm-started from the first-order prediction. The plan stops before a step whose
predicted decrease is below ``ftol`` x T (the decrease it would stop after): Cranium's
LeFort I at paper, at its best (T 1.059 mm², two parameters for two landmarks' six
coordinates), spent 54 trials and 74 s failing to resolve such a step.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from fem.limits import XTOL_FLOOR_MM, check
from inverse.objective import HEAD_AXES, Objective
from inverse.treatment import FTOL
from meshes.errors import InputError, SolverError

log = logging.getLogger(__name__)

#: How the landmark Jacobian is made (`inverse.objective.Objective.jacobian`).
MODES = ("auto", "direct", "adjoint")
#: Line-search trials with a step fraction above this are solved by quasi-Newton alone: a
#: trial it cannot solve is shortened (at paper size, Newton spent 200 s on one such trial).
QUICK_ALPHA = 0.1


@dataclasses.dataclass(frozen=True)
class PlanOptions:
    """How `gauss_newton` plans; validated where made (`fem.limits`, one-line `InputError`).

    Attributes:
        max_iterations: Gauss-Newton iterations at most.
        gtol: stop when the projected gradient is below it (mm² per unit);
        ftol: ... when T decreases by less than this, relative (also the forward solves'
            accuracy, ftol x the mean landmark distance);
        xtol: ... when a step is below it (units: mm, degrees).
        mu: initial Marquardt damping, relative to diag(H).
        armijo: sufficient decrease of the line search; max_backtracks: its halvings.
        max_step: trust region, the largest step in any parameter (mm or degrees).
        mode: landmark Jacobian by "direct" sensitivities, "adjoint" solves or "auto".
    """

    max_iterations: int = 20
    gtol: float = 1e-9
    ftol: float = FTOL
    xtol: float = 1e-7
    mu: float = 1e-9
    armijo: float = 1e-4
    max_backtracks: int = 8
    max_step: float = 10.0
    mode: str = "auto"

    def __post_init__(self):
        for name in ("max_iterations", "gtol", "ftol", "mu", "armijo", "max_backtracks",
                     "max_step"):
            object.__setattr__(self, name, check(name, getattr(self, name)))
        object.__setattr__(self, "xtol", check("step_tol", self.xtol, "xtol"))
        if self.mode not in MODES:
            raise InputError(f"mode must be one of {list(MODES)}, got {self.mode!r}")


@dataclasses.dataclass
class PlanResult:
    """Outcome of `gauss_newton`. Distances in mm, times in s.

    Attributes:
        params: (Np,) final parameters; params_initial: (Np,) start.
        objective, objective_initial: T at the end and at the start (mm²).
        converged: a stopping test was met (``reason`` says which); False on the iteration
            limit or a failed line search, which is reported, never raised.
        history: one dict per iteration: iteration, T, mean_distance_mm, params, step, alpha, mu,
            iterations, forward_solves, time_s.
        gn_iterations, forward_solves: counts; timings: forward, adjoint, sensitivity,
            line_search, total.
    """

    params: np.ndarray
    params_initial: np.ndarray
    objective: float
    objective_initial: float
    converged: bool
    reason: str
    history: list
    gn_iterations: int
    forward_solves: int
    timings: dict


def check_bounds(bounds, p0) -> np.ndarray:
    """(Np, 2) bounds that contain p0, else `InputError`."""
    b = np.asarray(bounds, dtype=float)
    if b.shape != (len(p0), 2) or np.any(np.isnan(b)) or np.any(b[:, 0] > b[:, 1]):
        raise InputError(f"bounds must be ({len(p0)}, 2) with lo <= hi, got {b.tolist()}")
    out = (p0 < b[:, 0]) | (p0 > b[:, 1])
    if np.any(out):
        raise InputError(f"the start point is outside the bounds for parameter index(es) "
                         f"{np.flatnonzero(out).tolist()}: p0 = {p0[out].tolist()}, bounds "
                         f"{b[out].tolist()}")
    return b


def reduced_step(S, weights3, r, p, tikhonov, mu, free):
    """Damped Gauss-Newton step (Np,) from the reduced system; fixed parameters get 0.

    S: (3Nt, Np) landmark sensitivity; weights3: (3Nt,); r: (3Nt,) residual, mm;
    mu: Marquardt damping relative to diag(H); free: (Np,) bool.
    """
    H = S.T @ (weights3[:, None] * S) + tikhonov * np.eye(len(p))
    g = S.T @ (weights3 * r) + tikhonov * p
    Hf = H[np.ix_(free, free)]
    d = np.diag(Hf)
    Hf = Hf + mu * np.diag(d + 1e-12 * max(d.max(initial=0.0), 1e-300))
    dp = np.zeros(len(p))
    dp[free] = np.linalg.solve(Hf, -g[free])
    return dp


def predicted_decrease(S, weights3, g, tikhonov, dp) -> float:
    """The decrease of T (mm²) the Gauss-Newton model predicts for the step dp (Np,):
    -(g·dp + ½ dpᵀ (S_Tᵀ W S_T + αI) dp), g (Np,) the gradient of T (other arguments as in
    `reduced_step`)."""
    Sd = S @ dp
    return -float(g @ dp + 0.5 * (Sd @ (weights3 * Sd) + tikhonov * dp @ dp))


def gauss_newton(scene, objective: Objective, p0=None, bounds=None,
                 options: PlanOptions | None = None, callback=None, **kw) -> PlanResult:
    """Minimise ``objective`` over the scene's parameters from ``p0`` (default 0), within
    ``bounds`` (Np, 2) (default the treatment's).

    ``options``: a `PlanOptions`, or its fields as keywords ``kw`` (not both). Stops when
    the projected gradient is below ``gtol``, T decreases by less than ``ftol`` relative,
    the step is below ``xtol``, or T < 1e-14 mm². The forward solves stop at the
    equilibrium's own xtol or ``ftol`` x the mean landmark distance, whichever is smaller:
    their landmark error stays below the relative change of T the plan resolves, and a
    resumed plan follows the same path; the equilibrium's xtol is back as it was afterwards.
    ``callback(p, entry)`` is called at the start and after every accepted iteration with
    its history entry.
    """
    if options is not None and kw:
        raise InputError(f"give the plan's options once: a PlanOptions or keywords "
                         f"({sorted(kw)}), not both")
    opts = options if options is not None else PlanOptions(**kw)
    with scene.eq.keeping_xtol():
        return _gauss_newton(scene, objective, p0, bounds, opts, callback)


def _gauss_newton(scene, objective, p0, bounds, opts: PlanOptions, callback):
    t_start = time.perf_counter()
    eq = scene.eq
    xtol_forward = eq.xtol
    ftol, mu, mode = opts.ftol, opts.mu, opts.mode

    def tighten(distance_mm: float):
        """Forward solves to ftol x the mean landmark distance (or their own xtol), not
        below `fem.limits.XTOL_FLOOR_MM` (targets reached: a distance of 0)."""
        eq.set_xtol(max(min(xtol_forward, ftol * distance_mm), XTOL_FLOOR_MM))
    n_p = eq.n_params
    p = np.zeros(n_p) if p0 is None else scene.param_vector(p0)
    p_init = p.copy()
    b = check_bounds(scene.treatment.bounds if bounds is None else bounds, p)
    lo, hi = b[:, 0], b[:, 1]
    timings = dict(forward=0.0, adjoint=0.0, sensitivity=0.0, line_search=0.0)
    forward_solves = 0

    def forward(q, key, quick=False):
        nonlocal forward_solves
        t = time.perf_counter()
        try:
            st = eq.solve(q, quick=quick)
            return st.iterations
        finally:
            forward_solves += 1
            timings[key] += time.perf_counter() - t

    its = forward(p, "forward") if np.any(p != eq.p) else 0
    tighten(float(objective.distances().mean()))
    if eq.xtol < eq.solved_xtol:   # the start to the plan's accuracy
        its += forward(p, "forward")
    T = T0 = objective.value()
    w3 = objective.weights.ravel()
    history = [dict(iteration=0, T=T, mean_distance_mm=float(objective.distances().mean()),
                    params=p.copy(), step=0.0, alpha=0.0, mu=mu, iterations=its,
                    forward_solves=forward_solves, time_s=time.perf_counter() - t_start)]
    _log(history[-1])
    if callback is not None:
        callback(p.copy(), history[-1])
    converged, reason, it = False, "iteration limit", 0
    for it in range(1, opts.max_iterations + 1):
        if T < 1e-14:
            converged, reason, it = True, "objective below 1e-14 mm²", it - 1
            break
        t = time.perf_counter()
        S, used = objective.jacobian(mode)
        timings["adjoint" if used == "adjoint" else "sensitivity"] += time.perf_counter() - t
        r = objective.residual().ravel()
        g = S.T @ (w3 * r) + objective.tikhonov * p
        free = ~(((p <= lo) & (g > 0)) | ((p >= hi) & (g < 0)))
        if np.max(np.abs(g[free]), initial=0.0) <= opts.gtol:
            converged, reason, it = True, "projected gradient below gtol", it - 1
            break
        tighten(history[-1]["mean_distance_mm"])
        dp = reduced_step(S, w3, r, p, objective.tikhonov, mu, free)
        if predicted_decrease(S, w3, g, objective.tikhonov, dp) <= ftol * T:
            converged, reason, it = True, "predicted decrease below ftol", it - 1
            break
        base = eq.snapshot()
        accepted, its = False, 0
        for _ in range(6):   # raise the damping until a step is accepted
            dp *= min(1.0, opts.max_step / max(np.max(np.abs(dp)), 1e-300))  # trust region
            alpha = 1.0
            for _ in range(opts.max_backtracks + 1):
                q = np.clip(p + alpha * dp, lo, hi)
                try:   # long trials may be cut short: quasi-Newton only, no fallback
                    its += forward(q, "line_search", quick=alpha > QUICK_ALPHA)
                    T_q = objective.value()
                except SolverError as e:
                    log.info("trial p = %s failed: %s", np.round(q, 4).tolist(), e)
                    T_q = np.inf
                if T_q <= T + opts.armijo * float(g @ (q - p)):
                    accepted = True
                    break
                alpha *= 0.5
            if accepted:
                break
            eq.restore(base)
            mu = max(10 * mu, 1e-6)
            dp = reduced_step(S, w3, r, p, objective.tikhonov, mu, free)
        base[1].destroy()   # the snapshot's displacement vector
        if not accepted:
            reason = "line search failed: no decrease even with strong damping"
            it -= 1
            break
        step = float(np.max(np.abs(q - p)))
        T_prev, p = T, q
        T = T_q
        mu = max(mu / 10, 1e-9) if alpha == 1.0 else max(4 * mu, 1e-3)
        history.append(dict(iteration=it, T=T, mean_distance_mm=float(
            objective.distances().mean()), params=p.copy(), step=step, alpha=alpha, mu=mu,
            iterations=its, forward_solves=forward_solves,
            time_s=time.perf_counter() - t_start))
        _log(history[-1])
        if callback is not None:
            callback(p.copy(), history[-1])
        if T_prev - T <= ftol * T_prev:
            converged, reason = True, "relative decrease below ftol"
            break
        if step <= opts.xtol:
            converged, reason = True, "step below xtol"
            break
    timings["total"] = time.perf_counter() - t_start
    return PlanResult(p, p_init, T, T0, converged, reason, history, it, forward_solves,
                      timings)


def plan_report(scene, result: PlanResult, objective, before: dict) -> dict:
    """The JSON report of a plan (docs/planning.md): the landmark table (``objective``'s
    targets, ``before`` {name: (3,)} mm; ``along``: the head axes along which the target
    holds the landmark, over which both distances are taken; ``offset_after_mm``: where it
    ends from its target along every head axis), parameters, history, timings and the bone
    motions."""
    after = scene.landmarks(objective.names)
    axes = objective.axes   # columns: left, anterior, superior (scene frame)
    table = {}
    for n, t, held in zip(objective.names, objective.targets, objective.held):
        off = lambda x: (x - t) @ axes   # noqa: E731
        table[n] = {"target": t, "along": [a for a, h in zip(HEAD_AXES, held) if h],
                    "before": before[n], "after": after[n],
                    "distance_before_mm": float(np.linalg.norm(off(before[n])[held])),
                    "distance_after_mm": float(np.linalg.norm(off(after[n])[held])),
                    "offset_after_mm": dict(zip(HEAD_AXES, off(after[n]).tolist()))}
    mean = lambda k: sum(v[k] for v in table.values()) / len(table)  # noqa: E731
    return {
        "case": scene.case or scene.domain.name, "resolution": scene.resolution,
        "degree": scene.domain.degree,
        "n_vertices": scene.domain.n_vertices, "n_ranks": scene.domain.comm.size,
        "param_names": scene.param_names, "params_initial": result.params_initial,
        "params_optimal": result.params, "landmarks": table,
        "mean_distance_before_mm": mean("distance_before_mm"),
        "mean_distance_after_mm": mean("distance_after_mm"),
        "gn_iterations": result.gn_iterations, "forward_solves": result.forward_solves,
        "converged": result.converged, "stop_reason": result.reason,
        "history": result.history, "timings_s": result.timings,
        **scene.motion_report(),
    }


def _log(h):
    log.info("GN %2d  T = %.4e mm²  mean distance %.4f mm  step %.3g  alpha %.3g  "
             "Newton %d  %.1f s", h["iteration"], h["T"], h["mean_distance_mm"], h["step"],
             h["alpha"], h["iterations"], h["time_s"])
