"""The CT pipeline (issue 16): a CT made from a synthetic head against that head, the two real
CTs through the scripts as a user chains them, and every bad input's one-line error."""

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from test_scripts import ROOT, _mpirun, _one_line_error, _run

from scripts._common import CRANIUM_CT, HEADSQ_CT

#: The tests' tier (conftest.py): CTs to scenes through the scripts.
TIER = "scripts"
#: CT scenes, meshed by CGAL (conftest.py skips them without pygalmesh).
pytestmark = pytest.mark.cgal

#: ct_scene.py at coarse, the tests' size, unless a test gives its own --resolution (the last
#: one given wins); a user's default is `meshes.ct.DEFAULT_RESOLUTION`.
CT_SCENE = [sys.executable, str(ROOT / "scripts" / "ct_scene.py"), "--resolution", "coarse"]
SIMULATE = [sys.executable, str(ROOT / "scripts" / "simulate.py")]
PLAN = [sys.executable, str(ROOT / "scripts" / "plan.py")]
VALIDATE = [sys.executable, str(ROOT / "scripts" / "validate.py")]
HEADSQ, CRANIUM = HEADSQ_CT, CRANIUM_CT
EXAMPLES = ROOT / "meshes" / "examples"
REPORT_KEYS = {"mesh", "n_vertices", "n_cells", "segments", "landmarks", "min_quality",
               "timings_s"}
#: The voxel of the CT made from the synthetic head (mm): 1.5 voxels is the landmark bound.
VOXEL_MM = 1.25

needs_headsq = pytest.mark.skipif(not HEADSQ.exists(), reason=f"{HEADSQ} is absent (the "
                                  "shared data folder is not beside the project)")
needs_cranium = pytest.mark.skipif(not CRANIUM.exists(), reason=f"{CRANIUM} is absent "
                                   "(Debian's invesalius-examples; `make test` installs it)")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A fresh mesh cache for this module's CT scenes."""
    path = tmp_path_factory.mktemp("cache")
    old = os.environ.get("ORTHODIFF_CACHE")
    os.environ["ORTHODIFF_CACHE"] = str(path)
    yield path
    if old is None:
        del os.environ["ORTHODIFF_CACHE"]
    else:
        os.environ["ORTHODIFF_CACHE"] = old


@pytest.fixture(scope="module")
def synthetic_ct(tmp_path_factory):
    """class1 voxelised at VOXEL_MM (.mha) and its scene file: (ct path, scene file)."""
    from meshes.synthetic import synthetic_ct, synthetic_scene_file
    from meshes.volume import write_volume

    d = tmp_path_factory.mktemp("synthetic_ct")
    write_volume(synthetic_ct("class1", VOXEL_MM), d / "class1.mha")
    (d / "class1.json").write_text(json.dumps(synthetic_scene_file("class1")))
    return d / "class1.mha", d / "class1.json"


def moved_spec(spec: dict, R, t, centre) -> dict:
    """The scene file with its cuts (`meshes.osteotomy.PLANES`) moved by
    x -> R (x - centre) + centre + t, its crop the moved box's bounds."""
    from meshes.osteotomy import PLANES

    spec = json.loads(json.dumps(spec))
    for k in (k for k in PLANES if k in spec):
        spec[k] = {"point": (R @ (np.array(spec[k]["point"]) - centre) + centre + t).tolist(),
                   "normal": (R @ np.array(spec[k]["normal"], float)).tolist()}
    lo, hi = np.array(spec["crop"]["min"]), np.array(spec["crop"]["max"])
    box = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                    for c in (lo[2], hi[2])])
    box = (box - centre) @ R.T + centre + t
    spec["crop"] = {**spec["crop"], "min": box.min(0).tolist(), "max": box.max(0).tolist()}
    return spec


def _ct_scene(tmp_path, ct, scene, *extra, resolution="coarse"):
    out = tmp_path / "scene"
    r = _run(CT_SCENE + ["--ct", str(ct), "--osteotomies", str(scene), "--resolution",
                         resolution, "--out", str(out), "--report", str(out / "ct.json"),
                         *extra])
    return r, out


def _simulate(tmp_path, name, args, n=1):
    rep = tmp_path / f"{name}.json"
    cmd = (_mpirun(n) if n > 1 else []) + SIMULATE + args + ["--report", str(rep)]
    r = _run(cmd)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(rep.read_text())


def test_ct_of_a_synthetic_head_matches_the_head(synthetic_ct, cache):
    """The pipeline on a CT made from the synthetic class1 head (medium): the landmarks built
    on its profile lie within 1.5 voxels of the same construction on the head's own mesh, the
    segments' areas within 10 %, and a 5 mm BSSO advance moves the landmarks as on the head
    within 0.3 mm, both with the tissue classes, which agree within 0.03 of the tissue's
    volume per class."""
    from inverse.scene import Scene
    from meshes.anatomy import SKIN, segment_tags
    from meshes.ct import ct_anatomy
    from meshes.external import attach_landmarks
    from meshes.landmarks import profile_landmarks
    from meshes.synthetic import CASES, case_osteotomies, synthetic_head

    ct, scene_file = synthetic_ct
    got, info = ct_anatomy(ct, scene_file, "medium")
    head = synthetic_head("class1", "medium")
    own = profile_landmarks(head.points, head.facets[head.facet_tags == SKIN],
                            case_osteotomies(CASES["class1"]).midsagittal)
    assert {"N", "Prn", "Sn", "Ls", "Li", "Pg", "Me"} <= set(got.landmarks) & set(own)
    for name, lm in got.landmarks.items():
        d = np.linalg.norm(lm.position(got.points) - own[name].position(head.points))
        assert d <= 1.5 * VOXEL_MM, (name, d)

    def areas(a):
        x = a.points[a.facets]
        area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        return {n: area[np.isin(a.facet_tags, segment_tags(t))].sum()   # teeth included
                for n, t in a.segments.items()}

    a_ct, a_head = areas(got), areas(head)
    assert set(a_ct) == set(a_head) == {"mandible", "maxilla_L", "maxilla_R"}
    for n in a_ct:
        assert abs(a_ct[n] / a_head[n] - 1) < 0.10, (n, a_ct[n], a_head[n])
    # the same anatomical points on the head's mesh
    attach_landmarks(head, got.landmark_positions(), tol=1.5 * VOXEL_MM)
    from meshes.tissue import tissue_report

    shares = tissue_report(got), tissue_report(head)
    for k in shares[0]:
        assert abs(shares[0][k] - shares[1][k]) < 0.03, shares
    moved = {}
    for name, anatomy in (("ct", got), ("head", head)):
        scene = Scene(anatomy, params_used=["mandible.advance_mm"], material="tissues")
        rest = scene.landmarks(rest=True)
        scene.solve({"mandible.advance_mm": 5.0})
        moved[name] = {k: v - rest[k] for k, v in scene.landmarks().items()}
    for k in got.landmarks:
        d = np.linalg.norm(moved["ct"][k] - moved["head"][k])
        assert d <= 0.3, (k, moved["ct"][k], moved["head"][k])


#: The ears added to the 3 mm CT of the synthetic head (mm): a pinna standing 15 mm out of the
#: side of the head from the crop's back face (y = -12) to EAR_FRONT, with a canal 9 mm square
#: and 25 mm deep (an adult's: 7-9 mm across, 25 mm to the eardrum) centred at CANAL_Z, its
#: front wall at y = 0, away from the ear's middle height (z = 10) and front edge (y = 12);
#: the tragion is at the canal's front rim.
EAR_FRONT, CANAL_Z = 12.0, 0.0


def _ears(a, v):
    x, y, z = np.meshgrid(*(v.centres(i) for i in range(3)), indexing="ij")
    pinna = (np.abs(x) > 60) & (np.abs(x) < 88) & (y <= EAR_FRONT) & (z > -15) & (z < 35)
    a[pinna] = 40
    a[(np.abs(x) > 63) & (y > -9) & (y < 0) & (np.abs(z - CANAL_Z) < 4.5)] = -1000   # canal


def test_tragion_at_the_front_rim_of_the_ear_canal(tmp_path):
    """Tragion is built in front of each ear canal, at its height, on the pinna's skin; a head
    without ears (the synthetic one) has none."""
    from meshes.ct import build  # not cached: the plain CT is another test's fresh one
    from meshes.landmarks import EAR_BIN_MM

    voxel = 3.0
    got, _ = build(_small_ct(tmp_path, _ears, "ears.mha"), _scene_file(tmp_path), "coarse")
    t = got.landmark_positions()
    assert {"T_L", "T_R"} <= set(t), sorted(t)
    for name, side in (("T_L", 1.0), ("T_R", -1.0)):
        x, y, z = t[name]
        assert side * x > 80, (name, t[name])   # on the pinna, not the head behind it
        assert -voxel / 2 <= y <= EAR_BIN_MM + voxel, (name, t[name])   # canal: y < 0
        assert abs(z - CANAL_Z) <= EAR_BIN_MM / 2 + voxel, (name, t[name])
    plain, _ = build(_small_ct(tmp_path), _scene_file(tmp_path), "coarse")
    assert not {"T_L", "T_R"} & set(plain.landmarks)


def test_ct_scene_is_deterministic_and_cached(tmp_path, cache):
    """Two builds of one CT give the same arrays bit for bit (CGAL's seed is fixed); the
    second `ct_anatomy` call comes from the cache, the same again."""
    from meshes.ct import build, ct_anatomy

    ct, scene = _small_ct(tmp_path), _scene_file(tmp_path)
    a, _ = build(ct, scene, "coarse")
    b, info_b = ct_anatomy(ct, scene, "coarse")
    c, info_c = ct_anatomy(ct, scene, "coarse")
    assert not info_b["cached"] and info_c["cached"]
    for x in (b, c):
        for key in ("points", "cells", "facets", "facet_tags"):
            assert np.array_equal(getattr(a, key), getattr(x, key)), key
        assert x.landmark_positions().keys() == a.landmark_positions().keys()


def test_label_map_input(tmp_path, cache):
    """A label map (1 tissue, 2 bone, as a 3D Slicer segmentation) gives the scene the CT of
    the same head gives: the same segments and landmarks. Without a fat label it has no
    tissue classes (homogeneous); with one (3: fat) its classes are the CT's."""
    from meshes.ct import ct_anatomy
    from meshes.synthetic import CT_HU
    from meshes.tissue import tissue_report

    ct = _small_ct(tmp_path)

    def to_labels(a, v):
        a[...] = np.where(a >= CT_HU["bone"], 2, np.where(a == CT_HU["fat"], 3,
                                                          np.where(a > -400, 1, 0)))

    labels = _small_ct(tmp_path, to_labels, name="labels.mha")
    from_ct, _ = ct_anatomy(ct, _scene_file(tmp_path), "coarse")
    plain, _ = ct_anatomy(labels, _scene_file(tmp_path, labels={"tissue": [1, 3]}), "coarse")
    from_map, _ = ct_anatomy(labels, _scene_file(tmp_path, labels={"fat": 3}), "coarse")
    assert from_ct.material == from_map.material == "tissues" and plain.tissues is None
    assert plain.material == "homogeneous"
    share_ct, share_map = tissue_report(from_ct), tissue_report(from_map)
    for k in share_ct:   # the two meshes differ a little: the same shares of each class
        assert abs(share_map[k] - share_ct[k]) < 0.02, (share_map, share_ct)
    assert from_map.segments == from_ct.segments
    assert set(from_map.landmarks) == set(from_ct.landmarks)
    for k, x in from_ct.landmark_positions().items():
        assert np.linalg.norm(from_map.landmark_positions()[k] - x) < 3.0, k


def _plan_recovers(tmp_path, mesh, p_star: dict, landmarks, n_landmarks_min=2):
    """simulate.py --mesh at p* writes the targets; plan.py --mesh planning p*'s parameters
    reaches them and finds p*."""
    pairs = [f"{k}={v}" for k, v in p_star.items()]
    sim = _simulate(tmp_path, "truth", ["--mesh", str(mesh), "--params-used", ",".join(p_star),
                                        "--p", *pairs])
    assert sim["converged"]
    assert len(landmarks) >= n_landmarks_min
    targets = tmp_path / "targets.json"
    targets.write_text(json.dumps({k: sim["landmarks"][k] for k in landmarks}))
    rep = tmp_path / "plan.json"
    r = _run(PLAN + ["--mesh", str(mesh), "--targets", str(targets), "--landmarks",
                     ",".join(landmarks), "--params-used", ",".join(p_star), "--tikhonov", "0",
                     "--ftol", "1e-9", "--report", str(rep)])
    assert r.returncode == 0, r.stderr[-2000:]
    plan = json.loads(rep.read_text())
    assert max(v["distance_after_mm"] for v in plan["landmarks"].values()) <= 0.01
    np.testing.assert_allclose(plan["params_optimal"], list(p_star.values()), rtol=1e-3,
                               atol=1e-3)


def _check_tissues(rep: dict, sim: dict):
    """A CT scene has skin, fat and lean tissue (`meshes.tissue`), and simulates with them
    by default."""
    assert rep["material"] == sim["material"] == "tissues"
    shares = rep["tissues"]
    assert abs(sum(shares.values()) - 1) < 1e-3
    assert shares["skin"] > 0.02 and shares["fat"] > 0.05 and shares["muscle"] > 0.3, shares


def _check_teeth(rep: dict, segments: set):
    """Every segment has teeth (`meshes.teeth`): crowns of at least 1 cm² with their
    vestibule, in a band no taller than the crown's search band and the vestibule."""
    from meshes.teeth import OCCLUSAL_MM, VESTIBULE_MM

    assert set(rep["teeth"]) == segments, rep["teeth"]
    for name, t in rep["teeth"].items():
        lo, hi = t["height_mm"]
        assert t["area_mm2"] > 100 and hi - lo < OCCLUSAL_MM + max(VESTIBULE_MM.values()), t


@needs_cranium
def test_cranium_lefort_scene_through_the_scripts(tmp_path, cache):
    """Cranium.inv3 (Debian): ct_scene.py writes the scene and its report; a 5 mm LeFort I
    advance converges; a LeFort I plan (targets from simulate.py) recovers p*."""
    r, out = _ct_scene(tmp_path, CRANIUM, EXAMPLES / "cranium.json")
    assert r.returncode == 0, r.stderr[-2000:]
    rep = json.loads((out / "ct.json").read_text())
    assert REPORT_KEYS <= set(rep)
    assert set(rep["segments"]) == {"maxilla_L", "maxilla_R"}
    assert {"Prn", "Sn"} <= set(rep["landmarks"])
    assert not {"T_L", "T_R"} & set(rep["landmarks"])   # the crop ends in front of the ears
    assert rep["min_quality"] > 0.05 and Path(rep["mesh"]).exists()
    _check_teeth(rep, {"maxilla_L", "maxilla_R"})
    sim = _simulate(tmp_path, "advance", ["--mesh", rep["mesh"], "--p", "maxilla.advance_mm=5"])
    assert sim["converged"] and sim["active_goal_error_max_mm"] < 0.05
    assert sim["contact"] == "sliding"
    _check_tissues(rep, sim)
    _plan_recovers(tmp_path, rep["mesh"], {"maxilla.advance_mm": 4.0, "maxilla.vertical_mm":
                                           -1.5}, sorted(rep["landmarks"]))


@needs_headsq
def test_headsq_double_jaw_scene_through_the_scripts(tmp_path, cache):
    """headsq (shared data): ct_scene.py, a 5 mm advance of both jaws (the CT's teeth are in
    occlusion: an independent 5 mm BSSO advance drives the lower incisors through the upper
    ones and crushes the tissue between them) converges, and a plan of both jaws (targets from
    simulate.py) recovers p*; a landmark the CT does not hold is refused with one line; the
    tragions sit on the two sides at one height."""
    r, out = _ct_scene(tmp_path, HEADSQ, EXAMPLES / "headsq.json")
    assert r.returncode == 0, r.stderr[-2000:]
    rep = json.loads((out / "ct.json").read_text())
    assert set(rep["segments"]) == {"mandible", "maxilla_L", "maxilla_R"}
    assert {"Li", "Pg", "Me", "T_L", "T_R"} <= set(rep["landmarks"])
    t_l, t_r = (np.array(rep["landmarks"][k]) for k in ("T_L", "T_R"))
    mid = json.loads((EXAMPLES / "headsq.json").read_text())["midsagittal"]["point"][0]
    assert t_l[0] - mid > 50 and mid - t_r[0] > 50   # on the two sides of the head,
    assert np.abs(t_l[1:] - t_r[1:]).max() < 2 * 3.2   # level and abreast within 2 voxels
    _check_teeth(rep, {"mandible", "maxilla_L", "maxilla_R"})
    upper = min(rep["teeth"][s]["height_mm"][0] for s in ("maxilla_L", "maxilla_R"))
    assert upper > rep["teeth"]["mandible"]["height_mm"][1]   # the upper teeth above the lower
    sim = _simulate(tmp_path, "advance", ["--mesh", rep["mesh"], "--p", "jaws.advance_mm=5"])
    assert sim["converged"] and sim["active_goal_error_max_mm"] < 0.05
    assert sim["contact"] == "sliding"
    _check_tissues(rep, sim)
    _plan_recovers(tmp_path, rep["mesh"], {"jaws.advance_mm": 3.0, "jaws.pitch_deg": 2.0},
                   sorted(rep["landmarks"]))
    targets = tmp_path / "t.json"
    targets.write_text(json.dumps({"Prn": [100.0, 0.0, -20.0]}))
    r = _run(PLAN + ["--mesh", rep["mesh"], "--targets", str(targets), "--landmarks", "Prn"])
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert r.returncode == 2 and len(errors) == 1 and "Prn" in errors[0], r.stderr[-2000:]


@needs_cranium
@pytest.mark.mpi
def test_ct_scene_simulates_the_same_on_1_and_2_ranks(tmp_path, cache):
    """simulate.py --mesh on the Cranium scene: the same landmarks on 1 and 2 ranks."""
    r, out = _ct_scene(tmp_path, CRANIUM, EXAMPLES / "cranium.json")
    assert r.returncode == 0, r.stderr[-2000:]
    mesh = str(out / "scene.vtu")
    reps = [_simulate(tmp_path, f"n{n}", ["--mesh", mesh, "--p", "maxilla.advance_mm=3",
                                           "maxilla.vertical_mm=1"], n=n) for n in (1, 2)]
    for k, x in reps[0]["landmarks"].items():
        np.testing.assert_allclose(reps[1]["landmarks"][k], x, atol=1e-6)


# ---------------------------------------------------------------------- bad input
def _small_ct(tmp_path, hu_fn=None, name="ct.mha"):
    """class1 voxelised at 3 mm (fast), optionally changed by hu_fn(array, volume)."""
    from meshes.synthetic import synthetic_ct
    from meshes.volume import write_volume

    v = synthetic_ct("class1", 3.0)
    if hu_fn is not None:
        hu_fn(v.array, v)
    write_volume(v, tmp_path / name)
    return tmp_path / name


def _scene_file(tmp_path, **changes):
    from meshes.synthetic import synthetic_scene_file

    spec = synthetic_scene_file("class1")
    spec.update(changes)
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(spec))
    return path


def _bone_block(a, v):
    a[:] = -1000
    a[10:30, 10:30, 10:30] = 1000   # bone in the air, no tissue around it
    a[10:30, 10:30, 30:34] = 40


def _two_d(tmp_path):
    import SimpleITK as sitk

    sitk.WriteImage(sitk.Image([16, 16], sitk.sitkInt16), str(tmp_path / "flat.mha"))
    return tmp_path / "flat.mha"


def _garbage(tmp_path):
    (tmp_path / "noise.mha").write_text("this is no image\n")
    return tmp_path / "noise.mha"


def _markups(folder, name, markups, ct=True):
    """Write a 3D Slicer markups file ``folder/name``; the small CT (or None)."""
    (folder / name).write_text(json.dumps({"@schema": "markups-schema-v1.0.3.json#",
                                           "markups": markups}))
    return _small_ct(folder) if ct else None


def _plane_markup(name, point, normal, system="LPS"):
    """A Slicer Plane markup from a point and a normal in the scene's frame."""
    from meshes.markups import FROM_FRAME

    to = FROM_FRAME[system]   # its own inverse
    return {"type": "Plane", "name": name, "coordinateSystem": system,
            "planeType": "pointNormal", "center": (to @ np.asarray(point, float)).tolist(),
            "normal": (to @ np.asarray(normal, float)).tolist(),
            "controlPoints": [{"label": f"{name}-1",
                               "position": (to @ np.asarray(point, float)).tolist()}]}


BAD = {
    "a markups file with no plane": (lambda t: _markups(t, "cuts.mrk.json", [
        {"type": "Fiducial", "controlPoints": [{"label": "A", "position": [0, 0, 0]}]}]),
        {"planes": "cuts.mrk.json"}, [], "holds no Plane markup"),
    "a plane with a zero normal": (lambda t: _markups(t, "le.mrk.json", [
        _plane_markup("lefort1", [0, 0, -15], [0, 0, 0])]), {"lefort1": "le.mrk.json"}, [],
        "zero normal"),
    "a markups file of no cut": (lambda t: _markups(t, "cuts.mrk.json", [
        _plane_markup("P", [0, 0, -15], [0, 0, 1])]), {"planes": "cuts.mrk.json"}, [],
        "no plane is named as a cut"),
    "not an image": (lambda t: _garbage(t), {}, [], "cannot read"),
    "a 2-D image": (lambda t: _two_d(t), {}, [], "3-D volume is needed"),
    "no body": (lambda t: _small_ct(t, lambda a, v: a.fill(-1000)), {}, [], "no body found"),
    "bone outside the skin": (lambda t: _small_ct(t, _bone_block), {}, [],
                              "bone lies outside the skin"),
    "a plane that cuts no bone": (lambda t: _small_ct(t), {"lefort1": {
        "point": [0, 0, 500], "normal": [0, 0, 1]}}, [], "cuts no bone"),
    "a segment with no facets": (lambda t: _small_ct(t), {"midsagittal": {
        "point": [60, 0, 0], "normal": [1, 0, 0]}}, [], "has no facets"),
    "a landmark off the skin": (lambda t: _small_ct(t), {}, ["Pg_far"], "off the skin"),
    "a crop that leaves no tissue": (lambda t: _small_ct(t), {"crop": {
        "min": [-10, 0, 10], "max": [10, 20, 30]}}, [], "leaves no tissue"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_ct_input_gets_one_line_and_writes_nothing(tmp_path, cache, case):
    """Each bad input of the pipeline: exit 2, one line naming the problem, no output."""
    make_ct, changes, landmark, needle = BAD[case]
    ct = make_ct(tmp_path)
    scene = _scene_file(tmp_path, **changes)
    extra = []
    if landmark:
        lm = tmp_path / "lm.json"
        lm.write_text(json.dumps({"Pg": [0.0, 140.0, -64.0]}))   # 40 mm in front of the chin
        extra = ["--landmarks", str(lm)]
    r, out = _ct_scene(tmp_path, ct, scene, *extra)
    _one_line_error(r, needle)
    assert not out.exists() or not any(out.iterdir())


def test_planes_from_slicer_markups(tmp_path, cache):
    """The scene file's planes from 3D Slicer markups: one file of named planes (LPS, centre
    and normal) and a cut given as its own file (RAS, three control points) give the cuts of
    the hand-typed file, and the same scene."""
    from meshes.ct import ct_anatomy, parse_scene_file
    from meshes.markups import FROM_FRAME
    from meshes.synthetic import synthetic_scene_file

    spec = synthetic_scene_file("class1")
    given = {k: spec.pop(k) for k in ("lefort1", "occlusal", "ramus_L", "ramus_R")}
    ras = FROM_FRAME["RAS"]
    p, n = np.asarray(given["lefort1"]["point"]), np.asarray(given["lefort1"]["normal"])
    u = np.cross(n, [1.0, 0, 0]) if abs(n[0]) < 0.9 else np.cross(n, [0, 1.0, 0])
    three = [p, p + 10 * u, p + 10 * np.cross(n, u)]   # counter-clockwise about n
    _markups(tmp_path, "lefort.mrk.json", [
        {"type": "Plane", "name": "cut", "coordinateSystem": "RAS", "planeType": "3Points",
         "controlPoints": [{"label": str(i), "position": (ras @ x).tolist()}
                           for i, x in enumerate(three)]}], ct=False)
    _markups(tmp_path, "cuts.mrk.json", [
        _plane_markup(k, given[k]["point"], given[k]["normal"])
        for k in ("occlusal", "ramus_L", "ramus_R")] + [
        _plane_markup("lefort1", [0, 0, 99], [0, 0, 1])], ct=False)   # the lefort1 entry wins
    typed = _scene_file(tmp_path, **spec, **given).rename(tmp_path / "typed.json")
    scene = _scene_file(tmp_path, **spec, planes="cuts.mrk.json", lefort1="lefort.mrk.json")
    _, cuts, _ = parse_scene_file(scene)
    _, want, _ = parse_scene_file(typed)
    for k in given:
        a, b = getattr(cuts, k), getattr(want, k)
        np.testing.assert_allclose(a.normal, b.normal, atol=1e-12)
        assert abs(a.distance(np.array([b.point]))[0]) < 1e-9, k
    ct = _small_ct(tmp_path)
    from_markups, _ = ct_anatomy(ct, scene, "coarse")
    from_typed, _ = ct_anatomy(ct, typed, "coarse")
    np.testing.assert_array_equal(from_markups.facet_tags, from_typed.facet_tags)
