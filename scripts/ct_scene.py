#!/usr/bin/env python3
"""A CT volume to a simulation-ready scene (tet mesh + JSON sidecar) for ``--mesh``.

    python3 scripts/ct_scene.py --ct ../shared/data/headsq/headsq.mhd \
        --osteotomies meshes/examples/headsq.json --resolution paper \
        --out out/headsq --report out/headsq/ct.json
    python3 scripts/plan.py --mesh out/headsq/scene.vtu --occlusion free --targets T.json
    python3 scripts/ct_scene.py --ct CT --propose-osteotomies proposed.json

``--ct``: a DICOM folder, NIfTI, NRRD, MetaImage (.mha/.mhd) or an InVesalius .inv3 project
(HU), or a label map with ``--labelmap`` (3D Slicer segmentation: 1 tissue, 2 bone). The
osteotomy file holds the cut planes, the crop and optionally the head frame (`meshes.ct`,
`meshes.osteotomy`, `meshes.frame`: estimated when not given); the landmarks are built on the
head frame's mid-sagittal profile (`meshes.landmarks`) unless ``--landmarks``
(JSON ``{name: [x, y, z]}`` or a 3D Slicer ``.mrk.json``) gives them. The result is cached;
the outputs are written whole or not at all. Under mpirun, rank 0 builds and writes.

``--propose-osteotomies O.json`` writes a starting osteotomy file instead, from the CT's
anatomy (`meshes.propose`: the planes, the crop, each by a documented rule), to adjust in 3D
Slicer or by hand; an ``--osteotomies`` file given with it lends its settings (thresholds,
frame, band widths), its planes replaced.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._common import parse, peak_rss_mb, run_main  # noqa: E402

MESH_NAME = "scene.vtu"


def parser():
    from meshes.ct import DEFAULT_RESOLUTION
    from meshes.synthetic import RESOLUTIONS
    from scripts._common import base_parser

    ap = base_parser(__doc__)
    ap.add_argument("--ct", required=True, help="CT volume (file or DICOM folder)")
    ap.add_argument("--osteotomies", help="JSON of cut planes and crop (mm)")
    ap.add_argument("--propose-osteotomies", metavar="O.json",
                    help="write a starting osteotomy file from the CT's anatomy, and stop")
    ap.add_argument("--landmarks", help="JSON {name: [x, y, z]} or 3D Slicer .mrk.json")
    ap.add_argument("--labelmap", action="store_true", help="--ct is a label map")
    ap.add_argument("--resolution", default=DEFAULT_RESOLUTION, choices=list(RESOLUTIONS),
                    help="mesh size (default %(default)s: within 0.1 mm of fine, "
                    "BENCHMARKS.md)")
    ap.add_argument("--out", help=f"output folder ({MESH_NAME} + its sidecar)")
    ap.add_argument("--report", help="JSON report path")
    ap.add_argument("--picture", help="PNG of the scene: skin, segments, landmarks")
    return ap


def propose(args, comm) -> int:
    """``--propose-osteotomies``: the proposed file, written whole on rank 0."""
    from fem.io import write_json
    from meshes.ct import read_scan, read_scene_file
    from meshes.errors import MeshError
    from meshes.propose import propose as proposal

    if args.labelmap:
        raise MeshError("--propose-osteotomies reads HU: give the CT, not a label map")
    spec = None
    if comm.rank == 0:
        try:
            base = None if args.osteotomies is None else read_scene_file(args.osteotomies)
            spec = proposal(read_scan(args.ct, base or {})[0], base, args.osteotomies or "")
        except MeshError as e:
            spec = str(e)
    spec = comm.bcast(spec, root=0)
    if isinstance(spec, str):
        raise MeshError(spec)
    write_json(args.propose_osteotomies, spec, comm)
    if comm.rank == 0:
        cuts = [k for k in spec if isinstance(spec[k], dict) and "normal" in spec[k]]
        print(f"{args.propose_osteotomies}: proposed {', '.join(cuts)} and the crop "
              f"{spec['crop']}; adjust them, then: ct_scene.py --osteotomies "
              f"{args.propose_osteotomies}")
    return 0


def intensity_line(intensity: dict, metal: dict) -> str:
    """One line: where the scan's HU came from, and its metal."""
    c, th = intensity["classes"], intensity["thresholds"]
    how = {"hu": "in HU", "given": "taken as they are (calibration: none)",
           "estimated": "put on HU by its classes"}[intensity["source"]]
    classes = ", ".join(f"{k} {v:g}" for k, v in c.items())
    return (f"intensities: {how}" + (f" (the scan's {classes})" if classes else "")
            + "; thresholds " + ", ".join(f"{k} {v['hu']:g} HU ({v['source']})"
                                          for k, v in th.items() if k in ("skin_hu", "bone_hu"))
            + (f"; metal {metal['mm3']:g} mm³ in {metal['components']} parts, its streaks "
               f"interpolated" if metal["mm3"] else "; no metal"))


def main(argv=None):
    args, comm = parse(parser(), argv)
    if args.propose_osteotomies:
        return propose(args, comm)
    if args.osteotomies is None or args.out is None:
        from meshes.errors import MeshError

        raise MeshError("give --osteotomies and --out to build a scene, or "
                        "--propose-osteotomies O.json to propose the osteotomies")
    import time

    import numpy as np

    from fem.io import write_json, write_on_root
    from meshes.anatomy import SKIN, segment_tags
    from meshes.errors import MeshError
    from meshes.external import write_tet_mesh
    from meshes.teeth import lopsided_teeth, teeth_report

    t0 = time.perf_counter()
    result = None
    if comm.rank == 0:
        from meshes.ct import ct_anatomy

        try:
            result = ct_anatomy(args.ct, args.osteotomies, args.resolution, args.labelmap,
                                args.landmarks)
        except MeshError as e:
            result = str(e)
    error = comm.bcast(result if isinstance(result, str) else None, root=0)
    if error:
        raise MeshError(error)
    mesh = Path(args.out) / MESH_NAME
    report = None
    if comm.rank == 0:
        anatomy, info = result
        timings = dict(info["timings_s"])
        teeth = teeth_report(anatomy)
        t = time.perf_counter()
    write_on_root(mesh, (lambda p: write_tet_mesh(anatomy, p)) if comm.rank == 0 else None,
                  comm)
    if comm.rank == 0:
        timings["write"] = time.perf_counter() - t
        timings["total"] = time.perf_counter() - t0
        report = {
            "mesh": str(mesh), "n_vertices": anatomy.n_vertices, "n_cells": anatomy.n_cells,
            "segments": {n: int(np.isin(anatomy.facet_tags, segment_tags(tag)).sum())
                         for n, tag in anatomy.segments.items()},
            "teeth": teeth, "teeth_lopsided": lopsided_teeth(teeth, anatomy.segments),
            "tissues": info["tissues"],
            "material": anatomy.material,
            "skin_facets": int((anatomy.facet_tags == SKIN).sum()),
            "landmarks": {n: p.tolist() for n, p in anatomy.landmark_positions().items()},
            "min_quality": info["min_quality"], "voxel_mm": info["voxel_mm"],
            "intensity": info.get("intensity"), "metal": info.get("metal"),
            "landmarks_left_out": info.get("landmarks_left_out", {}),
            **anatomy.head_frame.report(), "cached": info["cached"], "timings_s": timings}
        print(f"{mesh}: {anatomy.n_vertices} vertices, {anatomy.n_cells} tets, segments "
              f"{report['segments']}, landmarks {sorted(report['landmarks'])}, min quality "
              f"{info['min_quality']:.3f}, {timings['total']:.1f} s"
              + (" (cached)" if info["cached"] else ""))
        for name, why in info.get("landmarks_left_out", {}).items():
            print(f"landmark {name} left out: {why}")
        for name, why in report["teeth_lopsided"].items():
            print(f"warning: {name}: {why}")
        if info.get("intensity"):
            print(intensity_line(info["intensity"], info["metal"]))
        tilt = anatomy.head_frame.tilt_deg()
        print("head frame: tilted from the scanner's axes by "
              + ", ".join(f"{k.split('_')[0]} {v:+.2f} deg" for k, v in tilt.items())
              + "; " + ", ".join(f"{k} {v}" for k, v in anatomy.head_frame.sources.items()))
    if args.picture:
        from scripts._render import render_scene

        write_on_root(args.picture, (lambda p: render_scene(anatomy, p)) if comm.rank == 0
                      else None, comm)
    if args.report:
        rss = peak_rss_mb(comm)   # collective; the scene is built on rank 0
        write_json(args.report, comm.bcast(report and {**report, "peak_rss_mb": rss}, root=0),
                   comm)
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
