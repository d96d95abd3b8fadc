"""Plans that know their uncertainty (issue 46, docs/uncertainty.md): the expected objective
under the tissue's prior,

    E[T](p) ≈ T(p) + ½ Σ_t Σ_held w_t [A S_θ Σ_θ S_θᵀ Aᵀ]_t = T(p) + ½ |B(p)|²,

T at the prior's median and the trace term of the targets' covariance along their held axes
(B: the rows of S_θ Σ_θ^½ weighted as T's residuals), minimised by Levenberg-Marquardt from
the nominal plan. T's Jacobian is exact (`inverse.objective.Objective.jacobian`); B's is
forward differences in p, one forward solve and one dx/dθ per parameter (B's own
derivative needs third derivatives of the energy).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from inverse.uncertainty import Prior, material_rows
from meshes.errors import SolverError

#: Forward-difference step of B's Jacobian, per unit of each parameter (mm or degrees):
#: B is smooth in p, and the first-order prediction reaches p + h from p in a few
#: iterations.
FD_STEP = 0.05


@dataclasses.dataclass
class RobustResult:
    """``params`` (Np,) the robust plan; ``nominal`` (Np,) the plan it started from;
    ``expected`` and ``expected_nominal``: E[T] mm² at each, with ``band`` (½|B|²) and
    ``T`` parts; ``iterations``; ``forward_solves``."""

    params: np.ndarray
    nominal: np.ndarray
    expected: dict
    expected_nominal: dict
    iterations: int
    forward_solves: int


def _band(scene, obj, prior: Prior) -> np.ndarray:
    """B (Nt·3·nθ,) at the current equilibrium. Collective."""
    (rows,) = material_rows(scene, [obj.op], rtol=None)       # (Nt, 3, nθ)
    along = np.einsum("ik,lip->lkp", obj.axes, rows)
    return (np.sqrt(obj.weights)[:, :, None] * (along @ prior.factor)).ravel()


def _parts(scene, obj, prior) -> tuple:
    """(E[T]'s parts {"T", "band", "total"} mm², B) at the current equilibrium."""
    B = _band(scene, obj, prior)
    T = obj.value()
    return {"T": T, "band": 0.5 * float(B @ B), "total": T + 0.5 * float(B @ B)}, B


def robust_plan(scene, obj, prior: Prior, p_nominal, bounds=None,
                max_iterations: int = 5, ftol: float = 1e-4) -> RobustResult:
    """Minimise E[T] from the nominal plan ``p_nominal`` within ``bounds`` (Np, 2) (default
    the treatment's) (module docstring). Leaves the scene at the robust plan. Collective."""
    p0 = np.asarray(p_nominal, float)
    b = np.asarray(scene.treatment.bounds if bounds is None else bounds, float)
    n_p, solves = len(p0), 0
    scene.solve(p0)
    nominal, B = _parts(scene, obj, prior)
    p, value, mu, it = p0.copy(), nominal, 1e-3, 0
    for it in range(1, max_iterations + 1):
        S, _ = obj.jacobian()
        w = np.sqrt(obj.weights.ravel())
        r = np.concatenate([w * obj.residual().ravel(), B])
        dB = np.empty((len(B), n_p))
        for i in range(n_p):
            q = p.copy()
            q[i] += FD_STEP
            scene.solve(q)
            solves += 1
            dB[:, i] = (_band(scene, obj, prior) - B) / FD_STEP
        scene.solve(p)
        J = np.vstack([w[:, None] * S, dB])
        H = J.T @ J + obj.tikhonov * np.eye(n_p)
        g = J.T @ r + obj.tikhonov * p
        accepted = False
        while mu < 1e8:
            q = np.clip(p - np.linalg.solve(H + mu * np.diag(np.diag(H)), g), b[:, 0], b[:, 1])
            try:
                scene.solve(q)
                solves += 1
                trial, trial_B = _parts(scene, obj, prior)
            except SolverError:
                trial = {"total": np.inf}
            if trial["total"] < value["total"]:
                accepted = True
                break
            mu *= 10
        if not accepted:
            scene.solve(p)
            break
        done = value["total"] - trial["total"] < ftol * value["total"]
        p, value, B, mu = q, trial, trial_B, max(mu / 10, 1e-9)
        if done:
            break
    return RobustResult(p, p0, value, nominal, it, solves)
