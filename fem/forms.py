"""The energy and its forms: residual f, Jacobian K, the goal coupling df/dg and df/dp;
the state u, its soundness (det F > 0) and the energy and residual callbacks of SNES.
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import contextlib
import logging
import time

import dolfinx
import numpy as np

from fem import compat
from meshes.errors import InputError

log = logging.getLogger(__name__)

#: Default penalty stiffness k per unit active area, kPa/mm (= mN/mm^3): max active goal
#: error 0.002 mm on a 5 mm advance, 0.041 mm on the demo treatment (goal: 0.05 mm).
DEFAULT_PENALTY = 5.0e4


class Forms:
    """Assembly of the energy, f, K and df/dp on the current state (mixin of
    `fem.equilibrium.Equilibrium`, which builds the forms)."""

    @property
    def dfdp(self) -> list:
        """df/dp at the equilibrium: Np PETSc vectors (df/dg) dg/dp_i + (df/dR) dR/dp_i, mN per
        unit, recomputed when the equilibrium has changed (only its p matters where the
        goals are linear and nothing slides: then df/dg is constant and there is no R).
        Active and Dirichlet vertices are disjoint (checked by `Anatomy.validate`), so
        Dirichlet rows are zero."""
        constant = self.goals.linear and self.turn is None
        if self._dfdp_at is None or not (constant or np.array_equal(self._dfdp_at, self.p)):
            dR = None
            if self.turn is not None:
                self._assemble_couplings(at_equilibrium=True)
                dR = self.goals.turns_jacobian(self.p, self._sliding_tags)
            g = compat.petsc_vec(self.goal).duplicate()
            r = compat.petsc_vec(self.turn).duplicate() if dR is not None else None
            tmp = g.duplicate()
            for i, (y, J) in enumerate(zip(self._dfdp, self.goals.jacobian(self.p).T)):
                with g.localForm() as gl:
                    gl.array[:] = J
                self.dfdg.mult(g, y)
                if dR is not None:
                    with r.localForm() as rl:
                        self._fill_turns(rl.array, dR[:, i])
                    self.dfdR.mult(r, tmp)
                    y.axpy(1.0, tmp)
            for v in (g, r, tmp):
                if v is not None:
                    v.destroy()
            self._dfdp_at = self.p.copy()
        return self._dfdp

    def _fill_turns(self, array: np.ndarray, mats: np.ndarray):
        """Write one 3×3 per sliding tag, ``mats`` (n_tags, 3, 3), into a DG0 tensor array
        (local, ghosts included) at the cells of that tag's facets; zero elsewhere."""
        vals = array.reshape(-1, 9)
        vals[:] = 0.0
        for blocks, m in zip(self._turn_blocks, mats):
            vals[blocks] = m.ravel()

    @contextlib.contextmanager
    def _turns_at(self, p):
        """The sliding facets' normals at p (None, or nothing slides: as they are) for the
        block; then back."""
        if self.turn is None or p is None:
            yield
            return
        R = self._R
        self._set_turns(self.goals.turns(p, self._sliding_tags))
        try:
            yield
        finally:
            self._set_turns(R)

    def _set_turns(self, R):
        """Set the rotations R (n_tags, 3, 3) of the sliding facets' normals."""
        self._R = np.asarray(R, dtype=float)
        self._fill_turns(self.turn.x.array, self._R)
        self.turn.x.scatter_forward()

    def _saved(self):
        """(u, goal, turn) arrays to restore after an evaluation elsewhere."""
        return (self._uvec.copy(), self.goal.x.array.copy(),
                None if self.turn is None else (self.turn.x.array.copy(), self._R.copy()))

    def _restore(self, saved):
        u, self.goal.x.array[:], turn = saved
        if turn is not None:
            self.turn.x.array[:], self._R = turn
        self._set_state(u)
        u.destroy()
        self._obj_val = None

    def _assemble_couplings(self, at_equilibrium: bool = False):
        """df/dg (and df/dR where tissue slides) into `dfdg` (`dfdR`), at the state u and the
        goals set (``at_equilibrium``: at the equilibrium's u and p; both are restored)."""
        saved = None
        if at_equilibrium:
            saved = self._saved()
            self._set_params_only(self.p)
            self._set_state(self.u_eq)
        try:
            for M, name in ((self.dfdg, "coupling"), (self.dfdR, "turn_coupling")):
                if M is not None:
                    M.zeroEntries()
                    compat.assemble_matrix(M, self.forms[name])
                    M.assemble()
        finally:
            if saved is not None:
                self._restore(saved)

    def _contact_load(self, p, x: PETSc.Vec, turns_at=None) -> PETSc.Vec:
        """The penalties' residual f_c(x; p) as a new vector, mN, with the sliding facets'
        normals at ``turns_at`` (default p); the goals are restored."""
        saved = self._saved()
        try:
            self._set_params_only(p)
            if self.turn is not None and turns_at is not None:
                self._set_turns(self.goals.turns(turns_at, self._sliding_tags))
            self._set_state(x)
            out = self.b.duplicate()
            out.set(0.0)
            compat.assemble_vector(out, self.forms["contact"])
            out.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
            return out
        finally:
            self._restore(saved)

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

    def energy(self, x: PETSc.Vec) -> float:
        """E_NH + E_A at the state x (displacement, mm), µJ; +inf where x inverts an
        element. u is left at x. Collective."""
        return self._objective(None, x)

    def residual(self, x: PETSc.Vec, out: PETSc.Vec) -> None:
        """out = f(x) = dE/dx at the state x (mN); Dirichlet rows hold x minus its boundary
        value. u is left at x. Collective."""
        self._residual(None, x, out)

    def jacobian(self, x: PETSc.Vec, out: PETSc.Mat) -> None:
        """out = K(x) = df/dx at the state x (mN/mm), Dirichlet rows and columns identity.
        u is left at x. Collective."""
        self._set_state(x)
        self._assemble_jacobian(out)

    def load(self, dp) -> PETSc.Vec:
        """df/dp · dp (dp: (Np,)) as a new PETSc vector, mN: the load a step in p puts on
        the tissue at the current state. Collective."""
        return self._load(dp)

    def _objective(self, snes, x):
        """Energy at x, µJ (kPa mm³); +inf where any cell is inverted (ln det F is NaN at a
        P1 cell's single quadrature point; P2 is also checked at the vertices). The line
        search asks again for the point it accepted last: that value is remembered."""
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
        """Validate p (Np,) and set the goal field g(p) (and the sliding facets' turns R(p))."""
        p = np.asarray(p, dtype=float).reshape(-1)
        if p.shape != (self.n_params,):
            raise InputError(f"expected {self.n_params} parameters, got {p.size}")
        if not np.all(np.isfinite(p)):
            raise InputError(f"parameters must be finite, got {p.tolist()}")
        self._set_params_only(p)
        self._obj_val = None   # the energy depends on the goal
        return p

    def _set_params_only(self, p):
        self.goal.x.array[:] = self.goals.goal(p)
        if self.turn is not None:
            self._set_turns(self.goals.turns(p, self._sliding_tags))

    def coupling_transpose(self, lam: PETSc.Vec) -> np.ndarray:
        """(df/dp)ᵀ λ, shape (Np,) (collective). With λ = K⁻¹ ∂T/∂x, dT/dp = -(df/dp)ᵀ λ."""
        return np.array([g.dot(lam) for g in self.dfdp])

    def _goal_load(self, p) -> PETSc.Vec:
        """f_c(u_eq; p0) - f_c(u_eq; p) as a new vector, mN: the exact load of moving the
        goals from the equilibrium's p0 to p, with f_c the penalties' residual (for linear
        goals and glued tissue, the tangent load -df/dp dp). The sliding facets' normals
        stay at p0, as in K there: K's stiff penalty directions turn with them, and a load
        along the turned normals, answered by K at p0, slides the tissue along the teeth
        (docs/decisions.md, "Sliding lips")."""
        out = self._contact_load(self.p, self.u_eq)
        moved = self._contact_load(p, self.u_eq, turns_at=self.p)
        out.axpy(-1.0, moved)
        moved.destroy()
        return out

    def _cell_sums(self, name: str) -> np.ndarray:
        """A form of one DG0 test function assembled at the state u: (owned cells' dofs,)."""
        vec = compat.create_vector(self.forms[name])
        vec.set(0.0)
        compat.assemble_vector(vec, self.forms[name])
        vec.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        out = vec.array_r.copy()
        vec.destroy()
        return out

    def active_goal_error(self) -> float:
        """max over active vertices of |u - g|, and over the cells on sliding facets of the
        root mean square of (u - g)·n on them, mm (collective)."""
        gap = (self.u.x.array - self.goal.x.array).reshape(-1, 3)[:self.domain.n_owned]
        local = np.linalg.norm(gap[self._active], axis=1).max(initial=0.0)
        if self.turn is not None:   # the root mean square over each cell's sliding facets
            on = self._sliding_area > 0
            rms = np.sqrt(self._cell_sums("normal_gap")[on] / self._sliding_area[on])
            local = max(local, rms.max(initial=0.0))
        return self.domain.comm.allreduce(local, op=MPI.MAX)
