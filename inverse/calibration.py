"""The tissue's parameters θ learnt from outcomes (issue 46, docs/uncertainty.md).

A case is a scene, its bone movements and its outcome's skin in the scene's frame (what
``validate.py`` registered: a face scan, or a post-operative CT's skin). The residual of a
case is the signed distance of each predicted skin vertex the outcome covers to the outcome
(`inverse.validation.signed_distance`), less, for a CT's skin, the same vertex's distance at
rest to the pre-operative CT's skin extracted alike (the voxel's bias: on Cranium at paper,
0.19 mm RMS, against the tissue's 0.036), less the case's skin offset δ; its Jacobian,
n·dx/dθ, with n the outcome's normal at the closest point and dx/dθ from the kept
factorisation (`inverse.uncertainty`).

`fit` minimises the maximum a posteriori objective

    ½ Σ_cases |r(θ, g_c)|² / σ² + ½ (θ - θ₀)ᵀ Σ₀⁻¹ (θ - θ₀) + ½ Σ_cases g_cᵀ G⁻¹ g_c

by Gauss-Newton with Levenberg-Marquardt damping, σ the outcome's noise, (θ₀, Σ₀) the prior,
g_c case c's nuisance: a small rigid correction of its registration (rotation vector,
translation; prior `REGISTRATION_SD`) and its skin offset δ (`OFFSET_SD`). The
registration leaves the outcome about 0.05° off: on class3, its 0.0037 mm residual on the
forehead left 0.036 mm RMS on the face, more than the tissue's whole effect there
(0.05 mm), and the fit took it for tissue. Fitted with θ, the stable skin holds g to the
registration, and the rest is the tissue's. Residuals that the tissue cannot explain (a
swelling, a dressing, a resampled CT's nostrils) are left out as outliers
(`OUTLIER_SDS`), and the fit repeated.
The prior holds what the data cannot see: an eigen-direction of the data's information
JᵀJ/σ² weaker than the prior's precision along it is reported as unseen, and stays about
where the prior puts it. A common scale of every class's E is one such direction always: the
bone moves the tissue by a displacement, and a displacement's equilibrium does not depend on
the moduli's scale. The posterior covariance is (JᵀJ/σ² + Σ₀⁻¹)⁻¹ at the fit.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from inverse.uncertainty import Prior, set_theta
from meshes.errors import InputError, SolverError

#: The fit stops when a step changes no parameter by more than this (ln units: 0.1 %), or
#: lowers the objective (½ χ² and the prior's: the log posterior) by less than
#: `OBJECTIVE_TOL`: on a simulated post-operative Cranium, the weakly seen ν wandered for
#: steps that lowered it by 0.3 in 990; with 0.1 and 0.01 the ratios were the same to four
#: digits, in 9 and 10 iterations against 12.
STEP_TOL, OBJECTIVE_TOL = 1e-3, 1e-1
#: A direction is seen where the data's precision along it is at least this times the
#: prior's (docs/uncertainty.md).
SEEN_RATIO = 1.0
#: Largest change of θ in one step (ln units: a factor 1.65), a trust region: a wild step
#: asks the solver for a tissue it may take minutes to reach.
MAX_STEP = 0.5
#: Skin vertices farther than this from the outcome (mm) are not compared: the tissue moves
#: the skin by less than 1 mm (docs/uncertainty.md), so a gap of centimetres is another
#: surface. Fewer than `MIN_COVERED` of the skin's vertices within it: no overlap.
MAX_GAP_MM, MIN_COVERED = 10.0, 0.1
#: Residuals farther than this many SDs from their median at a fit are outliers, left out
#: of the next fit (the SD: the noise given, or 1.4826 × the case's median absolute
#: deviation where larger); at most `ROBUST_ROUNDS` fits. On a simulated post-operative
#: Cranium (paper), 1 % of the skin's vertices, at the nostrils, lips and eyelids, lay
#: 0.3-1.9 mm off at the true tissue against 0.04 mm RMS for the rest; a swelling 1.5 mm
#: high beside the lower lip moved fat's ratio 7.5 % by least squares, 0.4 % so
#: (tests/test_calibrate.py).
OUTLIER_SDS, ROBUST_ROUNDS = 3.0, 4
#: Prior SD of a case's registration correction g: rotation (rad, 0.5°) and translation
#: (mm), the registration's own error several times over (`inverse.validation`).
REGISTRATION_SD = np.array([np.radians(0.5)] * 3 + [0.5] * 3)
#: Prior SD (mm) of a case's skin offset δ: the outcome's skin lying uniformly deeper or
#: higher along its normals than the model's (a CT's reconstruction, threshold or
#: resampling; a camera's calibration). On a simulated post-operative Cranium (paper, one
#: resampling), the skin lay 0.019 mm deeper at the true tissue, and fat's ratio came 10 %
#: low; with δ (fitted 0.015 mm), 5 % low.
OFFSET_SD = 0.5
#: A case's nuisance parameters g: its registration correction, then its skin offset.
NUISANCE_SD = np.append(REGISTRATION_SD, OFFSET_SD)
NG = len(NUISANCE_SD)


@dataclasses.dataclass
class Case:
    """One outcome: ``scene`` (`inverse.scene.Scene`) and ``p`` its movements; the outcome's
    skin ``points`` (M, 3), ``tris`` (T, 3) in the scene's frame; ``name``; ``rest``: where
    the outcome is a CT's skin, the pre-operative CT's extracted alike ((points, tris), or
    None): each vertex's signed distance to it at rest is the extraction's bias, taken off
    the residual; ``skin`` (`inverse.validation.Skin` of the scene) and ``covered`` (N,) the
    skin vertices compared, fixed at the start, less the ``outliers`` (N,) that `Case.trim`
    found; ``last``: the covered vertices' residual (mm) at the last solve."""

    scene: object
    p: np.ndarray
    points: np.ndarray
    tris: np.ndarray
    name: str
    rest: tuple | None = None
    skin: object = None
    covered: np.ndarray | None = None
    bias: np.ndarray | None = None
    g: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(NG))
    outliers: np.ndarray | None = None
    last: np.ndarray | None = None

    def __post_init__(self):
        from inverse.validation import Skin

        self.skin = self.skin or Skin.of(self.scene)

    @property
    def outcome(self) -> np.ndarray:
        """The outcome's points (M, 3) moved by the registration correction ``g``."""
        from scipy.spatial.transform import Rotation

        return self.points @ Rotation.from_rotvec(self.g[:3]).as_matrix().T + self.g[3:6]

    def residual(self, jacobian: bool) -> tuple:
        """(r (K,) mm, J (K, nθ + `NG`) or None: d r / d(θ, g)) at the scene's equilibrium at
        ``p`` and its material, over the covered vertices (chosen at the first call).
        Collective."""
        from inverse.uncertainty import material_rows
        from inverse.validation import signed_distance
        from meshes.surface import boundary_edges, vertex_normals

        after, points = self.skin.at(self.scene), self.outcome
        d, seen, q, n = signed_distance(after, vertex_normals(after, self.skin.tris), points,
                                        self.tris)
        if self.covered is None:
            self.covered = seen & (np.abs(d) < MAX_GAP_MM)
            self.covered[np.unique(boundary_edges(self.skin.tris))] = False
            self.bias = np.zeros(len(d))
            if self.rest is not None:   # the extraction's own offset from the mesh's skin
                x = self.skin.rest
                self.bias, in_rest, *_ = signed_distance(x, vertex_normals(x, self.skin.tris),
                                                         *self.rest)
                self.covered &= in_rest & (np.abs(self.bias) < MAX_GAP_MM)
            if self.covered.mean() < MIN_COVERED:
                raise InputError(f"case {self.name}: the outcome lies within {MAX_GAP_MM:g} mm "
                                 f"of {self.covered.mean():.0%} of the scene's skin (at least "
                                 f"{MIN_COVERED:.0%} needed): it does not overlap the scene")
            self.outliers = np.zeros(len(d), dtype=bool)
        d = d - self.bias - self.g[6]
        self.last = np.where(self.covered, d, np.nan)
        used = self.covered & ~self.outliers
        if not jacobian:
            return d[used], None
        (rows,) = material_rows(self.scene, [self.skin.op], rtol=None)   # (N, 3, nθ)
        # d = (x - q)·n - δ, the outcome turned by ω and moved by t: dq = ω × q + t
        q, n = q[used], n[used]
        return d[used], np.hstack([np.einsum("ki,kit->kt", n, rows[used]), -np.cross(q, n),
                                   -n, -np.ones((len(n), 1))])

    def trim(self, noise_mm: float) -> bool:
        """Mark as outliers the covered vertices whose residual at the last solve lies more
        than `OUTLIER_SDS` SDs from the median, the SD the noise (mm) or the residual's
        robust one, the larger; whether the set changed."""
        r = self.last[self.covered]
        mid = np.median(r)
        sd = max(noise_mm, 1.4826 * np.median(np.abs(r - mid)))
        out = np.zeros_like(self.outliers)
        out[self.covered] = np.abs(r - mid) > OUTLIER_SDS * sd
        changed = bool((out != self.outliers).any())
        self.outliers = out
        return changed

    def solve(self, theta) -> None:
        """The equilibrium at ``p`` with the material θ. Collective."""
        set_theta(self.scene, theta)
        self.scene.solve(self.p)


@dataclasses.dataclass
class Fit:
    """What `fit` found: ``theta`` (nθ,), ``posterior`` covariance (nθ, nθ), ``unseen``
    (directions the data does not see: each ``{"direction": {name: weight}, "information":
    data precision / prior precision}``), ``rms_before``/``rms_after`` per case (mm),
    ``iterations``, ``converged``, ``history`` (objective per iteration), ``registration``
    per case: its g (the registration's correction: rotation vector rad, translation mm;
    the skin offset δ mm), ``outliers`` per case: the share of its compared vertices left
    out (`OUTLIER_SDS`); ``rms_after`` is the rest's."""

    theta: np.ndarray
    posterior: np.ndarray
    unseen: list
    rms_before: dict
    rms_after: dict
    iterations: int
    converged: bool
    history: list
    registration: dict
    outliers: dict


@dataclasses.dataclass
class Cases:
    """The cases of one fit, over groups of ranks: ``local`` [(index, `Case`)], the cases
    this rank's group holds (their scenes on the group's communicator), ``names`` of all
    the fit's cases in order, and ``comm`` every rank of the fit. All ranks sharing every
    scene: `Cases.shared`."""

    local: list
    names: list
    comm: object

    @classmethod
    def shared(cls, cases: list, comm) -> "Cases":
        return cls(list(enumerate(cases)), [c.name for c in cases], comm)

    @property
    def lead(self) -> bool:
        """This rank speaks for its group's cases (rank 0 of their scenes)."""
        return all(c.scene.domain.comm.rank == 0 for _, c in self.local)

    def stack(self, z, n_theta: int, jacobian: bool):
        """Residuals per case (in order) and the joint Jacobian (K, nθ + NG n_cases) at z =
        (θ, g_1, ...), each group solving its cases, then shared with every rank. An error
        in one group is raised on every rank. Collective over ``comm``."""
        mine, error = [], None
        for i, c in self.local:
            c.g = z[n_theta + NG * i:n_theta + NG * (i + 1)]
            try:
                c.solve(z[:n_theta])
                mine.append((i, *c.residual(jacobian)))
            except (SolverError, InputError) as e:   # the same on the group's ranks
                error = (type(e), str(e))
                break
        parts = self.comm.allgather((mine if self.lead else [], error))
        for _, err in parts:
            if err is not None:
                raise err[0](err[1])
        got = {i: (r, j) for part, _ in parts for i, r, j in part}
        rs = [got[i][0] for i in range(len(self.names))]
        if not jacobian:
            return rs, None
        js = []
        for i in range(len(self.names)):
            r, j = got[i]
            block = np.zeros((len(r), len(z)))
            block[:, :n_theta] = j[:, :n_theta]
            block[:, n_theta + NG * i:n_theta + NG * (i + 1)] = j[:, n_theta:]
            js.append(block)
        return rs, np.vstack(js)

    def trim(self, noise_mm: float) -> bool:
        """`Case.trim` of every case at the last solve; whether any set changed. Collective
        over ``comm``."""
        return any(self.comm.allgather(any([c.trim(noise_mm) for _, c in self.local])))

    def outliers(self) -> dict:
        """{case name: its share of the covered vertices that are outliers}. Collective."""
        mine = {c.name: float(c.outliers[c.covered].mean()) for _, c in self.local}
        return {k: v for part in self.comm.allgather(mine if self.lead else {})
                for k, v in part.items()}


def _descend(cases: Cases, z, rs, J, objective, P0_mean, P0, noise_mm: float,
             max_iterations: int, bounds) -> tuple:
    """Gauss-Newton with Levenberg-Marquardt damping from z (residuals ``rs`` and Jacobian
    ``J`` there) on ``objective``: (z, rs, J, iterations, converged, objective per
    iteration). Collective."""
    nt, (lo, hi) = len(z) - NG * len(cases.names), bounds
    mu, value = 1e-3, objective(rs, z)
    history, converged, it = [value], False, 0
    for it in range(1, max_iterations + 1):
        r = np.concatenate(rs)
        H = J.T @ J / noise_mm ** 2 + P0
        g = J.T @ r / noise_mm ** 2 + P0 @ z - P0_mean
        while True:   # Levenberg-Marquardt: damp until the objective falls
            step = -np.linalg.solve(H + mu * np.diag(np.diag(H)), g)
            trial = z + step * min(1.0, MAX_STEP / max(np.abs(step[:nt]).max(), 1e-300))
            if lo is not None:
                trial = np.clip(trial, lo, hi)
            try:
                trial_value = objective(cases.stack(trial, nt, False)[0], trial)
            except (SolverError, InputError):
                trial_value = np.inf
            if trial_value < value or mu > 1e8:
                break
            mu *= 10
        if not trial_value < value:
            converged = True   # no step lowers it: a minimum, to the solver's accuracy
            cases.stack(z, nt, False)   # the scenes back from the last trial
            break
        mu = max(mu / 10, 1e-9)
        step, z, fall, value = trial - z, trial, value - trial_value, trial_value
        history.append(value)
        rs, J = cases.stack(z, nt, True)
        if np.abs(step[:nt]).max() < STEP_TOL or fall < OBJECTIVE_TOL:
            converged = True
            break
    return z, rs, J, it, converged, history


def _rms(names, rs) -> dict:
    """{case name: RMS (mm) of its residuals}."""
    return dict(zip(names, (float(np.sqrt(np.mean(r ** 2))) for r in rs)))


def fit(cases: Cases, prior: Prior, noise_mm: float, max_iterations: int = 20,
        bounds=None) -> Fit:
    """θ of the cases together (one shared tissue) from the prior's median, with each case's
    registration correction (module docstring), each step projected into ``bounds``
    ((lo, hi), θ's units) where given; fitted again without the outliers (`OUTLIER_SDS`)
    until they stay the same. Collective over ``cases.comm``; leaves every scene at the
    fitted material."""
    from scipy.linalg import block_diag

    if not (np.isfinite(noise_mm) and noise_mm > 0):
        raise InputError(f"the outcome's noise must be a positive number of mm, got {noise_mm}")
    nt = len(prior.mean)
    n = len(cases.names)
    mean = np.concatenate([prior.mean, np.zeros(NG * n)])
    P0 = block_diag(np.linalg.inv(prior.covariance), np.diag(np.tile(NUISANCE_SD, n) ** -2.0))
    lo, hi = (None, None) if bounds is None else (
        np.concatenate([b, np.full(NG * n, s)]) for b, s in zip(bounds, (-np.inf, np.inf)))
    z = mean.copy()
    rs, J = cases.stack(z, nt, True)
    before = _rms(cases.names, rs)

    def objective(res, t):
        r = np.concatenate(res)
        return 0.5 * (r @ r) / noise_mm ** 2 + 0.5 * (t - mean) @ P0 @ (t - mean)

    history, it = [], 0
    for _ in range(ROBUST_ROUNDS):
        z, rs, J, steps, converged, values = _descend(cases, z, rs, J, objective, P0 @ mean,
                                                      P0, noise_mm, max_iterations, (lo, hi))
        it, history = it + steps, history + values
        if not cases.trim(noise_mm):
            break
        rs, J = cases.stack(z, nt, True)
    info = J.T @ J / noise_mm ** 2   # rs and J are z's: stacked where z was taken
    posterior = np.linalg.inv(info + P0)[:nt, :nt]
    # what the data see of θ, the registrations being free: the Schur complement
    a, b, c = info[:nt, :nt], info[:nt, nt:], info[nt:, nt:] + P0[nt:, nt:]
    lam, vec = np.linalg.eigh(a - b @ np.linalg.solve(c, b.T))
    unseen = []
    for k in range(len(lam)):
        v = vec[:, k]
        ratio = float(lam[k] / (v @ P0[:nt, :nt] @ v))
        if ratio < SEEN_RATIO:
            unseen.append({"direction": {n: round(float(w), 3) for n, w in
                                         zip(prior.names, v) if abs(w) > 0.2},
                           "information": ratio})
    after = _rms(cases.names, rs)
    return Fit(z[:nt], posterior, unseen, before, after, it, converged, history,
               {k: z[nt + NG * i:nt + NG * (i + 1)].tolist() for i, k in enumerate(cases.names)},
               cases.outliers())
