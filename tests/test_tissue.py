"""Tissue classes per cell (`meshes.tissue`) and their materials (`fem.material.Tissues`): the
skin layer's share against geometry, a layered block against the closed form, files and bad
input."""

import json

import numpy as np
import pytest
from test_contact import H_MM, L_MM, MANDIBLE, _block, _scene

from fem.material import HOMOGENEOUS, Tissues, material_from_spec
from meshes.anatomy import FIXED, TEETH_OFFSET
from meshes.errors import InputError, MeshError
from meshes.tissue import SAMPLES, SKIN_MM, TISSUES, surface_depth, tissue_fractions


def _top(block):
    """The block's top facets (z = H), which stand for the skin here."""
    return block.facets[block.facet_tags == FIXED]


def test_samples_lie_inside_the_tet_and_depth_is_exact():
    assert SAMPLES.shape == (10, 4) and np.allclose(SAMPLES.sum(axis=1), 1)
    assert SAMPLES.min() > 0 and np.allclose(SAMPLES.mean(axis=0), 0.25)
    block = _block(3, MANDIBLE + TEETH_OFFSET)
    rng = np.random.default_rng(1)
    q = rng.uniform([0, 0, 0], [L_MM, L_MM, H_MM], (500, 3))
    d = surface_depth(q, block.points, _top(block), within=SKIN_MM)
    near = H_MM - q[:, 2] < SKIN_MM
    np.testing.assert_allclose(d[near], H_MM - q[near, 2], atol=1e-12)
    assert np.all(d[~near] >= SKIN_MM - 1e-12)


@pytest.mark.parametrize("n", [3, 5])
def test_skin_layer_share_is_its_thickness_over_the_height(n):
    """Under a flat skin, the layer's share of the whole volume is t / H on any mesh (each
    cell it crosses keeps its share, to the ten samples' resolution); fat and lean tissue
    follow the rule given."""
    block = _block(n, MANDIBLE + TEETH_OFFSET)
    f = tissue_fractions(block.points, block.cells, _top(block), lambda x: x[:, 2] < 1.0)
    assert f.shape == (block.n_cells, 3) and np.allclose(f.sum(axis=1), 1)
    share = f.mean(axis=0)   # equal cell volumes
    assert abs(share[0] - SKIN_MM / H_MM) < 0.5 / n, share   # ~ a tenth of a cell layer
    assert abs(share[1] - 1.0 / H_MM) < 0.5 / n, share


def _layers_closed_form(delta, k, layers):
    """Bottom displacement w (mm) and each layer's stretch of a laterally confined stack of
    Neo-Hookean layers [(thickness, mu, lmbda)], held at the top, pushed up by ``delta`` at
    the bottom through the penalty k: one nominal stress P through all layers,
    P = mu (s - 1/s) + lmbda ln s / s in each, w = Σ t (1 - s), P = k (w - delta)."""
    from scipy.optimize import brentq

    def stretch(P, mu, lm):
        return brentq(lambda s: mu * (s - 1 / s) + lm * np.log(s) / s - P, 1e-3, 1.0)

    def w_of(P):
        return sum(t * (1 - stretch(P, mu, lm)) for t, mu, lm in layers)

    P = brentq(lambda P: P - k * (w_of(P) - delta), -k * delta, 0.0)
    return w_of(P), [stretch(P, mu, lm) for _, mu, lm in layers]


def test_layered_block_matches_the_closed_form():
    """A confined block of fat (z < 1 mm), lean tissue and a 2 mm skin under its held top,
    pushed 0.4 mm by a plate. Where the cells follow the layers (n = 4) the displacement is
    the closed form's to the penalty's error (test_contact: O(1/k), 8e-5 mm here). Where
    cells straddle the layers their mixed moduli err: the RMS error falls about as the
    cells' size (n = 3 to 13: 0.010 to 0.0028 mm)."""
    from fem.forms import DEFAULT_PENALTY

    delta, m = 0.4, Tissues()
    layers = [(1.0, m.fat.mu, m.fat.lmbda), (1.0, m.muscle.mu, m.muscle.lmbda),
              (SKIN_MM, m.skin.mu, m.skin.lmbda)]
    w, s = _layers_closed_form(delta, DEFAULT_PENALTY, layers)
    bounds = np.cumsum([0.0] + [t for t, _, _ in layers])

    def exact(z):   # u_z: the compression of the layers above z
        return sum((1 - si) * np.clip(bounds[i + 1] - np.maximum(z, bounds[i]), 0, None)
                   for i, si in enumerate(s))

    worst, rms = {}, {}
    for n in (4, 3, 13):
        block = _block(n, MANDIBLE + TEETH_OFFSET)
        block.tissues = tissue_fractions(block.points, block.cells, _top(block),
                                         lambda x: x[:, 2] < 1.0)
        scene = _scene(block, "sliding", material="tissues")
        scene.solve({"mandible.vertical_mm": delta})
        X, u = scene.domain.X, scene.eq.u.x.array.reshape(-1, 3)
        err = u[:, 2] - exact(X[:, 2])
        worst[n], rms[n] = np.abs(err).max(), np.sqrt(np.mean(err ** 2))
    assert worst[4] < 1e-4, worst
    rate = np.log(rms[3] / rms[13]) / np.log(13 / 3)
    assert rate > 0.7, (rate, rms)
    # the homogeneous material misses the layered answer by far more than the mixing
    homo = _layers_closed_form(delta, DEFAULT_PENALTY,
                               [(H_MM, HOMOGENEOUS.mu, HOMOGENEOUS.lmbda)])[0]
    assert abs(homo - w) < 1e-3   # the plate's position: the penalty holds it either way
    assert np.abs(exact(np.array([1.0, 2.0])) - delta * (1 - np.array([1.0, 2.0]) / H_MM)
                  ).min() > 10 * rms[13]


def test_voigt_mean_and_material_specs(tmp_path):
    m = Tissues()
    mu, lm = m.lame(np.array([[1, 0, 0], [0, 0.5, 0.5]]))
    assert mu[0] == pytest.approx(m.skin.mu)
    assert mu[1] == pytest.approx(0.5 * (m.fat.mu + m.muscle.mu))
    assert lm[1] == pytest.approx(0.5 * (m.fat.lmbda + m.muscle.lmbda))
    assert material_from_spec("homogeneous") == HOMOGENEOUS
    assert material_from_spec("tissues") == Tissues()
    f = tmp_path / "m.json"
    f.write_text(json.dumps({"skin": {"E": 50}, "fat": {"E": 2, "nu": 0.45}}))
    got = material_from_spec(str(f))
    assert got.skin.E == 50 and got.skin.nu == 0.47 and got.fat.nu == 0.45
    assert got.muscle == Tissues().muscle
    for spec, match in [({"skin": {"E": -1}}, "positive"), ({"skin": {"nu": 0.5}}, "nu"),
                        ({"bone": {"E": 1}}, "keys"), ({"fat": {"G": 1}}, "fat"),
                        ({"fat": {"E": "soft"}}, "fat"), ([1], "keys")]:
        f.write_text(json.dumps(spec))
        with pytest.raises(InputError, match=match) as e:
            material_from_spec(str(f))
        assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="material"):
        material_from_spec("rubber")


def test_anatomy_files_keep_tissues(tmp_path, tiny_anatomy):
    """The synthetic head's fractions survive save/load and the .vtu + sidecar a CT scene is
    written to; a scene on a mesh without them refuses ``material="tissues"``; bad
    fractions are refused."""
    from meshes.anatomy import Anatomy
    from meshes.external import load_tet_mesh, write_tet_mesh

    a = tiny_anatomy
    assert a.tissues is not None and a.material == "homogeneous"
    a.save(tmp_path / "a.npz")
    b = Anatomy.load(tmp_path / "a.npz")
    np.testing.assert_array_equal(b.tissues, a.tissues)
    write_tet_mesh(a, tmp_path / "a.vtu")
    c = load_tet_mesh(tmp_path / "a.vtu")
    np.testing.assert_allclose(c.tissues, a.tissues)
    assert json.loads((tmp_path / "a.vtu.json").read_text())["tissue_data"] == list(TISSUES)
    bad = Anatomy(a.points, a.cells, a.facets, a.facet_tags, dict(a.segments),
                  dict(a.pivots), dict(a.landmarks), tissues=a.tissues[:, :2])
    with pytest.raises(MeshError, match="tissue fractions"):
        bad.validate()
    bad.tissues, bad.material = None, "tissues"
    with pytest.raises(MeshError, match="tissue fractions"):
        bad.validate()


@pytest.mark.scripts
def test_material_option_of_the_scripts(tmp_path, tiny_anatomy):
    """simulate.py: the synthetic heads are homogeneous by default, ``--material tissues``
    is reported and changes the answer; a mesh without tissue classes, or a material file
    out of range, is one line of error, exit 2, nothing written."""
    from test_scripts import SIM, _run

    from meshes.anatomy import Anatomy
    from meshes.external import write_tet_mesh

    pg = {}
    for material in (None, "tissues"):
        rep = tmp_path / f"{material}.json"
        r = _run(SIM + ["--p", "mandible.advance_mm=4", "--report", str(rep)]
                 + ([] if material is None else ["--material", material]))
        assert r.returncode == 0, r.stderr[-2000:]
        out = json.loads(rep.read_text())
        assert out["material"] == (material or "homogeneous")
        pg[material] = np.array(out["landmarks"]["Li"])
    assert np.linalg.norm(pg["tissues"] - pg[None]) > 1e-3, pg

    a = tiny_anatomy
    plain = Anatomy(a.points, a.cells, a.facets, a.facet_tags, dict(a.segments),
                    dict(a.pivots), dict(a.landmarks))
    mesh = tmp_path / "plain.vtu"
    write_tet_mesh(plain, mesh)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"skin": {"E": 0}}))
    for args, match in [(["--mesh", str(mesh), "--material", "tissues"], "tissue classes"),
                        (SIM[2:4] + ["--material", str(bad)], "skin")]:
        rep = tmp_path / "r.json"
        r = _run(SIM[:2] + args + ["--p", "mandible.advance_mm=1", "--report", str(rep)])
        errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
        assert r.returncode == 2 and len(errors) == 1 and match in errors[0], r.stderr[-2000:]
        assert not rep.exists()


def test_a_cavity_open_through_a_nostril_lies_under_the_envelope():
    """A ball of tissue (radius 30 mm, 1 mm voxels) with a cavity (radius 8 mm, 20 mm deep)
    open to the air around it through a nostril 5 mm wide in each axial slice it spans (air
    no axial slice connects to the outside is airway, `meshes.segment`): the cavity's air
    lies more than `meshes.ct.LINING_MM` under the face's envelope (its lining carries no
    skin layer), the air at the ball's surface and at the nostril's mouth within one of its
    voxels (2 mm: `meshes.segment.ENVELOPE_VOXEL_MM`)."""
    from meshes import segment as seg
    from meshes.ct import LINING_MM

    g = np.stack(np.meshgrid(*[np.arange(-40.0, 41.0)] * 3, indexing="ij"), axis=-1)
    r = np.linalg.norm(g, axis=-1)
    cavity = np.linalg.norm(g - [10.0, 0.0, 0.0], axis=-1) <= 8.0
    nostril = (g[..., 0] >= 10.0) & (np.abs(g[..., 1]) <= 2.5) & (np.abs(g[..., 2]) <= 8.5)
    body = (r <= 30.0) & ~cavity & ~nostril
    labels = seg.label_volume(seg.Volume(body.astype(np.int16), np.ones(3), -40.0 * np.ones(3)),
                              body, np.zeros_like(body))
    assert (labels[1:-1, 1:-1, 1:-1][cavity] == seg.OUTSIDE).all()   # open to the air
    depth = seg.envelope_depth(seg.Volume(labels, np.ones(3), -41.0 * np.ones(3)))
    voxel = depth.spacing.max()   # the envelope's own (`meshes.segment.ENVELOPE_VOXEL_MM`)
    assert depth.at(g[cavity]).min() > LINING_MM and depth.at([[10.0, 0, 0]])[0] > 2 * LINING_MM
    mouth = nostril & (r > 29.0) & (r <= 31.0)
    assert depth.at(g[mouth]).max() <= voxel + 1e-6
    face = (np.abs(r - 30.5) < 0.5) & ~nostril & (g[..., 0] < 0)
    assert depth.at(g[face]).max() <= voxel + 1e-6
