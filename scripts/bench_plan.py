"""``bench.py plan``: class3-asym. In one process: the costs of one forward solve, the adjoint
gradient, the landmark block S_T, the finite-difference gradient (Np + 1 forward solves),
the skin sensitivities, a first-order prediction and a corrected one; then the whole plan
from p = 0 with ``scripts/plan.py`` (default goal).
"""

from __future__ import annotations

import itertools
import json
import sys
import tempfile
from pathlib import Path

from scripts._bench import (
    CORRECTED,
    ROOT,
    fd_gradient,
    goal,
    header,
    plan_work,
    prediction_errors,
    ranks_label,
    run,
    series_plot,
    write_section,
)

#: Goals (issue 4): a whole plan at paper size on 2 ranks (s), the adjoint gradient against
#: one forward solve, and S_T against one forward solve.
PLAN_GOAL_S, ADJOINT_GOAL, S_T_GOAL = 30.0, 0.3, 1.0
#: Issue 30: a plan's solves in at most this many forward solves from rest (ratio, one run).
PLAN_RATIO_GOAL = 3.0


def _derivative_costs(res: str, mags) -> dict:
    """Times (s) and errors (mm) of the derivative machinery at one equilibrium, 1 rank."""
    import time

    import numpy as np

    sys.path.insert(0, str(ROOT))
    from inverse.explore import SkinPredictor
    from inverse.scene import Scene
    from inverse.treatment import PLAN_PARAMS

    out = {}
    for tangent in (False, True):   # each from rest on a fresh scene (factorisation at rest)
        scene = Scene.from_case("class3-asym", res, params_used=PLAN_PARAMS)
        p = scene.param_vector({"mandible.advance_mm": -4.0, "mandible.yaw_deg": -3.0,
                                "maxilla.advance_mm": 1.5})
        obj = scene.objective(scene.default_targets())
        key = "tangent" if tangent else "plain"
        t = time.perf_counter()
        scene.solve(p, tangent=tangent)
        out[f"forward_{key}"] = time.perf_counter() - t
        t = time.perf_counter()
        g = obj.gradient()
        out[f"adjoint_{key}"] = time.perf_counter() - t
        out[f"adjoint_cg_{key}"] = scene.eq.tangent_ksp.getIterationNumber()
        out["n_params"] = len(p)
    t = time.perf_counter()
    S, mode = obj.jacobian()
    out["S_T"], out["S_T_mode"] = time.perf_counter() - t, mode
    # finite differences: Np forward solves from the equilibrium (warm, predicted)
    base = scene.eq.snapshot()
    t = time.perf_counter()
    fd = fd_gradient(scene, obj, 1e-3)
    out["fd_gradient"] = time.perf_counter() - t
    out["fd_vs_adjoint_rel_diff"] = float(np.abs(fd - g).max() / np.abs(g).max())
    scene.solve(p + 1e-3)          # a warm forward solve (the plan's line-search trials)
    scene.eq.restore(base)
    t = time.perf_counter()
    scene.solve(p + np.r_[0.5, np.zeros(len(p) - 1)])
    out["forward_warm"] = time.perf_counter() - t
    scene.eq.restore(base)
    scene.solve(np.zeros(len(p)))   # explore from the rest face
    base = scene.eq.snapshot()
    scene.eq.sensitivity()
    t = time.perf_counter()
    pred = SkinPredictor(scene)
    out["skin_sensitivity"] = time.perf_counter() - t
    out["n_skin"] = len(pred.vertices)
    pred.destroy()
    rows = prediction_errors(scene, mags)
    out["predictions"] = rows
    return out


def _plan_over_forward(report: dict, res: str, occ: str, n: int):
    """The plan's solve time over one forward solve from rest to the parameters it found
    (``simulate.py`` on n ranks), or None when that solve fails."""
    with tempfile.TemporaryDirectory() as d:
        params = Path(d) / "p.json"
        params.write_text(json.dumps(dict(zip(report["param_names"], report["params_optimal"]))))
        sim = run("simulate.py", n=n, args=[
            "--case", "class3-asym", "--resolution", res, "--occlusion", occ,
            "--params-used", ",".join(report["param_names"]), "--params", str(params)])
    if "error" in sim:
        return None
    return plan_work(report) / sim["timings_s"]["solve"]


def plan(args) -> None:
    goals, totals = [], {}   # totals: label -> [(resolution, s)]
    lines = header("Planning (class3-asym, default goal: 7 landmarks, `PLAN_PARAMS`: 10)",
                   args) + [
             "### Derivatives at one equilibrium (1 rank, seconds)", "",
             "Forward solves from rest to the plan's typical first move (mandible -4 mm, "
             "yaw -3°, maxilla 1.5 mm), then one adjoint gradient. Plain: the adjoint "
             "factorises K at the equilibrium (quasi-Newton's factorisation is K at rest); "
             "tangent-ready (`solve(tangent=True)`): the forward solve refactorises once "
             "near convergence (`SolverPolicy.tangent_refresh_xtols`) and the adjoint's CG "
             "reuses that factorisation. The columns after it are from the tangent-ready "
             "solve.", "",
             "| resolution | forward plain | adjoint (factorises) | forward tangent-ready | "
             "adjoint gradient (CG its) | adjoint / forward | forward, warm | "
             "S_T (mode) | FD gradient (Np solves) | FD/adjoint time | FD vs adjoint |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    pred_lines = ["", "### First-order exploration of the whole skin (1 rank)", "",
                  "From the rest face, mandible advanced by m mm and shifted 0.3 m mm; "
                  "errors are the max over the skin against the true equilibrium. "
                  + CORRECTED, "",
                  "| resolution | skin vertices | skin S s (Np solves excluded: see S_T) | m mm | "
                  "max skin displacement mm | "
                  "plain error mm | plain ms/call | corrected error mm | corrected s |",
                  "|---|---|---|---|---|---|---|---|---|"]
    for res in args.resolutions.split(","):
        c = _derivative_costs(res, [float(m) for m in args.magnitudes.split(",")])
        row = (f"| {res} | {c['forward_plain']:.2f} | {c['adjoint_plain']:.2f} | "
               f"{c['forward_tangent']:.2f} | {c['adjoint_tangent']:.2f} "
               f"({c['adjoint_cg_tangent']}) | "
               f"**{c['adjoint_tangent'] / c['forward_tangent']:.2f}** | "
               f"{c['forward_warm']:.2f} | {c['S_T']:.2f} ({c['S_T_mode']}) | "
               f"{c['fd_gradient']:.2f} | {c['fd_gradient'] / c['adjoint_tangent']:.0f}x | "
               f"{c['fd_vs_adjoint_rel_diff']:.1e} |")
        print(row, flush=True)
        lines.append(row)
        if res == "paper":
            goals += [goal("adjoint gradient / one forward solve, paper, 1 rank (plan)",
                           c["adjoint_tangent"] / c["forward_tangent"], "", limit=ADJOINT_GOAL,
                           source="issue 4"),
                      goal("landmark block S_T / one forward solve, paper, 1 rank (plan)",
                           c["S_T"] / c["forward_tangent"], "", limit=S_T_GOAL,
                           source="issue 4")]
        for r in c["predictions"]:
            if "error" in r:
                pred_lines.append(f"| {res} | | | {r['mag']:g} | failed: {r['error']} |"
                                  " | | | |")
                continue
            pred_lines.append(
                f"| {res} | {c['n_skin']} | {c['skin_sensitivity']:.2f} | {r['mag']:g} | "
                f"{r['disp']:.2f} | {r['plain']:.3f} | {r['t_plain_ms']:.3f} | "
                f"{r['corr']:.3f} | {r['t_corr']:.2f} |")
            print(pred_lines[-1], flush=True)
    lines += pred_lines
    lines += ["", "### Whole plan from p = 0 (`scripts/plan.py`, default options)", "",
              "`--occlusion free`: `PLAN_PARAMS` (10); `final`: the six `jaws.*` motions with "
              "the mandible held in the final occlusion (`make demo`). Plan / forward: the "
              "plan's solves (forward, sensitivity, adjoint, line search) over one forward "
              "solve from rest to the parameters it found (`simulate.py`, the same ranks, in "
              "the same run).", "",
              "| resolution | occlusion | ranks | GN iterations | forward solves | mean distance "
              "before mm | after mm | forward s | sensitivity s | adjoint s | line search s | "
              "total s | plan / forward |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for res, occ in itertools.product(args.resolutions.split(","), args.occlusions.split(",")):
        for n in map(int, args.ranks.split(",")):
            r = run("plan.py", ["--case", "class3-asym", "--resolution", res, "--occlusion",
                                 occ], n)
            if "error" in r:
                lines.append(f"| {res} | {occ} | {n} | failed: {r['error'][:60]} | | | | | | | | "
                             "| |")
            else:
                t = r["timings_s"]
                ratio = _plan_over_forward(r, res, occ, n)
                if res == "paper" and n == 2 and ratio is not None:
                    goals.append(goal(f"plan / forward from rest, --occlusion {occ}, paper, "
                                      "2 ranks (plan)", ratio, "", limit=PLAN_RATIO_GOAL,
                                      source="issue 30"))
                totals.setdefault(f"--occlusion {occ}, {ranks_label(n)}", []).append(
                    (res, t["total"]))
                if res == "paper" and n == 2:
                    goals.append(goal(f"whole plan from p = 0, --occlusion {occ}, paper, "
                                      "2 ranks (plan)", t["total"], "s", limit=PLAN_GOAL_S,
                                      source="the paper: ~20 min"))
                lines.append(
                    f"| {res} | {occ} | {n} | {r['gn_iterations']} | {r['forward_solves']} | "
                    f"{r['mean_distance_before_mm']:.2f} | {r['mean_distance_after_mm']:.2f} | "
                    f"{t['forward']:.1f} | {t['sensitivity']:.1f} | {t['adjoint']:.1f} | "
                    f"{t['line_search']:.1f} | **{t['total']:.1f}** | "
                    + ("failed" if ratio is None else f"**{ratio:.1f}**") + " |")
            print(lines[-1], flush=True)
    png = series_plot("plan", totals, "resolution", "plan.py total s", logy=False,
                      goal_line=PLAN_GOAL_S)
    lines += ["", f"![plan]({png})"]
    write_section("plan", "\n".join(lines), goals)
