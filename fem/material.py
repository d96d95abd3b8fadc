"""Hyperelastic soft-tissue material."""

from __future__ import annotations

import dataclasses

import ufl

from meshes.errors import InputError


@dataclasses.dataclass(frozen=True)
class NeoHookean:
    """Compressible Neo-Hookean solid.

    ``psi = mu/2 (tr C - 3) - mu ln J + lambda/2 (ln J)^2`` in kPa (energy per rest volume;
    with lengths in mm, energies are in uJ). Defaults: the paper's E = 5 kPa, nu = 0.47,
    density 0.9 g/ml (unused while quasi-static).
    """

    E: float = 5.0
    nu: float = 0.47
    density: float = 0.9

    def __post_init__(self):
        if not (self.E > 0 and self.E < 1e9):
            raise InputError(f"Young's modulus E = {self.E} kPa must be positive and finite")
        if not (-1.0 < self.nu < 0.5):
            raise InputError(f"Poisson's ratio nu = {self.nu} must lie in (-1, 0.5)")
        if not self.density > 0:
            raise InputError(f"density {self.density} g/ml must be positive")

    @property
    def mu(self) -> float:
        """Shear modulus, kPa."""
        return self.E / (2 * (1 + self.nu))

    @property
    def lmbda(self) -> float:
        """First Lame parameter, kPa."""
        return self.E * self.nu / ((1 + self.nu) * (1 - 2 * self.nu))

    def energy_density(self, F, mu=None, lmbda=None):
        """Strain energy density (UFL scalar, kPa) of the deformation gradient F. ``mu`` and
        ``lmbda`` may be UFL constants holding `mu` and `lmbda` (one compiled form serves
        every material); by default the numbers are used."""
        mu = self.mu if mu is None else mu
        lmbda = self.lmbda if lmbda is None else lmbda
        J = ufl.det(F)
        lnJ = ufl.ln(J)
        return 0.5 * mu * (ufl.tr(F.T * F) - 3) - mu * lnJ + 0.5 * lmbda * lnJ**2
