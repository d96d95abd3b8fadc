"""A plane (mm, in the scene's frame): the osteotomies' cuts, the head frame's planes and the
mid-sagittal plane the landmarks are built on. No other part of `meshes` is imported here,
so that `meshes.anatomy`, `meshes.frame`, `meshes.landmarks` and `meshes.osteotomy` import
it without a circle."""

from __future__ import annotations

import dataclasses

import numpy as np

from meshes.errors import MeshError


@dataclasses.dataclass(frozen=True)
class Plane:
    """A plane through ``point`` (3,) mm with unit ``normal`` (3,)."""

    point: tuple
    normal: tuple

    @classmethod
    def of(cls, name: str, spec) -> "Plane":
        """A plane from ``{"point": [x, y, z], "normal": [nx, ny, nz]}``."""
        try:
            p, n = (np.asarray(spec[k], dtype=float) for k in ("point", "normal"))
        except (KeyError, TypeError, ValueError):
            raise MeshError(f"osteotomy {name!r}: expected {{\"point\": [x, y, z], "
                            f"\"normal\": [nx, ny, nz]}} in mm, got {spec!r}") from None
        if p.shape != (3,) or n.shape != (3,) or not np.all(np.isfinite(np.r_[p, n])) \
                or np.linalg.norm(n) == 0:
            raise MeshError(f"osteotomy {name!r}: point and normal must be 3 finite numbers, "
                            f"the normal non-zero; got {spec!r}")
        return cls(tuple(p), tuple(n / np.linalg.norm(n)))

    def distance(self, x: np.ndarray) -> np.ndarray:
        """Signed distances (K,) mm of points x (K, 3)."""
        return (np.asarray(x, float) - self.point) @ np.asarray(self.normal)


def axis_plane(axis: int, value: float) -> Plane:
    """The plane ``x[axis] = value`` with the normal along +axis."""
    p, n = np.zeros(3), np.zeros(3)
    p[axis], n[axis] = value, 1.0
    return Plane(tuple(p), tuple(n))
