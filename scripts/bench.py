#!/usr/bin/env python3
"""Benchmarks (not timed tests). Results are printed and written into BENCHMARKS.md.

    python3 scripts/bench.py forward [--resolutions tiny,coarse,medium,paper]
                                     [--solvers direct,gamg] [--ranks 1,2]
    python3 scripts/bench.py plan [--resolutions coarse,paper] [--ranks 1,2]
    python3 scripts/bench.py stress [--cases coarse:20,paper:10] [--timeout 300]
    python3 scripts/bench.py accuracy [--parts mesh,tolerance,prediction,gradient]
    python3 scripts/bench.py plausibility [--resolutions coarse,paper] [--cases class1]
    python3 scripts/bench.py ct [--cts headsq,cranium] [--resolutions coarse,paper]

``accuracy``: run time against error (issue 5). Each part writes a section of BENCHMARKS.md
and a PNG under ``docs/``: ``mesh`` (tiny to fine, finest as reference: landmark error and the
planned p against wall time), ``tolerance`` (Newton tolerances against landmark error and
time), ``prediction`` (first-order error against |dp|, plain and corrected), ``gradient``
(adjoint against finite differences: cost against Np, FD error against h), ``order`` (P1
against P2: landmark error against time, the richest P2 as reference).

``plan``: class3-asym. In one process: the costs of one forward solve, the adjoint gradient,
the landmark block S_T, the finite-difference gradient (Np + 1 forward solves), the skin
sensitivities, a first-order prediction and a corrected one (error against the true
equilibrium). Then the whole plan from p = 0 with ``scripts/plan.py`` (default goal).

``forward``: rest-to-treated equilibrium on class3 with a 5 mm mandible advance, each
configuration a fresh ``scripts/simulate.py`` process (under ``mpirun -n N``), so the times
include nothing cached in memory; the mesh comes from the disk cache and FFCx's JIT cache.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from scripts._launch import mpirun  # noqa: E402

BENCH_MD = ROOT / "BENCHMARKS.md"
DOCS = ROOT / "docs"
#: The fixed class3 treatment of the accuracy study (NAME=VALUE, mm).
TREATMENT = ["mandible.advance_mm=5", "mandible.lateral_mm=1", "maxilla_L.advance_mm=2",
             "maxilla_R.advance_mm=2"]


def _machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB, {platform.platform()}"


def _simulate(res: str, solver: str, n: int, extra=(), script="simulate.py",
              args=None, timeout: float | None = None) -> dict:
    args = args or ["--case", "class3", "--resolution", res, "--solver", solver, "--p",
                    "mandible.advance_mm=5"]
    with tempfile.TemporaryDirectory() as d:
        rep = Path(d) / "r.json"
        cmd = [sys.executable, str(ROOT / "scripts" / script), *args, "--report", str(rep),
               *extra]
        cmd = [*mpirun(n), *cmd]
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"error": f"not solved within {timeout:g} s (stopped)"}
        if r.returncode != 0:
            return {"error": (r.stderr.strip().splitlines() or ["failed"])[-1]}
        return json.loads(rep.read_text())


def _write_section(name: str, body: str) -> None:
    """Replace (or append) the section between ``<!-- name -->`` markers in BENCHMARKS.md."""
    text = BENCH_MD.read_text(encoding="utf-8") if BENCH_MD.exists() else "# Benchmarks\n"
    start, end = f"<!-- {name} -->", f"<!-- /{name} -->"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text:
        text = re.sub(re.escape(start) + ".*?" + re.escape(end), lambda _: block, text,
                      flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    tmp = BENCH_MD.with_suffix(".md.part")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, BENCH_MD)


def forward(args) -> None:
    """Forward equilibrium across resolutions, presets and rank counts: time, memory,
    iterations. Iterative presets run up to ``--iterative-up-to`` (they take ~100x longer)."""
    rows = []
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
                r = _simulate(res, solver, n, extra=["--method", method])
                if "error" in r:
                    rows.append([res, "", "", n, solver, method, f"failed: {r['error'][:60]}"]
                                + [""] * (len(head) - 7))
                else:
                    t = r["timings_s"]
                    rows.append([res, r["n_vertices"], 3 * r["n_vertices"], n, solver, method,
                                 r["newton_iterations"], r["linear_iterations"],
                                 len(r["diagonal_shifts"]), r["factorisations"],
                                 f"{t['assemble']:.2f}", f"{t['linear_solve']:.2f}",
                                 f"**{t['solve']:.2f}**", f"{r['peak_rss_mb']:.0f}",
                                 f"{r['active_goal_error_max_mm']:.3f}"])
                print(rows[-1], flush=True)
    body = _header("Forward equilibrium (rest to 5 mm mandible advance, class3)", args) + [
        "`method`: quasi-Newton (L-BFGS on one kept factorisation, the default) or Newton "
        "(a factorisation per step); `its` counts its nonlinear iterations. "
        "`equilibrium s` is the whole solve (assembly + factorisation/solves + line search); "
        "`linear solve s` is its part outside assembly; `KSP its` counts Krylov iterations "
        "(1 per Newton step with a direct factorisation); `shifts` counts diagonal "
        "regularisations; peak RSS is summed over ranks. CHOLMOD is sequential in PETSc; "
        "like MUMPS it shifts K until it is positive definite (a failed Cholesky). "
        f"GAMG is run up to `{args.iterative_up_to}`.", "",
        *_table(head, rows)]
    _write_section("forward", "\n".join(body))


def stress(args) -> None:
    """Large single moves from rest (class3-asym, `PLAN_PARAMS`): the mandible advanced by m
    and shifted 0.3 m mm in one solve; each case a fresh ``simulate.py``, stopped after
    ``--timeout`` s."""
    head = ["resolution", "m mm", "its", "factorisations", "shifts", "continuation steps",
            "min det F", "goal err mm", "equilibrium s"]
    sys.path.insert(0, str(ROOT))
    from inverse.treatment import PLAN_PARAMS

    rows = []
    for case in args.cases.split(","):
        res, mag = case.split(":")
        m = float(mag)
        r = _simulate(res, "direct", 1, timeout=args.timeout, args=[
            "--case", "class3-asym", "--resolution", res, "--params-used",
            ",".join(PLAN_PARAMS), "--p", f"mandible.advance_mm={m:g}",
            f"mandible.lateral_mm={0.3 * m:g}"])
        if "error" in r:
            rows.append([res, f"{m:g}", r["error"][:70]] + [""] * (len(head) - 3))
        else:
            rows.append([res, f"{m:g}", r["newton_iterations"], r["factorisations"],
                         len(r["diagonal_shifts"]), r["continuation_steps"],
                         f"{r['min_det_F']:.2f}", f"{r['active_goal_error_max_mm']:.3f}",
                         f"**{r['timings_s']['solve']:.2f}**"])
        print(rows[-1], flush=True)
    body = _header("Stress: large single moves from rest (class3-asym, 1 rank)", args) + [
        "The mandible advanced by m mm and shifted 0.3 m mm from rest in one solve "
        "(`scripts/simulate.py`, `PLAN_PARAMS`, direct preset, quasi-Newton with Newton as "
        f"fallback); a case still running after {args.timeout:g} s is stopped.", "",
        *_table(head, rows)]
    _write_section("stress", "\n".join(body))


def _fd_gradient(scene, obj, h: float):
    """Forward-difference dT/dp (Np,): Np warm forward solves from the current equilibrium,
    which is restored afterwards."""
    import numpy as np

    base = scene.eq.snapshot()
    p, T0 = scene.eq.p.copy(), obj.value()
    fd = np.empty(len(p))
    for i in range(len(p)):
        scene.solve(p + h * np.eye(len(p))[i])
        fd[i] = (obj.value() - T0) / h
        scene.eq.restore(base)
    return fd


#: How the benchmarks' corrected prediction is made and timed.
CORRECTED = ("Corrected (`SkinPredictor.corrected`): continuation on the kept factorisation "
             "of K(p0), in substeps whose first-order step moves no vertex more than "
             "`CORRECTION_SUBSTEP_MM` = 4 mm, each started from the secant extrapolation of "
             "the last two (the first: first-order) and relaxed by `CORRECTION_ITERATIONS` = 6 "
             "quasi-Newton steps, the L-BFGS pairs kept from substep to substep; no assembly "
             "of K, no factorisation (a fresh predictor for each m, so every correction and "
             "true solve starts from the factorisation at p0).")


def _prediction_errors(scene, mags) -> list:
    """Plain and corrected first-order skin predictions against true equilibria, for
    the mandible advanced by m and shifted 0.3 m (mm), m in ``mags``, from the scene's
    equilibrium p0."""
    import time

    import numpy as np

    from inverse.explore import SkinPredictor

    base, rows = scene.eq.snapshot(), []
    names = scene.param_names
    for mag in mags:
        scene.eq.restore(base)
        pred = SkinPredictor(scene)   # K(p0) factorised again: the previous m replaced it
        dp = np.zeros(len(names))
        dp[names.index("mandible.advance_mm")] = mag
        dp[names.index("mandible.lateral_mm")] = 0.3 * mag
        t = time.perf_counter()
        for _ in range(100):
            plain = pred.predict(dp)
        t_plain = (time.perf_counter() - t) / 100
        t = time.perf_counter()
        corr, _ = pred.corrected(dp)
        t_corr = time.perf_counter() - t
        try:
            t = time.perf_counter()
            scene.solve(pred.p0 + dp)
            t_true = time.perf_counter() - t
        except Exception as e:  # report, do not stop the benchmark
            rows.append(dict(mag=mag, error=str(e)[:80]))
            pred.destroy()
            continue
        true = pred.op.apply(scene.eq.u_eq.array)
        scene.eq.restore(base)
        pred.destroy()
        rows.append(dict(mag=mag, disp=np.linalg.norm(true - pred.x0, axis=1).max(),
                         plain=np.linalg.norm(plain - true, axis=1).max(),
                         corr=np.linalg.norm(corr - true, axis=1).max(),
                         t_plain_ms=1e3 * t_plain, t_corr=t_corr, t_true=t_true))
    return rows


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
    fd = _fd_gradient(scene, obj, 1e-3)
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
    rows = _prediction_errors(scene, mags)
    out["predictions"] = rows
    return out


def plan(args) -> None:
    lines = ["## Planning (class3-asym, default goal: 7 landmarks, `PLAN_PARAMS`: 10)", "",
             f"Command: `python3 scripts/bench.py plan --resolutions {args.resolutions} "
             f"--ranks {args.ranks} --magnitudes {args.magnitudes} --occlusions "
             f"{args.occlusions}`", "",
             f"Machine: {_machine()}.", "",
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
              "the mandible held in the final occlusion (`make demo`).", "",
              "| resolution | occlusion | ranks | GN iterations | forward solves | mean distance "
              "before mm | after mm | forward s | sensitivity s | adjoint s | line search s | "
              "total s |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for res, occ in itertools.product(args.resolutions.split(","), args.occlusions.split(",")):
        for n in map(int, args.ranks.split(",")):
            r = _simulate(res, "direct", n, script="plan.py",
                          args=["--case", "class3-asym", "--resolution", res, "--occlusion", occ])
            if "error" in r:
                lines.append(f"| {res} | {occ} | {n} | failed: {r['error'][:60]} | | | | | | | | |")
            else:
                t = r["timings_s"]
                lines.append(
                    f"| {res} | {occ} | {n} | {r['gn_iterations']} | {r['forward_solves']} | "
                    f"{r['mean_distance_before_mm']:.2f} | {r['mean_distance_after_mm']:.2f} | "
                    f"{t['forward']:.1f} | {t['sensitivity']:.1f} | {t['adjoint']:.1f} | "
                    f"{t['line_search']:.1f} | **{t['total']:.1f}** |")
            print(lines[-1], flush=True)
    _write_section("plan", "\n".join(lines))


def _plot(name: str, draw) -> str:
    """Draw with ``draw(plt)`` and save ``docs/<name>.png`` atomically; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    DOCS.mkdir(exist_ok=True)
    draw(plt)
    plt.tight_layout()
    tmp = DOCS / f".{name}.part.png"
    plt.savefig(tmp, dpi=110)
    plt.close("all")
    os.replace(tmp, DOCS / f"{name}.png")
    return f"docs/{name}.png"


def _command(args) -> str:
    return "python3 scripts/bench.py " + " ".join(sys.argv[1:]) if sys.argv[1:] else \
        f"python3 scripts/bench.py {args.what}"


def _header(title: str, args) -> list:
    return [f"## {title}", "", f"Command: `{_command(args)}`", "", f"Machine: {_machine()}.", ""]


def _table(head: list, rows: list) -> list:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head),
            *("| " + " | ".join(map(str, r)) + " |" for r in rows)]


def _landmark_motion(report: dict) -> dict:
    """{landmark: (3,) displacement, mm} from a simulate.py report."""
    import numpy as np

    return {n: np.subtract(x, report["landmarks_rest"][n]) for n, x in report["landmarks"].items()}


def acc_mesh(args) -> None:
    """Mesh convergence on class3 with `TREATMENT`: forward landmark error and planned p."""
    import numpy as np

    levels = args.resolutions.split(",")
    fwd = {r: _simulate(r, "direct", args.ranks_mesh, args=[
        "--case", "class3", "--resolution", r, "--p", *TREATMENT]) for r in levels}
    for r, rep in fwd.items():
        if "error" in rep:
            raise SystemExit(f"forward at {r} failed: {rep['error']}")
    disp = {r: _landmark_motion(v) for r, v in fwd.items()}
    used = [t.split("=")[0] for t in TREATMENT]
    p_star = np.array([float(t.split("=")[1]) for t in TREATMENT])
    goal = ["Pg", "Me", "Li", "Ls", "Sn"]
    rows, plans = [], {}
    for r in levels:
        err = np.array([np.linalg.norm(disp[r][n] - disp[levels[-1]][n]) for n in disp[r]])
        # the same goal on every mesh: each mesh's rest landmarks + the reference's motion
        with tempfile.TemporaryDirectory() as d:
            tfile = Path(d) / "targets.json"
            tfile.write_text(json.dumps({n: (np.array(fwd[r]["landmarks_rest"][n])
                                             + disp[levels[-1]][n]).tolist() for n in goal}))
            pl = _simulate(r, "direct", args.ranks_mesh, script="plan.py", args=[
                "--case", "class3", "--resolution", r, "--targets", str(tfile),
                "--params-used", ",".join(used), "--tikhonov", "0", "--ftol", "1e-8"])
        if "error" in pl:
            raise SystemExit(f"plan at {r} failed: {pl['error']}")
        plans[r] = pl
        t = fwd[r]["timings_s"]
        rows.append([r, fwd[r]["n_vertices"], f"{t['solve']:.1f}", f"{err.max():.3f}",
                     f"{err.mean():.3f}", f"{pl['timings_s']['total']:.1f}",
                     " ".join(f"{v:.2f}" for v in pl["params_optimal"]),
                     f"{np.abs(np.array(pl['params_optimal']) - p_star).max():.2f}",
                     f"{pl['mean_distance_after_mm']:.3f}"])
        print(rows[-1], flush=True)
    ts = [fwd[r]["timings_s"]["solve"] for r in levels[:-1]]
    errs = [float(rw[3]) for rw in rows[:-1]]

    def draw(plt):
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        ax[0].loglog(ts, errs, "o-")
        for r, x, y in zip(levels, ts, errs):
            ax[0].annotate(r, (x, y))
        ax[0].axhline(0.1, ls="--", c="gray", label="0.1 mm (clinically irrelevant)")
        ax[0].set(xlabel="forward solve wall time (s)", ylabel=f"max landmark error vs "
                  f"{levels[-1]} (mm)", title="forward, class3, fixed treatment")
        ax[0].legend()
        tp = [plans[r]["timings_s"]["total"] for r in levels]
        for i, n in enumerate(used):
            ax[1].semilogx(tp, [plans[r]["params_optimal"][i] for r in levels], "o-", label=n)
        ax[1].set(xlabel="plan wall time (s)", ylabel="planned p (mm)",
                  title="planned treatment, same goal")
        ax[1].legend(fontsize=7)

    png = _plot("mesh_convergence", draw)
    body = _header("Accuracy: mesh convergence (class3)", args) + [
        f"Treatment `{' '.join(TREATMENT)}`, {args.ranks_mesh} rank(s). Error: landmark "
        f"displacement against `{levels[-1]}` (all 9 landmarks). Plan: the reference's "
        f"landmark motion of {', '.join(goal)} added to each mesh's rest landmarks, "
        f"parameters {', '.join(used)} (truth p* = {p_star.tolist()}), α = 0.", "",
        "Clinically irrelevant (max landmark error < 0.1 mm) from "
        + next((f"`{r[0]}` ({r[1]} vertices, {r[2]} s a forward solve)" for r in rows
                if float(r[3]) < 0.1), "no level") + " on.", "",
        *_table(["resolution", "vertices", "forward s", "max landmark err mm",
                 "mean err mm", "plan s", "planned p", "max abs(p − p*)",
                 "plan mean distance mm"], rows), "", f"![mesh convergence]({png})"]
    _write_section("accuracy-mesh", "\n".join(body))


TOLERANCE_CHOICE = {
    "newton": "The default is the cheapest setting that is also safe for small treatments: "
    "xtol = 0.1 mm, frtol = 1e-2. A first Newton step shorter than xtol is accepted, so a "
    "treatment smaller than xtol ends at the linear (first-order) solution; at 1 mm that errs "
    "0.03 mm (prediction table), at 0.1 mm about 3e-4 mm (the error grows with the square of "
    "the step). xtol = 1 mm passes the curve above only because its treatment is large.",
    "qn": "Quasi-Newton converges linearly, so its test asks for the last step and the search "
    "direction both below xtol; the default xtol = 0.005 mm (0.01 mm erred 1.8e-3 mm on a "
    "tiny mesh's return to rest). Below xtol = 1e-4 mm (`QN_MIN_XTOL`) a solve uses Newton."}
#: xtol settings (mm) of the tolerance curve per method; frtol = xtol / 10.
TOLERANCE_XTOLS = {"newton": [10.0 ** -k for k in range(0, 8)],
                   "qn": [10.0 ** -k for k in (0.5, 1, 1.5, 2, 2.5, 3, 3.5)]}


def acc_tolerance(args) -> None:
    """Tolerances (xtol mm, frtol) of each method against landmark error and time: from
    rest, and warm-started (first-order prediction) after a small change, as in a plan's
    trials. Reference: Newton to 1e-10 mm."""
    import time

    import numpy as np

    sys.path.insert(0, str(ROOT))
    from inverse.scene import Scene

    refs = {}
    for method in args.methods_tol.split(","):
        out = {}
        for res in args.resolutions_tol.split(","):
            curve = []
            settings = [(x, x / 10, method) for x in TOLERANCE_XTOLS[method]]
            for xtol, frtol, m in [(1e-10, 1e-12, "newton"), *settings]:   # reference first
                if (res, 2) in refs and xtol == 1e-10:
                    continue
                scene = Scene.from_case("class3", res,
                                        newton=dict(method=m, xtol=xtol, frtol=frtol))
                p = scene.param_vector(dict(t.split("=") for t in TREATMENT))
                row = [xtol, frtol]
                for q in (p, p + 0.3 * np.eye(len(p))[0] + 0.1 * np.eye(len(p))[1]):
                    t = time.perf_counter()
                    st = scene.solve(q)
                    dt = time.perf_counter() - t
                    lm = np.array(list(scene.landmarks().values()))
                    refs.setdefault((res, len(row)), lm)
                    row += [st.newton_iterations, dt, float(np.linalg.norm(
                        lm - refs[(res, len(row))], axis=1).max())]
                curve.append(row)
                print(method, res, row, flush=True)
                scene.eq.destroy()
            out[res] = curve[-len(settings):]
        _tolerance_section(method, out, args)


def _tolerance_section(method: str, out: dict, args) -> None:
    """BENCHMARKS section and plot of one method's tolerance curve."""
    rows = [[res, f"{c[0]:.0e}", f"{c[1]:.0e}", c[2], f"{c[3]:.2f}", f"{c[4]:.1e}", c[5],
             f"{c[6]:.2f}", f"{c[7]:.1e}"] for res, cs in out.items() for c in cs]
    chosen = {res: max((c for c in cs if c[4] < 1e-3 and c[7] < 1e-3), key=lambda c: c[0])
              for res, cs in out.items()}
    name = {"newton": "Newton", "qn": "quasi-Newton"}[method]

    def draw(plt):
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        for k, (i, what) in enumerate([(2, "from rest"), (5, "warm start (+0.3 mm)")]):
            for res, cs in out.items():
                ax[k].loglog([c[i + 1] for c in cs], [max(c[i + 2], 1e-12) for c in cs], "o-",
                             label=res)
                for c in cs:
                    ax[k].annotate(f"{c[0]:.0e}", (c[i + 1], max(c[i + 2], 1e-12)),
                                   fontsize=7)
            ax[k].axhline(1e-3, ls="--", c="gray", label="1e-3 mm")
            ax[k].set(xlabel="equilibrium wall time (s)", ylabel="max landmark error (mm)",
                      title=f"{name}, {what}; labels: xtol mm")
            ax[k].legend()

    suffix = "" if method == "newton" else "-" + method
    png = _plot("tolerance" + suffix, draw)
    body = _header(f"Accuracy: {name} tolerances", args) + [
        f"class3, `{' '.join(TREATMENT)}` from rest, then warm-started (first-order "
        "prediction) to 0.3 mm more advance and 0.1 mm more lateral shift, 1 rank, direct "
        f"preset, `method={method!r}`. A solve stops when a full step is below `xtol` "
        "(inf-norm, mm) and the residual is below `frtol` × the load of the step. Error: max "
        "over the 9 landmarks against Newton to xtol = 1e-10, frtol = 1e-12.", "",
        *_table(["resolution", "xtol mm", "frtol", "its (rest)", "s (rest)",
                 "err mm (rest)", "its (warm)", "s (warm)", "err mm (warm)"], rows), "",
        "Cheapest setting with landmark error < 1e-3 mm in both: " + "; ".join(
            f"{res}: xtol = {c[0]:.0e} mm ({c[2]} + {c[5]} iterations)"
            for res, c in chosen.items()) + ".", "", TOLERANCE_CHOICE[method], "",
        f"![tolerance]({png})"]
    _write_section("accuracy-tolerance" + suffix, "\n".join(body))


def acc_prediction(args) -> None:
    """First-order skin prediction error against |dp|, plain and corrected."""
    sys.path.insert(0, str(ROOT))
    from inverse.scene import Scene
    from inverse.treatment import PLAN_PARAMS

    mags = [1.0, 2.0, 3.0, 5.0, 7.0, 10.0, 14.0, 20.0]
    out = {}
    for res in args.resolutions_pred.split(","):
        scene = Scene.from_case("class3-asym", res, params_used=PLAN_PARAMS)
        out[res] = [r for r in _prediction_errors(scene, mags) if "error" not in r]
        scene.eq.destroy()
    rows = [[res, f"{r['mag']:g}", f"{r['disp']:.2f}", f"{r['plain']:.3f}",
             f"{r['t_plain_ms']:.3f}", f"{r['corr']:.3f}", f"{r['t_corr']:.2f}",
             f"{r['t_true']:.2f}"] for res, rs in out.items() for r in rs]

    def draw(plt):
        fig, ax = plt.subplots(figsize=(6, 4))
        for res, rs in out.items():
            d = [r["disp"] for r in rs]
            ax.loglog(d, [r["plain"] for r in rs], "o-", label=f"{res} plain")
            ax.loglog(d, [r["corr"] for r in rs], "s--", label=f"{res} corrected")
        ax.set(xlabel="max skin displacement (mm)", ylabel="max skin error (mm)",
               title="first-order prediction from the rest face")
        ax.legend()

    png = _plot("prediction", draw)
    body = _header("Accuracy: first-order prediction against |dp|", args) + [
        "class3-asym from the rest face; the mandible advanced by m mm and shifted 0.3 m mm. "
        "Max skin error against the true equilibrium. " + CORRECTED, "",
        *_table(["resolution", "m mm", "max skin displacement mm", "plain error mm",
                 "plain ms/call", "corrected error mm", "corrected s", "true equilibrium s"],
                rows), "", f"![prediction]({png})"]
    _write_section("accuracy-prediction", "\n".join(body))


def acc_gradient(args) -> None:
    """Adjoint gradient against forward differences: cost against Np, FD error against h."""
    import time

    import numpy as np

    sys.path.insert(0, str(ROOT))
    from inverse.scene import Scene
    from inverse.treatment import rigid_treatment

    res = args.resolution_grad
    names = rigid_treatment().names
    cost = []
    for n_p in (2, 6, 12, 18):
        scene = Scene.from_case("class3-asym", res, params_used=names[:n_p])
        p = 0.5 * np.ones(n_p)
        scene.solve(p)
        obj = scene.objective(scene.default_targets())
        t = time.perf_counter()
        g = obj.gradient()
        t_adj = time.perf_counter() - t
        t = time.perf_counter()
        fd = _fd_gradient(scene, obj, 1e-3)
        t_fd = time.perf_counter() - t
        cost.append((n_p, t_adj, t_fd, float(np.abs(fd - g).max() / np.abs(g).max())))
        print(cost[-1], flush=True)
        if n_p == 6:   # FD error against h at this equilibrium
            hs = [10.0 ** -k for k in range(0, 8)]
            h_err = [float(np.abs(_fd_gradient(scene, obj, h) - g).max() / np.abs(g).max())
                     for h in hs]
            print(list(zip(hs, h_err)), flush=True)
        scene.eq.destroy()

    def draw(plt):
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        ax[0].semilogy([c[0] for c in cost], [c[1] for c in cost], "o-", label="adjoint")
        ax[0].semilogy([c[0] for c in cost], [c[2] for c in cost], "s-",
                       label="forward differences")
        ax[0].set(xlabel="number of parameters Np", ylabel="gradient wall time (s)",
                  title=f"class3-asym {res}")
        ax[0].legend()
        ax[1].loglog(hs, h_err, "o-")
        ax[1].set(xlabel="FD step h (parameter units)",
                  ylabel="relative error vs adjoint", title="FD accuracy, Np = 6")

    png = _plot("gradient", draw)
    body = _header("Accuracy: adjoint gradient against finite differences", args) + [
        f"class3-asym {res}, default goal (7 landmarks), the first Np rigid parameters, at "
        "p = 0.5 (units). Adjoint: one tangent solve with the kept factorisation. FD: Np "
        "warm-started forward solves (h = 1e-3).", "",
        *_table(["Np", "adjoint s", "FD s", "FD/adjoint", "FD vs adjoint (rel.)"],
                [[n, f"{a:.3f}", f"{f:.2f}", f"{f / a:.0f}x", f"{e:.1e}"]
                 for n, a, f, e in cost]), "",
        "FD error against h (Np = 6): " + ", ".join(f"h = {h:.0e}: {e:.1e}"
                                                    for h, e in zip(hs, h_err)) + ".", "",
        f"![gradient]({png})"]
    _write_section("accuracy-gradient", "\n".join(body))


def acc_order(args) -> None:
    """P1 against P2 at nu = 0.47 on class3 with `TREATMENT`: landmark error against time."""
    import numpy as np

    runs = [(d, r) for d, levels in ((1, args.resolutions_p1), (2, args.resolutions_p2))
            for r in levels.split(",")]
    reps = {}
    for d, r in runs:
        reps[d, r] = _simulate(r, "direct", args.ranks_mesh, args=[
            "--case", "class3", "--resolution", r, "--degree", str(d), "--p", *TREATMENT])
        if "error" in reps[d, r]:
            raise SystemExit(f"P{d} at {r} failed: {reps[d, r]['error']}")
        print(d, r, reps[d, r]["timings_s"]["solve"], flush=True)
    ref = (2, args.resolutions_p2.split(",")[-1])
    motion = {k: _landmark_motion(v) for k, v in reps.items()}
    rows, curves = [], {1: [], 2: []}
    for d, r in runs:
        rep = reps[d, r]
        err = np.array([np.linalg.norm(motion[d, r][n] - motion[ref][n]) for n in motion[ref]])
        t = rep["timings_s"]["solve"]
        if (d, r) != ref:
            curves[d].append((t, err.max(), r))
        rows.append([f"P{d}", r, rep["n_vertices"], rep["n_dofs"], rep["newton_iterations"],
                     f"{t:.1f}", f"{rep['peak_rss_mb']:.0f}",
                     "reference" if (d, r) == ref else f"{err.max():.3f}",
                     "" if (d, r) == ref else f"{err.mean():.3f}",
                     f"{rep['active_goal_error_max_mm']:.3f}"])

    def draw(plt):
        fig, ax = plt.subplots(figsize=(6, 4))
        for d, c in curves.items():
            ax.loglog([t for t, _, _ in c], [e for _, e, _ in c], "o-", label=f"P{d}")
            for t, e, r in c:
                ax.annotate(r, (t, e), fontsize=7)
        ax.axhline(0.1, ls="--", c="gray", label="0.1 mm (clinically irrelevant)")
        ax.set(xlabel=f"forward solve wall time (s, {args.ranks_mesh} ranks)",
               ylabel=f"max landmark error vs P2/{ref[1]} (mm)",
               title="element order, class3, nu = 0.47")
        ax.legend()

    png = _plot("element_order", draw)
    body = _header("Accuracy: element order, P1 against P2 (class3, ν = 0.47)", args) + [
        f"Treatment `{' '.join(TREATMENT)}`, {args.ranks_mesh} rank(s), MUMPS. Error: "
        f"landmark displacement (9 landmarks) against P2 on `{ref[1]}`, the richest "
        "discretisation run. P2 integrates the elastic energy with degree-2 quadrature "
        "(4 points; degree 4 and 6 moved landmarks by < 8e-4 mm on tiny), P1 with one point "
        "(exact). The penalty is the same consistent facet integral.", "",
        *_table(["element", "resolution", "vertices", "dofs", "Newton its", "forward s",
                 "peak RSS MiB", "max landmark err mm", "mean err mm", "goal err mm"], rows),
        "", "Cheapest run below 0.1 mm: " + "; ".join(
            f"P{d}: " + next((f"`{r}` ({t:.1f} s, {e:.3f} mm)" for t, e, r in c if e < 0.1),
                             "none") for d, c in curves.items()) + ".", "",
        "Each resolution meshes the synthetic head anew and both elements use its straight-"
        "sided tetrahedra, so part of every error is the geometry (where the skin and the "
        "bone are), which a higher displacement degree does not remove. At ν = 0.47 P1 shows "
        "no locking that P2 would cure: at equal time P1 on a finer mesh is at least as "
        "accurate, with 3-7x less memory, so P1 stays the default. P2's consistent penalty "
        "spreads k over six nodes per facet: its bone ends 0.03-0.04 mm from the goal "
        "(P1: 0.003), still within the 0.05 mm tolerance.", "",
        f"![element order]({png})"]
    _write_section("accuracy-order", "\n".join(body))


def accuracy(args) -> None:
    parts = {"mesh": acc_mesh, "tolerance": acc_tolerance, "prediction": acc_prediction,
             "gradient": acc_gradient, "order": acc_order}
    for part in args.parts.split(","):
        if part not in parts:
            raise SystemExit(f"unknown part {part!r}; choose from {list(parts)}")
        parts[part](args)


#: Most ranks a benchmark may ask for (the machine has 2 cores; more only oversubscribe),
#: and the largest move (mm) it may ask for: the stress table's largest is 20 mm.
MAX_RANKS, MAX_MOVE_MM = 64, 100.0


def check_args(args) -> None:
    """Every option of the benchmark in range, lists not empty: ValueError naming the
    option and what it allows otherwise."""
    import math

    sys.path.insert(0, str(ROOT))
    from fem.policy import METHODS, PRESETS
    from meshes.synthetic import CASES, RESOLUTIONS
    from scripts.bench_ct import CTS

    def items(name):
        value = getattr(args, name)
        got = [v.strip() for v in str(value).split(",") if v.strip()]
        if not got:
            raise ValueError(f"--{name.replace('_', '-')} must name at least one item, "
                             f"got {value!r}")
        return got

    def among(name, allowed):
        for v in items(name):
            if v not in allowed:
                raise ValueError(f"--{name.replace('_', '-')}: unknown {v!r}; choose from "
                                 f"{list(allowed)}")

    def number(name, v, lo, hi, integer=False):
        try:
            x = int(v) if integer else float(v)
        except ValueError:
            x = math.nan
        if not (math.isfinite(x) and lo <= x <= hi):
            raise ValueError(f"--{name.replace('_', '-')} must be a finite "
                             f"{'integer' if integer else 'number'} in [{lo:g}, {hi:g}], got "
                             f"{v!r}")

    lists = {"resolutions": RESOLUTIONS, "resolutions_tol": RESOLUTIONS,
             "resolutions_pred": RESOLUTIONS, "resolutions_p1": RESOLUTIONS,
             "resolutions_p2": RESOLUTIONS, "iterative_up_to": RESOLUTIONS,
             "resolution_grad": RESOLUTIONS, "solvers": PRESETS, "methods": METHODS,
             "methods_tol": METHODS, "occlusions": ("free", "final"), "cts": CTS,
             "parts": ("mesh", "tolerance", "prediction", "gradient", "order")}
    for name, allowed in lists.items():
        if getattr(args, name, None) is not None:
            among(name, allowed)
    for n in items("ranks") if getattr(args, "ranks", None) is not None else []:
        number("ranks", n, 1, MAX_RANKS, integer=True)
    if getattr(args, "ranks_mesh", None) is not None:
        number("ranks_mesh", args.ranks_mesh, 1, MAX_RANKS, integer=True)
    for m in items("magnitudes") if getattr(args, "magnitudes", None) is not None else []:
        number("magnitudes", m, -MAX_MOVE_MM, MAX_MOVE_MM)
    if args.what == "stress":
        number("timeout", args.timeout, 1e-3, 1e6)
        for case in items("cases"):
            res, _, mag = case.partition(":")
            if res not in RESOLUTIONS:
                raise ValueError(f"--cases: {case!r} must be resolution:mm with a resolution "
                                 f"in {list(RESOLUTIONS)}")
            number("cases", mag, -MAX_MOVE_MM, MAX_MOVE_MM)
    elif args.what == "plausibility" and args.cases is not None:
        among("cases", CASES)
    elif args.what == "explorer":
        number("events", args.events, 1, 10000, integer=True)
        args.events = int(args.events)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors, exit 2 (the scripts' convention)."""

    def error(self, message):
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)


def main():
    ap = _Parser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True, parser_class=_Parser)
    f = sub.add_parser("forward", help="forward equilibrium across resolutions and solvers")
    f.add_argument("--resolutions", default="tiny,coarse,medium,paper")
    f.add_argument("--solvers", default="direct,cholmod,gamg")
    f.add_argument("--ranks", default="1,2")
    f.add_argument("--methods", default="qn,newton")
    f.add_argument("--iterative-up-to", default="paper",
                   help="largest resolution for the GAMG preset")
    pl = sub.add_parser("plan", help="derivatives, exploration and whole plans")
    pl.add_argument("--resolutions", default="coarse,paper")
    pl.add_argument("--ranks", default="1,2")
    pl.add_argument("--occlusions", default="free,final", help="plan.py --occlusion values")
    pl.add_argument("--magnitudes", default="2,5",
                    help="mandible advances m (mm) of the exploration table; at paper size the "
                         "true equilibrium of m = 10 from rest takes ~14 s (`stress`)")
    st = sub.add_parser("stress", help="large single moves from rest")
    st.add_argument("--cases", default="coarse:10,coarse:14,coarse:20,medium:14,paper:10,paper:20",
                    help="resolution:m pairs (m: mandible advance, mm)")
    st.add_argument("--timeout", type=float, default=300.0, help="seconds per case")
    a = sub.add_parser("accuracy", help="run time against error (plots in docs/)")
    a.add_argument("--parts", default="mesh,tolerance,prediction,gradient,order")
    a.add_argument("--resolutions", default="tiny,coarse,medium,paper,fine",
                   help="mesh part; the last is the reference")
    a.add_argument("--ranks-mesh", type=int, default=2)
    a.add_argument("--resolutions-tol", default="medium,paper")
    a.add_argument("--methods-tol", default="newton,qn")
    a.add_argument("--resolutions-pred", default="coarse,medium")
    a.add_argument("--resolution-grad", default="medium")
    a.add_argument("--resolutions-p1", default="tiny,coarse,medium,paper")
    a.add_argument("--resolutions-p2", default="tiny,coarse,medium",
                   help="order part; the last P2 level is the reference")
    pp = sub.add_parser("plausibility", help="soft-to-hard movement ratios against the "
                        "clinical literature")
    pp.add_argument("--resolutions", default="coarse,paper")
    pp.add_argument("--cases", default=None, help="comma-separated (default: all)")
    c = sub.add_parser("ct", help="the CT pipeline on the example CTs, to a plan")
    c.add_argument("--cts", default="headsq,cranium")
    c.add_argument("--resolutions", default="coarse,paper")
    e = sub.add_parser("explorer", help="the browser explorer in headless Chromium")
    e.add_argument("--resolutions", default="coarse,paper")
    e.add_argument("--ranks", default="1,2")
    e.add_argument("--events", default="60", help="slider events timed per row")
    e.add_argument("--screenshot", default="docs/explorer.png",
                   help="picture of the last row's page, relative to the project ('' none)")
    args = ap.parse_args()
    try:
        check_args(args)
    except ValueError as e:   # one line, exit 2, before any work (issue 19)
        ap.error(str(e))
    {"forward": forward, "plan": plan, "stress": stress, "accuracy": accuracy,
     "plausibility": plausibility, "ct": ct, "explorer": explorer}[args.what](args)


def plausibility(args) -> None:
    """Soft-to-hard movement ratios (`scripts/bench_plausibility.py`)."""
    sys.path.insert(0, str(ROOT))
    from scripts import bench_plausibility

    bench_plausibility.plausibility(args, _simulate, lambda t, a: _header(t, a), _table,
                                    _write_section)


def ct(args) -> None:
    """The CT pipeline on headsq and Cranium (`scripts/bench_ct.py`)."""
    sys.path.insert(0, str(ROOT))
    from scripts import bench_ct

    bench_ct.ct(args, lambda t, a: _header(t, a), _table, _write_section)


def explorer(args) -> None:
    """The browser explorer's interaction figures (`scripts/bench_explorer.py`)."""
    from scripts import bench_explorer

    bench_explorer.explorer(args, lambda t, a: _header(t, a), _table, _write_section)


if __name__ == "__main__":
    main()
