"""How sure a prediction is: the tissue's parameters θ (`fem.material.theta_names`: each
class's ln E and ln(1 - 2ν)) with a prior, their sensitivities dx/dθ at an equilibrium, and the
prediction bands, the linearised covariance ``S_θ Σ_θ S_θᵀ`` of each landmark and vertex
(docs/uncertainty.md).

* `Prior`: normal on θ (E and 1 - 2ν log-normal, multiplicative bands); medians from the
  scene's material, spreads `SD_LOG_E` and `SD_LOG_1M2NU` or a material file's,
  independent unless the file gives their correlation (a calibration's posterior).
* `theta_rows`: dx/dθ (N, 3, nθ) at the landmarks (and, asked for, every vertex), for nθ
  back-substitutions with the kept factorisation (`fem.equilibrium.Equilibrium.
  material_sensitivity`).
* `bands`: per point, the covariance (3×3, mm²), its SD along the head frame's axes, its
  1-σ ellipsoid's semi-axes, and the radius holding 95 % of the probability.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path

import numpy as np

from fem.material import (
    CORRELATION_KEY,
    classes,
    material_from_spec,
    theta,
    theta_names,
    with_theta,
)
from meshes.errors import InputError, SolverError

#: Prior SD of ln E per class (a 1-σ factor of e^SD). Each covers its measurements' spread
#: and the gap between methods and sites (docs/uncertainty.md has the sources):
#: skin 36 kPa by suction, 31-42 kPa over 16 subjects and four sites (Luboz 2014), 2σ
#: spans 22-59 kPa; fat 3.25 ± 0.91 kPa (breast, Samani 2007) and 2.7-4.4 kPa for the whole
#: tissue over the jaw (Wei 2021): 2σ spans 1.6-6.5 kPa; muscle 10.7 ± 1.8 kPa (masseter,
#: Olchowy 2021) and its tone: 2σ spans 6.5-17.6 kPa; one homogeneous tissue, the paper's
#: 5 kPa, as wide as fat, the range the published facial models span (a factor 2-3).
SD_LOG_E = {"skin": 0.25, "fat": 0.35, "muscle": 0.25, "tissue": 0.35}
#: Prior SD of ln(1 - 2ν): the published facial models take ν from 0.45 to 0.49, ln(1 - 2ν)
#: from -3.9 to -2.3; about the paper's 0.47 (-2.8), 2σ spans ν 0.433-0.487.
SD_LOG_1M2NU = 0.4
#: ν is sampled inside this range (redrawn outside: 3.5σ below the median).
NU_RANGE = (0.40, 0.499)


#: The bands' relative residual, where block CG on a factor of K elsewhere solves dx/dθ
#: (`fem.tangent.TangentSolves.responses`). At paper after a 5 mm advance from rest, the
#: landmark rows' worst error over the largest row against CG to 1e-12 (the bands' SDs'):
#: class3 with tissues 1.3 % at 1e-2 (0.9 %), 0.52 % at 3e-3 (0.26 %), 0.14 % at 1e-3
#: (0.10 %); class3 homogeneous 5.1 % (5.7 %), 0.22 % (0.27 %), 0.36 % (0.42 %); Cranium
#: sliding on tissues 0.27 % (0.46 %), 0.16 % (0.17 %), 0.04 % (0.04 %). 3e-3 takes 11
#: iterations where 1e-3 takes 14 (class3 with tissues); a band needs no more than 1 %.
BAND_RTOL = 3e-3
#: What BAND_RTOL gives: each row (and band) within this fraction of the largest.
BAND_ACCURACY = 0.01


@dataclasses.dataclass(frozen=True)
class Prior:
    """Normal prior on θ (`fem.material.theta_names` order).

    Attributes: names (nθ,); mean (nθ,): ln E/kPa and ln(1 - 2ν) per class; sd (nθ,);
    correlation (nθ, nθ), None for independent parameters.
    """

    names: tuple
    mean: np.ndarray
    sd: np.ndarray
    correlation: np.ndarray | None = None

    @classmethod
    def of(cls, material, spreads: dict | None = None) -> "Prior":
        """The prior centred on ``material`` (a `NeoHookean`, `fem.material.Tissues` or
        spec), spreads ``{class: {"sd_log_E": .., "sd_log_1m2nu": ..}}`` over the
        defaults."""
        material = material_from_spec(material)
        spreads = spreads or {}
        sd = []
        for c in classes(material):
            given = spreads.get(c, {})
            sd += [given.get("sd_log_E", SD_LOG_E[c]), given.get("sd_log_1m2nu", SD_LOG_1M2NU)]
        sd = np.asarray(sd, dtype=float)
        names = theta_names(material)
        bad = [n for n, s in zip(names, sd) if not (np.isfinite(s) and s > 0)]
        if bad:
            raise InputError(f"prior: the spread of {', '.join(bad)} must be positive and "
                             "finite")
        return cls(tuple(names), theta(material), sd)

    @classmethod
    def from_file(cls, path) -> "Prior":
        """From a material file (`fem.material.read_material_file`): its E and ν are the
        medians, its optional ``sd_log_E`` and ``sd_log_1m2nu`` per class the spreads, its
        optional `fem.material.CORRELATION_KEY` their correlation."""
        material = material_from_spec(str(path))
        spec = json.loads(Path(path).read_text())
        given = spec.pop(CORRELATION_KEY, None)
        prior = cls.of(material, {c: {k: v for k, v in s.items() if k.startswith("sd_")}
                                  for c, s in spec.items()})
        if given is None:
            return prior
        try:
            names, C = list(given["names"]), np.array(given["matrix"], dtype=float)
            ok = names == list(prior.names) and C.shape == (len(names),) * 2 and \
                np.allclose(C, C.T) and np.allclose(np.diag(C), 1.0)
            ok = ok and np.linalg.eigvalsh(C).min() > 0
        except (KeyError, TypeError, ValueError, np.linalg.LinAlgError):
            ok = False
        if not ok:
            raise InputError(f"material file {path}: {CORRELATION_KEY} must be {{\"names\": "
                             f"{list(prior.names)}, \"matrix\": a symmetric positive definite "
                             "matrix with a unit diagonal}")
        return dataclasses.replace(prior, correlation=C)

    @property
    def covariance(self) -> np.ndarray:
        """Σ_θ (nθ, nθ)."""
        C = np.eye(len(self.sd)) if self.correlation is None else self.correlation
        return self.sd[:, None] * C * self.sd[None, :]

    @property
    def factor(self) -> np.ndarray:
        """L (nθ, nθ), lower triangular, Σ_θ = L Lᵀ: θ = mean + L z for z standard normal."""
        if self.correlation is None:
            return np.diag(self.sd)
        return np.linalg.cholesky(self.covariance)

    def report(self) -> dict:
        """Per parameter: its median (E in kPa, or ν) and its 1-σ spread."""
        out = {}
        for n, m, s in zip(self.names, self.mean, self.sd):
            c, field = n.rsplit(".", 1)
            if field == "log_E":
                out[f"{c}.E_kPa"] = {"median": float(np.exp(m)), "sd_log": float(s)}
            else:
                out[f"{c}.nu"] = {"median": float((1 - np.exp(m)) / 2), "sd_log_1m2nu": float(s)}
        return out


def set_theta(scene, values) -> None:
    """Give ``scene`` the material with θ = ``values``; its next solve finds the
    equilibrium (`fem.equilibrium.Equilibrium.set_material`)."""
    scene.eq.set_material(with_theta(scene.eq.material, values))


def scene_prior(scene, path=None) -> Prior:
    """The prior of ``scene``'s material: ``path`` (a material file with spreads), else
    the scene's material file where it has one, else its material with `SD_LOG_E`."""
    if path is not None:
        return Prior.from_file(path)
    if isinstance(scene.material, str) and scene.material.endswith(".json"):
        return Prior.from_file(scene.material)
    return Prior.of(scene.eq.material)


@contextlib.contextmanager
def _columns(scene, rtol):
    """dx/dθ's nθ PETSc vectors at the current equilibrium, for the block. Collective."""
    cols = scene.eq.material_sensitivity(rtol)
    try:
        yield cols
    finally:
        for c in cols:
            c.destroy()


def material_rows(scene, ops: list, rtol: float | None = BAND_RTOL) -> list:
    """dx/dθ at the current equilibrium at the points of each `fem.domain.PointOperator` of
    ``ops``: one (N_i, 3, nθ) array each, mm per unit of θ, the same on every rank. nθ
    back-substitutions, or block CG on the kept factor to ``rtol`` (`BAND_RTOL`; None: the
    tangent's own, for calibration's gradients). Collective."""
    with _columns(scene, rtol) as cols:
        return [_rows(op, cols) for op in ops]


def _rows(op, cols) -> np.ndarray:
    """(N, 3, nθ): the columns at the points of ``op``. Collective."""
    return np.stack([op.apply(c.array, offset=False) for c in cols], axis=-1)


def theta_rows(scene, names=None, vertices: bool = False, rtol: float | None = BAND_RTOL):
    """dx/dθ at the current equilibrium (`material_rows`): (landmarks (Nl, 3, nθ) in
    ``names`` order (default all), and with ``vertices`` every vertex's (n_vertices, 3, nθ)
    on rank 0 (None elsewhere) or None). Collective."""
    names = list(scene.domain.landmarks) if names is None else list(names)
    op = scene.domain.point_operator(names)
    with _columns(scene, rtol) as cols:
        rows = _rows(op, cols)
        every = None
        if vertices:
            parts = [scene.domain.vertex_array(c.array) for c in cols]
            every = np.stack(parts, axis=-1) if scene.domain.comm.rank == 0 else None
        return rows, every


def covariances(rows: np.ndarray, prior: Prior) -> np.ndarray:
    """``S_θ Σ_θ S_θᵀ`` (N, 3, 3) mm² of points with rows (N, 3, nθ)."""
    scaled = rows @ prior.factor
    return np.einsum("nit,njt->nij", scaled, scaled)


def radius95(cov: np.ndarray) -> np.ndarray:
    """(N,) mm: the radius of the ball about the prediction that holds 95 % of a Gaussian
    with covariances ``cov`` (N, 3, 3). |δ|² is a χ² weighted by cov's eigenvalues λ,
    taken as c χ²_ν with its first two moments (c = Σλ²/Σλ, ν = (Σλ)²/Σλ²,
    Welch-Satterthwaite): exact for one, two or three equal λ, within 0.5 % of 10⁶ samples
    for 49 others (flat, elongated and random). scipy.special's quantile, not
    scipy.stats' (its import took 0.29 s of class3's 3.4 s of bands at paper)."""
    from scipy.special import chdtri

    lam = np.clip(np.linalg.eigvalsh(cov), 0.0, None)
    s1, s2 = lam.sum(axis=1), (lam ** 2).sum(axis=1)
    some = s2 > 0
    out = np.zeros(len(lam))
    c, nu = s2[some] / s1[some], s1[some] ** 2 / s2[some]
    out[some] = np.sqrt(c * chdtri(nu, 0.05))
    return out


def bands(rows: np.ndarray, prior: Prior, frame, names) -> dict:
    """Each point's band ``{name: {...}}``: ``sd_mm`` along the head frame's (left,
    anterior, superior) axes, ``ellipsoid_mm`` its 1-σ semi-axes (largest first) and
    ``ellipsoid_axes`` their directions in the head frame, ``r95_mm``, and
    ``by_parameter_mm``: the 1-σ motion each parameter alone gives (|S_θ,j| sd_j)."""
    cov = covariances(rows, prior)
    R = frame.rotation
    head = np.einsum("ai,nab,bj->nij", R, cov, R)
    r95 = radius95(cov)
    out = {}
    for k, n in enumerate(names):
        lam, vec = np.linalg.eigh(head[k])
        order = np.argsort(lam)[::-1]
        out[n] = {"sd_mm": np.sqrt(np.clip(np.diag(head[k]), 0, None)).tolist(),
                  "ellipsoid_mm": np.sqrt(np.clip(lam[order], 0, None)).tolist(),
                  "ellipsoid_axes": vec[:, order].T.tolist(),
                  "r95_mm": float(r95[k]),
                  "by_parameter_mm": {t: float(np.linalg.norm(rows[k, :, j]) * prior.sd[j])
                                      for j, t in enumerate(prior.names)}}
    return out


def band_report(scene, prior: Prior | None, names, vertices: bool):
    """(the report's ``bands``: the prior (`Prior.report`) and each landmark of ``names``'s
    band (`bands`), or None where ``prior`` is None; the point fields ``{"band_r95_mm":
    (n_vertices,)}`` on rank 0 where ``vertices``, else {}) at the current equilibrium.
    Collective."""
    if prior is None:
        return None, {}
    rows, every = theta_rows(scene, names, vertices)
    report = {"prior": prior.report(), "landmarks": bands(rows, prior, scene.head_frame,
                                                           names)}
    if not vertices:
        return report, {}
    return report, {"band_r95_mm": radius95(covariances(every, prior))
                    if scene.domain.comm.rank == 0 else None}


def sample_theta(prior: Prior, n: int, seed: int = 0) -> np.ndarray:
    """(n, nθ) samples of the prior, ν kept in `NU_RANGE` (redrawn outside)."""
    rng = np.random.default_rng(seed)
    nu = np.array([n_.endswith(".log_1m2nu") for n_ in prior.names])
    lo, hi = np.log(1 - 2 * np.array(NU_RANGE[::-1]))

    def bad(x):
        return ((x[:, nu] < lo) | (x[:, nu] > hi)).any(axis=1)

    L = prior.factor
    out = prior.mean + rng.standard_normal((n, len(prior.mean))) @ L.T
    while bad(out).any():
        redo = bad(out)
        out[redo] = prior.mean + rng.standard_normal((redo.sum(), len(prior.mean))) @ L.T
    return out



def monte_carlo(scene, p, prior: Prior, n: int, seed: int = 0, names=None) -> dict:
    """The bands checked against sampling: full nonlinear solves at ``n`` samples of the
    prior (`sample_theta`) at the treatment ``p``, against the linear bands there. Per
    landmark: ``linear_sd_mm`` and ``sampled_sd_mm`` (the RMS distance from the mean,
    sqrt(trace cov)), their ratio, and the samples' mean shift from the nominal prediction
    (``bias_mm``). The scene is left at its material and ``p``. Collective."""
    names = list(scene.domain.landmarks) if names is None else list(names)
    theta0 = prior.mean.copy()
    set_theta(scene, theta0)
    scene.solve(p)
    nominal = np.array([scene.landmarks(names)[k] for k in names])
    rows, _ = theta_rows(scene, names)
    linear = np.sqrt(np.einsum("nii->n", covariances(rows, prior)))
    points, failed = [], 0
    try:
        for t in sample_theta(prior, n, seed):
            set_theta(scene, t)
            try:
                scene.solve(p)
            except SolverError:   # a sample the solver cannot reach is counted
                failed += 1
                continue
            at = scene.landmarks(names)
            points.append([at[k] for k in names])
    finally:
        set_theta(scene, theta0)
        scene.solve(p)
    pts = np.array(points)                                   # (n, Nl, 3)
    sampled = np.sqrt(((pts - pts.mean(axis=0)) ** 2).sum(axis=2).mean(axis=0))
    return {"n_samples": len(pts), "failed": failed, "landmarks": {
        k: {"linear_sd_mm": float(linear[i]), "sampled_sd_mm": float(sampled[i]),
            "ratio": float(linear[i] / sampled[i]) if sampled[i] > 0 else None,
            "bias_mm": float(np.linalg.norm(pts[:, i].mean(axis=0) - nominal[i]))}
        for i, k in enumerate(names)}}
