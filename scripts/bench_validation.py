"""``bench.py validation``: the validation protocol's stages on Cranium (issue 29 §4).

Cranium's scene (``ct_scene.py``, a fresh cache) is moved by `P_STAR` in this process (the
truth), which makes two post-operative outcomes: a face scan of its skin
(`meshes.surface.synthetic_scan`: subdivided, `NOISE_MM` of noise, misplaced by `MISPLACE`)
and a CT (`inverse.postop.simulated_postop`: the CT warped by the outcome, misplaced the
same, `NOISE_HU` of noise). Then ``validate.py`` as a user runs it, on each number of ranks:
with the scan and the true movements, and with the CT and ``--measure-bone``; the time of
each stage, the registration's error against the known misplacement, the measured segments'
against their true motion, and the prediction's error; then each hostile post-operative CT
of the tests (`tests/hostile_postop.py`) with ``--measure-bone``.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from scripts._bench import run
from scripts.bench_ct import CTS

ROOT = Path(__file__).resolve().parents[1]
#: The truth's movements (a LeFort I advance with some impaction) and the outcome's
#: misplacement (rotation vector degrees, mm) and noise (mm, a 3dMD camera's; HU, a CT's).
P_STAR = {"maxilla.advance_mm": 4.0, "maxilla.vertical_mm": -1.5}
MISPLACE = ((2.0, -1.5, 3.0), (4.0, -3.0, 2.5))
NOISE_MM, NOISE_HU = 0.2, 20.0
#: validate.py's stages, in its report's order: with a face scan, with a CT.
STAGES = {"scan": ("scene", "registration", "simulation", "comparison", "total"),
          "ct": ("scene", "read", "registration", "measure_bone", "skin_surface", "simulation",
                 "comparison", "total")}


def _truth(mesh: str, ct_path, scene_file, out: Path) -> dict:
    """The outcomes ``out/post.ply`` and ``out/post.mha`` of the truth: the misplacement
    (4×4), the rest skin (N, 3), the segments' motions and bone points."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from inverse.postop import bone_surfaces, simulated_postop
    from inverse.scene import Scene
    from inverse.validation import Skin
    from meshes.ct import parse_scene_file
    from meshes.external import load_tet_mesh
    from meshes.surface import synthetic_scan, write_surface
    from meshes.volume import read_volume, write_volume

    scene = Scene(lambda: load_tet_mesh(mesh))
    skin, bones = Skin.of(scene), bone_surfaces(scene)
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(np.radians(MISPLACE[0])).as_matrix()
    M[:3, 3] = MISPLACE[1]
    p = scene.param_vector(P_STAR)
    write_volume(simulated_postop(scene, p, read_volume(ct_path),
                                  parse_scene_file(scene_file)[1], M, NOISE_HU),
                 out / "post.mha")
    write_surface(out / "post.ply", *synthetic_scan(skin.at(scene), skin.tris, NOISE_MM, M))
    return {"M": M, "rest": skin.rest, "motions": scene.transforms(p),
            "bones": {k: b.points for k, b in bones.items()}}


def _errors(T, points) -> tuple:
    """(degrees, largest displacement mm over points (K, 3)) of a 4×4 that should be I."""
    import numpy as np

    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
    return angle, np.linalg.norm(points @ T[:3, :3].T + T[:3, 3] - points, axis=1).max()


def _row(kind: str, n: int, v: dict, truth: dict) -> list:
    """A table row of validate.py's report ``v`` on n ranks."""
    import numpy as np

    reg = _errors(np.array(v["registration"]["transform"]) @ truth["M"], truth["rest"])
    row = [n, v["n_vertices"], *(f"{v['timings_s'][k]:.1f}" for k in STAGES[kind]),
           f"{v['registration']['residual_mm']:.2f}", f"{reg[0]:.3f}", f"{reg[1]:.3f}"]
    if kind == "ct":
        seg = np.max([_errors(np.linalg.inv(truth["motions"][k]) @ np.array(s["transform"]),
                              truth["bones"][k]) for k, s in v["segments"].items()], axis=0)
        row += [f"{seg[0]:.3f}", f"{seg[1]:.3f}"]
    e = v["error_mm"]
    return row + [f"{e['mean']:.3f}", f"{e['within_1mm']:.3f}"]


def _hostile(mesh: str, ct_path, scene_file, out: Path, env: dict) -> list:
    """Rows of validate.py --measure-bone (1 rank) on each hostile post-operative CT
    (`tests/hostile_postop.py`, the tests' construction): the registration's residual and
    condition, and each segment's error (RMS over its bone, mm) and condition."""
    import numpy as np

    sys.path.insert(0, str(ROOT / "tests"))
    from hostile_postop import VARIANTS, hostile_postop, rms_mm, truth

    from inverse.postop import bone_surfaces
    from inverse.scene import Scene
    from meshes.external import load_tet_mesh
    from meshes.volume import read_volume, write_volume

    bones = bone_surfaces(Scene(lambda: load_tet_mesh(mesh)))
    spec = json.loads(Path(scene_file).read_text())
    motions, M = truth(spec)
    pre, rows = read_volume(ct_path), []
    for name, kw in VARIANTS.items():
        post = out / "hostile.mha"
        write_volume(hostile_postop(pre, spec, motions, M, **kw), post)
        v = run("validate.py", ["--mesh", mesh, "--post", str(post), "--pre-ct", str(ct_path),
                                "--measure-bone", "--out", str(out / "hostile")], env=env)
        if "error" in v:
            rows.append([name, "failed: " + v["error"]])
            continue
        segs = v["segments"]
        errors = {k: rms_mm(np.array(s["transform"]), motions[k],
                            bones[k].points[np.unique(bones[k].tris)])
                  for k, s in segs.items()}
        rows.append([name, f"{v['registration']['residual_mm']:.2f}",
                     f"{v['registration']['condition']:.1f}",
                     ", ".join(f"{k} {e:.3f}" for k, e in errors.items()),
                     ", ".join(f"{k} {s['condition']:.1f}" for k, s in segs.items()),
                     f"{v['timings_s']['total']:.1f}"])
        print("hostile", rows[-1], flush=True)
    return rows


def validation(args) -> None:
    from scripts._bench import header, table, write_section

    ct_path, scene_file = CTS["cranium"][:2]
    rows = {"scan": [], "ct": []}
    movements = {"scan": ["--p", *[f"{k}={v}" for k, v in P_STAR.items()]],
                 "ct": ["--pre-ct", str(ct_path), "--measure-bone"]}
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        out = Path(out)
        env = {"ORTHODIFF_CACHE": cache}
        built = run("ct_scene.py", ["--ct", str(ct_path), "--osteotomies", str(scene_file),
                                    "--resolution", args.resolution, "--out",
                                    str(out / "scene")], env=env)
        if "error" in built:
            raise SystemExit(f"ct_scene.py failed: {built['error']}")
        mesh = built["mesh"]
        truth = _truth(mesh, ct_path, scene_file, out)
        for kind, post in (("scan", out / "post.ply"), ("ct", out / "post.mha")):
            for n in (int(k) for k in args.ranks.split(",")):
                rep = run("validate.py", ["--mesh", mesh, "--post", str(post), "--out",
                                          str(out / f"{kind}{n}"), *movements[kind]], n, env)
                if "error" in rep:
                    rows[kind].append([n, "failed: " + rep["error"]])
                    continue
                rows[kind].append(_row(kind, n, rep, truth))
                print(kind, rows[kind][-1], flush=True)
        hostile = _hostile(mesh, ct_path, scene_file, out, env)
    body = header("Validation against the outcome (Cranium, synthetic post-op scan and CT)",
                  args)
    body += [f"Cranium's scene at {args.resolution} size moved by "
             + ", ".join(f"`{k}={v:g}`" for k, v in P_STAR.items())
             + " is the truth. Its outcomes are misplaced by "
             f"{MISPLACE[0]} degrees (rotation vector) and {MISPLACE[1]} mm: a face scan (its "
             f"skin, subdivided, noised by {NOISE_MM:g} mm along the normals: "
             "`meshes.surface.synthetic_scan`) and a CT (Cranium warped by the outcome, noised "
             f"by {NOISE_HU:g} HU: `inverse.postop.simulated_postop`). Each row: "
             "`scripts/validate.py` on that many ranks; its stages in seconds, the "
             "registration's residual (on the stable skin; on the stable bone), its error "
             "against the known misplacement (degrees; mm, the largest over the skin), and "
             "the prediction's mean error and share within 1 mm.", "",
             "**A face scan, the true movements** (`--post post.ply --p ...`):", ""]
    common = ["residual mm", "registration error deg", "registration error mm"]
    body += table(["ranks", "vertices", *(f"{k} s" for k in STAGES["scan"]), *common,
                   "mean error mm", "within 1 mm"], rows["scan"])
    body += ["", "**A CT, the movements measured on it** (`--post post.mha --pre-ct "
             "Cranium.inv3 --measure-bone`; segment error: the worst segment's, degrees and mm "
             "over its bone):", ""]
    body += table(["ranks", "vertices", *(f"{k} s" for k in STAGES["ct"]), *common,
                   "segment error deg", "segment error mm", "mean error mm", "within 1 mm"],
                  rows["ct"])
    body += ["", "**Hostile post-operative CTs, the movements measured on them** (1 rank; "
             "`tests/hostile_postop.py`: each maxilla half's bone moved at the voxel level "
             "(advanced 3.5-4 mm, impacted 1.5-2 mm, pitched 1.5-2 degrees), its old place "
             "read as fluid, the soft tissue left where it was, then what each row names, "
             "misplaced and noised by 15 HU; a construction other than `simulated_postop`'s). "
             "Segment error: RMS over the segment's bone; condition: how well the bone "
             "determines the fit (`inverse.postop.fit_condition`, 1 for a sphere):", ""]
    body += table(["post-operative CT", "residual mm", "condition", "segment error mm",
                   "segment condition", "total s"], hostile)
    write_section("validation", "\n".join(body))
