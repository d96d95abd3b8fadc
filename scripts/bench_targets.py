"""``targets`` (issue 51): the paper-size forward and a whole plan on both targets, side by side
in one run: Debian's dolfinx 0.5.2 (`.venv`) and PyPI's 0.11 (`.venv-pypi`), each script a
fresh process of the target's interpreter under its own MPI's launcher. Both read the same
scene files, meshed once by the first target's gmsh (another gmsh meshes a case otherwise),
so their landmarks are compared too.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from scripts._bench import ROOT, header, run, table, write_section

TARGETS = {"Debian": ROOT / ".venv" / "bin" / "python",
           "PyPI": ROOT / ".venv-pypi" / "bin" / "python"}
_WRITE = ("import sys; from meshes.external import write_tet_mesh; "
          "from meshes.synthetic import synthetic_head; "
          "write_tet_mesh(synthetic_head(sys.argv[1], sys.argv[2]), sys.argv[3])")
_VERSIONS = ("from mpi4py import MPI; import dolfinx, petsc4py; "
             "mpi = ' '.join(MPI.Get_library_version().split()[:3]).rstrip(','); "
             "print(f'dolfinx {dolfinx.__version__}, PETSc {petsc4py.__version__}, {mpi}')")


def versions(python) -> str:
    """The target's dolfinx, PETSc and MPI. Python's own environment, not the C one this
    process's MPI may have added to (an Open MPI singleton's PMIx variables stop MPICH)."""
    r = subprocess.run([str(python), "-c", _VERSIONS], capture_output=True, text=True,
                       env=dict(os.environ))
    return r.stdout.strip() or f"unavailable: {(r.stderr.strip().splitlines() or ['?'])[-1]}"


def targets(args) -> None:
    found = {k: p for k, p in TARGETS.items() if p.exists()}
    lines = header("Two targets: Debian's dolfinx 0.5.2 and PyPI's 0.11 (issue 51)", args)
    lines += [f"- {k}: `{p.relative_to(ROOT)}`, {versions(p)}." for k, p in found.items()]
    lines += [f"- {k}: no `{p.relative_to(ROOT)}` (`make test-pypi` builds it)."
              for k, p in TARGETS.items() if k not in found]
    lines += ["", "Forward: class3, rest to a 5 mm mandible advance (`simulate.py`, "
              "quasi-Newton); plan: class3-asym from p = 0 to its goal (`plan.py`); seconds "
              "of the solve and of the whole plan. Landmarks apart: the largest distance "
              "between the targets' landmarks, on the same scene file (`amg`: within its CG's "
              "tolerance). Why PyPI's MUMPS factorises slower at 1 rank: docs/solver.md.", ""]
    head = ["run", "ranks", "solver", *(f"{k} s" for k in found),
            *(f"{k} peak RSS MiB" for k in found), "second / first", "landmarks apart mm"]
    runs = [("forward", n, s) for n in map(int, args.ranks.split(","))
            for s in args.solvers.split(",")] + [("plan", 2, "direct")]
    rows = []
    with tempfile.TemporaryDirectory() as d:
        scenes = {case: Path(d) / f"{case}.vtu" for case in ("class3", "class3-asym")}
        for case, path in scenes.items():
            subprocess.run([str(next(iter(found.values()))), "-c", _WRITE, case,
                            args.resolution, str(path)], check=True, cwd=ROOT)
        for what, n, solver in runs:
            got = {k: _run(what, scenes, solver, n, python) for k, python in found.items()}
            rows.append(_row(found, what, n, solver, got))
            print(rows[-1], flush=True)
    write_section("targets", "\n".join(lines + table(head, rows)))


def _run(what: str, scenes: dict, solver: str, n: int, python) -> dict:
    """One forward (class3, 5 mm advance) or plan (class3-asym's goal) report."""
    if what == "forward":
        return run("simulate.py", n=n, python=str(python), args=[
            "--mesh", str(scenes["class3"]), "--solver", solver, "--p", "mandible.advance_mm=5"])
    return run("plan.py", n=n, python=str(python), args=[
        "--mesh", str(scenes["class3-asym"]), "--goal", "class3-asym", "--solver", solver])


def _row(found: dict, what: str, n: int, solver: str, got: dict) -> list:
    ok = {k: r for k, r in got.items() if "error" not in r}
    key = "solve" if what == "forward" else "total"
    secs = [f"{ok[k]['timings_s'][key]:.2f}" if k in ok else
            f"failed: {got[k]['error'][:50]}" for k in found]
    rss = [f"{ok[k]['peak_rss_mb']:.0f}" if k in ok and "peak_rss_mb" in ok[k] else ""
           for k in found]
    ratio = apart = ""
    if len(ok) == 2:
        a, b = ok.values()
        ratio = f"{b['timings_s'][key] / a['timings_s'][key]:.2f}"
        apart = f"{max(_apart(a, b, m) for m in a['landmarks']):.1e}"
    return [what, n, solver, *secs, *rss, ratio, apart]


def _apart(a: dict, b: dict, name: str) -> float:
    """How far apart two reports (simulate.py's, or plan.py's after the plan) put landmark
    ``name``, mm."""
    x, y = (r["landmarks"][name] for r in (a, b))
    x, y = (v["after"] if isinstance(v, dict) else v for v in (x, y))
    return float(np.linalg.norm(np.subtract(x, y)))
