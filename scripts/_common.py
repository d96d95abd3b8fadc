"""Argument parsing and error reporting shared by the scripts (no physics here)."""

from __future__ import annotations

import json
import logging
import sys


def parse(ap, argv=None):
    """Parse our arguments; hand the rest (``-orthodiff_...`` options) to PETSc.

    Returns (args, comm)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args, rest = ap.parse_known_args(argv)
    bad = [a for a in rest if a.startswith("--")]
    if bad:
        ap.error(f"unrecognised arguments: {' '.join(bad)}")
    import petsc4py

    petsc4py.init([sys.argv[0], *rest])
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    logging.basicConfig(level=logging.INFO if comm.rank == 0 else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s")
    if comm.rank == 0:
        import mpi4py
        from petsc4py import PETSc

        import dolfinx

        logging.getLogger("orthodiff").info(
            "dolfinx %s, petsc4py %s, mpi4py %s, %d rank(s)", dolfinx.__version__,
            ".".join(map(str, PETSc.Sys.getVersion())), mpi4py.__version__, comm.size)
    return args, comm


def scene_parser(doc: str, plan: bool = False, params: str | None = None):
    """An argument parser with the scene options (`add_scene_args`); with ``params`` (what
    the parameters are, for the help), also ``--params FILE`` and ``--p NAME=VALUE ...``,
    read by `load_params`."""
    import argparse

    ap = argparse.ArgumentParser(description=doc,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(ap, plan)
    if params:
        ap.add_argument("--params", help=f"JSON file {{name: value}}: {params}")
        ap.add_argument("--p", nargs="*", default=[], metavar="NAME=VALUE",
                        help=f"{params} (override --params)")
    return ap


def add_scene_args(ap, plan: bool = False):
    """Scene options; for planning, ``--params-used`` defaults to `PLAN_PARAMS`."""
    from inverse.treatment import PLAN_PARAMS
    from meshes.synthetic import CASES, RESOLUTIONS

    ap.add_argument("--case", default="class3-asym", help=f"one of {sorted(CASES)}")
    ap.add_argument("--resolution", default="coarse", help=f"one of {list(RESOLUTIONS)}")
    ap.add_argument("--mesh", help="tetrahedral mesh file with a JSON sidecar (see README) "
                    "instead of a built-in case")
    ap.add_argument("--params-used", default=",".join(PLAN_PARAMS) if plan else None,
                    help="comma-separated subset of parameter names")
    ap.add_argument("--solver", default="direct", help="linear solver preset: direct, cholmod, "
                    "gamg")
    ap.add_argument("--method", default="qn", choices=("qn", "newton"),
                    help="nonlinear method: quasi-Newton on a kept factorisation (default) "
                    "or Newton (a factorisation per step)")
    ap.add_argument("--penalty", type=float, default=None, help="active penalty k, kPa/mm")
    ap.add_argument("--degree", type=int, default=1, choices=(1, 2),
                    help="Lagrange degree of the displacement (P2: ~7x the dofs, see BENCHMARKS)")


def scene_from_args(args, comm):
    from inverse.scene import Scene

    kw = {"solver": args.solver, "comm": comm, "degree": args.degree,
          "newton": {"method": args.method}}
    if args.params_used:
        kw["params_used"] = [s.strip() for s in args.params_used.split(",") if s.strip()]
    if args.penalty is not None:
        kw["penalty"] = args.penalty
    if args.mesh:
        from meshes.external import load_tet_mesh

        return Scene(lambda: load_tet_mesh(args.mesh), **kw)
    return Scene.from_case(args.case, args.resolution, **kw)


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


def run_main(main) -> int:
    """Run ``main``; report an orthodiff error on rank 0 as one line and exit code 2."""
    import signal

    from meshes.errors import OrthodiffError

    def interrupted(signum, frame):   # SIGTERM like Ctrl-C: unwind, once a write is done
        io = sys.modules.get("fem.io")     # not imported yet: no write in progress
        if io is None or io.interrupt_now(signum):
            raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, interrupted)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, interrupted)
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
