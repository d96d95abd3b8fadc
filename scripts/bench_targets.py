"""``targets`` (issue 51): the paper-size forward and a whole plan on both targets, side by side
in one run: Debian's dolfinx 0.5.2 (`.venv`) and PyPI's 0.11 (`.venv-pypi`), each script a
fresh process of the target's interpreter under its own MPI's launcher. Both read the same
cached mesh (the cache key is the case's, not the gmsh version's), so their landmarks are
compared too.
"""

from __future__ import annotations

import subprocess

import numpy as np

from scripts._bench import ROOT, header, simulate, table, write_section

TARGETS = {"Debian": ROOT / ".venv" / "bin" / "python",
           "PyPI": ROOT / ".venv-pypi" / "bin" / "python"}
_VERSIONS = ("from mpi4py import MPI; import dolfinx, petsc4py; "
             "print(f'dolfinx {dolfinx.__version__}, PETSc {petsc4py.__version__}, '"
             "f'{MPI.Get_library_version().splitlines()[0][:24]}')")


def versions(python) -> str:
    r = subprocess.run([str(python), "-c", _VERSIONS], capture_output=True, text=True)
    return r.stdout.strip() or f"unavailable: {(r.stderr.strip().splitlines() or ['?'])[-1]}"


def _apart(a: dict, b: dict, name: str) -> float:
    """How far apart two reports put landmark ``name``, mm."""
    return float(np.linalg.norm(np.subtract(a["landmarks"][name], b["landmarks"][name])))


def targets(args) -> None:
    targets = {k: p for k, p in TARGETS.items() if p.exists()}
    lines = header("Two targets: Debian's dolfinx 0.5.2 and PyPI's 0.11 (issue 51)", args)
    lines += [f"- {k}: `{p.relative_to(ROOT)}`, {versions(p)}." for k, p in targets.items()]
    lines += [f"- {k}: no `{p.relative_to(ROOT)}` (`make test-pypi` builds it)."
              for k, p in TARGETS.items() if k not in targets]
    lines += ["", "Forward: class3, rest to a 5 mm mandible advance (`simulate.py`, quasi-Newton); "
              "plan: class3-asym from p = 0 to its default goal (`plan.py`). Landmarks "
              "against the first target's, on the same mesh.", ""]
    head = ["run", "ranks", "solver", *(f"{k} s" for k in targets), *(
        f"{k} peak RSS MiB" for k in targets), "second / first", "landmarks apart mm"]
    rows = []
    runs = [("forward", n, s) for n in map(int, args.ranks.split(","))
            for s in args.solvers.split(",")] + [("plan", 2, "direct")]
    for what, n, solver in runs:
        got = {}
        for k, python in targets.items():
            if what == "forward":
                got[k] = simulate(args.resolution, solver, n, python=str(python))
            else:
                got[k] = simulate(args.resolution, solver, n, script="plan.py", python=str(
                    python), args=["--case", "class3-asym", "--resolution", args.resolution])
        ok = {k: r for k, r in got.items() if "error" not in r}
        key = "solve" if what == "forward" else "total"
        secs = [f"{ok[k]['timings_s'][key]:.2f}" if k in ok else
                f"failed: {got[k]['error'][:50]}" for k in targets]
        rss = [f"{ok[k]['peak_rss_mb']:.0f}" if k in ok and "peak_rss_mb" in ok[k] else ""
               for k in targets]
        ratio = apart = ""
        if len(ok) == 2:
            a, b = ok.values()
            ratio = f"{b['timings_s'][key] / a['timings_s'][key]:.2f}"
            apart = f"{max(_apart(a, b, m) for m in a['landmarks']):.1e}"
        rows.append([what, n, solver, *secs, *rss, ratio, apart])
        print(rows[-1], flush=True)
    write_section("targets", "\n".join(lines + table(head, rows)))
