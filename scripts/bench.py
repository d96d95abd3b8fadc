#!/usr/bin/env python3
"""Benchmarks (not timed tests). Results are printed and written into BENCHMARKS.md.

    python3 scripts/bench.py forward [--resolutions tiny,coarse,medium,paper]
                                     [--solvers direct,gamg] [--ranks 1,2]
    python3 scripts/bench.py plan [--resolutions coarse,paper] [--ranks 1,2]

``plan``: class3-asym. In one process: the costs of one forward solve, the adjoint gradient,
the landmark block S_T, the finite-difference gradient (Np + 1 forward solves), the skin
sensitivities, a first-order prediction and a chord-corrected one (error against the true
equilibrium). Then the whole plan from p = 0 with ``scripts/plan.py`` (default goal).

``forward``: rest-to-treated equilibrium on class3 with a 5 mm mandible advance, each
configuration a fresh ``scripts/simulate.py`` process (under ``mpirun -n N``), so the times
include nothing cached in memory; the mesh comes from the disk cache and FFCx's JIT cache.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH_MD = ROOT / "BENCHMARKS.md"


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
              args=None) -> dict:
    args = args or ["--case", "class3", "--resolution", res, "--solver", solver, "--p",
                    "mandible.advance_mm=5"]
    with tempfile.TemporaryDirectory() as d:
        rep = Path(d) / "r.json"
        cmd = [sys.executable, str(ROOT / "scripts" / script), *args, "--report", str(rep),
               *extra]
        if n > 1:
            launcher = shutil.which("mpirun") or shutil.which("mpiexec")
            root = ["--allow-run-as-root"] if os.geteuid() == 0 else []
            cmd = [launcher, *root, "-n", str(n), *cmd]
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        r = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if r.returncode != 0:
            return {"error": (r.stderr.strip().splitlines() or ["failed"])[-1]}
        return json.loads(rep.read_text())


def _write_section(name: str, body: str) -> None:
    """Replace (or append) the section between ``<!-- name -->`` markers in BENCHMARKS.md."""
    text = BENCH_MD.read_text() if BENCH_MD.exists() else "# Benchmarks\n"
    start, end = f"<!-- {name} -->", f"<!-- /{name} -->"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text:
        text = re.sub(re.escape(start) + ".*?" + re.escape(end), lambda _: block, text,
                      flags=re.S)
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    tmp = BENCH_MD.with_suffix(".md.part")
    tmp.write_text(text)
    os.replace(tmp, BENCH_MD)


def forward(args) -> None:
    rows = []
    header = ("| resolution | vertices | dofs | ranks | solver | Newton its | shifts | mesh s "
              "| compile s | assemble s | linear solve s | equilibrium s | goal err mm |")
    print(header)
    for res in args.resolutions.split(","):
        for solver in args.solvers.split(","):
            for n in map(int, args.ranks.split(",")):
                r = _simulate(res, solver, n)
                if "error" in r:
                    row = f"| {res} | | | {n} | {solver} | failed: {r['error'][:60]} |" \
                          " | | | | | | |"
                else:
                    t = r["timings_s"]
                    row = (f"| {res} | {r['n_vertices']} | {3 * r['n_vertices']} | {n} | "
                           f"{solver} | {r['newton_iterations']} | {len(r['diagonal_shifts'])} "
                           f"| {t['mesh']:.1f} | {t['compile']:.1f} | {t['assemble']:.2f} | "
                           f"{t['linear_solve']:.2f} | **{t['solve']:.2f}** | "
                           f"{r['active_goal_error_max_mm']:.3f} |")
                print(row, flush=True)
                rows.append(row)
    body = "\n".join([
        "## Forward equilibrium (rest to 5 mm mandible advance, class3)", "",
        f"Command: `python3 scripts/bench.py forward --resolutions {args.resolutions} "
        f"--solvers {args.solvers} --ranks {args.ranks}`", "",
        f"Machine: {_machine()}.", "",
        "`equilibrium s` is the whole solve (assembly + factorisation/solves + line search);",
        "`linear solve s` is its part outside assembly. `shifts` counts diagonal",
        "regularisations. Mesh time is a read from the disk cache.", "",
        header, "|" + "---|" * 13, *rows])
    _write_section("forward", body)


def _derivative_costs(res: str) -> dict:
    """Times (s) and errors (mm) of the derivative machinery at one equilibrium, 1 rank."""
    import time

    import numpy as np

    sys.path.insert(0, str(ROOT))
    from inverse.explore import SkinPredictor
    from inverse.scene import Scene
    from inverse.treatment import PLAN_PARAMS

    scene = Scene.from_case("class3-asym", res, params_used=PLAN_PARAMS)
    p = scene.param_vector({"mandible.advance_mm": -4.0, "mandible.yaw_deg": -3.0,
                            "maxilla_L.advance_mm": 1.5, "maxilla_R.advance_mm": 1.5})
    t = time.perf_counter()
    scene.solve(p)
    out = {"forward_from_rest": time.perf_counter() - t, "n_params": len(p)}
    obj = scene.objective(scene.default_targets())
    t = time.perf_counter()
    g = obj.gradient()
    out["adjoint_gradient"] = time.perf_counter() - t
    t = time.perf_counter()
    S, mode = obj.jacobian()
    out["S_T"], out["S_T_mode"] = time.perf_counter() - t, mode
    # finite differences: Np forward solves from the equilibrium (warm, predicted)
    base, h = scene.eq.snapshot(), 1e-3
    T0, fd = obj.value(), np.empty(len(p))
    t = time.perf_counter()
    for i in range(len(p)):
        e = np.zeros(len(p))
        e[i] = h
        scene.solve(p + e)
        fd[i] = (obj.value() - T0) / h
        scene.eq.restore(base)
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
    rows = []
    for mag in (2.0, 5.0, 10.0, 20.0):
        dp = np.zeros(len(p))
        dp[:2] = [mag, 0.3 * mag]      # mandible advanced and shifted
        t = time.perf_counter()
        for _ in range(100):
            plain = pred.predict(dp)
        t_plain = (time.perf_counter() - t) / 100
        t = time.perf_counter()
        corr, _ = pred.corrected(dp, steps=2, substeps=8)
        t_corr = time.perf_counter() - t
        try:
            scene.solve(dp)
        except Exception as e:  # report, do not stop the benchmark
            rows.append(dict(mag=mag, error=str(e)[:80]))
            scene.eq.restore(base)
            continue
        true = pred.op.apply(scene.eq.u_eq.array)
        scene.eq.restore(base)
        rows.append(dict(mag=mag, disp=np.linalg.norm(true - pred.x0, axis=1).max(),
                         plain=np.linalg.norm(plain - true, axis=1).max(),
                         corr=np.linalg.norm(corr - true, axis=1).max(),
                         t_plain_ms=1e3 * t_plain, t_corr=t_corr))
    out["predictions"] = rows
    return out


def plan(args) -> None:
    lines = ["## Planning (class3-asym, default goal: 7 landmarks, `PLAN_PARAMS`: 10)", "",
             f"Command: `python3 scripts/bench.py plan --resolutions {args.resolutions} "
             f"--ranks {args.ranks}`", "", f"Machine: {_machine()}.", "",
             "### Derivatives at one equilibrium (1 rank, seconds)", "",
             "| resolution | forward from rest | forward, warm | adjoint gradient | "
             "S_T (mode) | FD gradient (Np solves) | FD/adjoint time | FD vs adjoint |",
             "|---|---|---|---|---|---|---|---|"]
    pred_lines = ["", "### First-order exploration of the whole skin (1 rank)", "",
                  "From the rest face, mandible advanced by m mm and shifted 0.3 m mm; "
                  "errors are the max over the skin against the true equilibrium; "
                  "corrected = 8 continuation parts (doubled while a part inverts an "
                  "element) × 2 chord-Newton steps with the kept "
                  "factorisation.", "",
                  "| resolution | skin vertices | skin S s (Np solves excluded: see S_T) | m mm | "
                  "max skin displacement mm | "
                  "plain error mm | plain ms/call | corrected error mm | corrected s |",
                  "|---|---|---|---|---|---|---|---|---|"]
    for res in args.resolutions.split(","):
        c = _derivative_costs(res)
        row = (f"| {res} | {c['forward_from_rest']:.2f} | {c['forward_warm']:.2f} | "
               f"{c['adjoint_gradient']:.3f} | {c['S_T']:.3f} ({c['S_T_mode']}) | "
               f"{c['fd_gradient']:.2f} | {c['fd_gradient'] / c['adjoint_gradient']:.0f}x | "
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
              "| resolution | ranks | GN iterations | forward solves | mean distance before mm "
              "| after mm | forward s | sensitivity s | adjoint s | line search s | total s |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for res in args.resolutions.split(","):
        for n in map(int, args.ranks.split(",")):
            r = _simulate(res, "direct", n, script="plan.py",
                          args=["--case", "class3-asym", "--resolution", res])
            if "error" in r:
                lines.append(f"| {res} | {n} | failed: {r['error'][:60]} | | | | | | | | |")
            else:
                t = r["timings_s"]
                lines.append(
                    f"| {res} | {n} | {r['gn_iterations']} | {r['forward_solves']} | "
                    f"{r['mean_distance_before_mm']:.2f} | {r['mean_distance_after_mm']:.2f} | "
                    f"{t['forward']:.1f} | {t['sensitivity']:.1f} | {t['adjoint']:.1f} | "
                    f"{t['line_search']:.1f} | **{t['total']:.1f}** |")
            print(lines[-1], flush=True)
    _write_section("plan", "\n".join(lines))


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    f = sub.add_parser("forward", help="forward equilibrium across resolutions and solvers")
    f.add_argument("--resolutions", default="tiny,coarse,medium,paper")
    f.add_argument("--solvers", default="direct,gamg")
    f.add_argument("--ranks", default="1,2")
    pl = sub.add_parser("plan", help="derivatives, exploration and whole plans")
    pl.add_argument("--resolutions", default="coarse,paper")
    pl.add_argument("--ranks", default="1,2")
    args = ap.parse_args()
    {"forward": forward, "plan": plan}[args.what](args)


if __name__ == "__main__":
    main()
