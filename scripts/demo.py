#!/usr/bin/env python3
"""`make demo`: two stories, each the way a user chains the scripts.

1. **A real face**: Debian's Cranium CT (invesalius-examples, an upper face to the
   maxillary teeth), CT to scene at paper size (``ct_scene.py``, cached after the first
   run), then a LeFort I plan (``plan.py --goal midface-advance``): the advance that brings
   subnasale 3 mm forward (`inverse.targets.midface_advance`, held along the anterior axis
   only, its height free), in the head frame estimated on the CT. Writes
   ``out/demo/cranium/``. The plan moves the maxilla along the face's anterior axis only,
   and the model lifts the subnasal tissue 0.4 mm per mm advanced (BENCHMARKS.md, ct;
   published: little).
2. **The synthetic class III face**, the chin deviated to the right: the paper's story, a
   Sparse Gauss-Newton plan to its clinical goal (Arnett's true vertical line through Sn, the
   chin and lips on the mid-sagittal plane, Sn and tragion kept), the mandible held to the
   maxilla in the final occlusion and both moved as one unit (``--occlusion final``).
   Writes ``out/demo/class3-asym/``.

Each prints its landmark table before and after, the parameters found and the timings, and
writes the report (``report.json``), the face before and after (``before_after.png``), one
``<segment>.tfm`` per segment (3D Slicer) and the XDMF (``deformed.xdmf``, ParaView).
Extra arguments go to both plan.py runs (e.g. ``--resolution paper`` for the synthetic one).
"""

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from scripts import ct_scene, plan  # noqa: E402
from scripts._common import CRANIUM_CT as CRANIUM  # noqa: E402
from scripts._common import run_main  # noqa: E402

OUT = Path("out/demo")


def _story(title: str) -> None:
    print(f"\n{'=' * 78}\n{title}\n{'=' * 78}", flush=True)


def main(extra) -> int:
    from meshes.errors import InputError

    if not CRANIUM.exists():
        raise InputError(f"{CRANIUM} is absent: `make demo` installs Debian's "
                         "invesalius-examples")
    t0 = time.perf_counter()
    real = OUT / "cranium"
    _story("1. A real face: Debian's Cranium CT, a LeFort I advance to bring subnasale 3 mm "
           "forward")
    ct_scene.main(["--ct", str(CRANIUM), "--osteotomies",
                   str(ROOT / "meshes" / "examples" / "cranium.json"), "--resolution",
                   "paper", "--out", str(real), "--report", str(real / "ct.json")])
    plan.main(["--mesh", str(real / "scene.vtu"), "--goal", "midface-advance",
               "--params-used", "maxilla.advance_mm", "--out", str(real),
               "--picture", str(real / "before_after.png"), "--report",
               str(real / "report.json"), *extra])
    t1 = time.perf_counter()
    synthetic = OUT / "class3-asym"
    _story("2. The synthetic class III face, chin to the right: both jaws in the final "
           "occlusion")
    plan.main(["--case", "class3-asym", "--resolution", "coarse", "--occlusion", "final",
               "--out", str(synthetic), "--picture", str(synthetic / "before_after.png"),
               "--report", str(synthetic / "report.json"), *extra])
    print(f"\ndemo: the real face {t1 - t0:.1f} s, the synthetic face "
          f"{time.perf_counter() - t1:.1f} s; outputs in {real} and {synthetic}; "
          f"`make explore` opens the first in the browser")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(lambda: main(sys.argv[1:])))
