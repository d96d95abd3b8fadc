"""An interactive exploration session (paper Fig. 5): the state behind the browser explorer.

`Session` keeps a scene at an equilibrium x(p0) with its skin sensitivities
(`inverse.explore.SkinPredictor`) and answers what a surgeon asks of it: the true equilibrium
at p, warm-started from the first-order prediction (Fig. 5b compares the two), the corrected
prediction, re-linearisation at p, a plan to landmark targets, and the parameters whose true
equilibrium is closest to a predicted face (Fig. 5c). After a plan or a match the session is
re-linearised at its result, so the first-order sliders start from there.

Every method that computes is collective: all ranks call it with the same arguments and get
the same answer. `Session.request_params` and `Session.request_targets` validate a request's
values; no HTTP here (`scripts/explore_web.py`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from fem.limits import check
from inverse.explore import SkinPredictor, fit_surface
from inverse.planner import gauss_newton, plan_report
from inverse.treatment import FTOL, TIKHONOV
from meshes.errors import InputError

#: What a plan request may ask for (``occlusion``), and the parameters it plans: those of
#: ``scripts/plan.py`` (`inverse.treatment.PLAN_PARAMS`, `JAWS_PARAMS`).
OCCLUSIONS = ("final", "free")


def _finite_number(name: str, value) -> float:
    """A JSON number that is finite, else `InputError`."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def check_targets(rest: dict, targets) -> dict:
    """``{landmark: entry}`` from a request or a file: an object of known landmarks (``rest``
    {name: (3,)} mm), each a finite 3-vector in mm near the face, or one held along some
    head axes (`inverse.objective.load_targets`), as `inverse.objective.target_entry` writes
    it; `InputError` otherwise. Local: no communication."""
    from inverse.objective import HEAD_AXES, load_targets, target_entry

    if not isinstance(targets, dict) or not targets:
        raise InputError("'targets' must be an object {landmark: [x, y, z]} mm")
    for n, x in targets.items():
        point = x.get("at") if isinstance(x, dict) else x
        if not isinstance(point, list) or len(point) != 3:
            raise InputError(f"target {n} must be [x, y, z] in mm, got {x!r}")
        for c in point:
            _finite_number(f"target {n}", c)
    names, pts, held = load_targets(targets, rest)
    return {n: target_entry(x, [a for a, h in zip(HEAD_AXES, hs) if h])
            for n, x, hs in zip(names, pts, held)}


class Session:
    """Exploration around an equilibrium.

    Args:
        scene: the `Scene` to explore (its occlusion "final" or "free").
        make_scene: ``make_scene(occlusion) -> Scene``, called when a plan asks for the other
            occlusion (None: such a plan is refused).
        p0: (Np,) start equilibrium (default 0).
        targets: {landmark: entry} (`check_targets`) shown and planned to (default: the
            case's goal, none for an external mesh).
        prior: the tissue's prior of the bands shown (`inverse.uncertainty.Prior`; default:
            the scene's, `scene_prior`; False: no band).
    """

    def __init__(self, scene, make_scene=None, p0=None, targets=None, validation=None,
                 prior=None):
        from inverse.uncertainty import scene_prior

        self.validation = validation   # shown as it is (`payload`)
        self.prior = scene_prior(scene) if prior is None else (prior or None)
        self.occlusion = "free" if scene.treatment.occlusion is None else "final"
        self._make_scene, self.scenes = make_scene, {self.occlusion: scene}
        self.rest_landmarks = scene.landmarks(rest=True)   # the same in every scene
        if targets is None and scene.case is not None:
            targets = scene.default_targets()
        self.targets = None if targets is None else check_targets(self.rest_landmarks,
                                                                  targets)
        self.pred = None
        self.relinearise(np.zeros(len(scene.param_names)) if p0 is None
                         else scene.param_vector(p0))

    @property
    def scene(self):
        return self.scenes[self.occlusion]

    def request_params(self, values) -> np.ndarray:
        """(Np,) from a request's ``{name: value}``: known names, finite numbers within the
        parameters' bounds; names not given keep their value at p0. `InputError` otherwise.
        Local: no communication."""
        if not isinstance(values, dict):
            raise InputError("'p' must be an object {parameter: value}")
        names = self.scene.param_names
        unknown = [k for k in values if k not in names]
        if unknown:
            raise InputError(f"unknown parameter(s) {unknown}; known: {names}")
        p = self.pred.p0.copy()
        for k, v in values.items():
            p[names.index(k)] = _finite_number(k, v)
        bad = self.scene.treatment.outside_bounds(p)
        if bad:
            raise InputError(bad[0])
        return p

    def request_targets(self, targets=None) -> dict:
        """Validated targets of a plan request (`check_targets`); None: the session's."""
        if targets is None:
            if self.targets is None:
                raise InputError("no targets: give 'targets' {landmark: [x, y, z]} mm")
            return self.targets
        return check_targets(self.rest_landmarks, targets)

    # ------------------------------------------------------------------ answers
    def payload(self) -> dict:
        """The scene as the page needs it (GET /api/scene): parameters, skin triangles,
        skin at rest and at p0 (N, 3) mm, landmarks at p0 and their sensitivities
        (L, 3, Np) mm per unit, targets, the head's axes (``head_axes``: left, anterior,
        superior, scene frame) for the page's Front and Profile views, the bone (`_bone`),
        and a validation's map where the session has one (``validation``:
        ``signed_distance_mm`` (N,) per skin vertex, None where the scan does not hold it,
        and its ``error_mm``; `scripts/validate.py`), and the tissue's band at p0 (``band``:
        ``r95_mm`` (N,) per skin vertex and per landmark, `inverse.uncertainty`)."""
        scene, pred = self.scene, self.pred
        tr = scene.treatment
        return {"param_names": tr.names, "units": [q.unit for q in tr.params],
                "bounds": tr.bounds.tolist(), "p0": pred.p0.tolist(),
                "occlusion": self.occlusion,
                "triangles": scene.domain.boundary_triangles(pred.vertices).tolist(),
                "vertices": pred.x0.tolist(), "vertices_rest": pred.x_rest.tolist(),
                "landmarks": {n: x.tolist() for n, x in zip(pred.landmark_names, pred.lm0)},
                "landmark_sensitivity": pred.lm_S.tolist(),
                "targets": self.targets,
                "head_axes": scene.head_frame.rotation.T.tolist(),
                "bone": self._bone(), "validation": self.validation,
                "band": None if pred.band is None else {
                    "r95_mm": pred.band.tolist(), "landmarks": pred.lm_band}}

    def _bone(self) -> dict:
        """The bone under the skin for the page (GET /api/scene's ``bone``): its surface at
        rest (``vertices`` (B, 3) mm, ``triangles`` (F, 3) facing out of the bone), each
        vertex's segment (``segment`` (B,), an index into ``segments``, -1: bone that stays
        put), and each segment's motion at p0 and its derivatives (``transforms`` (4, 4) and
        ``transform_derivatives`` (Np, 4, 4) per unit, exact), from which the page draws the
        bone at first order, as the skin. Collective."""
        from meshes.anatomy import FIXED, FREE_BONE, segment_tags

        scene, dom = self.scene, self.scene.domain
        segments = list(dom.segments)
        tags = [FIXED, FREE_BONE, *(t for s in segments for t in segment_tags(dom.segments[s]))]
        verts = dom.boundary_vertices(tags)
        x = dom.vertex_operator(verts).apply(np.zeros(dom.X.size))
        which = np.full(len(verts), -1)
        for k, name in enumerate(segments):
            which[np.isin(verts, dom.boundary_vertices(segment_tags(dom.segments[name])))] = k
        T, dT = scene.treatment.transforms(self.pred.p0, dom.pivots, derivatives=True)
        return {"vertices": x.tolist(),
                "triangles": dom.boundary_triangles(verts, tags)[:, ::-1].tolist(),
                "segment": which.tolist(), "segments": segments,
                "transforms": [T[s].tolist() for s in segments],
                "transform_derivatives": [dT[s].tolist() for s in segments]}

    def sensitivity_bytes(self) -> bytes:
        """S_skin (N, 3, Np) as little-endian float32 in C order (GET /api/sensitivity)."""
        return np.ascontiguousarray(self.pred.S, dtype="<f4").tobytes()

    def _answer(self, skin, landmarks, p, iterations: int, seconds: float) -> dict:
        first = self.pred.predict(p - self.pred.p0)
        motions = self.scene.transforms(p)
        return {"p": dict(zip(self.scene.param_names, p.tolist())), "vertices": skin.tolist(),
                "landmarks": {n: np.asarray(x).tolist() for n, x in landmarks.items()},
                "transforms": [motions[s].tolist() for s in self.scene.domain.segments],
                "iterations": int(iterations), "seconds": seconds,
                "first_order_error_max_mm": float(np.linalg.norm(skin - first, axis=1).max())}

    def solve(self, p) -> dict:
        """The true equilibrium at p (Np,), warm-started from the first-order state
        x(p0) + dx/dp (p - p0) on the kept factorisation of K(p0) (no tangent solve: from
        wherever the last answer left the scene): skin, landmarks, iterations, seconds and
        the largest distance of the first-order skin x0 + S dp from it (Fig. 5b).
        Collective."""
        t = time.perf_counter()
        start = self.pred.state(p - self.pred.p0)
        try:
            stats = self.scene.solve(p, start=start)
        finally:
            start.destroy()
        seconds = time.perf_counter() - t
        return self._answer(self._skin(), self.scene.landmarks(), p,
                            stats.iterations, seconds)

    def corrected(self, p) -> dict:
        """The corrected prediction at p (`SkinPredictor.corrected`), the keys of `solve`.
        Collective."""
        eq = self.scene.eq
        before = eq.stats.iterations
        t = time.perf_counter()
        skin, landmarks = self.pred.corrected(p - self.pred.p0)
        seconds = time.perf_counter() - t
        return self._answer(skin, landmarks, p, eq.stats.iterations - before, seconds)

    def relinearise(self, p) -> dict:
        """Solve at p and make it the new p0, with new skin sensitivities. Collective."""
        t = time.perf_counter()
        self.scene.solve(p)
        if self.pred is not None:
            self.pred.destroy()
        self.pred = SkinPredictor(self.scene, self.prior)
        return {"p0": self.pred.p0.tolist(), "seconds": time.perf_counter() - t}

    def plan(self, targets: dict, occlusion: str, progress=None, tikhonov: float = TIKHONOV,
             ftol: float = FTOL, max_iterations: int = 20) -> dict:
        """Plan from the current p0 to ``targets`` (validated, `check_targets`) with
        the occlusion "final" (jaws.* motions) or "free" (`PLAN_PARAMS`), then re-linearise
        at the plan. A plan in the other occlusion starts from the parameters that reach p0's
        bone motions there where they can (otherwise from 0). ``progress(entry)`` gets each
        Gauss-Newton history entry; tikhonov, ftol, max_iterations as in ``scripts/plan.py``.
        Returns the plan report (`inverse.planner.plan_report`) with ``seconds``.
        Collective."""
        if occlusion not in OCCLUSIONS:
            raise InputError(f"'occlusion' must be one of {list(OCCLUSIONS)}, got {occlusion!r}")
        tikhonov, ftol = check("tikhonov", tikhonov), check("ftol", ftol)
        max_iterations = check("max_iterations", max_iterations)
        t = time.perf_counter()
        start, old = self.pred.p0, self.occlusion
        try:
            if occlusion != old:
                if self._make_scene is None and occlusion not in self.scenes:
                    raise InputError(f"this explorer's scene has the occlusion {old!r} only")
                motions = self.scene.transforms(self.pred.p0)
                if occlusion not in self.scenes:
                    self.scenes[occlusion] = self._make_scene(occlusion)
                self.occlusion = occlusion
                try:
                    start = self.scene.params_from_transforms(motions)
                except InputError:
                    start = np.zeros(len(self.scene.param_names))
                lo, hi = self.scene.treatment.bounds.T
                start = np.clip(start, lo, hi)
            scene = self.scene
            obj = scene.objective(targets, tikhonov=tikhonov)
            scene.solve(start)
            before = scene.landmarks(list(targets))
            result = gauss_newton(scene, obj, p0=start, ftol=ftol,
                                  max_iterations=max_iterations,
                                  callback=None if progress is None
                                  else lambda p, entry: progress(entry))
        except BaseException:
            self.occlusion = old   # the predictor's scene
            raise
        report = plan_report(scene, result, obj, before)
        self.targets = obj.entries()
        self.relinearise(result.params)
        report["seconds"] = time.perf_counter() - t
        return report

    def match(self, p) -> dict:
        """Fig. 5c: the parameters whose true equilibrium is closest to the first-order skin
        at p (least squares over every skin vertex, from p0), then re-linearise there.
        Returns ``p``, ``distance_max_mm``/``distance_mean_mm`` of the true skin from the
        predicted one, ``gn_iterations``, ``seconds``. Collective."""
        t = time.perf_counter()
        surface = self.pred.predict(p - self.pred.p0)
        result = fit_surface(self.scene, self.pred, surface)
        d = np.linalg.norm(self._skin() - surface, axis=1)
        out = {"p": dict(zip(self.scene.param_names, result.params.tolist())),
               "distance_max_mm": float(d.max()), "distance_mean_mm": float(d.mean()),
               "gn_iterations": result.gn_iterations, "converged": result.converged}
        self.relinearise(result.params)
        out["seconds"] = time.perf_counter() - t
        return out

    def export(self, p) -> dict:
        """The plan a VSP program takes (the page's Export): parameters, every segment's
        rigid motion (4×4, mm, scene frame) and the occlusion at p."""
        tr = self.scene.treatment
        return {"param_names": tr.names, "params": dict(zip(tr.names, p.tolist())),
                "units": dict(zip(tr.names, (q.unit for q in tr.params))),
                "transforms": {s: T.tolist() for s, T in self.scene.transforms(p).items()},
                "occlusion": None if tr.occlusion is None else tr.occlusion.tolist(),
                "targets": self.targets}

    def _skin(self) -> np.ndarray:
        return self.pred.op.apply(self.scene.eq.u_eq.array)

    def destroy(self):
        if self.pred is not None:
            self.pred.destroy()
