"""The only module that knows dolfinx versions: Debian 12's 0.5.2 and PyPI's 0.11
(``NEW_API``: 0.9 and later), both run by `make test` (docs/design.md has the API table).

Version-dependent choices are made once, at import time (scifem habit).
"""

from __future__ import annotations

from mpi4py import MPI

import logging
import os
import time

import dolfinx
import dolfinx.cpp
import dolfinx.fem.petsc as fem_petsc
import dolfinx.graph
import dolfinx.io
import dolfinx.jit
import dolfinx.mesh
import numpy as np
import ufl

VERSION = tuple(int(v) for v in dolfinx.__version__.split(".")[:2])
NEW_API = VERSION >= (0, 9)

if NEW_API:
    import basix.ufl
    from dolfinx.fem.petsc import NewtonSolverNonlinearProblem as _NewtonProblem
else:
    from dolfinx.fem.petsc import NonlinearProblem as _NewtonProblem

log = logging.getLogger(__name__)

# Seconds a process waits for a JIT module another process is compiling (FFCx's `timeout`,
# 10 s by default), and the age past which such a claim is a dead one. FFCx claims a module
# by creating its C file exclusively and marks it ready with `<module>.c.cached`; a process
# killed between the two (Ctrl-C during a first solve) leaves a claim that every later run
# waited 10 s for and then failed on: CI run 40 lost seven tests to one such C file. The
# largest form here (sliding, tissues) compiles in under 2 s alone and under 5 s with three
# processes compiling at once on 2 cores, so a claim 60 s old is dead.
JIT_WAIT_S = 60
#: How dolfinx's `mpi_jit` says a compile failed (0.5; 0.9+ on rank 0, on the others).
_MPI_JIT_FAILED = ("Failed just-in-time compilation", "Failed JIT compilation",
                   "JIT compilation failed on rank 0")
#: dolfinx's default JIT options, {name: (value, help)}.
JIT_DEFAULTS = (dolfinx.jit.DOLFINX_DEFAULT_JIT_OPTIONS if NEW_API
                else dolfinx.jit.DOLFINX_DEFAULT_JIT_PARAMETERS)


def vector_space(mesh, degree: int = 1):
    """Continuous Lagrange vector space of the given degree on ``mesh``."""
    if NEW_API:
        return dolfinx.fem.functionspace(mesh, ("Lagrange", degree, (mesh.geometry.dim,)))
    return jit(lambda _: dolfinx.fem.VectorFunctionSpace(mesh, ("CG", degree)), mesh.comm)


def tensor_space(mesh):
    """Piecewise-constant (DG0) 3×3 tensors on the cells of ``mesh``."""
    if NEW_API:
        return dolfinx.fem.functionspace(mesh, ("DG", 0, (3, 3)))
    return jit(lambda _: dolfinx.fem.TensorFunctionSpace(mesh, ("DG", 0)), mesh.comm)


def scalar_space(mesh, family: str = "DG", degree: int = 0):
    if NEW_API:
        return dolfinx.fem.functionspace(mesh, (family, degree))
    return jit(lambda _: dolfinx.fem.FunctionSpace(mesh, (family, degree)), mesh.comm)


def degree(V) -> int:
    """The polynomial degree of the Lagrange space ``V``."""
    return V.element.basix_element.degree if NEW_API else V.ufl_element().degree()


def create_mesh(comm, cells, x):
    """A P1 tetrahedral mesh of ``cells`` (n, 4) over the points ``x`` (m, 3), partitioned
    over ``comm`` from the ranks that hold them."""
    if NEW_API:
        element = basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,))
        return dolfinx.mesh.create_mesh(comm, cells, ufl.Mesh(element), x)
    element = ufl.VectorElement("Lagrange", ufl.tetrahedron, 1)
    return dolfinx.mesh.create_mesh(comm, cells, x, ufl.Mesh(element))


def facet_tags(mesh, facets, values):
    """MeshTags of the facets ``facets`` (n, 3), as input vertex indices, with ``values``
    (n,), from whichever ranks hold them."""
    tdim = mesh.topology.dim
    values = np.asarray(values, dtype=np.int32)
    if NEW_API:
        ents, vals = dolfinx.io.distribute_entity_data(mesh, tdim - 1, facets, values)
        adj = dolfinx.graph.adjacencylist(ents)
    else:
        ents, vals = dolfinx.cpp.io.distribute_entity_data(cpp_mesh(mesh), tdim - 1, facets,
                                                            values)
        adj = dolfinx.cpp.graph.AdjacencyList_int32(ents)
    return dolfinx.mesh.meshtags_from_entities(mesh, tdim - 1, adj, vals.astype(np.int32))


def cell_dofs(table) -> np.ndarray:
    """The dofs of each local cell (n_cells, k), ghosts included, from ``V.dofmap.list`` (a
    2-D array in 0.9+, an adjacency list in 0.5)."""
    if NEW_API:
        return np.asarray(table)
    width = table.offsets[1] - table.offsets[0] if len(table.offsets) > 1 else 1
    return table.array.reshape(-1, width)


def cell_nodes(mesh) -> np.ndarray:
    """The geometry nodes of each local cell (n_cells, 4), ghosts included."""
    return np.asarray(mesh.geometry.dofmaps[0]) if NEW_API else cell_dofs(mesh.geometry.dofmap)


def facet_nodes(mesh, facets) -> np.ndarray:
    """The geometry nodes (n, 3) of the local facets ``facets`` (n,), in the topology's
    order."""
    if NEW_API:
        return dolfinx.mesh.entities_to_geometry(mesh, 2, facets)
    return dolfinx.cpp.mesh.entities_to_geometry(cpp_mesh(mesh), 2, facets, False)


def newton_problem(residual, u, bcs, jacobian):
    """The problem dolfinx's ``NewtonSolver`` takes (the tutorial recipe's)."""
    return _NewtonProblem(residual, u, bcs=list(bcs), J=jacobian)


def cpp_mesh(mesh):
    """The C++ mesh object behind a Python ``dolfinx.mesh.Mesh`` (for ``dolfinx.cpp`` calls)."""
    return getattr(mesh, "_cpp_object", None) or mesh._mesh


def petsc_vec(u):
    """The PETSc vector that holds a Function's values (shares memory)."""
    return u.x.petsc_vec if NEW_API else u.vector


def _release_dead_claims():
    """Set aside (as FFCx does a failed compile, to ``.c.failed``) every JIT claim of the
    cache older than ``JIT_WAIT_S`` and never marked ready, with a warning naming it."""
    cache = (dolfinx.jit.get_options() if NEW_API else dolfinx.jit.get_parameters())["cache_dir"]
    for c in sorted(cache.glob("libffcx_*.c")):
        try:
            if (c.with_suffix(".c.cached").exists()
                    or time.time() - c.stat().st_mtime < JIT_WAIT_S):
                continue
            os.replace(c, c.with_suffix(".c.failed"))
        except FileNotFoundError:      # another process released it or finished it first
            continue
        log.warning("released a JIT claim no process finished in %g s: %s", JIT_WAIT_S, c)


def jit(compile_, comm):
    """``compile_(jit_params)`` (a dolfinx form, Expression or space on ``comm``), waiting
    ``JIT_WAIT_S`` for a module another process compiles, and compiling again once if a
    dead claim blocked it. In parallel, dolfinx's `mpi_jit` compiles on rank 0 first and
    fails on every rank together, the others without the reason: the ranks agree on it, and
    all retry or none. Spaces ignore the parameters: their element modules compile in well
    under FFCx's 10 s wait."""
    params = {"timeout": int(JIT_WAIT_S)}   # FFCx counts whole seconds
    try:
        return compile_(params)
    except (TimeoutError, RuntimeError) as e:
        timed_out = "JIT compilation timed out" in str(e)
        if isinstance(e, RuntimeError):
            if not any(m in str(e) for m in _MPI_JIT_FAILED):   # not mpi_jit's
                raise
            timed_out = comm.allreduce(timed_out, op=MPI.LOR)
        if not timed_out:
            raise
        _release_dead_claims()
        return compile_(params)


def form(ufl_form, options: dict | None = None):
    """Compile a UFL form with FFCx options (``form_compiler_params`` in 0.5)."""
    options = options or {}
    comm = ufl_form.ufl_domains()[0].ufl_cargo().comm
    if NEW_API:
        return jit(lambda p: dolfinx.fem.form(ufl_form, form_compiler_options=options,
                                              jit_options=p), comm)
    return jit(lambda p: dolfinx.fem.form(ufl_form, form_compiler_params=options,
                                          jit_params=p), comm)


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
    if NEW_API:
        expr = jit(lambda p: dolfinx.fem.Expression(ufl_expr, points, jit_options=p), mesh.comm)
    else:
        expr = jit(lambda p: dolfinx.fem.Expression(ufl_expr, points, jit_params=p), mesh.comm)
    tdim = mesh.topology.dim
    imap = mesh.topology.index_map(tdim)
    cells = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
    if NEW_API:
        return lambda: expr.eval(mesh, cells).reshape(len(cells), -1)
    return lambda: expr.eval(cells).reshape(len(cells), -1)
