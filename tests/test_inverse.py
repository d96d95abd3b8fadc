"""Inverse planning on tiny meshes: adjoint gradient, S_T, Gauss-Newton step, recovery."""

from mpi4py import MPI

import numpy as np
import pytest

from fem.policy import available
from fem.verification import taylor_test
from inverse.planner import reduced_step
from meshes.errors import InputError

#: The tests' tier (conftest.py): planning on the tiny heads.
TIER = "integration"
#: Tests of the CHOLMOD preset: PyPI's PETSc has no SuiteSparse.
NEEDS_CHOLMOD = pytest.mark.skipif(not available("cholmod"), reason="this PETSc has no CHOLMOD")


@pytest.fixture
def scene(tight_scene):
    return tight_scene


#: Both contacts, and the tissues' materials, for the derivative checks
#: (``request.getfixturevalue`` of each scene).
CONTACT_SCENES = pytest.mark.parametrize(
    "contact_scene", ["tight_sliding", "tight_scene", "tight_tissues"],
    ids=["sliding", "glued", "sliding-tissues"])


P0 = np.array([3.0, -1.0, 1.0, 2.0, 1.0, -2.0])
#: A point with rotations of 5-10°, where the exact rigid motions are far from linear.
P_ROT = np.array([2.0, -1.0, 1.0, 8.0, 6.0, -7.0])


def _objective(scene, names=("Pg", "Li", "Me", "Ls"), shift=(1.0, -2.0, 0.5), **kw):
    rest = scene.landmarks(rest=True)
    targets = {n: (rest[n] + np.asarray(shift) * (1 + i)).tolist() for i, n in enumerate(names)}
    return scene.objective(targets, **kw)


def _T_at(scene, obj, p):
    scene.solve(p)
    return obj.value()


@CONTACT_SCENES
@pytest.mark.parametrize("p0", [P0, P_ROT], ids=["small", "rotated"])
def test_taylor_adjoint_gradient(request, contact_scene, rng, p0):
    """The adjoint gradient: Taylor remainders of rate 1 without it and 2 with it, the lips
    sliding on the teeth (whose normals turn with the mandible) and glued."""
    scene = request.getfixturevalue(contact_scene)
    obj = _objective(scene, weights={"Pg": 2.0}, tikhonov=0.01)
    _T_at(scene, obj, p0)   # the equilibrium the gradient is taken at
    g = obj.gradient()
    for _ in range(2):   # random asymmetric directions
        d = rng.standard_normal(6)
        rate1, rate2 = taylor_test(lambda q: _T_at(scene, obj, q), p0, d, g @ d,
                                   0.2 * 0.5 ** np.arange(4))
        assert abs(rate1[-1] - 1) < 0.1, rate1    # asymptotically 1 without the gradient
        assert np.all(np.abs(rate2 - 2) < 0.1), rate2   # 2 with it
        scene.solve(p0)


def test_tangent_ready_solve_serves_the_adjoint_without_a_factorisation(mandible_only,
                                                                        tiny_anatomy):
    """solve(tangent=True): a quasi-Newton solve slower than TANGENT_LAG_ITS iterations
    refactorises once near convergence; the adjoint gradient then reuses that factorisation
    (CG, no new one) and equals the gradient with a factorisation at the equilibrium
    itself."""
    from fem.policy import DEFAULT_POLICY

    TANGENT_LAG_ITS = DEFAULT_POLICY.tangent_lag_its

    points, stats = {}, {}
    for tangent in (False, True):   # fresh scenes: both start from a factorisation at rest
        scene = mandible_only(tiny_anatomy, equilibrium=dict(xtol=1e-4))
        obj = _objective(scene)
        stats[tangent] = scene.solve(P0, tangent=tangent)
        points[tangent] = obj.points()
    assert stats[False].iterations > TANGENT_LAG_ITS   # the refresh has a use
    assert (stats[False].factorisations, stats[True].factorisations) == (1, 2)
    assert np.abs(points[True] - points[False]).max() < 1e-3   # the same equilibrium, mm
    eq, calls = scene.eq, []
    refactorise = eq.refactorisation.at_equilibrium
    eq.refactorisation.at_equilibrium = lambda: calls.append(1) or refactorise()
    g = obj.gradient()
    assert calls == [] and eq.tangent_ksp.getIterationNumber() > 1   # reused, iterated
    eq.factorise_at_equilibrium()   # now with K at the equilibrium itself
    assert stats[True].factorisations == 2   # the solve's stats stay the solve's
    g_exact = obj.gradient()
    assert eq.tangent_ksp.getIterationNumber() <= 2
    assert np.abs(g - g_exact).max() < 1e-8 * np.abs(g_exact).max()
    T, g_api = obj.value_and_gradient(P0)   # already there: no solve, the same gradient
    assert T == obj.value() and np.abs(g_api - g_exact).max() < 1e-8 * np.abs(g_exact).max()


@CONTACT_SCENES
@pytest.mark.parametrize("p0", [P0, P_ROT], ids=["small", "rotated"])
def test_landmark_sensitivity_matches_finite_differences(request, contact_scene,
                                                         central_differences, p0):
    scene = request.getfixturevalue(contact_scene)
    obj = _objective(scene)
    scene.solve(p0)
    S_direct, m1 = obj.jacobian("direct")
    S_adjoint, m2 = obj.jacobian("adjoint")
    assert (m1, m2) == ("direct", "adjoint")
    assert np.abs(S_direct - S_adjoint).max() < 1e-8 * np.abs(S_direct).max()
    # h = 4e-3: truncation 2e-8 at P_ROT (5e-9 at 2e-3: rate 2), while the forward solves'
    # ~1e-8 mm noise, divided by 2h, reached 3e-5 at h = 1e-3
    fd = central_differences(scene, obj, p0, h=4e-3)
    err = np.abs(fd - S_direct).max() / np.abs(S_direct).max()
    assert err < 1e-5, err
    # the auto mode picks the cheaper side: 6 parameters < 12 rows -> direct
    assert obj.jacobian()[1] == "direct"


def _turn(pitch, roll, yaw):
    """(3, 3) a rotation by the angles (degrees) about x, y and z."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", [pitch, roll, yaw], degrees=True).as_matrix()


def test_targets_held_along_tilted_head_axes(scene, rng):
    """Targets held along some axes of a tilted head frame: the adjoint gradient passes the
    Taylor test, S_T's rows are along the head's axes in both modes and give the gradient,
    a target moved along its free axes changes neither T nor dT/dp, and with every axis held
    T is the scene-frame objective's (a rotation keeps distances)."""
    from inverse.objective import Objective

    names = ["Pg", "Li", "Me", "Ls"]
    held = np.array([[0, 1, 0], [0, 1, 1], [1, 1, 1], [1, 0, 0]], bool)
    axes = _turn(8.0, -5.0, 6.0)
    op = scene.domain.point_operator(names)
    rest = scene.landmarks(rest=True)
    targets = np.array([rest[n] + [1.0, -2.0, 0.5] for n in names])
    w = np.array([2.0, 1.0, 0.5, 1.0])

    def objective(pts, held=held, axes=axes):
        return Objective(scene.eq, op, pts, w, 0.01, names, axes, held)

    obj = objective(targets)
    scene.solve(P0)
    g = obj.gradient()
    d = rng.standard_normal(6)
    rate1, rate2 = taylor_test(lambda q: _T_at(scene, obj, q), P0, d, g @ d,
                               0.2 * 0.5 ** np.arange(4))
    assert abs(rate1[-1] - 1) < 0.1 and np.all(np.abs(rate2 - 2) < 0.1), (rate1, rate2)
    scene.solve(P0)
    S_direct, S_adjoint = obj.jacobian("direct")[0], obj.jacobian("adjoint")[0]
    assert np.abs(S_direct - S_adjoint).max() < 1e-8 * np.abs(S_direct).max()
    gn = S_direct.T @ (obj.weights.ravel() * obj.residual().ravel()) + 0.01 * scene.eq.p
    assert np.abs(gn - g).max() < 1e-8 * np.abs(g).max()
    free = objective(targets + 5.0 * (~held) @ axes.T)   # 5 mm along each free axis
    assert free.value() == pytest.approx(obj.value(), rel=1e-12)
    assert np.abs(free.gradient() - g).max() < 1e-10 * np.abs(g).max()
    assert np.allclose(free.distances(), obj.distances(), rtol=1e-12)
    every = np.ones_like(held)
    assert objective(targets, every).value() == pytest.approx(
        objective(targets, every, np.eye(3)).value(), rel=1e-12)
    assert obj.entries()["Pg"]["along"] == ["anterior"] and isinstance(
        obj.entries()["Me"], list)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="assembles the KKT system on one rank")
def test_kkt_and_reduced_system_give_the_same_step(scene):
    """The sparse KKT system in (dx, dp, λ) and the reduced S_T system: the same dp."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    obj = _objective(scene, weights={"Pg": 3.0, "Li": 0.5}, tikhonov=0.02)
    scene.solve(P0)
    eq, op = scene.eq, obj.op
    indptr, indices, data = eq.tangent_matrix().getValuesCSR()
    n = len(indptr) - 1
    K = sp.csr_matrix((data, indices, indptr), shape=(n, n))
    G = np.stack([g.array for g in eq.dfdp], axis=1)
    L = sp.coo_matrix((np.repeat(op.weight, 3),
                       (3 * np.repeat(op.point, 3) + np.tile([0, 1, 2], len(op.point)),
                        3 * np.repeat(op.block, 3) + np.tile([0, 1, 2], len(op.block)))),
                      shape=(3 * op.n_points, n)).tocsr()
    w3 = obj.weights.ravel()
    W = sp.diags(w3)
    r = obj.residual().ravel()
    alpha = obj.tikhonov
    kkt = sp.bmat([[L.T @ W @ L, None, K],
                   [None, sp.identity(6) * alpha, sp.csr_matrix(G.T)],
                   [K, sp.csr_matrix(G), None]], format="csc")
    rhs = np.concatenate([-(L.T @ (w3 * r)), -alpha * eq.p, np.zeros(n)])
    sol = spla.spsolve(kkt, rhs)
    dp_kkt = sol[n:n + 6]
    S, _ = obj.jacobian()
    dp_red = reduced_step(S, w3, r, eq.p, alpha, 0.0, np.ones(6, bool))
    assert np.abs(dp_kkt - dp_red).max() < 1e-7 * np.abs(dp_red).max()


@pytest.mark.parametrize("case,subset,names,seed", [
    ("class3", ["mandible.advance_mm", "mandible.vertical_mm", "mandible.yaw_deg",
                "mandible.pitch_deg"], ["Pg", "Li"], 0),
    ("class3", None, ["Pg", "Li", "Me"], 1),
    ("class2", ["mandible.advance_mm", "mandible.lateral_mm", "maxilla_L.advance_mm",
                "maxilla_R.advance_mm"], ["Pg", "Ls", "Li"], 2),
    ("class3-asym", ["mandible.lateral_mm", "mandible.yaw_deg", "mandible.roll_deg",
                     "maxilla_L.vertical_mm", "maxilla_R.vertical_mm"], ["Pg", "Me", "Ls"], 3),
])
def test_plan_recovers_known_parameters(case, subset, names, seed):
    """Targets from a forward solve at p*: the plan from 0 finds them and p*."""
    from inverse.scene import Scene
    from inverse.treatment import rigid_treatment

    tr = rigid_treatment(("mandible",)) if subset is None else None
    scene = Scene.from_case(case, "tiny", treatment=tr, params_used=subset)
    n_p = len(scene.param_names)
    assert n_p <= 3 * len(names)
    rng = np.random.default_rng(seed)
    p_star = rng.uniform(-4, 4, n_p)
    with scene.eq.keeping_xtol():   # exactly reachable targets
        scene.eq.set_xtol(1e-9)
        scene.solve(p_star)
    targets = {k: v.tolist() for k, v in scene.landmarks(names).items()}
    scene.solve(np.zeros(n_p))
    res = scene.plan(targets, tikhonov=0.0, ftol=1e-6)
    obj = scene.objective(targets)
    assert res.converged, res.reason
    assert obj.distances().mean() < 0.01
    assert np.abs(res.params - p_star).max() < 1e-3 * np.abs(p_star).max()
    assert res.gn_iterations <= 5
    assert res.history[-1]["T"] < res.history[0]["T"]
    assert all(h1["T"] <= h0["T"] for h0, h1 in zip(res.history, res.history[1:]))


def test_plan_respects_bounds_and_reports_non_convergence(scene):
    obj = _objective(scene, names=("Pg", "Li", "Me"), shift=(0.0, 6.0, 0.0))
    bounds = np.tile([-1.0, 1.0], (6, 1))
    from inverse.planner import gauss_newton

    res = gauss_newton(scene, obj, bounds=bounds, max_iterations=2)
    assert np.all(np.abs(res.params) <= 1.0 + 1e-12)
    assert res.objective < res.objective_initial
    assert not res.converged and res.reason == "iteration limit"


def test_bad_targets_get_clear_errors(scene):
    rest = {k: v.tolist() for k, v in scene.landmarks(rest=True).items()}
    with pytest.raises(InputError, match="unknown landmark"):
        scene.objective({"Chin": [0, 0, 0]})
    with pytest.raises(InputError, match="not finite"):
        scene.objective({"Pg": [np.nan, 0, 0]})
    with pytest.raises(InputError, match="not finite"):
        scene.objective({"Pg": [np.inf, 0, 0]})
    with pytest.raises(InputError, match="at least one landmark"):
        scene.objective({})
    with pytest.raises(InputError, match="3-vector"):
        scene.objective({"Pg": [1, 2]})
    with pytest.warns(UserWarning, match="mm from its rest position"):
        scene.objective({"Pg": (np.array(rest["Pg"]) + [0, 80, 0]).tolist()})
    with pytest.raises(InputError, match="targets are in mm"):     # given in metres
        scene.objective({"Pg": (np.array(rest["Pg"]) / 1000).tolist()})
    from inverse.planner import gauss_newton

    obj = scene.objective({"Pg": rest["Pg"]})
    with pytest.raises(InputError, match="outside the bounds"):
        gauss_newton(scene, obj, p0=np.full(6, 5.0), bounds=np.tile([-1.0, 1.0], (6, 1)))


def test_default_goals_follow_the_clinical_rules():
    """class2: 3 landmarks, class3-asym: 7; chin onto the midline, lips to Arnett's TVL."""
    from inverse.targets import TVL_NORMS_MM, default_targets
    from meshes.synthetic import synthetic_head

    for case, n in [("class2", 3), ("class3-asym", 7)]:
        a = synthetic_head(case, "tiny")
        rest = {k: (a.points[lm.facet] * np.asarray(lm.weights)[:, None]).sum(0)
                for k, lm in a.landmarks.items()}
        t = default_targets(case, rest)
        assert len(t) == n
        assert t["Pg"][1] == pytest.approx(rest["Sn"][1] + TVL_NORMS_MM["Pg"])
        if case == "class3-asym":
            assert t["Pg"][0] == pytest.approx(0.5 * (rest["N"][0] + rest["Sn"][0]))
            assert t["Sn"] == pytest.approx(rest["Sn"].tolist())


def test_e_line_goal_puts_the_lips_at_ricketts_distances():
    """The e-line goal: Ls and Li moved along y only, to 4 and 2 mm behind the Prn-Pg line
    in the profile, in a tilted head frame too (targets in the scene's frame)."""
    from inverse.targets import E_LINE_MM, default_targets
    from meshes.frame import HeadFrame
    from meshes.synthetic import synthetic_head

    a = synthetic_head("class3", "tiny")
    rest = {k: (a.points[lm.facet] * np.asarray(lm.weights)[:, None]).sum(0)
            for k, lm in a.landmarks.items()}
    c, s = np.cos(np.radians(8.0)), np.sin(np.radians(8.0))
    M = np.eye(4)
    M[1:3, 1:3], M[:3, 3] = [[c, -s], [s, c]], [2.0, -5.0, 9.0]
    frame = HeadFrame(M, {"midsagittal": "given", "horizontal": "given"})
    scene_rest = {k: frame.to_scene(v) for k, v in rest.items()}
    t = {k: frame.to_head(np.array(v)) for k, v in
         default_targets("e-line", scene_rest, frame).items()}
    assert set(t) == {"Ls", "Li"}
    a_, b_ = rest["Prn"][1:], rest["Pg"][1:]
    line = (b_ - a_) / np.linalg.norm(b_ - a_)
    front = np.array([line[1], -line[0]]) * np.sign(line[1])   # unit normal, anterior (+y)
    assert front[0] > 0
    for k, d in E_LINE_MM.items():
        assert np.allclose(t[k][[0, 2]], rest[k][[0, 2]])   # y only
        assert (t[k][1:] - a_) @ front == pytest.approx(d, abs=1e-9), k   # d < 0: behind


def test_same_goal_from_class2_and_class3_starts_gives_the_same_bone_position():
    """Paper Fig. 4 on one anatomy: start states with the mandible retruded (class II-like)
    and protruded and yawed (class III-like); the same goal gives the same bone position.
    (Across the separately meshed class2/class3 heads the rest tissue differs, and so does
    the optimum; BENCHMARKS.md reports that gap.)"""
    from inverse.scene import Scene

    used = ["mandible.advance_mm", "mandible.lateral_mm", "mandible.vertical_mm",
            "mandible.yaw_deg"]
    scene = Scene.from_case("class1", "tiny", params_used=used)
    p_goal = np.array([2.0, 0.5, -1.0, 1.0])
    scene.solve(p_goal)
    targets = {k: v.tolist() for k, v in scene.landmarks(["Pg", "Li", "Me"]).items()}
    ends = []
    for start in ([-7.0, 0.0, 2.0, 0.0], [7.0, 3.0, -2.0, -5.0]):
        scene.solve(start)
        res = scene.plan(targets, p0=start, tikhonov=0.0, ftol=1e-6)
        assert res.converged, res.reason
        ends.append(res.params)
    goals = scene.eq.goals
    moved = (goals.goal(ends[0]) - goals.goal(ends[1])).reshape(-1, 3)
    assert np.linalg.norm(moved, axis=1).max() < 0.1


def test_fit_surface_recovers_the_treatment_of_a_predicted_face(scene):
    """Fig. 5c: the parameters whose true equilibrium best matches a predicted skin."""
    from inverse.explore import SkinPredictor, fit_surface

    scene.solve(P0)
    pred = SkinPredictor(scene)
    dp = np.array([0.5, 0.0, -0.3, 0.0, 0.4, 0.0])
    surface = pred.predict(dp)
    made = scene.eq.stats.factorisations
    skin, lm = pred.corrected(dp)
    assert np.array_equal(scene.eq.p, P0) and scene.eq.stats.factorisations == made
    scene.solve(P0 + dp)
    true = pred.op.apply(scene.eq.u_eq.array)
    err_plain = np.linalg.norm(surface - true, axis=1)
    err_corr = np.linalg.norm(skin - true, axis=1)
    assert err_corr.max() < 0.5 * err_plain.max()      # the quasi-Newton steps help
    assert np.allclose(lm["Pg"], scene.landmarks(["Pg"])["Pg"], atol=0.01)
    scene.solve(P0)
    res = fit_surface(scene, pred, true, ftol=1e-12)
    assert np.abs(res.params - (P0 + dp)).max() < 1e-3


def test_corrected_prediction_follows_the_path_where_first_order_inverts(mandible_scene,
                                                                        monkeypatch):
    """A 20 mm advance from rest on the tiny mesh: the first-order state inverts an element
    and errs 3.4 mm; the corrected prediction (substeps from secant starts, relaxed on the
    factorisation of K at rest) comes within 0.5 mm of the true equilibrium, with no
    factorisation and the scene left at rest. In one step that may not be halved its start
    inverts an element: the plain prediction is returned."""
    import dataclasses

    from inverse.explore import SkinPredictor

    eq = mandible_scene.eq
    mandible_scene.solve(np.zeros(6))
    pred = SkinPredictor(mandible_scene)
    dp = np.array([20.0, 0, 0, 0, 0, 0])
    with monkeypatch.context() as m:
        m.setattr(eq, "policy", dataclasses.replace(eq.policy, min_substep=2.0))
        np.testing.assert_array_equal(pred.corrected(dp, substep_mm=np.inf)[0],
                                      pred.predict(dp))
    for bad in (dict(dp=dp[:3]), dict(dp=dp * np.nan), dict(dp=dp, substep_mm=0.0),
                dict(dp=dp, iterations=0)):
        with pytest.raises(InputError):
            pred.corrected(**bad)
    made = eq.stats.factorisations
    skin, lm = pred.corrected(dp)
    assert eq.stats.factorisations == made and not np.any(eq.p) and eq.min_det_F() > 0
    halved = pred.corrected(dp, substep_mm=np.inf)[0]   # one step, inverts: halved
    mandible_scene.solve(dp)
    true = pred.op.apply(eq.u_eq.array)
    err_plain = np.linalg.norm(pred.predict(dp) - true, axis=1).max()
    err_corr = np.linalg.norm(skin - true, axis=1).max()
    err_halved = np.linalg.norm(halved - true, axis=1).max()   # 2 substeps of 10 mm
    assert err_plain > 2.0 and err_corr < 0.5, (err_plain, err_corr)
    assert err_halved < 0.5 * err_plain, (err_plain, err_halved)
    assert np.allclose(lm["Pg"], mandible_scene.landmarks(["Pg"])["Pg"], atol=0.5)
    pred.destroy()


@pytest.mark.parametrize("solver", ["direct", pytest.param("cholmod", marks=NEEDS_CHOLMOD)])
def test_block_sensitivity_equals_column_solves(mandible_only, tiny_anatomy, solver,
                                               monkeypatch):
    """dx/dp from one factorisation at the equilibrium and one block solve (MUMPS or
    CHOLMOD MatMatSolve) equals the Np tangent solves, column by column."""
    scene = mandible_only(tiny_anatomy, solver=solver)
    scene.solve({"mandible.advance_mm": 3.0, "mandible.yaw_deg": 2.0})
    eq = scene.eq
    with monkeypatch.context() as m:   # the block path makes no tangent solve
        m.setattr(eq.tangents, "step", lambda dp: pytest.fail("a column solve"))
        block = [s.array.copy() for s in eq.sensitivity()]
    eq.forget_sensitivities()   # tangent_step solves again
    for e, b in zip(np.eye(eq.n_params), block):
        col = eq.tangent_step(e)
        assert np.abs(b - col.array).max() < 1e-10 * np.abs(col.array).max()
        col.destroy()
    eq.destroy()
