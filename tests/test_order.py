"""P2 displacement (the element-order study): nodes, landmark operator, solve, derivatives."""

import numpy as np
import pytest
from conftest import TIGHT

from fem.domain import create_domain


@pytest.fixture(scope="module")
def p2_scene(tiny_anatomy, mandible_only):
    return mandible_only(tiny_anatomy, degree=2, equilibrium=TIGHT,
                         params_used=["mandible.advance_mm", "mandible.lateral_mm"])


def _quadratic(x):
    """A quadratic field (3, K) of points (3, K), mm."""
    return 1e-2 * np.stack([x[0] * x[1], x[2] ** 2, x[0] * x[2] - x[1] ** 2])


@pytest.mark.parametrize("degree", [1, 2])
def test_nodes_and_landmark_operator(tiny_anatomy, degree):
    """Node coordinates are dolfinx's; the landmark operator interpolates exactly what the
    space can represent: a quadratic field only in P2."""
    import dolfinx

    d = create_domain(tiny_anatomy, degree=degree)
    assert np.abs(d.V.tabulate_dof_coordinates()[:, :3] - d.X).max() < 1e-12
    vertex = d.input_index >= 0
    assert np.abs(d.X[vertex] - tiny_anatomy.points[d.input_index[vertex]]).max() < 1e-12
    u = dolfinx.fem.Function(d.V)
    u.interpolate(_quadratic)
    op = d.point_operator(list(d.landmarks))
    pts = np.array([lm.weights @ tiny_anatomy.points[list(lm.facet)]
                    for lm in d.landmarks.values()])
    assert np.abs(op.apply(np.zeros_like(u.x.array)) - pts).max() < 1e-12
    err = np.abs(op.apply(u.x.array, offset=False) - _quadratic(pts.T).T).max()
    if degree == 2:
        assert err < 1e-10, err
    else:
        assert err > 1e-3, err   # P1 cannot: the check above has teeth


def test_p2_equilibrium_and_sensitivity(p2_scene, mandible_scene, central_differences):
    """P2 converges to a sound state near the P1 one, and S_T matches central differences."""
    p = np.array([2.0, 0.5])
    st = p2_scene.solve(p)
    assert st.goal_error < 0.05 and st.min_det_F > 0.5
    mandible_scene.solve([p[0], p[1], 0, 0, 0, 0])
    a, b = p2_scene.landmarks(), mandible_scene.landmarks()
    # P1 and P2 differ by the discretisation error of tiny (BENCHMARKS: ~0.1 mm at 5 mm)
    assert max(np.linalg.norm(a[n] - b[n]) for n in a) < 0.2
    rest = p2_scene.landmarks(rest=True)
    obj = p2_scene.objective({n: (rest[n] + [0, 3, 0]).tolist() for n in ("Pg", "Li")})
    S, _ = obj.jacobian()
    fd = central_differences(p2_scene, obj, p)
    err = np.abs(fd - S).max() / np.abs(S).max()
    assert err < 1e-5, err


def test_tagged_triangles_face_out_of_the_tissue(tiny_anatomy):
    """The tagged facets, all of the tissue's boundary, oriented out of it: their flux of x/3
    (the divergence theorem) is the tissue's volume, summed from its tets."""
    from meshes.anatomy import signed_volumes

    d = create_domain(tiny_anatomy)
    tri, _ = d.tagged_triangles()
    x = tiny_anatomy.points
    a, b, c = (x[tri[:, k]] for k in range(3))
    flux = np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0
    volume = np.abs(signed_volumes(x, tiny_anatomy.cells)).sum()
    assert abs(flux - volume) < 1e-9 * volume, (flux, volume)
