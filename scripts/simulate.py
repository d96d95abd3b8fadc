#!/usr/bin/env python3
"""Forward simulation: the soft-tissue equilibrium for given treatment parameters.

    mpirun -n 2 python3 scripts/simulate.py --case class3 --resolution coarse \
        --p mandible.advance_mm=5 --out out/sim --report out/sim/report.json
    python3 scripts/simulate.py --case class3 --transforms plan.json   # VSP transforms

``--transforms`` takes a JSON ``{segment: 4x4 or "file.tfm"}`` (mm, scene frame, the
motion of each segment) or one ITK file ``<segment>.tfm`` (3D Slicer: LPS, resampling
convention); see `meshes.transforms`. Segments not named stay put. The scene's parameters
then default to each segment's own six motions.

PETSc options (e.g. ``-orthodiff_fwd_ksp_type cg``) pass through to the solver.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._common import (  # noqa: E402
    add_band_args,
    add_transforms_arg,
    check_movements,
    movements,
    parse,
    peak_rss_mb,
    run_main,
    scene_from_args,
    scene_parser,
    warn_bounds,
    write_transforms,
)


def main(argv=None):
    ap = scene_parser(__doc__, params="treatment parameters")
    ap.add_argument("--out", help="output folder for XDMF files")
    ap.add_argument("--report", help="JSON report path")
    add_transforms_arg(ap)
    add_band_args(ap)
    ap.add_argument("--list-params", action="store_true",
                    help="list parameter names, units and bounds, then exit")
    args, comm = parse(ap, argv)
    import time

    from fem.io import write_json
    from inverse.uncertainty import band_report, scene_prior

    t0 = time.perf_counter()
    check_movements(args)
    scene = scene_from_args(args, comm, groups=not args.transforms)
    if args.list_params:
        if comm.rank == 0:
            print(f"{'name':28s} {'unit':5s} {'kind':9s} bounds")
            for p in scene.treatment.params:
                print(f"{p.name:28s} {p.unit:5s} {p.kind:9s} [{p.bounds[0]:g}, {p.bounds[1]:g}]")
        return 0
    p = movements(args, scene)
    prior = None if args.no_bands else scene_prior(scene, args.prior)
    warnings = warn_bounds(scene, p, comm)
    stats = scene.solve(p)
    rest = scene.landmarks(rest=True)
    moved = scene.landmarks()
    err = scene.active_goal_error()
    timings = dict(scene.timings, assemble=stats.assemble, linear_solve=stats.linear_solve,
                   solve=stats.total)
    t = time.perf_counter()
    bands, fields = band_report(scene, prior, list(moved), vertices=bool(args.out))
    timings["bands"] = time.perf_counter() - t
    if args.out:
        scene.write(args.out, fields)
        write_transforms(scene.transforms(), args.out, comm)
    timings["total"] = time.perf_counter() - t0
    report = {
        "case": scene.case or scene.domain.name, "resolution": scene.resolution,
        "degree": scene.domain.degree,
        "n_vertices": scene.domain.n_vertices, "n_cells": scene.domain.n_cells,
        "n_dofs": scene.domain.n_dofs,
        "n_ranks": comm.size, "param_names": scene.param_names, "params": p,
        "landmarks": moved, "landmarks_rest": rest, "active_goal_error_max_mm": err,
        "iterations": stats.iterations,
        "linear_iterations": stats.linear_iterations, "converged": True,
        "diagonal_shifts": stats.shifts, "factorisations": stats.factorisations,
        "lagged_steps": stats.lagged, "continuation_steps": stats.continuation_steps,
        "min_det_F": stats.min_det_F, "min_det_F_at_mm": stats.min_det_F_at,
        "warnings": warnings + stats.warnings,
        **scene.motion_report(), "bands": bands,
        "solver": scene.eq.solver_name, "timings_s": timings,
        "peak_rss_mb": peak_rss_mb(comm),
    }
    if args.report:
        write_json(args.report, report, comm)
    if comm.rank == 0:
        print(f"{report['case']}: {report['n_vertices']} vertices, {comm.size} rank(s), "
              f"{stats.iterations} iterations, max active goal error "
              f"{err:.4f} mm, {timings['total']:.1f} s")
        for name in moved:
            d = moved[name] - rest[name]
            print(f"  {name:4s} moved {d.round(2)} mm")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
