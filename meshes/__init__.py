"""Anatomy: synthetic parametric heads (gmsh) and real anatomy loaded from files."""

from meshes.anatomy import Anatomy, Landmark
from meshes.errors import InputError, MeshError, OrthodiffError, SolverError
from meshes.synthetic import CASES, RESOLUTIONS, synthetic_head

__all__ = ["Anatomy", "Landmark", "CASES", "RESOLUTIONS", "synthetic_head", "InputError",
           "MeshError", "OrthodiffError", "SolverError"]
