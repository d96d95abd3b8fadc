"""The discretisation verified on its own (`fem.verification`): the Neo-Hookean energy's
observed convergence rates against a manufactured solution on nested unit cubes, the patch
test, and the Taylor test itself."""

import numpy as np
import pytest

from fem.verification import fitted_rate, manufactured_error, patch_error, rates, taylor_test


@pytest.mark.parametrize("degree, ns, rate", [(1, (4, 8, 16), 2.0), (2, (2, 4, 8), 3.0)])
def test_mesh_convergence_rate(degree, ns, rate):
    """L2 error against u* = 0.05 (sin πy, sin πz, sin πx) with its body force, on nested
    unit cubes: P1 converges at 2, P2 at 3 (observed 1.99 and 2.98)."""
    h = 1.0 / np.array(ns)
    err = [manufactured_error(n, degree) for n in ns]
    observed = fitted_rate(h, err)
    assert abs(observed - rate) < 0.1, (f"P{degree}: observed rate {observed:.3f} "
                                        f"(steps {rates(h, err).round(3)}), errors {err}")


@pytest.mark.parametrize("degree", [1, 2])
@pytest.mark.parametrize("F0", [np.diag([1.1, 0.95, 1.05]),
                                [[1.0, 0.2, 0.0], [0.0, 1.0, -0.1], [0.05, 0.0, 0.9]]],
                         ids=["stretch", "shear"])
def test_patch_test(degree, F0):
    """A homogeneous deformation imposed on the boundary of a distorted patch is reproduced
    at every node to round-off."""
    assert patch_error(F0, degree=degree) < 1e-10


def test_taylor_test_tells_a_wrong_derivative():
    """taylor_test gives rates (1, 2) for the right derivative of a vector function, and
    falls to 1 with one 10 % off."""
    def f(x):
        return np.array([np.sin(x[0]) * x[1], np.exp(x[1] - x[2])])

    def df(x, d):
        return np.array([np.cos(x[0]) * x[1] * d[0] + np.sin(x[0]) * d[1],
                         np.exp(x[1] - x[2]) * (d[1] - d[2])])

    x, d = np.array([0.3, -0.7, 0.2]), np.array([0.5, -1.0, 0.8])
    hs = 0.1 * 0.5 ** np.arange(5)
    r1, r2 = taylor_test(f, x, d, df(x, d), hs)
    assert np.all(np.abs(r1 - 1) < 0.1) and np.all(np.abs(r2 - 2) < 0.1), (r1, r2)
    _, wrong = taylor_test(f, x, d, 1.1 * df(x, d), hs)
    assert abs(wrong[-1] - 1) < 0.1, wrong
