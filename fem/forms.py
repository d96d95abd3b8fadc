"""The energy and its forms, a part that owns them (`EnergyForms`): E = E_NH + E_A (+ the
sliding penalty), its residual f, Jacobian K and goal couplings df/dg, df/dR as functions of
the state x and the parameters p; the displacement u they are evaluated at, the goal field
g(p), the sliding facets' turns R(p); the state's soundness (det F > 0).
"""

from __future__ import annotations

from mpi4py import MPI
from petsc4py import PETSc

import contextlib
import logging
import time

import dolfinx
import numpy as np
import ufl

from fem import compat
from fem.material import NeoHookean, neo_hookean
from meshes.errors import InputError

log = logging.getLogger(__name__)

#: Default penalty stiffness k per unit active area, kPa/mm (= mN/mm^3): max active goal
#: error 0.002 mm on a 5 mm advance, 0.041 mm on the demo treatment (goal: 0.05 mm).
DEFAULT_PENALTY = 5.0e4


class EnergyForms:
    """The forms of one scene and the fields they are evaluated at (`Equilibrium.forms`).

    Every evaluation takes the state it is at (a PETSc vector x, mm) and leaves u there; the
    goals are those of the last `set_params` (evaluations at other parameters restore them).

    Args:
        domain: the distributed anatomy (`fem.domain.Domain`).
        goals: the goal map g(p) (`fem.equilibrium.LinearGoals` or its interface).
        active_tags, sliding_tags: facet tags held to their goals whole (glued) and in the
            normal direction only (sliding).
        material: `NeoHookean` or `fem.material.Tissues`; penalty: k, kPa/mm.
        quadrature_degree: of the penalties' facet integrals; volume_quadrature_degree: of
            the energy's cell integral (None: 2 (degree - 1)).

    Attributes:
        u: the displacement (dolfinx Function) the forms are at; ``uvec``: its PETSc vector.
        goal: the goal field g(p); turn: the sliding facets' DG0 rotations R(p) (None where
            nothing slides).
        ufl, compiled: the forms by name (energy, residual, jacobian, coupling, contact, and
            where tissue slides turn_coupling, normal_gap, sliding_area), UFL and compiled.
        A, b: a matrix of K's layout (with the rigid-body near-nullspace) and a vector of f's.
        dfdg, dfdR: the couplings df/dg and df/dR (None where nothing slides) at the last
            `assemble_couplings`.
        assemble_s: seconds spent assembling the energy, f and K, cumulative.
    """

    def __init__(self, domain, goals, active_tags, sliding_tags, material, penalty: float,
                 quadrature_degree: int, volume_quadrature_degree: int | None):
        self.domain, self.goals = domain, goals
        V = domain.V
        self.u = dolfinx.fem.Function(V, name="displacement")
        self.uvec = compat.petsc_vec(self.u)
        self.goal = dolfinx.fem.Function(V, name="goal")
        self.n_params = goals.n_params
        n_local = self.u.x.array.size
        g0 = np.asarray(goals.goal(np.zeros(self.n_params)))
        if g0.shape != (n_local,):
            raise InputError(f"goals must be ({n_local},) per p, got {g0.shape}")
        active_tags, sliding_tags = tuple(active_tags), tuple(sliding_tags)
        if not active_tags and not sliding_tags:
            raise InputError("no facets are held to a goal: give active or sliding tags")
        # owned vertices held to their goals (checked after every solve)
        self._active = np.zeros(domain.n_owned, dtype=bool)
        if active_tags:
            blocks = domain.facet_blocks(active_tags)
            self._active[blocks[blocks < domain.n_owned]] = True
        v, du = ufl.TestFunction(V), ufl.TrialFunction(V)
        F = ufl.Identity(3) + ufl.grad(self.u)
        ds = domain.ds()
        md = {"quadrature_degree": quadrature_degree}
        gap = self.u - self.goal
        # material and penalty are constants (or cell fields), not numbers: the forms
        # compile once for all values
        k = dolfinx.fem.Constant(domain.mesh, PETSc.ScalarType(penalty))
        self.material = material
        mu, lmbda = self._lame_fields = tuple(self._lame(material))
        self._material_form = None   # df/dθ's form, compiled on first use
        qd = 2 * (domain.degree - 1) if volume_quadrature_degree is None else \
            volume_quadrature_degree
        dx = self._dx = ufl.dx(domain=domain.mesh, metadata={"quadrature_degree": qd})
        contact = 0
        if active_tags:
            contact = 0.5 * k * ufl.inner(gap, gap) * ds(active_tags, metadata=md)
        self.turn = None   # R(p) on the sliding facets' cells
        self._sliding_tags = sliding_tags
        if sliding_tags:
            self._setup_turns(sliding_tags)
            n = ufl.dot(self.turn, ufl.FacetNormal(domain.mesh))
            contact = contact + 0.5 * k * ufl.inner(gap, n) ** 2 * ds(sliding_tags, metadata=md)
        energy = neo_hookean(F, mu, lmbda) * dx + contact
        residual = ufl.derivative(energy, self.u, v)
        self.ufl = dict(energy=energy, residual=residual,
                        jacobian=ufl.derivative(residual, self.u, du),
                        coupling=ufl.derivative(residual, self.goal, du),   # df/dg
                        contact=ufl.derivative(contact, self.u, v))
        if self.turn is not None:   # df/dR, for df/dp = df/dg dg/dp + df/dR dR/dp
            self.ufl["turn_coupling"] = ufl.derivative(
                residual, self.turn, ufl.TrialFunction(self.turn.function_space))
            # per cell: the sliding facets' ∫ ((u - g)·n)² ds and their area (the gap check)
            w = ufl.TestFunction(compat.scalar_space(domain.mesh))
            sliding_ds = ds(sliding_tags, metadata=md)
            self.ufl["normal_gap"] = ufl.inner(gap, n) ** 2 * w * sliding_ds
            self.ufl["sliding_area"] = w * sliding_ds
        self.compiled = {name: compat.form(f) for name, f in self.ufl.items()}
        self.bcs = domain.dirichlet_bcs()
        self.A = compat.create_matrix(self.compiled["jacobian"])
        self._K_blocks = compat.create_matrix(self.compiled["jacobian"], "baij") \
            if domain.comm.size == 1 else None   # `jacobian`
        self.A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self.A.setOption(PETSc.Mat.Option.SYMMETRY_ETERNAL, True)
        self.b = compat.create_vector(self.compiled["residual"])
        self._set_near_nullspace()
        self.dfdg = compat.create_matrix(self.compiled["coupling"])
        self.dfdR = None if self.turn is None else \
            compat.create_matrix(self.compiled["turn_coupling"])
        if self.turn is not None:
            self._sliding_area = self._cell_sums("sliding_area")
        self._dfdp = [self.dfdg.createVecLeft() for _ in range(self.n_params)]
        self._dfdp_at = None   # the p of self._dfdp, and where tissue slides its x:
        self._dfdp_x = None if self.turn is None else self.uvec.duplicate()
        self._obj_x = self.uvec.duplicate()   # the point of the last energy evaluation
        self._obj_val = None                  # its energy (None: not valid)
        self.assemble_s = 0.0
        self.set_params(np.zeros(self.n_params))
        self.assemble_couplings()
        # det F at the vertices of each cell (constant on P1 cells, so its centroid)
        pts = np.array([[0.25] * 3] if domain.degree == 1 else
                       [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.25] * 3], dtype=float)
        self._det_F = compat.eval_expression(ufl.det(F), pts, domain.mesh)

    def _lame(self, material):
        """UFL (mu, lmbda), kPa: constants for one material, DG0 fields for `Tissues`."""
        mesh = self.domain.mesh
        if isinstance(material, NeoHookean):
            return [dolfinx.fem.Constant(mesh, PETSc.ScalarType(v))
                    for v in (material.mu, material.lmbda)]
        if self.domain.tissues is None:
            raise InputError(f"anatomy {self.domain.name!r} has no tissue classes: use the "
                             "homogeneous material")
        out = []
        space = compat.scalar_space(mesh)
        for name, values in zip(("mu", "lambda"), material.lame(self.domain.tissues)):
            f = dolfinx.fem.Function(space, name=name)
            self._fill_cells(f, values)
            out.append(f)
        return out

    @staticmethod
    def _fill_cells(f, values):
        """A DG0 field's value per local cell (ghosts included), in cell order."""
        f.x.array[compat.cell_dofs(f.function_space.dofmap.list)[:, 0]] = values

    # --- the material and its parameters θ (`fem.material.theta_names`)

    def set_material(self, material):
        """The material from now on: of the kind the forms were made with (one
        `NeoHookean`, or `fem.material.Tissues`); its values change, nothing compiles."""
        if isinstance(material, NeoHookean) != isinstance(self.material, NeoHookean):
            raise InputError(f"the scene's forms hold a {type(self.material).__name__}; "
                             f"cannot take a {type(material).__name__}")
        mu, lmbda = self._lame_fields
        if isinstance(material, NeoHookean):
            mu.value, lmbda.value = material.mu, material.lmbda
        else:
            for f, values in zip((mu, lmbda), material.lame(self.domain.tissues)):
                self._fill_cells(f, values)
        self.material = material
        self._obj_val = None

    def material_loads(self, x: PETSc.Vec) -> list:
        """df/dθ at the state x: one new PETSc vector per θ (`fem.material.theta_names`),
        mN per unit of θ; Dirichlet rows zero. E_NH is linear in (mu, lmbda), so df/dθ_j is
        E_NH's residual with (mu, lmbda) replaced by d(mu, lmbda)/dθ_j (one form, compiled
        on first use, assembled once per θ). u is left at x. Collective."""
        from fem.material import classes, lame_rates

        if self._material_form is None:
            space = compat.scalar_space(self.domain.mesh)
            rates = [dolfinx.fem.Function(space, name=n) for n in ("dmu", "dlambda")]
            F = ufl.Identity(3) + ufl.grad(self.u)
            form = ufl.derivative(neo_hookean(F, *rates) * self._dx, self.u,
                                  ufl.TestFunction(self.domain.V))
            self._material_form = (compat.form(form), rates)
        form, rates = self._material_form
        ones = np.ones((len(self.domain.mesh.topology.original_cell_index), 1))
        share = ones if isinstance(self.material, NeoHookean) else self.domain.tissues
        self.set_state(x)
        out = []
        for k, m in enumerate(classes(self.material).values()):
            for rate in lame_rates(m):
                for f, r in zip(rates, rate):
                    self._fill_cells(f, share[:, k] * r)
                vec = self.b.duplicate()
                with vec.localForm() as local:   # ghosts too: assembly adds into them
                    local.set(0.0)
                compat.assemble_vector(vec, form)
                vec.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
                compat.set_bc(vec, self.bcs, x, 0.0)
                out.append(vec)
        return out

    def _setup_turns(self, tags):
        """The DG0 rotation field of the sliding facets' cells, and the dof blocks of each
        tag's cells."""
        domain = self.domain
        tdim = domain.mesh.topology.dim
        self.turn = dolfinx.fem.Function(compat.tensor_space(domain.mesh), name="turn")
        f2c = domain.mesh.topology.connectivity(tdim - 1, tdim)
        cell_block = compat.cell_dofs(self.turn.function_space.dofmap.list)[:, 0]
        self._turn_blocks = []
        for tag in tags:
            facets = domain.facet_tags.indices[domain.facet_tags.values == tag]
            cells = np.array([f2c.links(f)[0] for f in facets], dtype=np.int64)
            self._turn_blocks.append(cell_block[cells])
        self._R = np.tile(np.eye(3), (len(tags), 1, 1))

    def _set_near_nullspace(self):
        """Rigid-body modes (3 translations, 3 rotations) of A, for GAMG."""
        X = self.domain.X
        n_owned = self.domain.n_owned
        vecs = [self.b.duplicate() for _ in range(6)]
        x = X[:n_owned]
        fields = [np.tile(e, (n_owned, 1)) for e in np.eye(3)]
        fields += [np.stack([-x[:, 1], x[:, 0], 0 * x[:, 0]], 1),
                   np.stack([0 * x[:, 0], -x[:, 2], x[:, 1]], 1),
                   np.stack([x[:, 2], 0 * x[:, 0], -x[:, 0]], 1)]
        for k, (vec, f) in enumerate(zip(vecs, fields)):   # Gram-Schmidt, twice is enough
            vec.setArray(f.ravel())
            for _ in range(2):
                for w in vecs[:k]:
                    vec.axpy(-w.dot(vec), w)
            vec.normalize()
        ns = PETSc.NullSpace().create(vectors=vecs, comm=self.domain.comm)
        self.A.setNearNullSpace(ns)

    # --- the parameters: goals g(p) and turns R(p)

    @property
    def linear(self) -> bool:
        """f is linear in p: the goals are (blendshapes) and nothing slides. Then df/dp is
        constant, and the load of a step dp is -df/dp dp exactly."""
        return self.goals.linear and self.turn is None

    def set_params(self, p) -> np.ndarray:
        """Validate p (Np,) and set the goal field g(p) (and the sliding facets' turns R(p))."""
        p = np.asarray(p, dtype=float).reshape(-1)
        if p.shape != (self.n_params,):
            raise InputError(f"expected {self.n_params} parameters, got {p.size}")
        if not np.all(np.isfinite(p)):
            raise InputError(f"parameters must be finite, got {p.tolist()}")
        self._set_goals(p)
        self._obj_val = None   # the energy depends on the goal
        return p

    def _set_goals(self, p):
        self.goal.x.array[:] = self.goals.goal(p)
        if self.turn is not None:
            self._set_turns(self.goals.turns(p, self._sliding_tags))

    def _fill_turns(self, array: np.ndarray, mats: np.ndarray):
        """Write one 3×3 per sliding tag, ``mats`` (n_tags, 3, 3), into a DG0 tensor array
        (local, ghosts included) at the cells of that tag's facets; zero elsewhere."""
        vals = array.reshape(-1, 9)
        vals[:] = 0.0
        for blocks, m in zip(self._turn_blocks, mats):
            vals[blocks] = m.ravel()

    @contextlib.contextmanager
    def turns_at(self, p):
        """The sliding facets' normals at p (None, or nothing slides: as they are) for the
        block; then back."""
        if self.turn is None or p is None:
            yield
            return
        R = self._R
        self._set_turns(self.goals.turns(p, self._sliding_tags))
        try:
            yield
        finally:
            self._set_turns(R)

    def _set_turns(self, R):
        """Set the rotations R (n_tags, 3, 3) of the sliding facets' normals."""
        self._R = np.asarray(R, dtype=float)
        self._fill_turns(self.turn.x.array, self._R)
        self.turn.x.scatter_forward()

    @contextlib.contextmanager
    def _elsewhere(self):
        """A block that may change u, the goals and the turns: all three are restored."""
        u, goal = self.uvec.copy(), self.goal.x.array.copy()
        turn = None if self.turn is None else (self.turn.x.array.copy(), self._R.copy())
        try:
            yield
        finally:
            self.goal.x.array[:] = goal
            if turn is not None:
                self.turn.x.array[:], self._R = turn
            self.set_state(u)
            u.destroy()
            self._obj_val = None

    # --- the state

    def set_state(self, x: PETSc.Vec):
        """u = x (ghosts updated)."""
        x.copy(self.uvec)
        self.uvec.ghostUpdate(PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)

    def min_det_F(self) -> float:
        """Smallest det F of the displacement u over all cells (collective): P1 F is constant
        per cell; for P2, det F at the cell's vertices and centroid."""
        det = self._det_F()
        local = det.min() if det.size else np.inf
        return self.domain.comm.allreduce(local, op=MPI.MIN)

    def min_det_F_at(self) -> tuple:
        """(smallest det F (`min_det_F`), the rest centroid (3,) mm of the cell where it is),
        the same on every rank. Collective."""
        comm = self.domain.comm
        det = self._det_F().min(axis=1)
        i = int(np.argmin(det)) if det.size else -1
        value, owner = comm.allreduce((float(det[i]) if det.size else np.inf, comm.rank),
                                      op=MPI.MINLOC)
        point = None
        if comm.rank == owner:
            mesh = self.domain.mesh
            point = mesh.geometry.x[compat.cell_nodes(mesh)[i], :3].mean(axis=0)
        return value, comm.bcast(point, root=owner)

    def finite(self, x) -> bool:
        """x has no NaN or inf on any rank. Collective."""
        return self.domain.comm.allreduce(bool(np.all(np.isfinite(x.array_r))), op=MPI.LAND)

    def sound(self, x) -> bool:
        """The state x is finite and inverts no element; u is left at x. Collective."""
        self.set_state(x)
        return self.finite(x) and self.min_det_F() > 0

    def _cell_sums(self, name: str) -> np.ndarray:
        """A form of one DG0 test function assembled at u: (owned cells' dofs,)."""
        vec = compat.create_vector(self.compiled[name])
        vec.set(0.0)
        compat.assemble_vector(vec, self.compiled[name])
        vec.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        out = vec.array_r.copy()
        vec.destroy()
        return out

    def active_goal_error(self) -> float:
        """max over active vertices of |u - g|, and over the cells on sliding facets of the
        root mean square of (u - g)·n on them, mm (collective)."""
        gap = (self.u.x.array - self.goal.x.array).reshape(-1, 3)[:self.domain.n_owned]
        local = np.linalg.norm(gap[self._active], axis=1).max(initial=0.0)
        if self.turn is not None:   # the root mean square over each cell's sliding facets
            on = self._sliding_area > 0
            rms = np.sqrt(self._cell_sums("normal_gap")[on] / self._sliding_area[on])
            local = max(local, rms.max(initial=0.0))
        return self.domain.comm.allreduce(local, op=MPI.MAX)

    # --- energy, residual, Jacobian at a state

    def energy(self, x: PETSc.Vec) -> float:
        """E_NH + E_A at x, µJ (kPa mm³); +inf where x inverts an element (ln det F is NaN
        at a P1 cell's single quadrature point; P2 is also checked at the vertices). The
        line search asks again for the point it accepted last: that value is remembered.
        u is left at x. Collective."""
        if self._obj_val is not None and self._obj_x.equal(x):
            return self._obj_val
        t = time.perf_counter()
        self.set_state(x)
        val = self.domain.comm.allreduce(
            dolfinx.fem.assemble_scalar(self.compiled["energy"]), op=MPI.SUM)
        if not np.isfinite(val) or (self.domain.degree > 1 and not self.min_det_F() > 0):
            val = np.inf
        x.copy(self._obj_x)
        self._obj_val = val
        self.assemble_s += time.perf_counter() - t
        return val

    def residual(self, x: PETSc.Vec, out: PETSc.Vec) -> None:
        """out = f(x) = dE/dx at x (mN); Dirichlet rows hold x minus its boundary value. u is
        left at x. Collective."""
        t = time.perf_counter()
        self.set_state(x)
        with out.localForm() as bl:
            bl.set(0.0)
        compat.assemble_vector(out, self.compiled["residual"])
        out.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
        compat.set_bc(out, self.bcs, x, -1.0)
        self.assemble_s += time.perf_counter() - t

    def jacobian(self, x: PETSc.Vec, out: PETSc.Mat, turns_at=None) -> None:
        """out = K(x) = df/dx at x (mN/mm), Dirichlet rows and columns identity; with the
        sliding facets' normals at the parameters ``turns_at`` (default: the goals'). u is
        left at x. ``out``: `A` or a duplicate of it. Collective.

        K is assembled into a matrix of 3×3 blocks (BAIJ: dolfinx inserts a vector
        element's entries block by block) and converted into ``out``, the AIJ matrix the
        solvers take (MUMPS's Cholesky takes no BAIJ): class3 with tissues at paper, 1 rank,
        0.25 s to assemble and 0.05 s to convert against 0.62 s straight into AIJ, the same
        values (PyPI's dolfinx 0.11 at coarse: 0.03 s against 0.05). On one rank only: on
        two, PETSc's conversion of MPIBAIJ into the AIJ matrix changes its nonzero pattern
        (a new nonzero on the next assembly; quasi-Newton stalled on the factor of it)."""
        t = time.perf_counter()
        self.set_state(x)
        with self.turns_at(turns_at):
            into = out if self._K_blocks is None else self._K_blocks
            into.zeroEntries()
            compat.assemble_matrix(into, self.compiled["jacobian"], self.bcs, 1.0)
            into.assemble()
            if into is not out:
                into.convert(out.getType(), out)
        self.assemble_s += time.perf_counter() - t

    # --- the couplings: df/dg, df/dR, df/dp and the loads of steps in p

    def assemble_couplings(self, p=None, x: PETSc.Vec | None = None):
        """df/dg (and df/dR where tissue slides) into `dfdg` (`dfdR`): at u and the goals set,
        or at the parameters p and the state x (then both are restored)."""
        with self._elsewhere() if p is not None else contextlib.nullcontext():
            if p is not None:
                self._set_goals(p)
                self.set_state(x)
            for M, name in ((self.dfdg, "coupling"), (self.dfdR, "turn_coupling")):
                if M is not None:
                    M.zeroEntries()
                    compat.assemble_matrix(M, self.compiled[name])
                    M.assemble()

    def dfdp(self, p, x: PETSc.Vec) -> list:
        """df/dp at the state x and parameters p: Np PETSc vectors (df/dg) dg/dp_i + (df/dR)
        dR/dp_i, mN per unit (owned by the part: do not change them). Kept until p changes,
        or x where tissue slides (df/dg and df/dR depend on it); where the goals are linear
        and nothing slides they are constant. Active and Dirichlet vertices are disjoint
        (checked by `Anatomy.validate`), so Dirichlet rows are zero."""
        same = self._dfdp_at is not None and (self.linear or (
            np.array_equal(self._dfdp_at, p) and (self.turn is None or self._dfdp_x.equal(x))))
        if not same:
            dR = None
            if self.turn is not None:
                self.assemble_couplings(p, x)
                dR = self.goals.turns_jacobian(p, self._sliding_tags)
            g = compat.petsc_vec(self.goal).duplicate()
            r = compat.petsc_vec(self.turn).duplicate() if dR is not None else None
            tmp = g.duplicate()
            for i, (y, J) in enumerate(zip(self._dfdp, self.goals.jacobian(p).T)):
                with g.localForm() as gl:
                    gl.array[:] = J
                self.dfdg.mult(g, y)
                if dR is not None:
                    with r.localForm() as rl:
                        self._fill_turns(rl.array, dR[:, i])
                    self.dfdR.mult(r, tmp)
                    y.axpy(1.0, tmp)
            for v in (g, r, tmp):
                if v is not None:
                    v.destroy()
            self._dfdp_at = np.array(p, dtype=float)
            if self.turn is not None:
                x.copy(self._dfdp_x)
        return self._dfdp

    def load(self, dp, p, x: PETSc.Vec) -> PETSc.Vec:
        """df/dp · dp (dp: (Np,)) at the equilibrium x at p, as a new PETSc vector, mN."""
        out = x.duplicate()
        out.set(0.0)
        out.maxpy(np.asarray(dp, dtype=float), self.dfdp(p, x))
        return out

    def goal_load_norm(self) -> float:
        """|df/dg g| with the goals set, mN: the scale of the whole load the goals put on the
        tissue (sliding: df/dg as last assembled)."""
        total = self.b.duplicate()
        self.dfdg.mult(compat.petsc_vec(self.goal), total)
        try:
            return total.norm()
        finally:
            total.destroy()

    def contact_load(self, p, x: PETSc.Vec, turns_at=None) -> PETSc.Vec:
        """The penalties' residual f_c(x; p) as a new vector, mN, with the sliding facets'
        normals at ``turns_at`` (default p); u and the goals are restored."""
        with self._elsewhere():
            self._set_goals(p)
            if self.turn is not None and turns_at is not None:
                self._set_turns(self.goals.turns(turns_at, self._sliding_tags))
            self.set_state(x)
            out = self.b.duplicate()
            out.set(0.0)
            compat.assemble_vector(out, self.compiled["contact"])
            out.ghostUpdate(PETSc.InsertMode.ADD, PETSc.ScatterMode.REVERSE)
            return out

    def goal_load(self, p0, x0: PETSc.Vec, p) -> PETSc.Vec:
        """f_c(x0; p0) - f_c(x0; p) as a new vector, mN: the exact load of moving the goals
        of the equilibrium x0 at p0 to p, with f_c the penalties' residual (for linear goals
        and glued tissue, the tangent load -df/dp dp). The sliding facets' normals stay at
        p0, as in K there: K's stiff penalty directions turn with them, and a load along
        the turned normals, answered by K at p0, slides the tissue along the teeth
        (docs/decisions.md, "Sliding lips")."""
        out = self.contact_load(p0, x0)
        moved = self.contact_load(p, x0, turns_at=p0)
        out.axpy(-1.0, moved)
        moved.destroy()
        return out

    def destroy(self):
        for obj in [self.A, self._K_blocks, self.b, self._obj_x, self._dfdp_x, self.dfdg,
                    self.dfdR, *self._dfdp]:
            if obj is not None:
                obj.destroy()
