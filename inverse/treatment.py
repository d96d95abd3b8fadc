"""Treatment model: goals of the active bone vertices ``x̂_A(p) = X_A + Σ p_i B_i`` (paper eq. 1).

Built-in parameters are linearised rigid motions of each active segment about its pivot, in
physical units. For segment ``s`` (``mandible``, ``maxilla_L``, ``maxilla_R``, and the group
``maxilla``: both LeFort I halves as one piece, about the mean of their pivots):

================  =====  ==========================================  ================
name              unit   blendshape B at a segment vertex X           default bounds
================  =====  ==========================================  ================
s.advance_mm      mm     +y (anterior)                                [-15, 15]
s.lateral_mm      mm     +x (patient's left)                          [-10, 10]
s.vertical_mm     mm     +z (superior)                                [-10, 10]
s.pitch_deg       deg    (pi/180) e_x × (X - c): front moves up       [-15, 15]
s.roll_deg        deg    (pi/180) e_y × (X - c): left side moves down [-10, 10]
s.yaw_deg         deg    (pi/180) e_z × (X - c): front moves right    [-10, 10]
================  =====  ==========================================  ================

Sculpted blendshapes are the difference between a modified and the rest bone surface.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np

from meshes.errors import InputError

MOTIONS = {  # name: (kind, axis, unit, bounds)
    "advance_mm": ("translation", (0, 1, 0), "mm", (-15.0, 15.0)),
    "lateral_mm": ("translation", (1, 0, 0), "mm", (-10.0, 10.0)),
    "vertical_mm": ("translation", (0, 0, 1), "mm", (-10.0, 10.0)),
    "pitch_deg": ("rotation", (1, 0, 0), "deg", (-15.0, 15.0)),
    "roll_deg": ("rotation", (0, 1, 0), "deg", (-10.0, 10.0)),
    "yaw_deg": ("rotation", (0, 0, 1), "deg", (-10.0, 10.0)),
}

#: Segment groups that also move as one piece: the LeFort I maxilla (both halves); a member's
#: own motions are then relative to the group's.
GROUPS = {"maxilla": ("maxilla_L", "maxilla_R")}
#: Parameters planned by default: the mandible's six motions and the maxilla's advance,
#: vertical position, cant (roll) and midline (yaw), en bloc. The halves' relative motion (a
#: split of the palate) is left out: skin landmarks barely decide it, and stepping the halves
#: apart vertically shears the tissue over the midline cut (a 7 mm step: 32 factorisations
#: where the same motion en bloc takes 2, medium). So is the maxilla's pitch: with it the
#: coarse default plan tilted the incisors 9° down into the lower lip (det F 0.09, bone
#: 0.4 mm short of its goal; there is no occlusion constraint) to gain 0.04 mm of landmark
#: distance (BENCHMARKS.md).
PLAN_PARAMS = [f"mandible.{m}" for m in MOTIONS] + [
    f"maxilla.{m}" for m in ("advance_mm", "vertical_mm", "roll_deg", "yaw_deg")]
#: Default Tikhonov weight α (mm² per unit²) and relative-decrease stop of a plan, shared by
#: `Scene.plan` and ``scripts/plan.py``: with α = 0 the motions the landmarks do not decide
#: drift to their bounds (the coarse class3-asym plan then crushes tissue).
TIKHONOV = 0.01
FTOL = 1e-3


@dataclasses.dataclass(frozen=True)
class Param:
    """One treatment parameter.

    Attributes:
        name: ``segment.motion`` or a sculpted blendshape's name.
        unit: "mm", "deg" or "1" (sculpted weight).
        segment: the segment it moves.
        kind: "translation", "rotation" or "sculpted".
        axis: (3,) direction (translation) or rotation axis.
        bounds: feasible range (lo, hi) in ``unit``.
        field: for sculpted shapes, a function X (K, 3) -> B (K, 3).
    """

    name: str
    unit: str
    segment: str
    kind: str
    axis: tuple = (0.0, 0.0, 0.0)
    bounds: tuple = (-np.inf, np.inf)
    field: object = None

    def values(self, X: np.ndarray, pivot: np.ndarray) -> np.ndarray:
        """Blendshape (K, 3), mm per unit, at rest positions X (K, 3) of segment vertices."""
        a = np.asarray(self.axis, dtype=float)
        if self.kind == "translation":
            return np.tile(a, (len(X), 1))
        if self.kind == "rotation":
            return np.deg2rad(1.0) * np.cross(a, X - pivot)
        return np.asarray(self.field(X), dtype=float)


class Treatment:
    """An ordered list of parameters and the blendshape matrix they define on a domain."""

    def __init__(self, params: list[Param]):
        names = [p.name for p in params]
        if len(set(names)) != len(names):
            raise InputError(f"duplicate parameter names in {names}")
        if not params:
            raise InputError("a treatment needs at least one parameter")
        self.params = list(params)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.params]

    @property
    def bounds(self) -> np.ndarray:
        """(Np, 2) feasible ranges."""
        return np.array([p.bounds for p in self.params], dtype=float)

    @property
    def segments(self) -> list[str]:
        """Segments (or groups) moved by at least one parameter, in order of first use."""
        return list(dict.fromkeys(p.segment for p in self.params))

    @property
    def active_segments(self) -> list[str]:
        """The mesh segments these parameters move (groups expanded to their members)."""
        return list(dict.fromkeys(m for s in self.segments for m in GROUPS.get(s, (s,))))

    def subset(self, names) -> "Treatment":
        """A treatment with only the named parameters, in the given order."""
        lookup = {p.name: p for p in self.params}
        unknown = [n for n in names if n not in lookup]
        if unknown:
            raise InputError(f"unknown parameter(s) {unknown}; known: {self.names}")
        return Treatment([lookup[n] for n in names])

    def vector(self, values: dict) -> np.ndarray:
        """Parameter vector (Np,) from ``{name: value}``; missing names are 0. A value is a
        number in the parameter's unit, or a string with that unit ("5", "5 mm", "3deg")."""
        unknown = [k for k in values if k not in self.names]
        if unknown:
            raise InputError(f"unknown parameter(s) {unknown}; known: {self.names}")
        p = np.zeros(len(self.params))
        for k, v in values.items():
            i = self.names.index(k)
            p[i] = _number_in(v, self.params[i])
        if not np.all(np.isfinite(p)):
            raise InputError(f"parameters must be finite: {dict(zip(self.names, p))}")
        return p

    def matrix(self, domain) -> np.ndarray:
        """Blendshape matrix B (n_local_blocks * 3, Np) on a `fem.domain.Domain`."""
        n = len(domain.X)
        B = np.zeros((n, 3, len(self.params)))
        for name in self.segments:
            members = GROUPS.get(name, (name,))
            missing = [m for m in members if m not in domain.segments]
            if missing:
                raise InputError(f"segment(s) {missing} of {name!r} not in the mesh "
                                 f"(segments: {list(domain.segments)})")
            blocks = domain.facet_blocks([domain.segments[m] for m in members])
            pivot = np.mean([domain.pivots[m] for m in members], axis=0)
            for i, p in enumerate(self.params):
                if p.segment == name:
                    B[blocks, :, i] = p.values(domain.X[blocks], pivot)
        return B.reshape(n * 3, -1)


def _number_in(value, param: "Param") -> float:
    """``value`` (number or "number [unit]") as a float in ``param.unit``, else `InputError`."""
    if not isinstance(value, bool):
        try:
            return float(value)
        except (TypeError, ValueError):
            pass
    m = re.fullmatch(r"\s*([-+]?\d*\.?\d+(?:[eE][-+]?\d+)?)\s*([a-zA-Z]+)\s*", str(value))
    if not m:
        raise InputError(f"parameter {param.name} = {value!r} is not a number")
    if m.group(2) != param.unit:
        raise InputError(f"parameter {param.name} is in {param.unit}, got {value!r}")
    return float(m.group(1))


def rigid_treatment(segments=("mandible", "maxilla_L", "maxilla_R"), motions=None) -> Treatment:
    """Built-in linearised rigid motions: for each segment, and each group of `GROUPS` whose
    members are all among them, the named motions (all six)."""
    segments = list(segments) + [g for g, members in GROUPS.items()
                                 if g not in segments and set(members) <= set(segments)]
    motions = list(MOTIONS) if motions is None else list(motions)
    bad = [m for m in motions if m not in MOTIONS]
    if bad:
        raise InputError(f"unknown motion(s) {bad}; known: {list(MOTIONS)}")
    return Treatment([Param(f"{s}.{m}", MOTIONS[m][2], s, MOTIONS[m][0], MOTIONS[m][1],
                            MOTIONS[m][3]) for s in segments for m in motions])


def sculpted_param(name: str, segment: str, rest_file, modified_file,
                   max_distance_mm: float = 1.0, bounds=(-1.0, 1.0)) -> Param:
    """A blendshape from a sculpted bone surface: modified minus rest, per rest vertex.

    The two surfaces (any meshio format) must have the same vertices in the same order.
    A mesh vertex takes the displacement of the nearest rest-surface vertex, which must lie
    within ``max_distance_mm``.
    """
    import meshio
    from scipy.spatial import cKDTree

    try:
        rest, mod = meshio.read(rest_file), meshio.read(modified_file)
    except (Exception, SystemExit) as e:  # meshio raises many types, even SystemExit
        raise InputError(f"cannot read sculpted surfaces {rest_file}, {modified_file}: {e}")
    if rest.points.shape != mod.points.shape:
        raise InputError(f"sculpted surface {modified_file} has {len(mod.points)} vertices, "
                         f"the rest surface {len(rest.points)}: they must correspond 1:1")
    disp = mod.points - rest.points
    if not np.all(np.isfinite(disp)):
        raise InputError(f"sculpted surface {modified_file} has NaN/inf coordinates")
    tree = cKDTree(rest.points)

    def field(X):
        d, i = tree.query(X)
        if np.any(d > max_distance_mm):
            raise InputError(f"sculpted blendshape {name!r}: {np.sum(d > max_distance_mm)} "
                             f"segment vertices are over {max_distance_mm} mm from the rest "
                             f"surface {rest_file} (max {d.max():.2f} mm)")
        return disp[i]

    return Param(name, "1", segment, "sculpted", bounds=tuple(bounds), field=field)
