#!/usr/bin/env python3
"""A prediction against the patient's outcome: register, simulate, compare (docs/validation.md).

    python3 scripts/validate.py --mesh out/patient/scene.vtu --post post_face.ply \
        --transforms transforms.json --out out/validation --report out/validation/report.json
    mpirun -n 2 python3 scripts/validate.py --case class3-asym --resolution coarse \
        --post scan.stl --p mandible.advance_mm=5 --out out/v --report out/v/report.json

``--post``: the post-operative face surface scan (STL, OBJ or PLY, mm, as 3dMD cameras and
photogrammetry write them), placed within a couple of centimetres and ten degrees of the
face (register it roughly in 3D Slicer first otherwise). It is registered to the scene on the
skin that surgery does not move; the movements (``--params``/``--p`` or ``--transforms``, as
for ``simulate.py``) are simulated; the predicted skin is compared with the scan per vertex,
per region and per landmark (`inverse.validation`). Writes the report, ``distance.png``
(front and profile) and ``distance.xdmf`` (the skin with its signed distance, for ParaView),
each whole or not at all; a registration that fails is a one-line error and writes nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._common import (  # noqa: E402
    add_transforms_arg,
    check_movements,
    movements,
    parse,
    run_main,
    scene_from_args,
    scene_parser,
    warn_bounds,
)


def main(argv=None):
    ap = scene_parser(__doc__, params="the bone movements (treatment parameters)")
    add_transforms_arg(ap)
    ap.add_argument("--post", required=True, help="post-operative face scan (.stl .obj .ply)")
    ap.add_argument("--out", required=True, help="output folder (distance.png, distance.xdmf)")
    ap.add_argument("--report", required=True, help="JSON report path")
    args, comm = parse(ap, argv)
    import time

    import numpy as np

    from fem.io import write_json, write_on_root
    from inverse import validation
    from meshes.frame import HeadFrame
    from meshes.surface import apply, read_surface, write_surface

    t0 = time.perf_counter()
    timings = {}
    check_movements(args)
    scan_points, scan_tris = read_surface(args.post)   # every rank: the same small file
    scene = scene_from_args(args, comm, groups=not args.transforms)
    p = movements(args, scene)
    warnings = warn_bounds(scene, p, comm)
    skin = validation.Skin.of(scene)
    rest, tris = skin.rest, skin.tris
    timings["scene"] = time.perf_counter() - t0
    t = time.perf_counter()
    frame = scene.head_frame or HeadFrame.identity()
    landmarks_rest = scene.landmarks(rest=True)
    reg = validation.register_scan(scan_points, scan_tris, rest, tris, validation.stable_mask(
        rest, skin.bone, frame, landmarks_rest))
    scan = apply(reg.transform, scan_points)   # in the scene's frame
    timings["registration"] = time.perf_counter() - t
    t = time.perf_counter()
    stats = scene.solve(p)
    after = skin.at(scene)
    timings["simulation"] = time.perf_counter() - t
    t = time.perf_counter()
    part, d, covered = validation.compare(after, rest, tris, frame, landmarks_rest,
                                          scene.landmarks(), scan, scan_tris)
    timings["comparison"] = time.perf_counter() - t
    out = Path(args.out)
    report = {"case": scene.case or scene.domain.name, "mesh": args.mesh,
              "resolution": scene.resolution, "occlusion": scene.treatment.occlusion,
              "contact": args.contact, "material": args.material, "post": str(args.post),
              "skin_distance": str(out / "distance.xdmf"),
              "n_vertices": scene.domain.n_vertices, "n_ranks": comm.size,
              "registration": reg.report(), "param_names": scene.param_names,
              "params": p, **part, "newton_iterations": stats.newton_iterations,
              "warnings": warnings + stats.warnings, "timings_s": timings}
    title = f"{report['case']}: the prediction against the outcome"
    if comm.rank == 0:
        from scripts._render import render_distance

        def picture(path):
            render_distance(after, tris, d, covered, path, title, scene.head_frame)

        def xdmf(path):
            write_surface(path, after, tris, {"signed_distance_mm": np.where(covered, d, np.nan),
                                              "covered": covered.astype(float)})
    write_on_root(out / "distance.png", picture if comm.rank == 0 else None, comm)
    write_on_root(out / "distance.xdmf", xdmf if comm.rank == 0 else None, comm)
    timings["total"] = time.perf_counter() - t0
    write_json(args.report, report, comm)
    if comm.rank == 0:
        e = report["error_mm"]
        print(f"{report['case']}: registered on {reg.n_points} skin vertices (residual "
              f"{reg.residual_mm:.2f} mm, overlap {reg.overlap:.0%}); the prediction against "
              f"the outcome over {e['n_vertices']} vertices: mean {e['mean']:.2f} mm, median "
              f"{e['median']:.2f}, p90 {e['p90']:.2f}, within 2 mm {e['within_2mm']:.0%}")
        for name, r in report["regions"].items():
            print(f"  {name:10s} mean {r['mean']:.2f} mm, within 2 mm {r['within_2mm']:.0%}")
        for name, v in report["landmarks"].items():
            print(f"  {name:4s} {v:.2f} mm")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
