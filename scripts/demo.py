#!/usr/bin/env python3
"""`make demo`: the built-in default case, class3-asym, treated with a typical double-jaw plan.

Mandible set back 5 mm and yawed 4 degrees back towards the midline, both maxilla halves
advanced 2 mm. Writes XDMF (open ``out/demo/deformed.xdmf`` in ParaView) and a JSON report.
Until planning lands, this shows the forward simulation of that treatment.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scripts import simulate  # noqa: E402
from scripts._common import run_main  # noqa: E402

TREATMENT = ["mandible.advance_mm=-5", "mandible.yaw_deg=-4", "maxilla_L.advance_mm=2",
             "maxilla_R.advance_mm=2"]

if __name__ == "__main__":
    args = ["--case", "class3-asym", "--resolution", "coarse", "--p", *TREATMENT,
            "--out", "out/demo", "--report", "out/demo/report.json", *sys.argv[1:]]
    sys.exit(run_main(lambda: simulate.main(args)))
