"""``bench.py plausibility``: soft-to-hard movement ratios of the synthetic faces against the
clinical literature (issue 15 §4).

For every case, resolution, contact of the tissue on the teeth (glued, sliding) and material
(homogeneous, tissues), two treatments from rest, each a fresh ``scripts/simulate.py``:
a 5 mm BSSO advance (``mandible.advance_mm``) and a 5 mm LeFort I advance en bloc
(``maxilla.advance_mm``). A ratio is the landmark's forward motion (+y of the head frame,
`meshes.frame`) over the bone's 5 mm (a translation: incisors, B and A points, bony pogonion
all move 5 mm); the nasal tip's elevation (+z) is reported beside its forward ratio.
"""

from __future__ import annotations

#: (treatment parameter, landmark, axis, published range, source)
RATIOS = [
    ("mandible.advance_mm", "Pg", 1, (0.9, 1.0), "Joss et al. 2010 (review)"),
    ("mandible.advance_mm", "Li", 1, (0.6, 0.9), "Joss et al. 2010; Lee et al. 2018: 66 %"),
    ("maxilla.advance_mm", "Sn", 1, (0.5, 0.9), "San Miguel Moragas et al. 2014 (review)"),
    ("maxilla.advance_mm", "Ls", 1, (0.2, 0.9), "San Miguel Moragas 2014; Lee 2018: 21 %"),
    ("maxilla.advance_mm", "Prn", 1, (0.13, 0.33), "Lee et al. 2018: 17 %"),
    ("maxilla.advance_mm", "Prn", 2, None, "little elevation"),
]
MOVE_MM = 5.0


def ratios(simulate, case: str, res: str, model: list) -> tuple[dict, dict]:
    """({(param, landmark, axis): ratio}, {param: forward s}) from two simulate.py runs
    (``simulate(args)``) with the options ``model`` (e.g. ``["--contact", "glued"]``)."""

    out, times = {}, {}
    for param in dict.fromkeys(r[0] for r in RATIOS):
        rep = simulate(["--case", case, "--resolution", res, "--params-used",
                        "mandible.advance_mm,maxilla.advance_mm", *model, "--p",
                        f"{param}={MOVE_MM}"])
        if "error" in rep:
            raise SystemExit(f"{case}/{res} {param}: {rep['error']}")
        times[param] = rep["timings_s"]["total"]
        for p, lm, axis, _, _ in RATIOS:
            if p == param:
                out[(p, lm, axis)] = head_motion(rep, lm, axis) / MOVE_MM
    return out, times


def head_motion(rep: dict, landmark: str, axis: int) -> float:
    """A landmark's motion (mm) in a simulate.py report along the head frame's axis ``axis``
    (1 anterior, 2 superior; `meshes.frame`), whatever the scene's frame."""
    import numpy as np

    d = np.subtract(rep["landmarks"][landmark], rep["landmarks_rest"][landmark])
    return float(d @ np.asarray(rep.get("head_frame", np.eye(4)))[:3, axis])


def plausibility(args) -> None:
    from meshes.synthetic import CASES, GENERATOR_VERSION, Z_LEFORT
    from scripts._bench import header, run, table, write_section

    cases = args.cases.split(",") if args.cases else sorted(CASES)
    models = [(c, m) for m in args.materials.split(",") for c in args.contacts.split(",")]
    head = ["treatment", "landmark", "published", "source"]
    cols, rows = [], {i: [] for i in range(len(RATIOS))}
    time_rows = {k: [] for k in ("BSSO 5 mm forward s", "LeFort I 5 mm forward s",
                                 "plan to the case's goal s")}
    for res in args.resolutions.split(","):
        for case in cases:
            for contact, material in models:
                cols.append(f"{case} {res} {contact} {material}")
                model = ["--contact", contact, "--material", material]
                r, times = ratios(lambda a: run("simulate.py", n=1, args=a), case, res,
                                  model)
                for i, (p, lm, axis, rng, _) in enumerate(RATIOS):
                    v = r[(p, lm, axis)]
                    ok = rng is None or rng[0] <= v <= rng[1]
                    rows[i].append(f"{v:.2f}" if ok else f"**{v:.2f}** ✗")
                plan = run("plan.py", n=1, args=[
                    "--case", case, "--resolution", res, *model])
                fwd = [f"{times[p]:.1f}" for p in ("mandible.advance_mm", "maxilla.advance_mm")]
                for key, v in zip(time_rows, fwd + [
                        plan.get("error", "")[:30] if "error" in plan else
                        f"{plan['timings_s']['total']:.1f}"]):
                    time_rows[key].append(v)
                print(res, case, contact, material, {k: round(v, 2) for k, v in r.items()}, fwd,
                      flush=True)
    body = header("Plausibility: soft-to-hard movement ratios (synthetic faces)", args) + [
        "Each column: a 5 mm BSSO advance (`mandible.advance_mm=5`) and a 5 mm LeFort I "
        "advance (`maxilla.advance_mm=5`) from rest, one `scripts/simulate.py` each, with the "
        "tissue on the teeth `--contact glued` (the paper's model) or `sliding` (the "
        "default of CT scenes: `meshes.teeth`, docs/decisions.md), and the paper's "
        "`--material homogeneous` or `tissues` (skin, fat and lean tissue per cell: "
        "`meshes.tissue`, `fem.material.Tissues`); a ratio is the soft-tissue "
        "landmark's forward motion over the bone's 5 mm (the nasal tip's elevation on the "
        "last row). ✗: outside the published range. Below the ratios: the two advances' "
        "times and `scripts/plan.py` to the case's built-in goal (one process each, 1 "
        "rank).", "",
        f"Generator version {GENERATOR_VERSION}: the LeFort I cut runs below the piriform rim "
        f"(z = {Z_LEFORT:g} mm), so the nose sits on bone that does not move; each jaw's "
        "crowns and vestibule are its teeth; each cell has its skin, fat and lean tissue "
        "(version 5). What the cut through the nasal base (version 2) "
        "gave, and what the change did to the forward solve and the plan: "
        "docs/decisions.md, with its command.", ""]
    body += table(head + cols, [
        [p.split(".")[0] + (" advance"), lm + (" up" if axis == 2 else " fwd"),
         "—" if rng is None else f"{rng[0]:g}–{rng[1]:g}", src, *rows[i]]
        for i, (p, lm, axis, rng, src) in enumerate(RATIOS)] + [
        ["time", key, "", "", *vals] for key, vals in time_rows.items()])
    write_section("plausibility", "\n".join(body))
