"""Argument parsing and error reporting shared by the scripts (no physics here)."""

from __future__ import annotations

import json
import logging
import sys
import traceback
from pathlib import Path

#: The two real example CTs (docs/anatomy.md): Debian's invesalius-examples (an upper face)
#: and the shared headsq (both jaws), read-only where they are.
CRANIUM_CT = Path("/usr/share/doc/invesalius-examples/examples/Cranium.inv3")
HEADSQ_CT = Path(__file__).resolve().parents[2] / "shared" / "data" / "headsq" / "headsq.mhd"


def parse(ap, argv=None):
    """Parse our arguments; hand the rest (``-orthodiff_...`` options) to PETSc.

    Returns (args, comm)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args, rest = ap.parse_known_args(argv)
    bad = [a for a in rest if a.startswith("--")]
    if bad:
        ap.error(f"unrecognised arguments: {' '.join(bad)}")
    from meshes.errors import InputError

    try:
        check_options(args)
    except InputError as e:   # before any work, on every rank alike
        _one_line_error(str(e))
    from mpi4py import MPI  # first: it loads the MPI library PETSc links (PyPI's MPICH)
    from petsc4py import init as petsc_init

    petsc_init([sys.argv[0], *rest])
    _own_signals()   # again: PETSc 3.25 (PyPI's) took SIGTERM as it started

    comm = MPI.COMM_WORLD
    # our progress on rank 0; the libraries' INFO (FFCx's compiler lines on a fresh machine:
    # cffi sets the root logger to INFO when it compiles) only with -v
    verbose = getattr(args, "verbose", False)
    logging.basicConfig(level=logging.INFO if comm.rank == 0 else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s")
    for handler in logging.getLogger().handlers:
        handler.addFilter(lambda r: verbose or r.levelno >= logging.WARNING
                          or r.name.split(".")[0] in OUR_LOGGERS)
    if comm.rank == 0:
        import mpi4py
        from petsc4py import PETSc

        import dolfinx

        logging.getLogger("orthodiff").info(
            "dolfinx %s, petsc4py %s, mpi4py %s, %d rank(s)", dolfinx.__version__,
            ".".join(map(str, PETSc.Sys.getVersion())), mpi4py.__version__, comm.size)
    return args, comm


#: Loggers that report progress on rank 0 (the rest of the root logger's output needs -v).
OUR_LOGGERS = ("orthodiff", "fem", "inverse", "meshes")
#: Numeric options checked by `check_options`: attribute -> `fem.limits.OPTIONS` key.
CHECKED = {"ftol": "ftol", "max_iterations": "max_iterations", "tikhonov": "tikhonov",
           "penalty": "penalty", "substep_mm": "substep_mm", "iterations": "iterations",
           "port": "port"}
#: Comma-separated list options that must name at least one item when given: what an item is.
LISTS = {"params_used": "parameter", "landmarks": "landmark", "scales": "scale"}


def names_list(text: str) -> list[str]:
    """Items of a comma-separated option, stripped, empty ones dropped."""
    return [s.strip() for s in text.split(",") if s.strip()]


def check_options(args) -> None:
    """Every option of a script in its range (`fem.limits`), lists not empty: `InputError`
    naming the option and the range otherwise."""
    from fem.limits import check
    from meshes.errors import InputError

    for attr, key in CHECKED.items():   # given as text: check() converts
        value = getattr(args, attr, None)
        if value is not None:
            setattr(args, attr, check(key, value, "--" + attr.replace("_", "-")))
    for attr, item in LISTS.items():
        value = getattr(args, attr, None)
        if value is not None and not names_list(value):
            raise InputError(f"--{attr.replace('_', '-')} must name at least one {item}, got "
                             f"{value!r}")
    for item in names_list(getattr(args, "scales", None) or ""):
        check("scale", item, "--scales")


def _one_line_error(message: str):
    """An option error as one line (rank 0), exit code 2: for argparse and `check_options`."""
    from mpi4py import MPI

    if MPI.COMM_WORLD.rank == 0:
        print(f"error: {message}", file=sys.stderr)
    raise SystemExit(2)


def base_parser(doc: str):
    """An argument parser with one-line errors (exit 2) and ``-v`` (the libraries' logs)."""
    import argparse

    ap = argparse.ArgumentParser(description=doc,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.error = _one_line_error
    ap.add_argument("-v", "--verbose", action="store_true",
                    help="also the libraries' logs (FFCx's JIT compiler lines, ...)")
    return ap


def scene_parser(doc: str, plan: bool = False, params: str | None = None):
    """An argument parser with the scene options (`add_scene_args`); with ``params`` (what
    the parameters are, for the help), also ``--params FILE`` and ``--p NAME=VALUE ...``,
    read by `load_params`."""
    ap = base_parser(doc)
    add_scene_args(ap, plan)
    if params:
        ap.add_argument("--params", help=f"JSON file {{name: value}}: {params}")
        ap.add_argument("--p", nargs="*", action="extend", default=[], metavar="NAME=VALUE",
                        help=f"{params} (override --params)")
    return ap


def add_scene_args(ap, plan: bool = False):
    """Scene options; for planning, ``--params-used`` defaults to `PLAN_PARAMS` (occlusion
    free) or `JAWS_PARAMS` (final occlusion)."""
    from meshes.synthetic import CASES, RESOLUTIONS

    ap.add_argument("--case", default="class3-asym", help=f"one of {sorted(CASES)}")
    ap.add_argument("--resolution", default="coarse", help=f"one of {list(RESOLUTIONS)}")
    ap.add_argument("--mesh", help="tetrahedral mesh file with a JSON sidecar (see README) "
                    "instead of a built-in case")
    ap.add_argument("--params-used", default=None,
                    help="comma-separated subset of parameter names" + (
                        " (default: the mandible's six motions and the maxilla's advance, "
                        "vertical, roll and yaw with --occlusion free; the six jaws.* motions "
                        "with --occlusion final)" if plan else ""))
    ap.add_argument("--occlusion", default="free", choices=("free", "final"),
                    help="free: maxilla and mandible move independently; final: the mandible "
                    "is held to the maxilla in the anatomy's final occlusion and both move as "
                    "one unit (the jaws.* motions)")
    ap.add_argument("--treatment", default="rigid", choices=("rigid", "linear"),
                    help="rigid: exact rigid motions (default); linear: the paper's "
                    "linearised blendshapes of the same names")
    ap.add_argument("--solver", default="direct", help="linear solver preset: direct, cholmod, "
                    "gamg")
    ap.add_argument("--method", default="qn", choices=("qn", "newton"),
                    help="nonlinear method: quasi-Newton on a kept factorisation (default) "
                    "or Newton (a factorisation per step)")
    ap.add_argument("--contact", default=None, choices=("sliding", "glued"),
                    help="the tissue on the teeth: sliding (only the normal gap is held; the "
                    "default of CT scenes) or glued (held like the rest of the bone, the "
                    "paper's model; the default of the synthetic heads and of meshes without "
                    "teeth)")
    ap.add_argument("--material", default=None,
                    help="the soft tissue: tissues (skin, fat and lean tissue per cell; the "
                    "default of CT scenes), homogeneous (the paper's E = 5 kPa, nu = 0.47; "
                    "the default of the synthetic heads and of meshes without tissue classes) "
                    "or a .json file of per-tissue E (kPa) and nu (docs/anatomy.md)")
    ap.add_argument("--penalty", default=None, help="active penalty k, kPa/mm")
    ap.add_argument("--degree", type=int, default=1, choices=(1, 2),
                    help="Lagrange degree of the displacement (P2: ~7x the dofs, see BENCHMARKS)")


def add_band_args(ap) -> None:
    """``--prior`` and ``--no-bands``: the prediction bands (`inverse.uncertainty`)."""
    ap.add_argument("--prior", help="material file (.json) whose E (kPa) and nu per class are "
                    "the prior's medians and optional sd_log_E, sd_log_1m2nu its spreads "
                    "(docs/uncertainty.md; default: the scene's material, documented spreads)")
    ap.add_argument("--no-bands", action="store_true",
                    help="skip the prediction bands (one back-substitution per material "
                    "parameter; the report's 'bands' and the XDMF's band_r95_mm)")


def scene_from_args(args, comm, plan: bool = False, groups: bool = True):
    """The `Scene` the options describe. ``plan``: the planning defaults of
    ``--params-used``; ``groups=False``: without group motions (maxilla.*, jaws.*) unless
    named, so that each segment's motion has one set of parameters."""
    from inverse.scene import Scene
    from inverse.treatment import JAWS_PARAMS, PLAN_PARAMS

    kw = {"solver": args.solver, "comm": comm, "degree": args.degree,
          "equilibrium": {"method": args.method}, "occlusion": args.occlusion,
          "linear": args.treatment == "linear", "groups": groups, "contact": args.contact,
          "material": args.material}
    if args.params_used is not None:
        kw["params_used"] = names_list(args.params_used)
        kw["groups"] = True
    elif plan:
        kw["params_used"] = JAWS_PARAMS if args.occlusion == "final" else PLAN_PARAMS
    if args.penalty is not None:
        kw["penalty"] = args.penalty
    if args.mesh:
        from meshes.external import load_tet_mesh

        return Scene(lambda: load_tet_mesh(args.mesh), **kw)
    return Scene.from_case(args.case, args.resolution, **kw)


def add_transforms_arg(ap) -> None:
    """``--transforms``: the bone motions as VSP transforms, instead of ``--params``/``--p``."""
    ap.add_argument("--transforms", help="JSON {segment: 4x4 | file.tfm} or one <segment>.tfm: "
                    "the bone motions (instead of --params/--p)")


def check_movements(args) -> None:
    """`InputError` when both transforms and parameters are given (before the scene)."""
    if args.transforms and (args.params or args.p):
        from meshes.errors import InputError

        raise InputError("give either --transforms or --params/--p, not both")


def movements(args, scene):
    """The treatment's parameters (P,) of ``--transforms`` or ``--params``/``--p``; the scene
    is built with ``groups=not args.transforms`` (`scene_from_args`)."""
    if args.transforms:
        from meshes.transforms import read_transforms

        return scene.params_from_transforms(read_transforms(args.transforms))
    return scene.param_vector(load_params(args.params, args.p, scene))


def warn_bounds(scene, p, comm) -> list[str]:
    """Warn (rank 0) of each parameter of p outside its feasible bounds; the messages."""
    import logging

    warnings = scene.treatment.outside_bounds(p)
    if comm.rank == 0:
        for w in warnings:
            logging.getLogger("orthodiff").warning(w)
    return warnings


def write_transforms(transforms: dict, out_dir, comm) -> None:
    """One ITK transform file ``<segment>.tfm`` per segment of ``transforms`` ({segment:
    4×4}, e.g. `inverse.scene.Scene.transforms`) into ``out_dir`` (3D Slicer)."""
    from pathlib import Path

    from fem.io import write_text
    from meshes.transforms import itk_text

    for seg, T in transforms.items():
        write_text(Path(out_dir) / f"{seg}.tfm", itk_text(T), comm)


def peak_rss_mb(comm) -> float:
    """Peak resident memory of the run, MiB, summed over ranks (collective)."""
    import resource

    return comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)


def load_params(path, pairs, scene) -> dict:
    """{name: value} from a JSON file and NAME=VALUE pairs (pairs win)."""
    from meshes.errors import InputError

    values = {}
    if path:
        try:
            with open(path) as fh:
                values = json.load(fh)
        except (OSError, json.JSONDecodeError) as e:
            raise InputError(f"cannot read parameter file {path}: {e}") from None
        if not isinstance(values, dict):
            raise InputError(f"{path} must hold a JSON object {{name: value}}")
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep:
            raise InputError(f"--p expects NAME=VALUE, got {pair!r}")
        values[name.strip()] = value
    return values


def read_json(path, what: str, comm):
    """A JSON file read on rank 0, on every rank; `InputError` ("cannot read <what> <path>:
    why") in one line otherwise. Collective."""
    from meshes.errors import InputError

    data, err = None, None
    if comm.rank == 0:
        try:
            with open(path, encoding="utf-8") as fh:
                data = json.load(fh)
        except (OSError, ValueError) as e:
            err = f"cannot read {what} {path}: {e}"
    data, err = comm.bcast((data, err), root=0)
    if err:
        raise InputError(err)
    return data


def _interrupted(signum, frame):
    """SIGTERM like Ctrl-C: unwind, once a write is done (`fem.io`)."""
    io = sys.modules.get("fem.io")     # not imported yet: no write in progress
    if io is None or io.interrupt_now(signum):
        raise KeyboardInterrupt(f"signal {signum}")


def _own_signals() -> None:
    """SIGTERM, and SIGINT unless the shell ignores it, go to `_interrupted`."""
    import signal

    signal.signal(signal.SIGTERM, _interrupted)
    if signal.getsignal(signal.SIGINT) in (signal.default_int_handler, _interrupted):
        signal.signal(signal.SIGINT, _interrupted)


def run_main(main) -> int:
    """Run ``main``; report an orthodiff error on rank 0 as one line and exit code 2."""
    from meshes.errors import OrthodiffError

    _own_signals()
    try:
        return main()
    except KeyboardInterrupt as e:
        print(f"interrupted ({e or 'SIGINT'}): no partial output was kept", file=sys.stderr)
        return 130
    except OrthodiffError as e:
        from mpi4py import MPI

        if MPI.COMM_WORLD.rank == 0:
            print(f"error: {e}", file=sys.stderr)
        return 2
    except Exception:   # a bug on one rank: the others would wait for it in a collective
        from mpi4py import MPI

        if MPI.COMM_WORLD.size == 1:
            raise
        traceback.print_exc()
        sys.stderr.flush()
        MPI.COMM_WORLD.Abort(1)
