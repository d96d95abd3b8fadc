"""First-order exploration of the skin around an equilibrium x(p0) (paper eq. 7, Fig. 5).

`SkinPredictor` holds ``x_skin(p0)`` and ``S_skin = dx_skin/dp`` (Np tangent solves with the
kept factorisation). A prediction ``x(p0) + S dp`` is a small dense mat-vec, real time.
`corrected` improves it with chord-Newton steps that reuse the same factorisation: each step
is one residual assembly and one pair of triangular solves, no refactorisation.
`fit_surface` is the Fig. 5c workflow: the parameters whose true equilibrium is closest to a
(predicted or edited) skin surface.
"""

from __future__ import annotations

import numpy as np

from fem.equilibrium import Equilibrium
from inverse.objective import Objective, point_sensitivity


class SkinPredictor:
    """Skin sensitivities at the scene's current equilibrium.

    Attributes:
        vertices: (N,) original indices of the skin vertices (same on every rank).
        x0: (N, 3) skin positions at p0, mm. S: (N, 3, Np) mm per parameter unit.
        p0: (Np,) parameters of the equilibrium.
    """

    def __init__(self, scene):
        self.scene, self.eq = scene, scene.eq
        dom = scene.domain
        self.vertices = dom.skin_vertices()
        self.op = dom.vertex_operator(self.vertices)
        self.p0 = self.eq.p.copy()
        self.x0 = self.op.apply(self.eq.u_eq.array)
        self.S = point_sensitivity(self.eq, self.op)
        self._S2 = self.S.reshape(-1, self.S.shape[-1])
        self.landmark_names = list(dom.landmarks)
        self.lm_op = dom.point_operator(self.landmark_names)
        self.lm0 = self.lm_op.apply(self.eq.u_eq.array)
        self.lm_S = point_sensitivity(self.eq, self.lm_op)

    def predict(self, dp) -> np.ndarray:
        """Plain first-order skin (N, 3) mm at p0 + dp. Local, no communication."""
        return self.x0 + (self._S2 @ np.asarray(dp, dtype=float)).reshape(-1, 3)

    def predict_landmarks(self, dp) -> dict:
        """Plain first-order landmarks {name: (3,)} mm at p0 + dp."""
        pts = self.lm0 + self.lm_S @ np.asarray(dp, dtype=float)
        return dict(zip(self.landmark_names, pts))

    def corrected(self, dp, steps: int = 1, substeps: int = 1, max_substeps: int = 32):
        """(skin (N, 3), landmarks {name: (3,)}) mm at p0 + dp: the first-order state, then
        ``steps`` chord-Newton steps with K's kept factorisation, repeated over ``substeps``
        equal parts of dp (a cheap continuation). Where a first-order sub-step would invert
        an element, the parts are doubled up to ``max_substeps``; beyond that the plain
        prediction is returned. No refactorisation; the scene stays at x(p0). Collective."""
        dp = np.asarray(dp, dtype=float)
        n = substeps
        while n <= max_substeps:
            out = self._chord_path(dp, steps, n)
            if out is not None:
                return out
            n *= 2
        return self.predict(dp), self.predict_landmarks(dp)

    def _chord_path(self, dp, steps: int, substeps: int):
        eq: Equilibrium = self.eq
        step = eq.tangent_step(dp / substeps)
        x, r, dx = eq.u_eq.copy(), step.duplicate(), step.duplicate()
        pc = eq.ksp.getPC()
        try:
            for k in range(1, substeps + 1):
                eq.set_params(self.p0 + dp * k / substeps)
                step.copy(dx)
                if self._step_valid(x, dx, +1.0) < 1.0:
                    return None
                for _ in range(steps):
                    eq._residual(None, x, r)
                    if not np.isfinite(r.norm()):
                        break
                    pc.apply(r, dx)
                    self._step_valid(x, dx, -1.0)
            return self.op.apply(x.array), dict(zip(self.landmark_names,
                                                    self.lm_op.apply(x.array)))
        finally:
            eq.set_params(self.p0)
            eq._set_state(eq.u_eq)
            for v in (x, r, dx, step):
                v.destroy()

    def _step_valid(self, x, dx, sign: float, halvings: int = 10):
        """x += sign·t·dx with the largest t in 1, 1/2, ... that inverts no element; returns
        t (0 if none)."""
        t = 1.0
        for _ in range(halvings):
            x.axpy(sign, dx)
            self.eq._set_state(x)
            if self.eq.min_det_F() > 0:
                return t
            x.axpy(-sign, dx)
            dx.scale(0.5)
            t *= 0.5
        self.eq._set_state(x)
        return 0.0


def fit_surface(scene, predictor: SkinPredictor, surface, **options):
    """Fig. 5c: parameters whose true equilibrium is closest to ``surface`` (N, 3) mm, the
    skin in `predictor`'s vertex order (e.g. a prediction the surgeon liked). Starts from
    p0; returns `inverse.planner.PlanResult`."""
    from inverse.planner import gauss_newton

    obj = Objective(scene.eq, predictor.op, surface)
    return gauss_newton(scene, obj, p0=predictor.p0, **options)
