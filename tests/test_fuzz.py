"""Property-based fuzzing (hypothesis): every run converges or raises a documented error;
none hangs (bounded iterations) and none returns NaN."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from inverse.objective import HEAD_AXES
from meshes.errors import InputError, SolverError

#: The tests' tier (conftest.py): fuzzing the tiny heads.
TIER = "integration"

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


#: The landmarks of the fuzzed target sets.
LANDMARKS = ["Pg", "Li", "Ls", "Me"]
#: One defect each: (landmark, value, whether the value (its "at" in a held entry) is an
#: offset from its rest position); ``None``: every entry removed.
DEFECTS = [("Chin", [0.0, 0.0, 0.0], False),            # no such landmark
           ("Pg", [float("nan"), 0.0, 0.0], False), ("Li", [0.0, float("inf"), 0.0], False),
           ("Ls", [1.0, 2.0], False), ("Me", [1.0, 2.0, 3.0, 4.0], False), ("Pg", "abc", False),
           ("Li", [], False), ("Ls", [[1.0, 2.0, 3.0]], False),
           ("Me", [0.0, 0.0, 150.0], True),              # beyond ABSURD_TARGET_MM
           ("Pg", {"along": ["anterior"]}, False),       # held, and no point
           ("Li", {"at": [0.0, 1.0, 0.0], "along": ["forward"]}, True),
           ("Ls", {"at": [0.0, 1.0, 0.0], "along": []}, True),
           ("Me", {"at": [0.0, 1.0, 0.0], "along": ["left", "left"]}, True),
           ("Pg", {"at": [0.0, 1.0, 0.0], "along": "anterior"}, True),
           ("Li", {"at": [0.0, 1.0, 0.0], "by": 1.0}, True),
           None]


def _offsets():
    """{landmark: ((3,) mm from its rest position, the head axes it is held along or None:
    all)}, within 40 mm (beyond 30 mm a warning)."""
    vec = st.lists(st.floats(-23.0, 23.0), min_size=3, max_size=3)
    along = st.none() | st.lists(st.sampled_from(HEAD_AXES), min_size=1, max_size=3,
                                 unique=True)
    return st.dictionaries(st.sampled_from(LANDMARKS), st.tuples(vec, along), min_size=1,
                           max_size=4)


def _entry(x, along):
    return x if along is None else {"at": x, "along": along}


@pytest.mark.parametrize("defects", [[False], DEFECTS], ids=["valid", "one-defect"])
@settings(max_examples=20, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_target_validation_accepts_valid_and_names_each_defect(mandible_scene, defects, data):
    """As many valid target sets as defective ones: valid targets (offsets from rest, the
    far ones with a warning) are taken as given; a set with one of `DEFECTS` raises
    InputError, never anything else."""
    import warnings

    offsets, defect = data.draw(_offsets()), data.draw(st.sampled_from(defects))
    rest = mandible_scene.landmarks(rest=True)
    targets = {n: _entry((np.asarray(rest[n]) + v).tolist(), along)
               for n, (v, along) in offsets.items()}
    if defect is None:
        targets = {}
    elif defect:
        name, value, relative = defect
        at = lambda v: (np.asarray(rest[name]) + v).tolist() if relative else v  # noqa: E731
        targets[name] = dict(value, at=at(value["at"])) if isinstance(value, dict) \
            else at(value)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if defect is not False:
            with pytest.raises(InputError):
                mandible_scene.objective(targets)
            return
        obj = mandible_scene.objective(targets)
    assert obj.n_points == len(targets)
    np.testing.assert_allclose(obj.targets, [np.asarray(rest[n]) + offsets[n][0]
                                             for n in targets])
    assert obj.held.tolist() == [[a in (offsets[n][1] or HEAD_AXES) for a in HEAD_AXES]
                                 for n in targets]
    for n, (_, along) in offsets.items():   # as a file writes them: a list when all held
        point = (np.asarray(rest[n]) + offsets[n][0]).tolist()
        want = point if along is None or len(along) == 3 else {
            "at": point, "along": [a for a in HEAD_AXES if a in along]}
        assert obj.entries()[n] == want
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
