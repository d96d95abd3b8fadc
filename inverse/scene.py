"""`Scene`: the Python API. An anatomy, a treatment model and the equilibrium solver together.

    scene = Scene.from_case("class3", "coarse")
    scene.solve({"mandible.advance_mm": 5.0})
    scene.landmarks()["Pg"]          # deformed position, mm
"""

from __future__ import annotations

from mpi4py import MPI

import time

import numpy as np

from fem.domain import create_domain
from fem.equilibrium import Equilibrium, SolveStats
from fem.forms import DEFAULT_PENALTY
from fem.io import write_grid
from fem.material import NeoHookean, Tissues, material_from_spec
from fem.policy import EquilibriumOptions
from inverse.treatment import Treatment, rigid_treatment
from meshes.anatomy import segment_tags
from meshes.errors import InputError
from meshes.synthetic import synthetic_head

#: How the tissue holds to the teeth (`Scene`'s ``contact``).
CONTACTS = ("sliding", "glued")


class Scene:
    """A patient model ready to simulate.

    Args:
        anatomy: an `Anatomy` or a callable returning one (evaluated on rank 0 only).
        treatment: parameters (default: six exact rigid motions per segment and group of
            the anatomy, `inverse.treatment.rigid_treatment`).
        params_used: optional subset of parameter names to keep, in order.
        occlusion: "free" (default: the jaws move independently), "final" (the mandible is
            held to the maxilla in the anatomy's final occlusion) or a 4×4 occlusion.
            Every segment is held to its goal; one that no parameter moves stays put.
        linear, groups: for the default treatment: the paper's linearised blendshapes instead
            of exact rigid motions; with the group motions (maxilla.*, jaws.*).
        contact: how the tissue holds to the teeth (`meshes.anatomy.TEETH_OFFSET` facets):
            "sliding" (only the normal gap is held: the lips slide on the teeth), "glued"
            (held like the rest of the segment, the paper's model) or None (default: the
            anatomy's ``contact`` where it has teeth, else glued: a CT scene's teeth slide,
            a synthetic head's are glued).
        degree: Lagrange degree of the displacement, 1 (default) or 2.
        material: "tissues" (skin, fat and lean tissue per cell, `fem.material.Tissues`),
            "homogeneous" (the paper's E = 5 kPa, nu = 0.47), a material file (.json,
            `fem.material.read_material_file`), a `NeoHookean` or `Tissues`, or None
            (default: the anatomy's ``material``: a CT scene's tissues, a synthetic head's
            homogeneous material).
        penalty (kPa/mm), solver (preset name), options (PETSc options), and
            ``equilibrium`` (a `fem.policy.EquilibriumOptions`, or a dict of its fields:
            method, xtol, frtol, max_it, ...; the nonlinear solve, quasi-Newton or Newton):
            passed to `fem.equilibrium.Equilibrium`. ``newton``: the same under its former
            name.
    """

    case: str | None = None
    resolution: str | None = None

    def __init__(self, anatomy, treatment: Treatment | None = None,
                 params_used=None, occlusion="free", linear: bool = False,
                 groups: bool = True, material: NeoHookean | Tissues | str | None = None,
                 penalty: float = DEFAULT_PENALTY, solver: str = "direct",
                 options: dict | None = None, equilibrium=None,
                 contact: str | None = None, degree: int = 1,
                 comm: MPI.Comm = MPI.COMM_WORLD, newton: dict | None = None):
        if newton is not None and equilibrium is not None:
            raise InputError("give the equilibrium's settings once: 'equilibrium' (or its "
                             "former name 'newton')")
        equilibrium = newton if equilibrium is None else equilibrium
        t0 = time.perf_counter()
        self.domain = create_domain(anatomy, comm, degree=degree)
        self.timings = {"mesh": time.perf_counter() - t0}
        treatment = treatment or rigid_treatment(tuple(self.domain.segments), linear=linear,
                                                 groups=groups)
        if isinstance(occlusion, str) and occlusion == "final":
            if self.domain.occlusion is None:
                raise InputError(f"anatomy {self.domain.name!r} has no final occlusion (give "
                                 "'occlusion' in its sidecar)")
            occlusion = self.domain.occlusion
        elif isinstance(occlusion, str) and occlusion != "free":
            raise InputError(f"occlusion must be 'free', 'final' or a 4x4, got {occlusion!r}")
        if not isinstance(occlusion, str):
            treatment = treatment.with_occlusion(occlusion)
        if self.domain.head_frame is not None:   # the motions' axes are the head's
            treatment = treatment.in_frame(self.domain.head_frame.matrix)
        self.treatment = treatment.subset(params_used) if params_used else treatment
        if contact not in (None, *CONTACTS):
            raise InputError(f"contact must be one of {list(CONTACTS)}, got {contact!r}")
        teeth = self.domain.teeth_tags
        if contact == "sliding" and not teeth:
            raise InputError(f"anatomy {self.domain.name!r} has no teeth facets for the lips "
                             "to slide on: use contact 'glued'")
        self.contact = contact or (self.domain.contact if teeth else "glued")
        sliding = teeth if self.contact == "sliding" else []
        material = self.domain.material if material is None else material
        #: "homogeneous", "tissues", a material file, or the repr of the material given
        self.material = material if isinstance(material, str) else repr(material)
        material = material_from_spec(material)
        glued = [t for s in self.domain.segments.values() for t in segment_tags(s)
                 if t not in sliding]
        t0 = time.perf_counter()
        if isinstance(equilibrium, EquilibriumOptions):   # whole: solver and options in it
            if solver != "direct" or options:
                raise InputError("give the solver and PETSc options in the "
                                 "EquilibriumOptions, not beside it")
        else:
            equilibrium = EquilibriumOptions(solver=solver, options=options or {},
                                             **(equilibrium or {}))
        self.eq = Equilibrium(self.domain, self.treatment.goal_map(self.domain), glued,
                              sliding, material=material, penalty=penalty,
                              settings=equilibrium)
        self.timings["compile"] = time.perf_counter() - t0
        self._landmark_op = self.domain.point_operator(list(self.domain.landmarks))

    @classmethod
    def from_case(cls, case: str = "class3-asym", resolution: str = "coarse",
                  comm: MPI.Comm = MPI.COMM_WORLD, **kwargs) -> "Scene":
        """A built-in synthetic case (see `meshes.synthetic.CASES`), generated on rank 0."""
        from meshes.synthetic import _check

        _check(case, resolution)  # same error on every rank before any collective call
        scene = cls(lambda: synthetic_head(case, resolution), comm=comm, **kwargs)
        scene.case, scene.resolution = case, resolution
        return scene

    @property
    def param_names(self) -> list[str]:
        return self.treatment.names

    @property
    def params(self) -> np.ndarray:
        """Parameters (Np,) of the current equilibrium."""
        return self.eq.p.copy()

    def param_vector(self, p) -> np.ndarray:
        """(Np,) from a dict ``{name: value}`` or a sequence; validated."""
        if isinstance(p, dict):
            return self.treatment.vector(p)
        p = np.asarray(p, dtype=float).reshape(-1)
        if p.size != len(self.param_names) or not np.all(np.isfinite(p)):
            raise InputError(f"expected {len(self.param_names)} finite parameters, got {p}")
        return p

    def solve(self, p, tangent: bool = False, start=None) -> SolveStats:
        """Equilibrium at ``p`` (dict or (Np,)), warm-started from the current equilibrium
        (or from the state ``start``). ``tangent``: an adjoint gradient follows (see
        `Equilibrium.solve`)."""
        return self.eq.solve(self.param_vector(p), tangent=tangent, start=start)

    def transforms(self, p=None) -> dict:
        """Rigid motion {segment: (4, 4)} of every bone segment at p (default: the current
        equilibrium's), mm, scene frame."""
        p = self.params if p is None else self.param_vector(p)
        return self.treatment.transforms(p, self.domain.pivots)

    @property
    def head_frame(self):
        """The anatomy's `meshes.frame.HeadFrame` (the identity where it has none)."""
        from meshes.frame import HeadFrame

        return self.domain.head_frame or HeadFrame.identity()

    def motion_report(self) -> dict:
        """Report keys of the current equilibrium's bone motions: ``transforms`` {segment:
        4×4} and ``occlusion`` (4×4, or None when the jaws are free), both in the scene's
        frame, the head frame they were built in (`meshes.frame.HeadFrame.report`), and
        ``contact`` (how the tissue held to the teeth), and ``displacement_max_mm``, the
        largest displacement at a vertex (the top of ParaView's colour bar). Collective."""
        dom = self.domain
        u = self.eq.u.x.array.reshape(-1, 3)[:dom.n_owned][dom.input_index[:dom.n_owned] >= 0]
        top = dom.comm.allreduce(float(np.linalg.norm(u, axis=1).max(initial=0.0)), op=MPI.MAX)
        return {"transforms": self.transforms(), "occlusion": self.treatment.occlusion,
                "contact": self.contact, "material": self.material,
                "displacement_max_mm": top, **self.head_frame.report()}

    def params_from_transforms(self, transforms: dict) -> np.ndarray:
        """The parameters (Np,) that move the segments by ``transforms`` ({segment: 4×4};
        unnamed segments stay put), see `Treatment.params_from_transforms`."""
        return self.treatment.params_from_transforms(transforms, self.domain.pivots)

    def landmarks(self, names=None, rest: bool = False) -> dict[str, np.ndarray]:
        """Landmark positions {name: (3,)} mm, deformed (or rest). Collective."""
        names = list(self.domain.landmarks) if names is None else list(names)
        unknown = [n for n in names if n not in self.domain.landmarks]
        if unknown:
            raise InputError(f"unknown landmark(s) {unknown}; known: {list(self.domain.landmarks)}")
        u = np.zeros_like(self.eq.u.x.array) if rest else self.eq.u.x.array
        pts = self._landmark_op.apply(u)
        order = list(self.domain.landmarks)
        return {n: pts[order.index(n)] for n in names}

    def active_goal_error(self) -> float:
        """Max distance (mm) of active vertices from their goals."""
        return self.eq.active_goal_error()

    def write(self, out_dir, fields: dict | None = None) -> list[str]:
        """ParaView's files into ``out_dir``, atomically; each is one grid that ParaView's
        default reader opens with its arrays (docs/decisions.md, "Files for ParaView"):

        * ``displacement.xdmf``: the rest volume with ``displacement`` (mm) at its vertices
          (*Warp By Vector* shows the deformed volume) and the tissue fractions of its cells;
        * ``deformed.xdmf``: the deformed boundary (skin, bone, cut faces), with
          ``displacement`` at its vertices and each triangle's ``tag`` (`meshes.anatomy`).

        ``fields``: more point data for both, ``{name: (n_vertices, ...)}`` on rank 0 (e.g.
        the band, `scripts._common.bands_of`). Returns the file names. Collective."""
        from pathlib import Path

        out = Path(out_dir)
        fields = fields or {}
        self.write_volume(out / "displacement.xdmf", {"displacement": self.eq.u.x.array},
                          fields)
        dom = self.domain
        tri, tag = dom.tagged_triangles()
        u, x = dom.vertex_array(self.eq.u.x.array), dom.vertex_array(dom.X)
        if dom.comm.rank == 0:
            used, tri = np.unique(tri, return_inverse=True)
            x, tri = x[used] + u[used], tri.reshape(-1, 3)
            fields = {"displacement": u[used], **{k: v[used] for k, v in fields.items()}}
        write_grid(out / "deformed.xdmf", x, ("triangle", tri), fields, {"tag": tag}, dom.comm)
        return ["displacement.xdmf", "displacement.h5", "deformed.xdmf", "deformed.h5"]

    def write_volume(self, path, fields: dict, gathered: dict | None = None) -> None:
        """The rest volume to ``path`` (`fem.io.write_grid`) with ``fields`` ``{name: local
        dof-block array}`` (e.g. ``eq.u.x.array``) and ``gathered`` ``{name: (n_vertices,
        ...)}`` on rank 0 at its vertices, and the tissue fractions
        (`meshes.tissue.TISSUES`) of its cells. Collective."""
        from meshes.tissue import TISSUES

        dom = self.domain
        point_data = {k: dom.vertex_array(v) for k, v in fields.items()}
        point_data.update(gathered or {})
        tissues = None if dom.tissues is None else dom.cell_array(dom.tissues)
        cell_data = {} if tissues is None else {n: tissues[:, k] for k, n in enumerate(TISSUES)}
        write_grid(path, dom.vertex_array(dom.X), ("tetra", dom.cell_array()), point_data,
                   cell_data, dom.comm)

    def objective(self, targets, landmarks=None, weights=None, tikhonov: float = 0.0):
        """`inverse.objective.Objective` for landmark targets.

        Args:
            targets: JSON path or ``{name: entry}`` (`inverse.objective.load_targets`: a
                point in mm, or a point held along some of the head frame's axes);
                ``landmarks``: optional subset of its names; weights: ``{name: w}`` or (Nt,);
                tikhonov: α (mm² per unit²).
        """
        from inverse.objective import Objective, load_targets

        names, pts, held = load_targets(targets, self.landmarks(rest=True), landmarks)
        if isinstance(weights, dict):
            bad = [n for n in weights if n not in names]
            if bad:
                raise InputError(f"weights for landmark(s) {bad} that have no target")
            weights = [float(weights.get(n, 1.0)) for n in names]
        return Objective(self.eq, self.domain.point_operator(names), pts, weights, tikhonov,
                         names, self.head_frame.rotation, held)

    def default_targets(self, goal: str | None = None) -> dict:
        """A built-in treatment goal ``{name: entry}`` (`inverse.targets`): ``goal``, or by
        default the case's."""
        from inverse.targets import default_targets

        return default_targets(goal or self.case, self.landmarks(rest=True),
                               self.domain.head_frame)

    def plan(self, targets=None, landmarks=None, weights=None, tikhonov: float | None = None,
             p0=None, **options):
        """Plan the treatment that brings landmarks to ``targets`` (default: the case's
        built-in goal); ``tikhonov`` defaults to `inverse.treatment.TIKHONOV`. Returns
        `inverse.planner.PlanResult`; the scene is left at the planned equilibrium.
        ``options`` go to `inverse.planner.gauss_newton` (stops at a relative decrease of
        T below ``ftol`` = `inverse.treatment.FTOL` by default)."""
        from inverse.planner import gauss_newton
        from inverse.treatment import TIKHONOV

        tikhonov = TIKHONOV if tikhonov is None else tikhonov
        targets = self.default_targets() if targets is None else targets
        obj = self.objective(targets, landmarks, weights, tikhonov)
        return gauss_newton(self, obj, p0=p0, **options)
