"""The tissue's parameters θ as differentiable parameters (issue 46, `inverse.uncertainty`):
dx/dθ by Taylor tests on a block, on the synthetic head (glued, and sliding on tissues at a
rotated treatment), the prior, and the bands' 95 % radius. Cranium's scene:
tests/test_calibrate.py; 1 against 2 ranks: tests/test_scripts.py, through the scripts."""

import dataclasses
import json

import numpy as np
import pytest

from fem.material import NeoHookean, Tissues, lame_rates, theta, theta_names, with_theta
from fem.verification import taylor_test
from meshes.errors import InputError

#: Taylor steps along a direction of θ whose entries are SD-sized (0.3).
HS = 0.5 * 0.5 ** np.arange(4)
#: A treatment of the mandible with rotations of 5-10° (tests/test_inverse.py's P_ROT).
P_ROT = np.array([2.0, -1.0, 1.0, 8.0, 6.0, -7.0])


def _direction(n_theta: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(n_theta) * 0.3


def _check_rates(rate1, rate2):
    assert abs(rate1[-1] - 1) < 0.1, rate1      # 1 without the derivative
    assert np.all(np.abs(rate2 - 2) < 0.15), rate2   # 2 with it


@pytest.mark.parametrize("material", [NeoHookean(E=7.0, nu=0.45), Tissues()])
def test_theta_round_trip_and_lame_rates(material):
    """with_theta(theta(m)) is m; the Lamé rates equal central differences of mu, lambda."""
    again = with_theta(material, theta(material))
    assert type(again) is type(material)
    np.testing.assert_allclose(theta(again), theta(material), rtol=1e-15)
    for m in ([material] if isinstance(material, NeoHookean) else
              [material.skin, material.fat, material.muscle]):
        dlogE, dnu = lame_rates(m)
        h = 1e-6
        c = 1 - 2 * m.nu   # ln c up and down by h
        for rate, step in ((dlogE, dict(E=m.E * np.exp(h))),
                           (dnu, dict(nu=(1 - c * np.exp(h)) / 2))):
            up = dataclasses.replace(m, **step)
            down = dataclasses.replace(m, **{k: (m.E * np.exp(-h) if k == "E" else
                                                 (1 - c * np.exp(-h)) / 2) for k in step})
            fd = [(getattr(up, a) - getattr(down, a)) / (2 * h) for a in ("mu", "lmbda")]
            np.testing.assert_allclose(rate, fd, rtol=1e-6)
    with pytest.raises(InputError, match="finite"):
        with_theta(material, np.where(np.char.endswith(theta_names(material), "nu"), np.inf,
                                      theta(material)))


@pytest.mark.parametrize("contact", ["glued", "sliding"])
def test_taylor_on_a_block(contact):
    """dx/dθ of a block of skin over fat over lean tissue on a plate moved 2 mm sideways and
    1 mm up, every dof: remainders of rate 1 without it and 2 with it."""
    from test_contact import _block, _scene

    from meshes.anatomy import SKIN

    block = _block(3, SKIN)
    z = block.points[block.cells].mean(axis=1)[:, 2]   # skin on top, fat, muscle below
    block.tissues = np.stack([z > 3, (z > 1.5) & (z <= 3), z <= 1.5], axis=1).astype(float)
    scene = _scene(block, contact, material="tissues")
    p = np.array([2.0, 1.0])
    scene.solve(p)
    th0 = theta(scene.eq.material)
    cols = scene.eq.material_sensitivity()
    S = np.stack([c.array.copy() for c in cols], axis=1)

    def u_at(t):
        scene.eq.set_material(with_theta(scene.eq.material, t))
        scene.solve(p)
        return scene.eq.u_eq.array.copy()

    d = _direction(len(th0), 0)
    _check_rates(*taylor_test(u_at, th0, d, S @ d, HS))


@pytest.mark.parametrize("contact_scene", ["tight_scene", "tight_tissues"],
                         ids=["glued-homogeneous", "sliding-tissues"])
def test_taylor_on_the_synthetic_head(request, contact_scene):
    """Landmark rows of dx/dθ at a treatment rotated 5-10°: rates 1 and 2. The homogeneous
    head's response to E alone is nil (displacement-driven: a common scale of the moduli
    moves nothing), its ν moves it."""
    from inverse.uncertainty import set_theta, theta_rows

    scene = request.getfixturevalue(contact_scene)
    scene.solve(P_ROT)
    th0 = theta(scene.eq.material)
    rows, _ = theta_rows(scene)

    def landmarks_at(t):
        set_theta(scene, t)
        scene.solve(P_ROT)
        return np.array(list(scene.landmarks().values()))

    try:
        for seed in (1, 2):
            d = _direction(len(th0), seed)
            _check_rates(*taylor_test(landmarks_at, th0, d, rows @ d, HS))
    finally:
        set_theta(scene, th0)
    if contact_scene == "tight_scene":
        log_e, nu = np.abs(rows).max(axis=(0, 1))
        assert log_e < 1e-3 * nu


def test_prior_from_a_material_file(tmp_path):
    """A material file gives the prior's medians and spreads; a class it leaves out keeps
    the documented ones; a spread that is not positive is one line."""
    from inverse.uncertainty import SD_LOG_1M2NU, SD_LOG_E, Prior

    path = tmp_path / "m.json"
    path.write_text(json.dumps({"fat": {"E": 4.0, "sd_log_E": 0.5}, "skin": {"nu": 0.46}}))
    prior = Prior.from_file(path)
    assert prior.names == tuple(theta_names(Tissues()))
    np.testing.assert_allclose(prior.mean[[0, 1, 2]], [np.log(36.0), np.log(0.08), np.log(4.0)])
    np.testing.assert_allclose(prior.sd, [SD_LOG_E["skin"], SD_LOG_1M2NU, 0.5, SD_LOG_1M2NU,
                                          SD_LOG_E["muscle"], SD_LOG_1M2NU])
    assert prior.report()["fat.E_kPa"] == {"median": pytest.approx(4.0), "sd_log": 0.5}
    path.write_text(json.dumps({"fat": {"E": 4.0, "sd_log_1m2nu": 0.0}}))
    with pytest.raises(InputError, match="fat.log_1m2nu must be positive"):
        Prior.from_file(path)


def test_a_correlated_prior_from_a_calibrations_material_file(tmp_path):
    """A material file with its spreads' correlation (as `calibrate.py` writes it): the
    material reads as without it; the prior's Σ is D C D, its bands S Σ Sᵀ, its samples'
    covariance Σ (4·10⁴ of them, within 3 %); a correlation that is not one (not positive
    definite, another θ's names) is one line."""
    from fem.material import CORRELATION_KEY, material_file, read_material_file
    from inverse.uncertainty import Prior, covariances, sample_theta

    rng = np.random.default_rng(1)
    A = rng.standard_normal((6, 6)) + 2 * np.eye(6)
    S = A @ A.T
    C = S / np.sqrt(np.outer(np.diag(S), np.diag(S)))
    sd = np.array([0.1, 0.05, 0.2, 0.05, 0.1, 0.05])
    spec = material_file(Tissues(), sd, C)
    path = tmp_path / "m.json"
    path.write_text(json.dumps(spec))
    assert read_material_file(path) == Tissues()
    prior = Prior.from_file(path)
    Sigma = np.outer(sd, sd) * C
    np.testing.assert_allclose(prior.covariance, Sigma, rtol=1e-12)
    rows = rng.standard_normal((4, 3, 6))
    np.testing.assert_allclose(covariances(rows, prior),
                               np.einsum("nit,ts,njs->nij", rows, Sigma, rows), rtol=1e-10)
    x = sample_theta(dataclasses.replace(prior, mean=np.zeros(6) + np.log(0.06) * np.tile(
        [0, 1], 3)), 40000)
    np.testing.assert_allclose(np.cov(x.T), Sigma, atol=0.03 * sd.max() ** 2)
    for bad in ({**spec[CORRELATION_KEY], "matrix": (-np.ones((6, 6)) + 2 * np.eye(6)).tolist()},
                {**spec[CORRELATION_KEY], "names": spec[CORRELATION_KEY]["names"][::-1]}):
        path.write_text(json.dumps({**spec, CORRELATION_KEY: bad}))
        with pytest.raises(InputError, match="correlation must be"):
            Prior.from_file(path)


def test_radius95_against_sampling():
    """The 95 % radius: 1.96 σ along one axis, √χ²₃(0.95) σ in a ball, and within 1 % of
    10⁶ samples of a flat, tilted covariance; 0 where nothing moves."""
    from inverse.uncertainty import radius95

    rng = np.random.default_rng(0)
    A = rng.standard_normal((3, 3)) * [1.0, 0.4, 0.05]
    cov = np.stack([np.diag([4.0, 0, 0]), np.eye(3), A @ A.T, np.zeros((3, 3))])
    r = radius95(cov)
    samples = np.linalg.norm(rng.standard_normal((10 ** 6, 3)) @ np.linalg.cholesky(
        cov[2]).T, axis=1)
    np.testing.assert_allclose(r[:2], [1.96 * 2, np.sqrt(7.8147)], rtol=1e-3)
    assert abs(r[2] / np.quantile(samples, 0.95) - 1) < 0.01
    assert r[3] == 0.0
