"""The stopping test on its own (`fem.stopping.StoppingTest`): a SNES stand-in feeds it
iterates and residual norms, and each rule stops where docs/design.md says (no mesh)."""

from mpi4py import MPI  # noqa: F401 (first: it loads the MPI library PETSc links)
from petsc4py import PETSc

import dataclasses

import numpy as np
import pytest

from fem.policy import DEFAULT_POLICY
from fem.stopping import DIVERGED_NAN, StoppingTest

#: The tests' tier (conftest.py): one part on its own, no mesh.
TIER = "unit"
Reason = PETSc.SNES.ConvergedReason


class _Snes:
    """The part of a SNES the test reads: its type, iterate and iteration limit."""

    def __init__(self, kind="qn", max_it=50):
        self.kind, self.max_it = kind, max_it
        self.x = PETSc.Vec().createSeq(3)
        self.x.set(0.0)

    def getType(self):
        return self.kind

    def getSolution(self):
        return self.x

    def getTolerances(self):
        return 0.0, 0.0, 0.0, self.max_it

    def solve(self, b, x):
        pass


@dataclasses.dataclass
class _Kept:
    step_shift: float = 0.0


def _run(test, snes, steps, norms, direction=0.0):
    """Iterations 0.. with the iterate moved by ``steps[i]`` (mm, inf-norm) before each and
    residual norms ``norms``: the reasons, up to the first nonzero one."""
    reasons = []
    for it, (step, fnorm) in enumerate(zip(steps, norms)):
        snes.x.shift(step)
        test.precheck(None, _vec(direction))
        reasons.append(test(snes, it, (0.0, 0.0, fnorm)))
        if reasons[-1]:
            break
    return reasons


def _vec(value):
    v = PETSc.Vec().createSeq(3)
    v.set(value)
    return v


def _test(**policy):
    test = StoppingTest(_vec(0.0), dataclasses.replace(DEFAULT_POLICY, **policy), _Kept())
    history = []
    test.start(xtol=0.01, frtol=1e-3, atol=1e-12, history=history, f_ref=None)
    return test, history


def test_a_short_step_with_a_small_residual_converges():
    """Newton: the step 1e-3 mm with the residual 1e-4 of the first stops converged; every
    norm is in the history."""
    test, history = _test()
    reasons = _run(test, _Snes("newtonls"), [0.0, 1.0, 1e-3], [1.0, 1e-2, 1e-4])
    assert reasons == [0, 0, Reason.CONVERGED_SNORM_RELATIVE]
    assert history == [1.0, 1e-2, 1e-4] and test.refresh is None


@pytest.mark.parametrize("frtol_met, shift", [(False, 0.0), (True, 1.0)])
def test_a_short_step_alone_or_a_shifted_one_goes_on(frtol_met, shift):
    """Newton: a short step whose residual is still large, or a short step of a shifted
    matrix (not a full Newton step), does not stop."""
    test, _ = _test()
    test.kept.step_shift = shift
    norm = 1e-4 if frtol_met else 0.5
    assert _run(test, _Snes("newtonls"), [0.0, 1.0, 1e-3], [1.0, 1e-2, norm]) == [0, 0, 0]


def test_an_absolute_residual_and_a_nan_stop_at_once():
    test, _ = _test()
    assert _run(test, _Snes(), [0.0], [1e-13]) == [Reason.CONVERGED_FNORM_ABS]
    assert _run(test, _Snes(), [0.0, 1.0], [1.0, np.nan]) == [0, DIVERGED_NAN]


def test_quasi_newton_needs_a_short_search_direction_too():
    """Quasi-Newton: a short step with a long search direction goes on; with the direction
    short too, it stops."""
    test, _ = _test()
    steps, norms = [0.0, 1.0, 1e-3], [1.0, 1e-2, 1e-4]
    assert _run(test, _Snes(), steps, norms, direction=1.0) == [0, 0, 0]
    assert _run(test, _Snes(), steps, norms, direction=1e-3)[-1] == \
        Reason.CONVERGED_SNORM_RELATIVE


def test_a_slow_rate_stops_later():
    """Quasi-Newton at a linear rate of 0.9: a step of 0.005 mm leaves ~0.045 mm, more than
    xtol = 0.01: it goes on; at a rate of 0.5 the same step stops (the residual met)."""
    for rate, want in ((0.9, 0), (0.5, Reason.CONVERGED_SNORM_RELATIVE)):
        test, history = _test()
        test.start(0.01, 1.0, 1e-30, history)
        norms = [1e-3 * rate ** i for i in range(5)]
        reasons = _run(test, _Snes(), [0.0, 1.0, 1.0, 1.0, 0.005], norms, direction=0.005)
        assert reasons[-1] == want, (rate, reasons)
        assert test.error_per_step(4) == pytest.approx(max(1.0, rate / (1 - rate)))


def test_a_stall_stops_to_refresh_and_says_so():
    """Quasi-Newton whose residual has not fallen by `SolverPolicy.stall_ratio` over
    ``stall_its`` iterations stops (DIVERGED_MAX_IT) with ``refresh == "stalled"``; the next
    run clears it."""
    test, _ = _test(stall_its=3, stall_ratio=0.5)
    snes = _Snes()
    reasons = _run(test, snes, [0.0] + [1.0] * 6, [1.0] * 7, direction=1.0)
    assert reasons == [0, 0, 0, Reason.DIVERGED_MAX_IT] and test.refresh == "stalled"
    test.run(snes, snes.x)
    assert test.refresh is None


def test_an_armed_tangent_refresh_fires_once_near_convergence():
    """Armed (``tangent=True``), quasi-Newton stops once within `tangent_refresh_xtols` x
    xtol after `tangent_lag_its` iterations, ``refresh == "tangent"``; then it is disarmed,
    and the same iterations go on."""
    policy = dict(tangent_lag_its=1, tangent_refresh_xtols=10.0, stall_its=100)
    test, history = _test(**policy)
    test.start(0.01, 1e-12, 1e-30, history, f_ref=None, tangent=True)
    steps, norms = [0.0, 1.0, 0.05, 0.05], [1.0, 0.5, 0.25, 0.125]
    assert _run(test, _Snes(), steps, norms, direction=0.05) == [0, 0, Reason.DIVERGED_MAX_IT]
    assert test.refresh == "tangent" and not test.tangent
    assert _run(test, _Snes(), steps, norms, direction=0.05) == [0, 0, 0, 0]


def test_the_iteration_limit():
    test, _ = _test()
    assert _run(test, _Snes("newtonls", max_it=2), [0.0, 1.0, 1.0], [1.0, 0.9, 0.8]) == \
        [0, 0, Reason.DIVERGED_MAX_IT]
