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


class PredictionInverts(SolverError):
    """A quick solve's first-order prediction inverts an element (nothing was solved).
    ``fraction``: of the step to the prediction, the longest whose prediction compresses no
    element by more than `fem.policy.SolverPolicy.trust_compression` (0 where none is)."""

    def __init__(self, message: str, fraction: float):
        super().__init__(message)
        self.fraction = fraction
