"""The teeth label: the bone-segment facets the soft tissue slides on (`fem.equilibrium`).

The lips and cheeks are not attached to the teeth, nor to the alveolar process between the
gingival margin and the fold of the vestibule (the labial and buccal vestibule: a cleft
lined by movable mucosa); they slide there (Kim et al. 2017, Med Phys 44:8). Above the fold
(maxilla) and below it (mandible: the chin, where mentalis inserts) the tissue is attached
to the bone. A segment's facet is tagged ``segment tag + TEETH_OFFSET`` when it lies on a
tooth, or within the vestibule's depth of one on the same segment:

* **teeth on a CT**: bone facets whose bone reaches `TEETH_HU` within `INSIDE_VOXELS` of
  the surface (enamel reads 2500-3000 HU and more, dentine about 1600-2000, cortical bone
  up to about 1900: Cranium's voxels above 2000 HU lie only in the bottom 6 mm of its field
  of view, through the crowns; 84 % of headsq's within 15 mm of its occlusal plane, with
  its fillings, the rest in the skull base and the chin's cortex), within `OCCLUSAL_MM` of
  the occlusal plane where the scene file gives one;
* **teeth on a synthetic head**: the band of each jaw's bone one crown height (`CROWN_MM`)
  from its occlusal edge;
* **the vestibule**: `VESTIBULE_MM` beyond the teeth.

Metal (fillings, brackets) reads above any bone and sits in the teeth, so it is taken for
a tooth, as it should be; its streaks fall in the tissue, which is not bone.
"""

from __future__ import annotations

import numpy as np

from meshes.anatomy import TEETH_OFFSET, segment_tags

#: HU above which bone is a tooth (module docstring).
TEETH_HU = 2000.0
#: Depth (voxels) into the bone, along the facet's inward normal, searched for a tooth.
INSIDE_VOXELS = (0.5, 1.0, 1.5, 2.0)
#: A CT's teeth lie within this distance (mm) of the occlusal plane: both crowns (9-11 mm)
#: and the CT's blur of them.
OCCLUSAL_MM = 15.0
#: Crown heights (mm) of the central incisors (Wheeler's Dental Anatomy: maxillary 10.5,
#: mandibular 9.0), per jaw: the synthetic heads' teeth.
CROWN_MM = {"maxilla": 10.5, "mandible": 9.0}
#: A segment's teeth are lopsided when their area is less than this share of its mirror
#: segment's (maxilla_L against maxilla_R): Cranium's halves hold 1502 and 1105 mm² (0.74);
#: an RTK CBCT whose crowns lie in the last 6 mm of its circular orbit's axial field, where
#: FDK lacks data, read its enamel below 2000 HU on one half: 476 and 0 mm².
LOPSIDED_SHARE = 0.33
#: Depth (mm) of the labial vestibule from the gingival margin to the fold, adults 15-50
#: years: maxilla 9-12, mandible 7-10 (a clinical survey of vestibular depth by age; Ward
#: 1976 measured 2.5-11.5 mm in the mandible). The tissue slides this far beyond the teeth.
VESTIBULE_MM = {"maxilla": 10.0, "mandible": 8.0}


def jaw(segment: str) -> str | None:
    """"maxilla" or "mandible" for the built-in segments' names, else None."""
    if segment == "mandible":
        return "mandible"
    if segment.startswith("maxilla"):
        return "maxilla"
    return None


def tag_teeth(points: np.ndarray, facets: np.ndarray, tags: np.ndarray, segments: dict,
              teeth: np.ndarray) -> np.ndarray:
    """Tags (F,) with the teeth (F,) bool, and the segment facets within the vestibule's
    depth of them on the same segment (vertex to vertex), retagged ``tag + TEETH_OFFSET``.
    Segments of no known jaw keep their tags."""
    from scipy.spatial import cKDTree

    out = tags.copy()
    for name, tag in segments.items():
        which = jaw(name)
        on = tags == tag
        mine = on & teeth
        if which is None or not mine.any():
            continue
        tree = cKDTree(points[np.unique(facets[mine])])
        d, _ = tree.query(points[facets[on]].reshape(-1, 3),
                          distance_upper_bound=VESTIBULE_MM[which])
        near = np.isfinite(d).reshape(-1, 3).any(axis=1)
        out[np.flatnonzero(on)[near]] = tag + TEETH_OFFSET
        out[mine] = tag + TEETH_OFFSET
    return out


def ct_teeth(hu_at, mid: np.ndarray, normals: np.ndarray, voxel_mm: float,
             occlusal=None) -> np.ndarray:
    """Teeth (B,) bool of facets with midpoints ``mid`` (B, 3) and outward normals (out of
    the tissue, into the bone) ``normals`` (B, 3), mm: `TEETH_HU` reached by ``hu_at``
    (points (K, 3) -> HU (K,)) at `INSIDE_VOXELS` of ``voxel_mm`` into the bone, and within
    `OCCLUSAL_MM` of the ``occlusal`` plane (`meshes.plane.Plane`) where it is given."""
    hu = np.max([hu_at(mid + k * voxel_mm * normals) for k in INSIDE_VOXELS], axis=0)
    teeth = hu >= TEETH_HU
    if occlusal is not None:
        n = np.asarray(occlusal.normal, float)
        d = (mid - np.asarray(occlusal.point, float)) @ (n / np.linalg.norm(n))
        teeth &= np.abs(d) <= OCCLUSAL_MM
    return teeth


def teeth_report(anatomy) -> dict:
    """{segment: {"facets", "area_mm2", "height_mm": [lo, hi]}} of each segment's teeth (and
    vestibule), heights along the head frame's superior axis (`meshes.frame`)."""
    out = {}
    for name, tag in anatomy.segments.items():
        on = anatomy.facet_tags == segment_tags(tag)[1]
        if not on.any():
            continue
        x = anatomy.points[anatomy.facets[on]]
        if anatomy.head_frame is not None:
            x = anatomy.head_frame.to_head(x.reshape(-1, 3)).reshape(x.shape)
        area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
        z = x[:, :, 2].mean(axis=1)
        out[name] = {"facets": int(on.sum()), "area_mm2": float(area.sum()),
                     "height_mm": [float(z.min()), float(z.max())]}
    return out


def lopsided_teeth(teeth: dict, segments) -> dict:
    """{segment: why} of the ``segments`` (names) whose teeth in `teeth_report`'s ``teeth``
    hold less than `LOPSIDED_SHARE` of their mirror segment's area (``name_L`` against
    ``name_R``): the lips slide on the other side only."""
    area = {k: v["area_mm2"] for k, v in teeth.items()}
    out = {}
    for name in segments:
        mirror = name[:-1] + {"L": "R", "R": "L"}[name[-1]] if name[-2:] in ("_L", "_R") else None
        mine, theirs = area.get(name, 0.0), area.get(mirror, 0.0)
        if mirror in segments and mine < LOPSIDED_SHARE * theirs:
            out[name] = (f"teeth on {mine:.0f} mm² against {theirs:.0f} on {mirror}: the lips "
                         f"slide on {mirror}'s side only; the enamel here reads below "
                         f"{TEETH_HU:g} HU (a CBCT's blur, or the edge of its field of view)")
    return out
