"""Treatment model: built-in rigid blendshapes and sculpted ones from surface files."""

import meshio
import numpy as np
import pytest

from fem.verification import taylor_test
from inverse.treatment import Treatment, rigid_treatment, sculpted_param
from meshes.anatomy import segment_tags
from meshes.errors import InputError


def _surfaces(anatomy, tmp_path, shift):
    """The mandible's rest bone surface and a 'sculpted' copy moved by ``shift`` (mm)."""
    tris = anatomy.facets[np.isin(anatomy.facet_tags, segment_tags(anatomy.segments["mandible"]))]
    used, local = np.unique(tris, return_inverse=True)
    pts = anatomy.points[used]
    rest, mod = tmp_path / "rest.obj", tmp_path / "mod.obj"
    meshio.Mesh(pts, [("triangle", local.reshape(-1, 3))]).write(rest)
    meshio.Mesh(pts + shift, [("triangle", local.reshape(-1, 3))]).write(mod)
    return rest, mod


def test_sculpted_blendshape_equals_the_rigid_motion_it_sculpts(tiny_anatomy, tmp_path):
    from inverse.scene import Scene

    rest, mod = _surfaces(tiny_anatomy, tmp_path, [0.0, 2.0, 0.0])
    sculpted = Treatment([sculpted_param("chin_forward", "mandible", rest, mod)])
    s1 = Scene(tiny_anatomy, treatment=sculpted)
    s1.solve([1.5])
    s2 = Scene(tiny_anatomy, treatment=rigid_treatment(("mandible",), ["advance_mm"]))
    s2.solve([3.0])
    for name, x in s1.landmarks().items():
        np.testing.assert_allclose(x, s2.landmarks([name])[name], atol=1e-6)
    assert s1.param_names == ["chin_forward"]


def test_sculpted_surfaces_must_correspond(tiny_anatomy, tmp_path):
    rest, _ = _surfaces(tiny_anatomy, tmp_path, [0.0, 0.0, 0.0])
    m = meshio.read(rest)
    bad = tmp_path / "bad.obj"
    meshio.Mesh(m.points[:-3], [("triangle", m.cells[0].data[:-5] % (len(m.points) - 3))]) \
        .write(bad)
    with pytest.raises(InputError, match="correspond 1:1"):
        sculpted_param("x", "mandible", rest, bad)
    with pytest.raises(InputError, match="cannot read"):
        sculpted_param("x", "mandible", rest, tmp_path / "missing.obj")


def test_maxilla_group_moves_both_halves_about_their_mean_pivot(tiny_anatomy):
    """``maxilla.*`` moves both LeFort I halves as one piece: at p = 0 (where the exact
    motions' derivative is the linearised blendshape) a translation is the sum of the
    halves' translations, a rotation turns both about the mean of their pivots."""
    from fem.domain import create_domain

    dom = create_domain(tiny_anatomy)
    t = rigid_treatment()
    assert "maxilla.roll_deg" in t.names and "maxilla_L.roll_deg" in t.names
    zero = np.zeros(len(t.names))
    B = t.goal_map(dom).jacobian(zero).reshape(len(dom.X), 3, -1)
    lin = rigid_treatment(linear=True)
    assert lin.names == t.names
    np.testing.assert_allclose(lin.goal_map(dom).jacobian(zero).reshape(B.shape), B,
                               atol=1e-12)
    col = {n: B[:, :, i] for i, n in enumerate(t.names)}
    np.testing.assert_array_equal(col["maxilla.advance_mm"],
                                  col["maxilla_L.advance_mm"] + col["maxilla_R.advance_mm"])
    halves = np.any(col["maxilla.advance_mm"] != 0, axis=1)
    c = 0.5 * (np.asarray(dom.pivots["maxilla_L"]) + np.asarray(dom.pivots["maxilla_R"]))
    expected = np.deg2rad(1.0) * np.cross([0.0, 1.0, 0.0], dom.X[halves] - c)
    np.testing.assert_allclose(col["maxilla.roll_deg"][halves], expected, atol=1e-12)
    assert not np.any(col["maxilla.roll_deg"][~halves])


PIVOTS = {"mandible": np.array([0.0, 40.0, -55.0]), "maxilla_L": np.array([15.0, 50.0, -20.0]),
          "maxilla_R": np.array([-15.0, 50.0, -20.0])}
SIX = ["advance_mm", "lateral_mm", "vertical_mm", "pitch_deg", "roll_deg", "yaw_deg"]


def test_exact_rigid_motion_keeps_the_segment_rigid(tiny_anatomy):
    """A 12° pitch: the exact goals keep every distance between mandible vertices; the
    linearised blendshapes stretch them by up to √(1 + θ²) - 1 = 2.17 %."""
    from fem.domain import create_domain

    dom = create_domain(tiny_anatomy)
    blocks = dom.facet_blocks([dom.segments["mandible"]])
    X = dom.X[blocks]
    rest = np.linalg.norm(X[:, None] - X[None], axis=-1)
    off = rest > 1.0
    stretch = {}
    for linear in (False, True):
        t = rigid_treatment(("mandible",), ["pitch_deg"], linear=linear)
        x = X + t.goal_map(dom).goal(np.array([12.0])).reshape(-1, 3)[blocks]
        d = np.linalg.norm(x[:, None] - x[None], axis=-1)
        stretch[linear] = np.abs(d[off] / rest[off] - 1).max()
    assert stretch[False] < 1e-12, stretch
    assert abs(stretch[True] - (np.hypot(1, np.deg2rad(12)) - 1)) < 1e-3, stretch


@pytest.mark.parametrize("tilted", [False, True])
def test_goal_jacobian_is_the_derivative_of_the_goals(tiny_anatomy, rng, tilted):
    """Taylor test of ∂x̂/∂p at rotations of 5-10° (groups, members, occlusion), in the
    scene's axes and in a head frame tilted 8° in pitch, 6° in yaw: the remainder falls at
    rate 2 with the Jacobian, 1 without."""
    from fem.domain import create_domain

    dom = create_domain(tiny_anatomy)
    t = rigid_treatment(occlusion=tiny_anatomy.occlusion)
    if tilted:
        a, b = np.radians(8.0), np.radians(6.0)
        H = np.eye(4)
        H[:3, :3] = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0],
                              [0, 0, 1]]) @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)],
                                                      [0, np.sin(a), np.cos(a)]])
        H[:3, 3] = [3.0, -20.0, 7.0]
        t = t.in_frame(H)
    gm = t.goal_map(dom)
    p = rng.uniform(-3, 3, len(t.names))
    rot = [i for i, n in enumerate(t.names) if n.endswith("_deg")]
    p[rot] = rng.choice([-1, 1], len(rot)) * rng.uniform(5, 10, len(rot))
    d = rng.standard_normal(len(p))
    rate1, rate2 = taylor_test(gm.goal, p, d, gm.jacobian(p) @ d, 0.5 * 0.5 ** np.arange(5))
    assert np.all(np.abs(rate1 - 1) < 0.1), rate1
    assert np.all(np.abs(rate2 - 2) < 0.1), rate2


@pytest.mark.parametrize("occluded", [False, True])
def test_parameters_to_transforms_and_back(occluded, rng):
    """p -> {segment: 4x4} -> p to 1e-9, for each segment's own motions (occlusion free)
    and for the jaws with the mandible in occlusion; the occlusion holds at any p."""
    occ = np.eye(4)
    occ[:3, :3] = rigid_treatment(("mandible",), ["yaw_deg"]).transforms(
        [6.0], {"mandible": np.zeros(3)})["mandible"][:3, :3]
    occ[:3, 3] = [-4.0, -8.0, 2.0]
    if occluded:
        t = rigid_treatment(occlusion=occ).subset([f"jaws.{m}" for m in SIX])
    else:
        t = rigid_treatment(groups=False)
    p = rng.uniform(-8, 8, len(t.names))
    T = t.transforms(p, PIVOTS)
    np.testing.assert_allclose(t.params_from_transforms(T, PIVOTS), p, atol=1e-9)
    if occluded:
        for seg in ("maxilla_L", "maxilla_R"):
            np.testing.assert_allclose(np.linalg.inv(T[seg]) @ T["mandible"], occ, atol=1e-12)
    for s, M in T.items():   # rigid
        np.testing.assert_allclose(M[:3, :3].T @ M[:3, :3], np.eye(3), atol=1e-12)


def test_transforms_that_the_parameters_cannot_reach_or_that_are_not_rigid():
    from meshes.transforms import rigid

    t = rigid_treatment().subset(["mandible.advance_mm"])
    T = np.eye(4)
    T[1, 3] = 3.0
    np.testing.assert_allclose(t.params_from_transforms({"mandible": T}, PIVOTS), [3.0])
    T[2, 3] = 1.0
    with pytest.raises(InputError, match="cannot be reached"):
        t.params_from_transforms({"mandible": T}, PIVOTS)
    with pytest.raises(InputError, match="unknown segment"):
        t.params_from_transforms({"chin": T}, PIVOTS)
    with pytest.raises(InputError, match="not rigid"):
        rigid(np.diag([1.1, 1.0, 1.0, 1.0]))
    with pytest.raises(InputError, match="last row"):
        rigid(np.ones((4, 4)))


def test_itk_transform_files(tmp_path):
    """A 3D Slicer file (LPS, resampling convention) reads as the segment's motion in our
    frame: a resampling translation of +5 mm along LPS y (posterior) is a 5 mm advance; our
    writer's files read back to the same 4x4."""
    from meshes.transforms import itk_text, read_itk, read_transforms

    f = tmp_path / "mandible.tfm"
    f.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                 "Transform: AffineTransform_double_3_3\n"
                 "Parameters: 1 0 0 0 1 0 0 0 1 0 5 0\nFixedParameters: 0 0 0\n")
    T = read_itk(f)
    np.testing.assert_allclose(T[:3, 3], [0, 5, 0], atol=1e-12)
    M = rigid_treatment().transforms(np.linspace(-5, 5, 30), PIVOTS)["mandible"]
    f.write_text(itk_text(M))
    np.testing.assert_allclose(read_itk(f), M, atol=1e-12)
    assert set(read_transforms(f)) == {"mandible"}
    (tmp_path / "t.json").write_text('{"maxilla_L": "mandible.tfm", "mandible": %s}'
                                     % np.eye(4).tolist())
    got = read_transforms(tmp_path / "t.json")
    np.testing.assert_allclose(got["maxilla_L"], M, atol=1e-12)
    f.write_text(itk_text(M).replace("AffineTransform", "BSplineTransform"))
    with pytest.raises(InputError, match="not supported"):
        read_itk(f)
    f.write_text("hello")
    with pytest.raises(InputError, match="not an ITK transform file"):
        read_itk(f)


def test_synthetic_occlusion_undoes_the_malocclusion():
    """class3: the mandible 7 mm forward and 2 mm down, the maxilla 2 mm back: the final
    occlusion moves the mandible 9 mm back and 2 mm up relative to the maxilla."""
    from meshes.synthetic import CASES, case_occlusion

    np.testing.assert_allclose(case_occlusion(CASES["class3"]),
                               [[1, 0, 0, 0], [0, 1, 0, -9], [0, 0, 1, 2], [0, 0, 0, 1]],
                               atol=1e-12)
    np.testing.assert_allclose(case_occlusion(CASES["class1"]), np.eye(4), atol=1e-12)
