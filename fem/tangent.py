"""Tangent solves at the equilibrium: K⁻¹ rhs by CG on the kept factorisation (refactorised
when it has gone stale), the sensitivities dx/dp (Np solves, cached) for adjoints and
exploration.
"""

from __future__ import annotations

from petsc4py import PETSc

import logging

import numpy as np

from fem.factorisation import FactorState
from meshes.errors import SolverError

log = logging.getLogger(__name__)


class TangentSolves:
    """Adjoint and sensitivity solves (mixin of `fem.equilibrium.Equilibrium`)."""

    def solve_tangent(self, rhs: PETSc.Vec, out: PETSc.Vec) -> int:
        """out = K⁻¹ rhs, K = df/du at the current equilibrium (collective; Dirichlet rows
        are identity). CG preconditioned by the kept factorisation; it is rebuilt at the
        equilibrium when the previous tangent solve needed more than `SolverPolicy.tangent_lag_its`
        iterations with it, when the last forward solve did (quasi-Newton from a
        factorisation far from here: at medium size CG then took 63 iterations, 3x a
        factorisation; ``solve(tangent=True)`` avoids that), or when CG fails; it then also
        serves the next solves as quasi-Newton's start. With a preconditioner of its own
        (`own_tangent_pc`) nothing is factorised. Returns the CG iteration count."""
        self._assemble_K()
        ksp = self.tangent_ksp
        far = self.factor is not FactorState.EQUILIBRIUM and \
            self._last_its > self.policy.tangent_lag_its
        own = self.own_tangent_pc
        for attempt in range(2):
            if not own and (attempt or far or self.factor in (FactorState.NONE,
                                                               FactorState.STALE)):
                self.factorise_at_equilibrium()
            ksp.setType("cg" if attempt == 0 else "gmres")  # GMRES if K is indefinite
            ksp.solve(rhs, out)
            if ksp.getConvergedReason() > 0:
                if attempt:
                    ksp.setType("cg")
                if not own and ksp.getIterationNumber() > self.policy.tangent_lag_its:
                    self.kept.slowed()
                return ksp.getIterationNumber()
        raise SolverError(f"tangent solve with K at p = {np.round(self.p, 4).tolist()} failed "
                          f"(KSP reason {self.tangent_ksp.getConvergedReason()}): K is "
                          "singular or indefinite at this equilibrium")

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
        if pc.getType() != "cholesky" or self.n_params == 0 or self.own_tangent_pc:
            return None
        if self.factor is not FactorState.EQUILIBRIUM:
            self.factorise_at_equilibrium()
            if self.factor is FactorState.SHIFTED:   # the tangent solves handle it
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
    def own_tangent_pc(self) -> bool:
        """The tangent solves have a preconditioner of their own, chosen by PETSc options
        under ``<prefix>tangent_`` (e.g. ``-orthodiff_fwd_tangent_pc_type gamg``: CG with
        algebraic multigrid on K, the rigid-body near-nullspace; docs/solver.md), instead of
        the kept factorisation."""
        return self.tangent_ksp.getPC().getType() != PETSc.PC.Type.PYTHON

    @property
    def has_sensitivity(self) -> bool:
        """dx/dp is cached for the current equilibrium (direct mode costs nothing more)."""
        return self._sens is not None
