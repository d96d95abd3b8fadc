"""Treatment model: the goals ``x̂_A(p)`` of the bone segments' surface vertices.

**Exact rigid motions** (the built-in parameters). A segment, or a group of segments, moves
rigidly about its pivot c::

    x̂ = R (X - c) + c + t,    R = Rz(yaw) · Ry(roll) · Rx(pitch)   (pitch applied first)

about the head's axes (x patient's left, y anterior, z superior: `meshes.frame`; the scene's
axes where the anatomy has no head frame), right-handed, in degrees; t in mm. The motions
are built in the head frame and returned in the scene's: ``T = H T_head H⁻¹`` with H the
head frame (head -> scene), so that an advance is along the face's anterior axis however the
head lay in the scanner. For a segment or group ``s``:

================  =====  ==============================  ================
name              unit   motion                          default bounds
================  =====  ==============================  ================
s.advance_mm      mm     t_y (anterior)                  [-15, 15]
s.lateral_mm      mm     t_x (patient's left)            [-10, 10]
s.vertical_mm     mm     t_z (superior)                  [-10, 10]
s.pitch_deg       deg    about +x: the front moves up    [-15, 15]
s.roll_deg        deg    about +y: the left side down    [-10, 10]
s.yaw_deg         deg    about +z: the front moves right [-10, 10]
================  =====  ==============================  ================

The segments form a tree (`PARENTS`): the LeFort I halves ``maxilla_L`` and ``maxilla_R``
make the group ``maxilla``; ``maxilla`` and ``mandible`` make ``jaws``, the maxillomandibular
complex (``jaws.pitch_deg`` rotates the occlusal plane). A segment's motion is the product of
the motions along its chain, outermost first: ``T_maxilla_L = T_jaws T_maxilla A_maxilla_L``;
a member's own motions are relative to its group's. A group's pivot is the mean of its
members' pivots (``jaws``: of the maxilla's and the mandible's, near the middle of the
occlusal plane); a segment's comes from the anatomy (default: the centroid of its bone
surface). ``∂x̂/∂p`` is analytic (`Treatment.transforms` with ``derivatives=True``).

**Occlusion.** With an occlusion O (4×4: the mandible's motion relative to the maxilla that
brings the teeth into the final occlusion), the mandible hangs from the maxilla:
``T_mandible = T_jaws T_maxilla O A_mandible``, so ``inv(T_maxilla) T_mandible = O`` while the
mandible's own motions are 0: maxilla and mandible then move as one unit.

**Linearised rigid motions** (``rigid_treatment(linear=True)``, the paper's blendshapes of the
same names): ``x̂ = X + Σ p_i B_i`` with B the translation axis or ``(π/180) a × (X - c)``.
Exact for translations only: a 12° pitch stretches the segment by 2.2 % (√(1 + θ²)).

**Sculpted blendshapes** (paper eq. 1) are linear and add to the rigid goal:
``x̂ = T X + Σ p_i B_i``.

Every segment of the anatomy is held to its goal; one that no parameter moves stays at X.
"""

from __future__ import annotations

import dataclasses
import functools
import re

import numpy as np

from meshes.anatomy import segment_tags
from meshes.errors import InputError
from meshes.transforms import rigid

MOTIONS = {  # name: (kind, axis index, unit, bounds)
    "advance_mm": ("translation", 1, "mm", (-15.0, 15.0)),
    "lateral_mm": ("translation", 0, "mm", (-10.0, 10.0)),
    "vertical_mm": ("translation", 2, "mm", (-10.0, 10.0)),
    "pitch_deg": ("rotation", 0, "deg", (-15.0, 15.0)),
    "roll_deg": ("rotation", 1, "deg", (-10.0, 10.0)),
    "yaw_deg": ("rotation", 2, "deg", (-10.0, 10.0)),
}
#: The segment tree: each segment's or group's group.
PARENTS = {"maxilla_L": "maxilla", "maxilla_R": "maxilla", "maxilla": "jaws",
           "mandible": "jaws"}
#: Each group's member segments (the leaves under it).
GROUPS = {"maxilla": ("maxilla_L", "maxilla_R"), "jaws": ("maxilla_L", "maxilla_R", "mandible")}
#: Parameters planned by default with the occlusion free: the mandible's six motions and the
#: maxilla's advance, vertical position, cant (roll) and midline (yaw), en bloc. The halves'
#: relative motion (a split of the palate) is left out: skin landmarks barely decide it, and
#: stepping the halves apart vertically shears the tissue over the midline cut (a 7 mm step:
#: 32 factorisations where the same motion en bloc takes 2, medium). So is the maxilla's
#: pitch: with it the coarse default plan tilted the incisors 9° down into the lower lip
#: (det F 0.09, bone 0.4 mm short of its goal) to gain 0.04 mm of landmark distance.
PLAN_PARAMS = [f"mandible.{m}" for m in MOTIONS] + [
    f"maxilla.{m}" for m in ("advance_mm", "vertical_mm", "roll_deg", "yaw_deg")]
#: Parameters planned with the final occlusion: the maxillomandibular complex's six motions.
JAWS_PARAMS = [f"jaws.{m}" for m in MOTIONS]
#: Default Tikhonov weight α (mm² per unit²) and relative-decrease stop of a plan, shared by
#: `Scene.plan` and ``scripts/plan.py``: with α = 0 the motions the landmarks do not decide
#: drift to their bounds (the coarse class3-asym plan then crushes tissue).
TIKHONOV = 0.01
FTOL = 1e-3
#: Lever (mm) that turns a rotation-block error into mm when matching transforms.
LEVER_MM = 100.0
#: A transform is reached when its residual (translation and lever-scaled rotation, mm) is
#: below this.
TRANSFORM_TOL_MM = 1e-6


@dataclasses.dataclass(frozen=True)
class Param:
    """One treatment parameter.

    Attributes:
        name: ``segment.motion`` or a sculpted blendshape's name.
        unit: "mm", "deg" or "1" (sculpted weight).
        segment: the segment or group it moves.
        kind: "rigid" (exact), "linear" (linearised rigid) or "sculpted".
        motion: a key of `MOTIONS` (rigid and linear kinds).
        bounds: feasible range (lo, hi) in ``unit``.
        field: for sculpted shapes, a function X (K, 3) -> B (K, 3).
    """

    name: str
    unit: str
    segment: str
    kind: str
    motion: str = ""
    bounds: tuple = (-np.inf, np.inf)
    field: object = None

    def values(self, X: np.ndarray, pivot: np.ndarray, axes=None) -> np.ndarray:
        """Linear blendshape (K, 3), mm per unit, at rest positions X (K, 3) of its
        segments' vertices (linear and sculpted kinds); ``axes`` (3, 3): the head's axes as
        columns (default the scene's)."""
        if self.kind == "sculpted":
            return np.asarray(self.field(X), dtype=float)
        kind, axis = MOTIONS[self.motion][:2]
        a = (np.eye(3) if axes is None else np.asarray(axes))[:, axis]
        if kind == "translation":
            return np.tile(a, (len(X), 1))
        return np.deg2rad(1.0) * np.cross(a, X - pivot)


def _motion_matrix(q: np.ndarray, c: np.ndarray):
    """A = [R, c + t - R c] (4×4) for the six motions q (MOTIONS order: mm, deg) about the
    pivot c (3,), and dA/dq (6, 4, 4) per unit."""
    t = np.array([q[1], q[0], q[2]])
    ang = np.deg2rad(q[3:])
    cs, sn = np.cos(ang), np.sin(ang)
    rots, drots = [], []
    for i, (co, si) in enumerate(zip(cs, sn)):   # about x, y, z
        j, k = (i + 1) % 3, (i + 2) % 3
        R, dR = np.eye(3), np.zeros((3, 3))
        R[j, j] = R[k, k] = co
        R[j, k], R[k, j] = -si, si
        dR[j, j] = dR[k, k] = -si
        dR[j, k], dR[k, j] = -co, co
        rots.append(R)
        drots.append(dR * np.deg2rad(1.0))
    Rx, Ry, Rz = rots
    R = Rz @ Ry @ Rx
    dRs = [Rz @ Ry @ drots[0], Rz @ drots[1] @ Rx, drots[2] @ Ry @ Rx]
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = R, c + t - R @ c
    dA = np.zeros((6, 4, 4))
    for m, axis in enumerate((1, 0, 2)):   # advance (y), lateral (x), vertical (z)
        dA[m, axis, 3] = 1.0
    for m, dR in enumerate(dRs):
        dA[3 + m, :3, :3], dA[3 + m, :3, 3] = dR, -dR @ c
    return A, dA


class Treatment:
    """An ordered list of parameters, an optional occlusion (4×4, scene frame) and the head
    frame (4×4, head -> scene; None: the identity) its motions are built in (module
    docstring).

    Pivots (``{segment: (3,)}`` mm) come from the anatomy, so methods that place motions
    take them as an argument."""

    def __init__(self, params: list[Param], occlusion=None, frame=None):
        names = [p.name for p in params]
        if len(set(names)) != len(names):
            raise InputError(f"duplicate parameter names in {names}")
        if not params:
            raise InputError("a treatment needs at least one parameter")
        self.params = list(params)
        self.occlusion = None if occlusion is None else rigid(occlusion, "the occlusion")
        self.frame = None if frame is None else rigid(frame, "the head frame")
        if self.occlusion is not None and any(p.kind == "linear" for p in self.params):
            raise InputError("an occlusion holds the mandible by an exact rigid motion: use "
                             "the exact rigid parameters, not the linearised ones")

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

    def subset(self, names) -> "Treatment":
        """A treatment with only the named parameters, in the given order."""
        lookup = {p.name: p for p in self.params}
        unknown = [n for n in names if n not in lookup]
        if unknown:
            raise InputError(f"unknown parameter(s) {unknown}; known: {self.names}")
        return Treatment([lookup[n] for n in names], self.occlusion, self.frame)

    def with_occlusion(self, occlusion) -> "Treatment":
        """The same parameters with the mandible held in ``occlusion`` (4×4) to the maxilla."""
        return Treatment(self.params, occlusion, self.frame)

    def in_frame(self, frame) -> "Treatment":
        """The same treatment with its motions built in the head frame ``frame`` (4×4, head
        -> scene; None: the scene's axes)."""
        return Treatment(self.params, self.occlusion, frame)

    @property
    def axes(self) -> np.ndarray:
        """(3, 3): the head's left, anterior and superior axes (columns), scene frame."""
        return np.eye(3) if self.frame is None else self.frame[:3, :3]

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

    def outside_bounds(self, p) -> list[str]:
        """A message for each parameter of p (Np,) outside its feasible bounds."""
        return [f"{par.name} = {v:g} {par.unit} is outside its feasible range "
                f"[{par.bounds[0]:g}, {par.bounds[1]:g}] {par.unit}"
                for par, v in zip(self.params, np.asarray(p, dtype=float))
                if not par.bounds[0] <= v <= par.bounds[1]]

    # ------------------------------------------------------------------ rigid motions
    def node_pivots(self, pivots: dict) -> dict:
        """Pivot (3,) of every segment in ``pivots`` and of every group with a member there:
        the mean of its members' (segment or group) pivots."""
        out = {s: np.asarray(c, dtype=float) for s, c in pivots.items()}
        for group in ("maxilla", "jaws"):   # inner groups first
            kids = [out[n] for n, g in PARENTS.items() if g == group and n in out]
            if kids:
                out[group] = np.mean(kids, axis=0)
        return out

    def _chain(self, segment: str, nodes: dict, occlusion) -> list:
        """The factors of a segment's motion, outermost first: node names, or the occlusion
        (a 4×4) where the mandible hangs from the maxilla."""
        chain, node = [segment], segment
        while node in PARENTS:
            if node == "mandible" and occlusion is not None:
                if "maxilla" not in nodes:
                    raise InputError("an occlusion holds the mandible to the maxilla, but the "
                                     "anatomy has no maxilla segment")
                chain.append(occlusion)
                node = "maxilla"
            else:
                node = PARENTS[node]
            chain.append(node)
        return chain[::-1]

    def transforms(self, p, pivots: dict, derivatives: bool = False):
        """Rigid motion ``{segment: (4, 4)}`` of every segment in ``pivots`` at p (Np,); with
        ``derivatives`` also ``{segment: (Np, 4, 4)}``, dT/dp_i per unit (0 for linear and
        sculpted parameters)."""
        p = np.asarray(p, dtype=float)
        H = np.eye(4) if self.frame is None else self.frame
        H_inv = np.linalg.inv(H)
        nodes = self.node_pivots({s: H_inv[:3, :3] @ c + H_inv[:3, 3]
                                  for s, c in pivots.items()})   # in the head frame
        occlusion = None if self.occlusion is None else H_inv @ self.occlusion @ H
        own = {}   # node -> [(motion index, parameter index)]
        for i, par in enumerate(self.params):
            if par.kind == "rigid":
                if par.segment not in nodes:
                    raise InputError(f"parameter {par.name}: segment {par.segment!r} is not in "
                                     f"the anatomy (segments: {list(pivots)})")
                own.setdefault(par.segment, []).append((list(MOTIONS).index(par.motion), i))
        mats = {}
        for node, pairs in own.items():
            q = np.zeros(6)
            for m, i in pairs:
                q[m] = p[i]
            mats[node] = _motion_matrix(q, nodes[node])
        T_all, dT_all = {}, {}
        for seg in pivots:
            chain = self._chain(seg, nodes, occlusion)
            factors = [f if not isinstance(f, str) else mats[f][0] if f in mats else np.eye(4)
                       for f in chain]
            T_all[seg] = functools.reduce(np.matmul, factors, np.eye(4))
            if derivatives:
                dT = np.zeros((len(p), 4, 4))
                left = np.eye(4)
                for j, f in enumerate(chain):
                    if isinstance(f, str) and f in own:
                        right = functools.reduce(np.matmul, factors[j + 1:], np.eye(4))
                        for m, i in own[f]:
                            dT[i] = left @ mats[f][1][m] @ right
                    left = left @ factors[j]
                dT_all[seg] = H @ dT @ H_inv
            # to the scene's frame; I + H (T - I) H⁻¹ keeps a segment held still exactly still
            T_all[seg] = np.eye(4) + H @ (T_all[seg] - np.eye(4)) @ H_inv
        return (T_all, dT_all) if derivatives else T_all

    def params_from_transforms(self, transforms: dict, pivots: dict) -> np.ndarray:
        """The parameters (Np,) whose motions are ``transforms`` ({segment: 4×4}; a segment
        not named is held, the identity): Gauss-Newton on the transforms' entries (rotation
        scaled by `LEVER_MM`), minimum-norm where parameters are redundant. `InputError` when
        the scene's parameters cannot reach them (within `TRANSFORM_TOL_MM`)."""
        unknown = [s for s in transforms if s not in pivots]
        if unknown:
            raise InputError(f"transform(s) for unknown segment(s) {unknown}; segments: "
                             f"{list(pivots)}")
        want = {s: rigid(transforms.get(s, np.eye(4)), f"transform of {s!r}") for s in pivots}
        scale = np.ones((3, 4))
        scale[:, :3] = LEVER_MM

        def residual(p):
            T, dT = self.transforms(p, pivots, derivatives=True)
            r = np.concatenate([((T[s] - want[s])[:3] * scale).ravel() for s in pivots])
            J = np.concatenate([(dT[s][:, :3] * scale).reshape(len(p), -1).T for s in pivots])
            return r, J

        p = np.zeros(len(self.params))
        for _ in range(50):
            r, J = residual(p)
            dp = np.linalg.lstsq(J, -r, rcond=None)[0]
            p += dp
            if np.abs(dp).max() < 1e-13:
                break
        r, _ = residual(p)
        if np.abs(r).max() > TRANSFORM_TOL_MM:
            raise InputError(f"the transforms cannot be reached with the parameters "
                             f"{self.names} (off by {np.abs(r).max():.3g} mm): use a scene "
                             "with the motions they need (--params-used)")
        return p

    # ------------------------------------------------------------------ goals on a mesh
    def goal_map(self, domain) -> "GoalMap":
        return GoalMap(self, domain)


class GoalMap:
    """The treatment's goal displacement ``g(p) = x̂(p) - X`` on a `fem.domain.Domain`'s dof
    blocks, (n_local_blocks * 3,) mm, and its Jacobian dg/dp (n_local_blocks * 3, Np) mm per
    unit; the interface `fem.equilibrium.Equilibrium` takes. Zero off the segments."""

    def __init__(self, treatment: Treatment, domain):
        self.treatment, self.pivots = treatment, dict(domain.pivots)
        self.n_params = len(treatment.params)
        self._X = domain.X
        self._blocks = {s: domain.facet_blocks(segment_tags(tag))
                        for s, tag in domain.segments.items()}
        self.linear = all(p.kind != "rigid" for p in treatment.params)
        nodes = treatment.node_pivots(self.pivots)
        n = len(domain.X)
        B = np.zeros((n, 3, self.n_params))
        self._tag_segment = {t: s for s, tag in domain.segments.items()
                             for t in segment_tags(tag)}
        self._turns = []   # (parameter, axis (3,) per unit, segments) of linearised rotations
        for i, par in enumerate(treatment.params):
            if par.kind == "rigid":
                continue
            members = GROUPS.get(par.segment, (par.segment,))
            missing = [m for m in members if m not in domain.segments]
            if missing and not (par.segment in GROUPS and len(missing) < len(members)):
                raise InputError(f"segment(s) {missing} of {par.name!r} not in the mesh "
                                 f"(segments: {list(domain.segments)})")
            blocks = domain.facet_blocks([t for m in members if m in domain.segments
                                          for t in segment_tags(domain.segments[m])])
            B[blocks, :, i] = par.values(domain.X[blocks], nodes[par.segment], treatment.axes)
            if par.kind == "linear" and MOTIONS[par.motion][0] == "rotation":
                axis = treatment.axes[:, MOTIONS[par.motion][1]]
                self._turns.append((i, np.deg2rad(1.0) * axis, members))
        self._B = B.reshape(n * 3, -1)
        if not self.linear:
            treatment.transforms(np.zeros(self.n_params), self.pivots)   # validates segments

    def goal(self, p) -> np.ndarray:
        """g(p), (n_local_blocks * 3,) mm."""
        g = self._B @ p
        if not self.linear:
            out = g.reshape(-1, 3)
            for s, T in self.treatment.transforms(p, self.pivots).items():
                X = self._X[self._blocks[s]]
                out[self._blocks[s]] += X @ T[:3, :3].T + T[:3, 3] - X
        return g

    def jacobian(self, p) -> np.ndarray:
        """dg/dp at p, (n_local_blocks * 3, Np) mm per unit."""
        if self.linear:
            return self._B
        J = self._B.copy().reshape(-1, 3, self.n_params)
        _, dT = self.treatment.transforms(p, self.pivots, derivatives=True)
        for s, d in dT.items():
            X = self._X[self._blocks[s]]
            J[self._blocks[s]] += np.einsum("kj,pij->kip", X, d[:, :3, :3]) + d[:, :3, 3].T
        return J.reshape(-1, self.n_params)

    def turns(self, p, tags) -> np.ndarray:
        """The rotation (len(tags), 3, 3) at p of the segment whose facets (or teeth) carry
        each tag: ``R`` of its rigid motion, plus ``θ [a]×`` for each linearised rotation θ
        about a that moves it."""
        out = np.tile(np.eye(3), (len(tags), 1, 1))
        segs = [self._tag_segment[t] for t in tags]
        if not self.linear:
            T = self.treatment.transforms(p, self.pivots)
            out[:] = [T[s][:3, :3] for s in segs]
        for i, a, members in self._turns:
            for j, s in enumerate(segs):
                if s in members:
                    out[j] += p[i] * _cross_matrix(a)
        return out

    def turns_jacobian(self, p, tags) -> np.ndarray:
        """d(turns)/dp (len(tags), Np, 3, 3) per unit."""
        segs = [self._tag_segment[t] for t in tags]
        out = np.zeros((len(tags), self.n_params, 3, 3))
        if not self.linear:
            _, dT = self.treatment.transforms(p, self.pivots, derivatives=True)
            out[:] = [dT[s][:, :3, :3] for s in segs]
        for i, a, members in self._turns:
            for j, s in enumerate(segs):
                if s in members:
                    out[j, i] += _cross_matrix(a)
        return out


def _cross_matrix(a: np.ndarray) -> np.ndarray:
    """[a]× (3, 3): [a]× v = a × v."""
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


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


def rigid_treatment(segments=("mandible", "maxilla_L", "maxilla_R"), motions=None,
                    linear: bool = False, occlusion=None, groups: bool = True) -> Treatment:
    """Built-in rigid motions: for each segment, and (``groups``) each group of `GROUPS`
    whose members are all among them, the named motions (all six); exact (default) or the
    paper's linearised blendshapes (``linear``)."""
    segments = list(segments) + [g for g, members in GROUPS.items() if groups and
                                 g not in segments and set(members) <= set(segments)]
    motions = list(MOTIONS) if motions is None else list(motions)
    bad = [m for m in motions if m not in MOTIONS]
    if bad:
        raise InputError(f"unknown motion(s) {bad}; known: {list(MOTIONS)}")
    kind = "linear" if linear else "rigid"
    return Treatment([Param(f"{s}.{m}", MOTIONS[m][2], s, kind, m, MOTIONS[m][3])
                      for s in segments for m in motions], occlusion)


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
