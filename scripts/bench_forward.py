"""``bench.py forward`` and ``bench.py stress``: rest-to-treated equilibria, each configuration a
fresh ``scripts/simulate.py`` process (under ``mpirun -n N``), and large single moves.
"""

from __future__ import annotations

import itertools
import sys

from scripts._bench import (
    ROOT,
    goal,
    header,
    ranks_label,
    series_plot,
    simulate,
    table,
    write_section,
)

#: The forward goal (s): paper size, class3, 5 mm advance from rest, 2 ranks.
FORWARD_GOAL_S = 5.0


def forward(args) -> None:
    """Forward equilibrium across resolutions, presets and rank counts: time, memory,
    iterations. Iterative presets run up to ``--iterative-up-to`` (they take ~100x longer)."""
    rows, times, goals = [], {}, []   # times: label -> [(dofs, s)]
    head = ["resolution", "vertices", "dofs", "ranks", "solver", "method", "its", "KSP its",
            "shifts", "factorisations", "assemble s", "linear solve s", "equilibrium s",
            "peak RSS MiB", "goal err mm"]
    levels = args.resolutions.split(",")
    last_iter = levels.index(args.iterative_up_to) if args.iterative_up_to in levels else -1
    for i, res in enumerate(levels):
        for solver in args.solvers.split(","):
            if solver == "gamg" and i > last_iter:
                continue
            for n, method in itertools.product(map(int, args.ranks.split(",")),
                                               args.methods.split(",")):
                if solver == "cholmod" and n > 1:
                    continue   # PETSc's CHOLMOD is sequential
                r = simulate(res, solver, n, extra=["--method", method])
                if "error" in r:
                    rows.append([res, "", "", n, solver, method, f"failed: {r['error'][:60]}"]
                                + [""] * (len(head) - 7))
                else:
                    t = r["timings_s"]
                    times.setdefault(f"{solver} {method}, {ranks_label(n)}", []).append(
                        (3 * r["n_vertices"], t["solve"]))
                    if (res, n, solver, method) == ("paper", 2, "direct", "qn"):
                        goals = [goal("forward, rest to a 5 mm advance, paper, 2 ranks "
                                      "(forward)", t["solve"], "s", limit=FORWARD_GOAL_S,
                                      source="the paper: 32 s on 6 cores")]
                    rows.append([res, r["n_vertices"], 3 * r["n_vertices"], n, solver, method,
                                 r["newton_iterations"], r["linear_iterations"],
                                 len(r["diagonal_shifts"]), r["factorisations"],
                                 f"{t['assemble']:.2f}", f"{t['linear_solve']:.2f}",
                                 f"**{t['solve']:.2f}**", f"{r['peak_rss_mb']:.0f}",
                                 f"{r['active_goal_error_max_mm']:.3f}"])
                print(rows[-1], flush=True)
    body = header("Forward equilibrium (rest to 5 mm mandible advance, class3)", args) + [
        "`method`: quasi-Newton (L-BFGS on one kept factorisation, the default) or Newton "
        "(a factorisation per step); `its` counts its nonlinear iterations. "
        "`equilibrium s` is the whole solve (assembly + factorisation/solves + line search); "
        "`linear solve s` is its part outside assembly; `KSP its` counts Krylov iterations "
        "(1 per Newton step with a direct factorisation); `shifts` counts diagonal "
        "regularisations; peak RSS is summed over ranks. CHOLMOD is sequential in PETSc; "
        "like MUMPS it shifts K until it is positive definite (a failed Cholesky). "
        + (f"GAMG is run up to `{args.iterative_up_to}`." if "gamg" in args.solvers else
           "GAMG is left out (`--solvers gamg`; docs/decisions.md)."), "",
        *table(head, rows)]
    png = series_plot("forward", times, "dofs", "equilibrium s", logx=True,
                      goal_line=FORWARD_GOAL_S)
    body += ["", f"![forward]({png})"]
    write_section("forward", "\n".join(body), goals)


def stress(args) -> None:
    """Large single moves from rest (class3-asym, `PLAN_PARAMS`): the mandible advanced by m
    and shifted 0.3 m mm in one solve; each case a fresh ``simulate.py``, stopped after
    ``--timeout`` s."""
    head = ["resolution", "m mm", "its", "factorisations", "shifts", "continuation steps",
            "min det F", "goal err mm", "equilibrium s"]
    sys.path.insert(0, str(ROOT))
    from inverse.treatment import PLAN_PARAMS

    rows, times = [], {}   # resolution -> [(m, s)]
    for case in args.cases.split(","):
        res, mag = case.split(":")
        m = float(mag)
        r = simulate(res, "direct", 1, timeout=args.timeout, args=[
            "--case", "class3-asym", "--resolution", res, "--params-used",
            ",".join(PLAN_PARAMS), "--p", f"mandible.advance_mm={m:g}",
            f"mandible.lateral_mm={0.3 * m:g}"])
        if "error" in r:
            rows.append([res, f"{m:g}", r["error"][:70]] + [""] * (len(head) - 3))
        else:
            times.setdefault(res, []).append((m, r["timings_s"]["solve"]))
            rows.append([res, f"{m:g}", r["newton_iterations"], r["factorisations"],
                         len(r["diagonal_shifts"]), r["continuation_steps"],
                         f"{r['min_det_F']:.2f}", f"{r['active_goal_error_max_mm']:.3f}",
                         f"**{r['timings_s']['solve']:.2f}**"])
        print(rows[-1], flush=True)
    body = header("Stress: large single moves from rest (class3-asym, 1 rank)", args) + [
        "The mandible advanced by m mm and shifted 0.3 m mm from rest in one solve "
        "(`scripts/simulate.py`, `PLAN_PARAMS`, direct preset, quasi-Newton with Newton as "
        f"fallback); a case still running after {args.timeout:g} s is stopped.", "",
        *table(head, rows)]
    png = series_plot("stress", times, "mandible advance m, mm (lateral 0.3 m)", "equilibrium s")
    write_section("stress", "\n".join(body + ["", f"![stress]({png})"]))
