"""A starting osteotomy file proposed from a CT's anatomy (``ct_scene.py --propose-osteotomies``).

The user adjusts it in 3D Slicer or by hand; each plane follows a rule with its anatomical
reference, found on the whole CT in the head frame (`meshes.frame`: given by the base file's
``frame`` or estimated), so that a tilted head gets the same cuts, turned with it:

* **teeth**: voxels of at least `meshes.teeth.TEETH_HU` (enamel, dentine, fillings), the
  largest cluster of them (`find_teeth`: linked within `TEETH_LINK_MM`, and across the
  mid-sagittal plane by their mirror images); fewer than `MIN_TEETH_MM3` is a CT without
  teeth, which gets a one-line error: every rule below is referred to the dentition;
* **occlusal plane**, between the dental arches: level in the head frame, at the median
  height of the teeth in the arch's front `OCCLUSAL_FRONT_MM` (the incisors' overlap: the
  anterior point of Downs' bisected occlusal plane). The dense voxels do not sample the arches
  evenly enough to fit its tilt (headsq's 3.2 mm voxels keep fillings and blur enamel: a
  least-squares plane of them tilts 34 degrees where the crowns lie level), so the tilt is
  the user's to adjust. Where the crowns reach the field of view's edge (Cranium: the scan
  ends through the maxillary crowns), the occlusal plane lies outside the scan and none is
  proposed, nor a mandible;
* **nasal floor**, the palatal plane's upper surface: beside the septum (`NASAL_BAND_MM` from
  the mid-sagittal plane), over the upper teeth's span from back to front, the lowest air
  (`NASAL_AIR_HU`) above the occlusal plane that has bone (the hard palate) within
  `PALATE_MM` under it; a robust line through those points (Theil-Sen) gives its slope, and
  its front is the piriform aperture's lower rim (Cranium: 37 columns, level in its head
  frame within 0.1 degrees: the palatal plane parallels the Frankfort horizontal, 1 ± 3.5
  degrees in adult norms);
* **LeFort I** (the maxilla's horizontal cut, from the piriform aperture to the
  pterygomaxillary junction): parallel to the occlusal plane, or to the nasal floor where the
  scan holds no occlusal plane; at the aperture `LEFORT_ABOVE_OCCLUSAL_MM` above the
  occlusal plane (above the incisors' apices) and no higher than the nasal floor;
* **pterygomaxillary plane** (the LeFort I segment's posterior end, the pterygomaxillary
  junction behind the maxillary tuberosity): perpendicular to the LeFort I plane and the
  mid-sagittal plane, `PTM_BEHIND_TEETH_MM` behind the upper teeth's back;
* **ramus cuts** (BSSO), where bone (the mandible, `MANDIBLE_MM3`) lies under the teeth below
  the occlusal plane: perpendicular to the occlusal plane and the mid-sagittal plane, each
  side's `RAMUS_BEHIND_TEETH_MM` behind that side's last molar (the teeth's back: the dense
  voxels of the lower molars may be too few to tell them, and the last upper and lower
  molars lie within a cusp of each other);
* **mid-sagittal plane**: the head frame's;
* **crop**: `CROP_MARGINS_MM` (behind the most posterior cut, above the LeFort I cut, below
  the mandible) inside the field of view, its whole width; the inferior face is free
  (traction-free: the neck, or the field of view's cut through the lips, is not tissue held
  by fixed bone), as is the anterior face where the field of view cuts the face flat
  (`FLAT_CUT_MM2`; headsq), one voxel behind the cut.

Heights and distances below are mm in the head frame (x left, y anterior, z superior); the
file's points and normals are in the scene's frame, as every scene file's.
"""

from __future__ import annotations

import numpy as np

from meshes import segment as seg
from meshes.errors import MeshError
from meshes.frame import estimate_on_scan, from_spec
from meshes.teeth import TEETH_HU
from meshes.volume import Volume, rotate_volume

#: Teeth voxels closer than this (mm) belong to one cluster (the dentition; apart from the
#: petrous bone's and a cortex's dense specks).
TEETH_LINK_MM = 6.0
#: Less than this volume (mm³) of teeth voxels is a CT without teeth (one premolar's crown
#: holds about 200 mm³ of enamel and dentine).
MIN_TEETH_MM3 = 100.0
#: Teeth voxels within this many voxels of the scan's edge: the field of view cuts the crowns.
FOV_EDGE_VOXELS = 1
#: A tooth's "back" is this percentile of the teeth's anterior coordinate: the last molar's
#: distal surface, robust to one stray voxel.
BACK_PERCENTILE = 2.0
#: The occlusal plane's height is the median of the teeth within this distance (mm) of the
#: arch's front: the incisors' overlap, the anterior point of Downs' (bisected) occlusal plane.
OCCLUSAL_FRONT_MM = 10.0
#: A field of view that ends through the face: the body's most anterior coronal slice holds
#: at least this area (mm²); a face that ends in the air tapers to the nose's tip (about 1 cm²).
FLAT_CUT_MM2 = 400.0
#: Bone of at least this volume (mm³) below the occlusal plane, under the teeth, is a mandible.
MANDIBLE_MM3 = 2000.0
#: Columns of the nasal floor: this far (mm, [min, max]) to either side of the mid-sagittal
#: plane, beside the septum.
NASAL_BAND_MM = (2.0, 10.0)
#: The nasal floor is searched this far (mm) above the occlusal plane (or the teeth's top):
#: the upper anterior dental height, incisal edge to nasal floor, is 28-30 mm in adults.
NASAL_SEARCH_MM = 40.0
#: Air above the nasal floor (HU): the meatus beside the septum is a few mm wide and lined
#: with mucosa, so its voxels read air and mucosa together (Cranium: -50 to -250 in the
#: lowest 5 mm above the palate, -400 and less only higher up; -400 found the floor in 8 of
#: its 41 columns, -150 in 37).
NASAL_AIR_HU = -150.0
#: The nasal floor's air runs at least this far (mm) upwards: not a pocket between teeth.
NASAL_AIR_MM = 3.0
#: Bone (the hard palate) lies within this distance (mm) under the nasal floor's air.
PALATE_MM = 8.0
#: Fewest columns (anterior positions, one voxel apart) where the nasal floor is found.
NASAL_MIN_COLUMNS = 3
#: The LeFort I cut at the piriform aperture lies this far (mm) above the occlusal plane, and
#: no higher than the nasal floor there (the aperture's lower rim; without an occlusal plane in
#: the scan, at the floor): the incisal edge to the nasal floor is 28-30 mm in adults and the
#: central incisor 23.5 mm long (Wheeler's Dental Anatomy), so the cut passes above the
#: incisors' apices and below the aperture.
LEFORT_ABOVE_OCCLUSAL_MM = 25.0
#: The pterygomaxillary junction lies this far (mm) behind the last upper molar's back: the
#: maxillary tuberosity.
PTM_BEHIND_TEETH_MM = 5.0
#: Each ramus cut lies this far (mm) behind the last molar's back on its side: the
#: retromolar region, where the sagittal split's medial cut on the ramus meets its buccal cut
#: along the external oblique ridge.
RAMUS_BEHIND_TEETH_MM = 8.0
#: Crop margins (mm): behind the most posterior cut (the tissue there is held by fixed bone),
#: above the LeFort I cut (the nose up to the soft-tissue nasion: nasal height, nasion to the
#: nasal floor, is 50-55 mm in adults), below the mandible's lower border (the chin's soft
#: tissue).
CROP_MARGINS_MM = {"behind": 40.0, "above": 80.0, "below": 15.0}


def _plane(point_head, normal_head, frame) -> dict:
    """A scene-file plane from a point and a normal in the head frame."""
    n = np.asarray(normal_head, float)
    return {"point": np.round(frame.to_scene(point_head), 2).tolist(),
            "normal": np.round(frame.rotation @ (n / np.linalg.norm(n)), 5).tolist()}


def find_teeth(volume: Volume, body: np.ndarray, frame) -> tuple:
    """(teeth (K, 3) mm head frame, mm³) of a CT: its voxels of at least `TEETH_HU` in the
    body, single-linked within `TEETH_LINK_MM`, a voxel also linked to its mirror image's
    neighbours (the other side of the arch, where the front teeth read too thin to link
    them), the largest cluster. `MeshError` for a CT without teeth."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    ijk = np.argwhere((volume.array >= TEETH_HU) & body)
    x = frame.to_head(volume.origin + ijk * volume.spacing)
    mm3 = 0.0
    if len(x):
        tree = cKDTree(x)
        pairs = np.vstack([tree.query_pairs(TEETH_LINK_MM, output_type="ndarray"),
                           tree.sparse_distance_matrix(cKDTree(x * [-1.0, 1.0, 1.0]),
                                                       TEETH_LINK_MM, output_type="ndarray")
                           [["i", "j"]].tolist() or np.zeros((0, 2), int)]).astype(int)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                           shape=(len(x), len(x)))
        _, lab = connected_components(graph, directed=False)
        keep = lab == np.argmax(np.bincount(lab))
        ijk, x = ijk[keep], x[keep]
        mm3 = float(len(x) * np.prod(volume.spacing))
    if mm3 < MIN_TEETH_MM3:
        raise MeshError(f"no teeth found in {volume.name}: {mm3:.0f} mm³ above {TEETH_HU:g} HU "
                        f"(at least {MIN_TEETH_MM3:g} needed); the proposal is referred to the "
                        "dentition: write the osteotomy file by hand")
    return ijk, x, mm3


def nasal_floor(hv: Volume, head_origin, teeth_h: np.ndarray, z_from: float,
                bone_hu: float) -> tuple:
    """(y (K,), z (K,)) mm, head frame: the nasal floor's points over the teeth's span, one
    per column beside the septum (module docstring); ``hv`` is the CT on the head's axes,
    its grid at head coordinates ``hv.centres(a) - head_origin[a]``; the search starts at
    height ``z_from``."""
    xs, ys, zs = (hv.centres(a) - head_origin[a] for a in range(3))
    dz = float(hv.spacing[2])
    air_n = max(1, int(np.ceil(NASAL_AIR_MM / dz)))
    palate_n = max(1, int(np.ceil(PALATE_MM / dz)))
    ax = np.abs(xs)
    cols_x = np.flatnonzero((ax >= NASAL_BAND_MM[0]) & (ax <= NASAL_BAND_MM[1]))
    cols_y = np.flatnonzero((ys >= teeth_h[:, 1].min()) & (ys <= teeth_h[:, 1].max()))
    k0 = int(np.searchsorted(zs, z_from))
    k1 = int(np.searchsorted(zs, z_from + NASAL_SEARCH_MM))
    out_y, out_z = [], []
    for j in cols_y:
        found = []
        for i in cols_x:
            col = hv.array[i, j, :]
            air, bone = col < NASAL_AIR_HU, col > bone_hu
            for k in range(max(k0, palate_n), min(k1, len(zs) - air_n)):
                if air[k:k + air_n].all() and bone[k - palate_n:k].any():
                    found.append(zs[k])
                    break
        if len(found) >= max(2, len(cols_x) // 3):
            out_y.append(ys[j])
            out_z.append(float(np.median(found)))
    return np.asarray(out_y), np.asarray(out_z)


def propose(scan: Volume, base: dict | None = None, where: str = "") -> dict:
    """The proposed scene file (a JSON object) of a CT in HU at its own voxels (module
    docstring; a CBCT's are averaged here as `meshes.ct.build` does): ``base``
    (a scene file's JSON, or None) gives the thresholds and the frame, and its settings other
    than planes and crop are kept. `MeshError` with one line where a rule finds nothing."""
    from scipy import stats

    from meshes.osteotomy import PLANES

    base = dict(base or {})
    if base.get("labels") is not None:
        raise MeshError("a label map has no HU to find the teeth by: propose the osteotomies "
                        "on the CT")
    skin_hu = float(base.get("skin_hu", seg.SKIN_HU))
    bone_hu = float(base.get("bone_hu", seg.BONE_HU))
    volume = scan.coarsened()
    body, bone = seg.labels_from_ct(volume, skin_hu, bone_hu)
    frame = from_spec(base["frame"], where) if base.get("frame") is not None else \
        estimate_on_scan(scan, lambda v: seg.labels_from_ct(v, skin_hu, bone_hu)[1], bone_hu)
    ijk, teeth, teeth_mm3 = find_teeth(volume, body, frame)
    shape = np.array(volume.array.shape)
    cut_by_fov = bool(np.any((ijk < FOV_EDGE_VOXELS) | (ijk >= shape - FOV_EDGE_VOXELS)))
    o = frame.origin
    hv = rotate_volume(volume, frame.rotation.T, o, fill=-1000.0)   # grid axes: the head's
    up, front, left = np.eye(3)[2], np.eye(3)[1], np.eye(3)[0]

    incisal = teeth[teeth[:, 1] >= teeth[:, 1].max() - OCCLUSAL_FRONT_MM]
    z_occ = None if cut_by_fov else float(np.median(incisal[:, 2]))
    chin = None if z_occ is None else _mandible_bottom(hv, o, teeth, z_occ, bone_hu)
    upper = teeth if chin is None else teeth[teeth[:, 2] >= z_occ]
    z_from = float(upper[:, 2].max()) if z_occ is None else z_occ
    y_floor, z_floor = nasal_floor(hv, o, upper, z_from, bone_hu)
    if len(y_floor) < NASAL_MIN_COLUMNS:
        raise MeshError(f"no nasal floor found above the teeth of {volume.name} (air beside the "
                        "septum with the palate under it): write the LeFort I plane by hand")
    slope, intercept = stats.theilslopes(z_floor, y_floor)[:2]
    y_front = float(y_floor.max())   # the piriform aperture's floor
    lf_point = np.array([0.0, y_front, slope * y_front + intercept])
    if z_occ is None:
        lf_normal = np.array([0.0, -slope, 1.0]) / np.hypot(1.0, slope)
    else:
        lf_normal = up
        lf_point[2] = min(lf_point[2], z_occ + LEFORT_ABOVE_OCCLUSAL_MM)
    lf_front = np.cross(lf_normal, left)   # anterior, in the LeFort I plane
    back = float(np.percentile(upper @ lf_front, BACK_PERCENTILE))
    ptm = lf_point + (back - PTM_BEHIND_TEETH_MM - lf_point @ lf_front) * lf_front
    planes = {"midsagittal": _plane(np.zeros(3), left, frame),
              "lefort1": _plane(lf_point, lf_normal, frame),
              "pterygomaxillary": _plane(ptm, lf_front, frame)}
    posterior = [ptm]
    if z_occ is not None:
        planes["occlusal"] = _plane([0.0, float(np.median(incisal[:, 1])), z_occ], up, frame)
    if chin is not None:
        for name, side in (("ramus_L", 1.0), ("ramus_R", -1.0)):
            mine = teeth[side * teeth[:, 0] > 0]
            if len(mine) == 0:
                raise MeshError(f"no teeth on the {'left' if side > 0 else 'right'} side of "
                                f"{volume.name}: write the ramus cuts by hand")
            y = float(np.percentile(mine[:, 1], BACK_PERCENTILE)) - RAMUS_BEHIND_TEETH_MM
            p = np.array([side * float(np.median(np.abs(mine[:, 0]))), y, z_occ])
            planes[name] = _plane(p, front, frame)
            posterior.append(p)
    spec = {k: v for k, v in base.items() if k not in PLANES and k not in ("crop", "planes")}
    spec["about"] = (f"Proposed by ct_scene.py --propose-osteotomies from {volume.name} "
                     "(meshes.propose): a starting point, to adjust in 3D Slicer or by hand; "
                     "mm in the scene's frame." + (" The field of view cuts the teeth: no "
                                                   "occlusal plane, no mandible."
                                                   if cut_by_fov else ""))
    spec.update(planes)
    bottom = frame.to_scene([0.0, 0.0, chin])[2] - CROP_MARGINS_MM["below"] \
        if chin is not None else -np.inf
    spec["crop"] = _crop(volume, body, frame.to_scene(np.array(posterior)),
                         frame.to_scene(lf_point), bottom)
    spec["proposal"] = {"head_frame": frame.matrix.round(5).tolist(),
                        "teeth_mm3": round(teeth_mm3, 1), "teeth_cut_by_field_of_view":
                        cut_by_fov, "mandible": chin is not None,
                        "nasal_floor_pitch_deg": round(float(np.degrees(np.arctan(slope))), 2),
                        "nasal_floor_columns": int(len(y_floor))}
    return spec


def _mandible_bottom(hv: Volume, o, teeth, z_occ: float, bone_hu: float):
    """The lowest bone's height (mm, head frame) under the teeth's footprint when at least
    `MANDIBLE_MM3` of bone lies there below the occlusal plane, else None (no mandible)."""
    hb = np.argwhere(hv.array > bone_hu) * hv.spacing + hv.origin - o
    lo, hi = teeth[:, :2].min(axis=0) - TEETH_LINK_MM, teeth[:, :2].max(axis=0) + TEETH_LINK_MM
    under = np.all((hb[:, :2] >= lo) & (hb[:, :2] <= hi), axis=1) \
        & (hb[:, 2] < z_occ - TEETH_LINK_MM)
    if under.sum() * float(np.prod(hv.spacing)) < MANDIBLE_MM3:
        return None
    return float(hb[under, 2].min())


def _crop(volume: Volume, body, posterior, lefort, bottom: float) -> dict:
    """The crop box (scene frame, the scanner's axes: the pipeline crops the CT's grid) with
    `CROP_MARGINS_MM` inside the field of view, and its free faces (module docstring):
    ``posterior`` (K, 3) the cuts' points, ``lefort`` (3,) the LeFort I point and ``bottom``
    the lowest height kept (-inf: the field of view's), mm."""
    m = CROP_MARGINS_MM
    lo = volume.origin.astype(float).copy()
    hi = lo + volume.spacing * (np.array(volume.array.shape) - 1)
    lo[1] = max(lo[1], float(posterior[:, 1].min()) - m["behind"])
    lo[2] = max(lo[2], bottom)
    hi[2] = min(hi[2], float(lefort[2]) + m["above"])
    free = ["-z"]
    rows = np.flatnonzero(body.any(axis=(0, 2)))
    front = rows[-1]
    if body[:, front, :].sum() * volume.spacing[0] * volume.spacing[2] >= FLAT_CUT_MM2:
        # the field of view cuts the face flat: end one voxel behind the cut, free there
        hi[1] = min(hi[1], float(volume.centres(1)[front - 1]))
        free.append("+y")
    return {"min": np.round(lo, 1).tolist(), "max": np.round(hi, 1).tolist(), "free": free}
