"""The kept factorisation on its own (`fem.factorisation.FactorState`), on a block of tissue:
each operation moves its state as docs/design.md says, and a factorisation is made only where
the state asks for one."""

import dataclasses

import numpy as np
import pytest
from test_contact import _block

from fem.factorisation import FactorState
from fem.policy import DEFAULT_POLICY

#: The tests' tier (conftest.py): one part on a block, seconds.
TIER = "unit"


def _scene(**equilibrium):
    from inverse.scene import Scene
    from inverse.treatment import rigid_treatment

    return Scene(_block(3, 0), rigid_treatment(("mandible",), ("lateral_mm", "vertical_mm")),
                 contact="glued", equilibrium=equilibrium)


def _made(eq) -> int:
    return eq.stats.factorisations


def test_states_of_a_solve_a_sensitivity_and_a_restore():
    """NONE until the first solve; a solve leaves a factorisation of K at a former
    equilibrium (ITERATE); dx/dp, where that factor is too far to serve block CG (here:
    never, `SolverPolicy.sensitivity_cg_its` = 0), refactorises once at the new one
    (EQUILIBRIUM), is cached, and first-order steps reuse that factor; a restored
    equilibrium is another (ITERATE)."""
    scene = _scene(policy=dataclasses.replace(DEFAULT_POLICY, sensitivity_cg_its=0))
    eq = scene.eq
    assert eq.factor is FactorState.NONE
    base = eq.snapshot()
    scene.solve([0.5, -0.8])
    assert eq.factor is FactorState.ITERATE
    made = _made(eq)
    S = eq.sensitivity()
    assert eq.factor is FactorState.EQUILIBRIUM and _made(eq) == made + 1
    assert eq.sensitivity() is S and _made(eq) == made + 1   # cached, not refactorised
    step = eq.tangent_step(np.array([0.1, 0.0]), eq.load(-np.array([0.1, 0.0])))
    np.testing.assert_allclose(step.array, 0.1 * S[0].array, rtol=1e-8, atol=1e-12)
    assert _made(eq) == made + 1
    step.destroy()
    eq.restore(base)
    assert eq.factor is FactorState.ITERATE
    base[1].destroy()
    eq.destroy()


@pytest.mark.parametrize("lag", [DEFAULT_POLICY.tangent_lag_its, 0])
def test_sensitivity_by_block_cg_on_a_near_factorisation(lag):
    """Where the solve that reached the equilibrium needed at most
    `SolverPolicy.tangent_lag_its` iterations from the kept factorisation (of K at an
    iterate near here), dx/dp comes from CG on all columns at once, preconditioned by that
    factor: no factorisation, the factor still the iterate's, each residual |K s + df/dp|
    within CG's 1e-11 of |df/dp| (the tangent KSP's tolerance), and the block solve's dx/dp
    at the equilibrium within what that leaves (1e-6). A farther factor (lag 0)
    refactorises at the equilibrium."""
    scene = _scene(policy=dataclasses.replace(DEFAULT_POLICY, tangent_lag_its=lag))
    eq = scene.eq
    scene.solve([0.5, -0.8])
    eq.factorise_at_equilibrium()
    st = scene.solve([0.55, -0.75])   # a small step: few iterations from the kept factor
    assert st.iterations <= DEFAULT_POLICY.tangent_lag_its and eq.factor is FactorState.ITERATE
    made = _made(eq)
    S = eq.sensitivity()
    block_cg = lag > 0
    assert _made(eq) == made + (0 if block_cg else 1)
    assert eq.factor is (FactorState.ITERATE if block_cg else FactorState.EQUILIBRIUM)
    K, r = eq.tangent_matrix(), S[0].duplicate()
    for s, c in zip(S, eq.dfdp):
        K.mult(s, r)
        r.axpy(1.0, c)
        assert r.norm() <= 1e-11 * c.norm(), (r.norm(), c.norm())
    r.destroy()
    S = [s.array.copy() for s in S]
    eq.forget_sensitivities()
    eq.factorise_at_equilibrium()
    for s, e in zip(S, eq.sensitivity()):
        np.testing.assert_allclose(s, e.array, rtol=0, atol=1e-6 * np.abs(e.array).max())
    eq.destroy()


def test_block_cg_that_gives_up_falls_back_to_the_factorisation(monkeypatch):
    """Block CG stopped after one iteration (`SolverPolicy.sensitivity_cg_its` = 1) gives
    up; dx/dp then refactorises at the equilibrium and solves there, with the K that CG
    used: K is assembled once."""
    scene = _scene(policy=dataclasses.replace(DEFAULT_POLICY, sensitivity_cg_its=1))
    eq = scene.eq
    scene.solve([0.5, -0.8])
    eq.factorise_at_equilibrium()
    scene.solve([0.55, -0.75])
    assert eq.factor is FactorState.ITERATE
    made, real, assembled = _made(eq), eq.forms.jacobian, []
    monkeypatch.setattr(eq.forms, "jacobian", lambda x, out, turns_at=None: (
        assembled.append(out) or real(x, out, turns_at)))
    eq.sensitivity()
    assert eq.factor is FactorState.EQUILIBRIUM and _made(eq) == made + 1
    assert assembled == [eq.linearisation.K], assembled
    eq.destroy()


def test_a_slow_tangent_solve_makes_it_stale_and_the_next_refactorises():
    """A tangent solve that needs more than `SolverPolicy.tangent_lag_its` CG iterations
    leaves the factorisation STALE; the next tangent solve refactorises at the equilibrium
    first (with tangent_lag_its = 0 every CG solve is slow)."""
    scene = _scene(policy=dataclasses.replace(DEFAULT_POLICY, tangent_lag_its=0))
    eq = scene.eq
    scene.solve([0.5, -0.8])
    rhs, out = eq.load(-np.array([0.1, 0.0])), eq.u_eq.duplicate()
    made = _made(eq)
    assert eq.solve_tangent(rhs, out) >= 1
    assert eq.factor is FactorState.STALE and _made(eq) == made + 1
    eq.solve_tangent(rhs, out)
    assert eq.factor is FactorState.STALE and _made(eq) == made + 2
    for v in (rhs, out):
        v.destroy()
    eq.destroy()


def test_a_shifted_factorisation_is_not_used_as_the_equilibriums(monkeypatch):
    """Where K at the equilibrium is not positive definite (the inertia check reports a
    negative pivot), it is factorised with a diagonal shift (SHIFTED): dx/dp then comes from
    tangent solves on K itself, not the block solve; the first needs more than
    `SolverPolicy.tangent_lag_its` iterations on the shifted factor (STALE), so the next
    refactorises (unshifted now: EQUILIBRIUM), and dx/dp equals the unshifted block solve's
    (no block CG on the factor left by the solve: `SolverPolicy.sensitivity_cg_its` = 0)."""
    scene = _scene(policy=dataclasses.replace(DEFAULT_POLICY, sensitivity_cg_its=0))
    eq = scene.eq
    scene.solve([0.5, -0.8])
    exact = [s.array.copy() for s in eq.sensitivity()]
    eq.forget_sensitivities()
    eq.kept.moved()                                # as if the equilibrium had moved
    pivots = iter([1])                             # one negative pivot, then the real ones
    real_inertia, real_solve = eq.kept.inertia, eq.tangents.solve
    monkeypatch.setattr(eq.kept, "inertia",
                        lambda pc, A: next(pivots, None) or real_inertia(pc, A))
    seen = []
    monkeypatch.setattr(eq.tangents, "solve",
                        lambda rhs, out: seen.append(eq.factor) or real_solve(rhs, out))
    shifts = len(eq.stats.shifts)
    S = eq.sensitivity()
    assert seen == [FactorState.SHIFTED, FactorState.STALE], seen
    assert eq.factor is FactorState.EQUILIBRIUM and len(eq.stats.shifts) == shifts + 1
    for s, e in zip(S, exact):   # CG to 1e-11 of the residual against a direct solve
        np.testing.assert_allclose(s.array, e, rtol=0, atol=1e-8 * np.abs(e).max())
    eq.destroy()


@pytest.mark.parametrize("method", ["qn", "newton"])
def test_a_new_equilibrium_keeps_no_factorisation_as_its_own(method):
    """After any solve that moves the equilibrium the factorisation is not the new
    equilibrium's, whichever method solved it."""
    scene = _scene(method=method)
    eq = scene.eq
    scene.solve([0.3, 0.0])
    eq.factorise_at_equilibrium()
    assert eq.factor is FactorState.EQUILIBRIUM
    scene.solve([0.6, 0.2])
    assert eq.factor is FactorState.ITERATE
    eq.destroy()


def test_k_at_the_equilibrium_is_assembled_once_per_equilibrium(monkeypatch):
    """The linearisation (`fem.tangent.Linearisation`) assembles K at the equilibrium once,
    for the factorisation there, the sensitivities and `tangent_matrix` alike; a new
    equilibrium assembles it again, with its own state, and drops dx/dp."""
    scene = _scene()
    eq = scene.eq
    scene.solve([0.5, -0.8])
    K, real = eq.linearisation.K, eq.forms.jacobian
    at_eq = []   # the states K was assembled at
    monkeypatch.setattr(eq.forms, "jacobian", lambda x, out, turns_at=None: (
        out is K and at_eq.append(x.array.copy())) or real(x, out, turns_at))
    eq.sensitivity()
    assert eq.tangent_matrix() is K and len(at_eq) == 1 and eq.has_sensitivity
    scene.solve([0.6, -0.8])
    assert not eq.has_sensitivity
    eq.tangent_matrix()
    eq.sensitivity()
    assert len(at_eq) == 2
    np.testing.assert_array_equal(at_eq[1], eq.u_eq.array)
    expected = K.duplicate()
    real(eq.u_eq, expected)
    expected.axpy(-1.0, K)
    assert expected.norm() == 0.0
    expected.destroy()
    eq.destroy()


def test_the_snes_set_shares_one_ksp_and_keeps_relaxations_pairs_until_dropped():
    """`SnesSet`: every quasi-Newton SNES (a fresh one per solve, relaxation's) uses Newton's
    KSP, so one factorisation serves them all, and dropping one keeps that KSP's factor;
    relaxation's SNES is resumed until dropped; each has its options prefix."""
    scene = _scene()
    eq = scene.eq
    scene.solve([0.5, -0.8])
    eq.factorise_at_equilibrium()
    sset, ksp = eq.snes_set, eq.snes_set.ksp
    first = sset.method(False, 5)
    second = sset.method(False, 5)
    assert first.handle == 0 and second is sset.qn   # the first was destroyed
    relax = sset.relax(3, resume=False)
    assert sset.relax(4, resume=True) is relax and relax.getTolerances()[3] == 4
    sset.drop_relaxation()
    assert sset.relaxation is None and sset.relax(3, resume=True) is not relax
    for snes in (second, sset.relaxation):
        assert snes.getKSP().handle == ksp.handle
        assert snes.getOptionsPrefix() == "orthodiff_fwd_qn_"
    assert sset.method(True, 5) is sset.newton and sset.newton.getOptionsPrefix() == \
        "orthodiff_fwd_"
    assert ksp.getPC().getFactorMatrix().handle != 0   # the factor survives the drops
    rhs, out = eq.load(-np.array([0.1, 0.0])), eq.u_eq.duplicate()
    ksp.getPC().apply(rhs, out)
    np.testing.assert_allclose(out.array, 0.1 * eq.sensitivity()[0].array, rtol=1e-8,
                               atol=1e-12)
    for v in (rhs, out):
        v.destroy()
    eq.destroy()


def test_a_kept_factorisation_serves_only_while_nothing_asks_for_a_new_one():
    """`KeptFactor.serves`: none held, a refactorisation asked for, a shift pending, a slow
    last solve, or (for quasi-Newton) a shifted factor: a new one; else it serves."""
    from mpi4py import MPI
    from petsc4py import PETSc

    from fem.factorisation import KeptFactor
    from fem.state import SolveStats

    A = PETSc.Mat().createAIJ((3, 3), nnz=1, comm=MPI.COMM_SELF)
    for i in range(3):
        A.setValue(i, i, 2.0)
    A.assemble()
    ksp = PETSc.KSP().create(MPI.COMM_SELF)
    ksp.getPC().setType("none")
    kept, stats = KeptFactor(ksp, MPI.COMM_SELF, {}, "unit_", 1e6, DEFAULT_POLICY), SolveStats()
    assert not kept.serves(0, 30)                      # nothing held
    kept.factorise(A, stats)
    assert kept.state is FactorState.ITERATE and stats.factorisations == 1
    assert kept.serves(30, 30) and not kept.serves(31, 30)
    kept.request_refactor()
    assert not kept.serves(0, 30)
    kept.factorise(A, stats)                           # the request is met
    assert kept.serves(0, 30)
    kept.set_shift(0.5)
    assert not kept.serves(0, 30)                      # a shift pending
    kept.factorise(A, stats)                           # a shifted factor
    kept.set_shift(0.0)
    assert kept.step_shift == 0.5
    assert kept.serves(0, 30) and not kept.serves(0, 30, unshifted=True)
    for obj in (ksp, A):
        obj.destroy()
