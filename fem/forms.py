"""The energy and its forms: residual f, Jacobian K, the goal coupling df/dg and df/dp;
the state u, its soundness (det F > 0) and the energy and residual callbacks of SNES.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import logging
import time

import dolfinx
import numpy as np

from fem import compat
from meshes.errors import InputError

log = logging.getLogger("fem.equilibrium")

#: Default penalty stiffness k per unit active area, kPa/mm (= mN/mm^3): max active goal
#: error 0.002 mm on a 5 mm advance, 0.041 mm on the demo treatment (goal: 0.05 mm).
DEFAULT_PENALTY = 5.0e4


class Forms:
    """Assembly of the energy, f, K and df/dp on the current state (mixin of
    `fem.equilibrium.Equilibrium`, which builds the forms)."""

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

    def _residual(self, snes, x, b):
        t = time.perf_counter()
        self._set_state(x)
        with b.localForm() as bl:
            bl.set(0.0)
        compat.assemble_vector(b, self.forms["residual"])
        b.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        compat.set_bc(b, self.bcs, x, -1.0)
        self._stats.assemble += time.perf_counter() - t

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

    def active_goal_error(self) -> float:
        """max over active vertices of |u - g|, mm (collective)."""
        gap = (self.u.x.array - self.goal.x.array).reshape(-1, 3)[:self.domain.n_owned]
        local = np.linalg.norm(gap[self._active], axis=1).max(initial=0.0)
        return self.domain.comm.allreduce(local, op=MPI.MAX)
