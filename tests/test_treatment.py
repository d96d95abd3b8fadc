"""Treatment model: built-in rigid blendshapes and sculpted ones from surface files."""

import meshio
import numpy as np
import pytest

from inverse.treatment import Treatment, rigid_treatment, sculpted_param
from meshes.errors import InputError


def _surfaces(anatomy, tmp_path, shift):
    """The mandible's rest bone surface and a 'sculpted' copy moved by ``shift`` (mm)."""
    tris = anatomy.facets[anatomy.facet_tags == anatomy.segments["mandible"]]
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
    """``maxilla.*`` moves both LeFort I halves as one piece: a translation is the sum of the
    halves' translations, a rotation turns both about the mean of their pivots."""
    from fem.domain import create_domain

    dom = create_domain(tiny_anatomy)
    t = rigid_treatment()
    assert "maxilla.roll_deg" in t.names and "maxilla_L.roll_deg" in t.names
    B = t.matrix(dom).reshape(len(dom.X), 3, -1)
    col = {n: B[:, :, i] for i, n in enumerate(t.names)}
    np.testing.assert_array_equal(col["maxilla.advance_mm"],
                                  col["maxilla_L.advance_mm"] + col["maxilla_R.advance_mm"])
    halves = np.any(col["maxilla.advance_mm"] != 0, axis=1)
    c = 0.5 * (np.asarray(dom.pivots["maxilla_L"]) + np.asarray(dom.pivots["maxilla_R"]))
    expected = np.deg2rad(1.0) * np.cross([0.0, 1.0, 0.0], dom.X[halves] - c)
    np.testing.assert_allclose(col["maxilla.roll_deg"][halves], expected, atol=1e-12)
    assert not np.any(col["maxilla.roll_deg"][~halves])
    sub = t.subset(["mandible.advance_mm", "maxilla.vertical_mm"])
    assert sub.active_segments == ["mandible", "maxilla_L", "maxilla_R"]
