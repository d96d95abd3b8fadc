"""The engine's strategy parts on their own, on a block of tissue (docs/design.md): the shared
`fem.state.EquilibriumState`, `Refactorisation`, `PathFollower` and `NonlinearSolver`, each
driven through its own methods rather than the facade's solve."""

import dataclasses

import numpy as np
import pytest
from test_factorisation import _made, _scene

from fem.factorisation import FactorState
from fem.policy import DEFAULT_POLICY
from meshes.errors import InputError

#: The tests' tier (conftest.py): one part on a block, seconds.
TIER = "unit"


def test_the_parts_share_one_state_and_settings_are_replaced_whole():
    """The facade's settings are the state's: a policy or method set on the facade is what
    every part reads; a bad one is refused and leaves the settings as they were; the step
    tolerance is validated."""
    eq = _scene().eq
    st = eq.state
    for part in (eq.refactorisation, eq.tangents, eq.path, eq.solver):
        assert part.state is st
    opts = eq.settings
    eq.policy = policy = dataclasses.replace(DEFAULT_POLICY, min_substep=0.5)
    assert st.policy is policy and eq.settings is not opts
    assert eq.kept.policy is eq.stop.policy is eq.linearisation.policy is policy
    assert eq.settings.max_it == opts.max_it and eq.settings.lag_its == opts.lag_its
    eq.method = "newton"
    assert eq.refactorisation.method_snes() is eq.snes_set.newton
    eq.method = "qn"
    assert eq.refactorisation.method_snes() is eq.snes_set.qn is not None
    before = eq.settings
    with pytest.raises(InputError, match="unknown method"):
        eq.method = "bfgs"
    assert eq.settings is before
    with pytest.raises(InputError):
        eq.set_xtol(-1.0)
    with eq.keeping_xtol():
        eq.set_xtol(1e-6)
        assert st.xtol == 1e-6
    assert st.xtol == opts.xtol
    eq.destroy()


def test_refactorisation_keeps_the_factor_for_quasi_newton_while_it_serves():
    """The SNES Jacobian callback: for a quasi-Newton SNES, nothing is assembled or
    factorised while the kept factor serves (a lagged step); a refactorisation asked for,
    or a Newton SNES, factorises."""
    scene = _scene()
    eq = scene.eq
    scene.solve([0.5, -0.8])
    refac, st = eq.refactorisation, eq.state
    qn = refac.method_snes()
    made, lagged = _made(eq), st.stats.lagged
    st.last_its = 0
    refac.jacobian(qn, eq.u_eq, eq.A)
    assert (_made(eq), st.stats.lagged) == (made, lagged + 1)
    eq.kept.request_refactor()
    refac.jacobian(qn, eq.u_eq, eq.A)
    assert _made(eq) == made + 1 and eq.factor is FactorState.ITERATE
    refac.jacobian(eq.snes_set.newton, eq.u_eq, eq.A)
    assert _made(eq) == made + 2
    refac.at_equilibrium()
    assert eq.factor is FactorState.EQUILIBRIUM
    eq.destroy()


def test_path_follower_predicts_and_relaxes_without_moving_the_equilibrium():
    """A first-order state is the equilibrium plus dx/dp dp (translations); a step that
    inverts an element is not admissible; relaxing the prediction lowers its residual; none
    of them moves the equilibrium (p, u) nor leaves the forms elsewhere."""
    scene = _scene()
    eq = scene.eq
    scene.solve([0.5, -0.8])
    path, st = eq.path, eq.state
    p0, u0 = st.p.copy(), st.u_eq.copy()
    p1 = p0 + np.array([0.4, 0.3])
    x = path.first_order(p1)
    step = eq.tangent_step(p1 - p0)
    ref = u0.copy()
    ref.axpy(1.0, step)
    # rigid goals: the response to the exact goals at p1 (`EnergyForms.goal_load`), which
    # translations make dx/dp dp up to the solver's tolerance
    np.testing.assert_allclose(x.array, ref.array, rtol=0, atol=1e-6 * np.abs(step.array).max())
    huge = step.copy()
    huge.scale(1e4)
    assert path.admissible(st.u_eq, huge) is None
    r0, r1 = eq.b.duplicate(), eq.b.duplicate()
    eq.set_params(p1)
    eq.residual(x, r0)   # at p1's goals
    stats = path.relax(p1, x, 5)
    assert np.array_equal(st.p, p0) and st.u_eq.equal(u0) and eq.forms.uvec.equal(u0)
    np.testing.assert_array_equal(eq.goal.x.array, scene.eq.goals.goal(p0))
    eq.set_params(p1)
    eq.residual(x, r1)
    assert stats.iterations >= 1 and r1.norm() < 0.1 * r0.norm(), (r0.norm(), r1.norm())
    eq.set_params(p0)
    for v in (u0, x, step, ref, huge, r0, r1):
        v.destroy()
    eq.destroy()


def test_nonlinear_solver_solves_at_a_p_then_commits():
    """`solve_at` is one SNES solve: it leaves the equilibrium (state.p, u_eq) where it
    was and the forms at the new state; the facade's solve then commits the same state."""
    scene = _scene()
    eq = scene.eq
    st, solver = eq.state, eq.solver
    p = np.array([0.5, -0.8])
    eq.set_params(p)
    solver.solve_at(p, st.p)
    assert not np.any(st.p) and np.abs(st.u_eq.array).max() == 0.0
    u = eq.forms.uvec.array.copy()
    assert np.abs(u).max() > 0.1
    scene.solve(p)
    np.testing.assert_allclose(st.u_eq.array, u, rtol=0, atol=5 * st.xtol)
    assert np.array_equal(st.p, p) and st.solved_xtol == st.xtol
    eq.destroy()
