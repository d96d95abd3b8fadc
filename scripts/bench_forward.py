"""``bench.py forward`` and ``bench.py stress``: rest-to-treated equilibria, each configuration a
fresh ``scripts/simulate.py`` process (under ``mpirun -n N``), and large single moves.
"""

from __future__ import annotations

import itertools
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._bench import (  # noqa: E402
    ROOT,
    goal,
    header,
    ranks_label,
    result,
    run,
    series_plot,
    simulate,
    table,
    worker,
    write_section,
)

#: The forward goal (s): paper size, class3, 5 mm advance from rest, 2 ranks.
FORWARD_GOAL_S = 5.0
#: Issue 53's goals, default solver and method on 2 ranks: fine's solve time per vertex at
#: most this multiple of paper's, and fine's peak memory (MiB, summed over ranks).
FINE_PER_VERTEX, FINE_PEAK_MIB = 1.3, 4096.0
#: The tangent study's preconditioners: the kept factorisation (the default), GAMG.
TANGENT_PCS = ("factorisation", "gamg")


def forward(args) -> None:
    """Forward equilibrium across resolutions, presets and rank counts: time, memory,
    iterations. Iterative presets run up to ``--iterative-up-to`` (they take ~100x longer)."""
    rows, times, goals = [], {}, []   # times: label -> [(dofs, s)]
    default2 = {}   # resolution -> report of the default solver and method on 2 ranks
    head = ["resolution", "vertices", "dofs", "ranks", "solver", "method", "its", "KSP its",
            "shifts", "factorisations", "assemble s", "linear solve s", "equilibrium s",
            "peak RSS MiB", "goal err mm"]
    levels = args.resolutions.split(",")
    last_iter = levels.index(args.iterative_up_to) if args.iterative_up_to in levels else -1
    last_all = levels.index(args.all_up_to) if args.all_up_to in levels else len(levels)
    for i, res in enumerate(levels):
        for solver in args.solvers.split(","):
            if solver == "gamg" and i > last_iter:
                continue
            for n, method in itertools.product(map(int, args.ranks.split(",")),
                                               args.methods.split(",")):
                if solver == "cholmod" and n > 1:
                    continue   # PETSc's CHOLMOD is sequential
                if solver == "amg" and method != "qn":
                    continue   # quasi-Newton's factor replaced; Newton on it is gamg's
                if i > last_all and (method != "qn" or solver == "cholmod"):
                    continue   # beyond --all-up-to: quasi-Newton on the factor or on AMG
                r = simulate(res, solver, n, extra=["--method", method])
                if "error" in r:
                    rows.append([res, "", "", n, solver, method, f"failed: {r['error'][:60]}"]
                                + [""] * (len(head) - 7))
                else:
                    t = r["timings_s"]
                    times.setdefault(f"{solver} {method}, {ranks_label(n)}", []).append(
                        (3 * r["n_vertices"], t["solve"]))
                    if (n, method) == (2, "qn"):
                        default2.setdefault(res, {})[solver] = r
                    if (res, n, solver, method) == ("paper", 2, "direct", "qn"):
                        goals += [goal("forward, rest to a 5 mm advance, paper, 2 ranks "
                                      "(forward)", t["solve"], "s", limit=FORWARD_GOAL_S,
                                      source="the paper: 32 s on 6 cores")]
                    rows.append([res, r["n_vertices"], 3 * r["n_vertices"], n, solver, method,
                                 r["iterations"], r["linear_iterations"],
                                 len(r["diagonal_shifts"]), r["factorisations"],
                                 f"{t['assemble']:.2f}", f"{t['linear_solve']:.2f}",
                                 f"**{t['solve']:.2f}**", f"{r['peak_rss_mb']:.0f}",
                                 f"{r['active_goal_error_max_mm']:.3f}"])
                print(rows[-1], flush=True)
    goals += _scale_goals(default2)
    body = header("Forward equilibrium (rest to 5 mm mandible advance, class3)", args) + [
        "`method`: quasi-Newton (L-BFGS on one kept factorisation, the default) or Newton "
        "(a factorisation per step); `its` counts its nonlinear iterations. "
        "`equilibrium s` is the whole solve (assembly + factorisation/solves + line search); "
        "`linear solve s` is its part outside assembly; `KSP its` counts Krylov iterations "
        "(1 per Newton step with a direct factorisation); `shifts` counts diagonal "
        "regularisations; peak RSS is summed over ranks. CHOLMOD is sequential in PETSc; "
        "like MUMPS it shifts K until it is positive definite (a failed Cholesky). "
        + (f"GAMG is run up to `{args.iterative_up_to}`." if "gamg" in args.solvers else
           "GAMG is left out (`--solvers gamg`; docs/decisions.md).")
        + " `amg` (quasi-Newton only) takes CG with GAMG to 1e-2 for the factor "
        "(`fem.policy.PRESETS`)."
        + f" Beyond `{args.all_up_to}` only quasi-Newton on `direct` and `amg` runs.", "",
        *table(head, rows)]
    png = series_plot("forward", times, "dofs", "equilibrium s", logx=True,
                      goal_line=FORWARD_GOAL_S)
    body += ["", f"![forward]({png})", "",
             *_tangent_table(levels, max(map(int, args.ranks.split(","))))]
    write_section("forward", "\n".join(body), goals)


def _scale_goals(default2: dict) -> list:
    """Issue 53's goal rows from the reports (`default2`: resolution -> {solver: simulate.py's
    report}, quasi-Newton on 2 ranks) where both paper and fine ran: each size's fastest
    solver for the time per vertex, fine's leanest for the memory."""
    if not {"paper", "fine"} <= set(default2):
        return []

    def per_vertex(r):
        return r["timings_s"]["solve"] / r["n_vertices"]

    best = {k: min(default2[k].items(), key=lambda kv: per_vertex(kv[1]))
            for k in ("paper", "fine")}
    lean = min(default2["fine"].items(), key=lambda kv: kv[1]["peak_rss_mb"])
    (fs, fine), (ps, paper) = best["fine"], best["paper"]
    return [goal("fine / paper, solve time per vertex, fastest solvers, 2 ranks (forward)",
                 per_vertex(fine) / per_vertex(paper), "", limit=FINE_PER_VERTEX,
                 source="issue 53", note=f"fine {fine['timings_s']['solve']:.1f} s ({fs}), "
                 f"paper {paper['timings_s']['solve']:.2f} s ({ps})"),
            goal(f"fine, peak memory summed over ranks, {lean[0]}, 2 ranks (forward)",
                 lean[1]["peak_rss_mb"], "MiB", limit=FINE_PEAK_MIB, source="issue 53")]


def _tangent_table(levels, n: int) -> list:
    """The tangent solve at the 5 mm advance's equilibrium with each of `TANGENT_PCS` on n
    ranks, a worker process each: its markdown."""
    from fem.policy import TANGENT_GAMG

    head = ["resolution", "dofs", "ranks", "preconditioner", "first solve s (CG its)",
            "next solve s (CG its)", "peak RSS MiB"]
    rows = []
    for res, pc in itertools.product(levels, TANGENT_PCS):
        r = worker(__file__, n, res, pc)
        rows.append([res, r.get("dofs", ""), n, pc] + (
            [r["error"], "", ""] if "error" in r else
            [f"**{r['first_s']:.2f}** ({r['first_its']})",
             f"{r['next_s']:.2f} ({r['next_its']})", f"{r['peak_rss_mb']:.0f}"]))
        print(rows[-1], flush=True)
    opts = " ".join(f"-orthodiff_fwd_tangent_{k} {v}" for k, v in TANGENT_GAMG.items())
    return ["### The tangent at the equilibrium: a preconditioner that scales", "",
            "K⁻¹ df/dp for `mandible.advance_mm` at the 5 mm advance's equilibrium "
            "(`Equilibrium.solve_tangent`, CG to a relative residual of 1e-11), one worker "
            "process each (`scripts/bench_forward.py`). `factorisation`: the kept MUMPS "
            "LDLᵀ, refactorised at the equilibrium by the first solve (quasi-Newton came from "
            "rest); `gamg`: CG with smoothed-aggregation AMG and the rigid-body "
            f"near-nullspace, switched on by `{opts}`; its first solve builds the hierarchy. "
            "The next solve has another right-hand side (df/dp scaled) on the same K.", "",
            *table(head, rows)]


def tangent_work(res: str, pc: str) -> None:
    """One worker (under mpirun): the tangent study's row at ``res`` with ``pc``."""
    from mpi4py import MPI  # first: it loads the MPI library PETSc links (PyPI's MPICH)
    from petsc4py import init as petsc_init

    petsc_init([sys.argv[0]])
    from petsc4py import PETSc

    from fem.policy import TANGENT_GAMG
    from inverse.scene import Scene
    from scripts._common import peak_rss_mb

    comm = MPI.COMM_WORLD
    if pc == "gamg":
        opts = PETSc.Options()
        for k, v in TANGENT_GAMG.items():
            opts[f"orthodiff_fwd_tangent_{k}"] = v
    scene = Scene.from_case("class3", res, params_used=["mandible.advance_mm"], comm=comm)
    scene.solve({"mandible.advance_mm": 5.0})
    eq = scene.eq
    assert eq.own_tangent_pc == (pc == "gamg")
    rhs, out = eq.dfdp[0].copy(), eq.dfdp[0].duplicate()
    out_rows = {"dofs": 3 * scene.domain.n_vertices}
    for name, scale in (("first", -1.0), ("next", -2.0)):
        rhs.array[:] = scale * eq.dfdp[0].array_r
        comm.Barrier()
        t = time.perf_counter()
        out_rows[f"{name}_its"] = eq.solve_tangent(rhs, out)
        out_rows[f"{name}_s"] = comm.allreduce(time.perf_counter() - t, op=MPI.MAX)
    out_rows["peak_rss_mb"] = peak_rss_mb(comm)
    result(out_rows, comm)


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
        r = run("simulate.py", n=1, timeout=args.timeout, args=[
            "--case", "class3-asym", "--resolution", res, "--params-used",
            ",".join(PLAN_PARAMS), "--p", f"mandible.advance_mm={m:g}",
            f"mandible.lateral_mm={0.3 * m:g}"])
        if "error" in r:
            rows.append([res, f"{m:g}", r["error"][:70]] + [""] * (len(head) - 3))
        else:
            times.setdefault(res, []).append((m, r["timings_s"]["solve"]))
            rows.append([res, f"{m:g}", r["iterations"], r["factorisations"],
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


if __name__ == "__main__":
    tangent_work(*sys.argv[1:3])
