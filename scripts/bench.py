#!/usr/bin/env python3
"""Benchmarks (not timed tests). Results are printed and written into BENCHMARKS.md.

    python3 scripts/bench.py forward [--resolutions tiny,coarse,medium,paper,fine]
                                     [--solvers direct,cholmod,amg] [--ranks 1,2]
                                     [--all-up-to paper]
    python3 scripts/bench.py plan [--resolutions coarse,paper] [--ranks 1,2]
    python3 scripts/bench.py stress [--cases coarse:20,paper:10] [--timeout 300]
    python3 scripts/bench.py accuracy [--parts mesh,ct,tolerance,prediction,gradient]
    python3 scripts/bench.py plausibility [--resolutions coarse,paper] [--cases class1]
    python3 scripts/bench.py ct [--cts headsq,cranium] [--resolutions coarse,paper] [--ranks 2]
    python3 scripts/bench.py validation [--resolution paper] [--ranks 1,2]
    python3 scripts/bench.py explorer [--resolutions coarse,paper] [--ranks 1,2]
    python3 scripts/bench.py peers [--resolutions tiny,coarse,medium,paper] [--ranks 1,2]
    python3 scripts/bench.py bands [--resolution paper] [--resolution-mc coarse] [--samples 64]
    python3 scripts/bench.py targets [--resolution paper] [--ranks 1,2] [--solvers direct,amg]
    python3 scripts/bench.py all       # every one above with its defaults: BENCHMARKS.md whole

One module a benchmark: ``bench_forward`` (forward, stress), ``bench_plan``,
``bench_accuracy``, ``bench_plausibility``, ``bench_ct``, ``bench_validation``,
``bench_explorer``, ``bench_peers``, ``bench_bands``, ``bench_targets``; the shared
helpers in ``_bench``. This file checks the options and dispatches.

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
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._bench import ROOT, SECTIONS  # noqa: E402

#: Most ranks a benchmark may ask for (the machine has 2 cores; more only oversubscribe),
#: and the largest move (mm) it may ask for: the stress table's largest is 20 mm.
MAX_RANKS, MAX_MOVE_MM = 64, 100.0

#: ``bench.py all``: every subcommand with its defaults, in BENCHMARKS.md's order.
ALL = tuple(dict.fromkeys(SECTIONS.values()))


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
             "all_up_to": RESOLUTIONS,
             "resolution_grad": RESOLUTIONS, "resolution": RESOLUTIONS,
             "resolution_mc": RESOLUTIONS, "solvers": PRESETS,
             "methods": METHODS,
             "methods_tol": METHODS, "occlusions": ("free", "final"), "cts": CTS,
             "resolutions_ct": RESOLUTIONS,
             "parts": ("mesh", "ct", "tolerance", "prediction", "gradient", "order")}
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
    elif args.what == "plausibility":
        if args.cases is not None:
            among("cases", CASES)
        among("contacts", ("glued", "sliding"))
        among("materials", ("homogeneous", "tissues"))
    elif args.what == "explorer":
        number("events", args.events, 1, 10000, integer=True)
        args.events = int(args.events)
    elif args.what == "bands":
        number("samples", args.samples, 2, 100000, integer=True)
        args.samples = int(args.samples)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors, exit 2 (the scripts' convention)."""

    def error(self, message):
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(2)


def main():
    ap = _Parser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True, parser_class=_Parser)
    f = sub.add_parser("forward", help="forward equilibrium across resolutions and solvers")
    f.add_argument("--resolutions", default="tiny,coarse,medium,paper,fine")
    f.add_argument("--solvers", default="direct,cholmod,amg",
                   help="presets (gamg: ~100x slower at paper, see docs/decisions.md)")
    f.add_argument("--ranks", default="1,2")
    f.add_argument("--methods", default="qn,newton")
    f.add_argument("--all-up-to", default="paper",
                   help="resolutions beyond it run quasi-Newton on direct and amg only")
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
    a.add_argument("--parts", default="mesh,ct,tolerance,prediction,gradient,order")
    a.add_argument("--resolutions", default="tiny,coarse,medium,paper,fine",
                   help="mesh part; the last is the reference")
    a.add_argument("--ranks-mesh", type=int, default=2)
    a.add_argument("--cts", default="cranium,headsq", help="ct part (an absent CT: a row "
                   "that says so)")
    a.add_argument("--resolutions-ct", default="coarse,medium,paper,fine",
                   help="ct part; the last is the reference")
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
    pp.add_argument("--contacts", default="glued,sliding")
    pp.add_argument("--materials", default="homogeneous,tissues")
    c = sub.add_parser("ct", help="the CT pipeline on the example CTs, to a plan")
    c.add_argument("--cts", default="headsq,cranium")
    c.add_argument("--resolutions", default="coarse,paper")
    c.add_argument("--ranks", type=int, default=2,
                   help="MPI ranks of simulate.py and plan.py (issue 30's goals: 2)")
    v = sub.add_parser("validation", help="the validation protocol on Cranium, a synthetic "
                       "post-op scan")
    v.add_argument("--resolution", default="paper")
    v.add_argument("--ranks", default="1,2")
    e = sub.add_parser("explorer", help="the browser explorer in headless Chromium")
    e.add_argument("--resolutions", default="coarse,paper")
    e.add_argument("--ranks", default="1,2")
    e.add_argument("--events", default="60", help="slider events timed per row")
    e.add_argument("--screenshot", default="docs/explorer.png",
                   help="picture of the last row's page, relative to the project ('' none)")
    pe = sub.add_parser("peers", help="the tutorial recipe, finite differences and LM + FD "
                        "beside orthodiff, in one run")
    pe.add_argument("--resolutions", default="tiny,coarse,medium,paper")
    pe.add_argument("--ranks", default="1,2")
    t = sub.add_parser("targets", help="paper forward and plan on Debian's dolfinx and PyPI's")
    t.add_argument("--resolution", default="paper")
    t.add_argument("--ranks", default="1,2")
    t.add_argument("--solvers", default="direct,amg", help="presets both targets have")
    b = sub.add_parser("bands", help="the prediction bands' cost, and against sampling")
    b.add_argument("--resolution", default="paper")
    b.add_argument("--resolution-mc", default="coarse")
    b.add_argument("--samples", default="64", help="Monte Carlo samples per scene")
    sub.add_parser("all", help="every benchmark with its defaults: BENCHMARKS.md whole")
    argv = sys.argv[1:]
    runs = [[w] for w in ALL] if argv[:1] == ["all"] and len(argv) == 1 else [argv]
    todo = []
    for argv in runs:
        args = ap.parse_args(argv)
        args.argv = argv
        try:
            check_args(args)
        except ValueError as e:   # one line, exit 2, before any work (issue 19)
            ap.error(str(e))
        todo.append(args)
    from scripts import (
        bench_accuracy,
        bench_bands,
        bench_ct,
        bench_explorer,
        bench_forward,
        bench_peers,
        bench_plan,
        bench_plausibility,
        bench_targets,
        bench_validation,
    )

    run = {"forward": bench_forward.forward, "plan": bench_plan.plan,
           "stress": bench_forward.stress, "accuracy": bench_accuracy.accuracy,
           "plausibility": bench_plausibility.plausibility, "ct": bench_ct.ct,
           "validation": bench_validation.validation,
           "explorer": bench_explorer.explorer, "peers": bench_peers.peers,
           "bands": bench_bands.bands, "targets": bench_targets.targets}
    for args in todo:
        print(f"== bench.py {' '.join(args.argv)}", flush=True)
        run[args.what](args)


if __name__ == "__main__":
    main()
