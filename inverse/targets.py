"""Clinical construction rules: landmark targets from a face's rest geometry (mm).

Axes: the head frame's (`meshes.frame`): +x patient's left, +y anterior, +z superior, with
the Frankfort horizontal and the mid-sagittal plane as the reference planes, where every
cephalometric norm and the true vertical are defined. Each rule takes and returns head-frame
points ``{name: (3,)}``; `default_targets` maps a scene's points in and out.

* `true_vertical_line` - Arnett's soft-tissue cephalometric analysis (Arnett et al., Am J
  Orthod Dentofacial Orthop 1999;116:239-253): with the head in natural position, the true
  vertical line (TVL) through subnasale Sn is the reference for the anterior-posterior
  position of the lower face. Norms (mean of the male and female values): upper lip Ls
  +3.5 mm, lower lip Li +1.9 mm, soft-tissue pogonion Pg -2.6 mm (behind the TVL). Menton
  Me moves with the chin (the same A-P correction as Pg). Only y changes.
* `e_line` - Ricketts' esthetic line from the nose tip Prn to Pg (Ricketts, Angle Orthod
  1957;27:14-37 and 1968): the upper lip lies ~4 mm and the lower lip ~2 mm behind it in the
  profile (y-z) view. The lips move along y only.
* `symmetry` - facial symmetry for asymmetric cases: Pg, the lip midpoints Ls, Li and Me are
  moved onto the mid-sagittal plane (x of N and Sn, the upper face that surgery does not move),
  and the tragion line T_L-T_R is levelled (both at their mean height).
* `keep` - the named landmarks stay where they are (e.g. Sn: do not advance the nose base).
* `midface_advance` - a retruded midface brought forward by a LeFort I: subnasale Sn
  `MIDFACE_ADVANCE_MM` anterior, held along the anterior axis only, as the true vertical
  line measures it (mild maxillary hypoplasia is corrected by 3-6 mm of advance, and Sn
  follows the bone at 0.5-0.9, San Miguel Moragas et al. 2014). Sn's height and the nasal
  tip are left free: the plan must not steer the maxilla by the nose, whose elevation the
  model overestimates (BENCHMARKS.md, ct; so does Sn's, which is why `make demo` plans the
  advance alone). For scenes with a midface and no mandible, such as Debian's Cranium CT
  (`make demo`).

A rule's target is a head-frame point, held along every axis, or ``{"at": point, "along":
[axis, ...]}`` held along the named axes only (`inverse.objective.load_targets`).

`DEFAULT_GOALS` composes them per case: class2 uses 3 landmarks, class3-asym 7 (paper 3.2);
``midface-advance`` and ``e-line`` are goals by name (``plan.py --goal``).
"""

from __future__ import annotations

import numpy as np

from meshes.errors import InputError

TVL_NORMS_MM = {"Ls": 3.5, "Li": 1.9, "Pg": -2.6}
E_LINE_MM = {"Ls": -4.0, "Li": -2.0}


def true_vertical_line(rest: dict, names=("Ls", "Li", "Pg", "Me")) -> dict:
    """Targets on Arnett's norms relative to the true vertical through Sn (y only)."""
    y0 = rest["Sn"][1]
    out = {}
    for n in names:
        x = np.array(rest[n], dtype=float)
        if n == "Me":
            x[1] += y0 + TVL_NORMS_MM["Pg"] - rest["Pg"][1]
        else:
            x[1] = y0 + TVL_NORMS_MM[n]
        out[n] = x
    return out


def e_line(rest: dict) -> dict:
    """Ls and Li at Ricketts' distances behind the Prn-Pg line, in the y-z profile."""
    a, b = np.asarray(rest["Prn"])[1:], np.asarray(rest["Pg"])[1:]
    t = (b - a) / np.linalg.norm(b - a)
    nrm = np.array([t[1], -t[0]])          # perpendicular to the line
    if nrm[0] < 0:
        nrm = -nrm                         # pointing anterior (+y)
    out = {}
    for n, d in E_LINE_MM.items():
        x = np.array(rest[n], dtype=float)
        # signed distance now, then move along y to reach d
        now = float((x[1:] - a) @ nrm)
        x[1] += (d - now) / nrm[0]
        out[n] = x
    return out


def symmetry(rest: dict, names=("Ls", "Li", "Pg", "Me")) -> dict:
    """Midline landmarks onto the mid-sagittal plane; tragion line levelled."""
    x_mid = 0.5 * (rest["N"][0] + rest["Sn"][0])
    out = {}
    for n in names:
        x = np.array(rest[n], dtype=float)
        x[0] = x_mid
        out[n] = x
    if "T_L" in rest and "T_R" in rest:
        z = 0.5 * (rest["T_L"][2] + rest["T_R"][2])
        for n in ("T_L", "T_R"):
            out[n] = np.array(rest[n], dtype=float)
            out[n][2] = z
    return out


def keep(rest: dict, names) -> dict:
    return {n: np.array(rest[n], dtype=float) for n in names}


def compose(rest: dict, *parts) -> dict:
    """Merge rule outputs: each coordinate of a landmark comes from the rule that moved it
    away from rest (the last one, if several did)."""
    out = {}
    for part in parts:
        for n, x in part.items():
            base = out.get(n, np.array(rest[n], dtype=float))
            out[n] = np.where(np.isclose(x, rest[n]), base, x)
    return out


MIDFACE_ADVANCE_MM = 3.0


def midface_advance(rest: dict) -> dict:
    """Sn `MIDFACE_ADVANCE_MM` anterior, held along the anterior axis only: its height is
    the surgeon's other choice (a target at rest height asks the LeFort I to hold Sn's
    elevation, which the model overestimates, and stops the advance short)."""
    sn = np.array(rest["Sn"], dtype=float)
    sn[1] += MIDFACE_ADVANCE_MM
    return {"Sn": {"at": sn, "along": ["anterior"]}}


DEFAULT_GOALS = {
    "class1": lambda r: true_vertical_line(r, ("Ls", "Li", "Pg")),
    "class2": lambda r: true_vertical_line(r, ("Li", "Pg", "Me")),
    "class3": lambda r: true_vertical_line(r, ("Ls", "Li", "Pg", "Me")),
    "class3-asym": lambda r: compose(r, keep(r, ("Sn", "T_L", "T_R")),
                                     true_vertical_line(r), symmetry(r)),
    "midface-advance": midface_advance,
    "e-line": e_line,
}
#: The landmarks each goal needs.
GOAL_LANDMARKS = {"midface-advance": ("Sn",), "e-line": ("Prn", "Pg", "Ls", "Li")}


def default_targets(case: str, rest: dict, frame=None) -> dict:
    """A built-in treatment goal (a case's, or a named one of `DEFAULT_GOALS`),
    ``{name: entry}`` in the scene's frame (`inverse.objective.load_targets`: ``[x, y, z]``
    mm, or ``{"at": [x, y, z], "along": [axis, ...]}``), from rest landmarks in it; the rules
    apply in the head frame ``frame`` (`meshes.frame.HeadFrame`; None: the scene's frame is
    the head's)."""
    if case not in DEFAULT_GOALS:
        raise InputError(f"no built-in goal {case!r}; give targets, or one of "
                         f"{sorted(DEFAULT_GOALS)}")
    missing = [n for n in GOAL_LANDMARKS.get(case, ("N", "Sn", "Pg", "Prn")) if n not in rest]
    if missing:
        raise InputError(f"the goal {case!r} needs landmarks {missing}")
    from meshes.frame import HeadFrame

    frame = frame or HeadFrame.identity()
    head = {n: frame.to_head(x) for n, x in rest.items()}
    out = {}
    for n, x in DEFAULT_GOALS[case](head).items():
        held = isinstance(x, dict)
        point = frame.to_scene(x["at"] if held else x).tolist()
        out[n] = {"at": point, "along": list(x["along"])} if held else point
    return out
