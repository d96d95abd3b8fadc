"""Every option validated at the edge (one line, exit code 2, nothing written); treatments
beyond their bounds and compressed tissue are reported; no input makes a run unbounded."""

import json
import sys

import numpy as np
import pytest
from hypothesis import Phase, given, settings
from hypothesis import strategies as st
from test_scripts import PLAN, ROOT, SIM, _run

from meshes.errors import InputError

#: The tests' tier (conftest.py): options at the scripts' edge.
TIER = "scripts"

EXPLORE = [sys.executable, str(ROOT / "scripts" / "explore.py"), "--case", "class3",
           "--resolution", "tiny"]
SCRIPTS = {"plan": PLAN, "sim": SIM, "explore": EXPLORE}


@pytest.mark.parametrize("script,args,match", [
    ("plan", ["--ftol", "-1"], "--ftol must be a finite number in [1e-12, 1)"),
    ("plan", ["--ftol", "1"], "--ftol must be a finite number in [1e-12, 1)"),
    ("plan", ["--ftol", "nan"], "--ftol must be"),
    ("plan", ["--ftol", "1e-13"], "--ftol must be a finite number in [1e-12, 1)"),
    ("plan", ["--max-iterations", "-3"], "--max-iterations must be an integer in [1, 1000]"),
    ("plan", ["--params-used", ",,"], "--params-used must name at least one parameter"),
    ("plan", ["--landmarks", " , "], "--landmarks must name at least one landmark"),
    ("plan", ["--tikhonov", "-0.5"], "--tikhonov must be a finite number in [0, 1e+06]"),
    ("plan", ["--tikhonov", "inf"], "--tikhonov must be"),
    ("sim", ["--penalty", "0"], "--penalty must be a finite number in (0, 1e+12]"),
    ("sim", ["--penalty", "nan"], "--penalty must be"),
    ("explore", ["--substep-mm", "0"], "--substep-mm must be a number in (0, inf]"),
    ("explore", ["--iterations", "0"], "--iterations must be an integer in [1, 100]"),
    ("explore", ["--scales", "1,nan"], "--scales must be a finite number"),
    ("explore", ["--scales", ","], "--scales must name at least one scale"),
    ("explore", ["--dp", "mandible.advance_mm=inf"], "finite"),
])
def test_bad_options_get_one_line_and_exit_2(tmp_path, script, args, match):
    out = tmp_path / "out"
    r = _run(SCRIPTS[script] + args + ["--out", str(out), "--report", str(out / "r.json")])
    assert r.returncode == 2, r.stderr[-2000:]
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and match in errors[0], r.stderr[-2000:]
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("args,match", [
    (["forward", "--resolutions", "huge"], "--resolutions: unknown 'huge'"),
    (["forward", "--ranks", "0"], "--ranks must be a finite integer in [1, 64]"),
    (["forward", "--solvers", ","], "--solvers must name at least one item"),
    (["plan", "--magnitudes", "nan"], "--magnitudes must be a finite number"),
    (["stress", "--timeout", "-1"], "--timeout must be a finite number"),
    (["stress", "--timeout", "abc"], "invalid float value"),
    (["stress", "--cases", "paper"], "--cases must be a finite number"),
    (["ct", "--cts", "foo"], "--cts: unknown 'foo'"),
    (["accuracy", "--cts", "foo"], "--cts: unknown 'foo'"),
    (["accuracy", "--resolutions-ct", "coarse,huge"], "--resolutions-ct: unknown 'huge'"),
    (["accuracy", "--parts", "ct,mesh2"], "--parts: unknown 'mesh2'"),
    (["plausibility", "--cases", "class9"], "--cases: unknown 'class9'"),
])
def test_bench_options_are_checked_before_any_work(args, match):
    """bench.py: one `error:` line, exit 2, before any benchmark runs (none writes
    BENCHMARKS.md: the file is unchanged)."""
    bench = ROOT / "BENCHMARKS.md"
    before = bench.read_text(encoding="utf-8")
    r = _run([sys.executable, str(ROOT / "scripts" / "bench.py"), *args], timeout=60)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == \
        [ln for ln in r.stderr.strip().splitlines() if ln.startswith("error:")][:1], r.stderr
    assert match in r.stderr, r.stderr
    assert bench.read_text(encoding="utf-8") == before


def test_a_treatment_beyond_its_bounds_and_crushed_tissue_are_reported(tmp_path):
    """simulate.py --p mandible.advance_mm=40 (bound 15): both warnings, on stderr and in
    the report; the crushed cell's place in the report's ``min_det_F_at_mm`` and in the
    warning."""
    rep = tmp_path / "r.json"
    r = _run(SIM + ["--p", "mandible.advance_mm=40", "--report", str(rep)])
    assert r.returncode == 0, r.stderr[-2000:]
    warnings = json.loads(rep.read_text())["warnings"]
    assert any("mandible.advance_mm = 40 mm is outside its feasible range [-15, 15]" in w
               for w in warnings), warnings
    assert any(w.startswith("tissue compressed to 3") for w in warnings), warnings
    where = json.loads(rep.read_text())["min_det_F_at_mm"]
    assert len(where) == 3 and np.all(np.isfinite(where)), where
    assert any(f"at ({', '.join(f'{c:.1f}' for c in where)}) mm" in w for w in warnings), \
        (where, warnings)
    for w in warnings:
        assert w in r.stderr


@pytest.mark.unit
def test_port_range():
    """Ports (the explorer's server) in [0, 65535], integers (0: any free port):
    `fem.limits.check` and so `check_options` for any script's ``--port``."""
    from fem.limits import check

    assert check("port", "8765", "--port") == 8765
    assert check("port", "0", "--port") == 0
    for bad in ("-1", "65536", "80.5", "http", "nan"):
        with pytest.raises(InputError, match="--port must be an integer in \\[0, 65535\\]"):
            check("port", bad, "--port")


@pytest.mark.integration
def test_the_python_api_refuses_the_same_values(mandible_scene):
    from inverse.explore import SkinPredictor
    from inverse.planner import gauss_newton
    from inverse.scene import Scene

    obj = mandible_scene.objective({"Pg": mandible_scene.landmarks(["Pg"])["Pg"].tolist()})
    for kw, match in [({"ftol": -1.0}, "ftol must be"), ({"max_iterations": 0},
                                                         "max_iterations must be"),
                      ({"ftol": float("nan")}, "ftol must be")]:
        with pytest.raises(InputError, match=match):
            gauss_newton(mandible_scene, obj, **kw)
    with pytest.raises(InputError, match="tikhonov must be"):
        mandible_scene.objective({"Pg": mandible_scene.landmarks(["Pg"])["Pg"].tolist()},
                                 tikhonov=-1.0)
    with pytest.raises(InputError, match="max_bisections must be"):
        mandible_scene.eq.solve(np.ones(6), max_bisections=-1)
    with pytest.raises(InputError, match="substep_mm must be"):
        SkinPredictor(mandible_scene).corrected(np.zeros(6), substep_mm=0.0)
    from meshes.synthetic import synthetic_head

    for kw, match in [({"penalty": -5.0}, "penalty must be"),
                      ({"newton": {"xtol": -1.0}}, "xtol must be"),
                      ({"newton": {"xtol": 0.0}}, "xtol must be"),
                      ({"newton": {"max_it": 10 ** 6}}, "max_it must be")]:
        with pytest.raises(InputError, match=match):
            Scene(synthetic_head("class3", "tiny"), params_used=["mandible.advance_mm"], **kw)


#: Each drawn run must end within this (s): a tiny scene's plan takes ~5-10 s.
RUN_BOUND_S = 120
NUMBERS = st.one_of(st.sampled_from(["-1", "0", "1e-12", "1", "nan", "inf", "-inf", "abc",
                                     "1e9", "3"]),
                    st.floats(-1e3, 1e3).map(lambda v: f"{v:.3g}"))
OPTIONS = {"plan": ["--ftol", "--tikhonov", "--max-iterations", "--penalty"],
           "sim": ["--penalty", "--p"]}


@settings(max_examples=10, deadline=None, derandomize=True,
          phases=[Phase.explicit, Phase.generate])   # no shrinking: each example is a run
@given(st.sampled_from(sorted(OPTIONS)), st.data())
def test_no_option_makes_a_run_unbounded(script, data):
    """Options drawn from valid, boundary and invalid values: every run finishes within
    `RUN_BOUND_S` (exit 0) or exits 2 with one line; none hangs."""
    args = []
    for flag in data.draw(st.lists(st.sampled_from(OPTIONS[script]), min_size=1, max_size=3,
                                   unique=True)):
        value = data.draw(NUMBERS)
        if flag == "--p":
            flag, value = "--p", f"mandible.advance_mm={value}"
        args += [flag, value]
    if script == "plan":
        args += ["--max-iterations", "2"] if "--max-iterations" not in args else []
    r = _run(SCRIPTS[script] + args, timeout=RUN_BOUND_S)
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert r.returncode in (0, 2), (args, r.stderr[-2000:])
    if r.returncode == 2:
        assert len(errors) == 1, (args, r.stderr[-2000:])


@pytest.mark.unit
@pytest.mark.parametrize("setting, value", [
    ("max_halvings", 0), ("stall_its", 2.5), ("stall_ratio", 0.0), ("rate_max", 1.0),
    ("qn_bisections", True), ("tangent_lag_its", -1), ("path_substep_mm", float("nan")),
    ("goal_failure_mm", 0.0), ("stall_ratio", "0.5")])
def test_a_solver_policy_out_of_range_is_refused(setting, value):
    """`SolverPolicy` checks each setting where it is made (``max_halvings=0`` once left a
    variable unbound in the line search): one clear error naming it."""
    import dataclasses

    from fem.policy import DEFAULT_POLICY

    with pytest.raises(InputError, match=f"SolverPolicy.{setting} must be"):
        dataclasses.replace(DEFAULT_POLICY, **{setting: value})


@pytest.mark.integration
def test_the_equilibrium_settings_under_their_former_name(mandible_only, tiny_anatomy):
    """``Scene(newton=...)`` still configures the equilibrium (whichever method), as
    ``equilibrium=`` does; both at once is a one-line error before anything is built."""
    scene = mandible_only(tiny_anatomy, newton=dict(xtol=1e-4, method="qn"))
    assert scene.eq.xtol == 1e-4 and scene.eq.method == "qn"
    st = scene.solve(scene.param_vector({"mandible.advance_mm": 3.0}))
    assert st.iterations == st.newton_iterations > 0, st
    scene.eq.destroy()
    with pytest.raises(InputError, match="give the equilibrium's settings once"):
        mandible_only(tiny_anatomy, newton={}, equilibrium={})
    from fem.policy import EquilibriumOptions

    opts = EquilibriumOptions(method="newton", xtol=1e-3)
    scene = mandible_only(tiny_anatomy, equilibrium=opts)
    assert scene.eq.settings is opts and scene.eq.xtol == 1e-3 and scene.eq.method == "newton"
    scene.eq.destroy()
    with pytest.raises(InputError, match="in the EquilibriumOptions, not beside it"):
        mandible_only(tiny_anatomy, equilibrium=opts, solver="cholmod")


@pytest.mark.unit
@pytest.mark.parametrize("bad, match", [
    (dict(frtol=0.0), "frtol must be"), (dict(atol=float("inf")), "atol must be"),
    (dict(xtol=1e-11), "xtol must be"), (dict(max_it=0), "max_it must be"),
    (dict(lag_its=-1), "lag_its must be"), (dict(shift_max=0.0), "shift_max must be"),
    (dict(quadrature_degree=1.5), "quadrature_degree must be"),
    (dict(volume_quadrature_degree=-1), "volume_quadrature_degree must be"),
    (dict(method="bfgs"), "unknown method"), (dict(solver="lu"), "unknown solver preset"),
    (dict(prefix=""), "an options prefix is required"), (dict(options=[1]), "options must be"),
    (dict(policy={}), "policy must be a SolverPolicy")])
def test_equilibrium_options_are_validated_where_they_are_made(bad, match):
    """`EquilibriumOptions` checks each field when made (`fem.limits`, one line), fills the
    method's defaults in, and is frozen."""
    import dataclasses

    from fem.policy import METHOD_DEFAULTS, EquilibriumOptions

    with pytest.raises(InputError, match=match):
        EquilibriumOptions(**bad)
    for method, defaults in METHOD_DEFAULTS.items():
        opts = EquilibriumOptions(method=method)
        assert {k: getattr(opts, k) for k in defaults} == defaults
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.xtol = 1.0


@pytest.mark.integration
def test_options_reach_whichever_snes_runs_under_one_prefix_each(mandible_only, tiny_anatomy):
    """The API's PETSc ``options`` reach the quasi-Newton SNES (the default method) as well
    as Newton's; each PETSc object has its own prefix, and the command line reaches
    quasi-Newton's under ``<prefix>qn_`` without touching Newton's."""
    from petsc4py import PETSc

    stol = 1.25e-9   # unused by our convergence test: harmless, and visible on the SNES
    scene = mandible_only(tiny_anatomy, options={"snes_stol": stol})
    eq = scene.eq
    scene.solve(scene.param_vector({"mandible.advance_mm": 2.0}))
    assert eq.snes["qn"].getType() == "qn" and eq.snes["qn"].getTolerances()[2] == stol
    assert eq.snes["newton"].getTolerances()[2] == stol
    prefixes = {eq.snes["newton"].getOptionsPrefix(), eq.snes["qn"].getOptionsPrefix(),
                eq.tangent_ksp.getOptionsPrefix()}
    assert prefixes == {"orthodiff_fwd_", "orthodiff_fwd_qn_", "orthodiff_fwd_tangent_"}
    eq.destroy()
    opts = PETSc.Options()
    opts["orthodiff_fwd_qn_snes_stol"] = 2 * stol
    try:
        scene = mandible_only(tiny_anatomy)
        scene.solve(scene.param_vector({"mandible.advance_mm": 2.0}))
        assert scene.eq.snes["qn"].getTolerances()[2] == 2 * stol
        assert scene.eq.snes["newton"].getTolerances()[2] != 2 * stol
        scene.eq.destroy()
    finally:
        opts.delValue("orthodiff_fwd_qn_snes_stol")


@pytest.mark.unit
@pytest.mark.parametrize("bad, match", [
    (dict(armijo=0.5), "armijo must be a finite number in (0, 0.5)"),
    (dict(max_backtracks=2.5), "max_backtracks must be an integer"),
    (dict(max_step=0.0), "max_step must be"), (dict(gtol=float("nan")), "gtol must be"),
    (dict(xtol=-1.0), "xtol must be"), (dict(ftol=1.0), "ftol must be"),
    (dict(mode="newton"), "mode must be one of"), (dict(max_iterations=0), "max_iterations")])
def test_plan_options_are_validated_where_they_are_made(bad, match):
    """`PlanOptions` checks each field through `fem.limits` when made, one line each; it is
    frozen, and `gauss_newton` takes it or its fields as keywords, not both."""
    import dataclasses

    from inverse.planner import PlanOptions, gauss_newton

    with pytest.raises(InputError, match=match.replace("(", r"\(").replace(")", r"\)")):
        PlanOptions(**bad)
    opts = PlanOptions(ftol=1e-4, max_iterations=3)
    assert opts.max_iterations == 3 and isinstance(opts.max_iterations, int)
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.ftol = 0.1
    with pytest.raises(InputError, match="give the plan's options once"):
        gauss_newton(None, None, options=opts, ftol=1e-3)
