#!/usr/bin/env python3
"""The interactive explorer in the browser (paper Fig. 5): first-order sliders, true solves.

    mpirun -n 2 python3 scripts/explore_web.py --case class3-asym --resolution paper \
        [--params P.json | --plan-report out/demo/cranium/report.json \
         | --validation out/validation/report.json] [--host 127.0.0.1] [--port 8765]

It solves the equilibrium at p0 (``--params``/``--p``, or a plan report's result, its case,
resolution and occlusion; or a ``validate.py`` report's movements, whose map of the
predicted skin's distance to the real one the page then shows), computes the skin
sensitivities there, prints the URL and serves the page (``scripts/web``, three.js from npm)
and its JSON API until SIGINT or SIGTERM (exit 0).

API (README): ``GET /api/scene``, ``GET /api/sensitivity`` (float32 LE, (N_skin, 3, Np), C
order), ``GET /api/progress``, and ``POST /api/solve``, ``/api/corrected``,
``/api/relinearise``, ``/api/match``, ``/api/export`` with ``{"p": {name: value}}``, and
``POST /api/plan`` with ``{"targets": {...}, "occlusion": "final"|"free"}``. One computation
runs at a time: a request that finds one running gets 503. Bad requests get
``400 {"error": "..."}``; no traceback reaches the client. Under mpirun, rank 0 serves and
broadcasts each request to every rank; all ranks compute (`inverse.session.Session`).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._common import (  # noqa: E402
    load_params,
    parse,
    read_json,
    run_main,
    scene_from_args,
    scene_parser,
)

WEB = Path(__file__).resolve().parent / "web"
#: The page's files, and three.js's from npm (``make install`` runs ``npm ci`` in scripts/web).
PAGE_FILES = {"/": "index.html", "/explorer.js": "explorer.js", "/explorer.css": "explorer.css"}
THREE = WEB / "node_modules" / "three"
#: Largest request body, bytes (a targets object is < 1 kB).
MAX_BODY = 1 << 20


def main(argv=None):
    ap = scene_parser(__doc__, params="the equilibrium p0 to explore at")
    ap.add_argument("--plan-report", help="a plan.py report: explore at its planned "
                    "parameters (its case, resolution and occlusion unless given)")
    ap.add_argument("--validation", help="a validate.py report: explore at its movements "
                    "(its scene unless given) and show its distance map")
    ap.add_argument("--targets", help="JSON {landmark: [x, y, z]} mm shown and planned to, "
                    "as plan.py's (default: the plan report's, or the case's clinical goal)")
    ap.add_argument("--host", default="127.0.0.1", help="address to bind (default loopback "
                    "only)")
    ap.add_argument("--port", default=8765, help="TCP port (0: any free port)")
    argv = sys.argv[1:] if argv is None else list(argv)
    args, comm = parse(ap, argv)
    from inverse.session import Session
    from meshes.errors import InputError
    from scripts._server import Server, bind

    sock, err = None, None
    if comm.rank == 0:   # before any work: a busy port or a missing page is one line
        try:
            sock = bind(args.host, args.port)
            if not (THREE / "build" / "three.module.js").is_file():
                raise InputError(f"three.js is not installed in {WEB}: run `make install` "
                                 "(npm ci there)")
        except InputError as e:
            err = str(e)
    err = comm.bcast(err, root=0)
    if err:
        raise InputError(err)
    if args.plan_report and args.validation:
        raise InputError("give a plan report or a validation report, not both")
    report, validation = None, None
    if args.plan_report:
        report = read_json(args.plan_report, "plan report", comm)
        _apply_report(args, argv, report, "params_optimal", args.plan_report, "plan.py")
    elif args.validation:
        report = read_json(args.validation, "validation report", comm)
        _apply_report(args, argv, report, "params", args.validation, "validate.py")
        validation = _validation_map(report, args.validation)
    first, used = args.occlusion, args.params_used

    def make_scene(occlusion):   # the first scene, or the other occlusion's for a plan
        args.occlusion = occlusion
        args.params_used = used if occlusion == first else None
        return scene_from_args(args, comm, plan=True)

    scene = make_scene(first)
    if report is not None and not (args.params or args.p):
        p0 = dict(zip(report["param_names"],
                      report["params_optimal" if args.plan_report else "params"]))
    else:
        p0 = load_params(args.params, args.p, scene)
    targets = None
    if args.targets:
        targets = read_json(args.targets, "targets file", comm)
    elif args.plan_report:
        from inverse.objective import HEAD_AXES, target_entry

        targets = {n: target_entry(v["target"], v.get("along", HEAD_AXES))
                   for n, v in report.get("landmarks", {}).items()}
    session = Session(scene, make_scene, scene.param_vector(p0), targets, validation)
    if validation is not None and len(validation["signed_distance_mm"]) != len(
            session.pred.vertices):
        session.destroy()
        raise InputError(f"{args.validation} maps {len(validation['signed_distance_mm'])} "
                         f"skin vertices, the scene has {len(session.pred.vertices)}: it "
                         "belongs to another scene")
    try:
        return Server(session, comm, sock, PAGE_FILES, WEB, THREE, MAX_BODY).run()
    finally:
        session.destroy()


def _apply_report(args, argv, report: dict, params: str, path, script: str) -> None:
    """A report's case, resolution, occlusion, contact, material and parameter names, where
    no option gives them; its parameters are under the key ``params``."""
    from meshes.errors import InputError

    if not isinstance(report, dict) or not {"param_names", params} <= set(report):
        raise InputError(f"{path} is not a {script} report")
    given = {a.split("=")[0] for a in argv}
    if "--mesh" not in given and "--case" not in given and report.get("mesh"):
        args.mesh = report["mesh"]
    for key in ("case", "resolution"):
        if f"--{key}" not in given and report.get(key) and not args.mesh:
            setattr(args, key, report[key])
    if "--occlusion" not in given:
        args.occlusion = "free" if report.get("occlusion") is None else "final"
    for key in ("contact", "material"):
        if f"--{key}" not in given and report.get(key):
            setattr(args, key, report[key])
    if "--params-used" not in given:
        args.params_used = ",".join(report["param_names"])


def _validation_map(report: dict, path) -> dict:
    """The page's ``validation``: the report's signed distances per skin vertex (None where
    the scan does not hold it), read from its ``skin_distance`` XDMF, and its ``error_mm``."""
    import meshio
    import numpy as np

    from meshes.errors import InputError

    try:
        d = meshio.read(report["skin_distance"]).point_data["signed_distance_mm"]
    except (KeyError, OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read its skin distance map "
                         f"{report.get('skin_distance')!r}: {e}") from None
    d = np.asarray(d, float).ravel()
    return {"signed_distance_mm": [None if np.isnan(v) else float(v) for v in d],
            "error_mm": report.get("error_mm")}


if __name__ == "__main__":
    sys.exit(run_main(main))
