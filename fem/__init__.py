"""The finite-element engine. mpi4py is imported first: it loads the MPI library that
petsc4py's PETSc links (PyPI's MPICH; Debian's Open MPI is found without it)."""

from mpi4py import MPI  # noqa: F401
