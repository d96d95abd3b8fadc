"""``bench.py validation``: the validation protocol's stages on Cranium (issue 29 §4).

A synthetic post-operative face scan: Cranium's scene (``ct_scene.py``, a fresh cache) is
moved by `P_STAR` in this process (the truth), and its skin made into a scan
(`meshes.surface.synthetic_scan`: subdivided, `NOISE_MM` of noise, misplaced by `MISPLACE`).
Then ``validate.py`` as a user runs it, on each number of ranks: the time of each stage
(loading the scene, the registration, the simulation, the comparison), the registration's
error against the known misplacement, and the prediction's error (the scan's noise, since the
movements are the truth).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from scripts._launch import mpirun
from scripts.bench_ct import CTS, _run

ROOT = Path(__file__).resolve().parents[1]
#: The truth's movements (a LeFort I advance with some impaction) and the scan's
#: misplacement (rotation vector degrees, mm) and noise (mm, a 3dMD camera's).
P_STAR = {"maxilla.advance_mm": 4.0, "maxilla.vertical_mm": -1.5}
MISPLACE = ((2.0, -1.5, 3.0), (4.0, -3.0, 2.5))
NOISE_MM = 0.2
#: validate.py's stages, in its report's order.
STAGES = ("scene", "registration", "simulation", "comparison", "total")


def _truth_scan(mesh: str, path: Path):
    """The scan of the truth at ``path``; returns (misplacement 4×4, rest skin (N, 3))."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from inverse.scene import Scene
    from inverse.validation import Skin
    from meshes.external import load_tet_mesh
    from meshes.surface import synthetic_scan, write_surface

    scene = Scene(lambda: load_tet_mesh(mesh), params_used=list(P_STAR))
    skin = Skin.of(scene)
    scene.solve(scene.param_vector(P_STAR))
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(np.radians(MISPLACE[0])).as_matrix()
    M[:3, 3] = MISPLACE[1]
    write_surface(path, *synthetic_scan(skin.at(scene), skin.tris, NOISE_MM, M))
    rest = skin.rest
    return M, rest


def validation(args) -> None:
    import numpy as np

    from scripts._bench import header, table, write_section

    ct_path, scene_file = CTS["cranium"][:2]
    rows = []
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                   ORTHODIFF_CACHE=cache)
        built = _run("ct_scene.py", ["--ct", str(ct_path), "--osteotomies", str(scene_file),
                                     "--resolution", args.resolution, "--out",
                                     str(Path(out) / "scene")], env)
        if "error" in built:
            raise SystemExit(f"ct_scene.py failed: {built['error']}")
        mesh = built["mesh"]
        scan = Path(out) / "post.ply"
        M, rest = _truth_scan(mesh, scan)
        for n in (int(k) for k in args.ranks.split(",")):
            rep = Path(out) / f"v{n}.json"
            r = subprocess.run(mpirun(n) + [
                sys.executable, str(ROOT / "scripts" / "validate.py"), "--mesh", mesh, "--post",
                str(scan), "--out", str(Path(out) / f"v{n}"),
                "--report", str(rep), "--p", *[f"{k}={v}" for k, v in P_STAR.items()]],
                capture_output=True, text=True, env=env)
            if r.returncode != 0:
                rows.append([n, "failed: " + (r.stderr.strip().splitlines() or [""])[-1]]
                            + [""] * (len(STAGES) + 4))
                continue
            v = json.loads(rep.read_text())
            TM = np.array(v["registration"]["transform"]) @ M
            off = np.linalg.norm(rest @ TM[:3, :3].T + TM[:3, 3] - rest, axis=1).max()
            angle = np.degrees(np.arccos(np.clip((np.trace(TM[:3, :3]) - 1) / 2, -1, 1)))
            e = v["error_mm"]
            rows.append([n, v["n_vertices"], *(f"{v['timings_s'][k]:.1f}" for k in STAGES),
                         f"{v['registration']['residual_mm']:.2f}", f"{angle:.3f}",
                         f"{off:.3f}", f"{e['mean']:.3f}", f"{e['within_1mm']:.3f}"])
            print(rows[-1], flush=True)
    body = header("Validation against the outcome (Cranium, a synthetic post-op scan)", args)
    body += [f"Cranium's scene at {args.resolution} size moved by "
             + ", ".join(f"`{k}={v:g}`" for k, v in P_STAR.items())
             + f" is the truth; its skin, subdivided, noised by {NOISE_MM:g} mm along the "
             f"normals and misplaced by {MISPLACE[0]} degrees (rotation vector) and "
             f"{MISPLACE[1]} mm, is the post-operative scan (`meshes.surface.synthetic_scan`). "
             "Each row: `scripts/validate.py --mesh --post --p` (the true movements) on that "
             "many ranks; its stages in seconds (the scene loaded, the registration, the "
             "simulation, the comparison, the whole run), the registration's residual on the "
             "stable skin, its error against the known misplacement (degrees; mm, the largest "
             "over the skin), and the prediction's mean error and share within 1 mm "
             "(the scan's noise: the movements are the truth).", ""]
    body += table(["ranks", "vertices", *(f"{k} s" for k in STAGES), "residual mm",
                   "registration error deg", "registration error mm", "mean error mm",
                   "within 1 mm"], rows)
    write_section("validation", "\n".join(body))
