"""Sliding contact of tissue on teeth (`fem.equilibrium`): a block of tissue on a rigid plate
against the closed-form answer, and the teeth label of the synthetic heads."""

import numpy as np
import pytest

from meshes.anatomy import FIXED, SKIN, TEETH_OFFSET, Anatomy, boundary_facets

L_MM, H_MM = 10.0, 4.0   # the block's width and height
MANDIBLE, MAXILLA_L = 11, 12


class Block(Anatomy):
    """A block of tissue, not a head: it has no skin or landmarks, and its rollers touch the
    held top, which a head's segments may not (`Anatomy.validate`'s rules are anatomy's,
    not the mechanics'), so its checks are skipped."""

    def validate(self):
        return self


def _block(n: int, lateral: int) -> Block:
    """[0, L]² × [0, H] in n × n × n cubes of six tetrahedra; the bottom (z = 0) is the
    mandible's teeth (the plate), the top is held, the sides are ``lateral`` (a tag)."""
    g = np.stack(np.meshgrid(*(np.linspace(0, s, n + 1) for s in (L_MM, L_MM, H_MM)),
                             indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    cells = []
    for i, j, k in np.ndindex(n, n, n):
        c = idx[i:i + 2, j:j + 2, k:k + 2]
        v0, v7 = c[0, 0, 0], c[1, 1, 1]
        for a, b in ((c[1, 0, 0], c[1, 1, 0]), (c[1, 0, 0], c[1, 0, 1]),
                     (c[0, 1, 0], c[1, 1, 0]), (c[0, 1, 0], c[0, 1, 1]),
                     (c[0, 0, 1], c[1, 0, 1]), (c[0, 0, 1], c[0, 1, 1])):   # Kuhn
            cells.append([v0, a, b, v7])
    cells = np.array(cells)
    vol = np.linalg.det(g[cells[:, 1:]] - g[cells[:, :1]])
    cells[vol < 0] = cells[vol < 0][:, [0, 2, 1, 3]]
    facets = boundary_facets(cells)
    z = g[facets][:, :, 2]
    tags = np.full(len(facets), lateral, dtype=np.int32)
    tags[np.all(z == 0, axis=1)] = MANDIBLE + TEETH_OFFSET
    tags[np.all(z == H_MM, axis=1)] = FIXED
    return Block(g, cells, facets, tags, {"mandible": MANDIBLE},
                 {"mandible": np.array([L_MM / 2, L_MM / 2, 0.0])}, {}, name=f"block {n}")


def _scene(block, contact, **kw):
    from inverse.scene import Scene
    from inverse.treatment import rigid_treatment

    return Scene(block, rigid_treatment(("mandible",), ("lateral_mm", "vertical_mm")),
                 contact=contact, equilibrium=dict(method="newton", xtol=1e-10, frtol=1e-10), **kw)


def test_plate_moved_along_itself_leaves_a_sliding_block_at_rest():
    """The plate moved 2 mm along x: sliding tissue stays where it was (its energy is 0 at
    rest: no tangential reaction); glued tissue is sheared with it."""
    block = _block(3, SKIN)
    moved = {}
    for contact in ("sliding", "glued"):
        scene = _scene(block, contact)
        scene.solve({"mandible.lateral_mm": 2.0})
        moved[contact] = np.abs(scene.eq.u.x.array).max()
    assert moved["sliding"] < 1e-10, moved
    assert moved["glued"] > 1.9, moved


def _confined(delta: float, k: float, mu: float, lmbda: float) -> float:
    """The bottom's displacement w (mm) of a block confined laterally, held at the top and
    pushed up by ``delta`` (mm) by a plate through the penalty k: the root of
    H ψ'(λ) = ... , i.e. P_zz(λ) = k (w - δ) with λ = 1 - w/H and, for F = diag(1, 1, λ),
    P_zz = μ (λ - 1/λ) + λ_L ln λ / λ (compressible Neo-Hookean)."""
    from scipy.optimize import brentq

    def balance(w):
        lam = 1 - w / H_MM
        return mu * (lam - 1 / lam) + lmbda * np.log(lam) / lam - k * (w - delta)

    return brentq(balance, 0.0, delta)


def test_plate_pushed_into_a_confined_block_matches_the_closed_form():
    """The plate pushed 0.4 mm into a block whose sides slide on rollers (confined
    compression: u = w (1 - z/H) e_z, w short of 0.4 mm by the penalty's gap P_zz / k): the
    block follows. P1 holds this linear field exactly (a patch test), so refining the mesh
    changes nothing; what is left is the penalty's, O(1/k): the rollers yield to the
    lateral stress by σ_xx / k, which the held top does not follow. It falls as k grows and
    is below 1e-4 mm at the default k."""
    from fem.forms import DEFAULT_PENALTY
    from fem.material import NeoHookean

    m, delta = NeoHookean(), 0.4
    penalties = DEFAULT_PENALTY * np.array([0.01, 0.1, 1.0])
    errors = np.zeros((len(penalties), 2))
    for a, k in enumerate(penalties):
        w = _confined(delta, k, m.mu, m.lmbda)
        for b, n in enumerate((2, 4)):
            scene = _scene(_block(n, MANDIBLE + TEETH_OFFSET), "sliding", penalty=k)
            scene.solve({"mandible.vertical_mm": delta})
            X, u = scene.domain.X, scene.eq.u.x.array.reshape(-1, 3)
            exact = np.zeros_like(u)
            exact[:, 2] = w * (1 - X[:, 2] / H_MM)
            errors[a, b] = np.abs(u - exact).max()
    assert np.allclose(errors[:, 0], errors[:, 1], rtol=0.1), errors   # no mesh error
    rate = np.log10(errors[:-1, 1] / errors[1:, 1])   # per decade of k
    assert np.all(np.abs(rate - 1) < 0.1), (rate, errors)
    assert errors[-1].max() < 1e-4, errors


@pytest.mark.scripts
def test_contact_option_of_the_scripts(tmp_path, tiny_anatomy):
    """simulate.py: a synthetic head's lips are glued to the teeth by default (a CT scene's
    slide: test_ct), ``--contact sliding`` lets them slide (a LeFort I advance then drags
    the subnasale less), and the report says which; on a mesh without teeth
    ``--contact sliding`` is one line of error, exit 2, nothing written."""
    import json

    from test_scripts import SIM, _run

    from meshes.anatomy import segment_tags
    from meshes.external import write_tet_mesh

    lips = {}
    for contact in (None, "sliding"):
        rep = tmp_path / f"{contact}.json"
        r = _run(SIM + ["--params-used", "maxilla.advance_mm", "--p",
                        "maxilla.advance_mm=5", "--report", str(rep)]
                 + ([] if contact is None else ["--contact", contact]))
        assert r.returncode == 0, r.stderr[-2000:]
        out = json.loads(rep.read_text())
        assert out["contact"] == (contact or "glued")
        lips[contact] = np.array(out["landmarks"]["Sn"])
    # the LeFort I segment's front is all teeth and vestibule: sliding, it pushes the
    # subnasale forward less (class1, coarse: 0.34 of the advance against 0.57)
    assert lips["sliding"][1] < lips[None][1] - 0.3, lips

    toothless = tiny_anatomy.facet_tags.copy()
    for tag in tiny_anatomy.segments.values():
        toothless[toothless == segment_tags(tag)[1]] = tag
    a = Anatomy(tiny_anatomy.points, tiny_anatomy.cells, tiny_anatomy.facets, toothless,
                dict(tiny_anatomy.segments), dict(tiny_anatomy.pivots),
                dict(tiny_anatomy.landmarks))
    mesh = tmp_path / "toothless.vtu"
    write_tet_mesh(a, mesh)
    rep = tmp_path / "toothless.json"
    r = _run(SIM[:2] + ["--mesh", str(mesh), "--p", "mandible.advance_mm=2", "--report",
                        str(rep)])
    assert r.returncode == 0 and json.loads(rep.read_text())["contact"] == "glued", r.stderr
    rep.unlink()
    r = _run(SIM[:2] + ["--mesh", str(mesh), "--contact", "sliding", "--report", str(rep)])
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert r.returncode == 2 and len(errors) == 1 and "teeth" in errors[0], r.stderr[-2000:]
    assert not rep.exists()
