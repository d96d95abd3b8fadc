"""Scripts end to end: outputs, bad input (clear error, no files), MPI (1 vs 2 ranks)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SIM = [sys.executable, str(ROOT / "scripts" / "simulate.py"), "--case", "class3",
       "--resolution", "tiny", "--params-used",
       "mandible.advance_mm,mandible.yaw_deg,maxilla_L.advance_mm,maxilla_R.advance_mm"]
REPORT_KEYS = {"case", "resolution", "n_vertices", "n_cells", "n_ranks", "param_names",
               "params", "landmarks", "landmarks_rest", "active_goal_error_max_mm",
               "newton_iterations", "converged", "timings_s"}


def _run(cmd, **kw):
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600, **kw)


def _mpirun(n):
    exe = shutil.which("mpirun") or shutil.which("mpiexec")
    extra = ["--allow-run-as-root", "--oversubscribe"] if os.geteuid() == 0 else []
    return [exe, *extra, "-n", str(n)]


@pytest.mark.mpi
def test_simulate_same_on_1_and_2_ranks(tmp_path):
    reports = {}
    for n in (1, 2):
        out = tmp_path / f"n{n}"
        r = _run(_mpirun(n) + SIM + ["--p", "mandible.advance_mm=5", "mandible.yaw_deg=2",
                                     "--out", str(out), "--report", str(out / "r.json")])
        assert r.returncode == 0, r.stderr[-2000:]
        reports[n] = json.loads((out / "r.json").read_text())
        assert {"displacement.xdmf", "displacement.h5", "deformed.xdmf", "deformed.h5",
                "r.json"} == {p.name for p in out.iterdir()}
    assert REPORT_KEYS <= set(reports[1])
    assert set(reports[1]["timings_s"]) >= {"mesh", "compile", "assemble", "linear_solve",
                                            "total"}
    assert reports[2]["n_ranks"] == 2 and reports[1]["active_goal_error_max_mm"] < 0.05
    for name, x1 in reports[1]["landmarks"].items():
        x2 = reports[2]["landmarks"][name]
        np.testing.assert_allclose(x2, x1, rtol=1e-8, atol=1e-8 * 100)
    moved = np.subtract(reports[1]["landmarks"]["Pg"], reports[1]["landmarks_rest"]["Pg"])
    assert moved[1] > 3.0


@pytest.mark.parametrize("args,match", [
    (["--case", "class7"], "unknown case"),
    (["--p", "mandible.wiggle_mm=3"], "unknown parameter"),
    (["--p", "mandible.advance_mm=nan"], "finite"),
    (["--p", "mandible.advance_mm=abc"], "not a number"),
])
def test_simulate_bad_input_writes_nothing(tmp_path, args, match):
    out = tmp_path / "out"
    r = _run(SIM + args + ["--out", str(out), "--report", str(out / "r.json")])
    assert r.returncode == 2
    assert match in r.stderr
    assert not out.exists() or not any(out.iterdir())


def test_simulate_bad_params_file(tmp_path):
    bad = tmp_path / "p.json"
    bad.write_text("{not json")
    r = _run(SIM + ["--params", str(bad), "--report", str(tmp_path / "r.json")])
    assert r.returncode == 2 and "cannot read parameter file" in r.stderr
    assert not (tmp_path / "r.json").exists()


def test_list_params():
    r = _run([sys.executable, str(ROOT / "scripts" / "simulate.py"), "--case", "class3",
              "--resolution", "tiny", "--list-params"])
    assert r.returncode == 0
    assert "mandible.advance_mm" in r.stdout and "maxilla_R.yaw_deg" in r.stdout


def test_readme_example_runs(tmp_path):
    """The README's Python example, run as written (so it never goes stale)."""
    text = (ROOT / "README.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    code = code.replace('"coarse"', '"tiny"')   # the same example on the test mesh
    r = _run([sys.executable, "-c", code], cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Pg" in r.stdout
