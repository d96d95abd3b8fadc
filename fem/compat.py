"""The only module that knows dolfinx versions. Written for 0.5.2 (Debian 12); 0.9+ names differ.

Version-dependent choices are made once, at import time (scifem habit).

The ``NEW_API`` branches (dolfinx 0.9 and later) never run here: the design card fixes
Debian's dolfinx 0.5.2, and no CI leg installs another. They are not a supported
configuration but a map for a port, each written from the 0.9 API's documentation
(``functionspace``, ``form``, ``create_matrix``, ``Expression``): a port starts by running
the test suite on a 0.9+ install and fixing what this map got wrong.
"""

from __future__ import annotations

from mpi4py import MPI

import logging
import os
import time

import dolfinx
import dolfinx.fem.petsc as fem_petsc
import dolfinx.jit
import numpy as np

VERSION = tuple(int(v) for v in dolfinx.__version__.split(".")[:2])
NEW_API = VERSION >= (0, 9)

log = logging.getLogger(__name__)

# Seconds a process waits for a JIT module another process is compiling (FFCx's `timeout`,
# 10 s by default), and the age past which such a claim is a dead one. FFCx claims a module
# by creating its C file exclusively and marks it ready with `<module>.c.cached`; a process
# killed between the two (Ctrl-C during a first solve) leaves a claim that every later run
# waited 10 s for and then failed on: CI run 40 lost seven tests to one such C file. The
# largest form here (sliding, tissues) compiles in under 2 s alone and under 5 s with three
# processes compiling at once on 2 cores, so a claim 60 s old is dead.
JIT_WAIT_S = 60


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


def cpp_mesh(mesh):
    """The C++ mesh object behind a Python ``dolfinx.mesh.Mesh`` (for ``dolfinx.cpp`` calls)."""
    return getattr(mesh, "_cpp_object", None) or mesh._mesh


def petsc_vec(u):
    """The PETSc vector that holds a Function's values (shares memory)."""
    return u.x.petsc_vec if NEW_API else u.vector


def _release_dead_claims():
    """Set aside (as FFCx does a failed compile, to ``.c.failed``) every JIT claim of the
    cache older than ``JIT_WAIT_S`` and never marked ready, with a warning naming it."""
    cache = dolfinx.jit.get_parameters()["cache_dir"]
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
            if "Failed just-in-time compilation" not in str(e):   # not mpi_jit's
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
