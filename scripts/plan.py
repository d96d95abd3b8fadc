#!/usr/bin/env python3
"""Plan a treatment: the bone movements that bring skin landmarks to their targets.

    mpirun -n 2 python3 scripts/plan.py --case class3-asym --resolution coarse \
        [--targets T.json] [--landmarks Pg,Li,Ls] [--params-used ...] \
        --out out/plan --report out/plan/report.json

Targets default to the case's clinical goal (`inverse.targets`). Parameters default to
`inverse.treatment.PLAN_PARAMS` (mandible: all six motions; maxilla en bloc: advance,
vertical, cant and yaw) with ``--occlusion free``, and to the six motions of the
maxillomandibular complex `inverse.treatment.JAWS_PARAMS` with ``--occlusion final`` (the
mandible held to the maxilla in the final occlusion). The report has the keys listed in
README.md, with ``transforms`` (segment -> 4x4) and ``occlusion``; ``--out`` also gets one
ITK ``<segment>.tfm`` per segment.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._common import (  # noqa: E402
    add_band_args,
    names_list,
    parse,
    read_json,
    run_main,
    scene_from_args,
    scene_parser,
    write_transforms,
)


def _load_checkpoint(path, signature: dict, comm) -> dict:
    """The plan state saved by an earlier run, checked against this run's ``signature``."""
    import json

    from meshes.errors import InputError

    if not path:
        raise InputError("--resume needs --checkpoint FILE (or --report)")
    state = read_json(path, "checkpoint", comm)
    if not isinstance(state, dict) or not state.get("history"):
        raise InputError(f"checkpoint {path} holds no plan state")
    old = state.get("signature", {})
    for key, value in json.loads(json.dumps(signature)).items():
        if old.get(key) != value:
            raise InputError(f"checkpoint {path} belongs to another plan: its {key} is "
                             f"{old.get(key)!r}, this run's is {value!r}")
    return state


def main(argv=None):
    from inverse.treatment import FTOL, TIKHONOV

    ap = scene_parser(__doc__, plan=True)
    ap.add_argument("--targets", help="JSON {landmark: [x, y, z]} mm, the scene's frame; an "
                    "entry {\"at\": [x, y, z], \"along\": [\"anterior\", ...]} holds the "
                    "landmark along those head axes only (default: the case's clinical goal)")
    ap.add_argument("--goal", help="a built-in clinical goal instead of --targets, built "
                    "on the scene's own landmarks in the head frame (inverse/targets.py): "
                    "class1, class2, class3, class3-asym, midface-advance, e-line (default: the "
                    "case's)")
    ap.add_argument("--landmarks", help="comma-separated subset of the targets to use")
    ap.add_argument("--tikhonov", default=TIKHONOV,
                    help="α of ½α|p|², mm² per unit²: prefers small movements where the "
                    "landmarks do not decide")
    ap.add_argument("--ftol", default=FTOL,
                    help="stop when T decreases by less than this fraction in an iteration")
    ap.add_argument("--max-iterations", default=20)
    ap.add_argument("--checkpoint", help="JSON file rewritten (atomically) after every "
                    "Gauss-Newton iteration with p and the history (default: next to --report)")
    ap.add_argument("--resume", action="store_true",
                    help="continue the plan saved in --checkpoint (same case and goal)")
    ap.add_argument("--out", help="output folder for XDMF of the planned result")
    ap.add_argument("--picture", help="PNG of the face before and after the plan, with the "
                    "landmarks and their targets")
    ap.add_argument("--report", help="JSON report path")
    add_band_args(ap)
    ap.add_argument("--robust", action="store_true",
                    help="then minimise the expected objective under the tissue's prior "
                    "(T plus the targets' band, docs/uncertainty.md) from the plan found; the "
                    "report's 'robust' compares the two, and --out and --picture show it")
    args, comm = parse(ap, argv)
    import time

    import numpy as np

    from fem.io import write_json
    from inverse.uncertainty import band_report, scene_prior

    t0 = time.perf_counter()
    scene = scene_from_args(args, comm, plan=True)
    if args.robust and args.no_bands:
        from meshes.errors import InputError

        raise InputError("--robust needs the tissue's prior: drop --no-bands")
    prior = None if args.no_bands else scene_prior(scene, args.prior)
    targets = args.targets or scene.default_targets(args.goal)
    names = names_list(args.landmarks) if args.landmarks is not None else None
    obj = scene.objective(targets, names, tikhonov=args.tikhonov)
    names = obj.names
    targets = obj.entries()
    before = scene.landmarks(names)
    from inverse.planner import gauss_newton, plan_report

    ckpt = args.checkpoint or (args.report + ".checkpoint.json" if args.report else None)
    state = {"signature": {"case": scene.case or scene.domain.name,
                           "resolution": scene.resolution, "degree": scene.domain.degree,
                           "n_vertices": scene.domain.n_vertices,
                           "param_names": scene.param_names, "targets": targets,
                           "tikhonov": args.tikhonov, "occlusion": args.occlusion,
                           "treatment": args.treatment},
             "params_initial": np.zeros(len(scene.param_names)), "before": before,
             "params": None, "history": []}
    if args.resume:
        state = _load_checkpoint(ckpt, state["signature"], comm)
    offset = max(len(state["history"]) - 1, 0)    # iterations already done

    def save(p, h):   # every accepted iteration (and the start): p and the history so far
        if state["history"] and h["iteration"] == 0:
            return    # a resumed run starts where the checkpoint ends
        state["history"].append(dict(h, iteration=h["iteration"] + offset))
        state["params"] = p
        write_json(ckpt, state, comm)

    mu = state["history"][-1]["mu"] if state["history"] else 1e-9
    result = gauss_newton(scene, obj, p0=state["params"], mu=mu, ftol=args.ftol,
                          max_iterations=args.max_iterations - offset,
                          callback=save if ckpt else None)
    if ckpt:          # one plan across runs: the checkpoint's iterations, then this run's
        result.history = state["history"]
        result.gn_iterations += offset
        result.params_initial = np.asarray(state["params_initial"], dtype=float)
        before = {n: np.asarray(v, dtype=float) for n, v in state["before"].items()}
    report = plan_report(scene, result, obj, before)
    report.update(mesh=args.mesh, goal=None if args.targets else args.goal or scene.case)
    report["resumed_from_iteration"] = offset if args.resume else None
    report["timings_s"] = dict(report["timings_s"], mesh=scene.timings["mesh"],
                               compile=scene.timings["compile"])
    if args.robust:
        report["robust"] = _robust(scene, obj, prior, result.params)
    t = time.perf_counter()   # the bands at the plan found (the robust one with --robust)
    report["bands"], fields = band_report(scene, prior, list(scene.domain.landmarks),
                                       vertices=bool(args.out or args.picture))
    report["timings_s"]["bands"] = time.perf_counter() - t
    if args.out:
        scene.write(args.out, fields)
        write_transforms(scene.transforms(), args.out, comm)
    if args.picture:
        _picture(scene, dict(zip(names, obj.targets)), args.picture, comm,
                 fields.get("band_r95_mm"))
    report["timings_s"]["total"] = time.perf_counter() - t0
    if args.report:
        write_json(args.report, report, comm)
    if comm.rank == 0:
        print_plan(report)
    return 0


def _robust(scene, obj, prior, nominal) -> dict:
    """The report's ``robust``: the plan of least expected T from the ``nominal`` one
    (`inverse.robust`), how far it moved, and the expected T of both. Leaves the scene at
    the robust plan."""
    import time

    from inverse.robust import robust_plan

    t = time.perf_counter()
    r = robust_plan(scene, obj, prior, nominal)
    return {"params": r.params, "params_nominal": r.nominal,
            "moved": dict(zip(scene.param_names, (r.params - r.nominal).tolist())),
            "expected_T_mm2": r.expected, "expected_T_nominal_mm2": r.expected_nominal,
            "distances_mm": dict(zip(obj.names, obj.distances().tolist())),
            "iterations": r.iterations, "forward_solves": r.forward_solves,
            "time_s": time.perf_counter() - t}


def _picture(scene, targets: dict, path, comm, band=None) -> None:
    """The skin at rest and at the planned equilibrium (`scripts._render`), with ``band``
    (n_vertices,) mm on rank 0 where given, written atomically by rank 0. Collective."""
    import numpy as np

    from fem.io import write_on_root
    from scripts._render import render_before_after

    dom = scene.domain
    verts = dom.boundary_vertices()
    op = dom.vertex_operator(verts)
    rest, after = op.apply(np.zeros_like(scene.eq.u_eq.array)), op.apply(scene.eq.u_eq.array)
    tris = dom.boundary_triangles(verts)
    landmarks = scene.landmarks(list(targets))
    title = f"{scene.case or dom.name}: the face before and after the plan"
    band = None if band is None else band[verts]
    write_on_root(path, lambda p: render_before_after(rest, after, tris, landmarks, targets,
                                                      p, title, scene.head_frame, band), comm)


def print_plan(report) -> None:
    """The landmark table, the parameters found and the timings, on stdout."""
    print(f"\n{report['case']}: {report['n_vertices']} vertices, {report['n_ranks']} rank(s); "
          f"{report['gn_iterations']} Gauss-Newton iterations, {report['forward_solves']} "
          f"forward solves, converged: {report['converged']} ({report['stop_reason']})")
    bands = (report.get("bands") or {}).get("landmarks", {})
    print(f"\n{'landmark':9s} {'before mm':>10s} {'after mm':>10s}   after - target, mm: "
          f"{'left':>6s} {'anterior':>8s} {'superior':>8s}   95 % band, mm")
    for n, v in report["landmarks"].items():
        off = v["offset_after_mm"]
        band = f"{bands[n]['r95_mm']:9.2f}" if n in bands else ""
        print(f"{n:9s} {v['distance_before_mm']:10.2f} {v['distance_after_mm']:10.2f}"
              f"{'':22s}{off['left']:6.2f} {off['anterior']:8.2f} {off['superior']:8.2f}"
              f"   {band}")
    print(f"{'mean':9s} {report['mean_distance_before_mm']:10.2f} "
          f"{report['mean_distance_after_mm']:10.2f}\n\nparameters found:")
    for n, v in zip(report["param_names"], report["params_optimal"]):
        print(f"  {n:26s} {v:8.2f}")
    if report.get("robust"):
        r = report["robust"]
        e, e0 = r["expected_T_mm2"], r["expected_T_nominal_mm2"]
        print(f"\nrobust plan: expected T {e0['total']:.4f} -> {e['total']:.4f} mm² (its band "
              f"{e0['band']:.4f} -> {e['band']:.4f}); moved from the plan found by:")
        for n, v in r["moved"].items():
            print(f"  {n:26s} {v:+8.3f}")
    print("\ntimings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in report["timings_s"].items()))


if __name__ == "__main__":
    sys.exit(run_main(main))
