#!/usr/bin/env python3
"""Benchmarks (not timed tests). Results are printed and written into BENCHMARKS.md.

    python3 scripts/bench.py forward [--resolutions tiny,coarse,medium,paper]
                                     [--solvers direct,gamg] [--ranks 1,2]

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


def _simulate(res: str, solver: str, n: int, extra=()) -> dict:
    with tempfile.TemporaryDirectory() as d:
        rep = Path(d) / "r.json"
        cmd = [sys.executable, str(ROOT / "scripts" / "simulate.py"), "--case", "class3",
               "--resolution", res, "--solver", solver, "--p", "mandible.advance_mm=5",
               "--report", str(rep), *extra]
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


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    f = sub.add_parser("forward", help="forward equilibrium across resolutions and solvers")
    f.add_argument("--resolutions", default="tiny,coarse,medium,paper")
    f.add_argument("--solvers", default="direct,gamg")
    f.add_argument("--ranks", default="1,2")
    args = ap.parse_args()
    {"forward": forward}[args.what](args)


if __name__ == "__main__":
    main()
