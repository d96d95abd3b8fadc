"""First-order exploration of the skin around an equilibrium x(p0) (paper eq. 7, Fig. 5).

`SkinPredictor` holds ``x_skin(p0)`` and ``S_skin = dx_skin/dp`` (Np tangent solves with the
kept factorisation). A prediction ``x(p0) + S dp`` is a small dense mat-vec, real time.
`corrected` improves it with a few quasi-Newton (L-BFGS) steps on the same kept factorisation:
each step is one pair of triangular solves and two residuals (its line search), no
refactorisation.
`fit_surface` is the Fig. 5c workflow: the parameters whose true equilibrium is closest to a
(predicted or edited) skin surface.
"""

from __future__ import annotations

import logging

import numpy as np

from fem.equilibrium import Equilibrium
from inverse.objective import Objective, point_sensitivity

#: Quasi-Newton steps of a corrected prediction (BENCHMARKS.md: error and time against it).
CORRECTION_ITERATIONS = 6

log = logging.getLogger(__name__)


class SkinPredictor:
    """Skin sensitivities at the scene's current equilibrium.

    Attributes:
        vertices: (N,) original indices of the skin vertices (same on every rank).
        x0: (N, 3) skin positions at p0, mm. S: (N, 3, Np) mm per parameter unit.
        p0: (Np,) parameters of the equilibrium. It keeps x(p0) and dx/dp on the volume
        (Np + 1 vectors), so corrections do not depend on where the scene is afterwards.
    """

    def __init__(self, scene):
        self.scene, self.eq = scene, scene.eq
        dom = scene.domain
        self.vertices = dom.skin_vertices()
        self.op = dom.vertex_operator(self.vertices)
        self.p0 = self.eq.p.copy()
        self.x0 = self.op.apply(self.eq.u_eq.array)
        self.S = point_sensitivity(self.eq, self.op)
        # x(p0) and dx/dp on the volume: corrections start from them wherever the scene is
        self._u0 = self.eq.u_eq.copy()
        self._dxdp = [s.copy() for s in self.eq.sensitivity()]
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

    def corrected(self, dp, iterations: int = CORRECTION_ITERATIONS):
        """(skin (N, 3), landmarks {name: (3,)}) mm at p0 + dp: the first-order state, then
        at most ``iterations`` quasi-Newton steps on K's kept factorisation
        (`Equilibrium.relax`). No assembly of K, no refactorisation; the scene's equilibrium
        is unchanged. Where the first-order state inverts an element, the steps would start
        from a shortened state far from the equilibrium (on coarse they then erred 2x more
        than the plain prediction): the plain prediction is returned. Collective."""
        eq: Equilibrium = self.eq
        dp = np.asarray(dp, dtype=float)
        step = self._u0.duplicate()
        step.set(0.0)
        step.maxpy(dp, self._dxdp)
        x = eq.admissible(self._u0, step)
        step.destroy()
        if x is None:
            log.info("the first-order state at dp = %s inverts an element: plain prediction",
                     np.round(dp, 3).tolist())
            return self.predict(dp), self.predict_landmarks(dp)
        try:
            eq.relax(self.p0 + dp, x, iterations)
            return self.op.apply(x.array), dict(zip(self.landmark_names,
                                                    self.lm_op.apply(x.array)))
        finally:
            x.destroy()

    def destroy(self):
        for v in (self._u0, *self._dxdp):
            v.destroy()


def fit_surface(scene, predictor: SkinPredictor, surface, **options):
    """Fig. 5c: parameters whose true equilibrium is closest to ``surface`` (N, 3) mm, the
    skin in `predictor`'s vertex order (e.g. a prediction the surgeon liked). Starts from
    p0; returns `inverse.planner.PlanResult`."""
    from inverse.planner import gauss_newton

    obj = Objective(scene.eq, predictor.op, surface)
    return gauss_newton(scene, obj, p0=predictor.p0, **options)
