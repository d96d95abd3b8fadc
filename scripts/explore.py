#!/usr/bin/env python3
"""First-order exploration: skin sensitivities at an equilibrium, predictions, and their error.

    mpirun -n 2 python3 scripts/explore.py --case class3 --resolution coarse \
        --p mandible.advance_mm=-3 --dp mandible.advance_mm=-2 mandible.yaw_deg=1 \
        --scales 0.5,1,2,4 --compare --out out/explore --report out/explore/report.json

At p0 (``--params``/``--p``) it computes S_skin = dx_skin/dp (Np solves with the kept
factorisation) and saves ``skin_sensitivity.npz`` (rest and current skin vertices, triangles,
S (N, 3, Np), names, p0) and ``sensitivity.xdmf`` (dx/dp_i on the volume, for ParaView).
For each ``scale·dp`` it times the plain prediction ``x(p0) + S dp`` and the corrected one
(continuation in substeps, each relaxed by a few quasi-Newton steps on the kept
factorisation); with ``--compare`` it also solves the
true equilibrium and reports max/mean skin error (mm) and the displacement at Pg.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._common import (  # noqa: E402
    load_params,
    names_list,
    parse,
    run_main,
    scene_from_args,
    scene_parser,
    warn_bounds,
)


def main(argv=None):
    ap = scene_parser(__doc__, params="the equilibrium p0 to explore at")
    ap.add_argument("--dp", nargs="*", action="extend", default=[], metavar="NAME=VALUE",
                    help="a change of the treatment to predict")
    ap.add_argument("--scales", default="1", help="comma-separated multiples of dp")
    ap.add_argument("--iterations", default=None,
                    help="quasi-Newton steps per substep of the corrected prediction "
                         "(default inverse.explore.CORRECTION_ITERATIONS)")
    ap.add_argument("--substep-mm", default=None,
                    help="largest first-order vertex motion of a substep of the corrected "
                         "prediction, mm (default inverse.explore.CORRECTION_SUBSTEP_MM)")
    ap.add_argument("--compare", action="store_true", help="solve the true equilibria")
    ap.add_argument("--out", help="folder for skin_sensitivity.npz and sensitivity.xdmf")
    ap.add_argument("--report", help="JSON report path")
    args, comm = parse(ap, argv)
    import numpy as np

    from fem.io import write_json
    from inverse.explore import CORRECTION_ITERATIONS, CORRECTION_SUBSTEP_MM, SkinPredictor

    t0 = time.perf_counter()
    scene = scene_from_args(args, comm)
    p0 = scene.param_vector(load_params(args.params, args.p, scene))
    dp = scene.param_vector(load_params(None, args.dp, scene))
    scales = [float(s) for s in names_list(args.scales)]   # checked by parse()
    warnings = warn_bounds(scene, p0, comm)
    for s in scales:
        warnings += warn_bounds(scene, p0 + s * dp, comm)
    t = time.perf_counter()
    scene.solve(p0)
    t_forward = time.perf_counter() - t
    t = time.perf_counter()
    pred = SkinPredictor(scene)
    t_sens = time.perf_counter() - t
    if args.out:
        _write(scene, pred, Path(args.out), comm)
    pg0 = dict(zip(pred.landmark_names, pred.lm0))["Pg"]
    rows = []
    for s in scales:
        d = s * dp
        n_calls = 200
        t = time.perf_counter()
        for _ in range(n_calls):
            plain = pred.predict(d)
        t_plain = (time.perf_counter() - t) / n_calls
        t = time.perf_counter()
        corr, corr_lm = pred.corrected(
            d, CORRECTION_ITERATIONS if args.iterations is None else args.iterations,
            CORRECTION_SUBSTEP_MM if args.substep_mm is None else args.substep_mm)
        t_corr = time.perf_counter() - t
        row = {"scale": s, "dp": d, "predict_ms": 1e3 * t_plain, "corrected_s": t_corr,
               "Pg_displacement_predicted": pred.predict_landmarks(d)["Pg"] - pg0,
               "Pg_displacement_corrected": corr_lm["Pg"] - pg0}
        if args.compare:
            t = time.perf_counter()
            scene.solve(p0 + d)
            row["true_solve_s"] = time.perf_counter() - t
            true = pred.op.apply(scene.eq.u_eq.array)
            pg = scene.landmarks(["Pg"])["Pg"] - pg0
            for name, x in (("plain", plain), ("corrected", corr)):
                e = np.linalg.norm(x - true, axis=1)
                row[f"{name}_error_max_mm"], row[f"{name}_error_mean_mm"] = e.max(), e.mean()
            row["skin_displacement_max_mm"] = np.linalg.norm(true - pred.x0, axis=1).max()
            row["Pg_displacement_true"] = pg
            scene.solve(p0)
        rows.append(row)
        if comm.rank == 0:
            print("  ".join(f"{k} {np.round(v, 3).tolist()}" for k, v in row.items()
                            if k != "dp"))
    report = {"case": scene.case or scene.domain.name, "resolution": scene.resolution,
              "degree": scene.domain.degree, "n_vertices": scene.domain.n_vertices,
              "n_ranks": comm.size,
              "n_skin_vertices": len(pred.vertices), "param_names": scene.param_names,
              "p0": p0, "predictions": rows, "warnings": warnings,
              "timings_s": {"forward": t_forward, "sensitivity": t_sens,
                            "total": time.perf_counter() - t0}}
    if args.report:
        write_json(args.report, report, comm)
    return 0


def _write(scene, pred, out: Path, comm):
    """skin_sensitivity.npz and sensitivity.xdmf (u and dx/dp_i on the volume)."""
    import numpy as np

    from fem.io import write_npz

    dom = scene.domain
    write_npz(out / "skin_sensitivity.npz", {
        "vertices": pred.vertices,
        "points_rest": pred.x_rest,
        "points": pred.x0, "triangles": dom.boundary_triangles(pred.vertices), "S": pred.S,
        "param_names": np.array(scene.param_names), "p0": pred.p0}, comm)
    fields = {"displacement": scene.eq.u.x.array,   # the owned values are what is written
              **{f"dx_d[{name}]": s.array
                 for name, s in zip(scene.param_names, scene.eq.sensitivity())}}
    scene.write_volume(out / "sensitivity.xdmf", fields)


if __name__ == "__main__":
    sys.exit(run_main(main))
