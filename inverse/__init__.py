"""Planning on the engine. mpi4py first, as in `fem`."""

from mpi4py import MPI  # noqa: F401
