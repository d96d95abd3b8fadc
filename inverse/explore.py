"""First-order exploration of the skin around an equilibrium x(p0) (paper eq. 7, Fig. 5).

`SkinPredictor` holds ``x_skin(p0)`` and ``S_skin = dx_skin/dp`` (Np tangent solves with the
kept factorisation). A prediction ``x(p0) + S dp`` is a small dense mat-vec, real time.
`corrected` improves it by continuation on the same kept factorisation: substeps along the path
to p0 + dp, each started from the secant extrapolation of the last two and relaxed by a few
quasi-Newton (L-BFGS) steps (one pair of triangular solves and two residuals each), no
assembly of K, no refactorisation.
`fit_surface` is the Fig. 5c workflow: the parameters whose true equilibrium is closest to a
(predicted or edited) skin surface.
"""

from __future__ import annotations

from mpi4py import MPI  # noqa: F401 (first: it loads the MPI library PETSc links)
from petsc4py import PETSc

import logging

import numpy as np

from fem.limits import check
from fem.policy import DEFAULT_POLICY
from inverse.objective import Objective, point_sensitivity

#: Quasi-Newton steps per substep of a corrected prediction (BENCHMARKS.md: error and time),
#: and the largest first-order vertex motion of a substep, mm: those of the solver's path
#: following. A 20 mm advance (and 6 mm lateral shift) of class3-asym from rest takes 6
#: substeps: coarse 3.18 -> 0.23 mm in 0.48 s (true equilibrium: 0.65 s), paper 3.13 ->
#: 0.33 mm in 8.3 s (true: 23 s) (BENCHMARKS.md); 3 mm substeps on class3, coarse: 0.10 mm
#: in 0.6 s against 0.19 mm in 0.5 s.
CORRECTION_ITERATIONS = DEFAULT_POLICY.path_iterations
CORRECTION_SUBSTEP_MM = DEFAULT_POLICY.path_substep_mm

log = logging.getLogger(__name__)


class SkinPredictor:
    """Skin sensitivities at the scene's current equilibrium.

    Attributes:
        vertices: (N,) original indices of the skin vertices (same on every rank).
        x0: (N, 3) skin positions at p0, x_rest at rest, mm. S: (N, 3, Np) mm per unit.
        p0: (Np,) parameters of the equilibrium. It keeps x(p0) and dx/dp on the volume
        (Np + 1 vectors), so corrections do not depend on where the scene is afterwards.
        band (N,), lm_band {name: mm}: with a ``prior`` (`inverse.uncertainty.Prior`), the
        tissue's 95 % radius at p0 at each skin vertex and landmark; else None.
    """

    def __init__(self, scene, prior=None):
        self.scene, self.eq = scene, scene.eq
        dom = scene.domain
        self.vertices = dom.boundary_vertices()
        self.op = dom.vertex_operator(self.vertices)
        self.p0 = self.eq.p.copy()
        self.x0 = self.op.apply(self.eq.u_eq.array)
        self.x_rest = self.op.apply(np.zeros_like(self.eq.u_eq.array))
        self.S = point_sensitivity(self.eq, self.op)
        # x(p0) and dx/dp on the volume: corrections start from them wherever the scene is
        self._u0 = self.eq.u_eq.copy()
        self._dxdp = [s.copy() for s in self.eq.sensitivity()]
        self._S2 = self.S.reshape(-1, self.S.shape[-1])
        self.landmark_names = list(dom.landmarks)
        self.lm_op = dom.point_operator(self.landmark_names)
        self.lm0 = self.lm_op.apply(self.eq.u_eq.array)
        self.lm_S = point_sensitivity(self.eq, self.lm_op)
        self.band, self.lm_band = None, None
        if prior is not None:   # the tissue's 95 % radius at p0 (`inverse.uncertainty`)
            from inverse.uncertainty import covariances, material_rows, radius95

            skin, lms = material_rows(scene, [self.op, self.lm_op])
            self.band = radius95(covariances(skin, prior))
            self.lm_band = dict(zip(self.landmark_names, radius95(covariances(lms, prior))))

    def predict(self, dp) -> np.ndarray:
        """Plain first-order skin (N, 3) mm at p0 + dp. Local, no communication."""
        return self.x0 + (self._S2 @ self.scene.param_vector(dp)).reshape(-1, 3)

    def predict_landmarks(self, dp) -> dict:
        """Plain first-order landmarks {name: (3,)} mm at p0 + dp."""
        pts = self.lm0 + self.lm_S @ self.scene.param_vector(dp)
        return dict(zip(self.landmark_names, pts))

    def corrected(self, dp, iterations: int = CORRECTION_ITERATIONS,
                  substep_mm: float = CORRECTION_SUBSTEP_MM):
        """(skin (N, 3), landmarks {name: (3,)}) mm at p0 + dp, by continuation from x(p0)
        on K(p0)'s kept factorisation (`Equilibrium.follow`: substeps of at most
        ``substep_mm`` first-order motion from secant starts, each relaxed by ``iterations``
        quasi-Newton steps with the L-BFGS pairs kept). The secant starts follow the path's
        curvature (coarse, 20 mm advance, 4 substeps of 10 steps: 0.44 mm; first-order
        starts: 1.29 mm) and the kept pairs its stiffening (paper, 20 mm: 0.62 -> 0.29 mm).
        No assembly of K, no refactorisation; the scene's equilibrium is unchanged. Where
        no path is found (every start of a short substep inverts an element), the plain
        prediction is returned. Collective."""
        iterations = check("iterations", iterations)
        substep_mm = check("substep_mm", substep_mm)
        dp = self.scene.param_vector(dp)
        step = self.step(dp)
        x = self.eq.follow(self.p0, self._u0, step, self.p0 + dp, iterations, substep_mm)
        step.destroy()
        if x is None:
            return self.predict(dp), self.predict_landmarks(dp)
        try:
            return self.op.apply(x.array), dict(zip(self.landmark_names,
                                                    self.lm_op.apply(x.array)))
        finally:
            x.destroy()

    def step(self, dp) -> PETSc.Vec:
        """dx/dp dp on the volume (a new PETSc vector, mm): no solve."""
        step = self._u0.duplicate()
        step.set(0.0)
        step.maxpy(self.scene.param_vector(dp), self._dxdp)
        return step

    def state(self, dp) -> PETSc.Vec:
        """The first-order displacement x(p0) + dx/dp dp on the volume (a new PETSc vector,
        mm), e.g. a warm start for the true solve at p0 + dp: no solve."""
        x = self.step(dp)
        x.axpy(1.0, self._u0)
        return x

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
