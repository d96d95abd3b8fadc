"""Exceptions raised for bad input anywhere in orthodiff.

Every message says what was wrong and what to do about it.
"""


class OrthodiffError(Exception):
    """Base class of all orthodiff errors."""


class InputError(OrthodiffError, ValueError):
    """A user-supplied value (case, parameter, file, target) is invalid."""


class MeshError(InputError):
    """A mesh is unreadable, not tetrahedral, inverted, or lacks required tags or landmarks."""


class SolverError(OrthodiffError, RuntimeError):
    """A solver failed even after regularisation and continuation."""
