"""Osteotomies proposed from a CT's anatomy (issue 28, ``ct_scene.py --propose-osteotomies``):
against the hand-made files of the two real CTs, turned with a tilted head, planned through
the scripts as a user chains them, and refused on a CT without teeth."""

import json

import numpy as np
import pytest
from test_ct import (
    CRANIUM,
    CT_SCENE,
    EXAMPLES,
    HEADSQ,
    _ct_scene,
    _plan_recovers,
    cache,  # noqa: F401 (a fixture: the module's fresh mesh cache)
    needs_cranium,
    needs_headsq,
)
from test_frame import PITCHED, _rotation
from test_scripts import _one_line_error, _run

#: The tests' tier (conftest.py): proposed osteotomies through the scripts.
TIER = "scripts"

#: Each proposed plane lies within this angle (degrees) and distance (mm, the hand-made plane's
#: distance from the proposed plane's point, which lies on the anatomy) of the hand-made
#: file's (the issue's bound).
ANGLE_DEG, DISTANCE_MM = 5.0, 5.0
CASES = {"cranium": pytest.param(CRANIUM, "cranium.json", marks=needs_cranium),
         "headsq": pytest.param(HEADSQ, "headsq.json", marks=needs_headsq)}


def _propose(tmp_path, ct, *extra, name="proposed.json"):
    out = tmp_path / name
    r = _run(CT_SCENE + ["--ct", str(ct), "--propose-osteotomies", str(out), *extra])
    return r, out


def _settings(tmp_path, hand: str):
    """The hand-made file's settings (thresholds, band widths), without its planes and crop:
    the base a user gives ``--propose-osteotomies`` (headsq: bone_hu 150 for its 3.2 mm
    voxels, which blur the thin palate below the default 226 HU)."""
    from meshes.osteotomy import PLANES

    want = json.loads((EXAMPLES / hand).read_text())
    path = tmp_path / "settings.json"
    path.write_text(json.dumps({k: v for k, v in want.items()
                                if k not in PLANES and k not in ("crop", "about")}))
    return path


def _angle_distance(a: dict, b: dict) -> tuple:
    """(degrees between the planes' normals, mm from plane a to b's point)."""
    from meshes.plane import Plane

    pa, pb = Plane.of("a", a), Plane.of("b", b)
    cos = min(1.0, abs(float(np.dot(pa.normal, pb.normal))))
    return float(np.degrees(np.arccos(cos))), float(abs(pa.distance(np.array([pb.point]))[0]))


@pytest.mark.parametrize("ct, hand", list(CASES.values()), ids=list(CASES))
def test_proposal_matches_the_hand_made_file(tmp_path, ct, hand):
    """Every plane of the hand-made file is proposed, within 5 degrees and 5 mm, with the
    same free crop faces; the proposal is a valid scene file as it is."""
    from meshes.ct import parse_scene_file

    r, out = _propose(tmp_path, ct, "--osteotomies", str(_settings(tmp_path, hand)))
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads(out.read_text())
    want = json.loads((EXAMPLES / hand).read_text())
    planes = [k for k in want if isinstance(want[k], dict) and "normal" in want[k]]
    for k in planes:
        angle, distance = _angle_distance(want[k], got[k])
        assert angle <= ANGLE_DEG and distance <= DISTANCE_MM, (k, angle, distance)
    assert set(got["crop"]["free"]) == set(want["crop"]["free"])
    parse_scene_file(out)   # a valid scene file as it is


@needs_cranium
@pytest.mark.parametrize("angles", PITCHED)
def test_proposal_turns_with_a_tilted_head(tmp_path, angles):
    """Cranium tilted in the scanner (pitch, roll, yaw degrees; resampled on its grid): the
    proposed planes, turned back, are the untilted head's within the frame's bound (1 degree)
    and a voxel's diagonal (the nasal floor's height is found to a voxel)."""
    from meshes.volume import read_volume, rotate_volume, write_volume

    v = read_volume(CRANIUM)
    centre = v.origin + v.spacing * (np.array(v.array.shape) - 1) / 2
    R = _rotation(*angles)
    write_volume(rotate_volume(v, R, centre), tmp_path / "tilted.nii.gz")
    flat = json.loads(_propose(tmp_path, CRANIUM, name="flat.json")[1].read_text())
    r, out = _propose(tmp_path, tmp_path / "tilted.nii.gz", name="tilted.json")
    assert r.returncode == 0, r.stderr[-2000:]
    tilted = json.loads(out.read_text())
    voxel = float(np.linalg.norm(v.spacing))
    for k in ("midsagittal", "lefort1", "pterygomaxillary"):
        back = {"point": (R.T @ (np.array(tilted[k]["point"]) - centre) + centre).tolist(),
                "normal": (R.T @ tilted[k]["normal"]).tolist()}
        angle, distance = _angle_distance(flat[k], back)
        assert angle <= 1.0 and distance <= voxel, (k, angle, distance)


@pytest.mark.usefixtures("cache")
@pytest.mark.parametrize("ct, hand", list(CASES.values()), ids=list(CASES))
@pytest.mark.cgal
def test_proposed_file_plans_through_the_scripts(tmp_path, ct, hand):
    """The proposed file, used as it is: ct_scene.py --osteotomies builds the scene with the
    hand-made file's segments, and a plan (targets from simulate.py) recovers p*."""
    r, proposed = _propose(tmp_path, ct, "--osteotomies", str(_settings(tmp_path, hand)))
    assert r.returncode == 0, r.stderr[-2000:]
    r, out = _ct_scene(tmp_path, ct, proposed)
    assert r.returncode == 0, r.stderr[-2000:]
    rep = json.loads((out / "ct.json").read_text())
    jaws = "mandible" in rep["segments"]
    assert set(rep["segments"]) == ({"mandible"} if jaws else set()) | {"maxilla_L",
                                                                        "maxilla_R"}
    p_star = {"jaws.advance_mm": 3.0, "jaws.pitch_deg": 2.0} if jaws else \
        {"maxilla.advance_mm": 4.0, "maxilla.vertical_mm": -1.5}
    _plan_recovers(tmp_path, rep["mesh"], p_star, sorted(rep["landmarks"]))


def test_proposal_on_a_ct_without_teeth_gets_one_line(tmp_path):
    """The voxelised synthetic head has bone but no teeth (nothing reads as enamel): exit 2,
    one line, nothing written; so does a label map."""
    from meshes.synthetic import synthetic_ct
    from meshes.volume import write_volume

    write_volume(synthetic_ct("class1", 2.0), tmp_path / "class1.mha")
    for extra, needle in (([], "no teeth found"), (["--labelmap"], "reads HU")):
        r, out = _propose(tmp_path, tmp_path / "class1.mha", *extra)
        _one_line_error(r, needle)
        assert not out.exists()
