#!/usr/bin/env python3
"""`make demo`: the paper's story on the built-in default case, class3-asym.

A class III face with the chin deviated to the right; the clinical goal (Arnett's true
vertical line through Sn, the chin and lips on the mid-sagittal plane, Sn and tragion kept:
7 landmarks, `inverse.targets`); the Sparse Gauss-Newton plan from p = 0, planned the way a
surgeon plans: the mandible held to the maxilla in the final occlusion and both moved as
one unit (``--occlusion final``, the six ``jaws.*`` motions); the landmark table before and
after, the parameters found and the timings. Writes ``out/demo/deformed.xdmf`` (open in
ParaView), ``out/demo/displacement.xdmf``, ``out/demo/report.json``,
``out/demo/before_after.png`` and one ``out/demo/<segment>.tfm`` per segment (3D Slicer).
Extra arguments go to scripts/plan.py (e.g. ``--resolution paper``).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts import plan  # noqa: E402
from scripts._common import run_main  # noqa: E402

if __name__ == "__main__":
    args = ["--case", "class3-asym", "--resolution", "coarse", "--occlusion", "final",
            "--out", "out/demo", "--picture", "out/demo/before_after.png",
            "--report", "out/demo/report.json", *sys.argv[1:]]
    sys.exit(run_main(lambda: plan.main(args)))
