"""The only module that knows dolfinx versions. Written for 0.5.2 (Debian 12); 0.9+ names differ.

Version-dependent choices are made once, at import time (scifem habit).

The ``NEW_API`` branches (dolfinx 0.9 and later) never run here: the design card fixes
Debian's dolfinx 0.5.2, and no CI leg installs another. They are not a supported
configuration but a map for a port, each written from the 0.9 API's documentation
(``functionspace``, ``form``, ``create_matrix``, ``Expression``): a port starts by running
the test suite on a 0.9+ install and fixing what this map got wrong.
"""

from __future__ import annotations

import dolfinx
import dolfinx.fem.petsc as fem_petsc
import numpy as np

VERSION = tuple(int(v) for v in dolfinx.__version__.split(".")[:2])
NEW_API = VERSION >= (0, 9)


def vector_space(mesh, degree: int = 1):
    """Continuous Lagrange vector space of the given degree on ``mesh``."""
    if NEW_API:
        return dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (mesh.geometry.dim,)))
    return dolfinx.fem.VectorFunctionSpace(mesh, ("CG", degree))


def tensor_space(mesh):
    """Piecewise-constant (DG0) 3×3 tensors on the cells of ``mesh``."""
    if NEW_API:
        return dolfinx.fem.functionspace(mesh, ("DG", 0, (3, 3)))
    return dolfinx.fem.TensorFunctionSpace(mesh, ("DG", 0))


def scalar_space(mesh, family: str = "DG", degree: int = 0):
    if NEW_API:
        return dolfinx.fem.functionspace(mesh, (family, degree))
    return dolfinx.fem.FunctionSpace(mesh, (family, degree))


def cpp_mesh(mesh):
    """The C++ mesh object behind a Python ``dolfinx.mesh.Mesh`` (for ``dolfinx.cpp`` calls)."""
    return getattr(mesh, "_cpp_object", None) or mesh._mesh


def petsc_vec(u):
    """The PETSc vector that holds a Function's values (shares memory)."""
    return u.x.petsc_vec if NEW_API else u.vector


def form(ufl_form, options: dict | None = None):
    """Compile a UFL form with FFCx options (``form_compiler_params`` in 0.5)."""
    options = options or {}
    if NEW_API:
        return dolfinx.fem.form(ufl_form, form_compiler_options=options)
    return dolfinx.fem.form(ufl_form, form_compiler_params=options)


def assemble_matrix(A, a, bcs=(), diagonal: float = 1.0):
    """Assemble bilinear form ``a`` into ``A`` with Dirichlet rows/columns and ``diagonal``."""
    if NEW_API:
        return fem_petsc.assemble_matrix(A, a, bcs=list(bcs), diag=diagonal)
    return fem_petsc.assemble_matrix(A, a, bcs=list(bcs), diagonal=diagonal)


def set_bc(b, bcs, x0=None, scale: float = 1.0):
    """``b[bc] = scale * (g - x0)`` on Dirichlet dofs (``alpha`` in 0.9+)."""
    if NEW_API:
        return fem_petsc.set_bc(b, list(bcs), x0, alpha=scale)
    return fem_petsc.set_bc(b, list(bcs), x0, scale)


def create_vector(L):
    """A PETSc vector for linear form ``L``."""
    if NEW_API:
        return fem_petsc.create_vector(L.function_spaces[0])
    return fem_petsc.create_vector(L)


create_matrix = fem_petsc.create_matrix
assemble_vector = fem_petsc.assemble_vector


def eval_expression(ufl_expr, points, mesh):
    """A function of no arguments returning ``ufl_expr`` (scalar) at reference ``points``
    (P, 3) of every local cell (ghosts included), shape (n_cells, P); compiled once."""
    expr = dolfinx.fem.Expression(ufl_expr, points)
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(tdim)
    cells = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
    if NEW_API:
        return lambda: expr.eval(mesh, cells).reshape(len(cells), -1)
    return lambda: expr.eval(cells).reshape(len(cells), -1)
