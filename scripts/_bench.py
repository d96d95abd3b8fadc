"""Shared by the benchmarks (``scripts/bench*.py``): the machine line, a fresh script process
per configuration, the BENCHMARKS.md sections, tables and plots.
"""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts._launch import mpirun  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


BENCH_MD = ROOT / "BENCHMARKS.md"


DOCS = ROOT / "docs"


#: The fixed class3 treatment of the accuracy study (NAME=VALUE, mm).
TREATMENT = ["mandible.advance_mm=5", "mandible.lateral_mm=1", "maxilla_L.advance_mm=2",
             "maxilla_R.advance_mm=2"]


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB, {platform.platform()}"


def run(script: str, args: list, n: int = 1, env: dict | None = None,
        timeout: float | None = None, python: str | None = None) -> dict:
    """A fresh ``scripts/<script>`` process with ``args`` on n ranks, by ``python`` (default:
    this interpreter; its own MPI's launcher), one thread per rank, ``env`` added to this
    environment: its ``--report``, or {"error": its last stderr line}."""
    python = python or sys.executable
    with tempfile.TemporaryDirectory() as d:
        rep = Path(d) / "r.json"
        cmd = [*mpirun(n, python), python, str(ROOT / "scripts" / script), *args,
               "--report", str(rep)]
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", **(env or {}))
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
        except subprocess.TimeoutExpired:
            return {"error": f"not solved within {timeout:g} s (stopped)"}
        if r.returncode != 0:
            return {"error": (r.stderr.strip().splitlines() or ["failed"])[-1]}
        return json.loads(rep.read_text())


def simulate(res: str, solver: str, n: int, extra=()) -> dict:
    """`run` of simulate.py on n ranks: class3 at ``res`` with ``solver``, a 5 mm BSSO advance,
    then ``extra``."""
    return run("simulate.py", ["--case", "class3", "--resolution", res, "--solver", solver,
                               "--p", "mandible.advance_mm=5", *extra], n)


def worker(path, n: int, *args) -> dict:
    """Run the benchmark module ``path`` as a worker under ``mpirun -n n`` with ``args``:
    the JSON its rank 0 printed after ``RESULT`` (`result`), or {"error": its last stderr
    line}."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    r = subprocess.run([*mpirun(n), sys.executable, str(path), *map(str, args)],
                       capture_output=True, text=True, encoding="utf-8", errors="replace",
                       env=env)
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
    if line is None:
        return {"error": (r.stderr.strip().splitlines() or ["failed"])[-1][:80]}
    return json.loads(line[7:])


def result(out: dict, comm) -> None:
    """A worker's answer, printed by rank 0 for `worker`."""
    if comm.rank == 0:
        print("RESULT " + json.dumps(out), flush=True)


#: A plan's solves in plan.py's ``timings_s``: issue 30's plan / forward ratio.
PLAN_WORK = ("forward", "adjoint", "sensitivity", "line_search")


def plan_work(report: dict) -> float:
    """The seconds a plan.py report spent solving (`PLAN_WORK`)."""
    return sum(report["timings_s"][k] for k in PLAN_WORK)


#: BENCHMARKS.md's sections in the report's order (their markers) and the subcommand that
#: writes each; ``bench.py all`` runs them all.
SECTIONS = {"forward": "forward", "stress": "stress", "plan": "plan", "peers": "peers",
            "accuracy-mesh": "accuracy", "accuracy-ct": "accuracy", "accuracy-order": "accuracy",
            "accuracy-tolerance": "accuracy", "accuracy-tolerance-qn": "accuracy",
            "accuracy-prediction": "accuracy", "accuracy-gradient": "accuracy",
            "plausibility": "plausibility", "ct": "ct", "validation": "validation",
            "explorer": "explorer", "bands": "bands", "targets": "targets"}

INTRO = """# Benchmarks

Written whole by `python3 scripts/bench.py all`; each subcommand rewrites its own sections and
this file around them, so nothing here is older than its section's command. Each section
gives its command, the machine, one table of the current code and its plot (under `docs/`).
The goals table is collected from the sections. What was tried and dropped is in
[docs/decisions.md](docs/decisions.md). The machine is noisy: compare figures within one
section, which is one run."""

_BLOCK = re.compile(r"<!-- ([a-z-]+) -->\n(.*?)\n<!-- /\1 -->", re.S)
_GOALS = re.compile(r"^<!-- goals: (.*) -->$", re.M)


def goal(name: str, value: float, unit: str, limit: float | None = None,
         peer: float | None = None, source: str = "", note: str = "") -> dict:
    """One row of the goals table: orthodiff's ``value`` (unit) against an upper ``limit``
    (met or missed, by how much) or a ``peer``'s figure measured in the same run (the speed-up);
    ``source`` says whose target it is (the paper, an issue), ``note`` adds to the figure."""
    if limit is not None:
        target, r = f"≤ {limit:g} {unit}" + (f" ({source})" if source else ""), value / limit
        ratio = f"{r:.2f}: met" if r <= 1 else f"{r:.2f}: **missed**"
    else:
        target = f"{peer:.3g} {unit}" + (f" ({source})" if source else "")
        ratio = f"**{peer / value:.1f}x faster**"
    return {"goal": name, "target": target, "orthodiff": f"{value:.3g} {unit}".strip()
            + (f", {note}" if note else ""), "ratio": ratio}


def write_section(name: str, body: str, goals=()) -> None:
    """Replace the section ``name`` (a key of `SECTIONS`) and write BENCHMARKS.md whole:
    `INTRO`, the goals table of every section's ``goals`` (`goal` rows), then the sections in
    `SECTIONS` order. Text outside the sections is not kept. Atomic."""
    if name not in SECTIONS:
        raise ValueError(f"unknown BENCHMARKS.md section {name!r}")
    text = BENCH_MD.read_text(encoding="utf-8") if BENCH_MD.exists() else ""
    blocks = {m.group(1): m.group(2) for m in _BLOCK.finditer(text) if m.group(1) in SECTIONS}
    blocks[name] = body.rstrip() + ("\n\n<!-- goals: " + json.dumps(list(goals)) + " -->"
                                    if goals else "")
    rows = [[g["goal"], g["target"], g["orthodiff"], g["ratio"]]
            for s in SECTIONS if s in blocks for m in _GOALS.finditer(blocks[s])
            for g in json.loads(m.group(1))]
    parts = [INTRO, "\n".join(["## Goals", "", "Each row from the section named in its goal; "
                               "a peer's figure is from the same run as orthodiff's.", "",
                               *table(["goal", "target", "orthodiff", "ratio"], rows)])]
    parts += [f"<!-- {s} -->\n{blocks[s]}\n<!-- /{s} -->" for s in SECTIONS if s in blocks]
    tmp = BENCH_MD.with_suffix(".md.part")
    tmp.write_text("\n\n".join(parts) + "\n", encoding="utf-8")
    os.replace(tmp, BENCH_MD)


def plot(name: str, draw) -> str:
    """Draw with ``draw(plt)`` and save ``docs/<name>.png`` atomically; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    DOCS.mkdir(exist_ok=True)
    draw(plt)
    plt.tight_layout()
    tmp = DOCS / f".{name}.part.png"
    plt.savefig(tmp, dpi=110)
    plt.close("all")
    os.replace(tmp, DOCS / f"{name}.png")
    return f"docs/{name}.png"


def series_plot(name: str, series: dict, xlabel: str, ylabel: str, logx: bool = False,
                logy: bool = True, goal_line: float | None = None) -> str:
    """Lines of ``series`` ({label: [(x, y)]}; x numbers, or names such as resolutions, drawn
    in their first order) with a dotted goal line at ``goal_line``, saved as
    ``docs/<name>.png`` (`plot`); returns its path."""
    names = list(dict.fromkeys(x for pts in series.values() for x, _ in pts
                               if isinstance(x, str)))

    def draw(plt):
        plt.figure(figsize=(6, 3.8))
        plt.xscale("log" if logx and not names else "linear")
        plt.yscale("log" if logy else "linear")
        for label, pts in series.items():
            plt.plot([names.index(x) if names else x for x, _ in pts], [y for _, y in pts],
                     "o-", label=label)
        if names:   # after the scales: setting one resets the ticks
            plt.xticks(range(len(names)), names)
        if goal_line is not None:
            plt.axhline(goal_line, color="k", ls=":", label="goal")
        plt.xlabel(xlabel)
        plt.ylabel(ylabel)
        plt.legend(fontsize=7)
    return plot(name, draw)


def ranks_label(n: int) -> str:
    return f"{n} rank{'s' * (n > 1)}"


def command(args) -> str:
    """The bench.py command line that ran this benchmark (``args.argv``, set by bench.py)."""
    return "python3 scripts/bench.py " + " ".join(getattr(args, "argv", [args.what]))


def header(title: str, args) -> list:
    return [f"## {title}", "", f"Command: `{command(args)}`", "", f"Machine: {machine()}.", ""]


def table(head: list, rows: list) -> list:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head),
            *("| " + " | ".join(map(str, r)) + " |" for r in rows)]


def landmark_motion(report: dict) -> dict:
    """{landmark: (3,) displacement, mm} from a simulate.py report."""
    import numpy as np

    return {n: np.subtract(x, report["landmarks_rest"][n]) for n, x in report["landmarks"].items()}


def fd_gradient(scene, obj, h: float):
    """Forward-difference dT/dp (Np,): Np warm forward solves from the current equilibrium,
    which is restored afterwards."""
    import numpy as np

    base = scene.eq.snapshot()
    p, T0 = scene.eq.p.copy(), obj.value()
    fd = np.empty(len(p))
    for i in range(len(p)):
        scene.solve(p + h * np.eye(len(p))[i])
        fd[i] = (obj.value() - T0) / h
        scene.eq.restore(base)
    return fd


def prediction_errors(scene, mags) -> list:
    """Plain and corrected first-order skin predictions against true equilibria, for
    the mandible advanced by m and shifted 0.3 m (mm), m in ``mags``, from the scene's
    equilibrium p0."""
    import time

    import numpy as np

    from inverse.explore import SkinPredictor

    base, rows = scene.eq.snapshot(), []
    names = scene.param_names
    for mag in mags:
        scene.eq.restore(base)
        pred = SkinPredictor(scene)   # K(p0) factorised again: the previous m replaced it
        dp = np.zeros(len(names))
        dp[names.index("mandible.advance_mm")] = mag
        dp[names.index("mandible.lateral_mm")] = 0.3 * mag
        t = time.perf_counter()
        for _ in range(100):
            plain = pred.predict(dp)
        t_plain = (time.perf_counter() - t) / 100
        t = time.perf_counter()
        corr, _ = pred.corrected(dp)
        t_corr = time.perf_counter() - t
        try:
            t = time.perf_counter()
            scene.solve(pred.p0 + dp)
            t_true = time.perf_counter() - t
        except Exception as e:  # report, do not stop the benchmark
            rows.append(dict(mag=mag, error=str(e)[:80]))
            pred.destroy()
            continue
        true = pred.op.apply(scene.eq.u_eq.array)
        scene.eq.restore(base)
        pred.destroy()
        rows.append(dict(mag=mag, disp=np.linalg.norm(true - pred.x0, axis=1).max(),
                         plain=np.linalg.norm(plain - true, axis=1).max(),
                         corr=np.linalg.norm(corr - true, axis=1).max(),
                         t_plain_ms=1e3 * t_plain, t_corr=t_corr, t_true=t_true))
    return rows


#: How the benchmarks' corrected prediction is made and timed.
CORRECTED = ("Corrected (`SkinPredictor.corrected`): continuation on the kept factorisation "
             "of K(p0), in substeps whose first-order step moves no vertex more than "
             "`CORRECTION_SUBSTEP_MM` = 4 mm, each started from the secant extrapolation of "
             "the last two (the first: first-order) and relaxed by `CORRECTION_ITERATIONS` = 6 "
             "quasi-Newton steps, the L-BFGS pairs kept from substep to substep; no assembly "
             "of K, no factorisation (a fresh predictor for each m, so every correction and "
             "true solve starts from the factorisation at p0).")
