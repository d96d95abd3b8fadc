"""Verification as a library: Taylor tests of derivatives, observed convergence rates, and the
discretisation's own checks of the Neo-Hookean energy the engine solves
(`fem.material.neo_hookean`): a manufactured solution on nested unit cubes, and the patch test.

Models: pyadjoint's ``taylor_test`` (the remainder of a first-order expansion falls at rate 2
with the derivative, 1 without) and scikit-fem's ``test_convergence.py`` (the slope of log
error over log h, printed where it fails).
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import numpy as np
import ufl
from dolfinx.nls.petsc import NewtonSolver

from fem import compat
from fem.material import HOMOGENEOUS, neo_hookean

#: Quadrature beyond twice the degree for the manufactured forms (sines and a logarithm, which
#: FFCx would integrate with 12 167 points a cell, taking minutes): with 2 more, P1 and P2
#: show their rates (2 and 3 in L2) to within 0.05.
QUADRATURE_EXTRA = 2


def rates(h, err) -> np.ndarray:
    """Observed rates log(e_i / e_i+1) / log(h_i / h_i+1) between successive (h, error)
    pairs (K,) each: (K - 1,)."""
    h, err = np.asarray(h, float), np.asarray(err, float)
    return np.log(err[:-1] / err[1:]) / np.log(h[:-1] / h[1:])


def fitted_rate(h, err) -> float:
    """The least-squares slope of log error over log h."""
    return float(np.polyfit(np.log(h), np.log(err), 1)[0])


def taylor_test(f, x, dx, derivative, hs) -> tuple[np.ndarray, np.ndarray]:
    """Rates of the Taylor remainders of ``f`` (x -> scalar or array) at ``x`` along ``dx``:
    (rates of |f(x + h dx) - f(x)|, rates of |f(x + h dx) - f(x) - h derivative|), max-norm
    over arrays, for the steps ``hs`` (decreasing). ``derivative``: the claimed directional
    derivative f'(x) dx. A right derivative gives about (1, 2)."""
    x, dx = np.asarray(x, float), np.asarray(dx, float)
    f0, d = np.asarray(f(x), float), np.asarray(derivative, float)
    r1, r2 = [], []
    for h in hs:
        fh = np.asarray(f(x + h * dx), float)
        r1.append(np.abs(fh - f0).max())
        r2.append(np.abs(fh - f0 - h * d).max())
    return rates(hs, r1), rates(hs, r2)


def _solve_neo_hookean(mesh, degree: int, material, u_exact, body=None):
    """The Neo-Hookean equilibrium on ``mesh`` (Lagrange ``degree``) with u = ``u_exact``
    (callable on (3, N) points) on the boundary and body force ``body`` (UFL vector, kPa/mm):
    the displacement Function. Newton to 1e-12 (dolfinx's NonlinearProblem, MUMPS LU)."""
    V = compat.vector_space(mesh, degree)
    u, v = dolfinx.fem.Function(V), ufl.TestFunction(V)
    dx = ufl.dx(metadata={"quadrature_degree": QUADRATURE_EXTRA + 2 * degree})
    energy = neo_hookean(ufl.Identity(3) + ufl.grad(u), material.mu, material.lmbda) * dx
    if body is not None:
        energy -= ufl.dot(body, u) * dx
    residual = ufl.derivative(energy, u, v)
    jacobian = ufl.derivative(residual, u, ufl.TrialFunction(V))
    g = dolfinx.fem.Function(V)
    g.interpolate(u_exact)
    mesh.topology.create_connectivity(2, 3)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    bc = dolfinx.fem.dirichletbc(g, dolfinx.fem.locate_dofs_topological(V, 2, facets))
    u.interpolate(u_exact)   # the start: the boundary values everywhere
    lu_newton(residual, u, [bc], jacobian, convergence_criterion="residual", rtol=1e-12,
              atol=1e-13).solve(u)
    return u


def lu_newton(residual, u, bcs, jacobian, **settings):
    """The FEniCSx tutorial's recipe for ``residual`` (UFL form) = 0 in ``u``: dolfinx's
    ``NonlinearProblem`` and ``NewtonSolver`` with a MUMPS LU each step, its attributes
    ``settings`` (e.g. ``convergence_criterion``, ``rtol``, ``max_it``): the solver."""
    solver = NewtonSolver(u.function_space.mesh.comm,
                          compat.newton_problem(residual, u, bcs, jacobian))
    for k, val in settings.items():
        setattr(solver, k, val)
    ksp = solver.krylov_solver
    opts, prefix = PETSc.Options(), ksp.getOptionsPrefix()
    for k, val in {"ksp_type": "preonly", "pc_type": "lu",
                   "pc_factor_mat_solver_type": "mumps"}.items():
        opts[f"{prefix}{k}"] = val
    ksp.setFromOptions()
    return solver


def manufactured_error(n: int, degree: int = 1, material=None, amplitude: float = 0.05,
                       comm=MPI.COMM_WORLD) -> float:
    """L2 error (mm) of the Neo-Hookean equilibrium on the unit cube (mm) of n×n×n×6 tets
    against the manufactured u* = amplitude (sin πy, sin πz, sin πx): its body force
    B = -div P(u*) (P = ∂ψ/∂F, by UFL), u = u* on the boundary. ``material``: a
    `fem.material.NeoHookean` (default the paper's). P1 converges at about 2, P2 at 3."""
    material = material or HOMOGENEOUS
    mesh = dolfinx.mesh.create_unit_cube(comm, n, n, n)
    x = ufl.SpatialCoordinate(mesh)
    u_star = amplitude * ufl.as_vector((ufl.sin(ufl.pi * x[1]), ufl.sin(ufl.pi * x[2]),
                                        ufl.sin(ufl.pi * x[0])))
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u_star))
    body = -ufl.div(ufl.diff(neo_hookean(F, material.mu, material.lmbda), F))

    def exact(p):
        return amplitude * np.sin(np.pi * np.stack([p[1], p[2], p[0]]))
    u = _solve_neo_hookean(mesh, degree, material, exact, body)
    e = u - u_star
    local = dolfinx.fem.assemble_scalar(compat.form(ufl.inner(e, e) * ufl.dx(
        metadata={"quadrature_degree": 2 * QUADRATURE_EXTRA + 2 * degree})))
    return float(np.sqrt(comm.allreduce(local, op=MPI.SUM)))


def patch_error(F0, n: int = 3, degree: int = 1, material=None,
                comm=MPI.COMM_WORLD) -> float:
    """The patch test: the largest nodal error (mm) of the Neo-Hookean equilibrium on the
    unit cube (a distorted n×n×n×6 tet mesh) whose boundary follows the homogeneous
    deformation x = F0 X (F0 (3, 3), det > 0), against that deformation (which solves it
    exactly: a constant stress, no body force). Zero to round-off for a consistent
    discretisation."""
    F0 = np.asarray(F0, float)
    mesh = dolfinx.mesh.create_unit_cube(comm, n, n, n)
    X = mesh.geometry.x
    X[:, :3] += 0.15 / n * np.sin(7.0 * X[:, [1, 2, 0]])   # an irregular patch
    exact = lambda p: (F0 - np.eye(3)) @ p   # noqa: E731  (p (3, N))
    u = _solve_neo_hookean(mesh, degree, material or HOMOGENEOUS, exact)
    want = dolfinx.fem.Function(u.function_space)
    want.interpolate(exact)
    local = np.abs(u.x.array - want.x.array).max(initial=0.0)
    return float(comm.allreduce(local, op=MPI.MAX))

