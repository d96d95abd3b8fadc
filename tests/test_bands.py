"""Bands and robust plans through the scripts (issue 46): ``plan.py --robust``'s expected
objective against the report's own bands, and bad input."""

import json
import sys

import numpy as np
from test_scripts import PLAN, _one_line_error, _run

from inverse.uncertainty import BAND_ACCURACY

#: The tests' tier (conftest.py).
TIER = "scripts"

AXES = ["left", "anterior", "superior"]


def test_robust_plan_reports_its_expected_objective(tmp_path):
    """class3-asym's default goal: E[T]'s band part is ½ Σ w sd² over the held axes of the
    report's bands (two code paths: block CG to BAND_RTOL, and exact solves); the robust
    plan's E[T] is at most the nominal one's, and it stays near it."""
    rep = tmp_path / "r.json"
    r = _run(PLAN + ["--robust", "--max-iterations", "4", "--report", str(rep)])
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads(rep.read_text())
    robust, bands = report["robust"], report["bands"]["landmarks"]
    band = 0.5 * sum(bands[n]["sd_mm"][AXES.index(a)] ** 2
                     for n, v in report["landmarks"].items() for a in v["along"])
    assert band > 0
    assert abs(robust["expected_T_mm2"]["band"] - band) < 2 * BAND_ACCURACY * band
    assert robust["expected_T_mm2"]["total"] <= robust["expected_T_nominal_mm2"]["total"]
    moved = np.array(list(robust["moved"].values()))
    assert np.all(np.isfinite(moved)) and np.abs(moved).max() < 1.0, robust["moved"]
    assert report["params_optimal"] == robust["params_nominal"]
    assert "robust plan: expected T" in r.stdout


def test_robust_needs_the_prior_and_a_prior_needs_spreads(tmp_path):
    out = tmp_path / "out"
    r = _run(PLAN + ["--robust", "--no-bands", "--report", str(out / "r.json")])
    _one_line_error(r, "--robust needs the tissue's prior")
    (tmp_path / "prior.json").write_text(json.dumps({"skin": {"sd_log_E": 0}}))
    r = _run([sys.executable] + PLAN[1:] + ["--prior", str(tmp_path / "prior.json"),
                                            "--report", str(out / "r.json")])
    _one_line_error(r, "skin.log_E must be positive")
    assert not out.exists()
