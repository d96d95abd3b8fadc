#!/usr/bin/env python3
"""Learn the tissue from outcomes: fit the material parameters θ (each class's ln E and
ln(1 - 2ν)) to validated cases (docs/uncertainty.md, `inverse.calibration`).

    python3 scripts/validate.py --mesh scene.vtu --post post.ply --transforms t.json \
        --out out/v1 --report out/v1/report.json          # a validated case
    mpirun -n 2 python3 scripts/calibrate.py --cases out/v1/report.json [out/v2/report.json]\
        --out out/cal --report out/cal/report.json
    python3 scripts/simulate.py --mesh scene.vtu --material out/cal/material.json ...

A case is ``validate.py``'s report: its scene (``--mesh`` or ``--case``/``--resolution``),
the movements it simulated (its ``transforms``: given, or measured by ``--measure-bone``)
and its outcome's skin registered in the scene's frame (``outcome.ply``). The cases fit one
shared θ (a cohort's tissue), or one each with ``--each``; all ranks share each scene, or
with ``--split`` the ranks split into groups that take a case each.

Writes ``material.json`` (``material_<case>.json`` with ``--each``): the fitted moduli, for
``--material``, with the posterior's spreads and correlation, for ``--prior`` of the next fit
and ``--material``'s bands; and the report:
θ with its posterior SD, the directions the data cannot see, the errors before and after
over the face and per region, and per case its registration's correction, its skin's offset
(mm) and the share of its skin left out as outliers. Bad input is one line, exit 2, nothing
written.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._common import base_parser, parse, read_json, run_main  # noqa: E402

#: A 3dMD camera's noise (mm, Gaussian SD along the normal): the residual's scale.
NOISE_MM = 0.2
#: A fit explains its outcome where its residual's RMS is at most this times the noise
#: (measured: 0.9-0.95 on noised scans of a simulated outcome; the noise of a subdivided
#: scan along the normals is a little under its SD).
FIT_RATIO = 1.5


def _names(paths) -> list:
    """Each case's name: its report's folder, made unique (``v``, ``v-2``)."""
    seen, out = {}, []
    for path in paths:
        name = Path(path).parent.name
        seen[name] = seen.get(name, 0) + 1
        out.append(name + (f"-{seen[name]}" if seen[name] > 1 else ""))
    return out


def _gathered(cases, what) -> dict:
    """{case name: what(case)} over every group's cases. Collective over ``cases.comm``."""
    mine = {cases.names[i]: what(c) for i, c in cases.local}
    return {k: v for part in cases.comm.allgather(mine if cases.lead else {})
            for k, v in part.items()}


def _case(path, material, comm, name):
    """A `inverse.calibration.Case` ``name`` from validate.py's report at ``path``: the scene
    with ``material`` (None: the case's) on ``comm``, its movements, its registered
    outcome. Collective over ``comm``."""
    import numpy as np

    from inverse.calibration import Case
    from inverse.scene import Scene
    from meshes.errors import InputError
    from meshes.surface import read_surface

    rep = read_json(path, "case", comm)
    missing = [k for k in ("outcome", "transforms", "registration") if not rep.get(k)]
    if missing or not Path(rep.get("outcome", "")).is_file():
        raise InputError(f"case {path}: not a validated case (validate.py's report with a "
                         f"registered outcome); it lacks {missing or [rep.get('outcome')]}")
    kw = dict(comm=comm, groups=False, contact=rep.get("contact"),
              material=material or rep.get("material"), occlusion=rep.get("occlusion") or "free")
    if rep.get("mesh"):
        from meshes.external import load_tet_mesh

        scene = Scene(lambda: load_tet_mesh(rep["mesh"]), **kw)
    else:
        scene = Scene.from_case(rep["case"], rep["resolution"], **kw)
    if rep.get("n_vertices") not in (None, scene.domain.n_vertices):
        raise InputError(f"case {path}: its scene had {rep['n_vertices']} vertices, this one "
                         f"has {scene.domain.n_vertices} (another mesh or mesher)")
    p = scene.params_from_transforms({k: np.asarray(T) for k, T in rep["transforms"].items()})
    points, tris = read_surface(rep["outcome"])
    rest = read_surface(rep["outcome_rest"]) if rep.get("outcome_rest") else None
    return Case(scene, p, points, tris, name=name, rest=rest)


def _regions(case) -> dict:
    """The face's and each region's error (validation.compare) at the case's equilibrium,
    against its outcome as the fit corrected its registration."""
    from inverse import validation
    from meshes.landmarks import staircase_mm

    scene = case.scene
    part, _, _ = validation.compare(case.skin.at(scene), case.skin.rest, case.skin.tris,
                                    scene.head_frame, scene.landmarks(rest=True), case.outcome,
                                    case.tris, staircase_mm(scene.domain.voxel_mm,
                                                            scene.head_frame))
    return {"face": part["error_mm"], **part["regions"]}


def _quality(found, noise_mm: float) -> dict:
    """The fit's residual (RMS, mm) against the noise given: within `FIT_RATIO` of it, the
    tissue explains the outcome; above, something else differs (the model, or the outcome's
    skin), and θ is not to be trusted: a warning says so."""
    worst = max(found.rms_after.values())
    ok = worst <= FIT_RATIO * noise_mm
    return {"residual_over_noise": worst / noise_mm, "explained": bool(ok),
            "warning": None if ok else (
                f"the residual after the fit, {worst:.3f} mm RMS, is {worst / noise_mm:.1f} "
                f"times the noise given ({noise_mm:g} mm): the outcome differs from the model "
                "by more than the tissue explains; do not trust the fitted tissue")}


def _ratios(names, theta, posterior) -> dict:
    """What the outcome sees best: each class's E over the first class's (``fat/skin``...),
    with the posterior SD of its log."""
    import numpy as np

    k = [i for i, n in enumerate(names) if n.endswith(".log_E")]
    out = {}
    for i in k[1:]:
        d = np.zeros(len(names))
        d[i], d[k[0]] = 1.0, -1.0
        key = f"{names[i].split('.')[0]}/{names[k[0]].split('.')[0]}"
        out[key] = {"value": float(np.exp(d @ theta)), "sd_log": float(np.sqrt(d @ posterior @ d))}
    return out


def _bounds(path, prior):
    """(lo, hi) of θ from a JSON ``{class: {"E": [lo, hi] kPa, "nu": [lo, hi]}}``, or None;
    `InputError` where they exclude the start (the prior's median)."""
    import json

    import numpy as np

    from meshes.errors import InputError

    if path is None:
        return None
    try:
        spec = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read bounds file {path}: {e}") from e
    lo, hi = np.full(len(prior.names), -np.inf), np.full(len(prior.names), np.inf)
    for c, given in (spec.items() if isinstance(spec, dict) else []):
        for key, f in (("E", np.log), ("nu", lambda v: np.log(1 - 2 * np.asarray(v)))):
            if key in given:
                name = f"{c}.{'log_E' if key == 'E' else 'log_1m2nu'}"
                if name not in prior.names:
                    raise InputError(f"bounds file {path}: unknown class {c!r}")
                a, b = sorted(f(np.asarray(given[key], float)))
                k = prior.names.index(name)
                lo[k], hi[k] = a, b
    if not np.all((lo <= prior.mean) & (prior.mean <= hi)):
        bad = [n for n, a, m, b in zip(prior.names, lo, prior.mean, hi) if not a <= m <= b]
        raise InputError(f"bounds file {path}: the start (the prior's median) lies outside "
                         f"the bounds of {', '.join(bad)}")
    return lo, hi


def main(argv=None):
    ap = base_parser(__doc__)
    ap.add_argument("--cases", nargs="+", required=True, help="validate.py reports")
    ap.add_argument("--each", action="store_true", help="one θ per case, not one shared")
    ap.add_argument("--split", action="store_true",
                    help="under mpirun, the ranks in groups, each taking its cases (round "
                    "robin), instead of all ranks sharing every scene")
    ap.add_argument("--prior", help="material file whose E and nu are the start and the "
                    "prior's medians, with optional sd_log_E, sd_log_1m2nu (default: the "
                    "scenes' material, documented spreads)")
    ap.add_argument("--bounds", help="JSON {class: {\"E\": [lo, hi] kPa, \"nu\": [lo, hi]}}")
    ap.add_argument("--noise-mm", type=float, default=NOISE_MM,
                    help="the outcome's noise, mm (the residual's scale)")
    ap.add_argument("--max-iterations", type=int, default=20)
    ap.add_argument("--out", required=True, help="folder for the fitted material file(s)")
    ap.add_argument("--report", required=True, help="JSON report path")
    args, comm = parse(ap, argv)
    import time

    import numpy as np

    from fem.io import write_json
    from fem.material import CORRELATION_KEY, material_file, with_theta
    from inverse.calibration import NG, Cases, fit
    from inverse.uncertainty import Prior, scene_prior
    from meshes.errors import InputError, MeshError

    t0 = time.perf_counter()
    names = _names(args.cases)
    n_groups = min(comm.size, len(args.cases)) if args.split else 1
    color = comm.rank % n_groups
    group = comm.Split(color, comm.rank) if n_groups > 1 else comm
    mine, error = [], None
    try:   # an error in one group is raised on every rank (no rank waits for it)
        mine = [(i, _case(path, args.prior, group, names[i]))
                for i, path in enumerate(args.cases) if i % n_groups == color]
    except (InputError, MeshError) as e:
        error = (type(e), str(e))
    for err in comm.allgather(error):
        if err is not None:
            raise err[0](err[1])
    prior = comm.bcast(Prior.from_file(args.prior) if args.prior else
                       scene_prior(mine[0][1].scene) if comm.rank == 0 else None, root=0)
    if len({k for ks in comm.allgather([tuple(scene_prior(c.scene).names) for _, c in mine])
            for k in ks}) > 1:
        raise InputError("the cases' materials differ in kind (tissues, homogeneous): give "
                         "--prior, or fit them --each")
    bounds = _bounds(args.bounds, prior)
    sets = ([Cases([(0, c)], [c.name], group) for _, c in mine] if args.each else
            [Cases(mine, names, comm)])
    fits = []
    for cases in sets:
        cases.stack(np.concatenate([prior.mean, np.zeros(NG * len(cases.names))]),
                    len(prior.mean), False)   # at the start: each outcome overlaps its scene
        before = _gathered(cases, _regions)
        found = fit(cases, prior, args.noise_mm, args.max_iterations, bounds)
        after = _gathered(cases, _regions)
        name = "material.json" if not args.each else f"material_{cases.names[0]}.json"
        sd = np.sqrt(np.diag(found.posterior))
        spec = material_file(with_theta(cases.local[0][1].scene.eq.material, found.theta), sd,
                             found.posterior / np.outer(sd, sd))
        correlation = spec.pop(CORRELATION_KEY)
        fits.append({"cases": cases.names, "file": str(Path(args.out) / name),
                     "ratios": _ratios(prior.names, found.theta, found.posterior),
                     "theta": dict(zip(prior.names, found.theta.tolist())),
                     "posterior_sd": dict(zip(prior.names, sd.tolist())),
                     "prior_sd": dict(zip(prior.names, prior.sd.tolist())),
                     "material": spec, "correlation": correlation, "unseen": found.unseen,
                     "iterations": found.iterations, "converged": found.converged,
                     "history": found.history,
                     "registration_correction": {k: g[:6] for k, g in found.registration.items()},
                     "skin_offset_mm": {k: g[6] for k, g in found.registration.items()},
                     "residual_rms_mm": {"before": found.rms_before, "after": found.rms_after},
                     "outliers": found.outliers,
                     "fit": _quality(found, args.noise_mm),
                     "error_before_mm": before, "error_after_mm": after})
    if args.each:   # every group's fits, in the cases' order
        lead = group.rank == 0
        fits = sorted((f for part in comm.allgather(fits if lead else []) for f in part),
                      key=lambda f: names.index(f["cases"][0]))
    files = {Path(f["file"]).name: {**f["material"], CORRELATION_KEY: f["correlation"]}
             for f in fits}
    out = Path(args.out)
    for name, spec in files.items():
        write_json(out / name, spec, comm)
    report = {"cases": args.cases, "n_ranks": comm.size, "rank_groups": n_groups,
              "noise_mm": args.noise_mm,
              "prior": prior.report(), "fits": fits,
              "timings_s": {"total": time.perf_counter() - t0}}
    write_json(args.report, report, comm)
    if comm.rank == 0:
        for f in fits:
            print(f"{', '.join(f['cases'])}: {f['iterations']} iterations, converged "
                  f"{f['converged']}; fitted, with its posterior SD:")
            for c, m in f["material"].items():
                print(f"  {c:7s} E {m['E']:8.3f} kPa (x/÷ e^{m['sd_log_E']:.3f})   "
                      f"nu {m['nu']:.4f}")
            for k, r in f["ratios"].items():
                print(f"  E {k:12s} {r['value']:.4f} (x/÷ e^{r['sd_log']:.3f})")
            for c in f["cases"]:
                b, a = f["error_before_mm"][c]["face"], f["error_after_mm"][c]["face"]
                print(f"  {c}: face RMS {b['rms']:.3f} -> {a['rms']:.3f} mm")
            if f["fit"]["warning"]:
                print(f"  warning: {f['fit']['warning']}")
            for u in f["unseen"]:
                print(f"  not seen by the data: {u['direction']} (information "
                      f"{u['information']:.2g} of the prior's)")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main))
