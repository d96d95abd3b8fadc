"""A prediction against the patient's outcome: the protocol of FEM validation studies.

1. **Register** the post-operative face to the pre-operative scene on the skin that surgery
   does not move (`register_scan`, `stable_mask`): the forehead, the nasal bridge, the
   orbits and the temples, `STABLE_ABOVE_MM` above the moving bone and off the nose. A
   rigid ICP (`meshes.registration.register_surface`) of that skin onto the scan; a
   registration whose overlap, residual or facing shows it failed is a one-line error,
   never a number in a report.
2. The bone movements are given (treatment parameters or VSP transforms), or measured on a
   post-operative CT (`inverse.postop`, which also registers a CT and gives its skin).
3. **Simulate** them (the forward solve).
4. **Compare** (`compare`): per skin vertex, the signed distance from the predicted skin to
   the real surface (`signed_distance`; > 0: the prediction stands out of the real face),
   where the scan holds the face (a vertex whose closest point lies on the scan's open rim is
   beyond it, one whose closest point faces the other way is in a fold the scan does not
   see) and the skin is skin: not on its own rim, where it meets a crop face or a free
   surface (CGAL rounds a crop face's edge, and an air pocket's mouth is the mesh's edge:
   Cranium at coarse, 224 of its 814 skin vertices, their distance to the CT's skin at rest
   up to 4.2 mm, the others' mean 0.17 mm); summarised (`summary`) over the face and per
   region (`region_masks`), and per landmark: the same constructions (`meshes.landmarks`) on
   the predicted skin and on the outcome's resampled on the scene's mesh (each vertex the
   outcome shows at its closest point on it), landmarks whose facet it shows: the same rule
   on surfaces of one resolution (Cranium's CT at coarse, the constructions on its 1 mm
   marching-cubes skin put Sn 2.2 mm from the mesh's at rest; and the material point of a
   lip that rolls is not where the construction finds the lip's front).

The metrics are those of the published studies (docs/validation.md): mean, median, 90th
percentile, RMS and max of the absolute distance, and the shares within 1 and 2 mm.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from meshes.errors import MeshError

#: The skin registered on lies this far (mm) above the moving bone's top (the LeFort I cut,
#: or the mandible's), off the nose below the nasion: the orbits, the temples, the nasal
#: bridge and the forehead. class3-asym at coarse, a 4 mm, 2 degree BSSO and a 2 mm LeFort I:
#: that skin moved 0.084 mm at most (the cheeks under the orbits; 0.42 mm with 15 mm, 0.11
#: with 25), the nose up to the nasion 0.8 mm (tests/test_validate.py checks 0.1 mm).
STABLE_ABOVE_MM = 30.0
#: A registration fails when fewer than this share of the stable skin finds the scan within
#: the last cut-off (`meshes.registration.ICP_CUTOFFS_MM`): no overlap, a scan of something else.
OVERLAP_MIN = 0.5
#: ... or when the RMS distance (mm) of the matched stable skin exceeds this: a surface scan
#: of a face is accurate to about 0.2-0.5 mm (3dMD), and the skin mesh lies within its facet
#: distance of the CT's (`meshes.ct.CGAL_SIZING`).
RESIDUAL_MAX_MM = 1.0
#: ... or when the scan's faces point into the head where the skin's point out (the median
#: cosine of the normals below this): a scan mirrored left to right, or inside out.
FACING_MIN = 0.0
#: Regions (`region_masks`), head frame, mm: half-widths from the mid-sagittal plane (nose;
#: lips and chin), the cheeks' outer bound, how far behind its landmark a region reaches, and
#: the nose's height above Sn where N is absent.
NOSE_HALF_MM, LIPS_HALF_MM, CHEEK_OUT_MM = 18.0, 25.0, 70.0
BEHIND_MM, NOSE_MM = 20.0, 40.0
#: The upper lip's height (mm, Sn to the stomion: 19-22 in adults, Farkas), where the scene
#: lacks Ls or Li to place the stomion (a field of view that ends through the lips).
UPPER_LIP_MM = 20.0
#: A skin vertex is in the scan where the scan's closest triangle faces within 60 degrees of
#: its normal (this cosine): otherwise the scan does not show that skin, and the closest point
#: is another part of the face (class3-asym, a scan cropped to what a frontal camera sees: the
#: jaw's sides found the cheeks' front up to 12.3 mm away, their normals 88 degrees apart).
COVER_COS = 0.5
#: The summary's thresholds (mm): the published shares within 1 and 2 mm.
WITHIN_MM = (1.0, 2.0)


@dataclasses.dataclass
class Registration:
    """A scan registered to the scene: ``transform`` (4×4, scan -> scene frame),
    ``residual_mm`` (RMS over the matched stable skin), ``overlap`` (its matched share),
    ``n_points`` (the stable skin vertices) and, for a CT, ``condition`` (how well the
    stable bone determines the fit, `inverse.postop.fit_condition`)."""

    transform: np.ndarray
    residual_mm: float
    overlap: float
    n_points: int
    condition: float | None = None

    def report(self) -> dict:
        out = {"transform": self.transform.tolist(), "residual_mm": self.residual_mm,
               "overlap": self.overlap, "n_points": self.n_points}
        return out if self.condition is None else {**out, "condition": self.condition}


@dataclasses.dataclass
class Skin:
    """A scene's skin: ``op`` (`fem.domain.PointOperator` of its vertices), ``tris`` (T, 3),
    ``rest`` (N, 3) mm, and ``bone`` (B, 3) mm: the moving segments' bone vertices at rest."""

    op: object
    tris: np.ndarray
    rest: np.ndarray
    bone: np.ndarray

    @classmethod
    def of(cls, scene) -> "Skin":
        """The skin of ``scene`` (`inverse.scene.Scene`). Collective."""
        from meshes.anatomy import segment_tags

        dom = scene.domain
        verts = dom.boundary_vertices()
        op = dom.vertex_operator(verts)
        zero = np.zeros_like(scene.eq.u_eq.array)
        tags = [t for s in dom.segments.values() for t in segment_tags(s)]
        bone = dom.vertex_operator(dom.boundary_vertices(tags)).apply(zero)
        return cls(op, dom.boundary_triangles(verts), op.apply(zero), bone)

    def at(self, scene) -> np.ndarray:
        """The skin (N, 3) mm at the scene's equilibrium. Collective."""
        return self.op.apply(scene.eq.u_eq.array)


def stable_mask(skin: np.ndarray, moving_bone: np.ndarray, frame, landmarks: dict) -> np.ndarray:
    """Skin vertices (N,) bool that surgery does not move (module docstring): ``skin`` (N, 3)
    higher than the moving bone (B, 3) by `STABLE_ABOVE_MM` in the head frame ``frame``, and
    off the nose (`NOSE_HALF_MM` from the mid-sagittal plane) below N where ``landmarks``
    (scene frame) have it."""
    x = frame.to_head(skin)
    top = float(frame.to_head(moving_bone)[:, 2].max()) if len(moving_bone) else -np.inf
    nose_top = frame.to_head(landmarks["N"])[2] if "N" in landmarks else np.inf
    return (x[:, 2] >= top + STABLE_ABOVE_MM) & ((np.abs(x[:, 0]) >= NOSE_HALF_MM)
                                                 | (x[:, 2] >= nose_top))


def register_scan(scan_points: np.ndarray, scan_tris: np.ndarray, skin: np.ndarray,
                  skin_tris: np.ndarray, stable: np.ndarray) -> Registration:
    """The scan (points, triangles; its own frame) registered to the skin (``skin`` (N, 3)
    rest positions, ``skin_tris``) on the ``stable`` (N,) vertices (module docstring).
    `MeshError` with one line where it fails."""
    from meshes.registration import register_surface
    from meshes.surface import apply, closest_points, normals_at, vertex_normals

    if stable.sum() < 3:
        raise MeshError(f"no skin lies {STABLE_ABOVE_MM:g} mm above the moving bone to register "
                        "the scan on (forehead, nasal bridge, orbits, temples)")
    x, n_x = skin[stable], vertex_normals(skin, skin_tris)[stable]
    T, d, matched = register_surface(x, scan_points, scan_tris, n_x)
    overlap = float(matched.mean())
    if overlap < OVERLAP_MIN:
        raise MeshError(f"the scan does not overlap the face: {overlap:.0%} of the skin surgery "
                        f"does not move lies on it after registration (at least "
                        f"{OVERLAP_MIN:.0%} needed): no overlap, or a scan of something else")
    residual = float(np.sqrt(np.mean(d[matched] ** 2)))
    if residual > RESIDUAL_MAX_MM:
        raise MeshError(f"the scan does not fit the face where surgery moves nothing: residual "
                        f"{residual:.2f} mm RMS (at most {RESIDUAL_MAX_MM:g}): a scan of "
                        "something else, or of another patient")
    _, q, tri = closest_points(apply(T, x[matched]), scan_points, scan_tris)
    n_skin = n_x[matched] @ T[:3, :3].T
    facing = float(np.median(np.einsum("ij,ij->i", n_skin,
                                       normals_at(scan_points, scan_tris, tri, q))))
    if facing < FACING_MIN:
        raise MeshError(f"the scan's faces point into the head (median cosine {facing:.2f} with "
                        "the skin's normals): a scan mirrored left to right, or inside out")
    return Registration(np.linalg.inv(T), residual, overlap, int(stable.sum()))


def signed_distance(x: np.ndarray, normals: np.ndarray, points: np.ndarray,
                    tris: np.ndarray) -> tuple:
    """(signed distance (K,) mm, covered (K,) bool, closest points (K, 3), the surface's
    unit normals there (K, 3)) from points x (K, 3) with unit normals (K, 3) to the surface:
    > 0 where x lies on the side its normals point to. Covered where
    the closest point lies inside the surface, not on its open rim, and the surface there
    faces the way x does, within `COVER_COS`."""
    from meshes.surface import SurfaceQuery, normals_at

    surface = SurfaceQuery(points, tris)
    d, q, tri = surface.closest(x)
    n = normals_at(points, tris, tri, q)   # one normal on an edge, whichever triangle
    side = np.einsum("ij,ij->i", x - q, n)
    facing = np.einsum("ij,ij->i", normals, n) > COVER_COS
    return np.where(side < 0, -d, d), ~surface.on_rim(q) & facing, q, n


def region_masks(x: np.ndarray, lm: dict) -> dict:
    """{region: (N,) bool} of skin points x (N, 3) by the landmarks ``lm`` {name: (3,)}, both
    in the head frame (docs/validation.md): nose, upper_lip, lower_lip, chin, cheek_L,
    cheek_R; a region whose landmarks the scene lacks is absent."""
    ax, y, z = np.abs(x[:, 0]), x[:, 1], x[:, 2]
    has = lambda *names: all(k in lm for k in names)   # noqa: E731
    out = {}
    stomion = (lm["Ls"][2] + lm["Li"][2]) / 2 if has("Ls", "Li") else \
        lm["Sn"][2] - UPPER_LIP_MM if has("Sn") else None
    fold = (lm["Li"][2] + lm["Pg"][2]) / 2 if has("Li", "Pg") else None   # labiomental
    if has("Sn"):
        sn = lm["Sn"]
        top = lm["N"][2] if has("N") else sn[2] + NOSE_MM
        out["nose"] = (ax <= NOSE_HALF_MM) & (z >= sn[2]) & (z <= top) & (y >= sn[1] - BEHIND_MM)
        if stomion is not None:
            out["upper_lip"] = (ax <= LIPS_HALF_MM) & (z >= stomion) & (z < sn[2]) \
                & (y >= sn[1] - BEHIND_MM)
            ear = min((lm[k][1] for k in ("T_L", "T_R") if k in lm), default=-np.inf)
            for name, side in (("cheek_L", 1.0), ("cheek_R", -1.0)):
                out[name] = (side * x[:, 0] > LIPS_HALF_MM) & (side * x[:, 0] <= CHEEK_OUT_MM) \
                    & (z >= stomion - BEHIND_MM / 2) & (z <= sn[2] + BEHIND_MM) \
                    & (y >= ear + BEHIND_MM)
    if stomion is not None and fold is not None:
        out["lower_lip"] = (ax <= LIPS_HALF_MM) & (z >= fold) & (z < stomion) \
            & (y >= lm["Li"][1] - BEHIND_MM)
    if fold is not None and has("Me"):
        out["chin"] = (ax <= LIPS_HALF_MM) & (z < fold) & (z >= lm["Me"][2] - BEHIND_MM / 4) \
            & (y >= lm["Pg"][1] - BEHIND_MM)
    return out


def summary(d: np.ndarray) -> dict:
    """The published metrics of signed distances d (K,) mm (module docstring)."""
    a = np.abs(np.asarray(d, float))
    if len(a) == 0:
        raise MeshError("no skin vertex to summarise")
    return {"mean": float(a.mean()), "median": float(np.median(a)),
            "p90": float(np.percentile(a, 90)), "rms": float(np.sqrt(np.mean(a ** 2))),
            "max": float(a.max()), "n_vertices": int(len(a)),
            **{f"within_{t:g}mm": float(np.mean(a <= t)) for t in WITHIN_MM}}


def compare(after: np.ndarray, rest: np.ndarray, skin_tris: np.ndarray, frame,
            landmarks_rest: dict, scan_points: np.ndarray, scan_tris: np.ndarray,
            staircase: float) -> tuple:
    """(report part, signed distance (N,), covered (N,)) of the predicted skin ``after``
    (N, 3, triangles ``skin_tris``) against the scan (registered: the scene's frame), with
    regions on the ``rest`` skin and its landmarks ``landmarks_rest`` (the scene's frame;
    ``frame`` the head frame, `meshes.frame`); the landmarks built on both skins alike
    (module docstring), with the scene's ``staircase`` (`meshes.landmarks.staircase_mm`)."""
    from meshes.ct import HEAD_MIDSAGITTAL
    from meshes.landmarks import skin_landmarks
    from meshes.surface import boundary_edges, vertex_normals

    d, seen, q, _ = signed_distance(after, vertex_normals(after, skin_tris), scan_points,
                                    scan_tris)
    covered = seen.copy()
    covered[np.unique(boundary_edges(skin_tris))] = False   # the skin's own rim
    if not covered.any():
        raise MeshError("the scan covers no skin vertex of the scene")
    head = frame.to_head(rest)
    lm_head = {k: frame.to_head(v) for k, v in landmarks_rest.items()}
    regions, absent = {}, []
    for name, mask in region_masks(head, lm_head).items():
        if (mask & covered).any():
            regions[name] = summary(d[mask & covered])
        else:
            absent.append(name)
    def built(x):   # {name: (3,)} of the constructions on the skin x (N, 3), in view
        try:
            found = skin_landmarks(frame.to_head(x), skin_tris, HEAD_MIDSAGITTAL,
                                   staircase=staircase)
        except MeshError:
            return {}
        return {k: v.position(x) for k, v in found.items() if seen[np.asarray(v.facet)].all()}

    real = built(np.where(seen[:, None], q, after))   # the outcome on the scene's mesh
    predicted = built(after)
    marks = {k: float(np.linalg.norm(predicted[k] - real[k]))
             for k in sorted(set(real) & set(predicted))}
    return ({"error_mm": summary(d[covered]), "regions": regions,
             "regions_not_in_scan": absent, "landmarks": marks,
             "covered": float(covered.mean())}, d, covered)
