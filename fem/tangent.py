"""Tangent solves at the equilibrium: the linearisation there, a part that owns it
(`Linearisation`: K, the tangent KSP, the cached dx/dp), and K⁻¹ rhs by CG on the kept
factorisation (refactorised when it has gone stale) and the sensitivities dx/dp (all columns
at once, cached) for adjoints and exploration (`TangentSolves`, a part).
"""

from __future__ import annotations

from mpi4py import MPI  # noqa: F401 (first: it loads the MPI library PETSc links)
from petsc4py import PETSc

import logging

import numpy as np

from fem.factorisation import FactorState
from meshes.errors import SolverError

log = logging.getLogger(__name__)

#: The tangent KSP's options prefix, after the equilibrium's (docs/solver.md).
TANGENT_PREFIX = "tangent_"


class _ApplyOther:
    """Python PC context that applies another, already built PC."""

    def __init__(self, pc):
        self.pc = pc

    def apply(self, pc, x, y):
        self.pc.apply(x, y)


class Linearisation:
    """The linearisation at the current equilibrium, a part that owns it (`Equilibrium.
    linearisation`): K = df/du there (assembled once per equilibrium, `matrix`), dx/dp there
    (`sensitivities`, kept once computed) and the tangent KSP that solves with K: CG
    preconditioned by the kept factorisation's PC (``factor_pc``), or by a PC of its own
    chosen under ``<prefix>tangent_`` (`own_pc`): `solve`; all columns of dx/dp at once with
    the kept factor: `block_cg` (CG preconditioned by it) and `block_solve` (it refactorised
    here). `moved` forgets K and dx/dp.

    Args:
        forms: the scene's `fem.forms.EnergyForms`; kept: the kept factorisation
            (`fem.factorisation.KeptFactor`); policy: `fem.policy.SolverPolicy`.
    """

    def __init__(self, forms, kept, prefix: str, policy):
        self.forms, self.kept, self.policy = forms, kept, policy
        factor_pc = kept.ksp.getPC()
        self.K = forms.A.duplicate()
        self._assembled = False
        self._sensitivities = None   # dx/dp: Np PETSc vectors, mm per unit, or None
        ksp = self.ksp = PETSc.KSP().create(forms.domain.comm)
        ksp.setOptionsPrefix(prefix + TANGENT_PREFIX)
        ksp.setType("cg")
        ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
        ksp.setTolerances(rtol=1e-11, atol=1e-30, max_it=200)
        ksp.setOperators(self.K)
        pc = ksp.getPC()
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(_ApplyOther(factor_pc))
        self.K.setNearNullSpace(forms.A.getNearNullSpace())   # for a PC of its own (GAMG)
        ksp.setFromOptions()

    def set_policy(self, policy):
        """The `fem.policy.SolverPolicy` of the next operations (the equilibrium's, when it
        is replaced)."""
        self.policy = policy

    def matrix(self, p, x) -> PETSc.Mat:
        """K at the equilibrium x at p (its normals), assembled once until `moved`."""
        if not self._assembled:
            self.forms.jacobian(x, self.K, turns_at=p)
            self._assembled = True
        return self.K

    def moved(self):
        """The equilibrium changed: K is assembled again when asked for, dx/dp solved again."""
        self._assembled = False
        self.forget_sensitivities()

    @property
    def sensitivities(self):
        """dx/dp at the equilibrium, kept (`keep_sensitivities`): Np PETSc vectors, mm per
        unit; None until solved."""
        return self._sensitivities

    def keep_sensitivities(self, columns: list) -> list:
        """Keep ``columns`` (dx/dp at the current equilibrium) until it moves; returns them."""
        self.forget_sensitivities()
        self._sensitivities = columns
        return columns

    def forget_sensitivities(self):
        """Drop the kept dx/dp."""
        for v in self._sensitivities or []:
            v.destroy()
        self._sensitivities = None

    @property
    def own_pc(self) -> bool:
        """The tangent solves have a preconditioner of their own, chosen by PETSc options
        under ``<prefix>tangent_`` (e.g. ``-orthodiff_fwd_tangent_pc_type gamg``: CG with
        algebraic multigrid on K, the rigid-body near-nullspace; docs/solver.md), instead of
        the kept factorisation."""
        return self.ksp.getPC().getType() != PETSc.PC.Type.PYTHON

    def solve(self, rhs: PETSc.Vec, out: PETSc.Vec, p, x: PETSc.Vec, last_its: int,
              refactorise) -> int:
        """out = K⁻¹ rhs, K at the equilibrium x at p (collective; Dirichlet rows identity).
        CG preconditioned by the kept factorisation; ``refactorise()`` rebuilds it at the
        equilibrium when the previous tangent solve needed more than
        `SolverPolicy.tangent_lag_its` iterations with it (STALE), when the last forward
        solve did (``last_its``: quasi-Newton from a factorisation far from here; at medium
        size CG then took 63 iterations, 3x a factorisation; ``solve(tangent=True)`` avoids
        that), or when CG fails; it then also serves the next solves as quasi-Newton's
        start. With a preconditioner of its own (`own_pc`) nothing is factorised. Returns
        the CG iteration count; raises `SolverError` where GMRES fails too."""
        self.matrix(p, x)
        ksp, kept, lag = self.ksp, self.kept, self.policy.tangent_lag_its
        far = kept.state is not FactorState.EQUILIBRIUM and last_its > lag
        own = self.own_pc
        for attempt in range(2):
            if not own and (attempt or far or kept.state in (FactorState.NONE,
                                                             FactorState.STALE)):
                refactorise()
            ksp.setType("cg" if attempt == 0 else "gmres")  # GMRES if K is indefinite
            ksp.solve(rhs, out)
            if ksp.getConvergedReason() > 0:
                if attempt:
                    ksp.setType("cg")
                if not own and ksp.getIterationNumber() > lag:
                    kept.slowed()
                return ksp.getIterationNumber()
        raise SolverError(f"tangent solve with K at p = {np.round(p, 4).tolist()} failed "
                          f"(KSP reason {ksp.getConvergedReason()}): K is "
                          "singular or indefinite at this equilibrium")

    def block_solve(self, columns: list, x: PETSc.Vec, refactorise):
        """-K⁻¹ c for each PETSc vector c of ``columns`` (e.g. df/dp) as one MatMatSolve with
        the factor of K at the equilibrium x (``refactorise()`` makes it, where it is not
        held): a list of new vectors, or None (not a Cholesky preset, no block solve in its
        package, no columns, or K not positive definite there)."""
        if not self._blockable(columns):
            return None
        if self.kept.state is not FactorState.EQUILIBRIUM:
            refactorise()
            if self.kept.state is FactorState.SHIFTED:   # the tangent solves handle it
                return None
        out = [x.duplicate() for _ in columns]
        if not self._apply_factor(columns, out):
            for v in out:
                v.destroy()
            return None
        for v in out:
            v.scale(-1.0)
        return out

    def block_cg(self, columns: list, p, x: PETSc.Vec, max_its: int,
                 rtol: float | None = None):
        """-K⁻¹ c for each PETSc vector c of ``columns``, K at the equilibrium x at p, by CG
        on all columns at once, preconditioned by the kept factorisation as it is (of K at
        a nearby iterate; one MatMatSolve per iteration for every column), to the relative
        residual ``rtol`` (default: the tangent KSP's): a list of new vectors, or None where
        a column needs more than ``max_its`` iterations, K is not positive definite along a
        direction, or the factorisation serves no block solve. Collective."""
        if not self._blockable(columns):
            return None
        K = self.matrix(p, x)
        rtol = self.ksp.getTolerances()[0] if rtol is None else rtol
        m = len(columns)
        X, R, Z, P, Q = ([x.duplicate() for _ in range(m)] for _ in range(5))
        done = False
        try:
            for c, xi, r in zip(columns, X, R):
                xi.set(0.0)
                c.copy(r)
                r.scale(-1.0)
            goal = [rtol * r.norm() for r in R]
            todo = [i for i in range(m) if goal[i] > 0.0]   # a zero column is solved
            if todo and not self._apply_factor(R, Z):
                return None
            for z, pi in zip(Z, P):
                z.copy(pi)
            rz = [r.dot(z) for r, z in zip(R, Z)]
            its = 0
            while todo and its < max_its:
                its += 1
                self._block_mult(K, [P[i] for i in todo], [Q[i] for i in todo])
                for i in todo:
                    pq = P[i].dot(Q[i])
                    if not pq > 0.0:   # not positive definite along P (or NaN)
                        return None
                    a = rz[i] / pq
                    X[i].axpy(a, P[i])
                    R[i].axpy(-a, Q[i])
                todo = [i for i in todo if R[i].norm() > goal[i]]
                if todo:
                    self._apply_factor([R[i] for i in todo], [Z[i] for i in todo])
                    for i in todo:
                        rz_new = R[i].dot(Z[i])
                        P[i].aypx(rz_new / rz[i], Z[i])
                        rz[i] = rz_new
            done = not todo
            log.debug("block CG of %d columns: %s after %d iterations", m,
                      "converged" if done else "gave up", its)
            return X if done else None
        finally:
            for v in (*R, *Z, *P, *Q, *(() if done else X)):
                v.destroy()

    def _blockable(self, columns: list) -> bool:
        """Block solves apply the kept factor itself: a Cholesky preset, columns to solve,
        and no preconditioner of the tangent's own."""
        return (self.kept.ksp.getPC().getType() == "cholesky" and bool(columns)
                and not self.own_pc)

    def _dense(self, vecs: list) -> PETSc.Mat:
        """A new dense matrix whose columns are the PETSc vectors ``vecs`` (one layout)."""
        n, N = vecs[0].getLocalSize(), vecs[0].getSize()
        mat = PETSc.Mat().createDense([(n, N), (None, len(vecs))],
                                      comm=self.forms.domain.comm)
        mat.setUp()
        mat.getDenseArray()[:] = np.stack([v.array_r for v in vecs], axis=1)
        mat.assemble()
        return mat

    @staticmethod
    def _columns_to(mat: PETSc.Mat, vout: list):
        """Copy the dense matrix's columns into the PETSc vectors ``vout``."""
        cols = mat.getDenseArray()
        for i, v in enumerate(vout):
            v.array[:] = cols[:, i]

    def _block_mult(self, K: PETSc.Mat, vin: list, vout: list):
        """vout[i] = K vin[i], all columns in one MatMatMult, K read once: the bands' 14
        iterations of six columns took 0.17 s against 0.33 s one by one (class3 at paper,
        1 rank)."""
        block = self._dense(vin)
        try:
            out = K.matMult(block)
            self._columns_to(out, vout)
            out.destroy()
        finally:
            block.destroy()

    def _apply_factor(self, vin: list, vout: list) -> bool:
        """vout[i] = F⁻¹ vin[i] for the kept factor F, all columns in one MatMatSolve: a
        triangular solve reads the whole factor, once for all columns (MUMPS, class3 at paper,
        2 ranks: one column 67-71 ms, six 132-141 ms). False where its package has no block
        solve."""
        pc = self.kept.ksp.getPC()
        rhs = self._dense(vin)
        sol = rhs.duplicate()
        try:
            pc.getFactorMatrix().matSolve(rhs, sol)
            self._columns_to(sol, vout)
            return True
        except PETSc.Error:   # a factorisation package without block solves
            return False
        finally:
            for mat in (rhs, sol):
                mat.destroy()

    def destroy(self):
        self.forget_sensitivities()
        self.ksp.destroy()
        self.K.destroy()


class TangentSolves:
    """Tangent, adjoint and sensitivity solves at the current equilibrium, a part: K⁻¹ rhs
    (`solve`), dx/dp (`sensitivity`, cached in the `Linearisation`) and dx/dp · dp (`step`).

    Args:
        forms: `fem.forms.EnergyForms`; kept: `fem.factorisation.KeptFactor`;
            linearisation: `Linearisation`; refactorisation:
            `fem.factorisation.Refactorisation`; state: `fem.state.EquilibriumState`.
    """

    def __init__(self, forms, kept, linearisation: Linearisation, refactorisation, state):
        self.forms, self.kept, self.linearisation = forms, kept, linearisation
        self.refactorisation, self.state = refactorisation, state

    @property
    def has_sensitivity(self) -> bool:
        """dx/dp is kept for the current equilibrium."""
        return self.linearisation.sensitivities is not None

    def solve(self, rhs: PETSc.Vec, out: PETSc.Vec) -> int:
        """out = K⁻¹ rhs, K = df/du at the current equilibrium (collective; Dirichlet rows
        are identity), by CG on the kept factorisation, refactorised at the equilibrium
        where it has gone stale or is far from here (`Linearisation.solve`). Returns the CG
        iteration count."""
        st = self.state
        return self.linearisation.solve(rhs, out, st.p, st.u_eq, st.last_its,
                                        self.refactorisation.at_equilibrium)

    def sensitivity(self) -> list:
        """dx/dp at the equilibrium: Np PETSc vectors ``s_i = -K⁻¹ df/dp_i`` (mm per unit),
        computed on first use (`responses`) and cached until the equilibrium changes."""
        lin, st = self.linearisation, self.state
        if lin.sensitivities is None:
            lin.keep_sensitivities(self.responses(self.forms.dfdp(st.p, st.u_eq)))
        return lin.sensitivities

    def responses(self, columns: list, rtol: float | None = None) -> list:
        """``-K⁻¹ c`` for each PETSc vector c of ``columns`` (loads such as df/dp_i or
        df/dθ_j) at the equilibrium: new vectors, mm per unit. With a direct solver: block CG
        on the kept factorisation where it is of K at an iterate near here (the solve that
        reached it needed at most `SolverPolicy.tangent_lag_its` iterations from it), or at
        any iterate where a loose relative residual ``rtol`` is asked for
        (`Linearisation.block_cg`, at most `SolverPolicy.sensitivity_cg_its` iterations);
        else one factorisation of K at the equilibrium (where none is held) and one block
        solve of all columns (`_apply_factor`); else a tangent solve per
        column (`step`). Collective."""
        lin, st = self.linearisation, self.state
        block = None
        if self.kept.state is FactorState.ITERATE and (rtol is not None or self.kept.serves(
                st.last_its, st.policy.tangent_lag_its, unshifted=True)):
            block = lin.block_cg(columns, st.p, st.u_eq, st.policy.sensitivity_cg_its, rtol)
        block = block or lin.block_solve(columns, st.u_eq, self.refactorisation.at_equilibrium)
        if block is None:
            block = []
            for c in columns:
                load = c.copy()
                load.scale(-1.0)
                block.append(self.step(np.zeros(len(st.p)), rhs=load))
        return block

    def step(self, dp, rhs: PETSc.Vec | None = None) -> PETSc.Vec:
        """dx = dx/dp · dp (a new PETSc vector, mm): from the cached sensitivities, else one
        tangent solve; with no factorisation yet, one is made at the equilibrium, and a
        Cholesky factor of K there is applied once (no K assembled, no CG); not so with the
        tangent's own preconditioner (`Linearisation.own_pc`). ``rhs``: the load to respond
        to instead of -df/dp dp (e.g. `EnergyForms.goal_load`; consumed)."""
        st, lin = self.state, self.linearisation
        dp = np.asarray(dp, dtype=float)
        out = st.u_eq.duplicate()
        out.set(0.0)
        if lin.sensitivities is not None and rhs is None:
            out.maxpy(dp, lin.sensitivities)
            return out
        rhs = self.forms.load(-dp, st.p, st.u_eq) if rhs is None else rhs
        own = lin.own_pc
        if not self.kept.ready and not own:
            self.refactorisation.at_equilibrium()
        pc = self.kept.ksp.getPC()
        if not own and self.kept.state is FactorState.EQUILIBRIUM and \
                pc.getType() == "cholesky":
            pc.apply(rhs, out)
        else:
            self.solve(rhs, out)
        rhs.destroy()
        return out
