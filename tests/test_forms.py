"""The energy's forms on their own (`fem.forms.EnergyForms`), on a block of tissue whose bottom
is the mandible's teeth: f is the energy's gradient and K the residual's, df/dp the
residual's derivative in p (the sliding facets' turns included), the exact goal load agrees
with -df/dp dp to first order, and an evaluation elsewhere leaves the fields as they were."""

import numpy as np
import pytest
from test_contact import _block

from fem.forms import DEFAULT_PENALTY, EnergyForms
from fem.material import HOMOGENEOUS
from fem.verification import taylor_test
from meshes.anatomy import SKIN, segment_tags

#: The tests' tier (conftest.py): one part on a block, seconds.
TIER = "unit"

#: Taylor steps: the remainders' rates are measured between these (decreasing) sizes.
STEPS = 0.02 * 0.5 ** np.arange(4)


@pytest.fixture(scope="module", params=["glued", "sliding"])
def forms(request):
    """EnergyForms of the block, the teeth glued or sliding, under exact rigid motions of the
    mandible (lateral, vertical, pitch: the turns of the sliding normals depend on p)."""
    from inverse.scene import Scene
    from inverse.treatment import rigid_treatment

    scene = Scene(_block(3, SKIN), rigid_treatment(("mandible",), ("lateral_mm", "vertical_mm",
                                                                   "pitch_deg")),
                  contact="glued")
    domain = scene.domain
    sliding = list(domain.teeth_tags) if request.param == "sliding" else []
    glued = [t for t in segment_tags(domain.segments["mandible"]) if t not in sliding]
    part = EnergyForms(domain, scene.treatment.goal_map(domain), glued, sliding, HOMOGENEOUS,
                       DEFAULT_PENALTY, 2, None)
    yield part
    part.destroy()
    scene.eq.destroy()


def _free(forms, rng, scale: float) -> np.ndarray:
    """A random owned-and-ghost displacement (mm) zero on the Dirichlet dofs."""
    d = rng.standard_normal(forms.u.x.array.shape) * scale
    for bc in forms.bcs:
        d[bc.dof_indices()[0]] = 0.0
    return d


def _vec(forms, array):
    v = forms.uvec.duplicate()
    v.array[:] = array[:v.getLocalSize()]
    return v


def _residual(forms, array) -> np.ndarray:
    x, out = _vec(forms, array), forms.b.duplicate()
    forms.residual(x, out)
    val = out.array.copy()
    x.destroy(), out.destroy()
    return val


P = np.array([0.4, -0.3, 2.0])   # mm, mm, degrees


def test_residual_is_the_energys_gradient_and_k_the_residuals(forms, rng):
    """Taylor remainders at a state away from rest: E(x + h d) - E - h f·d and
    f(x + h d) - f - h K d fall at rate 2 (at rate 1 without the derivative)."""
    forms.set_params(P)
    x0, d = _free(forms, rng, 0.05), _free(forms, rng, 1.0)
    dvec = _vec(forms, d)
    x = _vec(forms, x0)
    f = forms.b.duplicate()
    forms.residual(x, f)
    dE = f.dot(dvec)
    forms.jacobian(x, forms.A)
    Kd = forms.b.duplicate()
    forms.A.mult(dvec, Kd)
    owned = dvec.getLocalSize()
    r1, r2 = taylor_test(lambda a: forms.energy(_vec(forms, a)), x0, d, dE, STEPS)
    assert np.all(np.abs(r1 - 1) < 0.1) and np.all(np.abs(r2 - 2) < 0.1), (r1, r2)
    r1, r2 = taylor_test(lambda a: _residual(forms, a)[:owned], x0, d, Kd.array, STEPS)
    assert np.all(np.abs(r1 - 1) < 0.1) and np.all(np.abs(r2 - 2) < 0.1), (r1, r2)
    for v in (dvec, x, f, Kd):
        v.destroy()


def test_dfdp_is_the_residuals_derivative_in_p(forms, rng):
    """df/dp (df/dg dg/dp + df/dR dR/dp, at the state and p given) against central
    differences of f in p at a fixed state."""
    x0 = _free(forms, rng, 0.05)
    x = _vec(forms, x0)
    cols = [c.array.copy() for c in forms.dfdp(P, x)]
    for i, h in enumerate((1e-4, 1e-4, 1e-3)):
        e = np.zeros(3)
        e[i] = h
        forms.set_params(P + e)
        fp = _residual(forms, x0)
        forms.set_params(P - e)
        fm = _residual(forms, x0)
        fd = (fp - fm)[:len(cols[i])] / (2 * h)
        np.testing.assert_allclose(cols[i], fd, atol=1e-5 * np.abs(fd).max())
    forms.set_params(np.zeros(3))
    x.destroy()


def test_goal_load_is_the_goals_tangent_load_to_first_order(forms, rng):
    """The exact load of moving the goals from p0 to p0 + h dp at the state x0 against the
    tangent load -df/dg dg/dp h dp: their difference falls at rate 2. The sliding normals
    stay at p0 (K's normals), so the turns' df/dR dR/dp is not in it; where nothing slides,
    that is -df/dp dp (`load`)."""
    forms.set_params(P)
    x = _vec(forms, _free(forms, rng, 0.05))
    dp = np.array([1.0, -0.5, 2.0])
    forms.assemble_couplings(P, x)
    g, tangent = forms.dfdg.createVecRight(), forms.b.duplicate()
    g.array[:] = (forms.goals.jacobian(P) @ -dp)[:g.getLocalSize()]
    forms.dfdg.mult(g, tangent)
    if forms.turn is None:
        load = forms.load(-dp, P, x)
        np.testing.assert_allclose(load.array, tangent.array, atol=1e-12 * load.norm())
        load.destroy()
    owned = x.getLocalSize()

    def exact(p):
        v = forms.goal_load(P, x, p)
        try:
            return v.array[:owned].copy()
        finally:
            v.destroy()

    r1, r2 = taylor_test(exact, P, dp, tangent.array, STEPS)
    assert np.all(np.abs(r1 - 1) < 0.1) and np.all(r2 > 1.9), (r1, r2)
    for v in (g, tangent, x):
        v.destroy()


def test_evaluations_elsewhere_restore_the_fields(forms, rng):
    """`contact_load`, `goal_load` and the couplings at another p and state leave u, the
    goals and the turns as they were; an inverted state is unsound with energy +inf."""
    forms.set_params(P)
    forms.set_state(_vec(forms, _free(forms, rng, 0.05)))
    before = [forms.u.x.array.copy(), forms.goal.x.array.copy(),
              None if forms.turn is None else forms.turn.x.array.copy()]
    other = _vec(forms, _free(forms, rng, 0.05))
    for v in (forms.contact_load(-P, other), forms.goal_load(-P, other, P)):
        v.destroy()
    forms.assemble_couplings(-P, other)
    forms.dfdp(-2 * P, other)
    after = [forms.u.x.array, forms.goal.x.array,
             None if forms.turn is None else forms.turn.x.array]
    for a, b in zip(before, after):
        if a is not None:
            np.testing.assert_array_equal(a, b)
    crushed = forms.uvec.duplicate()
    crushed.array[:] = -3 * forms.domain.X[:forms.domain.n_owned].ravel()
    assert not forms.sound(crushed) and forms.energy(crushed) == np.inf
    for v in (other, crushed):
        v.destroy()
