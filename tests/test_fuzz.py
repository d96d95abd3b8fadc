"""Property-based fuzzing (hypothesis): every run converges or raises a documented error;
none hangs (bounded iterations) and none returns NaN."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from meshes.errors import InputError, SolverError

FUZZ = settings(max_examples=8, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@FUZZ
@given(st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6))
def test_forward_within_bounds_converges_or_says_why(mandible_scene, frac):
    scene = mandible_scene
    lo, hi = scene.treatment.bounds.T
    p = 0.5 * (lo + hi) + 0.2 * (hi - lo) * np.array(frac)   # the middle 40 % of the range
    try:
        scene.solve(p)
    except SolverError as e:       # documented: says the largest reachable step
        assert "largest step reached" in str(e)
        assert np.all(np.isfinite(scene.eq.u.x.array))
        return
    assert np.all(np.isfinite(scene.eq.u.x.array))
    assert scene.eq.min_det_F() > 0
    assert all(np.all(np.isfinite(x)) for x in scene.landmarks().values())
    scene.solve(np.zeros(6))


@FUZZ
@given(st.dictionaries(st.sampled_from(["Pg", "Li", "Ls", "Me", "Chin", ""]),
                       st.one_of(st.lists(st.floats(allow_nan=True, allow_infinity=True),
                                          min_size=0, max_size=4), st.text(max_size=3)),
                       max_size=4))
def test_target_validation_accepts_or_raises_input_error(mandible_scene, targets):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            obj = mandible_scene.objective(targets)
        except InputError:
            return
    assert np.all(np.isfinite(obj.targets)) and obj.n_points >= 1
    assert np.isfinite(obj.value())


@pytest.mark.parametrize("start", ["far", "bounds"])
def test_plan_from_bad_starts_decreases_monotonically(mandible_scene, start):
    """From far off the optimum, or at the bounds, T never increases."""
    scene = mandible_scene
    scene.solve(np.zeros(6))
    rest = scene.landmarks(rest=True)
    targets = {n: (rest[n] + [0.0, 3.0, -1.0]).tolist() for n in ("Pg", "Li", "Me")}
    bounds = np.tile([-6.0, 6.0], (6, 1))
    p0 = np.array([-6.0, 4.0, 0, 0, 0, 0]) if start == "far" else \
        np.array([-6.0, 6.0, 0, 0, 0, -6.0])   # on the bounds, pointing away from the goal
    res = scene.plan(targets, p0=p0, bounds=bounds, max_iterations=6)
    T = [h["T"] for h in res.history]
    assert all(b <= a for a, b in zip(T, T[1:])), T
    assert T[-1] < 0.5 * T[0]
    assert np.all(np.isfinite(res.params))
    scene.solve(np.zeros(6))
