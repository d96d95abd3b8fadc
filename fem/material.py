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


def neo_hookean(F, mu, lmbda):
    """``psi`` (`NeoHookean`), kPa (UFL scalar), of the deformation gradient F with Lame
    parameters mu and lmbda (numbers, constants or cell fields, kPa): constants and fields
    let one compiled form serve every material."""
    J = ufl.det(F)
    lnJ = ufl.ln(J)
    return 0.5 * mu * (ufl.tr(F.T * F) - 3) - mu * lnJ + 0.5 * lmbda * lnJ**2


#: The paper's single material (E = 5 kPa, nu = 0.47), ``--material homogeneous``.
HOMOGENEOUS = NeoHookean()


#: A material file's optional prior spreads per class (`inverse.uncertainty.Prior`).
PRIOR_KEYS = ("sd_log_E", "sd_log_1m2nu")
#: A material file's optional key beside its classes: the prior's correlation,
#: ``{"names": θ's names, "matrix": nθ × nθ}`` (`calibrate.py` writes its posterior's).
CORRELATION_KEY = "correlation"


@dataclasses.dataclass(frozen=True)
class Tissues:
    """One Neo-Hookean material per tissue class (`meshes.tissue.TISSUES`), kPa.

    A cell's Lame parameters are its classes' weighted by volume fraction (the Voigt mean):
    a layer thinner than its cells keeps its membrane stiffness E·t, which is what a stiff
    skin carries. Defaults, small-strain Young's moduli measured in vivo or fresh:

    * skin, E = 36 kPa: the initial modulus of the face's skin by aspiration, 31-42 kPa at
      the cheek, cheekbone, forehead and lower lip of 16 subjects (Luboz, Promayon, Payan
      2014, Ann Biomed Eng 42:2369); the middle of that range. Skin measured by torsion or
      tension reads 0.1-1 MPa, at larger strains and without the tissue under it; suction
      on the face is the nearest to what the lips and cheeks do here.
    * fat, E = 3.25 kPa: fresh adipose tissue at small strain, 3.25 ± 0.91 kPa (Samani,
      Zubovits, Plewes 2007, Phys Med Biol 52:1565, breast fat, indentation and inversion).
      No facial measurement of fat alone was found; in vivo indentation of the whole soft
      tissue over the jaw reads 2.7-4.4 kPa (Wei et al. 2021, Int J Appl Mech 13:2150034).
    * muscle, E = 10.7 kPa: the relaxed masseter by shear-wave elastography, 10.67 ± 1.77
      kPa in 140 healthy adults (Olchowy et al. 2021, Int J Environ Res Public Health
      18:9371), the largest cohort of a facial muscle found.
    * nu = 0.47 for each, the paper's: no source measures the tissues' compressibility
      better (all are nearly incompressible).
    """

    skin: NeoHookean = NeoHookean(E=36.0)
    fat: NeoHookean = NeoHookean(E=3.25)
    muscle: NeoHookean = NeoHookean(E=10.7)

    def lame(self, fractions):
        """(mu (M,), lmbda (M,)) kPa of cells with tissue ``fractions`` (M, 3)."""
        import numpy as np

        f = np.asarray(fractions, dtype=float)
        classes = (self.skin, self.fat, self.muscle)
        return (f @ np.array([m.mu for m in classes]),
                f @ np.array([m.lmbda for m in classes]))


# --- the material parameters θ (issue 46): each class's ln E and ln(1 - 2ν)

#: What θ holds per class: ln E (E in kPa) and ln(1 - 2ν), the log of the compressibility
#: (κ/μ = 2(1 + ν) / (3(1 - 2ν))). A band in either is multiplicative, and the landmarks
#: respond to the second nearly linearly where they do not to ν: Li on class3 (coarse,
#: 5 mm advance) over ν in [0.44, 0.495] leaves 12 % of its motion off a straight line in
#: ln(1 - 2ν), 42 % in ν (docs/uncertainty.md).
THETA_FIELDS = ("log_E", "log_1m2nu")


def classes(material) -> dict:
    """The material's classes {name: `NeoHookean`}: ``tissue`` for one material, else skin,
    fat and muscle (`Tissues`)."""
    if isinstance(material, NeoHookean):
        return {"tissue": material}
    return {f.name: getattr(material, f.name) for f in dataclasses.fields(material)}


def theta_names(material) -> list[str]:
    """Names of θ, ``<class>.log_E`` and ``<class>.log_1m2nu`` per class."""
    return [f"{c}.{k}" for c in classes(material) for k in THETA_FIELDS]


def theta(material):
    """θ (2 n_classes,): each class's (ln E/kPa, ln(1 - 2ν)), in `theta_names` order."""
    import numpy as np

    return np.array([v for m in classes(material).values()
                     for v in (np.log(m.E), np.log(1 - 2 * m.nu))])


def with_theta(material, values):
    """The material of the same kind with θ = ``values``; raises `InputError` (one line)
    where a value makes no material (ν outside (-1, 0.5), E not finite)."""
    import numpy as np

    values = np.asarray(values, dtype=float).reshape(-1)
    names = list(classes(material))
    if values.shape != (2 * len(names),) or not np.all(np.isfinite(values)):
        raise InputError(f"material parameters: expected {2 * len(names)} finite values "
                         f"({', '.join(theta_names(material))}), got {values.tolist()}")
    made = {c: dataclasses.replace(classes(material)[c], E=float(np.exp(values[2 * i])),
                                   nu=float((1 - np.exp(values[2 * i + 1])) / 2))
            for i, c in enumerate(names)}
    if isinstance(material, NeoHookean):
        return made["tissue"]
    return dataclasses.replace(material, **made)


def lame_rates(m: NeoHookean):
    """d(mu, lmbda)/d ln E and d(mu, lmbda)/d ln(1 - 2ν), kPa: ((2,), (2,))."""
    E, nu = m.E, m.nu
    d = (1 + nu) * (1 - 2 * nu)
    dnu = -(1 - 2 * nu) / 2   # dν / d ln(1 - 2ν)
    return (m.mu, m.lmbda), (dnu * -E / (2 * (1 + nu) ** 2),
                             dnu * E * (1 + 2 * nu ** 2) / d ** 2)


def read_material_file(path):
    """The material of a JSON file: ``{"skin": {"E": kPa, "nu": ..}, "fat": .., "muscle":
    ..}`` (`Tissues`; a class or value it leaves out keeps its default) or ``{"tissue":
    {..}}`` (one `NeoHookean`, the paper's by default). The prior's spreads `PRIOR_KEYS`
    beside them, and its `CORRELATION_KEY`, are `inverse.uncertainty.Prior`'s. Raises
    `InputError` (one line)."""
    import json
    from pathlib import Path

    try:
        spec = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read material file {path}: {e}") from e
    if isinstance(spec, dict):
        spec = {k: v for k, v in spec.items() if k != CORRELATION_KEY}
    one = isinstance(spec, dict) and set(spec) == {"tissue"}
    if not isinstance(spec, dict) or not (one or not set(spec) - {"skin", "fat", "muscle"}):
        raise InputError(f"material file {path}: expected an object with keys skin, fat, "
                         "muscle, or the key tissue alone")
    base = HOMOGENEOUS if one else Tissues()
    out = {}
    for name, given in spec.items():
        if not isinstance(given, dict) or set(given) - {"E", "nu", *PRIOR_KEYS}:
            raise InputError(f"material file {path}: {name} must be {{\"E\": kPa, "
                             "\"nu\": ..., optionally \"sd_log_E\", \"sd_log_1m2nu\"}")
        try:
            out[name] = dataclasses.replace(   # a value it leaves out keeps the class's
                classes(base)[name], **{k: float(v) for k, v in given.items()
                                        if k not in PRIOR_KEYS})
        except (TypeError, ValueError, InputError) as e:
            raise InputError(f"material file {path}: {name}: {e}") from e
    return out["tissue"] if one else dataclasses.replace(base, **out)


def material_file(material, spreads=None, correlation=None) -> dict:
    """What `read_material_file` reads back as ``material``: ``{class: {"E", "nu"}}``, with
    ``spreads`` (nθ,) where given, as the prior's (`PRIOR_KEYS`, `theta_names` order), and
    their ``correlation`` (nθ, nθ) where given (`CORRELATION_KEY`)."""
    out = {}
    for i, (c, m) in enumerate(classes(material).items()):
        out[c] = {"E": m.E, "nu": m.nu}
        if spreads is not None:
            out[c].update(zip(PRIOR_KEYS, map(float, spreads[2 * i:2 * i + 2])))
    if correlation is not None:
        out[CORRELATION_KEY] = {"names": theta_names(material),
                                "matrix": [[float(v) for v in row] for row in correlation]}
    return out


def material_from_spec(spec):
    """A material from "homogeneous", "tissues", a material file (`read_material_file`), or a
    `NeoHookean` or `Tissues` itself."""
    if isinstance(spec, (NeoHookean, Tissues)):
        return spec
    if spec == "homogeneous":
        return HOMOGENEOUS
    if spec == "tissues":
        return Tissues()
    if isinstance(spec, str) and spec.endswith(".json"):
        return read_material_file(spec)
    raise InputError(f"material must be 'homogeneous', 'tissues' or a .json material file, "
                     f"got {spec!r}")
