"""Scans as they come, through the scripts (issue 47): a CBCT's gray values, brackets with
streaks, and a head moved on the voxel grid give the scene and the predictions of the clean
CT in HU. Every hostile scan is made here with scipy and numpy (`test_intensity`'s
mappings and brackets), not by the code under test."""

import dataclasses
import json

import numpy as np
import pytest
from test_ct import (  # noqa: F401 (cache: a fixture)
    CRANIUM,
    CT_SCENE,
    EXAMPLES,
    PLAN,
    SIMULATE,
    _one_line_error,
    _run,
    cache,
    moved_spec,
    needs_cranium,
)
from test_intensity import REMAPS, _realistic, _with_brackets

#: The tests' tier (conftest.py): CTs to scenes through the scripts, in a fresh mesh cache.
TIER = "scripts"
pytestmark = [pytest.mark.usefixtures("cache"), pytest.mark.cgal]

#: The issue's bounds on a landmark's predicted motion under a 5 mm LeFort I advance when the
#: head moves on the voxel grid (mm), per resolution.
MOTION_MM = {"medium": 0.3, "paper": 0.2}


def _scene(folder, ct, spec, resolution):
    """ct_scene.py on ``ct`` (a path) with the scene file ``spec`` (a dict): its report."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.json").write_text(json.dumps(spec))
    r = _run(CT_SCENE + ["--ct", str(ct), "--osteotomies", str(folder / "scene.json"),
                         "--resolution", resolution, "--out", str(folder / "out"),
                         "--report", str(folder / "ct.json")])
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads((folder / "ct.json").read_text())


def _write(volume, path, dtype=np.int16):
    from meshes.volume import write_volume

    write_volume(dataclasses.replace(volume, array=np.rint(volume.array).astype(dtype)), path)
    return path


def _cranium():
    from meshes.volume import read_volume

    return read_volume(CRANIUM)


def _voxel(volume) -> float:
    """One voxel: its diagonal, mm."""
    return float(np.linalg.norm(volume.spacing))


def _angle_deg(A, B) -> float:
    R = np.asarray(A)[:3, :3].T @ np.asarray(B)[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def _same_scene(got: dict, want: dict, voxel: float, names: set):
    """The landmarks ``names`` in both, each within a voxel, and the frame within 1 degree."""
    assert names <= set(got["landmarks"]) & set(want["landmarks"]), (got["landmarks"], names)
    for k in set(got["landmarks"]) & set(want["landmarks"]):
        d = np.linalg.norm(np.subtract(got["landmarks"][k], want["landmarks"][k]))
        assert d <= voxel, (k, d)
    assert _angle_deg(got["head_frame"], want["head_frame"]) < 1.0


@pytest.fixture(scope="module")
def cranium_paper(tmp_path_factory, cache):  # noqa: F811 (the fixture, imported above)
    """Cranium.inv3 in HU at paper through ct_scene.py, in the module's fresh cache: its
    report."""
    if not CRANIUM.exists():
        pytest.skip(f"{CRANIUM} is absent (Debian's invesalius-examples)")
    spec = json.loads((EXAMPLES / "cranium.json").read_text())
    return _scene(tmp_path_factory.mktemp("cranium_hu"), CRANIUM, spec, "paper")


@pytest.fixture(scope="module")
def cranium_paper_advance(tmp_path_factory, cranium_paper):
    """`_advance` of `cranium_paper`: (rest, motion) under a 5 mm LeFort I."""
    return _advance(tmp_path_factory.mktemp("cranium_hu_advance"), "base",
                    cranium_paper["mesh"])


@needs_cranium
@pytest.mark.parametrize("remap", ["cbct", "12-bit", "gamma 0.8", "gamma 1.25"])
def test_cranium_in_gray_values_gives_the_hu_scene(tmp_path, cranium_paper, remap):
    """Cranium's HU mapped as a CBCT's gray values (stored as 16-bit unsigned) and built at
    paper: the report says the HU were estimated, with the classes; every landmark lies
    within a voxel of the HU scene's, the frame within 1 degree; the HU scene itself is
    read as HU, its thresholds the HU defaults."""
    assert cranium_paper["intensity"]["source"] == "hu"
    assert cranium_paper["intensity"]["thresholds"]["bone_hu"]["source"] == "HU default"
    v = _cranium()
    w = dataclasses.replace(v, array=REMAPS[remap](v.array.astype(np.float64)))
    ct = _write(w, tmp_path / "gray.mha", np.uint16)
    spec = json.loads((EXAMPLES / "cranium.json").read_text())
    rep = _scene(tmp_path / "gray", ct, spec, "paper")
    assert rep["intensity"]["source"] == "estimated", rep["intensity"]
    assert {"air", "soft", "bone"} == set(rep["intensity"]["classes"])
    assert rep["intensity"]["thresholds"]["skin_hu"]["source"] == "estimated"
    _same_scene(rep, cranium_paper, _voxel(v), {"N", "Prn", "Sn"})


@pytest.mark.parametrize("remap", ["cbct", "12-bit", "gamma 0.8"])
def test_synthetic_ct_in_gray_values_gives_the_hu_scene(tmp_path, remap):
    """The synthetic CT (2 mm voxels, a scanner's blur and noise) in HU and mapped as a
    CBCT's gray values, built at medium: every landmark within a voxel, the frame within 1
    degree (at coarse, the 5.5 mm mesh loses the 1.4 mm labiomental fold, and with it Pg,
    on one scan of the two)."""
    from meshes.synthetic import synthetic_scene_file

    v = _realistic(2.0)
    spec = synthetic_scene_file("class1")
    hu = _scene(tmp_path / "hu", _write(v, tmp_path / "hu.mha"), spec, "medium")
    w = dataclasses.replace(v, array=REMAPS[remap](v.array.astype(np.float64)))
    rep = _scene(tmp_path / "gray", _write(w, tmp_path / "gray.mha", np.uint16), spec,
                 "medium")
    assert hu["intensity"]["source"] == "hu" and rep["intensity"]["source"] == "estimated"
    _same_scene(rep, hu, _voxel(v), {"N", "Prn", "Sn", "Ls", "Li", "Pg"})


def _check_brackets(rep: dict, clean: dict, voxel: float, names: set):
    """The scene with brackets against the clean one: metal reported, its landmarks within a
    voxel, the frame within 1 degree, the tissue shares within 0.02, and teeth on every
    segment that had them, at least half their area."""
    assert rep["metal"]["mm3"] > 0 and rep["metal"]["streak_mm3"] > 0, rep["metal"]
    assert not rep["metal"]["teeth_all_metal"]
    assert clean["metal"] == {"mm3": 0.0}
    _same_scene(rep, clean, voxel, names)
    for k, share in clean["tissues"].items():
        assert abs(rep["tissues"][k] - share) <= 0.02, (k, rep["tissues"], clean["tissues"])
    for seg, teeth in clean["teeth"].items():
        assert rep["teeth"][seg]["area_mm2"] >= 0.5 * teeth["area_mm2"], (seg, rep["teeth"])


@needs_cranium
def test_cranium_with_brackets_gives_the_clean_scene(tmp_path, cranium_paper):
    """Brackets of 8000 HU on Cranium's front teeth with ±600 HU streaks in their slices,
    built at paper: `_check_brackets` against the clean scene."""
    v = _cranium()
    w, mask, _ = _with_brackets(v, teeth_hu=2000.0)
    assert mask.any()
    spec = json.loads((EXAMPLES / "cranium.json").read_text())
    rep = _scene(tmp_path / "brackets", _write(w, tmp_path / "brackets.mha"), spec, "paper")
    _check_brackets(rep, cranium_paper, _voxel(v), {"N", "Prn", "Sn"})


@needs_cranium
def test_teeth_found_on_one_half_say_so(tmp_path, cranium_paper):
    """Cranium whose right half reads at most 1700 HU, as an RTK CBCT's FDK read its crowns at
    the edge of its axial field: the report names maxilla_R, and only it, in ``teeth_lopsided``;
    the clean scene names none."""
    assert cranium_paper["teeth_lopsided"] == {}
    v = _cranium()
    spec = json.loads((EXAMPLES / "cranium.json").read_text())
    x = v.origin[0] + v.spacing[0] * np.arange(v.array.shape[0])
    right = (x < spec["midsagittal"]["point"][0])[:, None, None]   # LPS: x to the left
    a = np.where(right, np.minimum(v.array, 1700), v.array)
    folder = tmp_path / "lopsided"
    rep = _scene(folder, _write(dataclasses.replace(v, array=a), tmp_path / "r.mha"), spec,
                 "paper")
    assert set(rep["teeth_lopsided"]) == {"maxilla_R"}, rep["teeth"]
    assert rep["teeth"]["maxilla_L"]["area_mm2"] > 0.9 * \
        cranium_paper["teeth"]["maxilla_L"]["area_mm2"]


def test_synthetic_ct_with_brackets_gives_the_clean_scene(tmp_path):
    """The same on the synthetic CT (1.25 mm voxels, crowns of enamel) at medium."""
    from meshes.synthetic import synthetic_scene_file

    v = _realistic(1.25)
    clean = _with_brackets(v, hu=2500.0, streak=0.0)[0]   # its crowns, no metal
    dirty = _with_brackets(v)[0]
    spec = synthetic_scene_file("class1")
    want = _scene(tmp_path / "clean", _write(clean, tmp_path / "clean.mha"), spec, "medium")
    rep = _scene(tmp_path / "dirty", _write(dirty, tmp_path / "dirty.mha"), spec, "medium")
    _check_brackets(rep, want, _voxel(v), {"N", "Prn", "Sn", "Ls", "Li", "Pg"})


def test_a_volume_without_bone_is_refused_through_the_script(tmp_path):
    """A head of soft tissue alone, in gray values: ct_scene.py exits 2 with one line, and
    writes nothing."""
    from meshes.synthetic import synthetic_scene_file

    v = _realistic(3.0)
    w = dataclasses.replace(v, array=REMAPS["cbct"](np.where(v.array > 500, 40.0, v.array)))
    (tmp_path / "scene.json").write_text(json.dumps(synthetic_scene_file("class1")))
    out = tmp_path / "out"
    r = _run(CT_SCENE + ["--ct", str(_write(w, tmp_path / "soft.mha", np.uint16)),
                         "--osteotomies", str(tmp_path / "scene.json"), "--out", str(out)])
    _one_line_error(r, "no bone class")
    assert not out.exists()


def _shifted(v, spec: dict, voxels: float):
    """The volume's content moved by ``voxels`` of its own along every axis (linear
    interpolation, scipy), and the scene file's planes and crop moved with it: (volume, spec,
    shift mm)."""
    from scipy import ndimage

    t = voxels * v.spacing
    a = ndimage.shift(v.array.astype(np.float32), (voxels,) * 3, order=1, mode="nearest")
    return dataclasses.replace(v, array=a), moved_spec(spec, np.eye(3), t, np.zeros(3)), t


def _pitched(v, spec: dict, degrees: float):
    """The volume's content turned by ``degrees`` about the left-right axis through its
    centre (linear interpolation, scipy, air beyond the field of view) on a grid of the
    scanner's spacing and phase that holds it, and the scene file's planes and crop turned
    with it: (volume, spec, rotation (3, 3), centre (3,)). Not `meshes.volume.rotate_volume`,
    whose grid starts at the turned box's corner: on that grid N's old plateau passed at 5
    degrees, on the scanner's phase it was 2.15 mm off."""
    from scipy import ndimage

    a = np.radians(degrees)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    s, o, n = v.spacing, v.origin, np.array(v.array.shape)
    centre = o + s * (n - 1) / 2
    corners = o + np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) \
        * (n - 1) * s
    turned = (corners - centre) @ R.T + centre
    lo = np.floor((turned.min(0) - o) / s) * s + o
    shape = tuple(np.ceil((turned.max(0) - lo) / s).astype(int) + 1)
    out = ndimage.affine_transform(v.array.astype(np.float32), (R.T * s[None, :]) / s[:, None],
                                   (R.T @ (lo - centre) + centre - o) / s, output_shape=shape,
                                   order=1, cval=float(v.array.min()))
    w = dataclasses.replace(v, array=out, origin=lo)
    return w, moved_spec(spec, R, np.zeros(3), centre), R, centre


def _advance(tmp_path, name, mesh):
    rep = tmp_path / f"{name}.json"
    r = _run(SIMULATE + ["--mesh", str(mesh), "--p", "maxilla.advance_mm=5", "--report",
                         str(rep)])
    assert r.returncode == 0, r.stderr[-2000:]
    sim = json.loads(rep.read_text())
    rest = {k: np.array(p) for k, p in sim["landmarks_rest"].items()}
    return rest, {k: np.array(p) - rest[k] for k, p in sim["landmarks"].items()}


@needs_cranium
@pytest.mark.parametrize("resolution", ["medium", "paper"])
def test_cranium_moved_on_the_voxel_grid_predicts_the_same(tmp_path, request, resolution):
    """Cranium moved by a quarter and by half a voxel on its grid, its planes and crop moved
    with it, through ct_scene.py and simulate.py (a 5 mm LeFort I advance): every landmark's
    predicted motion within `MOTION_MM` of the unmoved scan's (0.3 mm at medium, 0.2 at
    paper), and its rest position, moved back, within a voxel. Before Sn was the profile's
    sharpest turn, Sn's motion moved by 0.5-0.9 mm and its rest position by 3.5-4.1 mm."""
    v = _cranium()
    spec0 = json.loads((EXAMPLES / "cranium.json").read_text())
    if resolution == "paper":   # the module's unmoved scene and advance, built once
        rest0, motion0 = request.getfixturevalue("cranium_paper_advance")
    else:
        rest0, motion0 = _advance(tmp_path, "base",
                                  _scene(tmp_path / "base", CRANIUM, spec0, resolution)["mesh"])
    for voxels in (0.25, 0.5):
        w, spec, t = _shifted(v, spec0, voxels)
        rep = _scene(tmp_path / f"s{voxels}", _write(w, tmp_path / f"s{voxels}.mha"), spec,
                     resolution)
        rest, motion = _advance(tmp_path, f"s{voxels}", rep["mesh"])
        assert {"N", "Prn", "Sn"} <= set(rest) & set(rest0), (rest, rest0)
        for k in set(rest) & set(rest0):
            assert np.linalg.norm(rest[k] - t - rest0[k]) <= _voxel(v), (voxels, k)
            d = np.linalg.norm(motion[k] - motion0[k])
            assert d <= MOTION_MM[resolution], (voxels, k, motion[k], motion0[k])


def test_synthetic_ct_moved_on_the_voxel_grid_predicts_the_same(tmp_path):
    """The synthetic CT (1.25 mm voxels, a scanner's partial volume: `test_frame._head_ct`)
    sampled with the head moved by a quarter and half a voxel and pitched 5 and 10 degrees,
    its planes and crop moved with it, through ct_scene.py and simulate.py at paper (a 5 mm
    LeFort I advance): each landmark's predicted motion within 0.2 mm of the unmoved scan's,
    and its rest position, moved back, within a voxel. Before Ls, Li and Pg were the bulges
    that stand out most, they moved 10-20 mm; before Pg's plateau was a voxel deep
    (`meshes.landmarks.CHIN_PLATEAU`), its rest position moved 2.9-3.2 mm along the chin's
    front, flat within a voxel over 15 mm; before the cuts' band edges followed their lines
    (`meshes.ct.snap_to_edges`), Sn's motion differed by 0.22 mm on the quarter voxel."""
    from test_frame import CENTRE, _head_ct, _motion, _rotation

    from meshes.synthetic import synthetic_scene_file

    voxel = 1.25
    spec0 = synthetic_scene_file("class1")
    moves = {"base": np.eye(4)}
    for f in (0.25, 0.5):
        moves[f"shift{f}"] = np.eye(4)
        moves[f"shift{f}"][:3, 3] = f * voxel
    for deg in (5.0, 10.0):
        moves[f"pitch{deg:g}"] = _motion(_rotation(deg, 0, 0), CENTRE)
    got = {}
    for name, M in moves.items():
        R, t = M[:3, :3], M[:3, 3]
        ct = _head_ct(M, voxel, ears_and_orbits=True)
        rep = _scene(tmp_path / name, _write(ct, tmp_path / f"{name}.mha"),
                     moved_spec(spec0, R, t, np.zeros(3)), "paper")
        rest, motion = _advance(tmp_path, name, rep["mesh"])
        got[name] = ({k: R.T @ (p - t) for k, p in rest.items()},
                     {k: R.T @ d for k, d in motion.items()})
    rest0, motion0 = got.pop("base")
    assert {"N", "Prn", "Sn", "Ls", "Li", "Pg", "Me"} <= set(rest0), rest0
    assert not {"T_L", "T_R"} & set(rest0), rest0   # canals without a pinna: no ear
    for name, (rest, motion) in got.items():
        assert set(rest) == set(rest0), (name, sorted(rest), sorted(rest0))
        for k in set(rest) & set(rest0):
            d = np.linalg.norm(motion[k] - motion0[k])
            assert d <= MOTION_MM["paper"], (name, k, motion[k], motion0[k])
            assert np.linalg.norm(rest[k] - rest0[k]) <= _voxel(ct), (name, k)


@needs_cranium
@pytest.mark.parametrize("degrees", [5.0, 10.0])
def test_cranium_pitched_keeps_its_landmarks(tmp_path, cranium_paper, cranium_paper_advance,
                                             degrees):
    """Cranium pitched by 5 and 10 degrees in the scanner (`_pitched`), its planes and crop
    turned with it, through ct_scene.py at paper: each landmark, turned back, within a voxel
    of the untilted scan's. N's hollow put it 2.15 mm off at 5 degrees before its own plateau
    (`meshes.landmarks.HOLLOW_PLATEAU_MM`). Each landmark's predicted motion under a 5 mm
    LeFort I (simulate.py), turned back, within 0.2 mm of the untilted scan's: Sn's differed
    by 0.32 mm at 5 degrees with the skin layer on the nasal lining and the cuts' band edges
    on ragged rows of facets (`meshes.ct.LINING_MM`, `meshes.ct.snap_to_edges`)."""
    w, spec, R, centre = _pitched(_cranium(), json.loads((EXAMPLES / "cranium.json")
                                                         .read_text()), degrees)
    rep = _scene(tmp_path, _write(w, tmp_path / "pitched.mha"), spec, "paper")
    want = cranium_paper["landmarks"]
    assert {"N", "Prn", "Sn"} <= set(rep["landmarks"]) & set(want), rep["landmarks"]
    for k in set(rep["landmarks"]) & set(want):
        back = R.T @ (np.array(rep["landmarks"][k]) - centre) + centre
        assert np.linalg.norm(back - want[k]) <= _voxel(w), (k, back, want[k])
    _, motion = _advance(tmp_path, "pitched", rep["mesh"])
    _, motion0 = cranium_paper_advance
    for k in set(motion) & set(motion0):
        d = np.linalg.norm(R.T @ motion[k] - motion0[k])
        assert d <= MOTION_MM["paper"], (k, R.T @ motion[k], motion0[k])


@needs_cranium
def test_a_landmark_the_view_cuts_is_left_out_with_its_reason(tmp_path):
    """Cranium cropped 17.5 mm below Prn (no Ls): Sn is left out and the report says why;
    the default goal that needs it is refused in one line."""
    spec = json.loads((EXAMPLES / "cranium.json").read_text())
    spec["crop"]["min"][2] = 15.0
    rep = _scene(tmp_path / "short", CRANIUM, spec, "coarse")
    assert "Sn" not in rep["landmarks"] and {"N", "Prn"} <= set(rep["landmarks"])
    assert "field of view" in rep["landmarks_left_out"]["Sn"], rep["landmarks_left_out"]
    r = _run(PLAN + ["--mesh", rep["mesh"], "--goal", "midface-advance", "--params-used",
                     "maxilla.advance_mm", "--out", str(tmp_path / "plan")])
    _one_line_error(r, "Sn")
