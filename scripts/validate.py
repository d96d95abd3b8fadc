#!/usr/bin/env python3
"""A prediction against the patient's outcome: register, simulate, compare (docs/validation.md).

    python3 scripts/validate.py --mesh out/patient/scene.vtu --post post_face.ply \
        --transforms transforms.json --out out/validation --report out/validation/report.json
    python3 scripts/validate.py --mesh out/patient/scene.vtu --post post_ct.nii.gz \
        --pre-ct pre_ct.nii.gz --measure-bone --out out/v --report out/v/report.json
    mpirun -n 2 python3 scripts/validate.py --case class3-asym --resolution coarse \
        --post scan.stl --p mandible.advance_mm=5 --out out/v --report out/v/report.json

``--post``: the outcome, either of two:

* a face surface scan (STL, OBJ or PLY, mm, as 3dMD cameras and photogrammetry write them),
  placed within a couple of centimetres and ten degrees of the face (register it roughly in
  3D Slicer first otherwise), registered on the skin that surgery does not move
  (`inverse.validation`);
* a post-operative CT (any format ``ct_scene.py`` reads) of a scene that ``ct_scene.py``
  made from ``--pre-ct``: registered on the bone that surgery does not move, its skin
  extracted as the scene's was (`inverse.postop`). ``--measure-bone`` then measures each
  segment's movement on it, instead of ``--params``/``--p`` or ``--transforms``, and writes
  it (``transforms.json`` for ``--transforms``, ``<segment>.tfm`` for 3D Slicer).

The movements are simulated; the predicted skin is compared with the outcome's per vertex,
per region and per landmark. Writes the report, ``distance.png`` (front and profile) and
``distance.xdmf`` (the skin with its signed distance, for ParaView) and ``outcome.ply`` (the
outcome's skin registered, in the scene's frame: a case of ``calibrate.py``; with a CT also
``outcome_rest.ply``, the pre-operative CT's skin extracted alike), each whole or not at
all; a registration that fails is a one-line error and writes nothing.
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
    write_transforms,
)

#: The post-operative CT's skin is extracted within the scene's skin box widened by this
#: (mm: more than the skin moves), and compared within the box of the rest and predicted
#: skin widened by `CROP_MM` (the same face the scene holds, for the landmarks'
#: constructions).
SKIN_BOX_MM, CROP_MM = 20.0, 2.0


def _check(args) -> bool:
    """Whether ``--post`` is a CT; `InputError` for options that do not go with it."""
    from meshes.errors import InputError
    from meshes.surface import SCAN_SUFFIXES

    check_movements(args)
    is_ct = not str(args.post).lower().endswith(SCAN_SUFFIXES)
    if is_ct and not args.pre_ct:
        raise InputError(f"{args.post} is no face scan ({', '.join(SCAN_SUFFIXES)}): a "
                         "post-operative CT needs --pre-ct, the CT the scene was made from")
    if not is_ct and (args.pre_ct or args.measure_bone):
        raise InputError("--pre-ct and --measure-bone go with a post-operative CT; a face "
                         "scan shows no bone")
    if args.measure_bone and (args.params or args.p or args.transforms):
        raise InputError("give --measure-bone or the movements (--params/--p, --transforms), "
                         "not both")
    return is_ct


def _ct_outcome(args, scene, skin, frame, landmarks, comm) -> dict:
    """The post-operative CT's part (rank 0's work, on every rank): ``registration``,
    ``segments`` ({name: (4×4, residual, condition)} with ``--measure-bone``), the skin
    surface in the scene's frame (``scan``: points, triangles) and ``timings``. Collective."""
    import time

    import numpy as np

    from inverse import postop
    from meshes.errors import MeshError
    from meshes.surface import apply

    thresholds = scene.domain.thresholds
    if thresholds is None:
        raise MeshError("the scene holds no CT thresholds: a post-operative CT validates a "
                        "scene that ct_scene.py made from a CT; validate others against a "
                        "face scan")
    bones = postop.bone_surfaces(scene)
    out = None
    if comm.rank == 0:
        from meshes.intensity import read_ct

        try:
            timings = {}
            t = time.perf_counter()
            (pre, _), (post, _) = read_ct(args.pre_ct), read_ct(args.post)   # HU
            timings["read"] = time.perf_counter() - t
            t = time.perf_counter()
            reg = postop.register_ct(pre, post, bones, frame, landmarks)
            timings["registration"] = time.perf_counter() - t
            segments = {}
            if args.measure_bone:
                t = time.perf_counter()
                segments = postop.measure_bone(pre, post, bones, reg)
                timings["measure_bone"] = time.perf_counter() - t
            t = time.perf_counter()
            to_post = np.linalg.inv(reg.transform)
            box = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
            lo, hi = skin.rest.min(axis=0) - SKIN_BOX_MM, skin.rest.max(axis=0) + SKIN_BOX_MM
            corners = apply(to_post, lo + box * (hi - lo))
            points, tris = postop.skin_surface(post, thresholds["skin_hu"],
                                               corners.min(axis=0), corners.max(axis=0))
            # the pre-operative CT's skin, extracted alike (the scene's frame is its own):
            # calibrate.py takes the voxel's bias out with it (docs/uncertainty.md)
            rest = postop.skin_surface(pre, thresholds["skin_hu"], lo, hi)
            timings["skin_surface"] = time.perf_counter() - t
            out = {"registration": reg, "segments": segments, "timings": timings,
                   "scan": (apply(reg.transform, points), tris), "scan_rest": rest}
        except MeshError as e:
            out = str(e)
    out = comm.bcast(out, root=0)
    if isinstance(out, str):
        raise MeshError(out)
    return out


def main(argv=None):
    ap = scene_parser(__doc__, params="the bone movements (treatment parameters)")
    add_transforms_arg(ap)
    ap.add_argument("--post", required=True,
                    help="post-operative face scan (.stl .obj .ply) or CT (as ct_scene.py's)")
    ap.add_argument("--pre-ct", help="the CT the scene was made from (with a post-operative CT)")
    ap.add_argument("--measure-bone", action="store_true",
                    help="measure each segment's movement on the post-operative CT")
    ap.add_argument("--out", required=True,
                    help="output folder (distance.png, distance.xdmf, measured transforms)")
    ap.add_argument("--report", required=True, help="JSON report path")
    args, comm = parse(ap, argv)
    import time

    import numpy as np

    from fem.io import write_json, write_on_root
    from inverse import validation
    from meshes.landmarks import staircase_mm
    from meshes.surface import apply, read_surface, write_surface

    t0 = time.perf_counter()
    timings = {}
    is_ct = _check(args)
    if not is_ct:
        scan_points, scan_tris = read_surface(args.post)   # every rank: the same small file
    scene = scene_from_args(args, comm, groups=not (args.transforms or args.measure_bone))
    skin = validation.Skin.of(scene)
    rest, tris = skin.rest, skin.tris
    timings["scene"] = time.perf_counter() - t0
    t = time.perf_counter()
    frame = scene.head_frame
    landmarks_rest = scene.landmarks(rest=True)
    segments = {}
    if is_ct:
        ct = _ct_outcome(args, scene, skin, frame, landmarks_rest, comm)
        reg, segments, scan = ct["registration"], ct["segments"], ct["scan"]
        scan_rest = ct["scan_rest"]
        timings.update(ct["timings"])
    else:
        reg = validation.register_scan(scan_points, scan_tris, rest, tris, validation.stable_mask(
            rest, skin.bone, frame, landmarks_rest))
        scan = (apply(reg.transform, scan_points), scan_tris)   # in the scene's frame
        timings["registration"] = time.perf_counter() - t
    if args.measure_bone:
        p = scene.params_from_transforms({k: T for k, (T, *_) in segments.items()})
    else:
        p = movements(args, scene)
    warnings = warn_bounds(scene, p, comm)
    t = time.perf_counter()
    stats = scene.solve(p)
    after = skin.at(scene)
    timings["simulation"] = time.perf_counter() - t
    t = time.perf_counter()
    if is_ct:   # the face the scene holds
        both = np.vstack([rest, after])
        scan = _crop(*scan, both.min(axis=0) - CROP_MM, both.max(axis=0) + CROP_MM)
    part, d, covered = validation.compare(after, rest, tris, frame, landmarks_rest, *scan,
                                          staircase_mm(scene.domain.voxel_mm, frame))
    timings["comparison"] = time.perf_counter() - t
    out = Path(args.out)
    report = {"case": scene.case or scene.domain.name, "mesh": args.mesh,
              "resolution": scene.resolution, "occlusion": scene.treatment.occlusion,
              "contact": args.contact, "material": args.material, "post": str(args.post),
              "post_kind": "ct" if is_ct else "surface scan", "pre_ct": args.pre_ct,
              "skin_distance": str(out / "distance.xdmf"), "outcome": str(out / "outcome.ply"),
              "outcome_rest": str(out / "outcome_rest.ply") if is_ct else None,
              "transforms": scene.transforms(),
              "n_vertices": scene.domain.n_vertices, "n_ranks": comm.size,
              "registration": reg.report(),
              "segments": {k: {"transform": T.tolist(), "residual_mm": r, "condition": c}
                           for k, (T, r, c) in segments.items()},
              "param_names": scene.param_names, "params": p, **part,
              "iterations": stats.iterations,
              "warnings": warnings + stats.warnings, "timings_s": timings}
    title = f"{report['case']}: the prediction against the outcome"
    if comm.rank == 0:
        from scripts._render import render_distance

        def picture(path):
            render_distance(after, tris, d, covered, path, title, scene.head_frame)

        def xdmf(path):
            write_surface(path, after, tris, {"signed_distance_mm": np.where(covered, d, np.nan),
                                              "covered": covered.astype(float)})
    if segments:
        _write_measured({k: T for k, (T, *_) in segments.items()}, out, comm)
    write_on_root(out / "distance.png", picture if comm.rank == 0 else None, comm)
    write_on_root(out / "distance.xdmf", xdmf if comm.rank == 0 else None, comm)
    write_on_root(out / "outcome.ply", lambda path: write_surface(path, *scan), comm)
    if is_ct:
        write_on_root(out / "outcome_rest.ply", lambda path: write_surface(path, *scan_rest),
                      comm)
    timings["total"] = time.perf_counter() - t0
    write_json(args.report, report, comm)
    if comm.rank == 0:
        e = report["error_mm"]
        on = f"{reg.n_points} skin vertices" if not is_ct else f"{reg.n_points} bone voxels"
        print(f"{report['case']}: registered on {on} (residual {reg.residual_mm:.2f} mm, "
              f"overlap {reg.overlap:.0%}); the prediction against the outcome over "
              f"{e['n_vertices']} vertices: mean {e['mean']:.2f} mm, median {e['median']:.2f}, "
              f"p90 {e['p90']:.2f}, within 2 mm {e['within_2mm']:.0%}")
        for name, (_, r, c) in segments.items():
            print(f"  {name:10s} measured, residual {r:.2f} mm, condition {c:.1f}")
        for name, r in report["regions"].items():
            print(f"  {name:10s} mean {r['mean']:.2f} mm, within 2 mm {r['within_2mm']:.0%}")
        for name, v in report["landmarks"].items():
            print(f"  {name:4s} {v:.2f} mm")
    return 0


def _crop(points, tris, lo, hi) -> tuple:
    """The surface's triangles whose vertices all lie in the box [lo, hi] (mm)."""
    inside = ((points >= lo) & (points <= hi)).all(axis=1)
    return points, tris[inside[tris].all(axis=1)]


def _write_measured(transforms: dict, out, comm) -> None:
    """The measured movements: ``transforms.json`` ({segment: 4×4}, the scene's frame, for
    ``--transforms``) and ``<segment>.tfm`` (ITK, 3D Slicer), each whole or not at all."""
    from fem.io import write_json

    write_json(out / "transforms.json", {k: T.tolist() for k, T in transforms.items()}, comm)
    write_transforms(transforms, out, comm)


if __name__ == "__main__":
    sys.exit(run_main(main))
