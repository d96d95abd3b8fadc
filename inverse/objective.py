"""Landmark objective ``T(p) = ½ Σ_l Σ_k w_lk (a_kᵀ(x_l(p) - x̂_l))² + ½ α |p|²`` and its
derivatives.

``x_l = L(X + u(p))`` are skin points (a sparse `PointOperator` L), ``u(p)`` the equilibrium;
``a_k`` the head's axes (left, anterior, superior), ``w_lk = w_l`` along the axes where the
target holds the landmark and 0 along the free ones; with every axis held, the term is
``w_l |x_l - x̂_l|²``.
With ``K = ∂f/∂u`` and ``G = ∂f/∂p`` at the equilibrium (``f(u(p), p) = 0``):

* gradient by ONE adjoint solve: ``K λ = Lᵀ W r``, ``dT/dp = -Gᵀ λ + α p``;
* landmark sensitivity ``S_T = L dx/dp = -L K⁻¹ G`` (3 Nt, Np) with ``min(Np, 3 Nt)`` solves:
  Np "direct" solves ``K s_i = -G_i`` or 3 Nt "adjoint" solves ``K λ_j = Lᵀ e_j``.

Every solve reuses the factorisation the forward solve built (`Equilibrium.solve_tangent`);
``value_and_gradient`` solves tangent-ready (`Equilibrium.solve`, ``tangent=True``).
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path

import numpy as np

from fem.domain import PointOperator
from fem.equilibrium import Equilibrium
from fem.limits import check
from meshes.errors import InputError

log = logging.getLogger(__name__)

#: A target farther than this from the landmark's rest position gets a warning, mm.
FAR_TARGET_MM = 30.0
#: Farther than this (mm) it is refused: no surgery moves the face that far; most likely
#: the coordinates are in other units (m, cm) or another frame.
ABSURD_TARGET_MM = 100.0


#: The head frame's axes (`meshes.frame`), as targets and plan reports name them.
HEAD_AXES = ("left", "anterior", "superior")


def target_entry(point, along=HEAD_AXES):
    """A target as a file writes it: ``[x, y, z]`` mm where it holds along every head axis,
    else ``{"at": [x, y, z], "along": [axis, ...]}`` (names of `HEAD_AXES`)."""
    point = np.asarray(point, dtype=float).tolist()
    along = [a for a in HEAD_AXES if a in along]
    return point if len(along) == len(HEAD_AXES) else {"at": point, "along": along}


def _parse_target(name: str, entry) -> tuple[np.ndarray, np.ndarray]:
    """(point (3,) mm, held (3,) bool along `HEAD_AXES`) of one target entry."""
    along = HEAD_AXES
    if isinstance(entry, dict):
        extra = sorted(set(entry) - {"at", "along"})
        if extra or "at" not in entry:
            raise InputError(f"target {name} must be [x, y, z] or {{\"at\": [x, y, z], "
                             f"\"along\": [axis, ...]}}, got keys {sorted(entry)}")
        along = entry.get("along", HEAD_AXES)
        if (not isinstance(along, list) or not along or len(set(map(str, along))) != len(along)
                or any(a not in HEAD_AXES for a in along)):
            raise InputError(f"target {name}: 'along' must list distinct head axes of "
                             f"{list(HEAD_AXES)}, got {along!r}")
        entry = entry["at"]
    try:
        x = np.asarray(entry, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"target {name} = {entry!r} is not a 3-vector in mm") from None
    if x.shape != (3,):
        raise InputError(f"target {name} = {entry!r} is not a 3-vector in mm")
    if not np.all(np.isfinite(x)):
        raise InputError(f"target {name} = {x.tolist()} is not finite")
    return x, np.isin(HEAD_AXES, along)


def load_targets(source, rest: dict, names=None, far_mm: float = FAR_TARGET_MM):
    """Validated landmark targets.

    Args:
        source: a JSON file path or a dict ``{name: entry}``; an entry is ``[x, y, z]`` (mm,
            the scene's frame), or ``{"at": [x, y, z], "along": ["anterior", ...]}``: the
            landmark is held to the point along the named head axes only (`HEAD_AXES`), as
            a true-vertical-line analysis measures the profile along the anterior axis.
        rest: ``{name: (3,)}`` rest positions of all known landmarks (mm).
        names: optional subset of the targets to use, in order.
    Returns:
        (names list, points (Nt, 3) mm, held (Nt, 3) bool along `HEAD_AXES`).
    """
    if isinstance(source, (str, Path)):
        try:
            source = json.loads(Path(source).read_text())
        except (OSError, ValueError) as e:
            raise InputError(f"cannot read targets file {source}: {e}") from None
    if not isinstance(source, dict):
        raise InputError("targets must be a JSON object {landmark: [x, y, z]}")
    names = list(source) if names is None else list(names)
    unknown = [n for n in names if n not in rest]
    if unknown:
        raise InputError(f"unknown landmark(s) {unknown}; known: {list(rest)}")
    missing = [n for n in names if n not in source]
    if missing:
        raise InputError(f"no target given for landmark(s) {missing}")
    if not names:
        raise InputError("targets need at least one landmark")
    pts, held = [], []
    for n in names:
        x, h = _parse_target(n, source[n])
        d = float(np.linalg.norm(x - rest[n]))
        if d > ABSURD_TARGET_MM:
            raise InputError(f"target {n} is {d:.0f} mm from its rest position (more than "
                             f"{ABSURD_TARGET_MM:g} mm): targets are in mm, in the mesh's "
                             "frame")
        if d > far_mm:
            warnings.warn(f"target {n} is {d:.1f} mm from its rest position (more than "
                          f"{far_mm:g} mm: outside the face?)", stacklevel=2)
        pts.append(x)
        held.append(h)
    return names, np.array(pts), np.array(held)


def point_sensitivity(eq: Equilibrium, op: PointOperator) -> np.ndarray:
    """dx/dp at the points of ``op``, (Nt, 3, Np) mm per unit, from the equilibrium's cached
    sensitivities (Np tangent solves on first use)."""
    return np.stack([op.apply(s.array, offset=False) for s in eq.sensitivity()], axis=-1)


class Objective:
    """T(p) for point targets on the current equilibrium of ``eq``.

    Residual rows are each point's offset along the head's axes (``axes``), so that a
    target can hold a landmark along some axes only (``held``): T sums the held rows.

    Args:
        eq: the equilibrium (its current state is x(p)).
        op: point operator L, Nt points.
        targets: (Nt, 3) target positions x̂, mm.
        weights: (Nt,) w_l (default 1).
        tikhonov: α, mm² per squared parameter unit.
        names: optional point names (landmarks), for reports.
        axes: (3, 3) the head's left, anterior and superior axes as columns, scene frame
            (default: the scene's axes).
        held: (Nt, 3) bool, the axes along which each target holds (default: all).
    """

    def __init__(self, eq: Equilibrium, op: PointOperator, targets, weights=None,
                 tikhonov: float = 0.0, names=None, axes=None, held=None):
        self.eq, self.op, self.names = eq, op, names
        self.targets = np.asarray(targets, dtype=float).reshape(op.n_points, 3)
        w = np.ones(op.n_points) if weights is None else np.asarray(weights, dtype=float)
        if w.shape != (op.n_points,) or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise InputError(f"weights must be {op.n_points} finite non-negative numbers")
        self.axes = np.eye(3) if axes is None else np.asarray(axes, dtype=float)
        self.held = np.ones((op.n_points, 3), bool) if held is None else np.asarray(held, bool)
        #: (Nt, 3): w_l on the held rows, 0 on the free ones.
        self.weights = w[:, None] * self.held
        self.tikhonov = check("tikhonov", tikhonov)

    @property
    def n_points(self) -> int:
        return self.op.n_points

    def points(self) -> np.ndarray:
        """Current points x_T (Nt, 3), mm, scene frame."""
        return self.op.apply(self.eq.u.x.array)

    def residual(self) -> np.ndarray:
        """x_T - x̂_T along the head's axes (Nt, 3) mm (free rows included)."""
        return (self.points() - self.targets) @ self.axes

    def value(self) -> float:
        r = self.residual()
        p = self.eq.p
        return 0.5 * float(np.sum(self.weights * r * r)) + 0.5 * self.tikhonov * float(p @ p)

    def distances(self) -> np.ndarray:
        """The distance of each point from its target along its held axes (Nt,), mm."""
        return np.linalg.norm(self.residual() * self.held, axis=1)

    def entries(self) -> dict:
        """``{name: entry}`` as a targets file gives them (`target_entry`)."""
        return {n: target_entry(x, [a for a, h in zip(HEAD_AXES, held) if h])
                for n, x, held in zip(self.names, self.targets, self.held)}

    def _adjoint(self, g: np.ndarray) -> np.ndarray:
        """-Gᵀ K⁻¹ Lᵀ A g for g (Nt, 3) along the head's axes A: one adjoint solve, result
        (Np,)."""
        rhs = self.eq.u_eq.duplicate()
        arr = np.zeros(rhs.getLocalSize())
        self.op.transpose_add(g @ self.axes.T, arr)
        rhs.setArray(arr)
        lam = rhs.duplicate()
        self.eq.solve_tangent(rhs, lam)
        out = -self.eq.coupling_transpose(lam)
        rhs.destroy()
        lam.destroy()
        return out

    def gradient(self) -> np.ndarray:
        """dT/dp (Np,) at the current equilibrium, by one adjoint solve (on the forward
        solve's factorisation when it was solved with ``tangent=True``)."""
        return self._adjoint(self.weights * self.residual()) + self.tikhonov * self.eq.p

    def value_and_gradient(self, p) -> tuple[float, np.ndarray]:
        """(T mm², dT/dp (Np,)) at p (Np,): a tangent-ready forward solve, then one adjoint
        solve that reuses its factorisation. For gradient-based optimisers, e.g.
        ``scipy.optimize.minimize(obj.value_and_gradient, p0, jac=True)``."""
        self.eq.solve(p, tangent=True)
        return self.value(), self.gradient()

    def jacobian(self, mode: str = "auto"):
        """S_T = dx_T/dp, shape (3 Nt, Np) (rows along the head's axes per point, as
        `residual`), and the mode used.

        ``mode``: "direct" (Np solves, cached in the equilibrium), "adjoint" (3 Nt solves)
        or "auto" (the cheaper; direct when the sensitivities are already cached).
        """
        n_rows, n_p = 3 * self.n_points, self.eq.n_params
        if mode == "auto":
            mode = "direct" if n_p <= n_rows or self.eq.has_sensitivity else "adjoint"
        if mode == "direct":
            S = np.einsum("ik,lip->lkp", self.axes, point_sensitivity(self.eq, self.op))
            return S.reshape(n_rows, n_p), mode
        if mode != "adjoint":
            raise InputError(f"unknown sensitivity mode {mode!r}: auto, direct or adjoint")
        S = np.empty((n_rows, n_p))
        for row in range(n_rows):
            e = np.zeros((self.n_points, 3))
            e.flat[row] = 1.0
            S[row] = self._adjoint(e)
        return S, mode
